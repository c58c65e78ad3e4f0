"""The highway driving domain (paper section IV-B) as a tabular MDP and a gymnasium environment.

The agent drives on a three-lane highway with a verge on either side. It is faster than every
other car, so the cars ahead come closer and are overtaken. State: the agent's position
0..4 (0 left verge, 1 left lane, 2 middle lane, 3 right lane, 4 right verge) and, for each lane
l = 1, 2, 3, the distance ``d_l`` in 0..5 to the nearest car ahead in that lane: 0 means the car
is level with the agent (a collision if the agent is in lane l) and 5 means no car in sight.
``5 * 6**3 = 1080`` states; actions 0 left, 1 right, 2 stay (moves are clipped at the verges).

Dynamics of one step. The agent's new position is deterministic in its action. Every lane then
moves independently of the others (so a step has 2**3 = 8 successors):

- a car at distance 1..4 comes one unit closer with the lane's *closing probability* and
  otherwise keeps its distance. The closing probability is the agent's speed relative to that
  lane's traffic: ``CLOSING[l]`` normally, ``CLOSING[l] * LANE_CHANGE_SLOWDOWN`` in a step in
  which the agent changes position (changing lanes costs speed; a move clipped at a verge is
  no change);
- an empty lane (distance 5) and a lane whose car has just been level with the agent
  (distance 0: it is overtaken and drops out of sight behind) get a new car at distance 4 with
  the lane's *appearance probability* ``APPEAR[l]``, and are empty (5) otherwise.

The paper does not publish its speeds; these were chosen by a search over the rates for the
largest pairwise disagreement between the three skills' optimal policies:

====== ========== =========== ==================================================================
lane   closing    appearance  traffic
====== ========== =========== ==================================================================
left   0.85       0.45        slow: a car ahead arrives within about one step
middle 0.25       0.50        fast: a car ahead stays near for ~4 steps per unit of distance,
                              so skill A waits for it in the middle lane
right  0.80       0.65        slow and dense
====== ========== =========== ==================================================================

``LANE_CHANGE_SLOWDOWN = 0.3``. Without it the car-hitting skill A is indifferent between its
actions whenever no car is one step away (about 40% of the states are exact ties: it can always
wait and reach any car in time), so its optimal policy would be arbitrary there; the slowdown
makes "stay unless a move pays" strictly optimal and leaves A with ties in 5% of states.

With these rates the pairwise share of states where the skills' optimal (greedy) actions differ
is A/B 57%, A/C 58%, B/C 56% (in the lanes: 72%, 74%, 88%). The ceiling is about 60%: on the
verges (40% of the states) every skill drives back onto the road. Under their optimal policies
A drives mostly in the middle lane and hits ~23 cars per 100 steps, B keeps to the right lane
(~73%) and dodges onto the right verge, C keeps to the left lane (~75%) and dodges onto the left
verge; B and C never collide. All three lanes are level with the agent at once in ~0.12% of the
steps and every lane has a car at distance <= 1 (the road is blocked ahead) in ~3%.

Reward features phi(s, a) are the *expected* state features of the next state s':
``collision`` (the agent's lane holds a car at distance 0), ``left_lane``, ``right_lane`` and
``on_verge``. Skills (paper): A hit cars (+500 a collision); B right lane (+10), collisions
(-500); C left lane (+10), collisions (-500).

Start states: the agent in one of the three lanes (uniform), the lanes drawn from the
stationary distribution of their own dynamics, and no car level with the agent.
"""

from __future__ import annotations

import dataclasses
from functools import lru_cache
from typing import Optional

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from .domain import Domain
from .mdp import TabularMDP
from .util.precision import float64_all

__all__ = ["highway", "HighwayEnv", "SkillEnv", "encode", "decode", "sample_step", "render_highway", "CLOSING",
           "APPEAR", "LANE_CHANGE_SLOWDOWN", "FEATURE_NAMES", "SKILL_WEIGHTS", "ENV_ID", "WORLDS", "world_parameters"]

ENV_ID = "npbrs/Highway-v0"
NUM_POSITIONS = 5
NUM_DISTANCES = 6
FAR = NUM_DISTANCES - 1
NEW_CAR = FAR - 1  # distance at which a new car appears
LANES = (1, 2, 3)  # positions that are lanes; lane index l = position - 1
LEFT, RIGHT, STAY = 0, 1, 2
ACTION_NAMES = ("left", "right", "stay")
POSITION_NAMES = ("left verge", "left lane", "middle lane", "right lane", "right verge")
NUM_STATES = NUM_POSITIONS * NUM_DISTANCES ** 3
NUM_ACTIONS = 3

CLOSING = np.array([0.85, 0.25, 0.80])
APPEAR = np.array([0.45, 0.50, 0.65])
LANE_CHANGE_SLOWDOWN = 0.3

#: Named worlds: the paper's and changed ones with the same features (other car speeds and
#: appearance rates), for re-solving inferred rewards in a world that has changed:
#: ``highway(world="slow_middle")``, ``gymnasium.make("npbrs/Highway-v0", world="slow_middle")``.
WORLDS = {
    "paper": {},
    # the middle lane's traffic is now slow and the side lanes' fast
    "slow_middle": {"closing": (0.30, 0.90, 0.30)},
    # slow, dense traffic in every lane
    "traffic_jam": {"closing": (0.95, 0.95, 0.95), "appear": (0.90, 0.90, 0.90)},
    # fast traffic in every lane: cars ahead close in slowly
    "fast_traffic": {"closing": (0.25, 0.25, 0.25)},
}

FEATURE_NAMES = ("collision", "left_lane", "right_lane", "on_verge")
SKILL_NAMES = ("A", "B", "C")
SKILL_WEIGHTS = np.array([
    [500.0, 0.0, 0.0, 0.0],   # A: hit as many cars as possible
    [-500.0, 0.0, 10.0, 0.0],  # B: right lane, avoid collisions
    [-500.0, 10.0, 0.0, 0.0],  # C: left lane, avoid collisions
])

# new position after each action, (positions, actions)
MOVES = np.array([[max(p - 1, 0), min(p + 1, NUM_POSITIONS - 1), p] for p in range(NUM_POSITIONS)])


def encode(position, d1, d2, d3):
    """State index of (position, d1, d2, d3); works elementwise on arrays."""
    return ((np.asarray(position) * NUM_DISTANCES + d1) * NUM_DISTANCES + d2) * NUM_DISTANCES + d3


def decode(state):
    """(position, d1, d2, d3) of a state index (elementwise on arrays)."""
    state = np.asarray(state)
    d3 = state % NUM_DISTANCES
    d2 = (state // NUM_DISTANCES) % NUM_DISTANCES
    d1 = (state // NUM_DISTANCES ** 2) % NUM_DISTANCES
    position = state // NUM_DISTANCES ** 3
    return position, d1, d2, d3


def lane_matrices(closing=CLOSING, appear=APPEAR) -> np.ndarray:
    """Per-lane distance transition matrices T[l, d, d'], shape (3, 6, 6)."""
    T = np.zeros((3, NUM_DISTANCES, NUM_DISTANCES))
    for l in range(3):
        for d in range(1, FAR):
            T[l, d, d - 1] += closing[l]
            T[l, d, d] += 1.0 - closing[l]
        for d in (0, FAR):
            T[l, d, NEW_CAR] += appear[l]
            T[l, d, FAR] += 1.0 - appear[l]
    return T


def transition_matrices(closing=CLOSING, appear=APPEAR, slowdown=LANE_CHANGE_SLOWDOWN) -> np.ndarray:
    """Lane matrices while keeping the position [0] and while changing lanes [1], (2, 3, 6, 6)."""
    closing = np.asarray(closing, dtype=np.float64)
    return np.stack([lane_matrices(closing, appear), lane_matrices(closing * slowdown, appear)])


def changes_lane(position, action):
    """Whether the action moves the agent to another position (clipped moves do not)."""
    return MOVES[position, action] != position


def state_features(states) -> np.ndarray:
    """Features of states as next states, (..., 4): collision, left_lane, right_lane, on_verge."""
    position, *dist = decode(states)
    dist = np.stack(dist, -1)
    lane = np.clip(position - 1, 0, 2)
    in_lane = (position >= 1) & (position <= 3)
    collision = in_lane & (np.take_along_axis(dist, lane[..., None], -1)[..., 0] == 0)
    return np.stack([collision, position == 1, position == 3, (position == 0) | (position == 4)],
                    -1).astype(np.float64)


def world_parameters(world: str = "paper", closing=None, appear=None, slowdown=None) -> dict:
    """The dynamics' rates of a named world (:data:`WORLDS`) with explicit ones on top:
    {"closing": (3,), "appear": (3,), "slowdown": float}, checked."""
    if world not in WORLDS:
        raise ValueError(f"unknown highway world {world!r}; known worlds: {', '.join(WORLDS)}")
    params = {"closing": tuple(CLOSING), "appear": tuple(APPEAR), "slowdown": LANE_CHANGE_SLOWDOWN, **WORLDS[world]}
    for name, value in (("closing", closing), ("appear", appear), ("slowdown", slowdown)):
        if value is not None:
            params[name] = value
    for name in ("closing", "appear"):
        arr = np.asarray(params[name], dtype=np.float64)
        if arr.shape != (3,) or not np.all((arr >= 0) & (arr <= 1)):
            raise ValueError(f"{name} must be three probabilities (left, middle, right lane), got {params[name]!r}")
        params[name] = tuple(float(x) for x in arr)
    slow = float(params["slowdown"])
    if not 0 <= slow <= 1 or np.any(np.asarray(params["closing"]) * slow > 1):
        raise ValueError(f"slowdown must lie in [0, 1], got {params['slowdown']!r}")
    params["slowdown"] = slow
    return params


def sample_step(rng: np.random.Generator, states, actions, closing=CLOSING, appear=APPEAR,
                slowdown=LANE_CHANGE_SLOWDOWN):
    """The environment's dynamics, vectorised: next states and their features.

    Args:
        rng: NumPy generator.
        states: int array (n,); actions: int array (n,).
        closing, appear, slowdown: the world's rates (the paper's by default).
    Returns:
        next_states (n,) and features (n, 4) of the next states.
    """
    position, d1, d2, d3 = decode(states)
    actions = np.asarray(actions)
    dist = np.stack([d1, d2, d3], -1)
    u = rng.random(dist.shape)
    closing = np.asarray(closing) * np.where(changes_lane(position, actions), slowdown, 1.0)[..., None]
    moving = (dist >= 1) & (dist <= FAR - 1)
    closer = np.where(u < closing, dist - 1, dist)
    refill = np.where(u < np.asarray(appear), NEW_CAR, FAR)
    dist = np.where(moving, closer, refill)
    nxt = encode(MOVES[position, actions], dist[..., 0], dist[..., 1], dist[..., 2])
    return nxt, state_features(nxt)


def _stationary(T: np.ndarray) -> np.ndarray:
    """Stationary distribution of a stochastic matrix T (n, n)."""
    n = T.shape[0]
    A = np.vstack([T.T - np.eye(n), np.ones(n)])
    b = np.zeros(n + 1)
    b[-1] = 1.0
    return np.linalg.lstsq(A, b, rcond=None)[0]


def _initial_distribution(T: np.ndarray) -> np.ndarray:
    pos, d1, d2, d3 = decode(np.arange(NUM_STATES))
    pi = [_stationary(T[l]) for l in range(3)]
    p = pi[0][d1] * pi[1][d2] * pi[2][d3] * np.isin(pos, LANES)
    dist = np.stack([d1, d2, d3], -1)
    level = np.isin(pos, LANES) & (dist[np.arange(NUM_STATES), np.clip(pos - 1, 0, 2)] == 0)
    p = np.where(level, 0.0, p)
    return p / p.sum()


def make_next_value_fn(T: np.ndarray):
    """E[V(s') | s, a] for V (..., S) -> (..., S, A), factored over the independent lanes.

    Given the action the three lanes move independently, so the expectation over the 8
    successors is a contraction of V (..., 5, 6, 6, 6) with one 6 x 6 matrix per lane (one
    set while keeping the position, one while changing lanes); the new position is a
    deterministic function of the action: a gather on the position axis.

    Args:
        T: (2, 3, 6, 6) lane matrices from :func:`transition_matrices`.
    """
    import jax.numpy as jnp

    # NumPy constants (float64 whatever JAX's setting when the domain is built)
    T = np.asarray(T, np.float64)
    positions = np.arange(NUM_POSITIONS)[:, None]
    kind = changes_lane(positions, np.arange(NUM_ACTIONS)[None, :]).astype(np.int32)
    moves = np.asarray(MOVES)

    def next_value(V):
        batch = V.shape[:-1]
        V = V.reshape(batch + (NUM_POSITIONS,) + (NUM_DISTANCES,) * 3)
        W = jnp.einsum("...pxyz,kax,kby,kcz->...kpabc", V, T[:, 0], T[:, 1], T[:, 2])
        W = W[..., kind, moves, :, :, :]  # (..., 5, A, 6, 6, 6)
        W = jnp.moveaxis(W, -4, -1)  # (..., 5, 6, 6, 6, A)
        return W.reshape(batch + (NUM_STATES, NUM_ACTIONS))

    return next_value


@lru_cache(maxsize=8)
def _build_mdp(discount: float, closing=tuple(CLOSING), appear=tuple(APPEAR),
               slowdown=LANE_CHANGE_SLOWDOWN) -> TabularMDP:
    T = transition_matrices(closing, appear, slowdown)  # (2, 3, 6, 6)
    states = np.arange(NUM_STATES)
    pos, d1, d2, d3 = decode(states)
    dist = np.stack([d1, d2, d3], -1)  # (S, 3)
    actions = np.arange(NUM_ACTIONS)
    kind = changes_lane(pos[:, None], actions[None, :]).astype(int)  # (S, A)
    # each lane has two outcomes (b_l = 0 or 1): closer / not closer, or a new car / none
    outcomes = np.array([[NEW_CAR, FAR]] + [[d - 1, d] for d in range(1, FAR)] + [[NEW_CAR, FAR]])  # (6, 2)
    lane_next = outcomes[dist]  # (S, 3, 2)
    lanes = np.arange(3)
    # lane_prob[s, a, l, j] = T[kind(s, a), l, d_l, lane_next[s, l, j]]
    lane_prob = T[kind[:, :, None, None], lanes[:, None], dist[:, None, :, None], lane_next[:, None]]  # (S, A, 3, 2)
    b = np.array(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij")).reshape(3, 8).T  # (8, 3)
    nd = lane_next[:, lanes, b]  # (S, 8, 3)
    probs = np.prod(lane_prob[:, :, lanes, b], -1)  # (S, A, 8)
    new_pos = MOVES[pos]  # (S, A)
    succ = encode(new_pos[:, :, None], nd[:, None, :, 0], nd[:, None, :, 1], nd[:, None, :, 2])  # (S, A, 8)
    features = np.einsum("sab,sabd->sad", probs, state_features(succ))
    return TabularMDP(successors=succ, probs=probs, features=features, feature_names=FEATURE_NAMES,
                      initial=_initial_distribution(T[0]), discount=discount,
                      state_vectors=np.stack([pos, d1, d2, d3], -1).astype(np.float64),
                      next_value_fn=make_next_value_fn(T), name="highway")


def describe_state(state: int) -> dict:
    """Named state variables of a state index."""
    pos, d1, d2, d3 = (int(x) for x in decode(int(state)))
    return {"position": pos, "position_name": POSITION_NAMES[pos], "distances": (d1, d2, d3)}


def highway(discount: float = 0.95, world: str = "paper", *, closing=None, appear=None, slowdown=None) -> Domain:
    """The highway domain: its tabular MDP, the paper's skills A, B, C and its environment.

    Args:
        discount: the MDP's discount.
        world: a named world of :data:`WORLDS` ("paper", or a changed one with the same
            features: "slow_middle", "traffic_jam", "fast_traffic").
        closing, appear: per lane (left, middle, right), the probability that a car ahead comes
            one unit closer in a step, and that a new car appears in an empty lane; slowdown:
            the factor on closing in a step that changes lanes. Given ones override the world's.
    """
    params = world_parameters(world, closing, appear, slowdown)
    mdp = _build_mdp(float(discount), params["closing"], params["appear"], params["slowdown"])
    if params != world_parameters():
        mdp = dataclasses.replace(mdp, name=f"highway ({world})" if world != "paper" else "highway (changed)")
    return Domain(name="highway", mdp=mdp, skill_names=SKILL_NAMES, skill_weights=SKILL_WEIGHTS, env_id=ENV_ID,
                  env_kwargs={"discount": float(discount), **params}, describe_state=describe_state)


# ---------------------------------------------------------------------------- environments
class SkillEnv(gym.Env):
    """A gymnasium environment over a tabular domain, rewarded by one skill's weights.

    Observations are state indices (``Discrete(S)``); ``info`` holds the decoded state
    variables and the realised features. Episodes never terminate; they are truncated after
    ``max_episode_steps`` steps. A subclass sets ``domain`` and implements
    ``sample_step(rng, states, actions) -> (next_states, features)`` (its own generative
    dynamics, vectorised; the tests check it against the tabular MDP) and ``render_state``.

    Args:
        skill: a skill name of the domain ("A", "B", "C"), a weight vector (D,), or None for
            zero reward.
        max_episode_steps: steps before ``truncated`` is returned.
        render_mode: None or "rgb_array".
        discount: discount of the domain's tabular MDP (does not affect the dynamics).
        world: the domain's world options (e.g. ``world="slow_middle"``, or its rates), passed to
            the domain's constructor; the environment's dynamics are that world's.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}
    domain_fn = None  # set by subclasses: discount -> Domain

    def __init__(self, skill=None, max_episode_steps: int = 500, render_mode: Optional[str] = None,
                 discount: float = 0.95, **world):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        if int(max_episode_steps) < 1:
            raise ValueError(f"max_episode_steps must be >= 1, got {max_episode_steps}")
        self.domain = type(self).domain_fn(discount, **world)
        self.world = {k: v for k, v in self.domain.env_kwargs.items() if k != "discount"}
        self.mdp = self.domain.mdp
        self.reward_weights = self.skill_weights(skill)
        self.skill = skill
        self.max_episode_steps = int(max_episode_steps)
        self.render_mode = render_mode
        self.observation_space = spaces.Discrete(self.mdp.num_states)
        self.action_space = spaces.Discrete(self.mdp.num_actions)
        self.state = None
        self._steps = 0

    def skill_weights(self, skill) -> np.ndarray:
        """Reward weights (D,) of a skill name, a weight vector, or None (zeros)."""
        D = self.mdp.num_features
        if skill is None:
            return np.zeros(D)
        if isinstance(skill, str):
            if skill not in self.domain.skill_names:
                raise ValueError(f"unknown skill {skill!r}; expected one of {self.domain.skill_names}")
            return self.domain.skill_weights[self.domain.skill_names.index(skill)].copy()
        w = np.asarray(skill, dtype=np.float64)
        if w.shape != (D,):
            raise ValueError(f"skill weights must have shape ({D},) for features {self.mdp.feature_names}, "
                             f"got {w.shape}")
        return w

    def sample_step(self, rng, states, actions):
        raise NotImplementedError

    def render_state(self, state: int) -> np.ndarray:
        raise NotImplementedError

    def _info(self, features=None) -> dict:
        info = dict(self.domain.describe_state(self.state))
        if features is not None:
            info["features"] = dict(zip(self.mdp.feature_names, (float(f) for f in features)))
        return info

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        """Start an episode in a state drawn from the MDP's initial distribution, or in
        ``options["state"]`` (e.g. where an option may start)."""
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"state"}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; the only one is 'state'")
        if "state" in options:
            state = options["state"]
            if not isinstance(state, (int, np.integer)) or not 0 <= int(state) < self.mdp.num_states:
                raise ValueError(f"reset state {state!r} is outside 0..{self.mdp.num_states - 1}")
            self.state = int(state)
        else:
            self.state = int(self.np_random.choice(self.mdp.num_states, p=self.mdp.initial))
        self._steps = 0
        return self.state, self._info()

    def step(self, action):
        if self.state is None:
            raise RuntimeError("call reset() before step()")
        if not self.action_space.contains(action):
            raise ValueError(f"action {action!r} is outside 0..{self.mdp.num_actions - 1}")
        nxt, feats = self.sample_step(self.np_random, np.array([self.state]), np.array([int(action)]))
        self.state = int(nxt[0])
        self._steps += 1
        reward = float(feats[0] @ self.reward_weights)
        truncated = self._steps >= self.max_episode_steps
        return self.state, reward, False, truncated, self._info(feats[0])

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self.state is None:
            raise RuntimeError("call reset() before render()")
        return self.render_state(self.state)


# ------------------------------------------------------------------------------- drawing
_CELL = 48
_GRASS = (70, 140, 60)
_ROAD = (80, 80, 85)
_MARK = (235, 235, 235)
_AGENT = (40, 90, 220)
_CAR = (210, 40, 40)
_CRASH = (255, 200, 0)


def _box(img, top, left, height, width, colour):
    img[max(top, 0):max(top + height, 0), max(left, 0):max(left + width, 0)] = colour


def render_highway(state: int) -> np.ndarray:
    """Top-down picture of a state (uint8, 288 x 240 x 3): road ahead at the top, agent at the bottom.

    Rows are distances 5 (top, in the distance) to 0 (bottom, level with the agent); a car at
    distance d is drawn in row d, a collision gets a yellow frame.
    """
    pos, *dist = (int(x) for x in decode(int(state)))
    H, W = NUM_DISTANCES * _CELL, NUM_POSITIONS * _CELL
    img = np.empty((H, W, 3), dtype=np.uint8)
    img[:] = _ROAD
    _box(img, 0, 0, H, _CELL, _GRASS)
    _box(img, 0, 4 * _CELL, H, _CELL, _GRASS)
    for x in (_CELL, 4 * _CELL):  # solid edge lines
        _box(img, 0, x - 1, H, 3, _MARK)
    for x in (2 * _CELL, 3 * _CELL):  # dashed lane lines
        for y in range(0, H, 24):
            _box(img, y, x - 1, 12, 3, _MARK)
    # the far row fades: cars there are out of sight
    img[:_CELL] = (0.6 * img[:_CELL] + 0.4 * 200).astype(np.uint8)

    def car(row, col, colour):
        top, left = (FAR - row) * _CELL + 5, col * _CELL + 10
        _box(img, top, left, _CELL - 10, _CELL - 20, colour)
        _box(img, top + 8, left + 4, 8, _CELL - 28, (200, 230, 255))  # windscreen

    crash = pos in LANES and dist[pos - 1] == 0
    for l, d in enumerate(dist):
        if d < FAR and not (crash and l == pos - 1):
            car(d, l + 1, _CAR)
    if crash:
        _box(img, (FAR * _CELL) + 1, pos * _CELL + 4, _CELL - 2, _CELL - 8, _CRASH)
        _box(img, (FAR * _CELL) + 4, pos * _CELL + 7, _CELL - 8, _CELL - 14, _CAR)
    car(0, pos, _AGENT)
    return img


class HighwayEnv(SkillEnv):
    """The highway domain as a gymnasium environment (``gymnasium.make("npbrs/Highway-v0")``).

    See the module docstring for the dynamics; kwargs as in :class:`SkillEnv`.
    """

    domain_fn = staticmethod(highway)

    def sample_step(self, rng, states, actions):
        return sample_step(rng, states, actions, **self.world)

    def render_state(self, state: int) -> np.ndarray:
        return render_highway(state)


if ENV_ID not in gym.registry:
    gym.register(id=ENV_ID, entry_point=HighwayEnv, max_episode_steps=500)


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
