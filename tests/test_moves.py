"""Birth and death of unique skills: exact reverses with reciprocal acceptance ratios."""

import jax
import jax.numpy as jnp
import numpy as np

from npbrs.inference.sampler.kernel import BPHMMKernel
from npbrs.inference.sampler.birth_death import birth_death_log_ratio, window_weights
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
    state = kernel.init(jax.random.PRNGKey(0), 0, None, (), {})
    f, eta, params, ll = state.features, state.eta, state.params, state.log_lik
    assert np.all(np.asarray(f[:, 2:]) == 0)
    i, k = 1, 3
    window = window_weights(jax.random.PRNGKey(5), data.mask, i, 5, 15)
    assert float(window[i].sum()) >= 5 and float(window.sum()) == float(window[i].sum())
    born, _ = em.propose(jax.random.PRNGKey(6), data, window)
    lr_birth, f2, p2, ll2 = birth_death_log_ratio(em, data, state.hyper, f, eta, params, ll, i, k, born, window, True)
    assert float(f2[i, k]) == 1.0
    old = jax.tree.map(lambda x: x[k], params)
    lr_death, f3, p3, ll3 = birth_death_log_ratio(em, data, state.hyper, f2, eta, p2, ll2, i, k, old, window, False)
    np.testing.assert_allclose(float(lr_death), -float(lr_birth), rtol=1e-10)
    np.testing.assert_array_equal(np.asarray(f3), np.asarray(f))
    for a, b in zip(jax.tree.leaves(p3), jax.tree.leaves(params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_allclose(np.asarray(ll3), np.asarray(ll), rtol=1e-12)
    assert np.isfinite(float(lr_birth))
