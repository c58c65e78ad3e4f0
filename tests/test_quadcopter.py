"""The quadcopter gate domain: its environment samples the tabular MDP's dynamics, its rewards
are the paper's, and its three skills are different behaviours."""

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from scipy import stats

from npbrs.domains import QuadcopterEnv, next_value_operator, quadcopter
from npbrs.domains.quadcopter import ENV_ID, HOOP_CELLS, decode, encode, sample_step

S = 9 * 6 ** 4


@pytest.fixture(scope="module")
def domain():
    return quadcopter()


@pytest.fixture(scope="module")
def policies(domain):
    return domain.expert_policies()


def test_imports_and_sizes(domain):
    mdp = domain.mdp
    assert (mdp.num_states, mdp.num_actions, mdp.num_successors) == (11664, 4, 6)
    assert mdp.feature_names == ("through_hoop", "top_row", "bottom_row")
    states = np.arange(S)
    parts = decode(states)
    np.testing.assert_array_equal(encode(*parts), states)
    assert parts[0].max() == 8 and max(p.max() for p in parts[1:]) == 5
    assert mdp.state_vectors.shape == (S, 10)
    np.testing.assert_array_equal(mdp.state_vectors[:, :2], np.stack([parts[0] // 3, parts[0] % 3], -1))
    # the hoops sit in six different places
    assert len({frozenset(c) for c in HOOP_CELLS}) == 6
    assert np.all(mdp.initial[parts[0] != 4] == 0)


def _moved(pos, a):
    row, col = divmod(pos, 3)
    if a == 0:
        row = max(row - 1, 0)
    elif a == 1:
        row = min(row + 1, 2)
    elif a == 2:
        col = max(col - 1, 0)
    else:
        col = min(col + 1, 2)
    return row, col


def test_rewards_are_the_papers_on_every_state_action(domain):
    rewards = domain.rewards()
    pos, h1 = decode(np.arange(S))[:2]
    expected = np.zeros((3, S, 4))
    for s in range(S):
        for a in range(4):
            row, col = _moved(int(pos[s]), a)
            through = (row * 3 + col) in HOOP_CELLS[h1[s]]
            expected[:, s, a] = [500 * through, 10 * (row == 0) - 500 * through, 10 * (row == 2) - 500 * through]
    np.testing.assert_array_equal(rewards, expected)


def test_environment_transitions_match_the_tabular_mdp(domain):
    """env.step from 10 states (every action): the copter's move and the shift of the slices
    are exact, and the new slice is uniform (pooled chi-square, p > 1e-4, fixed seed)."""
    mdp = domain.mdp
    env = QuadcopterEnv()
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    stat, dof, n = 0.0, 0, 600
    for s in rng.choice(S, size=10, replace=False):
        for a in range(4):
            nxt = []
            for _ in range(n):
                env.state = int(s)
                nxt.append(env.step(a)[0])
            succ = mdp.successors[s, a]
            assert set(nxt) <= set(succ.tolist()), (s, a)
            counts = np.array([nxt.count(t) for t in succ])
            stat += stats.chisquare(counts, n * mdp.probs[s, a]).statistic
            dof += 5
    assert stats.chi2.sf(stat, dof) > 1e-4


def test_vectorised_dynamics_match_the_mdp_everywhere(domain):
    mdp = domain.mdp
    rng = np.random.default_rng(1)
    states = np.repeat(np.arange(S), 4)
    actions = np.tile(np.arange(4), S)
    n = 60
    nxt = sample_step(rng, np.repeat(states, n), np.repeat(actions, n))[0].reshape(-1, n)
    succ = mdp.successors[states, actions]  # (SA, 6), distinct
    hit = nxt[:, :, None] == succ[:, None, :]
    assert hit.any(-1).all(), "a next state outside the MDP's support"
    counts = hit.sum(1)
    stat = ((counts - n / 6) ** 2 / (n / 6)).sum()
    assert stats.chi2.sf(stat, counts.shape[0] * 5) > 1e-4


def test_step_rewards_info_and_truncation(domain):
    env = gym.make(ENV_ID, skill="A", max_episode_steps=30)
    obs, info = env.reset(seed=1)
    assert info["row"] == 1 and info["col"] == 1 and len(info["hoops"]) == 4
    for t in range(30):
        prev = decode(obs)
        obs, reward, terminated, truncated, info = env.step(int(env.action_space.sample()))
        now = decode(obs)
        assert [int(x) for x in now[1:4]] == [int(x) for x in prev[2:5]]  # the slices shift
        assert reward == 500 * info["features"]["through_hoop"]
        assert not terminated and truncated == (t == 29)


def test_skills_differ_on_most_states(policies):
    for i, j in [(0, 1), (0, 2), (1, 2)]:
        differ = (policies[i] != policies[j]).mean()
        assert differ > 0.6, (i, j, differ)


def test_skills_behave_as_the_paper_describes(domain, policies):
    """A flies through most hoops; B keeps to the top row and C to the bottom row, through none."""
    mdp = domain.mdp
    rng = np.random.default_rng(2)
    for k, name in enumerate(domain.skill_names):
        s = rng.choice(S, size=300, p=mdp.initial)
        f = np.zeros(3)
        for _ in range(100):
            a = policies[k][s]
            f += mdp.features[s, a].sum(0)
            s = mdp.sample_next(rng, s, a)
        f /= 300 * 100
        if name == "A":
            assert f[0] > 0.7
        else:
            assert f[0] == 0 and f[1 if name == "B" else 2] > 0.7


def test_factored_next_value_equals_the_sparse_operator(domain):
    mdp = domain.mdp
    V = jnp.asarray(np.random.default_rng(4).normal(size=(2, S)) * 100)
    sparse = next_value_operator(mdp, "sparse")
    factored = next_value_operator(mdp, "factored")
    np.testing.assert_allclose(factored(V), sparse(V), rtol=0, atol=1e-12 * 100)
    G = jnp.asarray(np.random.default_rng(5).normal(size=(S, 4)))
    (vjp_f,) = jax.linear_transpose(factored, V[0])(G)
    (vjp_s,) = jax.linear_transpose(sparse, V[0])(G)
    np.testing.assert_allclose(vjp_f, vjp_s, rtol=0, atol=1e-12)


def test_env_checker_and_render():
    env = gym.make(ENV_ID, render_mode="rgb_array").unwrapped
    check_env(env, skip_render_check=False)
    env.reset(seed=0)
    shapes = {env.render().shape for _ in range(1)}
    for _ in range(10):
        env.step(env.action_space.sample())
        img = env.render()
        assert img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3
        shapes.add(img.shape)
    assert len(shapes) == 1
    a, b = env.render_state(int(encode(0, 0, 0, 0, 0))), env.render_state(int(encode(8, 0, 0, 0, 0)))
    assert (a != b).any()


@pytest.mark.parametrize("world", ["stormy", pytest.param("row_hoops", marks=pytest.mark.slow),
                                   pytest.param("windy", marks=pytest.mark.slow)])
def test_changed_worlds_sample_their_own_tabular_dynamics(world):
    """A changed world (other hoop frequencies, wind) keeps the features, changes the MDP, and
    its environment's sampler follows that MDP (pooled chi-square over every state-action);
    its factored next value equals the sparse one; expected features match the sampled ones."""
    changed, paper = quadcopter(world=world), quadcopter()
    mdp = changed.mdp
    assert mdp.fingerprint() != paper.mdp.fingerprint() and mdp.feature_names == paper.mdp.feature_names
    env = gym.make(ENV_ID, world=world).unwrapped
    assert env.mdp.fingerprint() == mdp.fingerprint()
    rng = np.random.default_rng(2)
    states = np.repeat(np.arange(0, S, 7), 4)
    actions = np.tile(np.arange(4), len(states) // 4)
    n = 200
    nxt, feats = env.sample_step(rng, np.repeat(states, n), np.repeat(actions, n))
    nxt = nxt.reshape(-1, n)
    stat, dof = 0.0, 0
    for i, (s, a) in enumerate(zip(states, actions)):
        expected = np.zeros(S)
        np.add.at(expected, mdp.successors[s, a], mdp.probs[s, a])
        support = np.flatnonzero(expected)
        counts = np.bincount(nxt[i], minlength=S)
        assert counts.sum() == counts[support].sum(), (s, a)
        stat += ((counts[support] - n * expected[support]) ** 2 / (n * expected[support])).sum()
        dof += len(support) - 1
    assert stats.chi2.sf(stat, dof) > 1e-4, (stat, dof)
    np.testing.assert_allclose(feats.reshape(len(states), n, 3).mean(1), mdp.features[states, actions], atol=0.15)
    V = jnp.asarray(np.random.default_rng(4).normal(size=(2, S)) * 100)
    np.testing.assert_allclose(next_value_operator(mdp, "factored")(V), next_value_operator(mdp, "sparse")(V),
                               rtol=0, atol=1e-10)


def test_world_options_are_checked():
    with pytest.raises(ValueError, match="unknown quadcopter world"):
        quadcopter(world="hurricane")
    with pytest.raises(ValueError, match="hoop_probs must be 6 probabilities"):
        quadcopter(hoop_probs=(0.5, 0.5, 0.5, 0, 0, 0))
    with pytest.raises(ValueError, match="wind must lie in"):
        quadcopter(wind=1.0)
