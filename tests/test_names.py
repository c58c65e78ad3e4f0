"""The action-name factor (``npbrs.models.names``): which of several equivalent actions a
demonstrator names. Equivalence against a dense comparison; the exact held-out and
leave-one-out terms against quadrature over the names' probabilities and against a refit
without the trajectory; the scores of a run with learned names against the same run's with
uniform names (the same draws: the factor leaves the skills' posterior alone)."""

import dataclasses

import numpy as np
import pytest
from scipy import integrate
from scipy.special import betaln, logsumexp

from npbrs.domains import Demonstrations, TabularMDP
from npbrs.models.names import CONCENTRATIONS, ActionNames


def stay_mdp():
    """3 states, 3 actions: in state 0 actions 1 and 2 both stay, action 0 moves to state 1;
    in state 1 every action differs; state 2 has all three actions going to state 0."""
    P = np.zeros((3, 3, 3))
    P[0, 0, 1] = P[0, 1, 0] = P[0, 2, 0] = 1.0
    P[1, 0, 0] = P[1, 1, 2] = 1.0
    P[1, 2, 1] = 1.0
    P[2, :, 0] = 1.0
    return TabularMDP.from_dense(P, discount=0.8)


def test_equivalent_actions_are_those_with_the_same_next_states_and_features():
    rng = np.random.default_rng(0)
    S, A, D = 6, 4, 3
    P = rng.dirichlet(np.ones(S), size=(S, A))
    P[1, 2] = P[1, 0]
    P[3, 3] = P[3, 1] = P[3, 2]
    P[5, 1] = P[5, 0]
    features = rng.normal(size=(S, A, D))
    features[1, 2] = features[1, 0]
    features[3, 1] = features[3, 3] = features[3, 2]  # state 5's actions 0 and 1: other features
    same = TabularMDP.from_dense(P, features=features).equivalent_actions()
    dense = np.array([[[np.allclose(P[s, a], P[s, b], atol=0, rtol=0) and np.array_equal(features[s, a], features[s, b])
                        for b in range(A)] for a in range(A)] for s in range(S)])
    np.testing.assert_array_equal(same, dense)
    assert same[1, 0, 2] and same[3, 1, 3] and not same[5, 0, 1]
    # one-hot state features: equal features, so the dynamics decide
    np.testing.assert_array_equal(stay_mdp().equivalent_actions()[0], [[1, 0, 0], [0, 1, 1], [0, 1, 1]])
    assert stay_mdp().equivalent_actions()[2].all()


def quadrature_correction(train, new):
    """log p(new names | train names) + the uniform names' nats, for one set of two equivalent
    actions: counts (n1, n2) and (m1, m2); each concentration c's terms by quadrature over q ~
    Beta(c / 2, c / 2), averaged by the posterior over c (prior one half on uniform names, the
    rest evenly over CONCENTRATIONS)."""
    (n1, n2), (m1, m2) = train, new
    log_ev, log_pred = [], []
    for c in CONCENTRATIONS:
        a = c / 2

        def moment(k1, k2):  # log of the integral of q^(k1 + a - 1) (1 - q)^(k2 + a - 1)
            return np.log(integrate.quad(lambda q: q ** (k1 + a - 1) * (1 - q) ** (k2 + a - 1), 0, 1,
                                         epsabs=0, epsrel=1e-12, limit=200)[0])

        log_ev.append(moment(n1, n2) - betaln(a, a))
        log_pred.append(moment(n1 + m1, n2 + m2) - moment(n1, n2))
    G = len(CONCENTRATIONS)
    log_ev.append(-(n1 + n2) * np.log(2))
    log_pred.append(-(m1 + m2) * np.log(2))
    log_w = np.concatenate([np.full(G, np.log(0.5 / G)), [np.log(0.5)]]) + np.array(log_ev)
    log_w -= logsumexp(log_w)
    return logsumexp(log_w + np.array(log_pred)) + (m1 + m2) * np.log(2)


def test_the_held_out_names_term_equals_quadrature():
    mdp = stay_mdp()
    # state 0: 7 steps name action 1, 2 name action 2 (counted); moves and state 1 are not counted
    train = Demonstrations([np.array([0] * 9 + [1]), np.array([0, 1])],
                           [np.array([1, 1, 2, 1, 1, 1, 2, 1, 1, 2]), np.array([0, 0])])
    new = Demonstrations([np.array([0, 0, 0, 0, 2]), np.array([0, 0, 1])],
                         [np.array([2, 1, 1, 1, 1]), np.array([1, 0, 0])])
    names = ActionNames.fit(mdp, train)
    got = names.heldout_correction(mdp, new)
    # trajectory 0: (3, 1) at state 0; its step in state 2 names one of three equivalent actions,
    # a set the fit never saw, so it is not counted (uniform names: no correction)
    assert got[0] == pytest.approx(quadrature_correction((7, 2), (3, 1)), abs=1e-8)
    assert got[1] == pytest.approx(quadrature_correction((7, 2), (1, 0)), abs=1e-8)
    # the direction: names like the fitted ones gain, the other name loses
    assert got[1] > 0 and names.heldout_correction(mdp, Demonstrations([np.array([0, 0])], [np.array([2, 2])]))[0] < 0


def test_the_leave_one_out_names_term_is_the_held_out_term_of_a_fit_without_the_trajectory():
    mdp = stay_mdp()
    rng = np.random.default_rng(1)
    states = [np.zeros(n, int) for n in (6, 4, 8, 5)]
    actions = [np.where(rng.random(len(s)) < 0.8, 2, 1) for s in states]
    loo = ActionNames.fit(mdp, Demonstrations(states, actions)).loo_correction()
    for i in range(len(states)):
        rest = Demonstrations([s for j, s in enumerate(states) if j != i], [a for j, a in enumerate(actions) if j != i])
        alone = Demonstrations([states[i]], [actions[i]])
        assert loo[i] == pytest.approx(ActionNames.fit(mdp, rest).heldout_correction(mdp, alone)[0], abs=1e-10)


def test_uniform_names_are_chosen_by_the_evidence_when_the_demonstrator_splits_evenly():
    mdp = stay_mdp()
    rng = np.random.default_rng(2)
    states = [np.zeros(400, int)]
    even = ActionNames.fit(mdp, Demonstrations(states, [rng.integers(1, 3, 400)]))
    assert even.log_bayes_factor < 0
    held = Demonstrations([np.zeros(50, int)], [rng.integers(1, 3, 50)])
    assert abs(even.heldout_correction(mdp, held)[0]) < 0.05  # (50 steps)
    one = ActionNames.fit(mdp, Demonstrations(states, [np.full(400, 2)]))
    assert one.log_bayes_factor > 100


def reward_run(train):
    """A FitResult of the reward emission (learned names) with given draws: 1 chain, 3 draws, 2
    skills, in :func:`stay_mdp`."""
    from npbrs.inference.driver.fit import resolve_config
    from npbrs.inference.driver.results import FitResult

    rng = np.random.default_rng(3)
    C, D, K = 1, 3, 2
    cfg = resolve_config(None, emission="reward", max_skills=K)
    zeros = np.zeros((C, D))
    features = np.ones((C, D, len(train.lengths), K))
    return FitResult(segmentation=[], num_skills=K, skill_params={}, skill_slots=np.arange(K), best_chain=0,
                     best_log_joint=0.0, stats={"log_joint": zeros, "num_skills": zeros, "num_switches": zeros},
                     samples={"theta": rng.normal(size=(C, D, K, 3)), "features": features,
                              "skill_steps": np.ones((C, D, K))},
                     config=cfg.to_dict(), emission={"name": "reward", "action_names": "learned"}, demos=train)


def test_a_runs_scores_add_the_names_term_to_those_of_uniform_names():
    mdp = stay_mdp()
    train = Demonstrations([np.array([0, 0, 0, 1, 0, 0]), np.array([0, 0, 1, 2, 0])],
                           [np.array([2, 2, 0, 0, 2, 2]), np.array([2, 0, 1, 0, 1])])
    new = Demonstrations([np.array([0, 0, 0, 1])], [np.array([2, 2, 0, 2])])
    learned = reward_run(train)
    uniform = dataclasses.replace(learned, emission={"name": "reward", "action_names": "uniform"})
    names = ActionNames.fit(mdp, train)
    a, b = (r.log_predictive(mdp, new, num_samples=8, num_draws=3) for r in (learned, uniform))
    np.testing.assert_allclose(a.per_trajectory - b.per_trajectory, names.heldout_correction(mdp, new), atol=1e-12)
    assert a.per_step == pytest.approx(a.per_trajectory.sum() / 4)
    la, lb = (r.add_log_likelihood(mdp, num_samples=8) for r in (learned, uniform))
    np.testing.assert_allclose(la - lb, np.broadcast_to(names.loo_correction(), la.shape), atol=1e-12)
