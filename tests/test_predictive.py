"""Held-out log-likelihood under a fit: the posterior predictive and the leave-one-out values
against brute-force enumeration of nonempty skill sets and skill sequences (transition weights
integrated exactly, Dirichlet-multinomial), and a true model scoring above a wrong one."""

import itertools

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import logsumexp

from npbrs.domains import Demonstrations, TabularMDP
from npbrs.inference.driver.fit import resolve_config
from npbrs.inference.driver.results import FitResult
from npbrs.models.bphmm import collapsed_sequence_log_prob

S, A, K = 2, 2, 2
ALPHA, KAPPA, GAMMA = 1.5, 2.0, 0.7


def two_state_mdp():  # (the dynamics do not enter the policy emission)
    return TabularMDP.from_dense(np.ones((S, A, S)) / S)


def policy_run(policies, features):
    """A FitResult of the policy emission with the given draws: policies (C, D, K, S, A),
    features (C, D, N, K)."""
    C, D = policies.shape[:2]
    cfg = resolve_config(None, emission="policy", max_skills=K, alpha=ALPHA, kappa=KAPPA, gamma=GAMMA)
    zeros = np.zeros((C, D))
    return FitResult(segmentation=[], num_skills=K, skill_params={}, skill_slots=np.arange(K), best_chain=0,
                     best_log_joint=0.0, stats={"log_joint": zeros, "num_skills": zeros, "num_switches": zeros},
                     samples={"policy": policies, "features": features, "skill_steps": np.ones((C, D, K))},
                     config=cfg.to_dict())


def exact_draw(policy, p_on, states, actions):
    """One draw by enumeration: (log sum_{f nonempty} p(f) sum_z p(z | f) prod_t pi_{z_t}(a_t |
    s_t), log P(f nonempty)), f_k ~ Bernoulli(p_on[k]) (a trajectory with steps uses a skill)."""
    T = len(states)
    log_emit = np.log(policy[:, states, actions]).T  # (T, K)
    zs = np.array(list(itertools.product(range(K), repeat=T)))
    terms = []
    for f in itertools.product([0, 1], repeat=K):
        if not any(f):
            continue
        log_pf = np.sum(np.where(np.array(f) == 1, np.log(p_on), np.log1p(-p_on)))
        lz = np.asarray(collapsed_sequence_log_prob(jnp.asarray(zs), jnp.ones(zs.shape, bool),
                                                    jnp.tile(jnp.asarray(f, jnp.float64), (len(zs), 1)),
                                                    KAPPA, GAMMA))
        terms.append(log_pf + logsumexp(lz + log_emit[np.arange(T), zs].sum(1)))
    return logsumexp(terms), np.log1p(-np.prod(1 - p_on))


def exact_log_predictive(policies, features, states, actions):
    """log p(x | fit, x has steps) = log mean_s sum_{f nonempty} p(f | F_s) sum_z p(z | f) prod_t
    pi_{z_t}(a_t | s_t) - log mean_s P(f nonempty | F_s), by enumeration."""
    C, D, N, _ = features.shape
    per_draw, nonempty = [], []
    for c in range(C):
        for d in range(D):
            m = features[c, d].sum(0)
            lp, ln = exact_draw(policies[c, d], (m + ALPHA / K) / (N + 1 + ALPHA / K), states, actions)
            per_draw.append(lp)
            nonempty.append(ln)
    return logsumexp(per_draw) - logsumexp(nonempty)


def draws(seed):
    rng = np.random.default_rng(seed)
    policies = rng.dirichlet(np.ones(A), size=(1, 3, K, S))  # (C, D, K, S, A)
    features = (rng.random((1, 3, 4, K)) < 0.6).astype(np.float64)
    features[..., 0] = 1.0
    return policies, features


def test_log_predictive_equals_enumeration_within_its_standard_error():
    policies, features = draws(0)
    run = policy_run(policies, features)
    demos = Demonstrations([np.array([0, 1, 1, 0, 1]), np.array([1, 0, 0])],
                           [np.array([1, 1, 0, 0, 1]), np.array([0, 0, 1])])
    out = run.log_predictive(two_state_mdp(), demos, num_samples=4000, seed=1)
    for i in range(2):
        exact = exact_log_predictive(policies, features, demos.states[i], demos.actions[i])
        se = out.per_trajectory_se[i]
        assert 0 < se < 0.05, se
        assert abs(out.per_trajectory[i] - exact) < 4 * se + 1e-3, (i, out.per_trajectory[i], exact, se)
    assert out.num_steps == 8 and out.per_step == pytest.approx(out.per_trajectory.sum() / 8)
    again = run.log_predictive(two_state_mdp(), demos, num_samples=4000, seed=1)
    np.testing.assert_array_equal(again.per_trajectory, out.per_trajectory)  # the same seed, the same answer


def test_pointwise_log_likelihood_equals_enumeration_within_its_standard_error():
    """The leave-one-out inputs of ``az.loo``: trajectory i's value under draw s, log p(x_i |
    theta_s, F_s without row i, x_i has steps), against enumeration of its skill set (the
    predictive (m_-ik + alpha/K) / (N + alpha/K) of the other rows, over the nonempty sets) and
    skill sequence (transition weights integrated exactly): within 4 Monte Carlo standard errors
    (the delta method on the same samples' second moment) in every (draw, trajectory). Leaving
    the empty set out without renormalising put every value log P(nonempty) lower (0.05 to 0.31
    nats here, 8 to 30 standard errors)."""
    from npbrs.inference.analysis.predictive import draw_moments

    policies, _ = draws(4)
    features = np.array([[[1, 0], [0, 1], [1, 0], [0, 1]], [[1, 1], [1, 0], [0, 1], [1, 0]],
                         [[1, 1], [1, 1], [1, 1], [1, 0]]], np.float64)[None]  # (1, 3, N, K)
    demos = Demonstrations([np.array([0, 1, 1, 0]), np.array([1, 0, 0]), np.array([0, 0, 1, 1, 0]),
                            np.array([1, 1, 0])],
                           [np.array([1, 1, 0, 0]), np.array([0, 0, 1]), np.array([1, 0, 0, 1, 1]),
                            np.array([0, 1, 1])])
    run = policy_run(policies, features)
    run.demos = demos
    M = 4000
    values = run.add_log_likelihood(two_state_mdp(), num_samples=M, seed=3)  # (C, D, N)
    moments = draw_moments(run, two_state_mdp(), demos, np.arange(3), M, 3, None, leave_one_out=True)
    se = np.sqrt(np.maximum(np.expm1(moments[:, :, 1] - 2 * moments[:, :, 0]), 0.0) / (M - 1))
    assert values.shape == (1, 3, 4) and np.all((se > 0) & (se < 0.05)), se
    N = features.shape[2]
    for d in range(3):
        for i in range(N):
            m = features[0, d].sum(0) - features[0, d, i]
            lp, log_nonempty = exact_draw(policies[0, d], (m + ALPHA / K) / (N + ALPHA / K), demos.states[i],
                                          demos.actions[i])
            exact = lp - log_nonempty
            assert abs(values[0, d, i] - exact) < 4 * se[0, d, i], (d, i, values[0, d, i], exact, se[0, d, i])
            assert -log_nonempty > 5 * se[0, d, i]  # (the unrenormalised value would fail here)
    # the errors are those of these values (the same seed, the same samples, the same answer)
    np.testing.assert_array_equal(moments[:, :, 0] - moments[:, :, 2], values)


@pytest.mark.parametrize("gamma", [1.0, 0.7])
def test_prior_eta_draws_follow_their_gamma_prior(gamma):
    """The predictive's transition weights: Gamma(gamma + kappa, 1) on the diagonal, Gamma(gamma,
    1) off it (at gamma = 1 drawn as Exponential(1)); Kolmogorov-Smirnov against scipy's Gamma,
    and independent of each other. (Exponential draws at gamma 0.7, or on the diagonal, fail.)"""
    import jax
    from scipy import stats

    from npbrs.models.bphmm import Hyper, sample_prior_eta

    eta = np.asarray(sample_prior_eta(jax.random.PRNGKey(0), Hyper(1.0, 3.0, gamma), (500, 4, 3, 3)))
    assert eta.shape == (500, 4, 3, 3) and eta.dtype == np.float64
    diag = np.eye(3, dtype=bool)
    for values, shape in ((eta[..., diag], gamma + 3.0), (eta[..., ~diag], gamma)):
        assert stats.kstest(values.ravel(), stats.gamma(shape).cdf).pvalue > 1e-3, shape
    off = eta[..., ~diag].reshape(-1, 6)
    assert abs(np.corrcoef(off[:, 0], off[:, 1])[0, 1]) < 0.05  # not one draw repeated
    again = sample_prior_eta(jax.random.PRNGKey(0), Hyper(1.0, 3.0, gamma), (500, 4, 3, 3))
    np.testing.assert_array_equal(np.asarray(again), eta)


def test_log_predictive_of_a_long_trajectory_does_not_move_with_the_number_of_samples():
    """A 400-step trajectory of two sticky skills: the held-out value with 16 samples a draw
    agrees with 1024 samples within their stated errors. Drawn from their prior alone, the
    transition weights rarely fit so many stays, and 16 samples fell far below 1024 (the
    guided rows of ``_guided_eta`` are what keeps the estimate where it belongs)."""
    rng = np.random.default_rng(5)
    policies = np.array([[[0.9, 0.1], [0.85, 0.15]], [[0.1, 0.9], [0.2, 0.8]]])  # (K, S, A)
    z = np.repeat([0, 1, 0, 1], 100)
    states = rng.integers(0, S, z.size)
    actions = (rng.random(z.size) < policies[z, states, 1]).astype(np.int64)
    run = policy_run(np.broadcast_to(policies, (1, 2, K, S, A)).copy(), np.ones((1, 2, 4, K)))
    demos = Demonstrations([states], [actions])
    few = run.log_predictive(two_state_mdp(), demos, num_samples=16, seed=2)
    many = run.log_predictive(two_state_mdp(), demos, num_samples=1024, seed=3)
    gap = abs(few.per_trajectory[0] - many.per_trajectory[0])
    assert gap < 4 * np.hypot(few.per_trajectory_se[0], many.per_trajectory_se[0]) + 0.05, (few, many)


def test_the_generating_policies_score_above_wrong_ones_on_held_out_data():
    rng = np.random.default_rng(3)
    true = np.array([[[0.9, 0.1], [0.9, 0.1]], [[0.1, 0.9], [0.1, 0.9]]])  # skill 0: action 0; skill 1: action 1
    states, actions = [], []
    for _ in range(6):
        s = rng.integers(0, S, 40)
        z = np.repeat(rng.integers(0, K, 4), 10)
        states.append(s)
        actions.append((rng.random(40) < true[z, s, 1]).astype(np.int64))
    demos = Demonstrations(states, actions)
    features = np.ones((1, 4, 6, K))
    good = policy_run(np.broadcast_to(true, (1, 4, K, S, A)).copy(), features)
    one_skill = policy_run(np.full((1, 4, K, S, A), 0.5), features)
    weak = policy_run(np.broadcast_to(0.5 + (true - 0.5) * 0.25, (1, 4, K, S, A)).copy(), features)
    scores = {name: r.log_predictive(two_state_mdp(), demos, num_samples=64).per_step
              for name, r in (("true", good), ("one", one_skill), ("weak", weak))}
    assert scores["true"] > scores["weak"] + 0.1 > scores["one"] + 0.1, scores


def test_bad_input_names_what_is_wrong(tmp_path):
    policies, features = draws(1)
    run = policy_run(policies, features)
    demos = Demonstrations([np.array([0, 1])], [np.array([1, 2])])
    with pytest.raises(ValueError, match="action"):
        run.log_predictive(two_state_mdp(), demos)
    ok = Demonstrations([np.array([0, 1])], [np.array([1, 0])])
    with pytest.raises(ValueError, match="num_samples"):
        run.log_predictive(two_state_mdp(), ok, num_samples=0)
    # demonstrations without a trajectory never reach log_predictive: Demonstrations refuses to
    # be built or loaded without one (its message, not one of log_predictive's)
    with pytest.raises(ValueError, match="^no trajectories$"):
        Demonstrations([], [])
    none = np.zeros(0, np.int64)
    np.savez(tmp_path / "none.npz", states=none, actions=none, lengths=none)
    with pytest.raises(ValueError, match="0 steps; a trajectory needs at least 2"):
        Demonstrations.load(tmp_path / "none.npz")


def test_arviz_loo_ranks_the_true_model_first_as_held_out_data_does(tmp_path):
    import arviz as az

    from npbrs.inference import load

    rng = np.random.default_rng(5)
    true = np.array([[[0.9, 0.1], [0.8, 0.2]], [[0.1, 0.9], [0.3, 0.7]]])

    def demos(n):
        states, actions = [], []
        for _ in range(n):
            s = rng.integers(0, S, 30)
            z = np.repeat(rng.integers(0, K, 3), 10)
            states.append(s)
            actions.append((rng.random(30) < true[z, s, 1]).astype(np.int64))
        return Demonstrations(states, actions)

    train, held = demos(8), demos(6)
    C, D = 2, 6
    features = np.ones((C, D, 8, K))
    runs = {"true": policy_run(np.broadcast_to(true, (C, D, K, S, A)).copy(), features),
            "single": policy_run(np.full((C, D, K, S, A), 0.5), features)}
    held_out = {}
    for name, run in runs.items():
        run.demos, run.segmentation = train, [np.zeros(len(s), np.int64) for s in train.states]
        ll = run.add_log_likelihood(two_state_mdp(), num_samples=64)
        assert ll.shape == (C, D, 8) and np.all(np.isfinite(ll))
        held_out[name] = run.log_predictive(two_state_mdp(), held, num_samples=64).per_step
    loo = {name: az.loo(run.to_arviz()) for name, run in runs.items()}
    assert loo["true"].elpd_loo > loo["single"].elpd_loo
    table = az.compare({name: run.to_arviz() for name, run in runs.items()})
    assert list(table.index) == ["true", "single"] and held_out["true"] > held_out["single"]
    runs["true"].save(tmp_path / "run.nc")  # the group survives a save and a load
    back = load(tmp_path / "run.nc")
    np.testing.assert_array_equal(back.log_likelihood, runs["true"].log_likelihood)
    assert back.equals(runs["true"])


def with_segmentations(run, demos):
    """The run's best segmentation and chains' best segmentations: skill k is slot k."""
    rows = [np.arange(len(s)) % K for s in demos.states]
    run.segmentation, run.demos = rows, demos
    T = max(demos.lengths)
    C = run.samples["features"].shape[0]
    run.chain_best_z = np.stack([np.stack([np.pad(r, (0, T - len(r)), constant_values=-1) for r in rows])] * C)
    return run


def exact_marginals(policies, features, states, actions, own=None):
    """p(z_t = k | x, fit) by enumeration: for a new trajectory, draws weighted by p(x | draw);
    own: each draw's fixed skill set of this trajectory (a fitted one) instead of the predictive,
    and the draws counted equally (they are posterior draws given x already)."""
    C, D, N, _ = features.shape
    T = len(states)
    zs = np.array(list(itertools.product(range(K), repeat=T)))
    joint = np.zeros((T, K))
    for c in range(C):
        for d in range(D):
            draw = np.zeros((T, K))
            m = features[c, d].sum(0)
            p_on = (m + ALPHA / K) / (N + 1 + ALPHA / K)
            log_emit = np.log(policies[c, d][:, states, actions]).T
            for f in itertools.product([0, 1], repeat=K):
                if not any(f):
                    continue
                if own is not None:
                    if tuple(own[c, d]) != f:
                        continue
                    log_pf = 0.0
                else:
                    log_pf = np.sum(np.where(np.array(f) == 1, np.log(p_on), np.log1p(-p_on)))
                lz = np.asarray(collapsed_sequence_log_prob(jnp.asarray(zs), jnp.ones(zs.shape, bool),
                                                            jnp.tile(jnp.asarray(f, jnp.float64), (len(zs), 1)),
                                                            KAPPA, GAMMA))
                w = np.exp(log_pf + lz + log_emit[np.arange(T), zs].sum(1))
                for t in range(T):
                    draw[t] += np.bincount(zs[:, t], weights=w, minlength=K)
            joint += draw if own is None else draw / draw.sum(1, keepdims=True)
    return joint / joint.sum(1, keepdims=True)


def test_segment_equals_enumerated_posterior_marginals():
    policies, features = draws(2)
    demos = Demonstrations([np.array([0, 1, 1, 0, 1]), np.array([1, 0, 0, 1]), np.array([0, 0, 1]),
                            np.array([1, 1, 0, 1])],
                           [np.array([1, 1, 0, 0, 1]), np.array([0, 0, 1, 1]), np.array([1, 0, 0]),
                            np.array([0, 1, 1, 0])])
    run = with_segmentations(policy_run(policies, features), demos)
    run.demos = None  # (a run without its demonstrations: these are new to it)
    new = run.segment(two_state_mdp(), demos, num_samples=3000, seed=2)
    run.demos = demos
    for i in range(4):
        expected = exact_marginals(policies, features, demos.states[i], demos.actions[i])
        np.testing.assert_allclose(new.probs[i], expected, atol=0.02)
        np.testing.assert_array_equal(new.labels[i], np.argmax(expected, 1))
    # the same trajectories as the fitted ones: each draw's own skill sets (rows of its features)
    fitted = run.segment(two_state_mdp(), num_samples=3000, seed=2)
    for i in range(4):
        expected = exact_marginals(policies, features, demos.states[i], demos.actions[i], own=features[:, :, i])
        np.testing.assert_allclose(fitted.probs[i], expected, atol=0.02)
    # the fitted demonstrations passed in (a copy) are the fitted ones, not new evidence again;
    # one action changed, they are new
    copy = Demonstrations([s.copy() for s in demos.states], [a.copy() for a in demos.actions])
    again = run.segment(two_state_mdp(), copy, num_samples=3000, seed=2)
    for a, b in zip(again.probs, fitted.probs):
        np.testing.assert_array_equal(a, b)
    actions = [a.copy() for a in demos.actions]
    actions[3][0] = 1 - actions[3][0]
    changed = run.segment(two_state_mdp(), Demonstrations(demos.states, actions), num_samples=3000, seed=2)
    np.testing.assert_allclose(changed.probs[0], exact_marginals(policies, features, demos.states[0],
                                                                 demos.actions[0]), atol=0.02)
