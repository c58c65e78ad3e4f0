import jax
import jax.numpy as jnp
import numpy as np
import pytest
from numpyro.diagnostics import effective_sample_size

from npbrs.domains import TabularMDP, make_soft_solver
from npbrs.inference.reward_move import RewardMALAInfo, RewardMALAState, build_kernel, init


def logistic_mdp(gamma=0.9):
    """One absorbing state, two actions, phi(s, a) = [a]: Q = r + gamma V, so
    log pi(1 | s) = theta - log(1 + e^theta), a logistic regression in theta."""
    return TabularMDP(successors=np.zeros((1, 2, 1), int), probs=np.ones((1, 2, 1)),
                      features=np.array([[[0.0], [1.0]]]), discount=gamma)


def exact_posterior(counts, sigma):
    """Mean and variance of theta given counts (n0, n1) by quadrature on a fine grid."""
    grid = np.linspace(-30, 30, 600001)
    n0, n1 = counts
    logp = n1 * grid - (n0 + n1) * np.logaddexp(0.0, grid) - 0.5 * grid ** 2 / sigma ** 2
    w = np.exp(logp - logp.max())
    w /= w.sum()
    mean = (w * grid).sum()
    return mean, (w * (grid - mean) ** 2).sum()


def test_mala_samples_the_exact_posterior_of_a_logistic_conditional():
    """Two skills at once (vmapped), each with its own counts: chain means and variances agree
    with quadrature within Monte Carlo standard errors."""
    sigma = 2.0
    counts = np.array([[3.0, 7.0], [10.0, 2.0]])
    truth = [exact_posterior(c, sigma) for c in counts]
    solver = make_soft_solver(logistic_mdp(), tol=1e-12)
    C = jnp.asarray(counts[:, None, :])  # (K, S=1, A=2)
    kernel = build_kernel(solver, prior_scale=sigma)
    step = jnp.asarray([1.1 * np.sqrt(v) for _, v in truth])
    state = init(solver, jnp.zeros((2, 1)), C, prior_scale=sigma)
    assert isinstance(state, RewardMALAState)

    @jax.jit
    def run(key, state):
        def one(st, k):
            st, info = kernel(k, st, C, step)
            return st, (st.theta[:, 0], info)

        return jax.lax.scan(one, state, jax.random.split(key, 4000))

    last, (theta, info) = run(jax.random.PRNGKey(0), state)
    assert isinstance(info, RewardMALAInfo)
    theta = np.asarray(theta)[500:]
    acc = np.asarray(info.is_accepted).mean(0)
    assert np.all((acc > 0.5) & (acc < 0.99)), acc
    assert not np.asarray(info.solver_failed).any()
    for k, (mean, var) in enumerate(truth):
        x = theta[:, k]
        ess = float(effective_sample_size(x[None]))
        assert ess > 300
        assert abs(x.mean() - mean) < 4 * x.std() / np.sqrt(ess), (k, x.mean(), mean, ess)
        dev = (x - x.mean()) ** 2
        ess_var = float(effective_sample_size(dev[None]))
        assert abs(dev.mean() - var) < 4 * dev.std() / np.sqrt(ess_var), (k, dev.mean(), var, ess_var)
    # the state carried along the chain is the density and gradient at its theta
    fresh = init(solver, last.theta, C, prior_scale=sigma, v0=last.V)
    np.testing.assert_allclose(last.log_density, fresh.log_density, rtol=1e-10)
    np.testing.assert_allclose(last.grad, fresh.grad, rtol=1e-8, atol=1e-10)


def test_bad_shapes_are_reported():
    solver = make_soft_solver(logistic_mdp(), tol=1e-12)
    C = jnp.asarray([[[4.0, 1.0]]])
    kernel = build_kernel(solver, prior_scale=3.0)
    state = RewardMALAState(jnp.zeros((1, 1)), jnp.zeros(1), jnp.zeros((1, 1)), jnp.zeros((1, 1)))
    with pytest.raises(ValueError, match="counts"):
        kernel(jax.random.PRNGKey(1), state, jnp.zeros((2, 1, 2)), 0.3)
    with pytest.raises(ValueError, match="theta"):
        init(solver, jnp.zeros((1, 2)), C)
    with pytest.raises(ValueError, match="counts"):
        init(solver, jnp.zeros((1, 1)), jnp.zeros((2, 1, 2)))
