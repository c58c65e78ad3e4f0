"""The labyrinth world (:func:`labyrinth`): mice in a binary-tree labyrinth that explore, go to the
water port and go home."""

from __future__ import annotations

import numpy as np

from ..mdp import TabularMDP
from ..util.precision import float64_all
from .base import World, _ending_transitions, _int, _lengths, _one_set, _real, _seed, _world

__all__ = ["labyrinth", "labyrinth_mdp"]

LABYRINTH_ACTIONS = ("left", "right", "back", "stay")


# -------------------------------------------------------------------------------- labyrinth
def labyrinth_mdp(depth: int = 6, discount: float = 0.9) -> TabularMDP:
    """A binary-tree labyrinth: nodes 0 .. 2^(depth+1) - 2 in breadth-first order (node 0 the
    entrance; node i's children 2i + 1 and 2i + 2; 2^depth - 1 junctions and 2^depth end
    nodes); actions left child, right child, back to the parent, stay (a move that does not
    exist, e.g. a child of an end node or the entrance's parent, stays); deterministic; one-hot
    state features; every trajectory starts at the entrance."""
    depth = _int("depth", depth, 1)
    discount = _real("discount", discount, 0.0, 1.0, open_high=True)
    S = 2 ** (depth + 1) - 1
    junctions = 2 ** depth - 1
    nodes = np.arange(S)
    succ = np.empty((S, len(LABYRINTH_ACTIONS), 1), dtype=np.int64)
    succ[:, 0, 0] = np.where(nodes < junctions, 2 * nodes + 1, nodes)
    succ[:, 1, 0] = np.where(nodes < junctions, 2 * nodes + 2, nodes)
    succ[:, 2, 0] = np.where(nodes > 0, (nodes - 1) // 2, nodes)
    succ[:, 3, 0] = nodes
    level = np.floor(np.log2(nodes + 1)).astype(np.int64)
    initial = np.zeros(S)
    initial[0] = 1.0
    return TabularMDP.from_successors(succ, np.ones(succ.shape), discount=discount, initial=initial,
                                      name=f"labyrinth{depth}",
                                      state_vectors=np.stack([level, nodes + 1 - 2 ** level], -1).astype(float))


def labyrinth(seed: int = 0, *, depth: int = 6, num_trajectories: int = 200, min_length: int = 15,
              max_length: int = 25, num_heldout: int = 100, inverse_temperature: float = 4.0,
              explore_scale: float = 1.0, port_end: float = 0.6, home_end: float = 0.6,
              explore_end: float = 0.1, travel_end: float = 0.02, discount: float = 0.9) -> World:
    """Mice in a binary-tree labyrinth: explore, go to the water port, go home.

    Rewards (one per node): "explore" draws a reward per node from Normal(0, explore_scale^2)
    (mild preferences over a near-random walk); "water" is 1 at the water port, an end node
    drawn with the seed; "home" is 1 at the entrance. Every trajectory starts at the entrance,
    with explore, water or home with probabilities 0.6, 0.35, 0.05. The water skill ends with
    probability ``port_end`` on reaching the port and ``travel_end`` elsewhere, home with
    ``home_end`` at the entrance and ``travel_end`` elsewhere, explore with ``explore_end``
    anywhere; after an end: explore -> water 0.6 / home 0.4, water -> home 0.7 / explore 0.3,
    home -> explore 0.7 / water 0.3. Lengths are uniform in min_length..max_length.

    Args:
        seed: the seed; depth: tree depth (6: 63 junctions and 64 end nodes, 127 nodes).
        num_trajectories, min_length, max_length: training demonstrations.
        num_heldout: held-out trajectories (same lengths' distribution).
        inverse_temperature: the experts' beta on the water and home rewards (of size 1).
        explore_scale: sd of the explore skill's node rewards (the inverse temperature does not
            scale them: exploring stays a near-random walk with mild preferences).
        port_end, home_end, explore_end, travel_end: the end probabilities above, in [0, 1].
        discount: gamma.
    Returns:
        a :class:`World`.
    """
    rng = _seed(seed)
    mdp = labyrinth_mdp(depth, discount=discount)
    num_trajectories = _int("num_trajectories", num_trajectories, 1)
    min_length = _int("min_length", min_length, 2)
    max_length = _int("max_length", max_length, min_length)
    num_heldout = _int("num_heldout", num_heldout, 1)
    beta = _real("inverse_temperature", inverse_temperature, 0.0, open_low=True)
    explore_scale = _real("explore_scale", explore_scale, 0.0)
    ends = {n: _real(n, v, 0.0, 1.0) for n, v in
            [("port_end", port_end), ("home_end", home_end), ("explore_end", explore_end), ("travel_end", travel_end)]}
    S = mdp.num_states
    port = int(rng.integers(2 ** depth - 1, S))
    rewards = np.zeros((3, S))
    rewards[0] = explore_scale * rng.standard_normal(S)
    rewards[1, port] = 1.0
    rewards[2, 0] = 1.0
    end = np.full((3, S), ends["travel_end"])
    end[0] = ends["explore_end"]
    end[1, port] = ends["port_end"]
    end[2, 0] = ends["home_end"]
    next_skill = np.array([[0.0, 0.6, 0.4], [0.3, 0.0, 0.7], [0.7, 0.3, 0.0]])
    parts = _one_set(3, np.array([0.6, 0.35, 0.05]), _ending_transitions(end, next_skill))
    params = dict(seed=int(seed), depth=depth, num_trajectories=num_trajectories, min_length=min_length,
                  max_length=max_length, num_heldout=num_heldout, inverse_temperature=beta,
                  explore_scale=explore_scale, discount=float(discount), water_port=port, **ends)
    train = _lengths(rng, num_trajectories, min_length, max_length)
    held = _lengths(rng, num_heldout, min_length, max_length)
    junctions = 2 ** depth - 1
    weights = np.concatenate([rewards[:1], beta * rewards[1:]])  # explore's preferences stay mild
    return _world("labyrinth", rng, mdp, ("explore", "water", "home"), weights, parts, train, held, params,
                  describe_state=lambda s: {"node": int(s), "depth": int(np.log2(int(s) + 1)),
                                            "end_node": int(s) >= junctions})


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
