"""The reward emission: each skill is a reward r_k = phi . theta_k, and a step is emitted by the
Boltzmann (maximum-entropy) policy of that reward, pi_k(a | s) = exp(Q_k(s, a) - V_k(s)).

Prior theta_k ~ Normal(0, prior_scale^2 I), or with ``prior_df`` nu each weight a Student t of
nu degrees of freedom and scale ``prior_scale`` (the default for more than ``START_FIT_FEATURES``
weights, one per state: nu = 2, scale 0.5). The conditional of theta_k given its steps
depends on the steps only through their (S, A) count table (:mod:`npbrs.models.reward`).

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

Moves on theta_k (``update``):

- ``"mala"`` (default): Metropolis-adjusted Langevin steps with the implicit gradient of the
  soft Bellman fixed point, a diagonal preconditioner from the Fisher information and a step
  size per skill, both tuned during warmup only (then frozen, so the chain is a valid MCMC).
  A skill with no steps is drawn exactly from the prior.
- ``"map"``: the paper's maximum a posteriori IRL step (warm-started L-BFGS). This makes the
  sampler a *stochastic EM*, not MCMC: its draws are not posterior samples.

The data-driven proposal of a new skill from weighted steps (a birth's window) fits IRL from
theta = 0 with a fixed number of L-BFGS steps (deterministic in the steps, so its density can
be evaluated in the reverse move) and draws theta from a Gaussian around the fit whose
covariance is the inverse Fisher information plus prior precision (a Laplace approximation),
inflated by ``proposal_inflation``. With ``proposal_broad_weight`` w > 0 the proposal is the
defensive mixture (1 - w) N(fit, C) + w N(fit, s^2 C), s = ``proposal_broad_scale``: its
draws stay near the fit, but a reverse move's density of a value many standard deviations
from the fit (a split-merge's current rewards, when the reverse split allocates the steps
differently) is about log w - D log s - d^2 / (2 s^2) instead of -d^2 / 2.
"""

from __future__ import annotations

import copy
import math
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist

from ..domains.util import linalg
from ..domains.solvers import make_soft_solver
from .emissions import Emission, EmissionInfo, register_emission
from . import reward_mala
from .mcmc import metropolis_accept, select
from .reward import (check_prior_df, count_log_likelihood_and_values, count_table, fisher_information, fit_reward,
                     log_policy, log_prior, prior_curvature, step_log_likelihoods)
from npbrs.domains.util.precision import float64_all

__all__ = ["RewardEmission", "SingleRewardEmission", "auto_prior_scale", "auto_prior_df"]

_UPDATES = ("mala", "map")
_T_EVIDENCE = ("laplace", "calibrated")
# prior_scale="auto" (the default): sigma = AUTO_SCALE for up to AUTO_SCALE_FEATURES weights (the
# paper's domains: 3 and 4 features), and beyond them sigma^2 D held at AUTO_SCALE^2 x
# AUTO_SCALE_FEATURES (sigma = 20 / sqrt(D)): one weight per state wants a far narrower prior
# (benchmarks/NOTES.md, "The reward prior's scale for one weight per state")
AUTO_SCALE, AUTO_SCALE_FEATURES = 10.0, 4
_STARTS = ("auto", "draw", "fit")
# start="auto" starts each skill at its IRL fit when the reward has more weights than this (one
# weight per state: a draw around the fit in that many dimensions lands far below it), and draws
# around the fit otherwise (a handful of features: the paper's domains, where starting at the
# fit gave the quadcopter a fourth skill in 2 of 10 runs)
START_FIT_FEATURES = 16
# the initial segmentation's windows for such rewards (RewardEmission.init_window)
SHORT_INIT_WINDOW = 5
# prior_df="auto" (the default): for rewards of more than START_FIT_FEATURES weights, each weight's
# prior is a Student t of AUTO_DF degrees of freedom and (with prior_scale="auto") scale
# AUTO_T_SCALE; a Gaussian otherwise (benchmarks/NOTES.md, session 44)
AUTO_DF, AUTO_T_SCALE = 2.0, 0.5


def auto_prior_df(num_features: int):
    """The reward prior's degrees of freedom for ``prior_df="auto"``: None (a Gaussian prior) for
    up to ``START_FIT_FEATURES`` (16) weights, ``AUTO_DF`` (2: a Student t per weight) beyond.

    With one weight per state, a skill's rewards are sparse (a goal, a few states to avoid) and
    its steps leave most states' weights unconstrained. Under a Gaussian prior wide enough for the
    goal's weight those weights wander by +-2 nats, and steps near another skill's bump switch to
    it; a t prior of scale 0.5 holds them near 0 and still lets the goal's weight reach 5. On the
    four-room world, started from the true segmentation, the sampler's labels then score 0.938
    (Gaussian: 0.906; the true model's Viterbi 0.953); from ``fit``'s start (4 chains, fit
    seeds 0-3) 0.863 against 0.790, and held-out -1.198 nats per step against the Gaussian's
    -1.216 (the oracle -1.169), at the same cost; the grid scores as before and the labyrinth's
    held-out within 0.005 of before (``benchmarks/NOTES.md``, session 44)."""
    D = int(num_features)
    if D < 1:
        raise ValueError(f"num_features must be at least 1, got {num_features!r}")
    return AUTO_DF if D > START_FIT_FEATURES else None


def auto_prior_scale(num_features: int) -> float:
    """The reward prior's sigma for ``prior_scale="auto"``: ``AUTO_SCALE`` (10) for up to
    ``AUTO_SCALE_FEATURES`` (4) weights, then sigma = 10 sqrt(4 / D), which keeps the prior's
    expected |theta|^2 = D sigma^2 at 400 however many weights there are.

    With one weight per state, a skill's Occam factor grows with its prior variance per
    visited state: at sigma 10 the four-room world's true skills lose to lumped multi-goal
    rewards along every path of single moves, at sigma 1-2 they do not (``benchmarks/NOTES.md``)."""
    D = int(num_features)
    if D < 1:
        raise ValueError(f"num_features must be at least 1, got {num_features!r}")
    return AUTO_SCALE * math.sqrt(min(1.0, AUTO_SCALE_FEATURES / D))


@register_emission("reward")
class RewardEmission(Emission):
    """Boltzmann policies of linear rewards (maximum-entropy IRL).

    Args:
        mdp: the TabularMDP (its features define the rewards).
        prior_scale: sigma of the Gaussian prior on reward weights (see npbrs.models.reward), or
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
            (:meth:`_t_laplace_correction`; close to importance sampling where "laplace" is
            about 0.3 nats a weight low). The greedy moves are a search aid of warmup, not MCMC
            moves: the choice changes which regions the chains reach, not what they sample.
            "calibrated" labelled the four rooms as well (4 chains, fit seeds 0-3: 0.860 against
            0.863) but found worse regions on the labyrinth (held-out -0.920 against -0.899 on
            fit seed 1, its chains' log joint 400-500 nats lower): "laplace"'s Occam penalty of
            about 0.3 nats per weight left to the prior helped there (``benchmarks/NOTES.md``,
            session 44).
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
            (see the module docstring), and ``prior_scale`` only sets the proposals' fits and
            the first preconditioner.
        solver_options: keyword options of :func:`npbrs.domains.make_soft_solver`.
        search_tol: the soft solves' relative tolerance (its derivatives' a tenth of it) in the
            work that steers the sampler and enters no acceptance ratio (:meth:`for_search`):
            the chains' starting rewards, the warmup's greedy merges and splits, and the MALA
            preconditioner's Fisher information. The reward move and every likelihood the
            sampler keeps use the solver's own tolerance (1e-10 unless ``solver_options`` says
            otherwise); a looser one of the solver's wins here too. At 1e-6 a second tiny
            highway fit took 4.2 s instead of 5.4 s, with the same skills
            (``benchmarks/NOTES.md``, session 39).
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
            fourth skill in 2 of 10 (``benchmarks/results/worlds-probes/``).
    """

    def __init__(self, mdp, prior_scale="auto", temperature: float = 1.0, discount: Optional[float] = None,
                 update: str = "mala", mala_steps: int = 3, step_size: float = 0.5, target_accept: float = 0.6,
                 map_steps: int = 5, fit_steps: int = 20, refit_steps: int = 3, proposal_inflation: float = 1.5,
                 solver_options: Optional[dict] = None, epsilon: float = 0.0, proposal_broad_weight: float = 0.1,
                 proposal_broad_scale: float = 10.0, scale_prior=False, start: str = "auto",
                 search_tol: float = 1e-6, prior_df="auto", t_evidence: str = "laplace"):
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
                "t_evidence": self.t_evidence}

    # ------------------------------------------------------------------ prior
    def _variance_prior(self):
        return dist.InverseGamma(*self.scale_prior)

    def _scales(self, params):
        """The prior's sigma: (K,) sampled, or the fixed ``prior_scale``."""
        return jnp.sqrt(params["sigma2"]) if self.scale_prior else self.prior_scale

    def _with_variance(self, theta, sigma2=None):
        """Params of weights (K, D) (or (D,)), with their sigma^2 when it is sampled."""
        return {"theta": theta, "sigma2": sigma2} if self.scale_prior else {"theta": theta}

    def _variance_conditional(self, theta):
        """The exact conditional of sigma^2 given weights (..., D): InvGamma(a + D/2, b + |theta|^2 / 2)."""
        a, b = self.scale_prior
        return dist.InverseGamma(a + 0.5 * theta.shape[-1], b + 0.5 * jnp.sum(theta ** 2, axis=-1))

    def sample_params(self, K):
        if not self.scale_prior:
            base = (dist.Normal(0.0, self.prior_scale) if self.prior_df is None
                    else dist.StudentT(self.prior_df, 0.0, self.prior_scale))
            theta = numpyro.sample("theta", base.expand([K, self.num_features]).to_event(2))
            return {"theta": theta}
        sigma2 = numpyro.sample("sigma2", self._variance_prior().expand([K]).to_event(1))
        theta = numpyro.sample("theta", dist.Normal(0.0, jnp.sqrt(sigma2)[:, None]).expand(
            [K, self.num_features]).to_event(2))
        return {"theta": theta, "sigma2": sigma2}

    def log_prior(self, params):
        scale = self._scales(params)
        lp = log_prior(params["theta"], jnp.asarray(scale)[..., None] if self.scale_prior else scale, self.prior_df)
        if self.scale_prior:
            lp = lp + self._variance_prior().log_prob(params["sigma2"])
        return lp

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

    def log_likelihoods(self, params, data, cache=(), solved=False):
        """Per-step log-likelihoods (N, T, K) and the cache with the values of ``params``;
        ``solved``: the cache's values are those of ``params`` already (what :meth:`update`
        returns with MALA): one backup, no solve."""
        theta = params["theta"]
        if solved:
            log_pi, V = log_policy(self.solver, theta, cache["V"], self.temperature, self.epsilon, solved=True)
        else:
            log_pi, V = self._log_policies_and_values(theta, cache)
        ll = step_log_likelihoods(log_pi, data.states, data.actions, data.mask)
        new_cache = dict(cache) if isinstance(cache, dict) else self.init_cache(theta.shape[0])
        new_cache["V"] = V
        return ll, new_cache

    # ------------------------------------------------------------------ moves
    def update(self, key, params, cache, data, weights, adapt, tune=False, redraw_unused=True):
        """The reward move (MALA, then with a sampled prior variance the magnitude move and
        sigma^2 | theta), or the MAP refit (``update="map"``). ``tune`` (a bool, not
        batched over chains): refresh the MALA preconditioner first, as :meth:`tune` does, from
        the Fisher information at the skills' current weights; here the move's first pass has
        solved each skill at them already, so the refresh costs only the tangent solves.
        ``redraw_unused`` (a bool, not batched): the skills without steps get prior draws (else
        they keep their parameters, also an exact move). With MALA (:attr:`solves_in_update`)
        the draws come before the move, whose first pass solves every skill, so that the
        returned cache holds the values of the returned weights (:meth:`log_likelihoods` with
        ``solved``)."""
        theta = params["theta"]
        K, D = theta.shape
        counts = self.counts(data, weights)  # (K, S, A)
        has_steps = jnp.sum(counts, axis=(1, 2)) > 0
        k_prior, k_move = jax.random.split(key)
        if not self.scale_prior:
            prior_draw = {"theta": self.prior_scale * (jax.random.normal(k_prior, (K, D)) if self.prior_df is None
                                                       else jax.random.t(k_prior, self.prior_df, (K, D)))}
        else:  # a skill without steps draws (sigma^2, theta) from the prior
            k_prior, k_var, k_var0 = jax.random.split(k_prior, 3)
            sigma2_0 = self._variance_prior().sample(k_var0, (K,))
            prior_draw = {"theta": jnp.sqrt(sigma2_0)[:, None] * jax.random.normal(k_prior, (K, D)), "sigma2": sigma2_0}
        drawn = ~has_steps & redraw_unused
        # the unused skills' weights, drawn or kept, before the move: its first pass solves them
        start = jax.tree.map(lambda d, p: jnp.where(drawn.reshape((K,) + (1,) * (d.ndim - 1)), d, p), prior_draw, params)
        if self.update_kind == "map":
            new, _, V, _, _ = fit_reward(self.solver, counts, theta, cache["V"], self._scales(params), self.map_steps,
                                         epsilon=self.epsilon, temperature=self.temperature, prior_df=self.prior_df)
            accept = jnp.ones(K)
            cache = {**cache, "V": V}
            out = {"theta": new}
        else:  # (MALA never moves a skill without steps: its start comes back as it went in)
            k_move, k_rescale = jax.random.split(k_move) if self.scale_prior else (k_move, None)
            new, cache, accept, log_density = self._mala(k_move, start["theta"], counts, cache, adapt,
                                                         self._scales(start), has_steps, tune)
            out = {"theta": new}
            if self.scale_prior:  # (nor does the magnitude move)
                out["theta"], out["sigma2"], cache = self._rescale(k_rescale, new, start["sigma2"], log_density,
                                                                   counts, cache, adapt, has_steps)
        if self.scale_prior:  # sigma^2 | theta exactly (the moves' own sigma^2 is not kept)
            out["sigma2"] = self._variance_conditional(out["theta"]).sample(k_var)
        # the skills without steps: their start, drawn or kept
        out = jax.tree.map(lambda n, s0: jnp.where(has_steps.reshape((K,) + (1,) * (n.ndim - 1)), n, s0), out, start)
        info = EmissionInfo(jnp.sum(jnp.where(has_steps, accept, 0.0)) / jnp.maximum(jnp.sum(has_steps), 1))
        return out, cache, info

    @property
    def solves_in_update(self) -> bool:
        """MALA's update returns the values of its weights in the cache (see :class:`Emission`)."""
        return self.update_kind != "map"

    # warmup sweeps between refreshes of the preconditioner (see :meth:`tune`)
    tune_every = 10
    # sweeps between prior redraws of unused skills in ``fit`` (a redraw's likelihoods are cold
    # solves: on the highway they took half of a sweep when redrawn every sweep)
    redraw_unused = 5

    def initial_skills(self, max_skills: int):
        """``fit``'s number of skills in the initial segmentation: every slot (``max_skills``)
        for rewards of more than ``START_FIT_FEATURES`` (16) weights, None (the kernel's half of
        the slots) otherwise. With one weight per state, a start with fewer skills than the data
        hold lumps goals into one skill, and the lump is a mode of its own that no split leaves
        (rooms, fit seeds 0-7: one-to-one 0.907 from every slot against 0.843 from half;
        ``benchmarks/NOTES.md``, session 45); the greedy merges remove the extra skills."""
        return int(max_skills) if self.num_features > START_FIT_FEATURES else None

    @property
    def init_window(self):
        """``fit``'s window length for the initial segmentation: ``SHORT_INIT_WINDOW`` (5) steps
        for rewards of more than ``START_FIT_FEATURES`` (16) weights, None (the kernel's 25)
        otherwise. With one weight per state each window's skill is fitted at the start
        (``start="auto"``); windows of 25 steps gave each starting skill the rewards of a few
        long runs, from which the benchmark worlds' chains did not find their way
        (``benchmarks/NOTES.md``, session 29)."""
        return SHORT_INIT_WINDOW if self.num_features > START_FIT_FEATURES else None

    def tune(self, params, cache, data, weights):
        """The MALA preconditioner from the Fisher information at the skills' current weights:
        per coordinate 1 / sqrt(F_dd + 1 / sigma^2) in the cache's "scale" (a Student t prior:
        its curvature at the current weights for 1 / sigma^2, :func:`npbrs.models.reward.prior_curvature`). The sampler calls
        this in warmup only, every ``tune_every`` sweeps (D tangent solves a skill: the most
        expensive part of a warmup sweep with many features); the sampling sweeps keep it fixed.
        The sampler asks :meth:`update` for it instead (``tune``), where the skills' values are
        solved already; this one solves for them."""
        theta = params["theta"]
        scale = self._preconditioner(theta, self._scales(params), self.counts(data, weights), cache["V"])
        return {**cache, "scale": scale}

    def _preconditioner(self, theta, prior_scale, counts, V, solved=False):
        """:meth:`tune`'s per-coordinate scales (K, D) at weights theta (K, D), by this
        emission's solver; ``solved``: V are their soft values already (no solve)."""
        fisher = jax.vmap(lambda t, c, v: jnp.diag(fisher_information(self.solver, t, c, v, self.temperature,
                                                                      solved)))(theta, counts, V)
        scale = jnp.asarray(prior_scale)
        curvature = prior_curvature(theta, scale[..., None] if jnp.ndim(scale) else scale, self.prior_df)
        return 1.0 / jnp.sqrt(jnp.maximum(fisher, 0.0) + curvature)

    def _mala(self, key, theta, counts, cache, adapt, prior_scale, active, tune=False):
        """``mala_steps`` steps of the reward move (:mod:`npbrs.models.reward_mala`) with the
        cache's preconditioner (refreshed during warmup by :meth:`tune`, or here where ``tune``
        is true: after the first pass, from its values, at the search's tolerance as
        :meth:`tune`); in warmup each skill's step size follows its acceptance rate towards
        ``target_accept``."""
        kernel = reward_mala.build_kernel(self.solver, prior_scale, temperature=self.temperature,
                                          epsilon=self.epsilon, prior_df=self.prior_df)
        search = self.for_search()

        def step(carry, x):
            key, evaluate = x
            state, log_step, acc_sum, scale = carry
            # the first pass solves every skill (the values of the weights returned, moved or not),
            # the steps only the skills with steps (``active``): the others are never moved
            state, info = kernel(key, state, counts, jnp.exp(log_step), scale ** 2, active | evaluate, evaluate)
            log_step = jnp.where(adapt & active & ~evaluate,
                                 log_step + 0.3 * (info.acceptance_rate - self.target_accept), log_step)
            if tune is not False:  # (the first pass's values are the weights' own: no solve)
                scale = jax.lax.cond(evaluate & tune, lambda s: search._preconditioner(s.theta, prior_scale, counts,
                                                                                      s.V, solved=True),
                                     lambda s: scale, state)
            return (state, log_step, acc_sum + info.acceptance_rate, scale), None

        # the chain's start (reward_mala.init) is the loop's first pass: one compiled solve for both
        init = (reward_mala.unevaluated(theta, cache["V"]), cache["log_step"], jnp.zeros(theta.shape[0]),
                cache["scale"])
        keys = jnp.concatenate([key[None], jax.random.split(key, self.mala_steps)])
        (state, log_step, acc_sum, scale), _ = jax.lax.scan(step, init, (keys, jnp.arange(self.mala_steps + 1) == 0))
        return (state.theta, {**cache, "V": state.V, "log_step": log_step, "scale": scale}, acc_sum / self.mala_steps,
                state.log_density)

    def _rescale(self, key, theta, sigma2, log_density, counts, cache, adapt, active=True):
        """A joint move of each skill's magnitude: (theta, sigma^2) -> (c theta, c^2 sigma^2),
        log c ~ N(0, h^2). The prior of theta given sigma cancels (with the Jacobian c^(D+2)),
        so the ratio is L(c theta) / L(theta) IG(c^2 sigma^2) / IG(sigma^2) c^2: the weights that
        the skill's steps leave alone (most of them, with one weight per state) move with the
        scale instead of holding it where it is. h is tuned in warmup to accept 40%."""
        K = theta.shape[0]
        ll_old = log_density - log_prior(theta, jnp.sqrt(sigma2)[:, None])
        k_c, k_acc = jax.random.split(key)
        log_c = jnp.exp(cache["log_rescale"]) * jax.random.normal(k_c, (K,))
        c = jnp.exp(log_c)
        prop, s2_prop = theta * c[:, None], sigma2 * c ** 2
        ll_new, V_new, ok = count_log_likelihood_and_values(self.solver, prop, counts, cache["V"], self.temperature,
                                                            self.epsilon)
        prior = self._variance_prior()
        log_ratio = ll_new - ll_old + prior.log_prob(s2_prop) - prior.log_prob(sigma2) + 2.0 * log_c
        accept, rate = metropolis_accept(k_acc, log_ratio, ok & active)  # (``active``: the skills with steps)
        theta, sigma2, V = select(accept, (prop, s2_prop, V_new), (theta, sigma2, cache["V"]))
        log_rescale = jnp.where(adapt & active, cache["log_rescale"] + 0.3 * (rate - 0.4), cache["log_rescale"])
        return theta, sigma2, {**cache, "V": V, "log_rescale": log_rescale}

    # ------------------------------------------------------------------ data-driven proposal
    def fit_point(self, data, weights, init=None):
        """IRL fits (M, D) to weighted steps (N, T, M): ``refit_steps`` L-BFGS steps from
        ``init``, or ``fit_steps`` from theta = 0 (:meth:`laplace`'s fits, at the fixed prior
        scale)."""
        return self._point(self._laplace_fit(self.counts(data, weights), init)[0])

    def _point(self, theta):
        """Params at fitted weights: sigma^2, when sampled, at its conditional mode given them."""
        if not self.scale_prior:
            return {"theta": theta}
        cond = self._variance_conditional(theta)
        return {"theta": theta, "sigma2": cond.rate / (cond.concentration + 1.0)}

    def laplace(self, counts, init=None, at_sampled_scale=False):
        """IRL fits (M, D) to count tables (M, S, A), ``refit_steps`` L-BFGS steps from ``init``
        (or ``fit_steps`` from theta = 0), their log-likelihoods (M,), the posterior precisions
        (M, D, D) at the fits, F + I / sigma^2 (F: the Fisher information, the observed one's
        stand-in), symmetrised, and the sigma (M,) of the fits' prior. Shared by the proposal
        and the evidence. With ``at_sampled_scale`` (a sampled prior variance) the fit is
        refitted, ``fit_steps`` steps, at sigma^2 = (b + |theta|^2 / 2) / (a + D / 2) of the
        first fit (where the Student-t prior's gradient is the Gaussian's): one compiled fit for
        both passes."""
        fit, log_lik, V, scale = self._laplace_fit(counts, init, at_sampled_scale)
        return fit, log_lik, self._laplace_precision(fit, counts, V, scale), scale

    def _laplace_fit(self, counts, init=None, at_sampled_scale=False):
        """:meth:`laplace`'s fits: (theta (M, D), log_lik (M,), V (M, S), scale (M,))."""
        M, D = counts.shape[0], self.num_features
        theta0 = jnp.zeros((M, D)) if init is None else init["theta"]
        steps = self.fit_steps if init is None else self.refit_steps
        fit_at = lambda theta, v, scale, n: fit_reward(self.solver, counts, theta, v, scale, n,  # noqa: E731
                                                       epsilon=self.epsilon, temperature=self.temperature,
                                                       prior_df=self.prior_df)[:3]
        scale = jnp.full((M,), self.prior_scale)
        if not at_sampled_scale:
            fit, log_lik, V = fit_at(theta0, jnp.zeros((M, self.num_states)), scale, steps)
            return fit, log_lik, V, scale
        a, b = self.scale_prior

        def one(carry, first):
            theta, _, V, scale = carry
            scale = jnp.where(first, scale, jnp.sqrt((b + 0.5 * jnp.sum(theta ** 2, -1)) / (a + 0.5 * D)))
            return (*fit_at(theta, V, scale, max(steps, self.fit_steps)), scale), None

        (fit, log_lik, V, scale), _ = jax.lax.scan(
            one, (theta0, jnp.zeros(M), jnp.zeros((M, self.num_states)), scale), jnp.array([True, False]))
        return fit, log_lik, V, scale

    def _laplace_precision(self, fit, counts, V, scale):
        """:meth:`laplace`'s precisions (M, D, D) at its fits."""
        # (at the fits' own values: no solve, only the tangent solves)
        F = fisher_information(self.solver, fit, counts, V, self.temperature, solved=True)  # (M, D, D)
        curvature = prior_curvature(fit, scale[:, None], self.prior_df)  # (M, D): 1 / sigma^2 for a Gaussian
        precision = F + jax.vmap(jnp.diag)(curvature)
        return 0.5 * (precision + jnp.swapaxes(precision, -1, -2))

    def fit_evidence(self, data, weights, init=None, with_evidence=True, with_likelihoods=False):
        """IRL fits (M, D) to weighted steps (N, T, M) and each skill's Laplace log evidence at
        its fit, log p(steps | theta) + log p0(theta) + D/2 log 2 pi - 1/2 log det(precision)
        (see :meth:`laplace`); with a sampled prior variance, sigma^2 integrated out too
        (:meth:`scale_mixture_evidence`). ``with_evidence`` (a bool, or a traced one): where
        false, the fits only, their log evidences NaN (no Fisher information computed), so
        that one compiled call serves fits and evidences (the greedy split's allocation).
        ``with_likelihoods``: also the fits' per-step log-likelihoods (N, T, M), from the fits'
        own soft values (one backup each, no solve)."""
        counts = self.counts(data, weights)
        M = counts.shape[0]
        theta, log_lik, V, scale = self._laplace_fit(counts, init, at_sampled_scale=bool(self.scale_prior))

        def evidence(_):
            precision = self._laplace_precision(theta, counts, V, scale)
            if not self.scale_prior:
                logdet = linalg.spd_logdet(precision)
                return (log_lik + self.log_prior({"theta": theta}) + 0.5 * self.num_features * jnp.log(2 * jnp.pi)
                        - 0.5 * logdet + (self._t_laplace_correction(theta, precision, scale)
                                          if self.t_evidence == "calibrated" else 0.0))
            return self.scale_mixture_evidence(theta, log_lik, precision, scale ** 2)

        if with_evidence is True:
            log_ev = evidence(None)
        else:
            log_ev = jax.lax.cond(with_evidence, evidence, lambda _: jnp.full((M,), jnp.nan), None)
        if not with_likelihoods:
            return self._point(theta), log_ev
        log_pi, _ = log_policy(self.solver, theta, V, self.temperature, self.epsilon, solved=True)
        return self._point(theta), log_ev, step_log_likelihoods(log_pi, data.states, data.actions, data.mask)

    def _t_laplace_correction(self, theta, precision, scale):
        """(M,) what a Student t prior's Laplace evidence misses: the Laplace approximation of
        the t density's own integral (1) is t(0) sqrt(2 pi / h0) (h0: its curvature at 0), short
        by c = -log of that (0.32 nats for 2 degrees of freedom, whatever the scale) for every
        weight the data leave to the prior, which with one weight per state is most of them: a
        skill's evidence came out tens of nats low, and a split's two skills twice that. Each
        weight adds c times the prior's share of its precision, h0 / (F_dd + h0): c where the
        data say nothing, 0 where they decide the weight (checked against importance sampling in
        ``tests/test_greedy.py``). 0 for a Gaussian prior, whose Laplace evidence is exact
        without data."""
        if self.prior_df is None:
            return jnp.zeros(theta.shape[0])
        nu, s = self.prior_df, jnp.asarray(scale, jnp.float64)[:, None]
        zero = jnp.zeros((1, 1))
        h0 = prior_curvature(zero, s, nu)  # (M, 1)
        c = -(log_prior(zero, 1.0, nu) + 0.5 * jnp.log(2 * jnp.pi / prior_curvature(zero, 1.0, nu)))[0, 0]  # scale-free
        F_diag = jnp.diagonal(precision, axis1=-2, axis2=-1) - prior_curvature(theta, s, nu)
        return c * jnp.sum(h0 / (jnp.maximum(F_diag, 0.0) + h0), -1)

    # the coarse grid of log sigma^2 that finds the peak of the evidence's integrand
    _LOG_VARIANCE_NODES = np.linspace(-16.0, 16.0, 257)

    def scale_mixture_evidence(self, theta, log_lik, precision, s2_fit):
        """The log evidence (M,) with sigma^2 ~ InvGamma(a, b) integrated out. The likelihood is
        taken as the quadratic around the fit theta, made at prior variance ``s2_fit`` (M,): its
        gradient there is theta / s2_fit (the fit's stationarity), its curvature the Fisher
        information F = precision - I / s2_fit. Its integral against Normal(0, sigma^2 I) is
        closed-form for every sigma^2,

            log ev(sigma^2) = c0 - D/2 log sigma^2 - 1/2 log det P + 1/2 h' P^-1 h,
            P = F + I / sigma^2, h = precision theta, c0 = log L - h' theta + 1/2 theta' F theta,

        (one eigendecomposition of F serves every sigma^2), and the integral over sigma^2 is a
        trapezoid rule in log sigma^2, 257 nodes on +-10 sd around the integrand's peak (found on
        a coarse grid of [-16, 16] and one Newton step). With the prior's variance pinned at
        s2_fit it is the fixed-scale Laplace evidence."""
        D = self.num_features
        F = precision - jnp.eye(D) / s2_fit[:, None, None]
        lam, Q = jnp.linalg.eigh(0.5 * (F + jnp.swapaxes(F, -1, -2)))
        lam = jnp.maximum(lam, 0.0)  # (M, D)
        h = jnp.einsum("mde,me->md", precision, theta)
        c0 = log_lik - jnp.sum(h * theta, -1) + 0.5 * jnp.einsum("md,mde,me->m", theta, F, theta)
        hq2 = jnp.einsum("mde,md->me", Q, h) ** 2  # (M, D)
        prior = self._variance_prior()

        def log_integrand(u):  # u: (J, M) values of log sigma^2 -> (J, M)
            inv = jnp.exp(-u)[..., None]
            per = (c0 - 0.5 * D * u - 0.5 * jnp.sum(jnp.log(lam + inv), -1) + 0.5 * jnp.sum(hq2 / (lam + inv), -1))
            return per + prior.log_prob(jnp.exp(u)) + u  # the prior's density in log sigma^2

        # a coarse grid finds the peak, one Newton step by central differences centres it
        # (exact for a quadratic), and the trapezoid rule runs on +-10 sd around it
        coarse = jnp.broadcast_to(jnp.asarray(self._LOG_VARIANCE_NODES)[:, None], (257, theta.shape[0]))
        f = log_integrand(coarse)
        j = jnp.clip(jnp.argmax(f, axis=0), 1, 255)
        cols = jnp.arange(theta.shape[0])
        step = coarse[1, 0] - coarse[0, 0]
        d1 = (f[j + 1, cols] - f[j - 1, cols]) / (2 * step)
        d2 = (f[j + 1, cols] - 2 * f[j, cols] + f[j - 1, cols]) / step ** 2
        curved = d2 < -1e-12
        peak = jnp.where(curved, coarse[j, cols] - d1 / jnp.where(curved, d2, -1.0), coarse[j, cols])
        sd = jnp.clip(jnp.where(curved, 1.0 / jnp.sqrt(-jnp.where(curved, d2, -1.0)), 4.0), 1e-4, 4.0)
        x = jnp.linspace(-10.0, 10.0, 257)
        fine = peak[None] + x[:, None] * sd[None]
        ends = (jnp.arange(257) == 0) | (jnp.arange(257) == 256)
        log_du = jnp.log(jnp.where(ends, 0.5, 1.0) * (x[1] - x[0]))[:, None] + jnp.log(sd)[None]
        return jax.scipy.special.logsumexp(log_integrand(fine) + log_du, axis=0)

    def proposal(self, data, weights, init=None):
        """Mean (D,) and Cholesky factor (D, D) of the Laplace proposal fitted to steps weighted by
        ``weights`` (N, T): the IRL fit (from one skill's params ``init`` when given) and its
        posterior covariance (see :meth:`laplace`), inflated by ``proposal_inflation``."""
        D = self.num_features
        one = None if init is None else {"theta": init["theta"][None]}
        mean, _, precision, _ = self.laplace(self.counts(data, weights)[None], one)
        cov = linalg.spd_inverse(precision[0]) * self.proposal_inflation ** 2
        chol = linalg.cholesky(0.5 * (cov + cov.T) + 1e-12 * jnp.eye(D))
        return mean[0], chol

    def _draw(self, key, mean, chol, broad_weight):
        """A draw of the proposal around mean; broad_weight 0: the narrow Gaussian only."""
        if broad_weight == 0:
            return mean + chol @ jax.random.normal(key, mean.shape)
        k_pick, k_draw = jax.random.split(key)
        scale = jnp.where(jax.random.bernoulli(k_pick, broad_weight), self.proposal_broad_scale, 1.0)
        return mean + scale * (chol @ jax.random.normal(k_draw, mean.shape))

    def _log_q(self, one, mean, chol):
        """log-density of the (mixture) proposal around mean at one skill's params (with the
        conditional density of its sigma^2 given theta, when sampled)."""
        theta = one["theta"]
        w = self.proposal_broad_weight
        lq = linalg.mvn_log_prob(theta, mean, chol)
        if w > 0:
            broad = linalg.mvn_log_prob(theta, mean, self.proposal_broad_scale * chol)
            lq = jnp.logaddexp(jnp.log1p(-w) + lq, jnp.log(w) + broad)
        if self.scale_prior:
            lq = lq + self._variance_conditional(theta).log_prob(one["sigma2"])
        return lq

    def _propose_one(self, key, mean, chol):
        if not self.scale_prior:
            return {"theta": self._draw(key, mean, chol, self.proposal_broad_weight)}
        k_theta, k_var = jax.random.split(key)
        theta = self._draw(k_theta, mean, chol, self.proposal_broad_weight)
        return {"theta": theta, "sigma2": self._variance_conditional(theta).sample(k_var)}

    def init_params(self, key, data, weights):
        """A starting point: each skill's IRL fit to its weighted steps (``start="fit"``, or
        "auto" with many features), or a draw of the Laplace proposal (the narrow component
        only) around it. (K, D)."""
        if self.starts_at_fit:  # the proposal's mean, every skill in one batched fit
            return self._point(self.laplace(self.counts(data, weights))[0])
        keys = jax.random.split(key, weights.shape[-1])
        return self._point(jax.vmap(lambda k, w: self._draw(k, *self.proposal(data, w), 0.0), in_axes=(0, 2))(
            keys, weights))

    def propose(self, key, data, weights):
        mean, chol = self.proposal(data, weights)
        one = self._propose_one(key, mean, chol)
        return one, self._log_q(one, mean, chol)

    def propose_and_score(self, key, data, weights, other_one, init=None):
        mean, chol = self.proposal(data, weights, init)
        one = self._propose_one(key, mean, chol)
        return one, self._log_q(one, mean, chol), self._log_q(other_one, mean, chol)

    def log_proposal(self, params_one, data, weights):
        return self._log_q(params_one, *self.proposal(data, weights))


@register_emission("single")
class SingleRewardEmission(RewardEmission):
    """Unsegmented IRL: one reward for every step (``fit`` runs it with one skill slot)."""

    fixed_max_skills = 1


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
