"""The subgoal emission: every skill is the Boltzmann policy of reaching one goal state.

This is the BNIRL-style baseline of the paper (section II-D, "subgoal state methods"): skill
k's reward is ``scale`` for *arriving* in its goal state g_k and 0 otherwise,

    r_g(s, a) = scale * P(s' = g | s, a),

(the expected reward of the transition, so it is a reward on (s, a) like every other reward
of npbrs), and its emission is the Boltzmann policy of that reward, pi_g(a | s) =
exp(Q_g(s, a) - V_g(s)), with Q_g, V_g the soft (maximum causal entropy) values of r_g.

Prior: the goal is uniform over a fixed set of *candidate* states C, a numpyro Categorical
site ``"goal"`` (zero probability outside C). BNIRL samples goals among the states the
demonstrations visit; here that restriction is the prior's support, not a property of the
move: pass ``candidates=demos`` to make C the visited states (optionally the
``max_candidates`` most visited). C is fixed when the emission is built, so every move below
is exact for that prior. (Restricting the candidates of a skill to the states visited *in its
own steps* would make the support depend on z and the Gibbs step would not be exact.)

Update: each skill's goal is drawn exactly from its conditional over C,
p(g | steps) ∝ prod_t pi_g(a_t | s_t). The steps enter only through two (S,) tables of the
skill's weighted steps: the state counts n(s) and the expected next-state occupancy
m(s') = sum_t w_t P(s' | s_t, a_t). Since log pi_g(a | s) = r_g(s, a) + gamma E[V_g(s')] - V_g(s),

    sum_t w_t log pi_g(a_t | s_t) = scale * m(g) + sum_s V_g(s) (gamma m(s) - n(s)),

so the conditional needs the soft values V_g of every candidate and one matrix product. The
values of a goal do not depend on the chain's state, so they are solved once, when the
emission is built, whenever the (|C|, S) table fits in ``max_table_mb`` (``precompute``);
otherwise every update re-solves them in chunks of ``chunk_size`` goals (``lax.map``), which
bounds memory (chunk * S * A) at the price of |C| soft solves per sweep. The per-step
log-likelihoods use the same formula and the same values. For scale: on two CPU cores a
candidate's solve takes about 8 ms on the highway (its demonstrations visit 732 states: a 6 MB
table built in 5 s) and 13-20 ms on the quadcopter (16 x 500 steps visit ~5000 of its 11664
states: a 465 MB table, above the default limit; raise ``max_table_mb`` or keep the
``max_candidates`` most visited states). The table is a constant of every compiled function
that uses it, so a large one also lengthens compilation (about 15 s for 90 MB).

The design notes say "reward 1 at one goal state"; with the Boltzmann temperature fixed at 1
such a small reward gives nearly uniform policies, so the reward's size is the option ``scale``
(default 10).
"""

from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from npbrs.domains.solvers import make_soft_solver

from .emissions import Emission, EmissionInfo, HMMData, register_emission
from npbrs.domains.util.compiling import jit
from npbrs.domains.util.precision import float64_all

__all__ = ["SubgoalEmission", "visited_states"]


def visited_states(data, max_states: Optional[int] = None) -> np.ndarray:
    """The distinct states of demonstrations, most visited first (ties: lower index first).

    Args:
        data: :class:`~npbrs.domains.Demonstrations` or :class:`~npbrs.models.emissions.HMMData`.
        max_states: keep at most this many of the most visited states.
    Returns:
        (n,) int64 state indices, sorted by decreasing visit count.
    """
    if isinstance(data, HMMData):
        steps = np.asarray(data.states)[np.asarray(data.mask)]
    elif hasattr(data, "states") and isinstance(data.states, (list, tuple)):
        steps = np.concatenate([np.asarray(s) for s in data.states])
    else:
        raise ValueError(f"expected Demonstrations or HMMData, got {type(data).__name__}")
    states, counts = np.unique(steps.astype(np.int64), return_counts=True)
    order = np.lexsort((states, -counts))
    states = states[order]
    if max_states is not None:
        if int(max_states) < 1:
            raise ValueError(f"max_candidates must be >= 1, got {max_states}")
        states = states[:int(max_states)]
    return states


def _candidate_states(candidates, max_candidates, S) -> np.ndarray:
    if candidates is None:
        if max_candidates is not None:
            raise ValueError("max_candidates needs data-derived candidates (candidates=demos)")
        return np.arange(S, dtype=np.int64)
    if isinstance(candidates, HMMData) or (hasattr(candidates, "states") and hasattr(candidates, "actions")):
        cand = visited_states(candidates, max_candidates)
    else:
        if max_candidates is not None:
            raise ValueError("max_candidates applies to data-derived candidates (candidates=demos), "
                             "not to an explicit list of states")
        cand = np.asarray(candidates)
        if cand.ndim != 1 or cand.size == 0:
            raise ValueError(f"candidates must be a non-empty 1-D array of state indices, got shape {cand.shape}")
        if cand.dtype.kind not in "iu":
            raise ValueError(f"candidates must be integer state indices, got dtype {cand.dtype}")
    bad = (cand < 0) | (cand >= S)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise ValueError(f"candidate {i} is state {cand[i]}, outside 0..{S - 1}")
    if np.unique(cand).size != cand.size:
        raise ValueError("candidates contain repeated states")
    return np.sort(cand).astype(np.int64)


@register_emission("subgoal")
class SubgoalEmission(Emission):
    """Each skill is the Boltzmann policy of reaching one goal state (BNIRL-style baseline).

    Params: ``{"goal": (K,) int32}`` state indices. See the module docstring for the model.

    Args:
        mdp: the TabularMDP.
        scale: the reward of arriving in the goal (its size sets how deterministic the
            policies are: the Boltzmann temperature is 1).
        candidates: the prior's support: None (every state), an array of state indices, or
            demonstrations (:class:`~npbrs.domains.Demonstrations` or HMMData): the states they
            visit.
        max_candidates: with demonstrations as candidates, keep the most visited states only.
        precompute: "auto" (when the (|C|, S) value table fits in ``max_table_mb``), True or
            False: solve every candidate once at construction, or re-solve them in every update.
        max_table_mb: memory allowed for the precomputed table.
        chunk_size: goals solved at once (bounds memory to chunk_size * S * A floats).
        tol: relative tolerance of the soft Bellman solves.
    """

    def __init__(self, mdp, scale: float = 10.0, candidates=None, max_candidates: Optional[int] = None,
                 precompute="auto", max_table_mb: float = 256.0, chunk_size: int = 32, tol: float = 1e-10):
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"scale must be a positive number, got {scale!r}")
        if int(chunk_size) < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        if precompute not in ("auto", True, False):
            raise ValueError(f"precompute must be 'auto', True or False, got {precompute!r}")
        self.mdp = mdp
        self.scale = float(scale)
        self.discount = float(mdp.discount)
        self.chunk_size = int(chunk_size)
        self.tol = float(tol)
        S = mdp.num_states
        cand = _candidate_states(candidates, max_candidates, S)
        self.candidates = jnp.asarray(cand, jnp.int32)
        self.num_candidates = int(cand.size)
        index = np.full(S, -1, np.int64)
        index[cand] = np.arange(cand.size)
        self._index = jnp.asarray(index, jnp.int32)  # state -> position in candidates, -1 outside
        probs = np.zeros(S)
        probs[cand] = 1.0 / cand.size
        self._prior_probs = jnp.asarray(probs)
        self._succ = jnp.asarray(mdp.successors, jnp.int32)
        self._trans = jnp.asarray(mdp.probs)
        # the solver (built outside any trace) is data of this emission: its arrays enter the
        # compiled programs as arguments
        self._solver = make_soft_solver(mdp, tol=self.tol)
        table_mb = cand.size * S * 8 / 2 ** 20
        self._precompute_option, self.max_table_mb = precompute, float(max_table_mb)
        self.precompute = bool(table_mb <= max_table_mb) if precompute == "auto" else bool(precompute)
        self._values = None
        if self.precompute:
            self._values = _SOLVE_CANDIDATES(self)

    @classmethod
    def from_mdp(cls, mdp, **options):
        return cls(mdp, **options)

    # ------------------------------------------------------------------ the goals' policies
    def goal_rewards(self, goals) -> jax.Array:
        """Reward tables r_g(s, a) = scale * P(s' = g | s, a), (n, S, A) for goals (n,)."""
        return self.scale * self._solver.expected_next_value(jax.nn.one_hot(goals, self.mdp.num_states, dtype=jnp.float64))

    def goal_values(self, goals, v0=None) -> jax.Array:
        """Soft state values V_g of goals (n,), (n, S)."""
        return self._solver(self.goal_rewards(goals), v0).V

    def _solve_candidates(self):
        return jax.lax.map(lambda g: self.goal_values(g[None])[0], self.candidates, batch_size=self.chunk_size)

    def _step_log_policy(self, goals, values, data):
        """log pi_g(a_t | s_t) for goals (K,) with values (K, S): (K, N, T)."""
        succ = self._succ[data.states, data.actions]  # (N, T, B)
        p = self._trans[data.states, data.actions]
        arrive = jnp.sum(p[None] * (succ[None] == goals[:, None, None, None]), -1)  # (K, N, T)
        next_v = jnp.sum(p[None] * values[:, succ], -1)
        return self.scale * arrive + self.discount * next_v - values[:, data.states]

    def _occupancies(self, data, weights):
        """State counts n (S, K) and expected next-state occupancies m (S, K) of weighted steps."""
        S = self.mdp.num_states
        w = weights * data.mask[..., None]  # (N, T, K)
        K = w.shape[-1]
        counts = jax.ops.segment_sum(w.reshape(-1, K), data.states.reshape(-1), num_segments=S)
        succ = self._succ[data.states, data.actions]  # (N, T, B)
        p = self._trans[data.states, data.actions]
        contrib = (p[..., None] * w[..., None, :]).reshape(-1, K)
        occupancy = jax.ops.segment_sum(contrib, succ.reshape(-1), num_segments=S)
        return counts, occupancy

    def candidate_log_likelihoods(self, data: HMMData, weights) -> jax.Array:
        """log p(steps of skill k | goal g) for every candidate g and skill k, (|C|, K).

        Args:
            data: HMMData. weights: (N, T, K) weights of the steps (one-hot of z).
        """
        counts, occupancy = self._occupancies(data, weights)
        coef = self.discount * occupancy - counts  # (S, K)
        arrive = self.scale * occupancy[self.candidates]  # (|C|, K)
        if self.precompute:
            return arrive + self._values @ coef

        def chunk(g):
            return self.goal_values(g[None])[0] @ coef

        return arrive + jax.lax.map(chunk, self.candidates, batch_size=self.chunk_size)

    def log_conditional(self, data: HMMData, weights) -> jax.Array:
        """Each skill's normalised log conditional over the candidate goals, (K, |C|)."""
        ll = self.candidate_log_likelihoods(data, weights).T
        return jax.nn.log_softmax(ll, axis=-1)  # the prior is uniform over the candidates

    # ------------------------------------------------------------------ the protocol
    def _prior(self, K):
        import numpyro.distributions as dist

        return dist.Categorical(probs=self._prior_probs).expand([K]).to_event(1)

    def sample_params(self, K):
        import numpyro

        return {"goal": numpyro.sample("goal", self._prior(K))}

    def log_prior(self, params):
        import numpyro.distributions as dist

        return dist.Categorical(probs=self._prior_probs).log_prob(params["goal"])

    def init_cache(self, K):
        return () if self.precompute else {"V": jnp.zeros((K, self.mdp.num_states))}

    def log_policies(self, params):
        goals = params["goal"].astype(jnp.int32)
        values = (self._values[jnp.maximum(self._index[goals], 0)] if self.precompute else self.goal_values(goals))
        S, A = self.mdp.num_states, self.mdp.num_actions
        grid = HMMData(states=jnp.broadcast_to(jnp.arange(S)[:, None], (S, A)),
                       actions=jnp.broadcast_to(jnp.arange(A)[None, :], (S, A)), mask=jnp.ones((S, A), bool))
        return self._step_log_policy(goals, values, grid)  # (K, S, A)

    def log_likelihoods(self, params, data, cache=()):
        goals = params["goal"].astype(jnp.int32)
        if self.precompute:
            # a goal outside the candidates has prior probability 0 (log joint -inf); clamp its index
            values = self._values[jnp.maximum(self._index[goals], 0)]
        else:
            values = self.goal_values(goals, v0=cache["V"])
            cache = {"V": values}
        ll = jnp.moveaxis(self._step_log_policy(goals, values, data), 0, -1)
        return jnp.where(data.mask[..., None], ll, 0.0), cache

    def _draw(self, key, data, weights):
        log_cond = self.log_conditional(data, weights)  # (K, |C|)
        idx = jax.random.categorical(key, log_cond, axis=-1)
        return self.candidates[idx], jnp.take_along_axis(log_cond, idx[:, None], -1)[:, 0]

    def update(self, key, params, cache, data, weights, step):
        goals, _ = self._draw(key, data, weights)
        return {"goal": goals}, cache, EmissionInfo(jnp.ones(()))

    def init_params(self, key, data, weights):
        return {"goal": self._draw(key, data, weights)[0]}

    def propose(self, key, data, weights):
        goals, log_q = self._draw(key, data, weights[..., None])
        return {"goal": goals[0]}, log_q[0]

    def log_proposal(self, params_one, data, weights):
        log_cond = self.log_conditional(data, weights[..., None])[0]
        idx = self._index[params_one["goal"]]
        return jnp.where(idx >= 0, log_cond[jnp.maximum(idx, 0)], -jnp.inf)

    def describe(self):
        """The options that rebuild this emission with ``from_mdp`` (plain data)."""
        all_states = self.num_candidates == self.mdp.num_states
        return {"name": self.name, "scale": self.scale,
                "candidates": None if all_states else np.asarray(self.candidates).tolist(),
                "precompute": self._precompute_option, "max_table_mb": self.max_table_mb,
                "chunk_size": self.chunk_size, "tol": self.tol}


# one compiled candidate table per emission structure and shapes, not a new jit per emission
_SOLVE_CANDIDATES = jit(SubgoalEmission._solve_candidates)

float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
