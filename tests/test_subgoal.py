"""The subgoal emission: its goal conditional is exact, and it plugs into the sampler."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import logsumexp

from emission_suite import check_emission
from npbrs.domains import Demonstrations, TabularMDP
from npbrs.inference import make_emission
from npbrs.models.emissions import HMMData, get_emission_class
from npbrs.models.subgoal import SubgoalEmission, visited_states

S, A, GAMMA, SCALE = 6, 3, 0.9, 5.0


@pytest.fixture(scope="module")
def tiny():
    rng = np.random.default_rng(0)
    P = rng.random((S, A, S)) * (rng.random((S, A, S)) < 0.6)
    P[..., 0] += 1e-3
    P /= P.sum(-1, keepdims=True)
    mdp = TabularMDP.from_dense(P, discount=GAMMA)
    N, T = 3, 15
    mask = np.ones((N, T), bool)
    mask[0, 12:] = False
    data = HMMData(jnp.asarray(rng.integers(0, S, (N, T)), jnp.int32),
                   jnp.asarray(rng.integers(0, A, (N, T)), jnp.int32), jnp.asarray(mask))
    z = rng.integers(0, 2, (N, T))
    weights = jax.nn.one_hot(z, 2) * data.mask[..., None]
    return P, mdp, data, weights


def brute_force_log_policy(P, goal, scale=SCALE):
    """Soft value iteration in plain NumPy for the reward of arriving in ``goal``, run until it
    stops changing (a contraction by GAMMA: 0.9^400 is 4e-19)."""
    r = scale * P[:, :, goal]
    V = np.zeros(P.shape[0])
    for _ in range(4000):
        Q = r + GAMMA * P @ V
        top = Q.max(-1)
        V, previous = top + np.log(np.exp(Q - top[:, None]).sum(-1)), V
        if np.max(np.abs(V - previous)) == 0.0:
            break
    return Q - V[:, None]


@pytest.fixture(scope="module")
def emission(tiny):
    return SubgoalEmission(tiny[1], scale=SCALE)


@pytest.mark.parametrize("precompute", [True, False])
def test_the_goal_conditional_equals_brute_force_enumeration(tiny, emission, precompute):
    P, mdp, data, weights = tiny
    em = emission if precompute else SubgoalEmission(mdp, scale=SCALE, precompute=False, chunk_size=4)
    assert em.precompute == precompute
    states, actions, mask = (np.asarray(x) for x in data)
    w = np.asarray(weights)
    policies = [brute_force_log_policy(P, g)[states, actions] for g in range(S)]
    log_lik = np.array([[np.sum(w[..., k] * policies[g]) for g in range(S)] for k in range(w.shape[-1])])
    expected = log_lik - logsumexp(log_lik, -1, keepdims=True)  # uniform prior over all states
    np.testing.assert_allclose(np.asarray(em.log_conditional(data, weights)), expected, atol=1e-7)


def test_step_log_likelihoods_are_the_goal_policies(tiny, emission):
    P, mdp, data, _ = tiny
    goals = jnp.array([1, 4], jnp.int32)
    ll, _ = emission.log_likelihoods({"goal": goals}, data, emission.init_cache(2))
    states, actions, mask = (np.asarray(x) for x in data)
    expected = np.stack([brute_force_log_policy(P, int(g))[states, actions] for g in goals], -1) * mask[..., None]
    np.testing.assert_allclose(np.asarray(ll), expected, atol=1e-8)


def test_the_update_draws_goals_from_their_conditional(tiny, emission):
    _, _, data, weights = tiny
    probs = np.exp(np.asarray(emission.log_conditional(data, weights)))
    params = {"goal": jnp.zeros(2, jnp.int32)}
    keys = jax.random.split(jax.random.PRNGKey(1), 4000)
    goals = np.asarray(jax.jit(jax.vmap(lambda k: emission.update(k, params, (), data, weights, 0)[0]["goal"]))(keys))
    for k in range(2):
        freq = np.bincount(goals[:, k], minlength=S) / len(keys)
        sd = np.sqrt(probs[k] * (1 - probs[k]) / len(keys))
        assert np.all(np.abs(freq - probs[k]) <= 5 * sd + 1e-12)


def test_subgoal_emission_follows_the_protocol(tiny, emission):
    check_emission(emission, tiny[2])


def test_candidates_from_demonstrations_are_the_prior_support(tiny, emission):
    _, mdp, data, weights = tiny
    demos = Demonstrations([[0, 2, 2, 3], [3, 3, 2, 5]], [[0, 1, 2, 0], [1, 1, 1, 2]])
    np.testing.assert_array_equal(visited_states(demos), [2, 3, 0, 5])  # most visited first
    np.testing.assert_array_equal(visited_states(demos, max_states=2), [2, 3])
    em = SubgoalEmission(mdp, scale=SCALE, candidates=demos)
    np.testing.assert_array_equal(np.asarray(em.candidates), [0, 2, 3, 5])
    lp = np.asarray(em.log_prior({"goal": jnp.array([0, 1, 5])}))
    np.testing.assert_allclose(lp, [-np.log(4), -np.inf, -np.log(4)])
    # the conditional is the full-support one renormalised over the candidates
    ll_full = np.asarray(emission.candidate_log_likelihoods(data, weights))
    ll = np.asarray(em.candidate_log_likelihoods(data, weights))
    np.testing.assert_allclose(ll, ll_full[[0, 2, 3, 5]], atol=1e-8)
    one, log_q = em.propose(jax.random.PRNGKey(0), data, weights[..., 0])
    assert int(one["goal"]) in (0, 2, 3, 5)
    assert float(em.log_proposal({"goal": jnp.int32(1)}, data, weights[..., 0])) == -np.inf


def test_subgoal_is_registered_and_built_from_an_mdp(tiny):
    mdp = tiny[1]
    assert get_emission_class("subgoal") is SubgoalEmission
    em = make_emission("subgoal", mdp, scale=3.0, candidates=np.array([1, 2]), precompute=False)
    assert isinstance(em, SubgoalEmission) and em.scale == 3.0 and em.num_candidates == 2
    options = em.describe()
    assert options["candidates"] == [1, 2]
    # the description rebuilds the emission
    again = make_emission(options.pop("name"), mdp, **options)
    np.testing.assert_array_equal(np.asarray(again.candidates), [1, 2])
    assert again.scale == 3.0 and not again.precompute


@pytest.mark.parametrize("options, message", [
    ({"scale": -1.0}, "scale must be a positive"),
    ({"candidates": np.array([0, 9])}, "candidate 1 is state 9, outside 0..5"),
    ({"candidates": np.array([1, 1])}, "repeated"),
    ({"max_candidates": 3}, "max_candidates needs data-derived candidates"),
])
def test_bad_options_are_rejected(tiny, options, message):
    with pytest.raises(ValueError, match=message):
        SubgoalEmission(tiny[1], **options)
