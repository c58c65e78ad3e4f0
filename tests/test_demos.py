import os

import numpy as np
import pytest

from npbrs.domains import TabularMDP
from npbrs.domains.demos import Demonstrations, generate_demonstrations
from npbrs.domains.domain import Domain
from npbrs.domains.registry import DOMAINS, get_domain


def toy_domain(seed=0, S=8, A=3, D=4, K=3):
    rng = np.random.default_rng(seed)
    P = rng.random((S, A, S)) * (rng.random((S, A, S)) < 0.5)
    P[..., 0] += 1e-3
    mdp = TabularMDP.from_dense(P / P.sum(-1, keepdims=True), features=rng.normal(size=(S, A, D)), discount=0.9)
    return Domain(name="toy", mdp=mdp, skill_names=tuple("ABC"[:K]), skill_weights=rng.normal(size=(K, D)))


@pytest.fixture(scope="module")
def domain():
    return toy_domain()


@pytest.fixture(scope="module")
def demos(domain):
    return generate_demonstrations(domain, num_trajectories=16, length=500, switch_prob=0.02, seed=0)


def test_generated_demonstrations_have_the_requested_shapes(demos, domain):
    assert demos.num_trajectories == 16
    np.testing.assert_array_equal(demos.lengths, [500] * 16)
    states, actions, mask = demos.padded()
    assert states.shape == actions.shape == mask.shape == (16, 500) and mask.all()
    assert demos.padded_skills().shape == (16, 500)
    demos.validate(domain.mdp, check_transitions=True)


def test_experts_act_by_their_skill_and_the_mdp_moves(demos, domain):
    policies = domain.expert_policies()
    P = domain.mdp.dense_transitions()
    for s, a, k in zip(demos.states, demos.actions, demos.skills):
        np.testing.assert_array_equal(a, policies[k, s])
        assert np.all(P[s[:-1], a[:-1], s[1:]] > 0)


def test_the_skill_switch_rate_is_switch_prob(domain):
    p = 0.05
    demos = generate_demonstrations(domain, num_trajectories=20, length=300, switch_prob=p, seed=1)
    n = 20 * 299
    switches = sum(np.count_nonzero(np.diff(k)) for k in demos.skills)
    assert abs(switches - n * p) < 4 * np.sqrt(n * p * (1 - p))  # binomial, 4 standard deviations
    # every skill is used, and the start skills are spread over them
    assert set(np.concatenate(demos.skills)) == {0, 1, 2}


def test_stochastic_experts_and_one_skill(domain):
    S, A = domain.mdp.num_states, domain.mdp.num_actions
    uniform = np.full((2, S, A), 1.0 / A)
    demos = generate_demonstrations(domain, num_trajectories=4, length=50, seed=2, policies=uniform)
    assert len(np.unique(np.concatenate(demos.actions))) == A
    single = generate_demonstrations(domain, num_trajectories=3, length=20, switch_prob=0.5, seed=2,
                                     policies=domain.expert_policies()[:1])
    assert all(np.all(k == 0) for k in single.skills)


def test_the_same_seed_gives_the_same_demonstrations(domain, demos):
    again = generate_demonstrations(domain, num_trajectories=16, length=500, switch_prob=0.02, seed=0)
    other = generate_demonstrations(domain, num_trajectories=16, length=500, switch_prob=0.02, seed=1)
    assert again == demos and again.fingerprint() == demos.fingerprint()
    assert other != demos and other.fingerprint() != demos.fingerprint()


def test_npz_round_trip_is_exact(tmp_path, demos):
    path = tmp_path / "demos.npz"
    demos.save(path)
    loaded = Demonstrations.load(path)
    assert loaded == demos and loaded.fingerprint() == demos.fingerprint()
    with np.load(path) as data:
        assert set(data.files) == {"states", "actions", "lengths", "skills", "mdp_fingerprint"}
    assert loaded.mdp_fingerprint == demos.mdp_fingerprint is not None
    assert os.listdir(tmp_path) == ["demos.npz"]  # no temporary file left behind

    ragged = Demonstrations([[0, 1, 2], [3, 4]], [[1, 1, 0], [2, 0]])
    ragged.save(tmp_path / "ragged.npz")
    loaded = Demonstrations.load(tmp_path / "ragged.npz")
    assert loaded == ragged and loaded.skills is None
    np.testing.assert_array_equal(loaded.lengths, [3, 2])


def test_padding(tmp_path):
    demos = Demonstrations([[0, 1, 2], [3, 4]], [[1, 1, 0], [2, 0]], skills=[[0, 0, 1], [1, 1]])
    states, actions, mask = demos.padded(pad_value=7)
    np.testing.assert_array_equal(states, [[0, 1, 2], [3, 4, 7]])
    np.testing.assert_array_equal(actions, [[1, 1, 0], [2, 0, 7]])
    np.testing.assert_array_equal(mask, [[True, True, True], [True, True, False]])
    np.testing.assert_array_equal(demos.padded_skills(), [[0, 0, 1], [1, 1, -1]])


def test_a_failed_save_leaves_nothing_behind(tmp_path, demos, monkeypatch):
    def broken(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", broken)
    with pytest.raises(OSError):
        demos.save(tmp_path / "demos.npz")
    assert os.listdir(tmp_path) == []


GOOD_S = [[0, 1, 2, 3], [4, 5, 6, 7, 0]]
GOOD_A = [[0, 1, 2, 0], [1, 1, 1, 2, 0]]


@pytest.mark.parametrize("states, actions, skills, message", [
    ([[0, 1, 2, 3], [4, 5, -6, 7, 0]], GOOD_A, None, "trajectory 1, step 2: state -6 is negative"),
    ([[0, 1, 2.5, 3], GOOD_S[1]], GOOD_A, None, "trajectory 0, step 2: state 2.5 is not an integer"),
    (GOOD_S, [[0, 1, 2, 0], [1, 1, np.nan, 2, 0]], None, "trajectory 1, step 2: action nan is not an integer"),
    (GOOD_S, [[0, 1, 2], GOOD_A[1]], None, "trajectory 0: 4 states but 3 actions"),
    (GOOD_S, GOOD_A, [[0, 0, 0, 0], [1, 1]], "trajectory 1: 5 states but 2 skills"),
    (GOOD_S, GOOD_A, [[0, 0, 0, 0], [1, 1, -1, 1, 1]], "trajectory 1, step 2: skill -1 is negative"),
    ([[0, 1], [3]], [[0, 1], [2]], None, "trajectory 1: 1 step; a trajectory needs at least 2"),
    ([[0, 1], []], [[0, 1], []], None, "trajectory 1: 0 steps"),
    ([[0, 1], [[1, 2]]], [[0, 1], [[1, 2]]], None, "trajectory 1: states must be a 1-D sequence"),
    (GOOD_S, GOOD_A[:1], None, "2 state trajectories but 1 action trajectories"),
    ([["a", "b"]], [[0, 1]], None, "trajectory 0: states must be integers"),
])
def test_bad_demonstrations_name_the_trajectory_and_step(states, actions, skills, message):
    with pytest.raises(ValueError, match=message):
        Demonstrations(states, actions, skills)


@pytest.mark.parametrize("states, actions, message", [
    (GOOD_S, [[0, 1, 2, 0], [1, 1, 1, 5, 0]], "trajectory 1, step 3: action 5 is outside 0..2"),
    ([[0, 1, 2, 3], [4, 5, 6, 8, 0]], GOOD_A, "trajectory 1, step 3: state 8 is outside 0..7"),
])
def test_validation_against_an_mdp_names_the_trajectory_and_step(domain, states, actions, message):
    with pytest.raises(ValueError, match=message):
        Demonstrations(states, actions).validate(domain.mdp)


def test_validation_of_transitions():
    # a deterministic chain: action 0 stays, action 1 moves right
    S = 4
    P = np.zeros((S, 2, S))
    P[np.arange(S), 0, np.arange(S)] = 1
    P[np.arange(S), 1, np.minimum(np.arange(S) + 1, S - 1)] = 1
    mdp = TabularMDP.from_dense(P)
    Demonstrations([[0, 0, 1, 2]], [[0, 1, 1, 0]]).validate(mdp, check_transitions=True)
    with pytest.raises(ValueError, match="trajectory 0, step 1: state 0 with action 1 cannot lead to state 2"):
        Demonstrations([[0, 0, 2, 2]], [[0, 1, 1, 0]]).validate(mdp, check_transitions=True)


def test_loading_a_bad_file_says_what_is_wrong(tmp_path):
    np.savez(tmp_path / "a.npz", states=np.arange(5), actions=np.zeros(5, int))
    with pytest.raises(ValueError, match="missing array lengths"):
        Demonstrations.load(tmp_path / "a.npz")
    np.savez(tmp_path / "b.npz", states=np.arange(5), actions=np.zeros(5, int), lengths=np.array([3, 3]))
    with pytest.raises(ValueError, match="lengths sum to 6 but states has shape"):
        Demonstrations.load(tmp_path / "b.npz")


def test_unknown_domains_list_the_known_ones():
    with pytest.raises(ValueError, match="unknown domain 'nope'; known domains: .*highway.*quadcopter"):
        get_domain("nope")


def test_the_generate_command_writes_a_file(tmp_path, capsys, monkeypatch):
    import argparse

    from npbrs.inference.cli import generate as cli_generate

    monkeypatch.setitem(DOMAINS, "toy-test", toy_domain)  # as register_domain does, undone afterwards
    parser = argparse.ArgumentParser()
    cli_generate.add_parser(parser.add_subparsers(dest="command", required=True))
    out = tmp_path / "toy.npz"
    args = parser.parse_args(["generate", "toy-test", "--trajectories", "3", "--length", "40", "--switch-prob",
                              "0.1", "--seed", "4", "-o", str(out)])
    assert args.func(args) == 0
    expected = generate_demonstrations(toy_domain(), num_trajectories=3, length=40, switch_prob=0.1, seed=4)
    assert Demonstrations.load(out) == expected
    assert "3 trajectories" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        parser.parse_args(["generate", "toy-test", "--switch-prob", "1.5"])


def test_demonstrations_remember_their_mdp_and_refuse_another(tmp_path):
    highway, quadcopter = get_domain("highway"), get_domain("quadcopter")
    demos = generate_demonstrations(highway, num_trajectories=2, length=20, seed=0)
    assert demos.mdp_fingerprint == highway.mdp.fingerprint() != quadcopter.mdp.fingerprint()
    demos.validate(highway.mdp)
    # highway states (0..1079) are in the quadcopter's range (0..11663): only the record tells
    with pytest.raises(ValueError, match="another MDP"):
        demos.validate(quadcopter.mdp)
    demos.save(tmp_path / "d.npz")
    back = Demonstrations.load(tmp_path / "d.npz")
    assert back == demos and back.mdp_fingerprint == demos.mdp_fingerprint
    with pytest.raises(ValueError, match="another MDP"):
        back.validate(quadcopter.mdp)
    # without a record (a user's own arrays) only the ranges are checked
    Demonstrations(demos.states, demos.actions).validate(quadcopter.mdp)


def test_same_trajectories_compares_states_and_actions_not_the_true_skills():
    def demos(states, actions, skills=None):
        return Demonstrations([np.array(x) for x in states], [np.array(x) for x in actions],
                              None if skills is None else [np.array(x) for x in skills])

    a = demos([[0, 1], [2, 0, 1]], [[1, 0], [0, 1, 1]])
    assert a.same_trajectories(demos([[0, 1], [2, 0, 1]], [[1, 0], [0, 1, 1]], [[0, 0], [1, 1, 0]]))
    assert not a.same_trajectories(demos([[0, 1], [2, 0, 1]], [[1, 1], [0, 1, 1]]))  # an action
    assert not a.same_trajectories(demos([[0, 1, 2], [0, 1]], [[1, 0, 0], [1, 1]]))  # the same steps, cut elsewhere
    assert not a.same_trajectories(demos([[0, 1]], [[1, 0]]))
