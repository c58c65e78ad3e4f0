"""Birth and death of unique skills: exact reverses with reciprocal acceptance ratios."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from npbrs.inference.sampler import (BPHMMKernel, MoveState, birth_death_log_ratio, birth_death_proposal,
                                     window_weights)
from npbrs.inference.sampler.birth_death import birth_death
from npbrs.models.bphmm import collapsed_feature_log_prob
from npbrs.models.emissions import PolicyEmission
from test_kernel import planted_policy_data


def test_collapsed_feature_prior_integrates_the_model_omega():
    from scipy import integrate, stats

    F = np.array([[1, 0, 1], [1, 0, 0], [0, 0, 1], [1, 0, 0]], float)
    alpha, (N, K) = 1.7, F.shape
    expected = 0.0
    for k in range(K):
        m = F[:, k].sum()
        val, _ = integrate.quad(lambda w: stats.beta(alpha / K, 1).pdf(w) * w ** m * (1 - w) ** (N - m), 0, 1,
                                points=[1e-8, 1e-4, 1e-2], limit=200)
        expected += np.log(val)
    np.testing.assert_allclose(float(collapsed_feature_log_prob(jnp.asarray(F), alpha)), expected, rtol=1e-6)


def test_birth_then_death_returns_the_state_with_reciprocal_ratios():
    data, _ = planted_policy_data(seed=2, N=4, T=30)
    em = PolicyEmission(4, 3)
    kernel = BPHMMKernel(em, data, max_skills=5, init_skills=2)
    start = kernel.init(jax.random.PRNGKey(0), 0, None, (), {})
    state, hyper = MoveState.of(start), start.hyper
    f, params, ll = state.features, state.params, state.log_lik
    assert np.all(np.asarray(f[:, 2:]) == 0)
    i, k = 1, 3
    window = window_weights(jax.random.PRNGKey(5), data.mask, i, 5, 15)
    assert float(window[i].sum()) >= 5 and float(window.sum()) == float(window[i].sum())
    born, _ = em.propose(jax.random.PRNGKey(6), data, window)
    # the birth proposes f_ik on and slot k's parameters (and their likelihoods) from the window
    birth = birth_death_proposal(state, em, data, i, k, born, True)
    assert float(birth.features[i, k]) == 1.0
    np.testing.assert_allclose(np.asarray(birth.log_lik), np.asarray(em.log_likelihoods(birth.params, data)[0]),
                               rtol=1e-12)
    lr_birth = birth_death_log_ratio(state, birth, em, data, hyper, i, k, window)
    # the death of slot k in i, whose prior draw puts back slot k's old parameters: the start
    old = jax.tree.map(lambda x: x[k], params)
    death = birth_death_proposal(birth, em, data, i, k, old, False)
    np.testing.assert_array_equal(np.asarray(death.features), np.asarray(f))
    for a, b in zip(jax.tree.leaves(death.params), jax.tree.leaves(params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_allclose(np.asarray(death.log_lik), np.asarray(ll), rtol=1e-12)
    lr_death = birth_death_log_ratio(birth, death, em, data, hyper, i, k, window)
    np.testing.assert_allclose(float(lr_death), -float(lr_birth), rtol=1e-10)
    # the ratio is a function of the two states: the death back to ``state`` itself gives the same
    lr_back = birth_death_log_ratio(birth, state, em, data, hyper, i, k, window)
    np.testing.assert_allclose(float(lr_back), -float(lr_birth), rtol=1e-10)
    assert np.isfinite(float(lr_birth))


class ReportingPolicy(PolicyEmission):
    """The policy emission, reporting the likelihoods of the first (or only) skill of a call
    ok where ``ok[0]``, of the second where ``ok[1]``: a stand-in for solves that did or did not
    converge. ``ok`` is an array (traced data), so every choice runs one compiled program."""

    reports_solves = True

    def __init__(self, num_states, num_actions, ok):
        super().__init__(num_states, num_actions)
        self.ok = np.array([bool(o) for o in ok] + [True] * (2 - len(ok)))

    def log_likelihoods(self, params, data, cache=(), with_ok=False):
        ll, cache = super().log_likelihoods(params, data, cache)
        if not with_ok:
            return ll, cache
        return ll, cache, jnp.asarray(self.ok)[:ll.shape[-1]]


def _birth_death_trials(em, state, data, hyper, seeds=range(24)):
    """(is_birth, possible, accepted) of one birth/death trial per seed, as (len(seeds),) arrays."""
    run = jax.jit(jax.vmap(lambda key: birth_death(key, state, em, data, hyper, 5, 15)[1]))
    info = run(jax.vmap(jax.random.PRNGKey)(jnp.arange(len(seeds)) + seeds[0]))
    return np.asarray(info.is_birth), np.asarray(info.possible), np.asarray(info.accepted)


def test_a_birth_is_possible_only_where_the_emission_reports_the_born_skill_ok():
    """A birth whose born skill's likelihoods the emission reports not ok (``reports_solves``,
    e.g. a soft solve that did not converge) is never possible, nor accepted; a death does not
    depend on it (its ratio holds the dying skill's likelihoods, already in the state, and none of
    the prior draw that replaces it)."""
    data, _ = planted_policy_data(seed=2, N=4, T=30)
    plain = PolicyEmission(4, 3)
    kernel = BPHMMKernel(plain, data, max_skills=5, init_skills=2)
    start = kernel.init(jax.random.PRNGKey(0), 0, None, (), {})
    # a skill unique to trajectory 0 and one to trajectory 1, so that deaths are possible too
    f = np.zeros((4, 5))
    f[:, 0] = f[0, 1] = f[1, 2] = 1.0
    state = MoveState.of(start)._replace(features=jnp.asarray(f))
    births, possible, _ = _birth_death_trials(plain, state, data, start.hyper)
    assert possible[births].all() and possible[~births].any()
    for ok, possible_births in (([True], True), ([False], False)):
        b, p, a = _birth_death_trials(ReportingPolicy(4, 3, ok), state, data, start.hyper)
        np.testing.assert_array_equal(b, births)
        assert np.all(p[b] == possible_births) and (possible_births or not a[b].any())
        np.testing.assert_array_equal(p[~b], possible[~b])


@pytest.mark.slow  # (two compiles of the reward birth; the default run checks the move's rule with a stand-in
# above and the reward emission's report in test_reward_emission.py)
def test_a_birth_whose_soft_solve_does_not_converge_is_impossible():
    """The reward emission reports its solves (``reports_solves``): with a solver that stops
    after one Newton step, short of its tolerance, no birth is possible; with the default solver
    the same births, from the same state and keys, are."""
    from gridworld import gridworld
    from npbrs.domains import generate_demonstrations
    from npbrs.models.emissions import HMMData
    from npbrs.models.reward.emission import RewardEmission

    dom = gridworld(size=3)
    data = HMMData.from_demonstrations(generate_demonstrations(dom, num_trajectories=3, length=20, seed=2))
    em = RewardEmission(dom.mdp)
    kernel = BPHMMKernel(em, data, max_skills=4, init_skills=2)
    start = kernel.init(jax.random.PRNGKey(0), 0, None, (), {})
    state = MoveState.of(start)
    births, possible, _ = _birth_death_trials(em, state, data, start.hyper, range(6))
    assert births.any() and possible[births].all()
    unconverged = RewardEmission(dom.mdp, solver_options={"max_iter": 1})
    b, p, a = _birth_death_trials(unconverged, state, data, start.hyper, range(6))
    np.testing.assert_array_equal(b, births)
    assert not p[b].any() and not a[b].any()
