"""The autoregressive (VAR(1), MNIW) emission: exact conjugate posterior, protocol, inputs."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from emission_suite import check_emission
from npbrs.domains import TabularMDP
from npbrs.inference import make_emission
from npbrs.models.autoregressive import AutoregressiveEmission
from npbrs.models.emissions import HMMData, get_emission_class

S, M, V0, S0, NU0 = 10, 2, 4.0, 0.5, 5.0


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(0)
    state_vectors = rng.normal(size=(S, M))
    N, T = 3, 20
    mask = np.ones((N, T), bool)
    mask[0, 15:] = False
    data = HMMData(jnp.asarray(rng.integers(0, S, (N, T)), jnp.int32), jnp.zeros((N, T), jnp.int32),
                   jnp.asarray(mask))
    z = rng.integers(0, 2, (N, T))
    z[2] = 0  # skill 1 keeps some steps, skill 0 most
    weights = jax.nn.one_hot(z, 3) * data.mask[..., None]  # skill 2 has no steps
    return AutoregressiveEmission(state_vectors, v0=V0, s0=S0, nu0=NU0), state_vectors, data, weights


def closed_form_posterior(state_vectors, data, weights, k):
    """The MNIW posterior by weighted least squares in plain NumPy."""
    states, mask = np.asarray(data.states), np.asarray(data.mask)
    w = np.asarray(weights)[..., k]
    X, Y, W = [], [], []
    for n in range(states.shape[0]):
        for t in range(states.shape[1] - 1):
            if mask[n, t] and mask[n, t + 1]:
                X.append(np.r_[state_vectors[states[n, t]], 1.0])
                Y.append(state_vectors[states[n, t + 1]])
                W.append(w[n, t])
    X, Y, W = np.array(X), np.array(Y), np.array(W)
    Sxx = np.eye(M + 1) / V0 + (X * W[:, None]).T @ X
    Syx = (Y * W[:, None]).T @ X
    Syy = (Y * W[:, None]).T @ Y
    mean = Syx @ np.linalg.inv(Sxx)
    scale = S0 * np.eye(M) + Syy - mean @ Sxx @ mean.T
    return mean, np.linalg.inv(Sxx), NU0 + W.sum(), scale


def test_the_posterior_is_the_closed_form_mniw_posterior(setup):
    em, sv, data, weights = setup
    post = em.posterior(data, weights)
    for k in range(3):
        mean, column_cov, dof, scale = closed_form_posterior(sv, data, weights, k)
        np.testing.assert_allclose(np.asarray(post.mean[k]), mean, atol=1e-10)
        np.testing.assert_allclose(np.asarray(post.column_cov[k]), column_cov, atol=1e-10)
        np.testing.assert_allclose(float(post.dof[k]), dof)
        np.testing.assert_allclose(np.asarray(post.scale[k]), scale, atol=1e-10)
    # a skill without steps keeps its prior
    np.testing.assert_allclose(np.asarray(post.mean[2]), 0.0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(post.scale[2]), S0 * np.eye(M), atol=1e-14)


def posterior_means(em, data, weights):
    post = em.posterior(data, weights)
    return {"dynamics": post.mean, "noise_cov": post.scale / (post.dof[:, None, None] - M - 1)}


def test_update_draws_have_the_posterior_means(setup):
    em, sv, data, weights = setup
    params = posterior_means(em, data, weights)
    keys = jax.random.split(jax.random.PRNGKey(1), 4000)
    draws = jax.jit(jax.vmap(lambda key: em.update(key, params, (), data, weights, 0)[0]))(keys)
    for k in range(2):
        mean, _, dof, scale = closed_form_posterior(sv, data, weights, k)
        for name, truth in [("dynamics", mean), ("noise_cov", scale / (dof - M - 1))]:
            x = np.asarray(draws[name][:, k])
            mcse = x.std(0) / np.sqrt(len(keys))
            np.testing.assert_array_less(np.abs(x.mean(0) - truth), 5 * mcse, err_msg=f"{name} of skill {k}")


def test_the_proposal_density_is_the_inverse_wishart_times_matrix_normal(setup):
    em, sv, data, weights = setup
    one, log_q = jax.jit(em.propose)(jax.random.PRNGKey(3), data, weights[..., 0])
    mean, column_cov, dof, scale = closed_form_posterior(sv, data, weights, 0)
    Sigma, W = np.asarray(one["noise_cov"]), np.asarray(one["dynamics"])
    expected = stats.invwishart(dof, scale).logpdf(Sigma) + stats.matrix_normal(mean, Sigma, column_cov).logpdf(W)
    np.testing.assert_allclose(float(log_q), expected, rtol=1e-10)
    prior_lp = jax.jit(em.log_prior)({k: v[None] for k, v in one.items()})
    expected_prior = (stats.invwishart(NU0, S0 * np.eye(M)).logpdf(Sigma)
                      + stats.matrix_normal(np.zeros((M, M + 1)), Sigma, V0 * np.eye(M + 1)).logpdf(W))
    np.testing.assert_allclose(float(prior_lp[0]), expected_prior, rtol=1e-10)


def test_a_step_emits_the_transition_out_of_its_state(setup):
    em, sv, data, weights = setup
    params = posterior_means(em, data, weights)
    ll, _ = em.log_likelihoods(params, data)
    states = np.asarray(data.states)
    for n, t, k in [(1, 3, 0), (2, 10, 1), (0, 13, 2)]:
        W, Sigma = np.asarray(params["dynamics"][k]), np.asarray(params["noise_cov"][k])
        loc = W @ np.r_[sv[states[n, t]], 1.0]
        expected = stats.multivariate_normal(loc, Sigma).logpdf(sv[states[n, t + 1]])
        np.testing.assert_allclose(float(ll[n, t, k]), expected)
    # the last step of each trajectory has no successor: the same (zero) for every skill
    assert np.all(np.asarray(ll[0, 14:]) == 0.0) and np.all(np.asarray(ll[1:, -1]) == 0.0)


def test_autoregressive_emission_follows_the_protocol(setup):
    check_emission(setup[0], setup[2])


def test_the_emission_needs_state_vectors():
    P = np.full((3, 2, 3), 1 / 3)
    with pytest.raises(ValueError, match="no state_vectors"):
        make_emission("autoregressive", TabularMDP.from_dense(P))
    mdp = TabularMDP.from_dense(P, state_vectors=np.arange(6.0).reshape(3, 2))
    em = make_emission("autoregressive", mdp, v0=2.0)
    assert get_emission_class("autoregressive") is AutoregressiveEmission
    assert em.dim == 2 and em.nu0 == 4.0
    options = em.describe()
    assert make_emission(options.pop("name"), mdp, **options).describe() == em.describe()
    with pytest.raises(ValueError, match="nu0 must exceed M - 1 = 1"):
        AutoregressiveEmission(np.zeros((3, 2)), nu0=0.5)
    with pytest.raises(ValueError, match=r"state_vectors\[1, 0\] is not finite"):
        AutoregressiveEmission(np.array([[0.0], [np.nan]]))
