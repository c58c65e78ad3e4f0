"""The chain's state (:class:`BPHMMState`: what the kernel's next sweep needs) and the part of
it that the sampler's moves read and change (:class:`MoveState`).

Every move is ``move(key, state, emission, data, hyper, ...) -> (state, info)``: ``state`` a
:class:`MoveState`, ``info`` a NamedTuple of the move's own, for diagnostics only (whether the
trial was possible and accepted, its log acceptance ratio or gain, the skills it touched). A
Metropolis-Hastings move decides with :func:`npbrs.models.mcmc.metropolis_accept` and keeps the
proposed or the current state with :func:`npbrs.models.mcmc.select`; its log acceptance ratio is
a public function of the current and the proposed state (``birth_death_log_ratio``,
``split_merge_log_ratio``).
"""

from __future__ import annotations

from typing import Any, Dict, NamedTuple, Optional

import jax

from npbrs.models.bphmm import Hyper

__all__ = ["BPHMMState", "MoveState"]


class BPHMMState(NamedTuple):
    """State of one chain of the BP-HMM sampler.

    step: sweeps done. num_warmup: sweeps of warmup (adaptation, no best-state tracking). rng_key: the chain's key. omega (K,), features (N, K) 0/1, eta (N, K, K),
    ends (K, S) and end_mean (K,): state-dependent end probabilities and their means (None
    without them),
    params: emission parameters {site: (K, ...)}, cache: emission cache, hyper: Hyper,
    z (N, T) skill sequences (-1 on padding), log_lik (N, T, K), log_marginals (N,),
    log_joint: the model's log density, num_skills: skills used by z, num_switches: mean
    switches per trajectory, accept: the emission move's mean acceptance, birth_accept: the
    fraction of birth/death trials accepted in the last sweep, split_accept: likewise for
    split-merge trials, greedy_merges, greedy_splits: the greedy merges and splits kept so far
    (they run in warmup only, so a draw shows warmup's totals), greedy_idle: the greedy sweeps
    in a row that kept nothing (``moves["greedy_patience"]``), best_*: the
    highest-log-joint state seen after warmup.
    """

    step: jax.Array
    num_warmup: jax.Array
    rng_key: jax.Array
    omega: jax.Array
    features: jax.Array
    eta: jax.Array
    params: Dict[str, jax.Array]
    cache: Any
    hyper: Hyper
    z: jax.Array
    log_lik: jax.Array
    log_marginals: jax.Array
    log_joint: jax.Array
    num_skills: jax.Array
    num_switches: jax.Array
    accept: jax.Array
    birth_accept: jax.Array
    split_accept: jax.Array
    greedy_merges: jax.Array
    greedy_splits: jax.Array
    greedy_idle: jax.Array
    best_log_joint: jax.Array
    best_z: jax.Array
    best_params: Dict[str, jax.Array]
    best_features: jax.Array
    ends: Any = None
    end_mean: Any = None


class MoveState(NamedTuple):
    """The chain's state as the moves see it (a pytree; K skill slots, N trajectories, T steps).

    features: (N, K) 0/1, which skills each trajectory may use. eta: (N, K, K) unnormalised
    transition weights. z: (N, T) skill sequences (-1 on padding). params: the emission's
    parameters {site: (K, ...)}. log_lik: (N, T, K) per-step log-likelihoods of ``params``
    (every move keeps them equal). gate: the ends' (N, T, K) with state-dependent ends (the
    moves hold it fixed), else None. gated: with a gate, a traced bool, false in the kernel's
    sticky phase (a gate of ones with eta's diagonal: the sticky BP-HMM, whose moves then run
    too); None: whether a gate is given (:attr:`is_gated`). end_model: with state-dependent
    ends, (ends (K, S), their means (K,), the concentration c), by which the greedy moves score
    skill sequences with the ends integrated out; None otherwise.
    """

    features: jax.Array
    eta: jax.Array
    z: jax.Array
    params: Dict[str, jax.Array]
    log_lik: jax.Array
    gate: Optional[jax.Array] = None
    gated: Optional[jax.Array] = None
    end_model: Optional[tuple] = None

    @property
    def is_gated(self):
        """Whether the ends switch: False without a gate, else ``gated`` (True when None)."""
        if self.gate is None:
            return False
        return True if self.gated is None else self.gated

    @classmethod
    def of(cls, state, gate=None, gated=None, end_model=None) -> "MoveState":
        """The moves' part of a state with these fields (e.g. a :class:`BPHMMState`), and
        the ``gate``, ``gated`` and ``end_model`` given."""
        return cls(*(getattr(state, name) for name in cls._fields[:-3]), gate, gated, end_model)
