"""The quadcopter gate domain (paper section IV-C) as a tabular MDP and a gymnasium environment.

A quadcopter flies down a corridor cut into 3 x 3 cross-sections ("slices"). Cells are numbered
``row * 3 + col`` with row 0 at the top (the ceiling) and column 0 on the left. Every step the
copter moves forward into the next slice and, by its action, one cell up (0), down (1), left (2)
or right (3) within the slice; a move into a wall leaves it where it is. Each slice holds a hoop
in one of six configurations, drawn uniformly and independently:

== ============ ============= =====================================
id name         cells inside  picture (# = inside the hoop)
== ============ ============= =====================================
0  top          0 1 2         ``### / ... / ...``  (under the ceiling)
1  bottom       6 7 8         ``... / ... / ###``  (on the ground)
2  left         0 3 6         ``#.. / #.. / #..``
3  right        2 5 8         ``..# / ..# / ..#``
4  centre       4             ``... / .#. / ...``
5  low corner   4 5 7 8       ``... / .## / .##``  (a 2 x 2 square)
== ============ ============= =====================================

The hoops sit in different places so that skills need different routes: the top and bottom
rows hold a full-width hoop once each (the row-keeping skills B and C must then leave their row
for one slice), the side columns cut through both of those rows at one end, the centre can
only be hit from the middle, and the low corner covers half of the bottom row.

State: the copter's cell and the configurations of the next four slices ``(pos, h1, h2, h3,
h4)``, ``9 * 6**4 = 11664`` states, index ``(((pos * 6 + h1) * 6 + h2) * 6 + h3) * 6 + h4``.
On a step with action a the copter moves to ``pos' = move(pos, a)`` inside slice h1; it flies
*through a hoop* when pos' is inside hoop h1. The next state is ``(pos', h2, h3, h4, h_new)``
with ``h_new`` uniform over the six configurations (6 successors).

Reward features phi(s, a), deterministic: ``through_hoop``, ``top_row`` and ``bottom_row`` of
pos'. Skills (paper): A through hoops (+500); B top row (+10), through a hoop (-500); C bottom
row (+10), through a hoop (-500). The copter starts in the centre cell with four random slices
ahead. ``state_vectors`` (for the autoregressive baseline) are (row, col) of the copter and the
(row, col) centre of each of the four hoops ahead: 10 numbers.
"""

from __future__ import annotations

from functools import lru_cache

import gymnasium as gym
import numpy as np

from .domain import Domain
from .highway import SkillEnv
from .mdp import TabularMDP
from .util.precision import float64_all

__all__ = ["quadcopter", "QuadcopterEnv", "encode", "decode", "sample_step", "render_quadcopter", "HOOPS",
           "HOOP_NAMES", "FEATURE_NAMES", "SKILL_WEIGHTS", "ENV_ID", "WORLDS", "world_parameters"]

ENV_ID = "npbrs/Quadcopter-v0"
SIDE = 3
NUM_CELLS = SIDE * SIDE
NUM_HOOPS = 6
LOOKAHEAD = 4
NUM_STATES = NUM_CELLS * NUM_HOOPS ** LOOKAHEAD
NUM_ACTIONS = 4
UP, DOWN, LEFT, RIGHT = 0, 1, 2, 3
ACTION_NAMES = ("up", "down", "left", "right")

HOOP_NAMES = ("top", "bottom", "left", "right", "centre", "low corner")
HOOP_CELLS = ((0, 1, 2), (6, 7, 8), (0, 3, 6), (2, 5, 8), (4,), (4, 5, 7, 8))
# HOOPS[h, cell]: whether the cell is inside hoop configuration h, (6, 9)
HOOPS = np.zeros((NUM_HOOPS, NUM_CELLS), dtype=bool)
for _h, _cells in enumerate(HOOP_CELLS):
    HOOPS[_h, list(_cells)] = True
HOOPS.setflags(write=False)

#: Named worlds: the paper's and changed ones with the same features (other hoop frequencies,
#: wind), for re-solving inferred rewards in a world that has changed:
#: ``quadcopter(world="windy")``, ``gymnasium.make("npbrs/Quadcopter-v0", world="windy")``.
#: ``hoop_probs``: the distribution of a new slice's hoop (in HOOP_NAMES order; uniform in the
#: paper's world); ``wind``: the probability that a step's move is blown away and the copter
#: stays in its cell (it still enters the next slice there).
WORLDS = {
    "paper": {},
    # hoops mostly across the top and bottom rows
    "row_hoops": {"hoop_probs": (0.30, 0.30, 0.10, 0.10, 0.10, 0.10)},
    # a quarter of the moves fail
    "windy": {"wind": 0.25},
    # row hoops and 40% of the moves fail
    "stormy": {"hoop_probs": (0.30, 0.30, 0.10, 0.10, 0.10, 0.10), "wind": 0.4},
}

FEATURE_NAMES = ("through_hoop", "top_row", "bottom_row")
SKILL_NAMES = ("A", "B", "C")
SKILL_WEIGHTS = np.array([
    [500.0, 0.0, 0.0],    # A: fly through as many hoops as possible
    [-500.0, 10.0, 0.0],  # B: fly under the ceiling, avoid hoops
    [-500.0, 0.0, 10.0],  # C: fly near the ground, avoid hoops
])


def _move(cell: int, action: int) -> int:
    row, col = divmod(cell, SIDE)
    dr, dc = ((-1, 0), (1, 0), (0, -1), (0, 1))[action]
    return min(max(row + dr, 0), SIDE - 1) * SIDE + min(max(col + dc, 0), SIDE - 1)


# new cell after each action, (9, 4)
MOVES = np.array([[_move(c, a) for a in range(NUM_ACTIONS)] for c in range(NUM_CELLS)])


def encode(pos, h1, h2, h3, h4):
    """State index of (pos, h1, h2, h3, h4); works elementwise on arrays."""
    return (((np.asarray(pos) * NUM_HOOPS + h1) * NUM_HOOPS + h2) * NUM_HOOPS + h3) * NUM_HOOPS + h4


def decode(state):
    """(pos, h1, h2, h3, h4) of a state index (elementwise on arrays)."""
    state = np.asarray(state)
    parts = []
    for _ in range(LOOKAHEAD):
        parts.append(state % NUM_HOOPS)
        state = state // NUM_HOOPS
    return (state,) + tuple(reversed(parts))


def world_parameters(world: str = "paper", hoop_probs=None, wind=None) -> dict:
    """The dynamics of a named world (:data:`WORLDS`) with explicit ones on top:
    {"hoop_probs": (6,) tuple, "wind": float}, checked."""
    if world not in WORLDS:
        raise ValueError(f"unknown quadcopter world {world!r}; known worlds: {', '.join(WORLDS)}")
    params = {"hoop_probs": (1.0 / NUM_HOOPS,) * NUM_HOOPS, "wind": 0.0, **WORLDS[world]}
    if hoop_probs is not None:
        params["hoop_probs"] = hoop_probs
    if wind is not None:
        params["wind"] = wind
    hp = np.asarray(params["hoop_probs"], dtype=np.float64)
    if hp.shape != (NUM_HOOPS,) or np.any(hp < 0) or not np.isclose(hp.sum(), 1.0, atol=1e-9):
        raise ValueError(f"hoop_probs must be {NUM_HOOPS} probabilities summing to one (hoops {HOOP_NAMES}), "
                         f"got {params['hoop_probs']!r}")
    w = float(params["wind"])
    if not 0 <= w < 1:
        raise ValueError(f"wind must lie in [0, 1), got {params['wind']!r}")
    return {"hoop_probs": tuple(float(x) for x in hp / hp.sum()), "wind": w}


def _cell_features(h1, new) -> np.ndarray:
    return np.stack([HOOPS[h1, new], new // SIDE == 0, new // SIDE == SIDE - 1], -1).astype(np.float64)


def transition_features(states, actions, wind: float = 0.0) -> np.ndarray:
    """Expected features of the steps (states, actions), (..., 3): through_hoop, top_row,
    bottom_row of the new cell (the moved one, or with probability ``wind`` the same one)."""
    pos, h1 = decode(states)[:2]
    moved = _cell_features(h1, MOVES[pos, np.asarray(actions)])
    if wind == 0:
        return moved
    return (1.0 - wind) * moved + wind * _cell_features(h1, np.broadcast_to(pos, np.shape(moved)[:-1]))


def sample_step(rng: np.random.Generator, states, actions, hoop_probs=None, wind: float = 0.0):
    """The environment's dynamics, vectorised: next states and the steps' features.

    Args:
        rng: NumPy generator.
        states: int array (n,); actions: int array (n,).
        hoop_probs, wind: the world's (see :data:`WORLDS`; uniform hoops, no wind by default).
    Returns:
        next_states (n,) and features (n, 3) of the steps.
    """
    pos, h1, h2, h3, h4 = decode(states)
    actions = np.asarray(actions)
    new = MOVES[pos, actions]
    if wind > 0:
        new = np.where(rng.random(np.shape(pos)) < wind, pos, new)
    if hoop_probs is None or np.allclose(hoop_probs, 1.0 / NUM_HOOPS):
        new_slice = rng.integers(NUM_HOOPS, size=np.shape(pos))
    else:
        new_slice = rng.choice(NUM_HOOPS, size=np.shape(pos), p=np.asarray(hoop_probs))
    nxt = encode(new, h2, h3, h4, new_slice)
    return nxt, _cell_features(h1, new)


def make_next_value_fn(hoop_probs=None, wind: float = 0.0):
    """E[V(s') | s, a] for V (..., S) -> (..., S, A), factored.

    The slices ahead shift by one and the new one is drawn from ``hoop_probs`` (uniform by
    default), so the expectation is a weighted sum over the last hoop axis of V (..., 9, 6, 6,
    6, 6), then a gather of the moved cell (mixed with the unmoved one at rate ``wind``); it
    does not depend on the slice being entered (h1), which is broadcast.
    """
    import jax.numpy as jnp

    # NumPy constants (float64 whatever JAX's setting when the domain is built)
    moves = np.asarray(MOVES)
    stay = np.broadcast_to(np.arange(NUM_CELLS)[:, None], MOVES.shape)
    hp = None if hoop_probs is None else np.asarray(hoop_probs, np.float64)

    def next_value(V):
        batch = V.shape[:-1]
        V = V.reshape(batch + (NUM_CELLS,) + (NUM_HOOPS,) * LOOKAHEAD)
        M = jnp.mean(V, axis=-1) if hp is None else jnp.tensordot(V, hp, axes=([-1], [0]))  # (..., pos', h2, h3, h4)
        G = jnp.moveaxis(M[..., moves, :, :, :], -4, -1)  # (..., pos, h2, h3, h4, A)
        if wind > 0:
            G = (1.0 - wind) * G + wind * jnp.moveaxis(M[..., stay, :, :, :], -4, -1)
        G = jnp.broadcast_to(G[..., :, None, :, :, :, :],
                             batch + (NUM_CELLS,) + (NUM_HOOPS,) * LOOKAHEAD + (NUM_ACTIONS,))
        return G.reshape(batch + (NUM_STATES, NUM_ACTIONS))

    return next_value


def _state_vectors() -> np.ndarray:
    pos, *hoops = decode(np.arange(NUM_STATES))
    rows, cols = np.divmod(np.arange(NUM_CELLS), SIDE)
    centre = np.stack([(HOOPS * rows).sum(1) / HOOPS.sum(1), (HOOPS * cols).sum(1) / HOOPS.sum(1)], -1)  # (6, 2)
    return np.concatenate([np.stack([pos // SIDE, pos % SIDE], -1)] + [centre[h] for h in hoops], -1)


@lru_cache(maxsize=8)
def _build_mdp(discount: float, hoop_probs=(1.0 / NUM_HOOPS,) * NUM_HOOPS, wind: float = 0.0) -> TabularMDP:
    states = np.arange(NUM_STATES)
    pos, h1, h2, h3, h4 = decode(states)
    new = MOVES[pos]  # (S, A)
    hp = np.asarray(hoop_probs, dtype=np.float64)

    def successors(cells):
        return encode(cells[:, :, None], h2[:, None, None], h3[:, None, None], h4[:, None, None],
                      np.arange(NUM_HOOPS)[None, None, :])  # (S, A, 6)

    succ = successors(new)
    probs = np.broadcast_to(hp, succ.shape).copy()
    if wind > 0:  # blown: the copter stays in its cell
        succ = np.concatenate([succ, successors(np.broadcast_to(pos[:, None], new.shape))], -1)
        probs = np.concatenate([(1.0 - wind) * probs, wind * probs], -1)
    features = transition_features(states[:, None], np.arange(NUM_ACTIONS)[None, :], wind)
    initial = (pos == SIDE + 1).astype(np.float64)  # the centre cell, any slices ahead
    uniform = np.allclose(hp, 1.0 / NUM_HOOPS)
    changed = wind > 0 or not uniform
    return TabularMDP(successors=succ, probs=probs, features=features, feature_names=FEATURE_NAMES,
                      initial=initial / initial.sum(), discount=discount, state_vectors=_state_vectors(),
                      next_value_fn=make_next_value_fn(None if uniform else tuple(hp), wind),
                      name="quadcopter (changed)" if changed else "quadcopter")


def describe_state(state: int) -> dict:
    """Named state variables of a state index."""
    pos, *hoops = (int(x) for x in decode(int(state)))
    return {"row": pos // SIDE, "col": pos % SIDE, "hoops": tuple(hoops),
            "hoop_names": tuple(HOOP_NAMES[h] for h in hoops)}


def quadcopter(discount: float = 0.95, world: str = "paper", *, hoop_probs=None, wind=None) -> Domain:
    """The quadcopter gate domain: its tabular MDP, the paper's skills A, B, C and its environment.

    Args:
        discount: the MDP's discount.
        world: a named world of :data:`WORLDS` ("paper", or a changed one with the same
            features: "row_hoops", "windy", "stormy").
        hoop_probs: the probability of each hoop (HOOP_NAMES order) in a new slice; wind: the
            probability that a move fails. Given ones override the world's.
    """
    params = world_parameters(world, hoop_probs, wind)
    mdp = _build_mdp(float(discount), params["hoop_probs"], params["wind"])
    return Domain(name="quadcopter", mdp=mdp, skill_names=SKILL_NAMES, skill_weights=SKILL_WEIGHTS, env_id=ENV_ID,
                  env_kwargs={"discount": float(discount), **params}, describe_state=describe_state)


# ------------------------------------------------------------------------------- drawing
_CELL = 32
_PAD = 12
_WALL = (60, 60, 70)
_AIR = (225, 232, 240)
_HOOP = (0, 190, 210)
_RIM = (200, 40, 160)
_COPTER = (30, 30, 30)
_ROTOR = (230, 120, 20)
_TRACE = (150, 150, 160)


def _draw_copter(img, top, left):
    """A top view of a quadcopter in the cell at (top, left): body, two arms, four rotors."""
    c, r = _CELL // 2, _CELL // 2 - 6
    for i in range(-r, r + 1):  # the arms, two diagonals
        img[top + c + i - 1:top + c + i + 1, left + c + i - 1:left + c + i + 1] = _COPTER
        img[top + c + i - 1:top + c + i + 1, left + c - i - 1:left + c - i + 1] = _COPTER
    for dy in (-r, r):
        for dx in (-r, r):
            img[top + c + dy - 3:top + c + dy + 3, left + c + dx - 3:left + c + dx + 3] = _ROTOR
    img[top + c - 4:top + c + 4, left + c - 4:left + c + 4] = _COPTER


def _panel(hoop, copter=None, ghost=None) -> np.ndarray:
    size = SIDE * _CELL
    img = np.empty((size + 4, size + 4, 3), dtype=np.uint8)
    img[:] = _WALL
    img[2:-2, 2:-2] = _AIR
    for cell in range(NUM_CELLS):
        r, c = divmod(cell, SIDE)
        top, left = 2 + r * _CELL, 2 + c * _CELL
        if hoop is not None and HOOPS[hoop, cell]:
            img[top:top + _CELL, left:left + _CELL] = _RIM
            img[top + 4:top + _CELL - 4, left + 4:left + _CELL - 4] = _HOOP
        if ghost == cell:
            img[top + 12:top + _CELL - 12, left + 12:left + _CELL - 12] = _TRACE
        if copter == cell:
            _draw_copter(img, top, left)
    return img


def render_quadcopter(state: int) -> np.ndarray:
    """Picture of a state (uint8, 124 x 572 x 3): the copter's slice, then the four slices ahead.

    The first panel shows the copter (black, orange rotors) in its slice; the next panels show each slice's
    hoop (cyan cells in a magenta rim) and, in grey, the copter's cell for reference. A bar
    under the first panel marks where the copter is.
    """
    pos, *hoops = (int(x) for x in decode(int(state)))
    panels = [_panel(None, copter=pos)] + [_panel(h, ghost=pos) for h in hoops]
    h = panels[0].shape[0]
    gap = np.full((h, _PAD, 3), 255, dtype=np.uint8)
    row = np.concatenate(sum(([p, gap] for p in panels), [])[:-1], axis=1)
    img = np.full((h + 2 * _PAD, row.shape[1] + 2 * _PAD, 3), 255, dtype=np.uint8)
    img[_PAD:_PAD + h, _PAD:_PAD + row.shape[1]] = row
    img[_PAD + h + 4:_PAD + h + 8, _PAD:_PAD + panels[0].shape[1]] = _COPTER
    return img


class QuadcopterEnv(SkillEnv):
    """The quadcopter gate domain as a gymnasium environment (``gymnasium.make("npbrs/Quadcopter-v0")``).

    Rewards are the realised features of the step (passing through the hoop of the slice
    entered, the row of the new cell) dotted with the skill's weights; kwargs as in
    :class:`~npbrs.domains.highway.SkillEnv`.
    """

    domain_fn = staticmethod(quadcopter)

    def sample_step(self, rng, states, actions):
        return sample_step(rng, states, actions, **self.world)

    def render_state(self, state: int) -> np.ndarray:
        return render_quadcopter(state)


if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point=QuadcopterEnv, max_episode_steps=500)


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
