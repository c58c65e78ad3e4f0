"""The tabular grid world (:func:`tabular_grid`): an open gridworld with a reward per state and
modes that end at their goals; and the gridworld dynamics it shares with the four rooms."""

from __future__ import annotations

from typing import List

import numpy as np

from ..mdp import TabularMDP
from ..util.precision import float64_all
from .base import World, _ending_transitions, _expert_log_policies, _int, _one_set, _real, _seed, _world

__all__ = ["tabular_grid", "grid_mdp"]

GRID_ACTIONS = ("up", "down", "left", "right", "stay")
_GRID_MOVES = ((-1, 0), (1, 0), (0, -1), (0, 1), (0, 0))


# ------------------------------------------------------------------------------- gridworlds
def _grid_dense(free: np.ndarray, slip: float) -> np.ndarray:
    """(S, 5, S) moves on the free cells of a grid (row-major order); a move into a wall or off
    the grid stays; with probability ``slip`` the move is a uniformly random one instead."""
    H, W = free.shape
    index = -np.ones((H, W), dtype=np.int64)
    cells = np.argwhere(free)
    index[free] = np.arange(len(cells))
    S, A = len(cells), len(_GRID_MOVES)
    P = np.zeros((S, A, S))
    for s, (r, c) in enumerate(cells):
        for b, (dr, dc) in enumerate(_GRID_MOVES):
            r2, c2 = r + dr, c + dc
            target = index[r2, c2] if 0 <= r2 < H and 0 <= c2 < W and free[r2, c2] else s
            for a in range(A):
                P[s, a, target] += (1.0 - slip) * (a == b) + slip / A
    return P


def grid_mdp(size: int = 5, slip: float = 0.0, discount: float = 0.9) -> TabularMDP:
    """An open size x size gridworld: actions up, down, left, right, stay; one-hot state
    features; a uniform initial state. State s is cell (s // size, s % size)."""
    size = _int("size", size, 2)
    slip = _real("slip", slip, 0.0, 1.0)
    discount = _real("discount", discount, 0.0, 1.0, open_high=True)
    free = np.ones((size, size), dtype=bool)
    cells = np.argwhere(free).astype(np.float64)
    return TabularMDP.from_dense(_grid_dense(free, slip), discount=discount, name=f"grid{size}x{size}",
                                 state_vectors=cells)


def _corner_regions(size: int, goal_size: int) -> List[np.ndarray]:
    """Cells (row, col) of goal_size x goal_size blocks in the corners: top-left, bottom-right,
    top-right, bottom-left."""
    lo, hi = range(goal_size), range(size - goal_size, size)
    return [np.array([(r, c) for r in rows for c in cols]) for rows, cols in
            ((lo, lo), (hi, hi), (lo, hi), (hi, lo))]


def _switch_rate(step: np.ndarray, p0: np.ndarray, end: np.ndarray, length: int) -> float:
    """Expected switches per step transition of a length-``length`` trajectory whose skill ends
    with probability end[k, s'] on entering s' and then becomes one of the others uniformly:
    the joint chain over (skill, state) propagated exactly. step (K, S, S): state transitions
    under skill k's policy; p0 (K, S): the first step's joint distribution."""
    K = end.shape[0]
    p, total = p0, 0.0
    for _ in range(length - 1):
        q = np.einsum("ks,kst->kt", p, step)
        moved = q * end
        total += moved.sum()
        p = q - moved + (moved.sum(0, keepdims=True) - moved) / (K - 1)
    return total / (length - 1)


def goal_ends(step: np.ndarray, p0: np.ndarray, goal: np.ndarray, goal_factor: float, switch_rate: float,
              length: int) -> np.ndarray:
    """End probabilities q, ``goal_factor`` q at the goal (capped at 1), with q chosen by
    bisection so that trajectories of ``length`` steps switch at ``switch_rate`` per step
    (:func:`_switch_rate`); a ValueError when no q reaches it.

    Args:
        step: (K, S, S) each mode's state transitions under its policy; p0: (K, S) the first
            (mode, state) distribution; goal: (K, S) bool, where each mode's goal is.
        goal_factor, switch_rate, length: as the worlds take them.
    Returns:
        ((K, S) the end probability of each mode in each state, q).
    """
    def ends(q):
        return np.where(goal, min(1.0, goal_factor * q), q)

    # the rate rises with q: bisect on it (q = 1 switches at every step)
    lo, hi = 0.0, 1.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _switch_rate(step, p0, ends(mid), length) < switch_rate else (lo, mid)
    q = 0.5 * (lo + hi)
    achieved = _switch_rate(step, p0, ends(q), length)
    if abs(achieved - switch_rate) > 1e-3 * switch_rate + 1e-9:
        raise ValueError(f"switch_rate {switch_rate} cannot be reached with goal_factor {goal_factor} "
                         f"(closest: {achieved:.4g})")
    return ends(q), q


def tabular_grid(seed: int = 0, *, size: int = 5, num_modes: int = 2, num_trajectories: int = 200,
                 length: int = 500, num_heldout: int = 50, switch_rate: float = 0.05, goal_factor: float = 10.0,
                 goal_size: int = 2, goal_reward: float = 1.0, inverse_temperature: float = 3.0,
                 slip: float = 0.0, discount: float = 0.9) -> World:
    """A gridworld with tabular state rewards and modes that end at their goals.

    Mode k's reward is ``goal_reward`` on a goal_size x goal_size block in a corner (top-left,
    bottom-right, top-right, bottom-left, in that order) and 0 elsewhere. A trajectory starts in
    a uniformly random cell with a uniformly random mode; on entering a cell, the current mode
    ends with probability q_k(s) = min(1, goal_factor * q) in its own goal block and q elsewhere,
    and the next mode is one of the others, uniformly. q is calibrated so that the expected
    number of switches per step transition of a trajectory of ``length`` steps is
    ``switch_rate`` (``world.params["switch_elsewhere"]`` and ``["switch_at_goal"]``).

    Args:
        seed: the seed; the same seed gives the same world and data.
        size: grid side; num_modes: 2, 3 or 4 modes.
        num_trajectories, length: training demonstrations (all of ``length`` steps).
        num_heldout: held-out trajectories (also of ``length`` steps).
        switch_rate: expected switches per step transition, in (0, 1).
        goal_factor: how much likelier a mode ends in its goal block than elsewhere (>= 1).
        goal_size: side of the goal blocks (at most size // 2, so that they do not overlap).
        goal_reward: the reward of a goal cell; inverse_temperature: the experts' beta.
        slip: probability that a move is a uniformly random one; discount: gamma.
    Returns:
        a :class:`World`.
    """
    rng = _seed(seed)
    size = _int("size", size, 2)
    num_modes = _int("num_modes", num_modes, 2)
    if num_modes > 4:
        raise ValueError(f"num_modes must be 2, 3 or 4 (one per corner), got {num_modes}")
    num_trajectories = _int("num_trajectories", num_trajectories, 1)
    length = _int("length", length, 2)
    num_heldout = _int("num_heldout", num_heldout, 1)
    switch_rate = _real("switch_rate", switch_rate, 0.0, 1.0, open_low=True, open_high=True)
    goal_factor = _real("goal_factor", goal_factor, 1.0)
    goal_size = _int("goal_size", goal_size, 1)
    if goal_size > size // 2:
        raise ValueError(f"goal_size must be at most size // 2 = {size // 2} so that the corner blocks do not "
                         f"overlap, got {goal_size}")
    goal_reward = _real("goal_reward", goal_reward, 0.0, open_low=True)
    beta = _real("inverse_temperature", inverse_temperature, 0.0, open_low=True)
    mdp = grid_mdp(size, slip=slip, discount=discount)
    S, K = mdp.num_states, num_modes
    goal = np.zeros((K, S), dtype=bool)
    for k, cells in enumerate(_corner_regions(size, goal_size)[:K]):
        goal[k, cells[:, 0] * size + cells[:, 1]] = True
    weights = beta * goal_reward * goal.astype(np.float64)
    log_pi = _expert_log_policies(mdp, weights)
    step = np.einsum("ksa,sat->kst", np.exp(log_pi), mdp.dense_transitions())
    p0 = np.full((K, S), 1.0 / (K * S))

    end, q = goal_ends(step, p0, goal, goal_factor, switch_rate, length)
    next_mode = (1.0 - np.eye(K)) / (K - 1)
    parts = _one_set(K, np.full(K, 1.0 / K), _ending_transitions(end, next_mode))
    names = tuple(("top_left", "bottom_right", "top_right", "bottom_left")[:K])
    params = dict(seed=int(seed), size=size, num_modes=K, num_trajectories=num_trajectories, length=length,
                  num_heldout=num_heldout, switch_rate=switch_rate, goal_factor=goal_factor, goal_size=goal_size,
                  goal_reward=goal_reward, inverse_temperature=beta, slip=float(slip), discount=float(discount),
                  switch_elsewhere=q, switch_at_goal=min(1.0, goal_factor * q))
    return _world("tabular_grid", rng, mdp, names, weights, parts, np.full(num_trajectories, length),
                  np.full(num_heldout, length), params,
                  describe_state=lambda s: {"row": int(s) // size, "col": int(s) % size})


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
