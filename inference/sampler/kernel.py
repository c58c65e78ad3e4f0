"""The BP-HMM Gibbs sampler as a ``numpyro.infer.mcmc.MCMCKernel``.

One sweep (jitted whole, static shapes: K = ``max_skills`` slots with an active mask):

1. features f_ik, one skill at a time for all trajectories at once, from their conditional
   with the skill sequences summed out (forward filter with f_ik = 0 and f_ik = 1);
2. skill sequences z_i by forward filtering, backward sampling (then, when on, split-merge
   trials, and in warmup only greedy merges and splits: ``npbrs.inference.sampler.schedule``);
3. transition weights eta_i from their conjugate (Gamma-Dirichlet) conditional given z_i, and
   skill popularities omega_k | F ~ Beta(alpha/K + m_k, 1 + N - m_k) (independent given z, F);
4. emission parameters with the emission's own move given the steps assigned to each skill;
5. optionally alpha, kappa, gamma by random-walk Metropolis on log scale.

With state-dependent ends (``termination``; ``npbrs.models.bphmm.Termination``) every filter
of steps 1-2 (and of the moves, which hold the ends fixed) uses the ends' gate, eta's
conditional counts the switches only, and step 3 also draws each skill's mean end
probability mu_k given z with the ends integrated out (random-walk Metropolis on its logit),
then the ends beta_k(s) from their Beta conditional.

Every density used here is one of the model's own (``npbrs.models.bphmm``); the conditionals
of steps 1, 3 and 5 are :mod:`npbrs.inference.sampler.conditionals`'. What runs in warmup only
to help the search (sticky start and phase, greedy moves, the emission's tuning) is the warmup
schedule's (:class:`~npbrs.inference.sampler.schedule.WarmupSchedule`).
"""

from __future__ import annotations

from functools import partial
from typing import Dict, Optional

import jax
import jax.numpy as jnp
import numpy as np
from numpyro.infer.mcmc import MCMCKernel

from npbrs.domains.util.pytree import Pytree
from npbrs.models.bphmm import (Hyper, Termination, bphmm_model, end_gate, hmm_parameters, log_joint_terms,
                                log_marginal_likelihoods)
from npbrs.models.mcmc import select
from npbrs.models.emissions import Emission, EmissionInfo, HMMData
from npbrs.models.hmm import batch_backward_sample, batch_forward_filter

from npbrs.domains.util.compiling import jit
from npbrs.domains.util.precision import float64_all

from .birth_death import birth_death
from .conditionals import feature_conditional, sample_end_model, sample_eta_omega, sample_features, sample_hyperparameters
from .options import check_moves
from .schedule import WarmupSchedule
from .split_merge import split_merge
from .state import BPHMMState, MoveState

#: The initial segmentation's window length where neither the caller nor the emission gives one.
DEFAULT_INIT_WINDOW = 25


def initial_window(emission: Emission, init_window: Optional[int] = None) -> int:
    """The initial segmentation's window length: ``init_window`` when given, else the
    emission's ``init_window`` when it is not None (rewards of one weight per state: 5), else
    ``DEFAULT_INIT_WINDOW``. The kernel and ``fit`` (which records it) both use this."""
    if init_window is not None:
        return int(init_window)
    return int(emission.init_window or DEFAULT_INIT_WINDOW)


def initial_skills(emission: Emission, max_skills: int, init_skills: Optional[int] = None) -> int:
    """The skills of the initial segmentation: ``init_skills`` when given, else the emission's
    ``initial_skills(max_skills)`` when it gives a number (rewards of one weight per state:
    every slot), else half the slots, (max_skills + 1) // 2. The kernel and ``fit``
    (which records it) both use this."""
    if init_skills is not None:
        return int(init_skills)
    chosen = emission.initial_skills(int(max_skills))
    return int(chosen) if chosen is not None else max(1, (int(max_skills) + 1) // 2)


__all__ = ["BPHMMKernel", "skill_weights", "initial_window", "initial_skills", "DEFAULT_INIT_WINDOW"]


def skill_weights(z, mask, K):
    """(N, T, K) one-hot skill of every real step of z (N, T); zero on padding."""
    return jax.nn.one_hot(z, K, dtype=jnp.float64) * mask[..., None]


def _label_invariant(z, mask, K):
    """(skills used, mean switches per trajectory), trajectories without steps (padding) left out."""
    used = jnp.any(skill_weights(z, mask, K) > 0, axis=(0, 1))
    switches = jnp.sum((z[:, 1:] != z[:, :-1]) & mask[:, 1:], axis=1)
    real = jnp.sum(jnp.any(mask, axis=1))
    mean = jnp.sum(switches.astype(jnp.float64)) / jnp.maximum(real, 1).astype(jnp.float64)
    return jnp.sum(used).astype(jnp.int32), mean


class BPHMMKernel(MCMCKernel, Pytree):
    """Gibbs sampler of the BP-HMM for any emission model.

    Args:
        emission: an :class:`~npbrs.models.emissions.Emission`.
        data: :class:`~npbrs.models.emissions.HMMData`.
        max_skills: truncation K (skill slots).
        alpha, kappa, gamma: BP-HMM hyperparameters (initial values when sampled).
        hyperpriors: optional {"alpha" | "kappa" | "gamma": (shape, rate)}: sample those.
        init_skills: skills used by the initial state (data-driven: trajectories cut into
            windows of ``init_window`` steps assigned to skills at random, each skill's
            parameters proposed from its windows; None: :func:`initial_skills`'s).
        init_window: window length of the initial segmentation (None: :func:`initial_window`'s).
        sample_features: Gibbs on the features (off only for tests of the other steps).
        moves: the moves' options (:data:`npbrs.inference.sampler.options.MOVE_DEFAULTS`: every
            move and aid off, a redraw every sweep). The exact moves: "birth_death" and
            "split_merge" trials per sweep (split-merge: the emission needs ``fit_point``),
            "window", "blocks", "start" (the sweep, warmup included, from which they run; before
            it a sweep is plain Gibbs), "redraw_unused" (the sweeps between prior redraws of the
            parameters of skills without steps, their exact conditional; kept as they are in
            between, also exact, which saves the reward emission's solves). The warmup aids, not
            MCMC moves (the sampling sweeps and the log joint are the model's): "sticky_start",
            "sticky_phase", "greedy_merge", "greedy_split" (the emission needs ``fit_evidence``),
            "greedy_from", "greedy_patience": :mod:`npbrs.inference.sampler.schedule`.
        termination: a :class:`~npbrs.models.bphmm.Termination`: skills end with a probability
            that depends on the state entered (sampled); None: the sticky BP-HMM.
    """

    sample_field = "params"

    def __init__(self, emission: Emission, data: HMMData, max_skills: int, alpha=1.0, kappa=10.0,
                 gamma=1.0, hyperpriors: Optional[Dict] = None, init_skills: Optional[int] = None,
                 init_window: Optional[int] = None, sample_features: bool = True, moves: Optional[Dict] = None,
                 termination: Optional[Termination] = None):
        self.emission = emission
        self.termination = None if termination is None else Termination(
            int(termination.num_states), float(termination.concentration),
            tuple(float(x) for x in termination.mean_prior))
        self.data = data
        self.max_skills = int(max_skills)
        self.hyper0 = Hyper(jnp.float64(alpha), jnp.float64(kappa), jnp.float64(gamma))
        self.hyperpriors = dict(hyperpriors or {})
        self.init_skills = initial_skills(emission, self.max_skills, init_skills)
        self.init_window = initial_window(emission, init_window)
        self.sample_features = bool(sample_features)
        self.moves = check_moves(moves)
        if self.moves["split_merge"] and not emission.supports_split_merge():
            raise ValueError(f"moves.split_merge: the {emission.name!r} emission has no fit_point, which "
                             "split-merge moves need; use birth_death moves or implement Emission.fit_point")
        for name in ("greedy_merge", "greedy_split"):
            if self.moves[name] and not emission.supports_greedy_merge():
                raise ValueError(f"moves.{name}: the {emission.name!r} emission has no fit_evidence, which greedy "
                                 "moves need; implement Emission.fit_evidence")

    # ------------------------------------------------------------------ numpyro hooks
    @property
    def model(self):
        return partial(bphmm_model, self.data, self.emission, self.max_skills, *self.hyper0,
                       hyperpriors=self.hyperpriors or None, termination=self.termination)

    @property
    def default_fields(self):
        ends = ("ends", "end_mean") if self.termination is not None else ()
        return ("params", "log_joint", "num_skills", "num_switches", "features", "accept", "birth_accept",
                "split_accept", "greedy_merges", "greedy_splits") + ends

    def get_diagnostics_str(self, state):
        return f"log joint {float(state.log_joint):.1f}, skills {int(state.num_skills)}"

    def init(self, rng_key, num_warmup, init_params, model_args, model_kwargs):
        """Initial state(s). ``init_params`` may hold {"z": (N, T) skill labels in [0, K)}: start
        every chain from that segmentation (see :meth:`check_segmentation`) instead of the
        random windows."""
        batched = jnp.ndim(rng_key) > 1 or (jax.dtypes.issubdtype(rng_key.dtype, jax.dtypes.prng_key)
                                            and jnp.ndim(rng_key) > 0)
        z0 = None if not init_params or init_params.get("z") is None else jnp.asarray(init_params["z"], jnp.int32)
        return _init_state(self, rng_key, z0, jnp.asarray(num_warmup, jnp.int32), batched)

    def check_segmentation(self, z) -> np.ndarray:
        """An initial segmentation as an (N, T) int32 array in [0, K) (-1 on padding), from per
        trajectory label arrays (any integers; relabelled 0, 1, ... in order of value) or an
        (N, T) array; ValueError naming the trajectory and step of a bad entry."""
        N, T = self.data.states.shape
        lengths = np.asarray(self.data.mask).sum(1)
        N_real = int(np.sum(lengths > 0))  # trajectories padding the data to a bucket have no step
        if isinstance(z, np.ndarray) and z.ndim == 2:
            z = [z[i, :lengths[i]] for i in range(z.shape[0])] if z.shape == (N, T) else list(z)
        try:
            rows = [np.asarray(r) for r in z]
        except TypeError:
            raise ValueError(f"init_segmentation must be a sequence of per-trajectory label arrays, got "
                             f"{type(z).__name__}") from None
        if len(rows) == N and N_real < N:
            rows = rows[:N_real]
        if len(rows) != N_real:
            raise ValueError(f"init_segmentation has {len(rows)} trajectories, the demonstrations {N_real}")
        for i, r in enumerate(rows):
            if r.shape != (lengths[i],):
                raise ValueError(f"init_segmentation[{i}] has shape {r.shape}; trajectory {i} has {lengths[i]} steps")
            if r.dtype.kind not in "biuf":
                raise ValueError(f"init_segmentation[{i}] holds {r.dtype} values, not integer skill labels")
            if r.size and r.dtype.kind == "f" and (not np.all(np.isfinite(r)) or np.any(r != np.round(r))):
                bad = int(np.argmax(~np.isfinite(r) | (r != np.round(r))))
                raise ValueError(f"init_segmentation[{i}][{bad}] = {r[bad].item()!r} is not an integer skill label")
        labels = np.unique(np.concatenate(rows).astype(np.int64))
        if len(labels) > self.max_skills:
            raise ValueError(f"init_segmentation uses {len(labels)} skills, more than max_skills = {self.max_skills}")
        out = np.full((N, T), -1, np.int32)
        for i, r in enumerate(rows):
            out[i, :lengths[i]] = np.searchsorted(labels, r.astype(np.int64))
        return out

    def sample(self, state, model_args, model_kwargs):
        if jnp.ndim(state.step) > 0:
            # the chains sweep in lock-step: one unbatched "moves on" flag keeps the moves a real
            # conditional under vmap (a batched predicate would run them in every sweep), and one
            # for the greedy moves of all chains (see :meth:`greedy_open`)
            clock = (state.step[0], state.num_warmup[0], self.greedy_open(state))
            return jax.vmap(self.sweep, in_axes=(0, None))(state, clock)
        return self.sweep(state)

    # ------------------------------------------------------------------ pieces
    @property
    def schedule(self) -> WarmupSchedule:
        """The warmup aids of this kernel's ``moves`` (built on each call: not part of the pytree)."""
        return WarmupSchedule.of(self.moves, self.hyperpriors)

    @property
    def _valid(self):
        """(N,) the trajectories with steps: the others pad the data (to a shape bucket, or to the
        devices), after the real ones, and are left out of the model (see
        :mod:`npbrs.inference.sampler.conditionals`): a padded run's draws of the real
        trajectories are the unpadded run's."""
        return jnp.any(self.data.mask, axis=1)

    def greedy_open(self, state: BPHMMState):
        """Whether the greedy moves still run (``moves["greedy_patience"]``): while some chain of
        ``state`` (one chain, or chains stacked on axis 0) has kept a greedy move in its last
        ``greedy_patience`` greedy sweeps. The chains of a run stop them together (vectorised,
        skipping them saves time only then), so a driver that sweeps the chains one at a time
        passes this of all of them as the sweep's ``clock`` (numpyro's sequential chains, which
        see one chain at a time, stop each chain's on its own). See :meth:`WarmupSchedule.greedy_open`."""
        return self.schedule.greedy_open(state.greedy_idle)

    def gate(self, state: BPHMMState):
        """(N, T, K) every step's end probabilities under ``state``'s ends (the filters' gate),
        or None without state-dependent ends."""
        if self.termination is None:
            return None
        return end_gate(state.ends, self.data.states, self.data.mask)

    def _finish(self, state: BPHMMState, solved: bool = False) -> BPHMMState:
        """Recompute likelihoods, the log joint and the summaries of ``state``; ``solved``: its
        cache is the emission's update's, whose values are its parameters' (``Emission.solves_in_update``)."""
        K = self.max_skills
        log_lik, cache = self.emission.log_likelihoods(state.params, self.data, state.cache,
                                                       **({"solved": True} if solved else {}))
        log_marg = log_marginal_likelihoods(state.features, state.eta, log_lik, self.data.mask, self.gate(state))
        terms = log_joint_terms(state.omega, state.features, state.eta, state.params, log_marg, state.hyper,
                                self.emission, self.hyperpriors or None, valid=self._valid, ends=state.ends,
                                end_mean=state.end_mean, termination=self.termination)
        log_joint = sum(terms.values())
        num_skills, num_switches = _label_invariant(state.z, self.data.mask, K)
        return state._replace(cache=cache, log_lik=log_lik, log_marginals=log_marg, log_joint=log_joint,
                              num_skills=num_skills, num_switches=num_switches)

    def initial_state(self, rng_key, z0=None, num_warmup=0) -> BPHMMState:
        """One chain's initial state for ``rng_key`` (no checks, no compilation of its own: it
        traces under ``jit``, ``vmap`` and ``eval_shape``). ``z0``: an (N, T) segmentation to
        start from (see :meth:`check_segmentation`), or None: random windows of
        ``init_window`` steps over ``init_skills`` skills. ``num_warmup``: the chain's warmup
        sweeps. :meth:`init` is numpyro's entry point, compiled and batched over keys."""
        N, T = self.data.states.shape
        K, K0 = self.max_skills, self.init_skills
        keys = jax.random.split(rng_key, 6)
        if z0 is None:
            num_windows = -(-T // self.init_window)
            window_skill = jax.random.randint(keys[0], (N, num_windows), 0, K0)
            z = jnp.repeat(window_skill, self.init_window, axis=1)[:, :T]
        else:
            z = z0
        z = jnp.where(self.data.mask, z, -1).astype(jnp.int32)
        weights = skill_weights(z, self.data.mask, K)
        # (a starting point: fitted at the emission's search accuracy, Emission.for_search)
        params = self.emission.for_search().init_params(keys[1], self.data, weights)
        if z0 is None:
            features = jnp.zeros((N, K)).at[:, :K0].set(1.0)
        else:  # a given segmentation: each trajectory has the features of the skills it uses
            features = (jnp.sum(weights, axis=1) > 0).astype(jnp.float64)
        hyper = self.hyper0
        eta, omega = sample_eta_omega(keys[3], z, features, hyper, self.data.mask, self.termination is not None)
        ends = end_mean = None
        if self.termination is not None:
            a, b = self.termination.mean_prior  # (the means start at their prior's)
            end_mean, ends = sample_end_model(keys[5], z, features, jnp.full((K,), a / (a + b)), self.data,
                                              self.termination)
        zero = jnp.float64(0.0)
        state = BPHMMState(
            step=jnp.int32(0), num_warmup=jnp.asarray(num_warmup, jnp.int32), rng_key=keys[4], omega=omega,
            features=features, eta=eta, params=params,
            cache=self.emission.init_cache(K), hyper=hyper, z=z,
            log_lik=jnp.zeros((N, T, K)), log_marginals=jnp.zeros(N), log_joint=zero,
            num_skills=jnp.int32(0), num_switches=zero, accept=zero, birth_accept=zero, split_accept=zero,
            greedy_merges=jnp.int32(0), greedy_splits=jnp.int32(0), greedy_idle=jnp.int32(0),
            best_log_joint=jnp.float64(-jnp.inf), best_z=z,
            best_params=params, best_features=features, ends=ends, end_mean=end_mean)
        return self._finish(state)

    def sample_eta(self, key, z, features, hyper):
        """A draw of the transition weights eta (N, K, K) from their conditional given the skill
        sequences z (N, T), the features (N, K) and the hyperparameters (see
        :func:`~npbrs.inference.sampler.conditionals.sample_eta_omega`, which the sweep calls to
        draw omega in the same batch)."""
        return sample_eta_omega(key, z, features, hyper, self.data.mask, self.termination is not None)[0]

    def feature_logits(self, state: BPHMMState, features, k, current=None) -> jax.Array:
        """log p(f_ik = 1 | rest) - log p(f_ik = 0 | rest) for every trajectory i, (N,),
        with the skill sequences summed out. ``features`` replaces ``state.features``;
        ``current``: the trajectories' log marginals under ``features`` when known (the
        sweep carries them); otherwise they are filtered too (see
        :func:`~npbrs.inference.sampler.conditionals.feature_conditional`)."""
        return feature_conditional(features, k, state.eta, state.log_lik, state.omega, self.data.mask,
                                   self.gate(state), None, current)[0]

    def sweep(self, state: BPHMMState, clock=None) -> BPHMMState:
        """One full sweep: features, birth/death, skill sequences, split-merge, greedy merges
        (warmup only), eta and omega, emission parameters, hyperparameters. The moves run from
        sweep ``moves["start"]`` on; the warmup aids as :attr:`schedule` decides. ``clock``:
        (sweep, warmup sweeps, :meth:`greedy_open`) as unbatched scalars that replace the
        state's own for those tests: :meth:`sample` passes the first chain's, shared by
        vectorised chains so that the tests stay real conditionals under vmap (a batched
        predicate would run both branches in every sweep)."""
        N, K = state.features.shape
        mask = self.data.mask
        schedule = self.schedule
        step, num_warmup, greedy_any = ((state.step, state.num_warmup, self.greedy_open(state)) if clock is None
                                        else clock)
        model_kappa = state.hyper.kappa
        state = state._replace(hyper=schedule.sticky_hyper(state.hyper, step, num_warmup))
        key, k_feat, k_bd, k_z, k_eta, k_em, k_hyp, k_sm = jax.random.split(state.rng_key, 8)
        k_gm = jax.random.fold_in(k_sm, 1)
        # the ends are held fixed until step 3 (in the sticky phase, the sticky BP-HMM's switching)
        gate, gated, current = schedule.switching(self.gate(state), state, mask, step, num_warmup)
        features = (sample_features(k_feat, state.features, state.eta, state.log_lik, state.omega, mask, current,
                                    gate, gated) if self.sample_features else state.features)
        # the moves' state (``npbrs.inference.sampler.state``): each move maps it to a new one
        # (in the sticky phase they move the sticky BP-HMM, as the sweep does)
        end_model = None
        if self.termination is not None:  # (the greedy moves score skill sequences with the ends integrated out)
            end_model = (state.ends, state.end_mean, jnp.float64(self.termination.concentration))
        moved = MoveState.of(state, gate, gated, end_model)._replace(features=features)
        # the emission as the work that is not an MCMC move uses it: the greedy moves, the tune
        search = self.emission.for_search()
        blocks = min(self.moves["blocks"], N)  # refits of a split's allocation (split-merge, greedy splits)
        moves_on = True
        if self.moves["start"]:
            moves_on = step >= self.moves["start"]
        if moves_on is not True:
            def gated_move(run, operands, skipped):
                """run(operands) from the start sweep on; before it, (operands, skipped)."""
                return jax.lax.cond(moves_on, run, lambda ops: (ops, skipped), operands)
        else:
            def gated_move(run, operands, skipped):
                return run(operands)

        def trials(move, key, count):
            """``count`` trials of ``move`` from ``moved``: (state, each trial's accepted (count,))."""
            def one(carry, key):
                carry, info = move(key, carry, self.emission, self.data, state.hyper)
                return carry, info.accepted

            return lambda ops: jax.lax.scan(one, ops, jax.random.split(key, count))

        births = jnp.zeros(())
        if self.moves["birth_death"]:
            lo, hi = self.moves["window"]
            run = trials(partial(birth_death, min_len=lo, max_len=hi), k_bd, self.moves["birth_death"])

            def births_run(ops):
                ops, accepted = run(ops)
                return ops, jnp.mean(accepted.astype(jnp.float64))

            moved, births = gated_move(births_run, moved, births)
        log_init, log_trans, active = hmm_parameters(moved.features, state.eta, gated)
        _, log_alpha = batch_forward_filter(log_init, log_trans, moved.log_lik, mask, active, gate)
        moved = moved._replace(z=batch_backward_sample(k_z, log_trans, log_alpha, mask, active, gate))
        splits = jnp.zeros(())
        if self.moves["split_merge"]:
            run = trials(partial(split_merge, num_blocks=blocks), k_sm, self.moves["split_merge"])

            def splits_run(ops):
                ops, accepted = run(ops)
                return ops, jnp.mean(accepted.astype(jnp.float64))

            # eta changes here only for trajectories a move touched; eta is redrawn after the moves
            moved, splits = gated_move(splits_run, moved, splits)
        moved, greedy_kept = schedule.greedy_step(k_gm, moved, search, self.data, state.hyper, blocks,
                                                  (state.greedy_merges, state.greedy_splits, state.greedy_idle),
                                                  (step, num_warmup, greedy_any))
        features, z, params = moved.features, moved.z, moved.params
        hyper = state.hyper
        if self.hyperpriors:  # (hyperparameters | z, F), then (eta, omega | z, F, hyperparameters)
            hyper = sample_hyperparameters(k_hyp, z, features, hyper, self.hyperpriors, mask, gate, gated)
        # eta | z, F and omega | F are conditionally independent: one block
        eta, omega = sample_eta_omega(k_eta, z, features, hyper, mask, gated)
        ends = {}
        if self.termination is not None:
            mean0 = state.end_mean if moved.end_model is None else moved.end_model[1]
            end_mean, new_ends = sample_end_model(jax.random.fold_in(k_eta, 1), z, features, mean0, self.data,
                                                  self.termination)
            ends = dict(ends=new_ends, end_mean=end_mean)
        weights = skill_weights(z, mask, K)
        cache, tuned = schedule.tune_step(self.emission, search, params, state.cache, self.data, weights, step,
                                          num_warmup)
        every = self.moves["redraw_unused"]
        solved = bool(self.emission.solves_in_update)
        if solved:  # (the update draws or keeps the unused skills' parameters itself)
            tuned["redraw_unused"] = (step % every == 0) if every > 1 else True
        params, cache, info = self.emission.update(k_em, params, cache, self.data, weights, step < num_warmup, **tuned)
        if not isinstance(info, EmissionInfo):
            raise TypeError(f"the {self.emission.name!r} emission's update returned {type(info).__name__} as its "
                            "info; it must return (params, cache, npbrs.models.emissions.EmissionInfo(accept=...))")
        if every > 1 and not solved:
            # a skill without steps has its prior as conditional: the update's prior draw every
            # ``every`` sweeps (the clock's, shared by vectorised chains), and between those the
            # parameters as they are (also exact), whose likelihoods need no new solve
            keep = ~jnp.any(weights > 0, axis=(0, 1)) & (step % every != 0)
            params = select(keep, moved.params, params)
        accept = jnp.asarray(info.accept, jnp.float64)
        new = state._replace(rng_key=key, omega=omega, features=features, eta=eta, params=params, cache=cache,
                             z=z, accept=jnp.mean(accept), birth_accept=births, split_accept=splits,
                             hyper=hyper, **greedy_kept, **ends)
        new = self._finish(new._replace(hyper=schedule.model_hyper(new.hyper, model_kappa)), solved)
        better = (state.step >= state.num_warmup) & (new.log_joint > state.best_log_joint)
        pick = lambda a, b: jax.tree.map(lambda x, y: jnp.where(better, x, y), a, b)  # noqa: E731
        return new._replace(step=state.step + 1, best_log_joint=jnp.where(better, new.log_joint, state.best_log_joint),
                            best_z=pick(new.z, state.best_z), best_params=pick(new.params, state.best_params),
                            best_features=pick(new.features, state.best_features))

    def sample_hyperparameters(self, key, z, features, hyper: Hyper, gate=None, gated=None) -> Hyper:
        """The hyperparameters with a prior (``hyperpriors``) given the skill sequences z (N, T)
        and the features (N, K), omega and eta integrated out
        (:func:`~npbrs.inference.sampler.conditionals.sample_hyperparameters`); ``gate``: the
        ends' with state-dependent ends (``gated``, a traced bool, false in the sticky phase)."""
        return sample_hyperparameters(key, z, features, hyper, self.hyperpriors, self.data.mask, gate, gated)


@partial(jit, static_argnums=4, once=True)
def _init_state(kernel: BPHMMKernel, rng_key, z0, num_warmup, batched: bool):
    """The initial state(s), compiled per kernel structure and shapes (the kernel's data and
    emission are arguments, so a new dataset of the same shapes reuses the program)."""
    if batched:
        return jax.vmap(kernel.initial_state, in_axes=(0, None, None))(rng_key, z0, num_warmup)
    return kernel.initial_state(rng_key, z0, num_warmup)


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
