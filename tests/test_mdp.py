import gymnasium as gym
import numpy as np
import pytest

from npbrs.domains import TabularMDP


def random_dense(rng, S=5, A=3):
    P = rng.random((S, A, S)) * (rng.random((S, A, S)) < 0.6)
    P[..., 0] += 1e-3
    return P / P.sum(-1, keepdims=True)


def test_from_dense_round_trips_the_transition_tensor():
    rng = np.random.default_rng(0)
    P = random_dense(rng)
    mdp = TabularMDP.from_dense(P, features=rng.normal(size=(5, 3, 2)), discount=0.9)
    np.testing.assert_allclose(mdp.dense_transitions(), P, atol=1e-15)
    assert (mdp.num_states, mdp.num_actions, mdp.num_features) == (5, 3, 2)


def test_one_hot_features_too_large_to_hold_are_refused_and_names_are_summarised(monkeypatch):
    """A robot world of 10^5 states without features of its own: not an 80 GB one-hot array (a
    MemoryError deep in NumPy), but a ValueError that says what to give instead; and the MDP's
    repr does not list one name per state."""
    from npbrs.domains import mdp as mdp_module

    S = 100_000
    succ, probs = np.zeros((S, 2, 1), np.int64), np.ones((S, 2, 1))
    with pytest.raises(ValueError, match=r"one-hot state features .* 100000 states .* give features=\(S, A, D\)"):
        TabularMDP.from_successors(succ, probs)
    small = TabularMDP.from_successors(succ[:40], probs[:40])  # 40 states: one-hot, 40 weights
    assert small.num_features == 40 and small.features.shape == (40, 2, 40)
    text = repr(small)
    assert "state0" in text and "(40 features)" in text and "state39" in text and "state20" not in text
    monkeypatch.setattr(mdp_module, "ONE_HOT_MAX_BYTES", 8 * 40 * 2 * 40 - 1)  # the bound is on the array's bytes
    with pytest.raises(ValueError, match="40 states"):
        TabularMDP.from_successors(succ[:40], probs[:40])


def test_frozenlake_transition_probabilities_match():
    env = gym.make("FrozenLake-v1")
    mdp = TabularMDP.from_gymnasium(env)
    P = mdp.dense_transitions()
    table = env.unwrapped.P
    terminal = {s2 for s in table for a in table[s] for _, s2, _, done in table[s][a] if done}
    assert terminal == {5, 7, 11, 12, 15}
    # no features: one-hot state features, as from_dense gives (every goal can be a skill)
    dense = TabularMDP.from_dense(mdp.dense_transitions())
    np.testing.assert_array_equal(mdp.features, dense.features)
    assert mdp.feature_names == dense.feature_names and mdp.num_features == 16
    own = TabularMDP.from_gymnasium(env, features="env_reward")
    assert own.feature_names == ("env_reward",) and own.features[14, 2, 0] > 0  # right of 14 reaches the goal
    with pytest.raises(ValueError, match="env_reward"):
        TabularMDP.from_gymnasium(env, features="reward")
    for s in range(16):
        for a in range(4):
            expected = np.zeros(16)
            for p, s2, _, _ in table[s][a]:
                expected[s2] += p
            if s in terminal:  # episodes end there: absorbing in the tabular MDP
                expected = np.eye(16)[s]
            np.testing.assert_allclose(P[s, a], expected, atol=1e-12)


@pytest.mark.parametrize("mutate, message", [
    (lambda succ, probs, feats: probs.__setitem__((2, 1, 0), -0.5), "state 2, action 1"),
    (lambda succ, probs, feats: probs.__setitem__((3, 0, 0), probs[3, 0, 0] + 0.3), "state 3, action 0"),
    (lambda succ, probs, feats: succ.__setitem__((4, 2, 1), 99), "state 4, action 2"),
    (lambda succ, probs, feats: feats.__setitem__((1, 2, 0), np.nan), "state 1, action 2"),
])
def test_invalid_mdps_name_state_and_action(mutate, message):
    rng = np.random.default_rng(1)
    mdp = TabularMDP.from_dense(random_dense(rng), features=rng.normal(size=(5, 3, 2)))
    succ, probs, feats = mdp.successors.copy(), mdp.probs.copy(), mdp.features.copy()
    mutate(succ, probs, feats)
    with pytest.raises(ValueError, match=message):
        TabularMDP(successors=succ, probs=probs, features=feats)


def test_bad_discount_and_shapes():
    rng = np.random.default_rng(2)
    P = random_dense(rng)
    with pytest.raises(ValueError, match="discount"):
        TabularMDP.from_dense(P, discount=1.0)
    with pytest.raises(ValueError, match="features"):
        TabularMDP.from_dense(P, features=np.zeros((4, 3, 2)))
    with pytest.raises(ValueError, match="dense transitions"):
        TabularMDP.from_dense(P[:, :, :4])
