"""The highway domain: its environment samples the tabular MDP's dynamics, its rewards are the
paper's, and its three skills are different behaviours."""

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from scipy import stats

from npbrs.domains import HighwayEnv, highway, next_value_operator
from npbrs.domains.highway import (CLOSING, ENV_ID, LANE_CHANGE_SLOWDOWN, decode, encode,
                                   sample_step)


@pytest.fixture(scope="module")
def domain():
    return highway()


@pytest.fixture(scope="module")
def policies(domain):
    return domain.expert_policies()


def test_imports_and_sizes(domain):
    from npbrs.domains import highway as h, quadcopter as q  # noqa: F401  the public names

    mdp = domain.mdp
    assert (mdp.num_states, mdp.num_actions, mdp.num_successors) == (1080, 3, 8)
    assert mdp.feature_names == ("collision", "left_lane", "right_lane", "on_verge")
    assert domain.skill_names == ("A", "B", "C") and domain.env_id == ENV_ID
    states = np.arange(1080)
    pos, d1, d2, d3 = decode(states)
    np.testing.assert_array_equal(encode(pos, d1, d2, d3), states)
    assert pos.max() == 4 and max(d1.max(), d2.max(), d3.max()) == 5
    np.testing.assert_array_equal(mdp.state_vectors, np.stack([pos, d1, d2, d3], -1))
    assert domain.describe_state(int(encode(3, 0, 4, 5))) == {
        "position": 3, "position_name": "right lane", "distances": (0, 4, 5)}


def _paper_reward(s, a, skill):
    """The paper's reward of (s, a), written from the dynamics in the module docstring."""
    pos, *dist = (int(x) for x in decode(s))
    new = min(max(pos + (-1, 1, 0)[a], 0), 4)
    p_hit = 0.0
    if 1 <= new <= 3 and dist[new - 1] == 1:  # only a car one unit away can become level
        p_hit = CLOSING[new - 1] * (LANE_CHANGE_SLOWDOWN if new != pos else 1.0)
    return {"A": 500 * p_hit,
            "B": 10 * (new == 3) - 500 * p_hit,
            "C": 10 * (new == 1) - 500 * p_hit}[skill]


def test_rewards_are_the_papers_on_every_state_action(domain):
    rewards = domain.rewards()
    for k, skill in enumerate(domain.skill_names):
        expected = np.array([[_paper_reward(s, a, skill) for a in range(3)] for s in range(1080)])
        np.testing.assert_allclose(rewards[k], expected, rtol=0, atol=1e-12)


def _chi_square(observed_next, mdp, states, actions):
    """Pooled chi-square statistic and degrees of freedom of sampled next states against P."""
    stat, dof = 0.0, 0
    for i, (s, a) in enumerate(zip(states, actions)):
        succ, p = mdp.successors[s, a], mdp.probs[s, a]
        expected = np.zeros(mdp.num_states)
        np.add.at(expected, succ, p)
        support = expected > 0
        counts = np.bincount(observed_next[i], minlength=mdp.num_states)
        assert counts[~support].sum() == 0, f"state {s}, action {a}: a next state outside the MDP's support"
        n = counts.sum()
        stat += (((counts - n * expected) ** 2)[support] / (n * expected[support])).sum()
        dof += support.sum() - 1
    return stat, dof


def test_environment_transitions_match_the_tabular_mdp(domain):
    """Many steps of env.step from 10 states (every action): a pooled chi-square test
    (p > 1e-4 with a fixed seed), and a total-variation bound from the sample size."""
    mdp = domain.mdp
    env = HighwayEnv()
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    states = np.repeat(rng.choice(1080, size=10, replace=False), 3)
    actions = np.tile(np.arange(3), 10)
    # include the rarer situations: cars level with the agent, lane changes next to cars
    states[:3] = encode(2, 0, 1, 1)
    n = 1000
    observed = np.empty((len(states), n), dtype=np.int64)
    for i, (s, a) in enumerate(zip(states, actions)):
        for t in range(n):
            env.state = int(s)
            observed[i, t] = env.step(int(a))[0]
    stat, dof = _chi_square(observed, mdp, states, actions)
    assert stats.chi2.sf(stat, dof) > 1e-4, (stat, dof)
    P = mdp.dense_transitions()
    for i, (s, a) in enumerate(zip(states, actions)):
        tv = 0.5 * np.abs(np.bincount(observed[i], minlength=1080) / n - P[s, a]).sum()
        # E[TV] <= 0.5 * sqrt(B / n) for B outcomes; 3x that is far in the tail
        assert tv < 1.5 * np.sqrt(8 / n), (s, a, tv)


def test_vectorised_dynamics_match_the_mdp_everywhere(domain):
    """The vectorised sampler the environment and Q-learning share, from every state-action."""
    mdp = domain.mdp
    rng = np.random.default_rng(1)
    states = np.repeat(np.arange(1080), 3)
    actions = np.tile(np.arange(3), 1080)
    n = 400
    nxt = sample_step(rng, np.repeat(states, n), np.repeat(actions, n))[0].reshape(-1, n)
    stat, dof = _chi_square(nxt, mdp, states, actions)
    assert stats.chi2.sf(stat, dof) > 1e-4, (stat, dof)


def test_step_rewards_info_and_truncation(domain):
    env = gym.make(ENV_ID, skill="B", max_episode_steps=50)
    obs, info = env.reset(seed=3)
    assert domain.mdp.initial[obs] > 0 and set(info) == {"position", "position_name", "distances"}
    w = domain.skill_weights[1]
    P = domain.mdp.dense_transitions()
    for t in range(50):
        prev = obs
        obs, reward, terminated, truncated, info = env.step(int(env.action_space.sample()))
        feats = np.array([info["features"][name] for name in domain.mdp.feature_names])
        assert reward == pytest.approx(feats @ w)
        assert not terminated and truncated == (t == 49)
        assert P[prev].sum(0)[obs] > 0
    assert env.unwrapped.skill_weights(None).tolist() == [0.0] * 4
    with pytest.raises(ValueError, match="unknown skill 'D'"):
        HighwayEnv(skill="D")
    with pytest.raises(ValueError, match="shape"):
        HighwayEnv(skill=[1.0, 2.0])


def test_start_states_follow_the_initial_distribution(domain):
    env = domain.make_env()
    starts = np.array([env.reset(seed=seed)[0] for seed in range(3000)])
    pos, *dist = decode(starts)
    assert np.isin(pos, [1, 2, 3]).all()
    assert not (np.stack(dist, -1)[np.arange(len(pos)), pos - 1] == 0).any(), "no start state is a collision"
    observed = np.bincount(pos, minlength=5)[1:4]
    assert stats.chisquare(observed).pvalue > 1e-4  # the three lanes equally often


def test_skills_differ_on_most_states(domain, policies):
    """Pairwise, the skills' optimal actions differ on a majority of all states (the ceiling is
    about 60%: on the verges every skill drives back onto the road) and on most lane states."""
    pos = decode(np.arange(1080))[0]
    lanes = (pos >= 1) & (pos <= 3)
    for i, j in [(0, 1), (0, 2), (1, 2)]:
        differ = policies[i] != policies[j]
        assert differ.mean() > 0.55, (i, j, differ.mean())
        assert differ[lanes].mean() > 0.7, (i, j, differ[lanes].mean())


def test_skills_behave_as_the_paper_describes(domain, policies):
    """Under its optimal policy A hits cars, B keeps right and C keeps left without hitting any."""
    mdp = domain.mdp
    rng = np.random.default_rng(2)
    for k, name in enumerate(domain.skill_names):
        s = rng.choice(1080, size=500, p=mdp.initial)
        hits, pos = 0.0, np.zeros(5)
        for _ in range(100):
            a = policies[k][s]
            hits += mdp.features[s, a, 0].sum()
            s = mdp.sample_next(rng, s, a)
            pos += np.bincount(decode(s)[0], minlength=5)
        share = pos / pos.sum()
        if name == "A":
            assert hits / 500 > 10
        else:  # collisions only where the road is blocked: ~0.002 per 100 steps
            assert hits / 500 < 0.05
            assert share[3 if name == "B" else 1] > 0.6


def test_factored_next_value_equals_the_sparse_operator(domain):
    mdp = domain.mdp
    V = jnp.asarray(np.random.default_rng(4).normal(size=(2, 3, 1080)) * 100)
    sparse = next_value_operator(mdp, "sparse")
    factored = next_value_operator(mdp, "factored")
    np.testing.assert_allclose(factored(V), sparse(V), rtol=0, atol=1e-12 * 100)
    # the solvers differentiate through its transpose: it must be linear and transpose to P^T
    G = jnp.asarray(np.random.default_rng(5).normal(size=(1080, 3)))
    (vjp_f,) = jax.linear_transpose(factored, V[0, 0])(G)
    (vjp_s,) = jax.linear_transpose(sparse, V[0, 0])(G)
    np.testing.assert_allclose(vjp_f, vjp_s, rtol=0, atol=1e-12)


def test_env_checker_and_render():
    env = gym.make(ENV_ID, render_mode="rgb_array").unwrapped
    check_env(env, skip_render_check=False)
    env.reset(seed=0)
    shapes = set()
    for _ in range(20):
        img = env.render()
        assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
        shapes.add(img.shape)
        env.step(env.action_space.sample())
    assert len(shapes) == 1
    # a crash is drawn in yellow, distinct from an ordinary frame
    crash = env.render_state(int(encode(2, 5, 0, 5)))
    calm = env.render_state(int(encode(2, 5, 5, 5)))
    assert (np.abs(crash.astype(int) - calm.astype(int)).sum(-1) > 0).any()
    assert HighwayEnv().render() is None


@pytest.mark.parametrize("world", ["traffic_jam", pytest.param("slow_middle", marks=pytest.mark.slow),
                                   pytest.param("fast_traffic", marks=pytest.mark.slow)])
def test_changed_worlds_sample_their_own_tabular_dynamics(world):
    """A changed world (other car speeds, appearance rates, lane-change cost) keeps the
    features, changes the MDP, and its environment's sampler follows that MDP; its factored
    next value equals the sparse one."""
    changed, paper = highway(world=world), highway()
    mdp = changed.mdp
    assert mdp.fingerprint() != paper.mdp.fingerprint()
    assert mdp.feature_names == paper.mdp.feature_names
    env = gym.make(ENV_ID, world=world).unwrapped
    assert env.mdp.fingerprint() == mdp.fingerprint()
    rng = np.random.default_rng(7)
    states = np.repeat(np.arange(1080), 3)
    actions = np.tile(np.arange(3), 1080)
    n = 300
    nxt = env.sample_step(rng, np.repeat(states, n), np.repeat(actions, n))[0].reshape(-1, n)
    stat, dof = _chi_square(nxt, mdp, states, actions)
    assert stats.chi2.sf(stat, dof) > 1e-4, (stat, dof)
    # the paper's sampler would not pass against this world's MDP
    old = sample_step(rng, np.repeat(states, n), np.repeat(actions, n))[0].reshape(-1, n)
    stat, dof = _chi_square(old, mdp, states, actions)
    assert stats.chi2.sf(stat, dof) < 1e-10
    V = jnp.asarray(np.random.default_rng(4).normal(size=(2, 1080)) * 100)
    np.testing.assert_allclose(next_value_operator(mdp, "factored")(V), next_value_operator(mdp, "sparse")(V),
                               rtol=0, atol=1e-10)


def test_world_options_are_checked():
    with pytest.raises(ValueError, match="unknown highway world 'rush'"):
        highway(world="rush")
    with pytest.raises(ValueError, match="appear must be three probabilities"):
        highway(appear=(0.5, 1.5, 0.2))
    assert highway(closing=(0.5, 0.2, 0.6)).mdp.fingerprint() != highway().mdp.fingerprint()


def test_reset_to_a_chosen_state():
    env = gym.make(ENV_ID).unwrapped
    assert env.reset(seed=0, options={"state": 17})[0] == 17 and env.state == 17
    with pytest.raises(ValueError, match="reset state 1080 is outside 0..1079"):
        env.reset(options={"state": 1080})
    with pytest.raises(ValueError, match="unknown reset options"):
        env.reset(options={"start": 3})
