"""Control evaluation: the expert gets its own score, shared randomness, wrong skills score lower."""

import numpy as np
import pytest

from npbrs.domains import Demonstrations, TabularMDP, generate_demonstrations
from npbrs.domains.control import evaluate_control, expert_control, replay, skill_policies
from npbrs.domains.domain import Domain


# (greedy policies solved to convergence many times: level 0 runs them slowly)
pytestmark = pytest.mark.library_level


@pytest.fixture(scope="module")
def highway_case():
    from npbrs.domains.highway import highway

    domain = highway()
    return domain, generate_demonstrations(domain, num_trajectories=4, length=200, seed=0)


def relabel(segmentation, mapping):
    return [np.asarray(mapping)[z] for z in segmentation]


def test_the_true_segmentation_and_rewards_get_the_experts_score_exactly(highway_case):
    domain, demos = highway_case
    expert = expert_control(domain, demos, seed=3)
    same = evaluate_control(domain, demos, demos.skills, domain.rewards(), seed=3)
    np.testing.assert_array_equal(same["rewards"], expert["rewards"])
    assert expert["skills"] == 3 and expert["switches"] == np.mean([np.count_nonzero(np.diff(z)) for z in demos.skills])
    # skill labels are arbitrary and a reward's scale does not change its optimal policy
    perm = [2, 0, 1]
    rewards = np.empty_like(domain.rewards())
    rewards[perm] = 3.0 * domain.rewards()
    relabelled = evaluate_control(domain, demos, relabel(demos.skills, perm), rewards, seed=3)
    np.testing.assert_array_equal(relabelled["rewards"], expert["rewards"])
    # reward weights (K, D) are accepted too
    weights = evaluate_control(domain, demos, demos.skills, domain.skill_weights, seed=3)
    np.testing.assert_array_equal(weights["rewards"], expert["rewards"])


def test_wrong_skills_score_lower_on_the_highway(highway_case):
    domain, demos = highway_case
    expert = expert_control(domain, demos)
    hit_cars_always = [np.zeros(len(z), int) for z in demos.skills]  # skill A everywhere
    swapped = relabel(demos.skills, [0, 2, 1])  # right lane and left lane confused
    one = evaluate_control(domain, demos, hit_cars_always, domain.rewards())
    assert one["skills"] == 1 and one["switches"] == 0
    assert one["reward"] < expert["reward"] - 1000
    assert evaluate_control(domain, demos, swapped, domain.rewards())["reward"] < expert["reward"]


def test_the_same_seed_gives_the_same_rollouts(highway_case):
    domain, demos = highway_case
    a = expert_control(domain, demos, seed=1)
    b = expert_control(domain, demos, seed=1)
    c = expert_control(domain, demos, seed=2)
    assert all(np.array_equal(x, y) for x, y in zip(a["states"], b["states"]))
    assert not all(np.array_equal(x, y) for x, y in zip(a["states"], c["states"]))
    for s, d in zip(a["states"], demos.states):
        assert s[0] == d[0] and len(s) == len(d)


def toy_domain():
    rng = np.random.default_rng(0)
    P = rng.random((4, 2, 4))
    P /= P.sum(-1, keepdims=True)
    mdp = TabularMDP.from_dense(P, features=rng.normal(size=(4, 2, 3)), discount=0.9)
    return Domain(name="toy", mdp=mdp, skill_names=("A", "B"), skill_weights=rng.normal(size=(2, 3))), P


def test_replay_samples_next_states_from_the_dynamics():
    domain, P = toy_domain()
    n = 20000
    policies = np.array([[1, 1, 1, 1]])
    states, _ = replay(domain.mdp, np.full(n, 2), [np.zeros(2, int)] * n, policies, seed=0)
    freq = np.bincount([s[1] for s in states], minlength=4) / n
    sd = np.sqrt(P[2, 1] * (1 - P[2, 1]) / n)
    np.testing.assert_array_less(np.abs(freq - P[2, 1]), 5 * sd)


def test_scores_are_the_true_skills_expected_rewards():
    domain, _ = toy_domain()
    demos = Demonstrations([[0, 1, 2], [3, 3]], [[0, 0, 0], [1, 1]], skills=[[0, 1, 1], [1, 0]])
    policies = np.array([[0, 1, 0, 1], [1, 1, 0, 0]])
    out = evaluate_control(domain, demos, [[1, 1, 0], [0, 0]], policies, seed=5)
    R = domain.rewards()
    expected = [sum(R[k, s, a] for k, s, a in zip(true, st, ac))
                for true, st, ac in zip(demos.skills, out["states"], out["actions"])]
    np.testing.assert_allclose(out["rewards"], expected)
    for z, st, ac in zip([[1, 1, 0], [0, 0]], out["states"], out["actions"]):
        np.testing.assert_array_equal(ac, policies[z, st])
    assert out["switches"] == 0.5 and out["skills"] == 2


def test_bad_inputs_name_what_is_wrong():
    domain, _ = toy_domain()
    demos = Demonstrations([[0, 1, 2], [3, 3]], [[0, 0, 0], [1, 1]], skills=[[0, 1, 1], [1, 0]])
    policies = np.zeros((2, 4), int)
    with pytest.raises(ValueError, match="trajectory 1: segmentation has shape \\(3,\\) but the demonstration has 2"):
        evaluate_control(domain, demos, [[0, 0, 0], [0, 0, 0]], policies)
    with pytest.raises(ValueError, match="trajectory 0, step 2: segmentation label 2 is outside 0..1"):
        evaluate_control(domain, demos, [[0, 0, 2], [0, 0]], policies)
    with pytest.raises(ValueError, match="carry none"):
        evaluate_control(domain, Demonstrations(demos.states, demos.actions), [[0, 0, 0], [0, 0]], policies)
    with pytest.raises(ValueError, match="skill 1, state 3: action 2 is outside 0..1"):
        skill_policies(domain.mdp, np.array([[0, 0, 0, 0], [0, 0, 0, 2]]))
    with pytest.raises(ValueError, match="reward weights \\(K, D\\) and need D = 3"):
        skill_policies(domain.mdp, np.zeros((2, 4)))
