"""Tabular Markov decision processes with sparse successor transitions and reward features.

A :class:`TabularMDP` stores its dynamics as successor indices and probabilities of shape
``(S, A, B)``: ``successors[s, a, b]`` is a possible next state of taking ``a`` in ``s`` and
``probs[s, a, b]`` its probability (unused slots have probability 0 and point at state 0).
Rewards are linear in features: ``r(s, a) = features[s, a] . theta``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from .util.pytree import Pytree

__all__ = ["TabularMDP"]

_PROB_ATOL = 1e-6


def _first_bad(mask: np.ndarray):
    """Index tuple of the first True entry of ``mask``."""
    return tuple(int(i) for i in np.argwhere(mask)[0])


def set_frozen(obj, **fields) -> None:
    """Set the fields of a frozen dataclass instance, making its arrays read-only."""
    for name, value in fields.items():
        if isinstance(value, np.ndarray):
            value.setflags(write=False)
        object.__setattr__(obj, name, value)


@dataclass(frozen=True, eq=False)
class TabularMDP(Pytree):
    """A finite MDP with known dynamics and linear reward features.

    Args:
        successors: int array (S, A, B), next-state indices.
        probs: float array (S, A, B), their probabilities; each (s, a) row sums to 1.
        features: float array (S, A, D), reward features phi(s, a).
        feature_names: D names of the features.
        initial: float array (S,), initial-state distribution (uniform when omitted).
        discount: gamma in [0, 1).
        state_vectors: optional float array (S, M), a numeric description of every state
            (used by emissions that model states as vectors, e.g. the autoregressive one).
        next_value_fn: optional domain-supplied operator mapping values V of shape
            (..., S) to expected next values E[V(s') | s, a] of shape (..., S, A), written in
            ``jax.numpy``; it must agree with ``successors``/``probs``.
        name: a label for messages and plots.
    """

    successors: np.ndarray
    probs: np.ndarray
    features: np.ndarray
    feature_names: tuple = ()
    initial: Optional[np.ndarray] = None
    discount: float = 0.95
    state_vectors: Optional[np.ndarray] = None
    next_value_fn: Optional[Callable] = field(default=None, repr=False)
    name: str = "mdp"

    def __post_init__(self):
        succ = np.asarray(self.successors)
        probs = np.asarray(self.probs, dtype=np.float64)
        feats = np.asarray(self.features, dtype=np.float64)
        if succ.ndim != 3:
            raise ValueError(f"successors must have shape (S, A, B), got shape {succ.shape}")
        if not np.issubdtype(succ.dtype, np.integer):
            raise ValueError(f"successors must be integers, got dtype {succ.dtype}")
        S, A, B = succ.shape
        if S < 1 or A < 1 or B < 1:
            raise ValueError(f"successors must have S, A, B >= 1, got shape {succ.shape}")
        if probs.shape != succ.shape:
            raise ValueError(f"probs has shape {probs.shape} but successors has shape {succ.shape}")
        if not np.all(np.isfinite(probs)):
            s, a, b = _first_bad(~np.isfinite(probs))
            raise ValueError(f"transition probability of state {s}, action {a}, slot {b} is not finite")
        if np.any(probs < 0):
            s, a, b = _first_bad(probs < 0)
            raise ValueError(f"transition probability of state {s}, action {a}, slot {b} is negative ({probs[s, a, b]})")
        bad_idx = (succ < 0) | (succ >= S)
        if np.any(bad_idx):
            s, a, b = _first_bad(bad_idx)
            raise ValueError(f"successor of state {s}, action {a}, slot {b} is {succ[s, a, b]}, outside 0..{S - 1}")
        totals = probs.sum(-1)
        bad_sum = np.abs(totals - 1.0) > _PROB_ATOL
        if np.any(bad_sum):
            s, a = _first_bad(bad_sum)
            raise ValueError(f"transition probabilities of state {s}, action {a} sum to {totals[s, a]:.6g}, not 1")
        probs = probs / totals[..., None]
        if feats.ndim == 2 and feats.shape[0] == S:
            # state-only features phi(s): the same for every action
            feats = np.repeat(feats[:, None, :], A, axis=1)
        if feats.ndim != 3 or feats.shape[:2] != (S, A):
            raise ValueError(f"features must have shape (S, A, D) = ({S}, {A}, D), got {feats.shape}")
        if not np.all(np.isfinite(feats)):
            s, a, d = _first_bad(~np.isfinite(feats))
            raise ValueError(f"feature {d} of state {s}, action {a} is not finite ({feats[s, a, d]})")
        D = feats.shape[2]
        names = tuple(self.feature_names) if len(self.feature_names) else tuple(f"phi{d}" for d in range(D))
        if len(names) != D:
            raise ValueError(f"feature_names has {len(names)} names for {D} features")
        if self.initial is None:
            init = np.full(S, 1.0 / S)
        else:
            init = np.asarray(self.initial, dtype=np.float64)
            if init.shape != (S,):
                raise ValueError(f"initial must have shape ({S},), got {init.shape}")
            if not np.all(np.isfinite(init)) or np.any(init < 0):
                raise ValueError("initial distribution has negative or non-finite entries")
            if abs(init.sum() - 1.0) > _PROB_ATOL:
                raise ValueError(f"initial distribution sums to {init.sum():.6g}, not 1")
        gamma = float(self.discount)
        if not (0.0 <= gamma < 1.0) or not np.isfinite(gamma):
            raise ValueError(f"discount must lie in [0, 1), got {self.discount}")
        sv = self.state_vectors
        if sv is not None:
            sv = np.asarray(sv, dtype=np.float64)
            if sv.ndim == 1:
                sv = sv[:, None]
            if sv.ndim != 2 or sv.shape[0] != S:
                raise ValueError(f"state_vectors must have shape ({S}, M), got {sv.shape}")
            if not np.all(np.isfinite(sv)):
                s, m = _first_bad(~np.isfinite(sv))
                raise ValueError(f"state_vectors[{s}, {m}] is not finite")
        set_frozen(self, successors=succ.astype(np.int32), probs=probs, features=feats, feature_names=names,
                   initial=init, discount=gamma, state_vectors=sv)

    # ------------------------------------------------------------------ sizes
    @property
    def num_states(self) -> int:
        return self.successors.shape[0]

    @property
    def num_actions(self) -> int:
        return self.successors.shape[1]

    @property
    def num_successors(self) -> int:
        return self.successors.shape[2]

    @property
    def num_features(self) -> int:
        return self.features.shape[2]

    # ------------------------------------------------------------ constructors
    @classmethod
    def from_successors(cls, successors, probs, features=None, **kwargs) -> "TabularMDP":
        """Build from sparse successor arrays (S, A, B); features default to one-hot states."""
        successors = np.asarray(successors)
        if features is None:
            features, kwargs = _one_hot_state_features(successors.shape[0], successors.shape[1], kwargs)
        return cls(successors=successors, probs=probs, features=features, **kwargs)

    @classmethod
    def from_dense(cls, transitions, features=None, **kwargs) -> "TabularMDP":
        """Build from a dense transition tensor P[s, a, s'] of shape (S, A, S)."""
        P = np.asarray(transitions, dtype=np.float64)
        if P.ndim != 3 or P.shape[0] != P.shape[2]:
            raise ValueError(f"dense transitions must have shape (S, A, S), got {P.shape}")
        if not np.all(np.isfinite(P)):
            s, a, t = _first_bad(~np.isfinite(P))
            raise ValueError(f"transition probability of state {s}, action {a} to state {t} is not finite")
        if np.any(P < 0):
            s, a, t = _first_bad(P < 0)
            raise ValueError(f"transition probability of state {s}, action {a} to state {t} is negative ({P[s, a, t]})")
        S, A, _ = P.shape
        B = max(1, int((P > 0).sum(-1).max()))
        # the B largest entries of each row, in state order; zero rows are caught by validation
        order = np.argsort(-P, axis=-1, kind="stable")[..., :B]
        succ = np.sort(order, axis=-1)
        probs = np.take_along_axis(P, succ, axis=-1)
        kept = probs.sum(-1)
        lost = np.abs(kept - P.sum(-1)) > 1e-12
        if np.any(lost):  # cannot happen: B covers every nonzero entry
            raise AssertionError("internal error in from_dense")
        succ = np.where(probs > 0, succ, 0)
        if features is None:
            features, kwargs = _one_hot_state_features(S, A, kwargs)
        return cls(successors=succ, probs=probs, features=features, **kwargs)

    @classmethod
    def from_gymnasium(cls, env, features=None, **kwargs) -> "TabularMDP":
        """Build from a gymnasium toy-text environment exposing ``env.unwrapped.P``.

        ``P[s][a]`` is a list of ``(prob, next_state, reward, terminated)``. Terminal next
        states become absorbing (every action returns to them with probability 1). Features:
        an (S, A, D) array; None (the default), one-hot state features as in
        :meth:`from_dense` (a reward weight per state, so every goal can be a skill); or
        ``"env_reward"``, the environment's own reward as the single feature (its expectation
        over next states), so ``theta = [1]`` recovers it.
        """
        base = getattr(env, "unwrapped", env)
        if not hasattr(base, "P"):
            raise ValueError(f"environment {env} has no transition table P (not a toy-text environment)")
        table = base.P
        S = int(base.observation_space.n)
        A = int(base.action_space.n)
        dense = np.zeros((S, A, S))
        reward = np.zeros((S, A))
        terminal = np.zeros(S, dtype=bool)
        for s in range(S):
            for a in range(A):
                for p, s2, r, done in table[s][a]:
                    dense[s, a, s2] += p
                    reward[s, a] += p * r
                    if done:
                        terminal[s2] = True
        for s in np.flatnonzero(terminal):
            dense[s] = 0.0
            dense[s, :, s] = 1.0
            reward[s] = 0.0
        if isinstance(features, str):
            if features != "env_reward":
                raise ValueError(f"features must be an array, None (one-hot states) or 'env_reward', got {features!r}")
            features = reward[..., None]
            kwargs.setdefault("feature_names", ("env_reward",))
        kwargs.setdefault("name", getattr(getattr(env, "spec", None), "id", None) or type(base).__name__)
        init = getattr(base, "initial_state_distrib", None)
        if init is not None and "initial" not in kwargs:
            kwargs["initial"] = np.asarray(init, dtype=np.float64) / np.sum(init)
        return cls.from_dense(dense, features=features, **kwargs)

    # --------------------------------------------------------------- views
    def fingerprint(self) -> str:
        """SHA-256 hex digest of the dynamics, features and discount: what a run or a set of
        demonstrations records to recognise the MDP it belongs to (a domain's next-value
        operator is code and is not part of it)."""
        import hashlib

        h = hashlib.sha256()
        for name in ("successors", "probs", "features", "initial", "state_vectors"):
            value = getattr(self, name, None)
            if value is not None:
                h.update(name.encode())
                h.update(np.ascontiguousarray(value).tobytes())
        h.update(repr((float(self.discount), tuple(self.feature_names))).encode())
        return h.hexdigest()

    def dense_transitions(self) -> np.ndarray:
        """The dense transition tensor P[s, a, s'] (S, A, S); memory S*A*S floats."""
        S, A, _ = self.successors.shape
        P = np.zeros((S, A, S))
        s_idx, a_idx = np.meshgrid(np.arange(S), np.arange(A), indexing="ij")
        np.add.at(P, (s_idx[..., None], a_idx[..., None], self.successors), self.probs)
        return P

    def equivalent_actions(self) -> np.ndarray:
        """Which actions of each state are equivalent: the same next-state distribution and the
        same reward features, hence the same soft Q-value under every reward.

        Returns:
            bool (S, A, A): ``[s, a, b]`` is True when b is equivalent to a in s (a is to itself).
        """
        order = np.argsort(np.where(self.probs > 0, self.successors, -1), axis=-1, kind="stable")
        succ = np.take_along_axis(np.where(self.probs > 0, self.successors, -1), order, axis=-1)
        prob = np.take_along_axis(self.probs, order, axis=-1)
        S, A = self.num_states, self.num_actions
        same = np.zeros((S, A, A), dtype=bool)
        for a in range(A):
            same[:, a, a] = True
            for b in range(a + 1, A):
                eq = (np.all(succ[:, a] == succ[:, b], axis=-1) & np.all(np.abs(prob[:, a] - prob[:, b]) <= 1e-12, -1)
                      & np.all(self.features[:, a] == self.features[:, b], axis=-1))
                same[:, a, b] = same[:, b, a] = eq
        return same

    def reward(self, theta) -> np.ndarray:
        """Reward table r(s, a) = phi(s, a) . theta, shape (S, A) (or (K, S, A) for theta (K, D))."""
        theta = np.asarray(theta, dtype=np.float64)
        if theta.shape[-1] != self.num_features:
            raise ValueError(f"theta has {theta.shape[-1]} entries but the MDP has {self.num_features} features")
        return np.einsum("sad,...d->...sa", self.features, theta)

    def with_features(self, features, feature_names=()) -> "TabularMDP":
        """The same dynamics with other reward features."""
        return TabularMDP(successors=self.successors, probs=self.probs, features=features,
                          feature_names=feature_names, initial=self.initial, discount=self.discount,
                          state_vectors=self.state_vectors, next_value_fn=self.next_value_fn, name=self.name)

    def with_discount(self, discount) -> "TabularMDP":
        return TabularMDP(successors=self.successors, probs=self.probs, features=self.features,
                          feature_names=self.feature_names, initial=self.initial, discount=discount,
                          state_vectors=self.state_vectors, next_value_fn=self.next_value_fn, name=self.name)

    def sample_next(self, rng: np.random.Generator, states, actions) -> np.ndarray:
        """Sample next states for arrays of states and actions (NumPy, vectorised)."""
        states = np.asarray(states)
        actions = np.asarray(actions)
        p = self.probs[states, actions]  # (..., B)
        u = rng.random(states.shape)[..., None]
        idx = (np.cumsum(p, -1) < u).sum(-1)
        idx = np.minimum(idx, self.num_successors - 1)
        return np.take_along_axis(self.successors[states, actions], idx[..., None], -1)[..., 0]

    def __repr__(self):
        names = list(self.feature_names)
        if len(names) > 8:  # a reward weight per state: not a million names
            names = names[:3] + ["...", f"({len(names)} features)", "..."] + names[-2:]
        return (f"TabularMDP(name={self.name!r}, num_states={self.num_states}, num_actions={self.num_actions}, "
                f"num_successors={self.num_successors}, features={names}, discount={self.discount})")


ONE_HOT_MAX_BYTES = 2 ** 30  # the largest dense one-hot feature array made by default (1 GiB)


def _one_hot_state_features(S: int, A: int, kwargs: dict):
    size = 8 * S * A * S  # the (S, A, S) float64 array the MDP holds, and the solvers a copy of it
    if size > ONE_HOT_MAX_BYTES:
        raise ValueError(
            f"one-hot state features (the default without features) for {S} states and {A} actions would be a "
            f"dense ({S}, {A}, {S}) array of {size / 2 ** 30:.1f} GiB, and {S} reward weights per skill (the "
            "sampler's curvature matrices are weights x weights per skill); give features=(S, A, D) or (S, D) of "
            "your own with a few dozen features (e.g. distances to landmarks, cell types, regions)")
    kwargs = dict(kwargs)
    kwargs.setdefault("feature_names", tuple(f"state{s}" for s in range(S)))
    return np.eye(S), kwargs
