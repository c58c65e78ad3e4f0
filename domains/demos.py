"""Demonstrations: ragged (state, action) trajectories with optional true skills, their
``.npz`` files, and the paper's sticky-switching experts that generate them (section IV-A).

A file holds ``states`` and ``actions`` (every trajectory's integers, concatenated),
``lengths`` (per trajectory) and, when known, ``skills`` (the true skill of every step).
"""

from __future__ import annotations

import hashlib
import os
from typing import Optional, Sequence

import numpy as np

from .util.files import atomic_savez
from .util.precision import float64_all

__all__ = ["Demonstrations", "generate_demonstrations"]

_FIELDS = ("state", "action", "skill")


def _as_integer_trajectory(values, i: int, what: str) -> np.ndarray:
    """One trajectory's values as a 1-D int64 array, or a ValueError naming the bad step."""
    arr = np.asarray(values)
    if arr.ndim != 1:
        raise ValueError(f"trajectory {i}: {what}s must be a 1-D sequence, got shape {arr.shape}")
    if arr.dtype.kind in "iu":
        return arr.astype(np.int64)
    if arr.dtype.kind != "f":
        raise ValueError(f"trajectory {i}: {what}s must be integers, got dtype {arr.dtype}")
    bad = ~np.isfinite(arr) | (arr != np.round(arr))
    if np.any(bad):
        t = int(np.argmax(bad))
        raise ValueError(f"trajectory {i}, step {t}: {what} {arr[t]} is not an integer")
    return arr.astype(np.int64)


def _check_range(trajectories, what: str, upper: Optional[int]):
    """ValueError at the first value outside 0..upper-1 (outside 0.. when upper is None)."""
    for i, arr in enumerate(trajectories):
        bad = (arr < 0) if upper is None else ((arr < 0) | (arr >= upper))
        if np.any(bad):
            t = int(np.argmax(bad))
            allowed = "negative" if upper is None else f"outside 0..{upper - 1}"
            raise ValueError(f"trajectory {i}, step {t}: {what} {arr[t]} is {allowed}")


class Demonstrations:
    """Ragged demonstrations: per trajectory, the integer states and actions of every step,
    and optionally the true skill of every step.

    Args:
        states: N sequences of state indices (a trajectory of length T_i has T_i states).
        actions: N sequences of action indices, the same lengths.
        skills: optional N sequences of true skill indices, the same lengths.
        mdp_fingerprint: optional ``TabularMDP.fingerprint()`` of the MDP the demonstrations
            were recorded in (``generate_demonstrations`` records it, files keep it):
            :meth:`validate` then refuses another MDP.

    Values must be non-negative integers (integer-valued floats are accepted); a trajectory
    needs at least 2 steps. Ranges against an MDP are checked by :meth:`validate`.
    Bad input raises ValueError naming the trajectory and step at fault.
    """

    def __init__(self, states: Sequence, actions: Sequence, skills: Optional[Sequence] = None,
                 mdp_fingerprint: Optional[str] = None):
        states, actions = list(states), list(actions)
        skills = None if skills is None else list(skills)
        if len(states) != len(actions):
            raise ValueError(f"{len(states)} state trajectories but {len(actions)} action trajectories")
        if skills is not None and len(skills) != len(states):
            raise ValueError(f"{len(states)} state trajectories but {len(skills)} skill trajectories")
        if len(states) == 0:
            raise ValueError("no trajectories")
        columns = [states, actions] + ([skills] if skills is not None else [])
        converted = [[_as_integer_trajectory(v, i, what) for i, v in enumerate(col)]
                     for what, col in zip(_FIELDS, columns)]
        for i, traj in enumerate(zip(*converted)):
            T = len(traj[0])
            for what, arr in zip(_FIELDS[1:], traj[1:]):
                if len(arr) != T:
                    raise ValueError(f"trajectory {i}: {T} states but {len(arr)} {what}s")
            if T < 2:
                raise ValueError(f"trajectory {i}: {T} step{'s' if T != 1 else ''}; a trajectory needs at least 2")
        for what, col in zip(_FIELDS, converted):
            _check_range(col, what, None)
            for arr in col:
                arr.setflags(write=False)
        self.states = converted[0]
        self.actions = converted[1]
        self.skills = converted[2] if skills is not None else None
        self.mdp_fingerprint = None if mdp_fingerprint is None else str(mdp_fingerprint)

    # ---------------------------------------------------------------- sizes
    @property
    def num_trajectories(self) -> int:
        return len(self.states)

    @property
    def lengths(self) -> np.ndarray:
        """(N,) int64 trajectory lengths."""
        return np.array([len(s) for s in self.states], dtype=np.int64)

    @property
    def num_steps(self) -> int:
        return int(self.lengths.sum())

    def __len__(self) -> int:
        return self.num_trajectories

    def __repr__(self):
        lengths = self.lengths
        return (f"Demonstrations(num_trajectories={self.num_trajectories}, lengths {lengths.min()}..{lengths.max()}, "
                f"skills={'yes' if self.skills is not None else 'no'})")

    # ---------------------------------------------------------------- views
    def _pad(self, trajectories, pad_value) -> np.ndarray:
        lengths = self.lengths
        out = np.full((len(lengths), int(lengths.max())), pad_value, dtype=np.int64)
        for i, arr in enumerate(trajectories):
            out[i, :len(arr)] = arr
        return out

    def padded(self, pad_value: int = 0):
        """Equal-length arrays, padded at the end.

        Returns:
            states: (N, T_max) int64; actions: (N, T_max) int64, ``pad_value`` at padding;
            mask: (N, T_max) bool, True at real steps.
        """
        mask = np.arange(int(self.lengths.max()))[None, :] < self.lengths[:, None]
        return self._pad(self.states, pad_value), self._pad(self.actions, pad_value), mask

    def padded_skills(self, pad_value: int = -1) -> np.ndarray:
        """True skills as an (N, T_max) int64 array, ``pad_value`` at padding."""
        if self.skills is None:
            raise ValueError("these demonstrations carry no true skills")
        return self._pad(self.skills, pad_value)

    # ----------------------------------------------------------- validation
    def validate(self, mdp, check_transitions: bool = False) -> "Demonstrations":
        """Check the states and actions against an MDP; returns self.

        Args:
            mdp: a TabularMDP.
            check_transitions: also require every recorded next state to have positive
                probability under the MDP's dynamics.
        Raises:
            ValueError naming the trajectory, step and value at fault.
        """
        if self.mdp_fingerprint is not None and self.mdp_fingerprint != mdp.fingerprint():
            raise ValueError(f"these demonstrations were recorded in another MDP than {mdp.name!r} (MDP fingerprint "
                             f"{self.mdp_fingerprint[:12]}..., this one {mdp.fingerprint()[:12]}...)")
        _check_range(self.states, "state", mdp.num_states)
        _check_range(self.actions, "action", mdp.num_actions)
        if check_transitions:
            for i, (s, a) in enumerate(zip(self.states, self.actions)):
                succ, probs = mdp.successors[s[:-1], a[:-1]], mdp.probs[s[:-1], a[:-1]]
                possible = np.any((succ == s[1:, None]) & (probs > 0), axis=-1)
                if not np.all(possible):
                    t = int(np.argmin(possible))
                    raise ValueError(f"trajectory {i}, step {t}: state {s[t]} with action {a[t]} cannot lead to "
                                     f"state {s[t + 1]} under the MDP")
        return self

    # ---------------------------------------------------------------- files
    def _arrays(self) -> dict:
        arrays = {"states": np.concatenate(self.states), "actions": np.concatenate(self.actions),
                  "lengths": self.lengths}
        if self.skills is not None:
            arrays["skills"] = np.concatenate(self.skills)
        return {k: v.astype("<i8") for k, v in arrays.items()}

    def save(self, path) -> None:
        """Write an ``.npz`` file at exactly ``path``, atomically (a temporary file, then a rename)."""
        arrays = self._arrays()
        if self.mdp_fingerprint is not None:
            arrays["mdp_fingerprint"] = np.asarray(self.mdp_fingerprint)
        atomic_savez(path, arrays)

    @classmethod
    def load(cls, path) -> "Demonstrations":
        """Read a file written by :meth:`save` (or any ``.npz`` with the same arrays).

        Raises:
            FileNotFoundError: no such file. ValueError naming the file: not an ``.npz`` of
            integer arrays (npbrs never reads pickled data), missing or inconsistent arrays.
        """
        import zipfile

        if not os.path.exists(path):
            raise FileNotFoundError(f"no demonstrations file {path}")
        try:
            with np.load(path, allow_pickle=False) as data:
                if not hasattr(data, "files"):
                    raise ValueError("a single array, not an .npz archive")
                missing = [k for k in ("states", "actions", "lengths") if k not in data.files]
                if missing:
                    raise ValueError(f"{path}: missing array{'s' if len(missing) > 1 else ''} {', '.join(missing)}")
                arrays = {k: np.asarray(data[k]) for k in data.files if k in ("states", "actions", "lengths", "skills")}
                recorded = str(data["mdp_fingerprint"]) if "mdp_fingerprint" in data.files else None
        except (zipfile.BadZipFile, EOFError, OSError, ValueError) as e:
            if str(e).startswith(f"{path}:"):
                raise
            reason = ("its contents are not arrays npbrs reads (pickled or unknown data)"
                      if "pickle" in str(e) else f"{type(e).__name__}: {e}")
            raise ValueError(f"{path}: not a demonstrations file (an .npz with states, actions and lengths); "
                             f"{reason}") from None
        lengths = arrays["lengths"]
        if lengths.ndim != 1 or lengths.dtype.kind not in "iu" or np.any(lengths < 0):
            raise ValueError(f"{path}: lengths must be a 1-D array of non-negative integers")
        total = int(lengths.sum())
        bounds = np.cumsum(lengths)[:-1]
        columns = {}
        for name in ("states", "actions", "skills"):
            if name not in arrays:
                continue
            if arrays[name].shape != (total,):
                raise ValueError(f"{path}: lengths sum to {total} but {name} has shape {arrays[name].shape}")
            columns[name] = np.split(arrays[name], bounds)
        return cls(**columns, mdp_fingerprint=recorded)

    def fingerprint(self) -> str:
        """SHA-256 hex digest of the content (lengths, states, actions, skills)."""
        h = hashlib.sha256()
        for name, arr in sorted(self._arrays().items()):
            h.update(name.encode())
            h.update(np.ascontiguousarray(arr).tobytes())
        return h.hexdigest()

    def same_trajectories(self, other: "Demonstrations") -> bool:
        """Whether ``other`` holds the same trajectories (states and actions, in order), whatever
        either says of the true skills."""
        if self is other:
            return True
        if not np.array_equal(self.lengths, other.lengths):
            return False
        mine, theirs = self._arrays(), other._arrays()
        return all(np.array_equal(mine[k], theirs[k]) for k in ("states", "actions"))

    def __eq__(self, other):
        if not isinstance(other, Demonstrations):
            return NotImplemented
        mine, theirs = self._arrays(), other._arrays()
        return mine.keys() == theirs.keys() and all(np.array_equal(mine[k], theirs[k]) for k in mine)

    __hash__ = None


def generate_demonstrations(domain, num_trajectories: int = 16, length: int = 500, switch_prob: float = 0.02,
                            seed: int = 0, policies=None) -> Demonstrations:
    """Demonstrations by experts that switch skills at random (the paper's section IV-A).

    Each trajectory starts in a state drawn from ``domain.mdp.initial`` with a skill drawn
    uniformly; after every step the skill switches with probability ``switch_prob`` to one of
    the other skills (uniformly); the active skill's expert acts and the next state is drawn
    from the MDP. The true skills are recorded.

    Args:
        domain: a Domain (its ``mdp`` and ``expert_policies()``).
        num_trajectories: N.
        length: steps per trajectory (at least 2).
        switch_prob: probability of switching skill between consecutive steps.
        seed: NumPy seed; the same seed gives the same demonstrations.
        policies: optional experts overriding ``domain.expert_policies()``: (K, S) action
            indices, or (K, S, A) action probabilities (stochastic experts).
    Returns:
        Demonstrations with true skills.
    """
    mdp = domain.mdp
    S, A = mdp.num_states, mdp.num_actions
    if int(num_trajectories) < 1:
        raise ValueError(f"num_trajectories must be at least 1, got {num_trajectories}")
    if int(length) < 2:
        raise ValueError(f"length must be at least 2, got {length}")
    if not (0.0 <= float(switch_prob) <= 1.0):
        raise ValueError(f"switch_prob must lie in [0, 1], got {switch_prob}")
    policies = np.asarray(domain.expert_policies() if policies is None else policies)
    if policies.ndim == 2:
        if policies.shape[1] != S or policies.shape[0] < 1:
            raise ValueError(f"deterministic policies must have shape (K, {S}), got {policies.shape}")
        if policies.dtype.kind not in "iu" or np.any((policies < 0) | (policies >= A)):
            raise ValueError(f"deterministic policies must hold actions in 0..{A - 1}")
    elif policies.ndim == 3:
        if policies.shape[1:] != (S, A) or policies.shape[0] < 1:
            raise ValueError(f"stochastic policies must have shape (K, {S}, {A}), got {policies.shape}")
        if np.any(policies < 0) or np.any(np.abs(policies.sum(-1) - 1.0) > 1e-6):
            raise ValueError("stochastic policies must hold probabilities that sum to 1 over actions")
        cumulative = np.cumsum(policies, axis=-1)
    else:
        raise ValueError(f"policies must have shape (K, S) or (K, S, A), got {policies.shape}")
    K = policies.shape[0]
    N, T = int(num_trajectories), int(length)

    rng = np.random.default_rng(seed)
    states = np.empty((N, T), dtype=np.int64)
    actions = np.empty((N, T), dtype=np.int64)
    skills = np.empty((N, T), dtype=np.int64)
    s = rng.choice(S, size=N, p=mdp.initial)
    k = rng.integers(K, size=N)
    for t in range(T):
        states[:, t], skills[:, t] = s, k
        if policies.ndim == 2:
            a = policies[k, s]
        else:
            a = np.minimum((cumulative[k, s] < rng.random(N)[:, None]).sum(-1), A - 1)
        actions[:, t] = a
        if t + 1 < T:
            s = mdp.sample_next(rng, s, a)
            if K > 1:
                switch = rng.random(N) < switch_prob
                k = np.where(switch, (k + rng.integers(1, K, size=N)) % K, k)
    return Demonstrations(list(states), list(actions), list(skills), mdp_fingerprint=mdp.fingerprint())


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
