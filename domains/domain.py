"""A domain: a tabular MDP, its named reward skills, and the gymnasium environment built on it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Dict, Optional

import numpy as np

from .mdp import TabularMDP

__all__ = ["Domain"]


@dataclass(frozen=True, eq=False)
class Domain:
    """A world with known skills.

    Attributes:
        name: short name ("highway", "quadcopter", ...).
        mdp: the TabularMDP.
        skill_names: the names of the true skills, e.g. ("A", "B", "C").
        skill_weights: (K, D) reward weights of the skills over ``mdp.features``.
        env_id: the registered gymnasium id (e.g. "npbrs/Highway-v0"), or None.
        env_kwargs: keyword arguments that ``gymnasium.make(env_id, ...)`` needs.
        describe_state: optional function state index -> dict of named state variables.
    """

    name: str
    mdp: TabularMDP
    skill_names: tuple
    skill_weights: np.ndarray
    env_id: Optional[str] = None
    env_kwargs: Dict = field(default_factory=dict)
    describe_state: Optional[Callable[[int], dict]] = field(default=None, repr=False)

    def __post_init__(self):
        w = np.asarray(self.skill_weights, dtype=np.float64)
        if w.ndim != 2 or w.shape != (len(self.skill_names), self.mdp.num_features):
            raise ValueError(f"skill_weights must have shape ({len(self.skill_names)}, {self.mdp.num_features}), "
                             f"got {w.shape}")
        w.setflags(write=False)
        object.__setattr__(self, "skill_weights", w)
        object.__setattr__(self, "skill_names", tuple(self.skill_names))

    @property
    def num_skills(self) -> int:
        return len(self.skill_names)

    def rewards(self) -> np.ndarray:
        """Reward tables of the skills, (K, S, A)."""
        return self.mdp.reward(self.skill_weights)

    def expert_q(self) -> np.ndarray:
        """Optimal (hard) Q-functions of the skills, (K, S, A), by value iteration."""
        from .solvers import value_iteration

        return np.asarray(value_iteration(self.mdp, self.rewards()).Q)

    def expert_policies(self) -> np.ndarray:
        """Deterministic optimal policies of the skills, (K, S) action indices."""
        from .solvers import greedy_policy

        return greedy_policy(self.expert_q())

    def make_env(self, **kwargs):
        """A gymnasium environment of this domain (``gymnasium.make(env_id, **kwargs)``)."""
        if self.env_id is None:
            raise ValueError(f"domain {self.name!r} has no gymnasium environment")
        import gymnasium as gym

        return gym.make(self.env_id, **{**self.env_kwargs, **kwargs})
