"""The reward emission: each skill is a reward r_k = phi . theta_k, and a step is emitted by the
Boltzmann (maximum-entropy) policy of that reward, pi_k(a | s) = exp(Q_k(s, a) - V_k(s)).

Prior theta_k ~ Normal(0, prior_scale^2 I), or with ``prior_df`` nu each weight a Student t of
nu degrees of freedom and scale ``prior_scale`` (the default for more than ``START_FIT_FEATURES``
weights, one per state: nu = 2, scale 0.5). The conditional of theta_k given its steps
depends on the steps only through their (S, A) count table (:mod:`npbrs.models.reward.likelihood`).

With ``scale_prior=(a, b)`` each skill's prior variance is sampled instead: sigma_k^2 ~
InvGamma(a, b) (the site ``sigma2``), theta_k | sigma_k ~ Normal(0, sigma_k^2 I), so that the data
say how large rewards are (one weight per state, the usual choice without features, wants a
much narrower prior than three hand-made features do). After the move on theta_k, a joint move
of its magnitude, (theta_k, sigma_k^2) -> (c theta_k, c^2 sigma_k^2), and then sigma_k^2 from its
exact conditional InvGamma(a + D/2, b + |theta_k|^2 / 2); a skill without steps draws both from
the prior. Proposals fit theta at the fixed ``prior_scale`` (a reference only) and draw sigma^2
from its conditional given the proposed theta, so that the proposal's ratio to the prior is
the marginal (Student-t) prior of theta. That prior's tail in |theta| falls only as
|theta|^-(2a + 1): a skill whose steps a deterministic policy explains (the likelihood keeps
rising with the reward's scale) then wanders to huge scales with a = 1 (a 10 x 64 gridworld,
2 chains of 40 + 40 sweeps: R-hat of the log joint 1.24), which is why it is not the default.

:class:`RewardEmission` is assembled from its parts: the prior (:class:`.prior.RewardPrior`), the
update, its tuning and the proposals (:class:`.moves.RewardMoves`), and the fits and evidences of
the greedy moves (:class:`.evidence.RewardEvidence`); the likelihood is here.
"""

from __future__ import annotations

import copy
from typing import Optional

import jax.numpy as jnp
import numpy as np

from npbrs.domains.solvers import make_soft_solver
from npbrs.domains.util.precision import float64_all
from ..emissions import Emission, register_emission
from .evidence import RewardEvidence
from .likelihood import count_table, log_policy, step_log_likelihoods
from .moves import RewardMoves
from .prior import AUTO_T_SCALE, START_FIT_FEATURES, RewardPrior, auto_prior_df, auto_prior_scale, check_prior_df

__all__ = ["RewardEmission", "SingleRewardEmission"]

_UPDATES = ("mala", "map")
_T_EVIDENCE = ("laplace", "calibrated")
_STARTS = ("auto", "draw", "fit")
_ACTION_NAMES = ("learned", "uniform")
# the initial segmentation's windows for rewards of more than START_FIT_FEATURES weights
# (RewardEmission.init_window)
SHORT_INIT_WINDOW = 5


@register_emission("reward")
class RewardEmission(RewardMoves, RewardEvidence, RewardPrior, Emission):
    """Boltzmann policies of linear rewards (maximum-entropy IRL).

    Args:
        mdp: the TabularMDP (its features define the rewards).
        prior_scale: sigma of the Gaussian prior on reward weights (:mod:`npbrs.models.reward.prior`), or
            "auto" (default): :func:`auto_prior_scale` of the number of features, 10 for up to 4
            features (the paper's domains) and 20 / sqrt(D) beyond (one weight per state: 1.96
            for the 104 cells of the four-room world); with a Student t prior (``prior_df``) the
            t's scale, "auto": ``AUTO_T_SCALE`` (0.5).
        prior_df: "auto" (default): :func:`auto_prior_df`, a Gaussian prior for up to 16 weights
            and a Student t of 2 degrees of freedom per weight beyond; None/False/"off": the
            Gaussian; a positive number nu: a Student t of nu degrees of freedom per weight.
        t_evidence: the greedy moves' evidence of a skill under a Student t prior: "laplace"
            (default), the Laplace approximation at the fit, or "calibrated", which adds what the
            Laplace approximation of the t misses for each weight the data leave to the prior
            (:mod:`npbrs.models.reward.evidence`; close to importance sampling where "laplace" is
            about 0.3 nats a weight low). The greedy moves are a search aid of warmup, not MCMC
            moves: the choice changes which regions the chains reach, not what they sample.
            "calibrated" labelled the four rooms as well (4 chains, fit seeds 0-3: 0.860 against
            0.863) but found worse regions on the labyrinth (held-out -0.920 against -0.899 on
            fit seed 1, its chains' log joint 400-500 nats lower): "laplace"'s Occam penalty of
            about 0.3 nats per weight left to the prior helped there (``docs/design.md``: priors
            for many reward weights).
        temperature: inverse temperature tau of the Boltzmann policy, pi ~ exp(tau Q); the
            rewards are tau * phi . theta (tau = 1: folded into theta).
        discount: the discount of the skills' soft value iteration (default: the MDP's).
        update: "mala" (valid MCMC) or "map" (stochastic EM, as in the paper).
        mala_steps: MALA steps per sweep; step_size: initial MALA step size.
        target_accept: the acceptance rate the step size is tuned to during warmup.
        map_steps: L-BFGS steps of a "map" update.
        fit_steps: L-BFGS steps of the data-driven proposal's IRL fit (from theta = 0).
        refit_steps: L-BFGS steps of a warm-started fit (a split-merge move's refits and
            final proposals, which start from the allocation's fits).
        proposal_inflation: factor on the proposal's standard deviations.
        proposal_broad_weight, proposal_broad_scale: weight w and scale s of the broad
            component of the defensive-mixture proposal (w = 0: a single Gaussian).
        scale_prior: False (default; or None, "off"): the prior's sigma is ``prior_scale``,
            fixed; or (a, b): each skill's prior variance sigma_k^2 ~ InvGamma(a, b) is sampled
            (see :mod:`npbrs.models.reward.emission`), and ``prior_scale`` only sets the proposals' fits and
            the first preconditioner.
        solver_options: keyword options of :func:`npbrs.domains.make_soft_solver`.
        search_tol: the soft solves' relative tolerance (its derivatives' a tenth of it) in the
            work that steers the sampler and enters no acceptance ratio (:meth:`for_search`):
            the chains' starting rewards, the warmup's greedy merges and splits, and the MALA
            preconditioner's Fisher information. The reward move and every likelihood the
            sampler keeps use the solver's own tolerance (1e-10 unless ``solver_options`` says
            otherwise); a looser one of the solver's wins here too. At 1e-6 a second tiny
            highway fit took 4.2 s instead of 5.4 s, with the same skills.
        epsilon: probability that the demonstrator acts uniformly at random instead of by the
            skill's Boltzmann policy (a noisy expert): pi = (1 - eps) Boltzmann + eps / A. A few
            actions that no reward explains then cost log(eps / A) each instead of opening a
            skill of their own. The Fisher information used for preconditioning and proposal
            scales stays the Boltzmann policy's (an approximation; the moves stay exact).
        start: the skills' rewards at a chain's start: "draw" draws them from the data-driven
            proposal around each skill's IRL fit to its starting steps; "fit" starts at the fit
            itself; "auto" (default) is "fit" for rewards of more than ``START_FIT_FEATURES``
            (16) weights and "draw" otherwise. With one weight per state a draw lies far below
            the fit and the first sweep scrambles the starting segmentation ("fit" keeps it: the
            labyrinth's default fit found 4 skills instead of 8); with a handful of features a
            draw lands near the fit, and starting at the fit gave the quadcopter's 500-step runs a
            fourth skill in 2 of 10 (``docs/design.md``).
        action_names: "learned" (default): which of several equivalent actions (the same next
            states and features, so the same Q under every reward) the demonstrator names is
            learned from the fitted demonstrations, and enters their scores
            (:mod:`npbrs.models.names`; it leaves the skills' posterior unchanged); "uniform":
            the Boltzmann policy's even split.
    """

    def __init__(self, mdp, prior_scale="auto", temperature: float = 1.0, discount: Optional[float] = None,
                 update: str = "mala", mala_steps: int = 3, step_size: float = 0.5, target_accept: float = 0.6,
                 map_steps: int = 5, fit_steps: int = 20, refit_steps: int = 3, proposal_inflation: float = 1.5,
                 solver_options: Optional[dict] = None, epsilon: float = 0.0, proposal_broad_weight: float = 0.1,
                 proposal_broad_scale: float = 10.0, scale_prior=False, start: str = "auto",
                 search_tol: float = 1e-6, prior_df="auto", t_evidence: str = "laplace",
                 action_names: str = "learned"):
        if action_names not in _ACTION_NAMES:
            raise ValueError(f"unknown action_names {action_names!r}; expected one of {_ACTION_NAMES}")
        self.action_names = action_names
        if start not in _STARTS:
            raise ValueError(f"unknown start {start!r}; expected one of {_STARTS}")
        if update not in _UPDATES:
            raise ValueError(f"unknown reward update {update!r}; expected one of {_UPDATES}")
        if t_evidence not in _T_EVIDENCE:
            raise ValueError(f"unknown t_evidence {t_evidence!r}; expected one of {_T_EVIDENCE}")
        self.t_evidence = t_evidence
        if scale_prior is False or scale_prior is None or (isinstance(scale_prior, str) and scale_prior == "off"):
            scale_prior = None
        else:
            if np.ndim(scale_prior) != 1 or len(scale_prior) != 2 or not all(
                    np.isfinite(v) and v > 0 for v in scale_prior):
                raise ValueError(f"scale_prior must be (a, b), two positive numbers (sigma^2 ~ InvGamma(a, b)), or "
                                 f"False/None/'off' (a fixed prior_scale), got {scale_prior!r}")
            scale_prior = (float(scale_prior[0]), float(scale_prior[1]))
        if isinstance(prior_df, str) and prior_df == "auto":
            # (a sampled scale is its own heavy-tailed prior: the t is not added to it)
            prior_df = None if scale_prior else auto_prior_df(mdp.num_features)
        else:
            off = prior_df is False or (isinstance(prior_df, str) and prior_df == "off")
            prior_df = None if off else check_prior_df(prior_df)
            if prior_df is not None and scale_prior:
                raise ValueError("prior_df (a Student t prior per weight) and scale_prior (a sampled scale per "
                                 "skill) cannot be combined: give one of them")
        self.prior_df = prior_df
        if isinstance(prior_scale, str):
            if prior_scale != "auto":
                raise ValueError(f"prior_scale must be a positive number or 'auto', got {prior_scale!r}")
            prior_scale = AUTO_T_SCALE if prior_df is not None else auto_prior_scale(mdp.num_features)
        for name, value in [("prior_scale", prior_scale), ("temperature", temperature), ("step_size", step_size),
                            ("proposal_inflation", proposal_inflation), ("proposal_broad_scale", proposal_broad_scale),
                            ("search_tol", search_tol)]:
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        if not (np.isfinite(proposal_broad_weight) and 0 <= proposal_broad_weight < 1):
            raise ValueError(f"proposal_broad_weight must lie in [0, 1), got {proposal_broad_weight!r}")
        if not (np.isfinite(epsilon) and 0 <= epsilon < 1):
            raise ValueError(f"epsilon must lie in [0, 1), got {epsilon!r}")
        if not 0 < target_accept < 1:
            raise ValueError(f"target_accept must lie in (0, 1), got {target_accept!r}")
        for name, value in [("mala_steps", mala_steps), ("map_steps", map_steps), ("fit_steps", fit_steps),
                            ("refit_steps", refit_steps)]:
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        self.scale_prior = scale_prior
        if discount is not None:
            mdp = mdp.with_discount(discount)
        self.mdp = mdp
        self.prior_scale = float(prior_scale)
        self.temperature = float(temperature)
        self.discount = float(mdp.discount)
        self.update_kind = update
        self.start = start
        self.starts_at_fit = start == "fit" or (start == "auto" and mdp.num_features > START_FIT_FEATURES)
        self.mala_steps = int(mala_steps)
        self.step_size = float(step_size)
        self.target_accept = float(target_accept)
        self.map_steps = int(map_steps)
        self.fit_steps = int(fit_steps)
        self.refit_steps = int(refit_steps)
        self.epsilon = float(epsilon)
        self.proposal_inflation = float(proposal_inflation)
        self.proposal_broad_weight = float(proposal_broad_weight)
        self.proposal_broad_scale = float(proposal_broad_scale)
        self.solver_options = dict(solver_options or {})
        self.solver = make_soft_solver(mdp, **self.solver_options)
        self.search_tol = float(search_tol)
        self.num_states, self.num_actions = mdp.num_states, mdp.num_actions
        self.num_features = mdp.num_features

    def describe(self):
        return {"name": self.name, "prior_scale": self.prior_scale, "temperature": self.temperature,
                "discount": self.discount, "update": self.update_kind, "mala_steps": self.mala_steps,
                "step_size": self.step_size, "target_accept": self.target_accept, "map_steps": self.map_steps,
                "fit_steps": self.fit_steps, "refit_steps": self.refit_steps, "proposal_inflation": self.proposal_inflation,
                "epsilon": self.epsilon, "proposal_broad_weight": self.proposal_broad_weight,
                "proposal_broad_scale": self.proposal_broad_scale,
                # False, not None, for a fixed scale: a saved configuration (TOML has no None) keeps it
                "scale_prior": list(self.scale_prior) if self.scale_prior else False, "start": self.start,
                "search_tol": self.search_tol, "prior_df": self.prior_df if self.prior_df is not None else False,
                "t_evidence": self.t_evidence, "action_names": self.action_names}

    def for_search(self) -> "RewardEmission":
        """This emission with its solver at ``search_tol`` (see :meth:`Emission.for_search`); a
        shallow copy sharing the arrays, so it can be made inside a trace."""
        if self.search_tol <= self.solver.tol:
            return self
        search = copy.copy(self)
        search.solver = self.solver.with_tolerance(self.search_tol)
        return search

    # ------------------------------------------------------------------ likelihood
    def init_cache(self, K):
        cache = {"V": jnp.zeros((K, self.num_states)), "log_step": jnp.full((K,), np.log(self.step_size)),
                 "scale": jnp.full((K, self.num_features), self.prior_scale)}
        if self.scale_prior:  # the step of the magnitude move (:meth:`_rescale`)
            cache["log_rescale"] = jnp.full((K,), np.log(0.1))
        return cache

    def counts(self, data, weights):
        """Weighted (state, action) counts of the real steps of ``data``: (S, A) for weights (N, T),
        (K, S, A) for weights (N, T, K) (e.g. one-hot skill assignments: one table per skill)."""
        return count_table(data.states, data.actions, weights, self.num_states, self.num_actions, data.mask)

    def _log_policies_and_values(self, theta, cache=()):
        K = theta.shape[0]
        v0 = cache["V"] if isinstance(cache, dict) and cache["V"].shape[0] == K else None
        return log_policy(self.solver, theta, v0, self.temperature, self.epsilon)

    def log_policies(self, params):
        """The demonstrator's policies: Boltzmann in the soft Q of tau * reward, mixed with
        uniform actions at rate epsilon, (K, S, A) (the policies the likelihood uses)."""
        return self._log_policies_and_values(params["theta"])[0]

    def log_likelihoods(self, params, data, cache=(), solved=False, with_ok=False):
        """Per-step log-likelihoods of K skills' weights.

        Args:
            params: {"theta": (K, D)} (and "sigma2" with ``scale_prior``).
            data: the demonstrations (:class:`HMMData`).
            cache: a cache of K skills (its values warm-start the solve), or () for a cold start.
            solved: the cache's values are those of ``params`` already (what :meth:`update`
                returns with MALA): one backup, no solve.
            with_ok: also return ok (``reports_solves``).
        Returns:
            (ll (N, T, K), cache with the values of ``params``), and with ``with_ok`` third ok
            (K,) bool: skill k's solve converged to the solver's tolerance and its
            log-likelihoods are finite.
        """
        theta = params["theta"]
        if solved:
            v0 = cache["V"]
        else:
            v0 = cache["V"] if isinstance(cache, dict) and cache["V"].shape[0] == theta.shape[0] else None
        log_pi, V, residual = log_policy(self.solver, theta, v0, self.temperature, self.epsilon, solved=solved,
                                         with_residual=True)
        ll = step_log_likelihoods(log_pi, data.states, data.actions, data.mask)
        new_cache = dict(cache) if isinstance(cache, dict) else self.init_cache(theta.shape[0])
        new_cache["V"] = V
        if not with_ok:
            return ll, new_cache
        ok = (residual <= self.solver.tol) & jnp.all(jnp.isfinite(ll), axis=(0, 1))
        return ll, new_cache, ok

    # ------------------------------------------------------------------ capabilities
    @property
    def learns_action_names(self) -> bool:
        """Scores include the learned names of equivalent actions (see :class:`Emission`)."""
        return self.action_names == "learned"

    @property
    def solves_in_update(self) -> bool:
        """MALA's update returns the values of its weights in the cache (see :class:`Emission`)."""
        return self.update_kind != "map"

    # warmup sweeps between refreshes of the preconditioner (see :meth:`tune`)
    tune_every = 10
    # sweeps between prior redraws of unused skills in ``fit`` (a redraw's likelihoods are cold
    # solves: on the highway they took half of a sweep when redrawn every sweep)
    redraw_unused = 5
    # ``update`` takes ``tune`` and refreshes the preconditioner after its first pass (no solve)
    tunes_in_update = True
    # ``fit_evidence`` takes ``with_evidence`` (false: fits only, no Fisher information) and
    # ``with_likelihoods`` (the fits' per-step log-likelihoods from their own soft values)
    fits_without_evidence = True
    fits_with_likelihoods = True
    # ``log_likelihoods`` takes ``with_ok`` (whether each skill's solve converged)
    reports_solves = True

    def initial_skills(self, max_skills: int):
        """``fit``'s number of skills in the initial segmentation: every slot (``max_skills``)
        for rewards of more than ``START_FIT_FEATURES`` (16) weights, None (the kernel's half of
        the slots) otherwise. With one weight per state, a start with fewer skills than the data
        hold lumps goals into one skill, and the lump is a mode of its own that no split leaves
        (rooms, fit seeds 0-7: one-to-one 0.907 from every slot against 0.843 from half;
        ``docs/design.md``: starts for a reward weight per state); the greedy merges remove the
        extra skills."""
        return int(max_skills) if self.num_features > START_FIT_FEATURES else None

    @property
    def init_window(self):
        """``fit``'s window length for the initial segmentation: ``SHORT_INIT_WINDOW`` (5) steps
        for rewards of more than ``START_FIT_FEATURES`` (16) weights, None (the kernel's 25)
        otherwise. With one weight per state each window's skill is fitted at the start
        (``start="auto"``); windows of 25 steps gave each starting skill the rewards of a few
        long runs, from which the benchmark worlds' chains did not find their way."""
        return SHORT_INIT_WINDOW if self.num_features > START_FIT_FEATURES else None


@register_emission("single")
class SingleRewardEmission(RewardEmission):
    """Unsegmented IRL: one reward for every step (``fit`` runs it with one skill slot)."""

    fixed_max_skills = 1


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
