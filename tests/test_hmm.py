import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats
from scipy.special import logsumexp

from npbrs.models.hmm import (NEG_LOG, backward_sample, batch_backward_sample, batch_forward_filter, batch_smooth, path_log_prob,
                              batch_viterbi, forward_filter, initial_counts, smooth, transition_counts, viterbi)


def random_hmm(seed, K, T):
    rng = np.random.default_rng(seed)
    init = rng.dirichlet(np.ones(K))
    trans = rng.dirichlet(np.ones(K), size=K)
    log_lik = rng.normal(scale=1.5, size=(T, K))
    return np.log(init), np.log(trans), log_lik


def path_table(log_init, log_trans, log_lik):
    """Every path of the HMM and its joint log-probability log p(z, x)."""
    T, K = log_lik.shape
    paths = np.array(list(itertools.product(range(K), repeat=T)))
    logp = log_init[paths[:, 0]] + log_lik[np.arange(T), paths].sum(1)
    logp += log_trans[paths[:, :-1], paths[:, 1:]].sum(1)
    return paths, logp


CASES = [(seed, K, T) for seed, (K, T) in enumerate([(2, 1), (2, 4), (2, 6), (3, 3), (3, 5)])]


@pytest.mark.parametrize("seed, K, T", CASES)
def test_the_filter_equals_brute_force_enumeration(seed, K, T):
    log_init, log_trans, log_lik = random_hmm(seed, K, T)
    log_marginal, log_alpha = jax.jit(forward_filter)(log_init, log_trans, log_lik)
    paths, logp = path_table(log_init, log_trans, log_lik)
    np.testing.assert_allclose(log_marginal, logsumexp(logp), rtol=1e-12)
    for t in range(T):  # filtered p(z_t | x_1..t): enumerate the prefix alone
        prefix_paths, prefix_logp = path_table(log_init, log_trans, log_lik[:t + 1])
        expected = [logsumexp(prefix_logp[prefix_paths[:, t] == k]) for k in range(K)]
        np.testing.assert_allclose(log_alpha[t], np.array(expected) - logsumexp(prefix_logp), atol=1e-12)


@pytest.mark.parametrize("seed, K, T", CASES)
def test_viterbi_equals_the_brute_force_argmax_path(seed, K, T):
    log_init, log_trans, log_lik = random_hmm(seed, K, T)
    z, log_prob = jax.jit(viterbi)(log_init, log_trans, log_lik)
    paths, logp = path_table(log_init, log_trans, log_lik)
    np.testing.assert_array_equal(z, paths[np.argmax(logp)])
    np.testing.assert_allclose(log_prob, logp.max(), rtol=1e-12)


@pytest.mark.parametrize("seed, K, T", CASES)
def test_the_smoother_equals_brute_force_posterior_marginals(seed, K, T):
    log_init, log_trans, log_lik = random_hmm(seed, K, T)
    _, log_alpha = forward_filter(log_init, log_trans, log_lik)
    post = np.exp(jax.jit(smooth)(log_trans, log_alpha))
    paths, logp = path_table(log_init, log_trans, log_lik)
    weights = np.exp(logp - logsumexp(logp))
    expected = np.array([[weights[paths[:, t] == k].sum() for k in range(K)] for t in range(T)])
    np.testing.assert_allclose(post, expected, atol=1e-12)


def test_the_smoother_skips_padding_and_inactive_skills_and_batches():
    log_init, log_trans, log_lik = random_hmm(7, 3, 5)
    active = np.array([True, False, True])
    _, log_alpha = forward_filter(log_init, log_trans, log_lik, active=active)
    alone = np.exp(smooth(log_trans, log_alpha, active=active))
    assert np.all(alone[:, 1] == 0)
    # the same trajectory padded to 8 steps, beside an unpadded random one, in one batch
    pad = np.concatenate([log_lik, np.full((3, 3), np.nan)])
    other = np.random.default_rng(1).normal(size=(8, 3))
    lls, mask = np.stack([pad, other]), np.array([[True] * 5 + [False] * 3, [True] * 8])
    act = np.stack([active, np.ones(3, bool)])
    _, alphas = batch_forward_filter(log_init, log_trans, lls, mask, act)
    both = batch_smooth(log_trans, alphas, mask, act)
    np.testing.assert_allclose(np.exp(both[0, :5]), alone, atol=1e-12)
    assert np.all(np.asarray(both[0, 5:]) == NEG_LOG)
    np.testing.assert_allclose(np.exp(both[1]).sum(-1), 1.0, rtol=1e-12)


def path_frequencies(z, K):
    T = z.shape[1]
    codes = np.asarray(z) @ (K ** np.arange(T)[::-1])
    return np.bincount(codes, minlength=K ** T)


@pytest.mark.parametrize("seed, K, T", [(10, 2, 4), (11, 3, 3)])
def test_backward_sampler_draws_paths_with_their_posterior_probabilities(seed, K, T):
    log_init, log_trans, log_lik = random_hmm(seed, K, T)
    _, log_alpha = forward_filter(log_init, log_trans, log_lik)
    n = 20000
    keys = jax.random.split(jax.random.key(seed), n)
    z = jax.jit(jax.vmap(backward_sample, in_axes=(0, None, None)))(keys, log_trans, log_alpha)
    _, logp = path_table(log_init, log_trans, log_lik)
    posterior = np.exp(logp - logsumexp(logp))  # paths in the same lexicographic order
    counts = path_frequencies(z, K)
    assert stats.chisquare(counts, n * posterior).pvalue > 1e-3
    # and every path within 4.5 binomial standard errors
    assert np.all(np.abs(counts / n - posterior) <= 4.5 * np.sqrt(posterior * (1 - posterior) / n) + 1e-12)


def test_padding_at_the_end_changes_nothing():
    log_init, log_trans, log_lik = random_hmm(20, 3, 5)
    garbage = np.array([[np.nan, -np.inf, 1e6]] * 4)
    padded = np.concatenate([log_lik, garbage])
    mask = np.arange(9) < 5
    m0, a0 = forward_filter(log_init, log_trans, log_lik)
    m1, a1 = forward_filter(log_init, log_trans, padded, mask)
    np.testing.assert_allclose(m1, m0, rtol=1e-14)
    np.testing.assert_allclose(a1[:5], a0, rtol=1e-14)
    np.testing.assert_allclose(a1[5:], np.repeat(a0[-1:], 4, 0), rtol=1e-14)  # padding repeats the last

    z0, p0 = viterbi(log_init, log_trans, log_lik)
    z1, p1 = viterbi(log_init, log_trans, padded, mask)
    np.testing.assert_array_equal(z1, np.concatenate([z0, [-1] * 4]))
    np.testing.assert_allclose(p1, p0, rtol=1e-14)

    key = jax.random.key(3)
    s0 = backward_sample(key, log_trans, a0)
    s1 = backward_sample(key, log_trans, a1, mask)
    np.testing.assert_array_equal(s1, np.concatenate([s0, [-1] * 4]))


def test_an_empty_trajectory_has_likelihood_one():
    log_init, log_trans, log_lik = random_hmm(21, 2, 3)
    mask = np.zeros(3, bool)
    m, _ = forward_filter(log_init, log_trans, log_lik, mask)
    z, p = viterbi(log_init, log_trans, log_lik, mask)
    s = backward_sample(jax.random.key(0), log_trans, forward_filter(log_init, log_trans, log_lik, mask)[1], mask)
    assert float(m) == 0.0 and float(p) == 0.0
    np.testing.assert_array_equal(z, [-1, -1, -1])
    np.testing.assert_array_equal(s, [-1, -1, -1])


def test_inactive_skills_have_zero_probability_and_are_never_sampled():
    K, T = 4, 5
    rng = np.random.default_rng(30)
    log_eta = np.log(rng.gamma(1.0, size=(K, K)))  # unnormalised weights, as the sampler keeps them
    log_lik = rng.normal(size=(T, K))
    log_lik[:, 1] = 50.0  # the inactive skill explains the data best
    active = np.array([True, False, True, True])

    m, log_alpha = forward_filter(np.zeros(K), log_eta, log_lik, active=active)
    assert np.all(np.exp(log_alpha[:, 1]) == 0.0)
    # the same as the HMM on the active skills alone, normalised and starting uniformly
    sub = np.flatnonzero(active)
    sub_trans = log_eta[np.ix_(sub, sub)]
    sub_trans = sub_trans - logsumexp(sub_trans, axis=1, keepdims=True)
    _, logp = path_table(np.full(3, -np.log(3)), sub_trans, log_lik[:, sub])
    np.testing.assert_allclose(m, logsumexp(logp), rtol=1e-12)

    z, _ = viterbi(np.zeros(K), log_eta, log_lik, active=active)
    assert 1 not in np.asarray(z)
    keys = jax.random.split(jax.random.key(0), 2000)
    draws = jax.vmap(backward_sample, in_axes=(0, None, None, None, None))(keys, log_eta, log_alpha, None, active)
    assert 1 not in np.asarray(draws)


def test_one_active_skill_gives_no_nan_in_values_or_gradients():
    K, T = 3, 6
    rng = np.random.default_rng(31)
    log_lik = rng.normal(size=(T, K))
    log_trans = np.full((K, K), -np.inf)  # log 0 everywhere but the one skill's self-loop
    log_trans[2, 2] = 0.0
    log_init = np.array([-np.inf, -np.inf, 0.0])
    active = np.array([False, False, True])

    m, log_alpha = forward_filter(log_init, log_trans, log_lik, active=active)
    np.testing.assert_allclose(m, log_lik[:, 2].sum(), rtol=1e-12)
    assert np.all(np.isfinite(log_alpha))
    np.testing.assert_allclose(np.exp(log_alpha), np.tile([0.0, 0.0, 1.0], (T, 1)))
    grad = jax.grad(lambda ll: forward_filter(log_init, log_trans, ll, active=active)[0])(log_lik)
    np.testing.assert_allclose(grad, np.tile([0.0, 0.0, 1.0], (T, 1)))
    z, p = viterbi(log_init, log_trans, log_lik, active=active)
    np.testing.assert_array_equal(z, [2] * T)
    np.testing.assert_allclose(p, m, rtol=1e-12)
    np.testing.assert_array_equal(backward_sample(jax.random.key(1), log_trans, log_alpha, active=active), [2] * T)


def test_the_filter_gradient_matches_brute_force():
    log_init, log_trans, log_lik = random_hmm(40, 3, 4)
    paths, log_prior = path_table(log_init, log_trans, np.zeros_like(log_lik))

    def brute(ll):
        return jax.nn.logsumexp(log_prior + ll[np.arange(4), paths].sum(1))

    grad = jax.grad(lambda ll: forward_filter(log_init, log_trans, ll)[0])(log_lik)
    np.testing.assert_allclose(grad, jax.grad(brute)(jnp.asarray(log_lik)), atol=1e-12)


def test_batched_versions_equal_one_trajectory_at_a_time():
    N, K, T = 4, 3, 6
    rng = np.random.default_rng(50)
    log_init = np.log(rng.dirichlet(np.ones(K)))  # shared
    log_trans = np.log(rng.dirichlet(np.ones(K), size=(N, K)))  # per trajectory
    log_lik = rng.normal(size=(N, T, K))
    lengths = np.array([6, 2, 4, 5])
    mask = np.arange(T)[None] < lengths[:, None]
    active = np.array([[1, 1, 1], [1, 0, 1], [0, 1, 0], [1, 1, 0]], bool)

    m, a = jax.jit(batch_forward_filter)(log_init, log_trans, log_lik, mask, active)
    z, p = jax.jit(batch_viterbi)(log_init, log_trans, log_lik, mask, active)
    key = jax.random.key(5)
    s = jax.jit(batch_backward_sample)(key, log_trans, a, mask, active)
    keys = jax.random.split(key, N)
    for i in range(N):
        mi, ai = forward_filter(log_init, log_trans[i], log_lik[i], mask[i], active[i])
        zi, pi = viterbi(log_init, log_trans[i], log_lik[i], mask[i], active[i])
        np.testing.assert_allclose(m[i], mi, rtol=1e-13)
        np.testing.assert_allclose(a[i], ai, rtol=1e-13)
        np.testing.assert_array_equal(z[i], zi)
        np.testing.assert_allclose(p[i], pi, rtol=1e-13)
        np.testing.assert_array_equal(s[i], backward_sample(keys[i], log_trans[i], ai, mask[i], active[i]))
        assert np.all(np.isin(np.asarray(s[i])[mask[i]], np.flatnonzero(active[i])))
        assert np.all(np.asarray(s[i])[~mask[i]] == -1)


def test_transition_and_initial_counts():
    z = np.array([[0, 0, 1, 2, 2, -1], [2, 1, 1, 0, 0, 0]])
    mask = np.array([[1, 1, 1, 1, 1, 0], [1, 1, 1, 1, 0, 0]], bool)
    n = transition_counts(z, mask, 3)
    np.testing.assert_array_equal(n[0], [[1, 1, 0], [0, 0, 1], [0, 0, 1]])
    np.testing.assert_array_equal(n[1], [[0, 0, 0], [1, 1, 0], [0, 1, 0]])
    np.testing.assert_array_equal(initial_counts(z, mask, 3), [[1, 0, 0], [0, 0, 1]])


@pytest.mark.parametrize("case", ["rare_exits", "rarely_entered", "masked"])
def test_the_filter_stays_exact_with_rare_transitions_and_peaked_likelihoods(case):
    """The recursion runs in probability space: transitions of weight e^-600, a skill entered
    from anywhere with weight e^-750 only (below the smallest float64: its column's scale must
    move into the likelihoods), steps only one skill explains (log-likelihoods down to -900),
    and padding at the start and in the middle must still give the log-space recursion's
    marginal and filtered probabilities (a NumPy reference)."""
    from scipy.special import logsumexp

    rng = np.random.default_rng(5)
    T, K = 60, 4
    log_trans = rng.normal(size=(K, K))
    log_trans[0, 1:] = -600.0  # leaving skill 0 is nearly impossible, but the data force it
    log_trans[2, 3] = -400.0
    log_lik = -rng.gamma(2.0, size=(T, K))
    log_lik[:20, 1:] -= 500.0  # skill 0 alone explains the first 20 steps
    log_lik[20:, 0] -= 500.0   # then skill 0 cannot explain a step
    log_init = np.log(rng.dirichlet(np.ones(K)))
    mask = np.ones(T, bool)
    if case == "rarely_entered":
        log_trans[:, 3] = -750.0  # skill 3 is entered (or kept) with weight e^-750 ...
        log_lik[40:, :3] -= 900.0  # ... but only it explains the last 20 steps
    if case == "masked":
        mask[:3] = False
        mask[30:33] = False
    lt = log_trans - logsumexp(log_trans, axis=1, keepdims=True)
    pred, total, alphas = log_init - logsumexp(log_init), 0.0, []
    filt = pred
    for t in range(T):
        if not mask[t]:
            alphas.append(filt)
            continue
        joint = pred + log_lik[t]
        c = logsumexp(joint)
        total += c
        filt = joint - c
        alphas.append(filt)
        pred = logsumexp(filt[:, None] + lt, axis=0)
    log_marginal, log_alpha = forward_filter(log_init, log_trans, log_lik, mask)
    np.testing.assert_allclose(float(log_marginal), total, rtol=1e-12)
    np.testing.assert_allclose(np.exp(log_alpha), np.exp(np.array(alphas)), atol=1e-12)


def test_the_filter_stays_finite_where_the_data_need_a_transition_below_the_smallest_float():
    """Leaving skill 0 has weight e^-760 (below the smallest float64, about e^-745), and from
    step 20 on skill 0 explains a step e^-800 worse than the others: every term of the step's
    normaliser underflows in probability space. The filter floors predictions at e^-700 (the
    log-space recursion it replaced, at e^-708), so the marginal stays finite, is at least the
    exact one and at most the floor's difference (60 nats, and a few of normalisation) above
    it; the filtered probabilities are the exact ones before the switch, and their likeliest
    skill is the exact one everywhere. (Without the floor the marginal is NaN.)"""
    from scipy.special import logsumexp

    rng = np.random.default_rng(6)
    T, K = 40, 3
    log_trans = rng.normal(size=(K, K))
    log_trans[0, 1:] = -760.0
    log_lik = -rng.gamma(2.0, size=(T, K))
    log_lik[:20, 1:] -= 500.0
    log_lik[20:, 0] -= 800.0
    lt = log_trans - logsumexp(log_trans, axis=1, keepdims=True)
    pred, total, alphas = np.log(np.full(K, 1.0 / K)), 0.0, []
    for t in range(T):
        joint = pred + log_lik[t]
        total += logsumexp(joint)
        alphas.append(joint - logsumexp(joint))
        pred = logsumexp(alphas[-1][:, None] + lt, axis=0)
    log_marginal, log_alpha = forward_filter(np.zeros(K), log_trans, log_lik)
    assert np.all(np.isfinite(np.asarray(log_alpha))) and np.isfinite(float(log_marginal))
    assert total <= float(log_marginal) <= total + 65.0
    np.testing.assert_array_equal(np.argmax(log_alpha, 1), np.argmax(np.array(alphas), 1))
    np.testing.assert_allclose(np.exp(log_alpha[:20]), np.exp(np.array(alphas[:20])), atol=1e-12)


# ----------------------------------------------------------------------------- gated transitions
def gated_hmm(seed, K, T, zero_diagonal=True):
    """An HMM whose skills end with a probability that changes from step to step: gate (T, K),
    the switch matrix with an empty diagonal (a skill that ends is followed by another)."""
    log_init, log_trans, log_lik = random_hmm(seed, K, T)
    rng = np.random.default_rng(100 + seed)
    if zero_diagonal:
        trans = np.exp(log_trans) * (1 - np.eye(K))
        log_trans = np.log(trans / trans.sum(1, keepdims=True) + 1e-300)
    gate = rng.uniform(0.02, 0.98, size=(T, K))
    gate[rng.uniform(size=(T, K)) < 0.2] = 1.0  # the skill surely ends there
    return log_init, log_trans, log_lik, gate


def gated_path_table(log_init, log_trans, log_lik, gate, active=None):
    """Every path and its log p(z, x) with A_t = (1 - g_t) I + g_t pi, dense, step by step."""
    T, K = log_lik.shape
    act = np.ones(K, bool) if active is None else np.asarray(active)
    pi = np.exp(log_trans) * act[None, :]
    pi = pi / pi.sum(1, keepdims=True)
    p0 = np.exp(log_init) * act
    p0 = p0 / p0.sum()
    paths = np.array([p for p in itertools.product(range(K), repeat=T) if all(act[list(p)])])
    with np.errstate(divide="ignore"):
        logp = np.log(p0[paths[:, 0]]) + log_lik[np.arange(T), paths].sum(1)
        for t in range(1, T):
            A = (1 - gate[t])[:, None] * np.eye(K) + gate[t][:, None] * pi
            logp += np.log(A[paths[:, t - 1], paths[:, t]])
    return paths, logp


GATED = [(seed, K, T) for seed, (K, T) in enumerate([(2, 1), (2, 5), (3, 4), (3, 5)], start=40)]


@pytest.mark.parametrize("zero_diagonal", [True, False], ids=["switches", "with_redraws"])
@pytest.mark.parametrize("seed, K, T", GATED)
def test_gated_filter_smoother_viterbi_and_path_probability_equal_enumeration(seed, K, T, zero_diagonal):
    # (with weight on the switch matrix's diagonal, a step's stay and "ends, then draws itself
    # again" add up: the case where the gated matrix's diagonal has two terms)
    log_init, log_trans, log_lik, gate = gated_hmm(seed, K, T, zero_diagonal=zero_diagonal)
    paths, logp = gated_path_table(log_init, log_trans, log_lik, gate)
    total = logsumexp(logp)
    log_marginal, log_alpha = jax.jit(forward_filter)(log_init, log_trans, log_lik, gate=gate)
    np.testing.assert_allclose(log_marginal, total, rtol=1e-12)
    for t in range(T):
        prefix_paths, prefix_logp = gated_path_table(log_init, log_trans, log_lik[:t + 1], gate[:t + 1])
        expected = [logsumexp(prefix_logp[prefix_paths[:, t] == k]) for k in range(K)]
        np.testing.assert_allclose(log_alpha[t], np.array(expected) - logsumexp(prefix_logp), atol=1e-12)
    post = np.exp(jax.jit(smooth)(log_trans, log_alpha, gate=gate))
    weights = np.exp(logp - total)
    expected = np.array([[weights[paths[:, t] == k].sum() for k in range(K)] for t in range(T)])
    np.testing.assert_allclose(post, expected, atol=1e-12)
    z, best = jax.jit(viterbi)(log_init, log_trans, log_lik, gate=gate)
    np.testing.assert_array_equal(z, paths[np.argmax(logp)])
    np.testing.assert_allclose(best, logp.max(), rtol=1e-12)
    for j in np.random.default_rng(seed).choice(len(paths), size=min(6, len(paths)), replace=False):
        np.testing.assert_allclose(path_log_prob(log_init, log_trans, log_lik, paths[j], gate=gate), logp[j],
                                   rtol=1e-12)


@pytest.mark.parametrize("seed, K, T", [(50, 2, 4), (51, 3, 3)])
def test_gated_backward_sampler_draws_paths_with_their_posterior_probabilities(seed, K, T):
    # a switch matrix with weight on its diagonal too: the gate's "ends, then draws itself again"
    log_init, log_trans, log_lik, gate = gated_hmm(seed, K, T, zero_diagonal=False)
    _, log_alpha = forward_filter(log_init, log_trans, log_lik, gate=gate)
    n = 20000
    keys = jax.random.split(jax.random.key(seed), n)
    z = jax.jit(jax.vmap(lambda k: backward_sample(k, log_trans, log_alpha, gate=gate)))(keys)
    paths, logp = gated_path_table(log_init, log_trans, log_lik, gate)
    posterior = np.exp(logp - logsumexp(logp))
    counts = path_frequencies(z, K)
    assert stats.chisquare(counts, n * posterior).pvalue > 1e-3
    assert np.all(np.abs(counts / n - posterior) <= 4.5 * np.sqrt(posterior * (1 - posterior) / n) + 1e-12)


def test_gated_filters_skip_padding_inactive_skills_and_batch():
    log_init, log_trans, log_lik, gate = gated_hmm(60, 3, 5)
    active = np.array([True, False, True])
    paths, logp = gated_path_table(log_init, log_trans, log_lik, gate, active)
    m, a = forward_filter(log_init, log_trans, log_lik, active=active, gate=gate)
    np.testing.assert_allclose(m, logsumexp(logp), rtol=1e-12)
    # padded to 8 steps (NaN likelihoods and gates there), beside another trajectory, in a batch
    lls = np.stack([np.concatenate([log_lik, np.full((3, 3), np.nan)]), np.random.default_rng(2).normal(size=(8, 3))])
    gates = np.stack([np.concatenate([gate, np.full((3, 3), np.nan)]), np.full((8, 3), 0.3)])
    mask = np.array([[True] * 5 + [False] * 3, [True] * 8])
    act = np.stack([active, np.ones(3, bool)])
    ms, alphas = batch_forward_filter(log_init, log_trans, lls, mask, act, gates)
    np.testing.assert_allclose(ms[0], m, rtol=1e-12)
    np.testing.assert_allclose(alphas[0, :5], a, atol=1e-12)
    post = batch_smooth(log_trans, alphas, mask, act, gates)
    np.testing.assert_allclose(np.exp(post[0, :5]), np.exp(smooth(log_trans, a, active=active, gate=gate)), atol=1e-12)
    weights = np.exp(logp - logsumexp(logp))  # the smoother's marginals by enumeration
    expected = np.array([[weights[paths[:, t] == k].sum() for k in range(3)] for t in range(5)])
    np.testing.assert_allclose(np.exp(post[0, :5]), expected, atol=1e-12)
    zs, ps = batch_viterbi(log_init, log_trans, lls, mask, act, gates)
    np.testing.assert_array_equal(zs[0], np.concatenate([paths[np.argmax(logp)], [-1] * 3]))
    draws = batch_backward_sample(jax.random.key(0), log_trans, alphas, mask, act, gates)
    assert np.all(np.asarray(draws[0, 5:]) == -1) and not np.any(np.asarray(draws[0, :5]) == 1)
    # a gate of ones everywhere is the ungated chain
    ones = np.ones_like(gate)
    np.testing.assert_allclose(forward_filter(log_init, log_trans, log_lik, gate=ones)[0],
                               forward_filter(log_init, log_trans, log_lik)[0], rtol=1e-13)


def test_the_gated_filters_gradients_are_the_posterior_marginals_and_finite_differences():
    """d log p(x) / d log_lik[t, k] is p(z_t = k | x) (Fisher's identity: what a move that
    sums the skill sequences out differentiates), with state-dependent ends, a padded step, an
    inactive skill and a trajectory whose first step is not its first row; d / d gate matches
    central differences; all finite at each trajectory's first step (its unused prediction there,
    floored at exp(-700), must not be divided by its sum inside a ``where``: the zero cotangent
    times 1 / exp(-700) overflows)."""
    log_init, log_trans, log_lik, gate = gated_hmm(61, 3, 5, zero_diagonal=False)
    active = np.array([True, False, True])
    lls = np.stack([np.concatenate([log_lik, np.zeros((2, 3))]), np.concatenate([np.zeros((2, 3)), log_lik])])
    gates = np.stack([np.concatenate([gate, np.full((2, 3), 0.5)]), np.concatenate([np.full((2, 3), 0.5), gate])])
    mask = np.array([[True] * 5 + [False] * 2, [False] * 2 + [True] * 5])

    def total(ll, g):
        return jnp.sum(batch_forward_filter(log_init, log_trans, ll, mask, active, g)[0])

    g_ll, g_gate = jax.grad(total, argnums=(0, 1))(lls, gates)
    assert np.all(np.isfinite(g_ll)) and np.all(np.isfinite(g_gate))
    paths, logp = gated_path_table(log_init, log_trans, log_lik, gate, active)
    weights = np.exp(logp - logsumexp(logp))
    expected = np.array([[weights[paths[:, t] == k].sum() for k in range(3)] for t in range(5)])
    np.testing.assert_allclose(g_ll[0, :5], expected, atol=1e-12)
    np.testing.assert_allclose(g_ll[1, 2:], expected, atol=1e-12)
    assert np.all(g_ll[0, 5:] == 0) and np.all(g_ll[1, :2] == 0)  # padding
    h = 1e-6
    for i, t, k in [(0, 1, 0), (0, 4, 2), (1, 3, 2), (1, 6, 0)]:
        up, down = gates.copy(), gates.copy()
        up[i, t, k] += h
        down[i, t, k] -= h
        np.testing.assert_allclose(g_gate[i, t, k], (total(lls, up) - total(lls, down)) / (2 * h), rtol=1e-6, atol=1e-9)


def test_the_backward_samplers_inverse_transform_gives_each_index_its_probability():
    """Each step's draw (one uniform by inverse transform): over a grid of n uniforms the share
    of each index is its probability to within 1/n, an index of zero weight (an inactive skill,
    NEG_LOG, or -inf) is never drawn, not even at u = 0, and u next to 1 draws a real index."""
    from npbrs.models.hmm import inverse_transform

    logits = jnp.array([NEG_LOG, np.log(0.2), -np.inf, np.log(0.5), np.log(0.3), NEG_LOG]) + 3.0
    n = 20_000
    u = (np.arange(n) + 0.5) / n
    draws = np.asarray(jax.vmap(inverse_transform, in_axes=(None, 0))(logits, u))
    share = np.bincount(draws, minlength=6) / n
    np.testing.assert_allclose(share, [0, 0.2, 0, 0.5, 0.3, 0], atol=1.5 / n)
    # the first and the last index with weight at the ends of [0, 1); past them (rounding) the heaviest
    assert int(inverse_transform(logits, 0.0)) == 1
    assert int(inverse_transform(logits, 1.0 - 2.0 ** -53)) == 4
    assert int(inverse_transform(logits, 1.0)) == 3
