"""The warmup schedule around the exact sweep: search aids that run in warmup only.

:class:`~npbrs.inference.sampler.kernel.BPHMMKernel`'s sweep samples the posterior with exact
Gibbs steps and Metropolis-Hastings moves. In warmup, whose draws are discarded, it also runs
aids that change where the sampling sweeps start but not what they sample. Each is off unless
its option (``moves``, :data:`npbrs.inference.sampler.options.MOVE_DEFAULTS`) turns it on:

- the sticky start (``sticky_start``: a factor f >= 1 on a fixed kappa): the sweep sees kappa
  times a factor that falls linearly from f at the first sweep to 1 at mid-warmup
  (:meth:`WarmupSchedule.sticky_hyper`). Long segments while the skills form keep one-hot
  rewards' search from over-switched modes (``benchmarks/NOTES.md``). No effect when kappa is
  sampled;
- the sticky phase (``sticky_phase``: with state-dependent ends, a fraction of warmup): those
  sweeps search under the sticky BP-HMM, each trajectory's own stays (eta's diagonal) instead
  of the ends (:meth:`WarmupSchedule.switching`; the trans-dimensional and greedy moves move
  that sticky model too). From a random start the state model's search mixes the skills'
  goals where the sticky one does not (``benchmarks/NOTES.md``); the ends are drawn from the
  skill sequences in every sweep, so they are ready when the phase ends;
- the greedy merges and splits (``greedy_merge``, ``greedy_split``: trials per sweep, from
  ``greedy_from`` x warmup on; :mod:`npbrs.inference.sampler.greedy`), which stop for the rest
  of warmup once every chain's last ``greedy_patience`` greedy sweeps kept nothing
  (:meth:`WarmupSchedule.greedy_open`, :meth:`WarmupSchedule.greedy_step`; a greedy sweep costs
  several plain ones, and a long warmup's chains have mostly settled by then);
- the emission's tuning (its ``tune``, every ``tune_every`` warmup sweeps: e.g. the reward
  move's preconditioner, :meth:`WarmupSchedule.tune_step`). Any fixed preconditioner leaves
  the posterior invariant; tuning it changes the move's efficiency only.

The sampling sweeps and the log joint keep the model's kappa and switching.

A sweep decides with its *clock*, ``(step, num_warmup, greedy_open)``: the sweeps done, the
warmup sweeps, and :meth:`WarmupSchedule.greedy_open` of the run's chains. Vectorised chains
sweep in lock-step and share the first chain's clock, so that each decision is one unbatched
predicate and ``jax.lax.cond`` runs one branch (a batched predicate would run both in every
sweep). The kernel calls, in sweep order: :meth:`~WarmupSchedule.sticky_hyper` (before the
sweep's keys are split), :meth:`~WarmupSchedule.switching` (before the features),
:meth:`~WarmupSchedule.greedy_step` (after split-merge), :meth:`~WarmupSchedule.tune_step`
(before the emission's update) and :meth:`~WarmupSchedule.model_hyper` (on the new state).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from npbrs.models.bphmm import Hyper, log_marginal_likelihoods

from .greedy import greedy_trials
from .state import MoveState

__all__ = ["WarmupSchedule"]


class WarmupSchedule(NamedTuple):
    """Which warmup aids a kernel runs, from its ``moves`` options (plain values: the kernel
    builds it from its options, so it adds nothing to the kernel's pytree).

    sticky_start: the factor on kappa at the first sweep (1: off). sticky_phase: the fraction
    of warmup under sticky switching (0: off). greedy_merge, greedy_split: greedy trials per
    sweep (0: off). greedy_from: the fraction of warmup from which they run. greedy_patience:
    greedy sweeps without a kept move after which they stop (0: never). fixed_kappa: whether
    kappa is fixed (no hyperprior; the sticky start acts only then).
    """

    sticky_start: float = 1.0
    sticky_phase: float = 0.0
    greedy_merge: int = 0
    greedy_split: int = 0
    greedy_from: float = 0.75
    greedy_patience: int = 10
    fixed_kappa: bool = True

    @classmethod
    def of(cls, moves: dict, hyperpriors=None) -> "WarmupSchedule":
        """The schedule of checked ``moves`` options (``check_moves``) and the kernel's
        ``hyperpriors`` ({name: (shape, rate)} or None)."""
        return cls(moves["sticky_start"], moves["sticky_phase"], moves["greedy_merge"], moves["greedy_split"],
                   moves["greedy_from"], moves["greedy_patience"], "kappa" not in (hyperpriors or {}))

    @property
    def sticky(self) -> bool:
        """Whether the sticky start is on (a factor > 1 on a fixed kappa)."""
        return self.sticky_start > 1.0 and self.fixed_kappa

    @property
    def greedy(self) -> bool:
        """Whether any greedy trials run."""
        return bool(self.greedy_merge or self.greedy_split)

    def greedy_open(self, greedy_idle):
        """Whether the greedy moves still run: while some chain has kept a greedy move in its
        last ``greedy_patience`` greedy sweeps.

        Args:
            greedy_idle: () or (chains,) int: each chain's greedy sweeps in a row that kept
                nothing (NumPy on the host, or JAX).

        Returns:
            () bool, NumPy for a NumPy ``greedy_idle`` (a host state stays on the host).
        """
        patience = self.greedy_patience
        xp = np if isinstance(greedy_idle, (np.ndarray, np.generic)) else jnp
        return xp.any(greedy_idle < patience) if patience else xp.bool_(True)

    def sticky_hyper(self, hyper: Hyper, step, num_warmup) -> Hyper:
        """The hyperparameters the sweep sees: ``hyper`` with kappa times the sticky start's
        factor, which falls linearly from ``sticky_start`` at sweep 0 to 1 at mid-warmup;
        ``hyper`` itself when the sticky start is off.

        Args:
            hyper: the chain's :class:`~npbrs.models.bphmm.Hyper`.
            step, num_warmup: () int, the clock's sweep and warmup sweeps.

        Returns:
            Hyper.
        """
        if not self.sticky:
            return hyper
        half = jnp.maximum(num_warmup // 2, 1)
        factor = self.sticky_start + (1.0 - self.sticky_start) * jnp.clip(step / half, 0.0, 1.0)
        return hyper._replace(kappa=hyper.kappa * factor)

    def model_hyper(self, hyper: Hyper, kappa) -> Hyper:
        """The new state's hyperparameters with the model's ``kappa`` back (the sticky start
        never reaches the state: the log joint and the sampling sweeps keep the model's)."""
        return hyper._replace(kappa=kappa) if self.sticky else hyper

    def switching(self, gate, state, mask, step, num_warmup):
        """The filters' switching in this sweep: the model's, or in the sticky phase the sticky
        BP-HMM's (a gate of ones with eta's diagonal: every step "ends" and redraws from its
        trajectory's row).

        Args:
            gate: (N, T, K) the ends' gate of ``state``, or None without state-dependent ends.
            state: the chain's state (its features, eta, log_lik and log_marginals are read).
            mask: (N, T) the data's real steps.
            step, num_warmup: () int, the clock's sweep and warmup sweeps.

        Returns:
            (gate (N, T, K) or None, gated: a traced bool with a gate (false in the sticky
            phase), else False, the trajectories' log marginals (N,) under that switching).
        """
        ends_on, current = True, state.log_marginals
        if gate is not None and self.sticky_phase > 0.0:
            ends_on = step >= jnp.floor(self.sticky_phase * num_warmup)
            gate = jnp.where(ends_on, gate, 1.0)
            current = jax.lax.cond(ends_on, lambda s: s.log_marginals, lambda s: log_marginal_likelihoods(
                s.features, s.eta, s.log_lik, mask, gate, False), state)
        gated = ends_on if gate is not None else False
        return gate, gated, current

    def greedy_step(self, key, moved: MoveState, search, data, hyper: Hyper, num_blocks: int, counts, clock):
        """The greedy trials of this sweep (:func:`~npbrs.inference.sampler.greedy.greedy_trials`),
        in the warmup sweeps from ``greedy_from`` x warmup on while :meth:`greedy_open`.

        Args:
            key: the sweep's greedy key (split into the merges' and the splits' keys).
            moved: the moves' :class:`~npbrs.inference.sampler.state.MoveState`.
            search: the emission as search uses it (``Emission.for_search``: not an MCMC move,
                so its fits may be solved less exactly).
            data: HMMData. hyper: the sweep's hyperparameters.
            num_blocks: refits of a split's allocation.
            counts: (greedy_merges, greedy_splits, greedy_idle) of the chain, () int each.
            clock: (step, num_warmup, greedy_open) of the sweep.

        Returns:
            (moved, {"greedy_merges", "greedy_splits", "greedy_idle": the new counts}); with no
            greedy trials configured, (moved, {}).
        """
        if not self.greedy:
            return moved, {}
        step, num_warmup, greedy_any = clock
        merges, splits, idle = counts
        greedy_on = (step < num_warmup) & (step >= jnp.floor(self.greedy_from * num_warmup))

        def greedy_run(ops):
            k_merge, k_split = jax.random.split(key)
            ops, merged, split = greedy_trials(k_merge, k_split, ops, search, data, hyper, self.greedy_merge,
                                               self.greedy_split, num_blocks)
            return ops, (merged, split)

        # the trials stop for every chain at once (``greedy_any``: while any chain's last
        # ``greedy_patience`` greedy sweeps kept something), so that skipping them saves time
        ran = greedy_on & greedy_any
        moved, (merged, split) = jax.lax.cond(ran, greedy_run, lambda ops: (ops, (jnp.int32(0), jnp.int32(0))),
                                              moved)
        idle = jnp.where(ran, jnp.where(merged + split > 0, 0, idle + 1), idle)
        return moved, dict(greedy_merges=merges + merged, greedy_splits=splits + split,
                           greedy_idle=idle.astype(jnp.int32))

    @staticmethod
    def tune_step(emission, search, params, cache, data, weights, step, num_warmup):
        """The emission's tuning in this sweep (its ``tune``, e.g. a preconditioner: any fixed
        one leaves the posterior invariant; the search's accuracy), every ``tune_every`` warmup
        sweeps. The clock, not the state's step: under vectorised chains a batched flag would
        make the emission's warmup-only work run always.

        Args:
            emission: the sweep's emission; search: its ``for_search()`` (whose ``tune`` runs).
            params, cache: the parameters before the update and the emission's cache.
            data: HMMData. weights: (N, T, K) the steps assigned to each skill.
            step, num_warmup: () int, the clock's sweep and warmup sweeps.

        Returns:
            (cache, keyword arguments for ``emission.update``: {"tune": flag} when the update
            tunes itself, else {} with the cache tuned here).
        """
        tune, tuned = search.tune, {}
        if tune is not None:
            every = int(emission.tune_every)
            tune_now = (step < num_warmup) & (step % every == 0)
            if emission.tunes_in_update:
                tuned = {"tune": tune_now}  # (the update tunes itself where it has what tuning needs)
            else:
                cache = jax.lax.cond(tune_now, lambda c: tune(params, c, data, weights), lambda c: c, cache)
        return cache, tuned
