"""Experts: Q-learning in the environment (the paper's demonstrators) reaches the optimal return,
and policy evaluation is exact."""

import gymnasium as gym
import numpy as np
import pytest

from npbrs.domains import (TabularMDP, greedy_policy, highway, policy_return, policy_values, q_learning,
                           quadcopter, value_iteration)


def test_policy_values_solve_the_bellman_equation():
    rng = np.random.default_rng(0)
    P = rng.random((6, 3, 6)) * (rng.random((6, 3, 6)) < 0.5) + 1e-3
    P /= P.sum(-1, keepdims=True)
    mdp = TabularMDP.from_dense(P, features=rng.normal(size=(6, 3, 2)), discount=0.9)
    reward = rng.normal(size=(6, 3))
    pi = rng.dirichlet(np.ones(3), size=6)
    expected = np.linalg.solve(np.eye(6) - 0.9 * np.einsum("sa,sat->st", pi, P), (pi * reward).sum(-1))
    np.testing.assert_allclose(policy_values(mdp, reward, pi), expected, atol=1e-12)
    det = rng.integers(3, size=6)
    np.testing.assert_allclose(policy_values(mdp, reward, det), policy_values(mdp, reward, np.eye(3)[det]), atol=1e-12)
    # the optimal policy's value is value iteration's
    Q = np.asarray(value_iteration(mdp, reward).Q)
    np.testing.assert_allclose(policy_values(mdp, reward, greedy_policy(Q)), Q.max(-1), atol=1e-8)
    assert policy_return(mdp, reward, det) == pytest.approx(mdp.initial @ policy_values(mdp, reward, det))
    with pytest.raises(ValueError, match="state 2"):
        bad = pi.copy()
        bad[2] = [0.5, 0.6, -0.1]
        policy_values(mdp, reward, bad)


@pytest.fixture(scope="module")
def road():
    return highway()


@pytest.mark.parametrize("skill", ["A", "B", "C"])
def test_q_learning_reaches_95_percent_of_the_optimal_return_on_the_highway(road, skill):
    k = road.skill_names.index(skill)
    reward = road.rewards()[k]
    optimal = policy_return(road.mdp, reward, road.expert_policies()[k])
    Q = q_learning(road, skill, num_episodes=2048, episode_length=200, seed=0)
    learned = policy_return(road.mdp, reward, greedy_policy(Q))
    assert optimal > 0 and learned >= 0.95 * optimal, (learned, optimal)


@pytest.mark.slow
@pytest.mark.parametrize("skill", ["A", "B", "C"])
def test_q_learning_reaches_95_percent_of_the_optimal_return_on_the_quadcopter(skill):
    domain = quadcopter()
    k = domain.skill_names.index(skill)
    reward = domain.rewards()[k]
    optimal = policy_return(domain.mdp, reward, domain.expert_policies()[k])
    Q = q_learning(domain, skill, num_episodes=25600, episode_length=250, seed=0)
    learned = policy_return(domain.mdp, reward, greedy_policy(Q))
    assert learned >= 0.95 * optimal, (learned, optimal)


def test_q_learning_uses_the_environment_reward_of_any_gymnasium_env():
    env = gym.make("FrozenLake-v1", is_slippery=False)
    mdp = TabularMDP.from_gymnasium(env, features="env_reward", discount=0.9)
    Q = q_learning(env, num_episodes=400, episode_length=50, epsilon=0.3, alpha=0.5, discount=0.9, seed=0)
    reward = mdp.reward([1.0])
    optimal = np.asarray(value_iteration(mdp, reward).V) @ mdp.initial
    assert policy_return(mdp, reward, greedy_policy(Q)) == pytest.approx(optimal, rel=1e-6)
    with pytest.raises(ValueError, match="skill"):
        q_learning(env, "A", num_episodes=1, episode_length=1)


def test_q_learning_is_reproducible_and_validates(road):
    a = q_learning(road, "B", num_episodes=256, episode_length=20, seed=3)
    b = q_learning(road.make_env(skill="B"), num_episodes=256, episode_length=20, seed=3)
    np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="alpha"):
        q_learning(road, "B", alpha=0.0)
    with pytest.raises(ValueError, match="q0"):
        q_learning(road, "B", q0=np.zeros((3, 3)))
