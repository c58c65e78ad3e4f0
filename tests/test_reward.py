import jax
import jax.numpy as jnp
import numpy as np
import pytest

from npbrs.domains import TabularMDP, greedy_policy, make_soft_solver
from npbrs.models.reward.irl import fit_reward, irl_fit
from npbrs.models.reward.likelihood import (count_log_likelihood, count_log_likelihood_and_grad, count_table,
                                            fisher_information, log_policy, log_posterior, step_log_likelihoods)


def random_mdp(seed, S=8, A=3, D=4, gamma=0.9):
    rng = np.random.default_rng(seed)
    P = rng.random((S, A, S)) * (rng.random((S, A, S)) < 0.5)
    P[np.arange(S), :, rng.integers(0, S, S)] += 0.05
    P /= P.sum(-1, keepdims=True)
    return TabularMDP.from_dense(P, features=rng.normal(size=(S, A, D)), discount=gamma)


@pytest.fixture(scope="module")
def small():
    mdp = random_mdp(0)
    solver = make_soft_solver(mdp, tol=1e-13, grad_tol=1e-13)
    rng = np.random.default_rng(1)
    theta = 2.0 * rng.normal(size=(2, mdp.num_features))
    counts = rng.integers(0, 6, size=(2, mdp.num_states, mdp.num_actions)).astype(float)
    return mdp, solver, theta, counts


def test_count_table_is_a_weighted_histogram_of_the_steps():
    rng = np.random.default_rng(0)
    S, A, N, T, K = 5, 3, 4, 7, 2
    states, actions = rng.integers(0, S, (N, T)), rng.integers(0, A, (N, T))
    weights = rng.random((N, T, K))
    mask = rng.random((N, T)) < 0.8
    expected = np.zeros((K, S, A))
    for i in range(N):
        for t in range(T):
            if mask[i, t]:
                expected[:, states[i, t], actions[i, t]] += weights[i, t]
    np.testing.assert_allclose(count_table(states, actions, weights, S, A, mask=mask), expected, atol=1e-12)
    unweighted = np.zeros((S, A))
    np.add.at(unweighted, (states[mask], actions[mask]), 1.0)
    np.testing.assert_allclose(count_table(states, actions, None, S, A, mask=mask), unweighted, atol=1e-12)
    with pytest.raises(ValueError, match="trajectory 1, step 2: action 7 is outside 0..2"):
        bad = actions.copy()
        bad[1, 2] = 7
        count_table(states, bad, None, S, A)


def test_sum_of_step_log_likelihoods_equals_the_count_log_likelihood(small):
    mdp, solver, theta, _ = small
    rng = np.random.default_rng(2)
    states = rng.integers(0, mdp.num_states, (3, 10))
    actions = rng.integers(0, mdp.num_actions, (3, 10))
    mask = np.arange(10)[None, :] < np.array([[10], [6], [3]])
    log_pi, V = log_policy(solver, theta)
    steps = step_log_likelihoods(log_pi, states, actions, mask=mask)  # (N, T, K)
    assert steps.shape == (3, 10, 2)
    assert np.all(np.asarray(steps)[~mask] == 0.0)
    for k in range(2):
        np.testing.assert_allclose(steps[..., k], np.where(mask, np.asarray(log_pi)[k][states, actions], 0.0))
    counts = count_table(states, actions, None, mdp.num_states, mdp.num_actions, mask=mask)
    np.testing.assert_allclose(steps.sum((0, 1)), count_log_likelihood(solver, theta, counts), rtol=1e-12)


def test_gradient_equals_central_finite_differences(small):
    _, solver, theta, counts = small
    ll, grad, _ = count_log_likelihood_and_grad(solver, theta, counts)
    eps = 1e-5
    fd = np.zeros_like(theta)
    for k in range(theta.shape[0]):
        for d in range(theta.shape[1]):
            pair = theta[k] + eps * np.outer([1.0, -1.0], np.eye(theta.shape[1])[d])  # both sides at once
            up, down = np.asarray(count_log_likelihood(solver, pair, counts[k]))
            fd[k, d] = (up - down) / (2 * eps)
    np.testing.assert_allclose(grad, fd, rtol=1e-7, atol=1e-7 * np.abs(fd).max())
    np.testing.assert_allclose(ll, count_log_likelihood(solver, theta, counts), rtol=1e-12)


def test_implicit_gradient_equals_differentiating_an_unrolled_loop(small):
    mdp, solver, theta, counts = small
    P = jnp.asarray(mdp.dense_transitions())
    phi = jnp.asarray(mdp.features)
    gamma = mdp.discount

    def unrolled(t, c):
        r = phi @ t
        V = jax.lax.fori_loop(0, 800, lambda _, V: jax.nn.logsumexp(r + gamma * P @ V, axis=-1),
                              jnp.zeros(mdp.num_states))
        Q = r + gamma * P @ V
        return jnp.sum(c * jax.nn.log_softmax(Q, axis=-1))

    ref = jax.jit(jax.vmap(jax.grad(unrolled)))(jnp.asarray(theta), jnp.asarray(counts))
    _, grad, _ = count_log_likelihood_and_grad(solver, theta, counts)
    np.testing.assert_allclose(grad, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())


def test_forward_mode_equals_reverse_mode(small):
    """The implicit tangent solve makes forward mode work too (Fisher information, Hessians by
    forward over reverse): a directional derivative equals the gradient's projection."""
    _, solver, theta, counts = small
    direction = np.random.default_rng(3).normal(size=theta.shape)
    _, tangent = jax.jit(lambda t, v: jax.jvp(lambda t_: count_log_likelihood(solver, t_, counts), (t,), (v,)))(
        jnp.asarray(theta), jnp.asarray(direction))
    _, grad, _ = count_log_likelihood_and_grad(solver, theta, counts)
    np.testing.assert_allclose(tangent, np.sum(np.asarray(grad) * direction, -1), rtol=1e-9)


def test_fisher_information_of_a_logistic_policy():
    """One absorbing state, phi(s, a) = [a]: pi(1) = sigmoid(theta), Fisher = n p (1 - p)."""
    mdp = TabularMDP(successors=np.zeros((1, 2, 1), int), probs=np.ones((1, 2, 1)),
                     features=np.array([[[0.0], [1.0]]]), discount=0.9)
    theta = np.array([[0.7], [-2.0]])
    counts = np.array([[[3.0, 5.0]], [[1.0, 1.0]]])
    F = fisher_information(make_soft_solver(mdp, tol=1e-12), theta, counts)
    p = 1.0 / (1.0 + np.exp(-theta[:, 0]))
    np.testing.assert_allclose(F[:, 0, 0], counts.sum((1, 2)) * p * (1 - p), rtol=1e-9)


def test_fisher_information_matches_finite_differences_of_the_policy(small):
    """Several features (the tangent solves are batched over them): F = sum_s n_s
    Cov_pi[d log pi / d theta], with the Jacobian by central differences of the solved policy."""
    mdp, solver, theta, counts = small
    F = np.asarray(fisher_information(solver, theta, counts))
    h, D = 1e-5, mdp.num_features
    for k in range(len(theta)):
        pi = np.exp(np.asarray(log_policy(solver, theta[k])[0]))
        J = np.stack([(np.asarray(log_policy(solver, theta[k] + h * e)[0]) -
                       np.asarray(log_policy(solver, theta[k] - h * e)[0])) / (2 * h) for e in np.eye(D)], -1)
        centred = J - np.einsum("sa,sad->sd", pi, J)[:, None, :]
        expected = np.einsum("s,sa,sad,sae->de", counts[k].sum(-1), pi, centred, centred)
        np.testing.assert_allclose(F[k], expected, rtol=1e-6, atol=1e-8)
    # at values already solved for (``solved``: an IRL fit's), no solve, the same information
    # and policy; at values of other weights, not (checked to fail with the tangents' policy
    # taken from the warm start instead of the backup)
    log_pi, V = log_policy(solver, theta)
    np.testing.assert_allclose(fisher_information(solver, theta, counts, V, solved=True), F, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(log_policy(solver, theta, V, solved=True)[0], log_pi, atol=1e-11)
    assert "while" not in str(jax.make_jaxpr(lambda t, v: log_policy(solver, t, v, solved=True)[0])(theta, V))
    _, V_other = log_policy(solver, 0.5 * theta)
    assert not np.allclose(fisher_information(solver, theta, counts, V_other, solved=True), F, rtol=1e-3)
    with pytest.raises(ValueError, match="solved=True needs"):
        fisher_information(solver, theta, counts, solved=True)


def test_irl_fit_reaches_a_stationary_point_inside_jit_and_warm_starts(small):
    mdp, solver, _, counts = small
    K, D = len(counts), mdp.num_features
    fit = jax.jit(lambda c, t0, v0: fit_reward(solver, c, t0, v0, 3.0, 40))
    theta, ll, V, _, evals = fit(jnp.asarray(counts), jnp.zeros((K, D)), jnp.zeros((K, mdp.num_states)))
    _, grad, _ = count_log_likelihood_and_grad(solver, theta, counts)
    _, grad0, _ = count_log_likelihood_and_grad(solver, np.zeros_like(theta), counts)
    # the log-posterior's gradient vanishes to rounding (relative to where the fit started)
    assert np.abs(grad - theta / 9.0).max() < 1e-5 * np.abs(grad0).max()
    # warm-started at its own answer, a fit stays there
    again, _, _, _, evals_again = fit(jnp.asarray(counts), theta, V)
    np.testing.assert_allclose(again, theta, atol=1e-5)
    assert np.all(np.asarray(evals_again) <= np.asarray(evals))


def _rollout(mdp, policy, rng, N=16, T=200):
    s = rng.choice(mdp.num_states, size=N, p=mdp.initial)
    states, actions = np.zeros((N, T), int), np.zeros((N, T), int)
    for t in range(T):
        states[:, t], actions[:, t] = s, policy[s]
        s = mdp.sample_next(rng, s, policy[s])
    return states, actions


@pytest.mark.library_level
@pytest.mark.parametrize("name", ["highway", "quadcopter"])
def test_irl_recovers_each_skill_from_its_demonstrations(name):
    """16 x 200 steps of one expert: the fitted reward's optimal policy takes an optimal action of
    the expert's own reward on >= 95% of the visited states, and on held-out demonstrations its
    Boltzmann policy beats a uniform policy by a wide margin."""
    from npbrs.domains import get_domain

    dom = get_domain(name)
    mdp = dom.mdp
    q_expert = dom.expert_q()  # (3, S, A)
    policies = greedy_policy(q_expert)
    rng = np.random.default_rng(0)
    demos = [_rollout(mdp, policies[k], rng) for k in range(3)]
    held_out = [_rollout(mdp, policies[k], rng) for k in range(3)]
    counts = np.stack([np.asarray(count_table(s, a, None, mdp.num_states, mdp.num_actions)) for s, a in demos])
    solver = make_soft_solver(mdp)
    fit = irl_fit(solver, counts, num_steps=30)
    log_pi, _ = log_policy(solver, fit.theta)
    greedy = greedy_policy(log_pi)
    for k in range(3):
        visited = np.unique(demos[k][0])
        q = q_expert[k][visited]
        # actions that are optimal for the expert's reward (the expert breaks exact ties by index,
        # which no reward on these features can express)
        optimal = q >= q.max(-1, keepdims=True) - 1e-9 * np.abs(q_expert[k]).max()
        assert optimal[np.arange(len(visited)), greedy[k][visited]].mean() >= 0.95, (name, k)
        s, a = held_out[k]
        per_step = float(step_log_likelihoods(log_pi[k], s, a).mean())
        assert per_step > -np.log(mdp.num_actions) + 0.5, (name, k, per_step)


def test_bad_input_names_the_problem(small):
    mdp, solver, theta, counts = small
    with pytest.raises(ValueError, match="theta"):
        log_policy(solver, np.zeros(mdp.num_features + 1))
    bad = theta.copy()
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match=r"theta\[1, 2\] is not finite"):
        log_policy(solver, bad)
    with pytest.raises(ValueError, match="counts"):
        count_log_likelihood(solver, theta, counts[:, :3])
    with pytest.raises(ValueError, match="counts"):
        count_log_likelihood(solver, theta, -counts)
    with pytest.raises(ValueError, match="prior_scale"):
        irl_fit(solver, counts, prior_scale=0.0)
    with pytest.raises(ValueError, match="feature 1 of state 0, action 0 is not finite"):
        TabularMDP(successors=mdp.successors, probs=mdp.probs,
                   features=np.where(np.arange(4) == 1, np.nan, mdp.features))


def test_noisy_expert_likelihood_and_gradient(small):
    """epsilon-noisy Boltzmann policy: the count log-likelihood is the mixture's, computed by
    hand from the Boltzmann policy, and its gradient equals central finite differences."""
    from npbrs.models.reward.likelihood import noisy_log_policy

    _, solver, theta, counts = small
    eps_noise = 0.07
    A = counts.shape[-1]
    log_pi, _ = log_policy(solver, theta)
    by_hand = np.sum(counts * np.log((1 - eps_noise) * np.exp(np.asarray(log_pi)) + eps_noise / A), axis=(1, 2))
    ll, grad, _ = count_log_likelihood_and_grad(solver, theta, counts, None, eps_noise)
    np.testing.assert_allclose(np.asarray(ll), by_hand, rtol=1e-12)
    np.testing.assert_allclose(np.exp(np.asarray(noisy_log_policy(log_pi, eps_noise))).sum(-1), 1.0, rtol=1e-12)

    def ll_at(t):
        return float(count_log_likelihood_and_grad(solver, t[None], counts[k][None], None, eps_noise)[0][0])

    h = 1e-5
    for k in range(theta.shape[0]):
        fd = np.array([(ll_at(theta[k] + h * e) - ll_at(theta[k] - h * e)) / (2 * h) for e in np.eye(theta.shape[1])])
        np.testing.assert_allclose(np.asarray(grad[k]), fd, rtol=1e-6, atol=1e-7 * np.abs(fd).max())
    # epsilon = 0 is the Boltzmann policy itself
    ll0, g0, _ = count_log_likelihood_and_grad(solver, theta, counts, None, 0.0)
    ll_plain, g_plain, _ = count_log_likelihood_and_grad(solver, theta, counts)
    np.testing.assert_allclose(np.asarray(ll0), np.asarray(ll_plain), rtol=1e-14)


def test_a_warm_started_refit_with_much_data_improves_in_few_evaluations(small):
    """A refit started near its optimum (as the greedy and split-merge moves' refits are) with
    many steps of data: the first step (no curvature pairs yet) is as long as the prior's scale
    and overshoots by orders of magnitude; the line search's quadratic backtracking reaches the
    right length in a few trials (halving alone used 12 evaluations here, 23 on the highway's
    skills, spending every backtrack of a line search that then failed)."""
    mdp, solver, _, counts = small
    K, D = len(counts), mdp.num_features
    many = jnp.asarray(500.0 * counts)
    theta, _, V, _, _ = jax.jit(lambda c: fit_reward(solver, c, jnp.zeros((K, D)), jnp.zeros((K, mdp.num_states)),
                                                     10.0, 60))(many)
    start = theta + 0.02
    post = lambda t: log_posterior(solver, t, many, V, 10.0).log_density  # noqa: E731
    new, _, _, _, evals = jax.jit(lambda c, t, v: fit_reward(solver, c, t, v, 10.0, 3))(many, start, V)
    assert np.all(np.asarray(post(new)) > np.asarray(post(start)))
    assert np.all(np.asarray(evals) <= 9), evals  # 7 here; 12 with halving
