"""The found skills for control: options estimated from a segmentation recover planted ones,
run in a gymnasium environment, and rewards solved again in a changed world (transfer) equal
an independent soft value iteration, and reproduce the original policy in the same world."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium import spaces

from npbrs.domains import TabularMDP
from npbrs.domains.demos import Demonstrations
from npbrs.domains.options import estimate_options, run_option
from npbrs.inference.driver.config import ModelConfig
from npbrs.inference.driver.results import FitResult

from gridworld import gridworld

# planted options on a line of 6 states: skill 0 walks in 0..3 and stops on arriving in 3 with
# probability 0.4; skill 1 walks in 2..5 and stops on arriving in 2 with probability 0.25
LOW, HIGH = {0: 0, 1: 2}, {0: 3, 1: 5}
PLANTED = {0: np.array([0, 0, 0, 0.4, 0, 0]), 1: np.array([0, 0, 0.25, 0, 0, 0])}


def _planted_segmentation(num_trajectories=300, length=60, seed=0):
    rng = np.random.default_rng(seed)
    states, labels = [], []
    for _ in range(num_trajectories):
        k = int(rng.integers(2))
        s = int(rng.integers(LOW[k], HIGH[k] + 1))
        st, zs = [], []
        for t in range(length):
            st.append(s)
            zs.append(k)
            s = int(np.clip(s + rng.choice([-1, 1]), LOW[k], HIGH[k]))  # arrive
            if rng.random() < PLANTED[k][s]:
                k = 1 - k
        states.append(np.array(st))
        labels.append(np.array(zs))
    return states, labels


def test_options_recover_planted_initiation_and_termination():
    """Termination per state within 4 binomial standard errors of the planted probability
    (plus the prior's pull), zero-probability states near zero, initiation sets exact."""
    states, labels = _planted_segmentation()
    uniform = np.full((2, 6, 2), 0.5)
    options = estimate_options(states, labels, uniform, np.zeros((2, 6), int), prior_strength=2.0)
    for k, opt in enumerate(options):
        np.testing.assert_array_equal(np.flatnonzero(opt.initiation), np.arange(LOW[k], HIGH[k] + 1))
        arrivals = opt.stops + opt.goes
        for s in range(6):
            if arrivals[s] == 0:
                continue
            p = PLANTED[k][s]
            se = np.sqrt(max(p * (1 - p), 0.01) / arrivals[s])
            assert abs(opt.termination[s] - p) < 4 * se + 2.0 / arrivals[s], (k, s, opt.termination[s], p)
        # a state never reached falls back on the skill's average rate
        never = np.flatnonzero(arrivals == 0)
        assert never.size and np.allclose(opt.termination[never], (opt.stops.sum() + 1) / (arrivals.sum() + 2))


def test_option_runs_in_a_gymnasium_environment_until_it_terminates():
    class Line(gym.Env):
        observation_space = spaces.Discrete(6)
        action_space = spaces.Discrete(2)

        def reset(self, *, seed=None, options=None):
            super().reset(seed=seed)
            self.s = 0
            return self.s, {}

        def step(self, action):
            self.s = int(np.clip(self.s + (1 if action == 1 else -1), 0, 5))
            return self.s, float(self.s), False, False, {}

    right = np.zeros((6, 2))
    right[:, 1] = 1.0
    states, labels = [np.array([0, 1, 2, 3, 4, 5])], [np.zeros(6, int)]
    (opt,) = estimate_options(states, labels, right[None], np.ones((1, 6), int))
    opt = type(opt)(**{**opt.__dict__, "termination": np.array([0, 0, 0, 1.0, 0, 0])})
    run = run_option(Line(), opt, seed=0)
    assert run.reason == "terminated" and run.final_state == 3
    np.testing.assert_array_equal(run.states, [0, 1, 2])
    np.testing.assert_array_equal(run.rewards, [1, 2, 3])
    short = run_option(Line(), opt, seed=0, max_steps=2)
    assert short.reason == "max_steps" and short.final_state == 2
    outside = type(opt)(**{**opt.__dict__, "initiation": np.array([False, True, True, True, True, True])})
    with pytest.raises(ValueError, match="state 0 is outside the initiation set"):
        run_option(Line(), outside, seed=0)
    with pytest.raises(ValueError, match="Discrete\\(6\\)"):
        run_option(gym.make("FrozenLake-v1"), opt, seed=0)


def test_options_reject_bad_input():
    states, labels = [np.array([0, 1, 7])], [np.array([0, 0, 0])]
    with pytest.raises(ValueError, match="trajectory 0: state 7 is outside 0..5"):
        estimate_options(states, labels, np.full((1, 6, 2), 0.5), np.zeros((1, 6), int))
    with pytest.raises(ValueError, match="skill 0, state 0: action probabilities do not sum to one"):
        estimate_options([np.array([0, 1])], [np.array([0, 0])], np.full((1, 6, 2), 0.4), np.zeros((1, 6), int))


# ------------------------------------------------------------------------------ transfer
def _soft_policy(mdp, theta, tau, eps, iters=3000):
    """Independent soft value iteration in NumPy on the dense transitions."""
    P = mdp.dense_transitions()
    r = tau * np.einsum("sad,kd->ksa", mdp.features, theta)
    V = np.zeros((theta.shape[0], mdp.num_states))
    for _ in range(iters):
        Q = r + mdp.discount * np.einsum("sat,kt->ksa", P, V)
        V = np.log(np.exp(Q - Q.max(-1, keepdims=True)).sum(-1)) + Q.max(-1)
    return (1 - eps) * np.exp(Q - V[..., None]) + eps / mdp.num_actions


def _result(mdp, theta, options, demos=None, segmentation=None):
    cfg = ModelConfig.from_dict({"emission": {"name": "reward", "options": options}}).to_dict()
    K = theta.shape[0]
    seg = segmentation if segmentation is not None else [np.zeros(n, np.int64) for n in demos.lengths]
    return FitResult(segmentation=seg, num_skills=K, skill_params={"theta": theta}, skill_slots=np.arange(K),
                     best_chain=0, best_log_joint=0.0, stats={"log_joint": np.zeros((1, 2))}, samples={},
                     config=cfg, feature_names=tuple(mdp.feature_names), demos=demos,
                     mdp_fingerprint=mdp.fingerprint())


@pytest.fixture(scope="module")
def worlds():
    paper = gridworld(size=3, slip=0.1).mdp
    slippery = gridworld(size=3, slip=0.5).mdp  # the same features' names, other dynamics
    return paper, slippery


def test_rewards_solved_in_a_changed_world_equal_soft_value_iteration(worlds):
    """Temperature 2 and epsilon 0.1: the transferred Boltzmann policies equal an independent
    NumPy soft value iteration in the changed MDP, and the greedy ones its argmax."""
    paper, slippery = worlds
    theta = np.array([[1.5, -0.5, 0.0], [0.0, 0.3, 2.0]])
    result = _result(paper, theta, {"temperature": 2.0, "epsilon": 0.1},
                     demos=Demonstrations([np.array([0, 1, 2])], [np.array([3, 3, 1])]))
    pi = result.policies(slippery)
    ref = _soft_policy(slippery, theta, 2.0, 0.1)
    np.testing.assert_allclose(pi, ref, atol=1e-7)
    assert np.abs(pi - result.policies(paper)).max() > 1e-3  # the world did change them
    # the optimal policy of the changed world (hard value iteration on the dense transitions)
    P, r = slippery.dense_transitions(), np.einsum("sad,kd->ksa", slippery.features, theta)
    V = np.zeros((2, 9))
    for _ in range(3000):
        Q = r + slippery.discount * np.einsum("sat,kt->ksa", P, V)
        V = Q.max(-1)
    greedy = result.policies(slippery, greedy=True)
    np.testing.assert_allclose(Q[np.arange(2)[:, None], np.arange(9), greedy], Q.max(-1), rtol=0, atol=1e-8)


def test_transfer_to_the_same_world_reproduces_the_fitted_policy(worlds):
    """In a rebuilt copy of the fitted MDP the transferred policy is the emission's own, the one
    whose log-probabilities the fit's likelihood used, exactly."""
    from npbrs.inference import make_emission
    from npbrs.models.emissions import HMMData

    paper, _ = worlds
    copy = TabularMDP.from_successors(paper.successors, paper.probs, paper.features,
                                      feature_names=paper.feature_names, discount=paper.discount)
    theta = np.array([[1.0, 2.0, -1.0]])
    demos = Demonstrations([np.array([0, 4, 8, 5])], [np.array([3, 1, 4, 0])])
    result = _result(paper, theta, {"temperature": 0.5}, demos=demos)
    pi = result.policies(copy)
    em = make_emission("reward", paper, temperature=0.5)
    ll, _ = em.log_likelihoods({"theta": theta}, HMMData.from_demonstrations(demos))
    np.testing.assert_allclose(np.log(pi[0, demos.states[0], demos.actions[0]]), np.asarray(ll)[0, :, 0], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(pi, result.policies(paper))


def test_transfer_and_options_refuse_a_world_they_do_not_fit(worlds):
    paper, slippery = worlds
    theta = np.array([[1.0, 0.0, 0.0]])
    demos = Demonstrations([np.array([0, 1, 2, 5])], [np.array([3, 3, 1, 4])])
    result = _result(paper, theta, {}, demos=demos)
    other = paper.with_features(paper.features[..., :2], ("top_left", "top_right"))
    with pytest.raises(ValueError, match="rewards are over 3 features .* has 2"):
        result.policies(other)
    with pytest.raises(ValueError, match="fitted in another MDP"):
        result.options(slippery)
    options = result.options(paper)
    assert len(options) == 1 and options[0].initiation[[0, 1, 2, 5]].all()
    np.testing.assert_allclose(options[0].policy, result.policies(paper)[0])


def test_posterior_mean_rewards_average_the_draws_that_hold_each_skill(worlds):
    """rewards="mean": each skill's weights averaged over the draws in which its (matched) slot
    has steps, chains matched to the run's skills by their segmentations; "best" is the best
    draw's; the policies are those of the chosen weights."""
    from npbrs.inference.analysis.skills import skill_parameters

    paper, _ = worlds
    rng = np.random.default_rng(3)
    # two chains of 4 draws over 3 slots; the run's skills are chain 0's slots 0 and 2, which
    # chain 1 holds as slots 1 and 0
    theta = rng.normal(size=(2, 4, 3, 3))
    steps = np.ones((2, 4, 3), np.int64)
    steps[0, 1, 2] = 0  # skill 1 is absent from chain 0's draw 1
    z_run = np.array([0, 0, 2, 2, 2])
    chain_z = np.stack([z_run, np.array([1, 1, 0, 0, 0])])[:, None, :]  # (C, N, T)
    demos = Demonstrations([np.array([0, 1, 2, 5, 8])], [np.array([3, 3, 1, 1, 4])])
    result = _result(paper, np.array([[9.0, 9.0, 9.0], [8.0, 8.0, 8.0]]), {}, demos=demos,
                     segmentation=[np.array([0, 0, 1, 1, 1])])
    result.samples = {"theta": theta, "skill_steps": steps}
    result.chain_best_z = chain_z
    result.stats = {"log_joint": np.zeros((2, 4))}
    mean = skill_parameters(result, "mean")["theta"]
    expected0 = np.concatenate([theta[0, :, 0], theta[1, :, 1]]).mean(0)
    expected1 = np.concatenate([theta[0, [0, 2, 3], 2], theta[1, :, 0]]).mean(0)
    np.testing.assert_allclose(mean, np.stack([expected0, expected1]))
    np.testing.assert_array_equal(skill_parameters(result, "best")["theta"], result.skill_params["theta"])
    fixed = _result(paper, mean, {}, demos=demos)
    np.testing.assert_allclose(result.policies(paper, rewards="mean"), fixed.policies(paper, rewards="best"))
    np.testing.assert_array_equal(result.policies(paper, greedy=True), fixed.policies(paper, greedy=True))
    with pytest.raises(ValueError, match="unknown rewards 'map'"):
        result.policies(paper, rewards="map")
