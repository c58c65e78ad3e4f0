"""The four-room world (:func:`rooms`): goal-seeking skills, each trajectory with its own few of
them."""

from __future__ import annotations

import math
from itertools import combinations
from typing import Sequence

import numpy as np

from ..mdp import TabularMDP
from ..util.precision import float64_all
from .base import World, _int, _lengths, _real, _seed, _world
from .grid_world import _grid_dense

__all__ = ["rooms", "rooms_mdp"]


# ------------------------------------------------------------------------------------ rooms
def _rooms_free(size: int) -> np.ndarray:
    """Free cells of a four-room grid: a wall row and column through the middle, each wall
    with a doorway on either side of the crossing."""
    free = np.ones((size, size), dtype=bool)
    mid = size // 2
    free[mid, :] = False
    free[:, mid] = False
    for d in (mid // 2, mid + 1 + (size - mid - 1) // 2):
        free[mid, d] = True  # doorways in the horizontal wall
        free[d, mid] = True  # and in the vertical one
    return free


def rooms_mdp(size: int = 11, slip: float = 0.0, discount: float = 0.9) -> TabularMDP:
    """A four-room gridworld on a size x size grid (size 11: 104 free cells, as in Sutton, Precup
    and Singh's): actions up, down, left, right, stay; only free cells are states (row-major
    order, ``mdp.state_vectors`` their (row, col)); one-hot state features; a uniform initial
    state."""
    size = _int("size", size, 5)
    slip = _real("slip", slip, 0.0, 1.0)
    discount = _real("discount", discount, 0.0, 1.0, open_high=True)
    free = _rooms_free(size)
    return TabularMDP.from_dense(_grid_dense(free, slip), discount=discount, name=f"rooms{size}",
                                 state_vectors=np.argwhere(free).astype(np.float64))


def rooms(seed: int = 0, *, size: int = 11, num_skills: int = 5, num_trajectories: int = 60,
          min_length: int = 60, max_length: int = 140, num_heldout: int = 20,
          skills_per_trajectory: Sequence[int] = (2, 3), switch_prob: float = 0.04,
          inverse_temperature: float = 5.0, slip: float = 0.0, discount: float = 0.9) -> World:
    """The four-room kind: goal-seeking skills, each trajectory with its own few of them.

    Skill k's reward is 1 at its goal cell: the four outer corners, then the doorways (top,
    left, right, bottom), in that order. A trajectory draws how many skills it uses uniformly
    from ``skills_per_trajectory`` and then which, uniformly; it starts in a uniformly random
    cell with one of them, uniformly; at every step its skill switches with probability
    ``switch_prob`` to another of its own, uniformly. Lengths are uniform in
    min_length..max_length.

    Args:
        seed: the seed; size: grid side (at least 5); num_skills: 2..8.
        num_trajectories, min_length, max_length: training demonstrations.
        num_heldout: held-out trajectories.
        skills_per_trajectory: the possible sizes of a trajectory's skill set (each 1..num_skills).
        switch_prob: per-step switching probability, in [0, 1].
        inverse_temperature: the experts' beta; slip: random-move probability; discount: gamma.
    Returns:
        a :class:`World`.
    """
    rng = _seed(seed)
    mdp = rooms_mdp(size, slip=slip, discount=discount)
    num_skills = _int("num_skills", num_skills, 2)
    if num_skills > 8:
        raise ValueError(f"num_skills must be at most 8 (four corners and four doorways), got {num_skills}")
    num_trajectories = _int("num_trajectories", num_trajectories, 1)
    min_length = _int("min_length", min_length, 2)
    max_length = _int("max_length", max_length, min_length)
    num_heldout = _int("num_heldout", num_heldout, 1)
    try:
        sizes = sorted({int(n) for n in skills_per_trajectory})
    except (TypeError, ValueError):
        raise ValueError(f"skills_per_trajectory must be a sequence of integers, got {skills_per_trajectory!r}") \
            from None
    if not sizes or sizes[0] < 1 or sizes[-1] > num_skills:
        raise ValueError(f"skills_per_trajectory must hold sizes in 1..{num_skills}, got {skills_per_trajectory!r}")
    switch_prob = _real("switch_prob", switch_prob, 0.0, 1.0)
    beta = _real("inverse_temperature", inverse_temperature, 0.0, open_low=True)
    free = _rooms_free(size)
    index = -np.ones(free.shape, dtype=np.int64)
    index[free] = np.arange(free.sum())
    mid, last = size // 2, size - 1
    doors = (mid // 2, mid + 1 + (size - mid - 1) // 2)
    goals = [(0, 0), (0, last), (last, 0), (last, last), (doors[0], mid), (mid, doors[0]), (mid, doors[1]),
             (doors[1], mid)][:num_skills]
    names = ("top_left", "top_right", "bottom_left", "bottom_right", "top_door", "left_door", "right_door",
             "bottom_door")[:num_skills]
    K, S = num_skills, mdp.num_states
    weights = np.zeros((K, S))
    for k, (r, c) in enumerate(goals):
        weights[k, index[r, c]] = beta
    sets = [c for n in sizes for c in combinations(range(K), n)]
    set_probs = np.array([1.0 / (len(sizes) * math.comb(K, len(c))) for c in sets])
    member = np.zeros((len(sets), K), dtype=bool)
    for m, c in enumerate(sets):
        member[m, list(c)] = True
    n_in = member.sum(-1, keepdims=True)
    initial = member / n_in
    others = np.where(n_in[:, :, None] > 1, member[:, None, :] / np.maximum(n_in[:, :, None] - 1, 1), 0.0)
    others = others * (1.0 - np.eye(K))[None]  # (M, K, K): uniform over the set's other skills
    stay = np.where(n_in[:, :, None] > 1, 1.0 - switch_prob, 1.0)
    trans = stay * np.eye(K)[None] + (1.0 - stay) * others
    parts = {"skill_sets": member, "skill_set_probs": set_probs, "initial_skill": initial,
             "transitions": trans[:, None]}
    params = dict(seed=int(seed), size=size, num_skills=K, num_trajectories=num_trajectories,
                  min_length=min_length, max_length=max_length, num_heldout=num_heldout,
                  skills_per_trajectory=tuple(sizes), switch_prob=switch_prob, inverse_temperature=beta,
                  slip=float(slip), discount=float(discount), goals=goals)
    train = _lengths(rng, num_trajectories, min_length, max_length)
    held = _lengths(rng, num_heldout, min_length, max_length)
    cells = np.argwhere(free)
    return _world("rooms", rng, mdp, names, weights, parts, train, held, params,
                  describe_state=lambda s: {"row": int(cells[s][0]), "col": int(cells[s][1])})


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
