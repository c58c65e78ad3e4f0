"""A scalable built-in test world: an open L x L gridworld with sparse successors and a handful
of reward features, for measuring the solvers at large S (L = 1000 is S = 10^6 states).

:func:`open_gridworld` builds it with vectorised NumPy (no loop over states), so that
L = 1000 takes a few seconds and about 1 GB at its peak.

Cells and actions. State s is the cell (row, col) = divmod(s, L), row 0 at the top. Actions
(:data:`ACTIONS`): 0 stay, 1 north (row - 1), 2 south (row + 1), 3 east (col + 1), 4 west
(col - 1). A move into the border leaves the agent where it is.

Dynamics (B = 3 successor slots per state and action). A move goes where it is aimed with
probability 1 - slip and to each of the two perpendicular directions with probability slip / 2
(north and south slip east and west; east and west slip north and south), as in FrozenLake.
Staying is certain: its two other slots have probability 0 (and point at state 0, the
:class:`~npbrs.domains.TabularMDP` convention for unused slots).

Features (state features phi(s), the same for every action). ``num_features`` goal cells are
drawn uniformly without replacement from the grid with ``seed``; feature d is the nearness to
goal d, ``1 - manhattan(s, goal_d) / (2 (L - 1))``, which is 1 at the goal and at least 0 (at
the opposite corner of a corner goal). A reward ``phi . theta`` with one positive weight is a
skill that walks to its goal; weights of both signs mix seeking and avoiding. The goals are
``mdp.state_vectors[goal]`` for ``goal`` in :func:`goal_cells`.

Initial state: uniform. State vectors: (row, col) as floats.
"""

from __future__ import annotations

import math

import numpy as np

from .mdp import TabularMDP

__all__ = ["open_gridworld", "goal_cells", "ACTIONS", "MOVES", "MAX_SIDE"]

ACTIONS = ("stay", "north", "south", "east", "west")
MOVES = ((0, 0), (-1, 0), (1, 0), (0, 1), (0, -1))  # (d_row, d_col) per action
# per action, its slip directions (action indices): perpendicular moves; stay has none
_SLIPS = ((0, 0), (3, 4), (3, 4), (1, 2), (1, 2))
MAX_SIDE = 4096  # S = L^2 must fit int32 state indices with room to spare (16.8 million states)


def _check_int(name, value, low, high=None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if value < low or (high is not None and value > high):
        bound = f"at least {low}" if high is None else f"in {low}..{high}"
        raise ValueError(f"{name} must be {bound}, got {value}")
    return int(value)


def _check_real(name, value, low, high, open_high=False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number, got {value!r}")
    value = float(value)
    if not (math.isfinite(value) and low <= value and (value < high if open_high else value <= high)):
        raise ValueError(f"{name} must lie in [{low:g}, {high:g}{')' if open_high else ']'}, got {value!r}")
    return value


def goal_cells(L: int, num_features: int = 4, seed: int = 0) -> np.ndarray:
    """The goal states (num_features,) of :func:`open_gridworld` with these arguments."""
    L = _check_int("L", L, 2, MAX_SIDE)
    num_features = _check_int("num_features", num_features, 1, L * L)
    seed = _check_int("seed", seed, 0)
    return np.random.default_rng(seed).choice(L * L, size=num_features, replace=False)


def open_gridworld(L: int, *, num_features: int = 4, slip: float = 0.1, discount: float = 0.95,
                   seed: int = 0) -> TabularMDP:
    """An open L x L gridworld (S = L^2 states, 5 actions, 3 successor slots) with
    ``num_features`` goal-nearness features; see the module docstring for the dynamics.

    Args:
        L: side of the grid, 2..4096 (S = L^2; L = 1000 is a million states).
        num_features: number of goal cells and features, 1..L^2.
        slip: probability that a move goes sideways instead (half to each side), in [0, 1].
        discount: gamma in [0, 1).
        seed: seeds the goal cells (non-negative integer).
    Raises:
        ValueError naming the argument at fault.
    """
    L = _check_int("L", L, 2, MAX_SIDE)
    num_features = _check_int("num_features", num_features, 1, L * L)
    slip = _check_real("slip", slip, 0.0, 1.0)
    discount = _check_real("discount", discount, 0.0, 1.0, open_high=True)
    seed = _check_int("seed", seed, 0)
    S, A = L * L, len(ACTIONS)
    row, col = np.divmod(np.arange(S, dtype=np.int32), np.int32(L))

    def target(a):  # the cell a move in direction a reaches (int32, (S,))
        dr, dc = MOVES[a]
        return np.clip(row + dr, 0, L - 1) * np.int32(L) + np.clip(col + dc, 0, L - 1)

    successors = np.zeros((S, A, 3), dtype=np.int32)
    probs = np.zeros((S, A, 3))
    successors[:, 0, 0] = np.arange(S, dtype=np.int32)
    probs[:, 0, 0] = 1.0
    for a in range(1, A):
        successors[:, a, 0] = target(a)
        probs[:, a, 0] = 1.0 - slip
        for b, side in enumerate(_SLIPS[a], start=1):
            successors[:, a, b] = target(side)
            probs[:, a, b] = 0.5 * slip

    goals = goal_cells(L, num_features, seed)
    grow, gcol = np.divmod(goals, L)
    features = np.empty((S, num_features))
    for d in range(num_features):
        dist = np.abs(row - grow[d]) + np.abs(col - gcol[d])
        features[:, d] = 1.0 - dist / (2.0 * (L - 1))
    names = tuple(f"near_goal{d}" for d in range(num_features))
    cells = np.stack([row, col], axis=1).astype(np.float64)
    return TabularMDP(successors=successors, probs=probs, features=features, feature_names=names, discount=discount,
                      state_vectors=cells, name=f"open_grid{L}x{L}")
