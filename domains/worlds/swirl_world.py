"""The state-pair gridworld (:func:`swirl_grid`): rewards on (previous cell, cell) pairs and mode
ends that depend on the cell, after the switching-IRL (SWIRL) gridworld benchmark; and the
pair-state MDP it lives in (:func:`pair_grid_mdp`)."""

from __future__ import annotations

from typing import Tuple

import numpy as np

from ..demos import Demonstrations
from ..mdp import TabularMDP
from ..util.precision import float64_all
from .base import World, _ending_transitions, _expert_log_policies, _int, _one_set, _real, _seed, _world
from .grid_world import _grid_dense, goal_ends, grid_mdp

__all__ = ["swirl_grid", "pair_grid_mdp", "pair_cells", "cell_view"]


# ------------------------------------------------------------------------- the pair-state MDP
def _pairs(cell_P: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """The pair-states of a cell MDP P (C, A, C): every (previous cell, cell) with the cell
    reachable from the previous one in one step, or equal to it (a trajectory's first state),
    in (previous, cell) row-major order; and the (C, C) index of each pair (-1: not a state)."""
    C = cell_P.shape[0]
    reachable = cell_P.sum(1) > 0
    reachable[np.arange(C), np.arange(C)] = True
    pairs = np.argwhere(reachable)
    index = -np.ones((C, C), dtype=np.int64)
    index[pairs[:, 0], pairs[:, 1]] = np.arange(len(pairs))
    return pairs, index


def pair_grid_mdp(size: int = 5, slip: float = 0.0, discount: float = 0.9) -> TabularMDP:
    """An open size x size gridworld whose states are (previous cell, cell) pairs: a reward per
    state is a reward per pair, a move's reward. Actions up, down, left, right, stay on the
    cell (a move off the grid stays; with probability ``slip`` the move is a uniformly random
    one instead); from pair (p, c) the agent moves to (c, c'). The states are the pairs whose
    cell is the previous cell or one of its neighbours (5 x 5: 105 of them), in (previous,
    cell) row-major order of the cells' row-major indices; ``mdp.state_vectors`` holds each
    state's (previous row, previous column, row, column). A trajectory starts in a pair (c, c)
    with the cell uniform (no move yet). One-hot state features."""
    size = _int("size", size, 2)
    slip = _real("slip", slip, 0.0, 1.0)
    discount = _real("discount", discount, 0.0, 1.0, open_high=True)
    cell_P = _grid_dense(np.ones((size, size), dtype=bool), slip)
    pairs, index = _pairs(cell_P)
    S, A = len(pairs), cell_P.shape[1]
    P = np.zeros((S, A, S))
    for s, (_, c) in enumerate(pairs):
        nxt = np.flatnonzero(index[c] >= 0)  # (p, c) -a-> (c, c') with P(c' | c, a)
        P[s][:, index[c, nxt]] = cell_P[c][:, nxt]
    initial = np.zeros(S)
    initial[index[np.arange(size * size), np.arange(size * size)]] = 1.0 / (size * size)
    rows, cols = np.divmod(pairs, size)
    vectors = np.stack([rows[:, 0], cols[:, 0], rows[:, 1], cols[:, 1]], -1).astype(np.float64)
    return TabularMDP.from_dense(P, discount=discount, initial=initial, name=f"pairgrid{size}x{size}",
                                 state_vectors=vectors)


def pair_cells(mdp: TabularMDP, size: int) -> np.ndarray:
    """(S, 2) the (previous cell, cell) of each state of :func:`pair_grid_mdp`, cells in
    row-major order (cell = row * size + column)."""
    v = mdp.state_vectors.astype(np.int64)
    return np.stack([v[:, 0] * size + v[:, 1], v[:, 2] * size + v[:, 3]], -1)


def cell_view(world: World):
    """(mdp, demos, heldout): ``world``'s demonstrations (from :func:`swirl_grid`) on the cells
    alone, the plain gridworld :func:`~npbrs.domains.worlds.grid_mdp` with its one-hot cell
    features (a reward per cell), as data recorded as cells would be fitted without features of
    pairs; the actions and true skills are the same."""
    size = int(world.params["size"])
    cells = pair_cells(world.mdp, size)[:, 1]
    mdp = grid_mdp(size, slip=world.params["slip"], discount=world.params["discount"])

    def view(d):
        return Demonstrations([cells[s] for s in d.states], list(d.actions), list(d.skills),
                              mdp_fingerprint=mdp.fingerprint())

    return mdp, view(world.demos), view(world.heldout)


# ------------------------------------------------------------------------------- the world
def swirl_grid(seed: int = 0, *, size: int = 5, num_trajectories: int = 200, length: int = 500,
               num_heldout: int = 50, switch_rate: float = 0.05, goal_factor: float = 10.0,
               goal_reward: float = 1.0, pair_scale: float = 0.25, inverse_temperature: float = 3.0,
               slip: float = 0.0, discount: float = 0.9) -> World:
    """Two modes, water and home, with rewards on (previous cell, cell) pairs and ends that
    depend on the cell: the kind of SWIRL's gridworld benchmark.

    The MDP is :func:`pair_grid_mdp`'s: the observed trajectory is a walk on the cells, and
    its states are the (previous cell, cell) pairs, so that a reward on pairs is a weight per
    state (one-hot state features: the like-for-like features for rewards on pairs). Mode
    "water" seeks the top-left cell, mode "home" the bottom-right one: mode k's reward of pair
    (p, c) is ``goal_reward`` when c is its goal cell plus ``pair_scale`` times a standard
    normal draw of its own per pair (drawn with the seed: each mode's own preferences for
    particular moves, which no reward on the cell alone can express). A trajectory starts in a
    uniformly random cell (the pair (c, c)) with a uniformly random mode; on entering a cell the
    current mode ends with probability q_k(c) = min(1, goal_factor * q) at its own goal cell and
    q elsewhere, and the other mode follows. q is calibrated so that the expected number of
    switches per step transition of a trajectory of ``length`` steps is ``switch_rate``
    (``world.params["switch_elsewhere"]`` and ``["switch_at_goal"]``; 0.05: about 25 switches
    in 500 steps).

    Args:
        seed: the seed; the same seed gives the same world and data.
        size: grid side.
        num_trajectories, length: training demonstrations (all of ``length`` steps).
        num_heldout: held-out trajectories (also of ``length`` steps).
        switch_rate: expected switches per step transition, in (0, 1).
        goal_factor: how much likelier a mode ends at its goal cell than elsewhere (>= 1).
        goal_reward: the reward of entering or staying at the goal cell.
        pair_scale: the standard deviation of the modes' rewards per pair (>= 0; 0: rewards on
            the cell alone).
        inverse_temperature: the experts' beta (on both reward terms).
        slip: probability that a move is a uniformly random one; discount: gamma.
    Returns:
        a :class:`World` whose demonstrations' states are the pair-states; the cells are
        ``mdp.state_vectors[:, 2:]`` (row, column) of them (the previous cell's in ``[:, :2]``);
        :func:`cell_view` gives the same data on the cells alone (a reward per cell: features
        that cannot express the truth's rewards on pairs).
    """
    rng = _seed(seed)
    size = _int("size", size, 2)
    num_trajectories = _int("num_trajectories", num_trajectories, 1)
    length = _int("length", length, 2)
    num_heldout = _int("num_heldout", num_heldout, 1)
    switch_rate = _real("switch_rate", switch_rate, 0.0, 1.0, open_low=True, open_high=True)
    goal_factor = _real("goal_factor", goal_factor, 1.0)
    goal_reward = _real("goal_reward", goal_reward, 0.0, open_low=True)
    pair_scale = _real("pair_scale", pair_scale, 0.0)
    beta = _real("inverse_temperature", inverse_temperature, 0.0, open_low=True)
    mdp = pair_grid_mdp(size, slip=slip, discount=discount)
    S, K = mdp.num_states, 2
    cell = pair_cells(mdp, size)[:, 1]
    goals = np.array([0, size * size - 1])  # water: top-left; home: bottom-right
    at_goal = cell[None, :] == goals[:, None]  # (K, S): the pairs that enter or stay at mode k's goal
    rewards = goal_reward * at_goal + pair_scale * rng.standard_normal((K, S))
    weights = beta * rewards
    log_pi = _expert_log_policies(mdp, weights)
    step = np.einsum("ksa,sat->kst", np.exp(log_pi), mdp.dense_transitions())
    p0 = np.broadcast_to(mdp.initial / K, (K, S))

    end, q = goal_ends(step, p0, at_goal, goal_factor, switch_rate, length)
    other = 1.0 - np.eye(K)
    parts = _one_set(K, np.full(K, 1.0 / K), _ending_transitions(end, other))
    params = dict(seed=int(seed), size=size, num_trajectories=num_trajectories, length=length,
                  num_heldout=num_heldout, switch_rate=switch_rate, goal_factor=goal_factor, goal_reward=goal_reward,
                  pair_scale=pair_scale, inverse_temperature=beta, slip=float(slip), discount=float(discount),
                  switch_elsewhere=q, switch_at_goal=min(1.0, goal_factor * q))
    vectors = mdp.state_vectors.astype(np.int64)
    return _world("swirl_grid", rng, mdp, ("water", "home"), weights, parts, np.full(num_trajectories, length),
                  np.full(num_heldout, length), params,
                  describe_state=lambda s: {"prev_row": int(vectors[s, 0]), "prev_col": int(vectors[s, 1]),
                                            "row": int(vectors[s, 2]), "col": int(vectors[s, 3])})


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
