"""Birth and death of unique skills: exact reverses with reciprocal acceptance ratios."""

import jax
import jax.numpy as jnp
import numpy as np

from npbrs.inference.sampler import (BPHMMKernel, MoveState, birth_death_log_ratio, birth_death_proposal,
                                     window_weights)
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
