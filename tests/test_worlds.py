"""The benchmark worlds (npbrs.domains.worlds): their data, their generating model and its oracle."""

import itertools

import numpy as np
import pytest

from npbrs.domains import Demonstrations
from npbrs.domains.worlds import (WORLDS, SkillProcess, cell_view, grid_mdp, labyrinth, labyrinth_mdp, pair_grid_mdp,
                                  rooms, rooms_mdp, swirl_grid, tabular_grid)

# tiny versions of the four worlds (one solver compilation each)
TINY = {
    "tabular_grid": dict(size=4, num_modes=2, num_trajectories=6, length=30, num_heldout=3, goal_size=1),
    "labyrinth": dict(depth=2, num_trajectories=8, min_length=5, max_length=9, num_heldout=4),
    "rooms": dict(size=5, num_skills=3, num_trajectories=6, min_length=5, max_length=12, num_heldout=3),
    "swirl_grid": dict(size=3, num_trajectories=6, length=30, num_heldout=3),
}


@pytest.fixture(scope="module")
def tiny():
    return {name: WORLDS[name](seed=3, **kwargs) for name, kwargs in TINY.items()}


def brute_force(model, states, actions):
    """log p(actions | states) and the most probable skill sequence, by enumerating every skill
    set and every skill sequence of the generating model."""
    K, T = model.num_skills, len(states)
    pi = np.exp(model.log_policies)
    total, best, best_z = 0.0, -1.0, None
    for m, p_set in enumerate(model.skill_set_probs):
        for z in itertools.product(range(K), repeat=T):
            p = p_set * model.initial_skill[m, z[0]] * pi[z[0], states[0], actions[0]]
            for t in range(1, T):
                at = states[t] if model.transitions.shape[1] > 1 else 0
                p *= model.transitions[m, at, z[t - 1], z[t]] * pi[z[t], states[t], actions[t]]
            total += p
            if p > best:
                best, best_z = p, z
    return np.log(total), np.array(best_z)


def short_pieces(world, lengths=(5, 3, 4)):
    """The first steps of a few training trajectories (ragged, to exercise the padding)."""
    d = world.demos
    return Demonstrations([d.states[i][:n] for i, n in enumerate(lengths)],
                          [d.actions[i][:n] for i, n in enumerate(lengths)],
                          [d.skills[i][:n] for i, n in enumerate(lengths)])


# ------------------------------------------------------------------------------ the data
@pytest.mark.parametrize("name", sorted(TINY))
def test_the_same_seed_gives_the_same_world_and_another_seed_another(name, tiny):
    again = WORLDS[name](seed=3, **TINY[name])
    world = tiny[name]
    assert again.demos == world.demos and again.heldout == world.heldout
    np.testing.assert_array_equal(again.model.log_policies, world.model.log_policies)
    np.testing.assert_array_equal(again.domain.skill_weights, world.domain.skill_weights)
    other = WORLDS[name](seed=4, **TINY[name])
    assert other.demos != world.demos and other.heldout != world.heldout
    assert world.demos != world.heldout


@pytest.mark.parametrize("name", sorted(TINY))
def test_the_demonstrations_are_valid_and_have_the_requested_sizes(name, tiny):
    world, sizes = tiny[name], TINY[name]
    mdp, K = world.mdp, world.model.num_skills
    for demos, n in [(world.demos, sizes["num_trajectories"]), (world.heldout, sizes["num_heldout"])]:
        demos.validate(mdp, check_transitions=True)
        assert demos.num_trajectories == n
        low, high = (sizes["length"],) * 2 if "length" in sizes else (sizes["min_length"], sizes["max_length"])
        assert np.all((demos.lengths >= low) & (demos.lengths <= high))
        assert all(np.all((z >= 0) & (z < K)) for z in demos.skills)
    np.testing.assert_array_equal(mdp.features, np.repeat(np.eye(mdp.num_states)[:, None], mdp.num_actions, 1))
    assert world.domain.skill_weights.shape == (K, mdp.num_states) == world.model.log_policies.shape[:2]
    np.testing.assert_allclose(np.exp(world.model.log_policies).sum(-1), 1.0)


def test_the_full_sized_worlds_have_the_published_shapes():
    maze = labyrinth_mdp()  # depth 6: 63 junctions and 64 end nodes
    assert (maze.num_states, maze.num_actions) == (127, 4) and maze.initial[0] == 1.0
    children = maze.successors[:, :2, 0]
    assert np.sum(children[:, 0] != np.arange(127)) == 63  # junctions have a left child ...
    np.testing.assert_array_equal(maze.successors[1:, 2, 0], (np.arange(1, 127) - 1) // 2)  # ... all a parent
    assert (grid_mdp().num_states, grid_mdp().num_actions) == (25, 5)
    assert (rooms_mdp().num_states, rooms_mdp().num_actions) == (104, 5)
    pairs = pair_grid_mdp()  # 25 cells entered from themselves, 40 neighbouring pairs each way
    assert (pairs.num_states, pairs.num_actions) == (105, 5)


def test_labyrinth_trajectories_start_at_the_entrance(tiny):
    assert all(s[0] == 0 for s in tiny["labyrinth"].demos.states)


def test_each_rooms_trajectory_uses_its_own_two_or_three_skills():
    world = rooms(seed=0, size=5, num_skills=5, num_trajectories=40, min_length=60, max_length=80, num_heldout=1)
    used = [np.unique(z).size for z in world.demos.skills]
    assert max(used) <= 3 and min(used) >= 1 and np.mean(np.array(used) >= 2) > 0.8
    assert np.unique(np.concatenate(world.demos.skills)).size == 5
    assert world.model.skill_sets.sum(-1).tolist() == [2] * 10 + [3] * 10


@pytest.mark.parametrize("rate", [0.05, 0.12])
def test_the_gridworld_switches_at_the_requested_rate_mostly_at_the_goals(rate):
    world = tabular_grid(seed=1, num_trajectories=60, length=200, num_heldout=1, switch_rate=rate)
    switches = [np.diff(z) != 0 for z in world.demos.skills]
    observed = np.mean(np.concatenate(switches))
    assert abs(observed - rate) < 0.15 * rate, observed
    # where the switches happen: on entering the current mode's goal block, goal_factor times likelier
    goal = world.domain.skill_weights > 0  # (K, S)
    at_goal = np.concatenate([goal[z[:-1], s[1:]] for z, s in zip(world.demos.skills, world.demos.states)])
    switched = np.concatenate(switches)
    ratio = switched[at_goal].mean() / switched[~at_goal].mean()
    assert 4 < ratio < 25, ratio
    assert world.params["switch_at_goal"] == pytest.approx(10 * world.params["switch_elsewhere"])


def test_the_pair_grid_moves_from_pair_to_pair_and_starts_without_a_move():
    mdp, size = pair_grid_mdp(4), 4
    v = mdp.state_vectors.astype(int)  # (previous row, previous column, row, column)
    assert np.all(np.abs(v[:, :2] - v[:, 2:]).sum(-1) <= 1)  # the previous cell is the cell or a neighbour
    assert len({tuple(r) for r in v}) == mdp.num_states
    np.testing.assert_array_equal(v[mdp.initial > 0][:, :2], v[mdp.initial > 0][:, 2:])
    assert np.sum(mdp.initial > 0) == size * size and np.allclose(mdp.initial[mdp.initial > 0], 1 / 16)
    # from (p, c) each action leads to (c, c') with c' the cell the move reaches on the plain grid
    cells = grid_mdp(size)
    nxt = v[mdp.successors[:, :, 0]]  # (S, A, 4)
    np.testing.assert_array_equal(nxt[..., :2], np.broadcast_to(v[:, None, 2:], nxt[..., :2].shape))
    c = v[:, 2] * size + v[:, 3]
    np.testing.assert_array_equal(nxt[..., 2] * size + nxt[..., 3], cells.successors[c, :, 0])


def test_the_swirl_grid_rewards_pairs_and_switches_at_the_requested_rate_mostly_at_the_goals():
    world = swirl_grid(seed=1, size=4, num_trajectories=60, length=200, num_heldout=1)
    v = world.mdp.state_vectors.astype(int)
    for states in world.demos.states:  # the observed walk on the cells: each pair's previous cell is the last cell
        np.testing.assert_array_equal(v[states[1:], :2], v[states[:-1], 2:])
    # the modes' rewards differ between pairs that enter the same cell (a move's reward)
    w = world.domain.skill_weights
    c = v[:, 2] * 4 + v[:, 3]
    assert all(np.ptp(w[k, c == cell]) > 0.1 for k in range(2) for cell in range(16))
    assert world.params["switch_at_goal"] == pytest.approx(10 * world.params["switch_elsewhere"])
    switched = np.concatenate([np.diff(z) != 0 for z in world.demos.skills])
    assert abs(switched.mean() - 0.05) < 0.15 * 0.05, switched.mean()
    goal = np.array([0, 15])  # water: top-left; home: bottom-right
    at_goal = np.concatenate([c[s[1:]] == goal[z[:-1]] for z, s in zip(world.demos.skills, world.demos.states)])
    ratio = switched[at_goal].mean() / switched[~at_goal].mean()
    assert 4 < ratio < 25, ratio


def test_the_cell_view_is_the_same_walk_on_the_plain_grid(tiny):
    world = tiny["swirl_grid"]
    mdp, demos, heldout = cell_view(world)
    v = world.mdp.state_vectors.astype(int)
    assert mdp.num_states == 9 and mdp.fingerprint() == grid_mdp(3).fingerprint()
    for view, pairs in [(demos, world.demos), (heldout, world.heldout)]:
        view.validate(mdp, check_transitions=True)
        for a, b in [(view.actions, pairs.actions), (view.skills, pairs.skills)]:
            assert all(np.array_equal(x, y) for x, y in zip(a, b)) and len(a) == len(b)
        for cells, states in zip(view.states, pairs.states):
            np.testing.assert_array_equal(cells, v[states, 2] * 3 + v[states, 3])


# ---------------------------------------------------------------------------- the oracle
def random_process(seed=0, S=4, A=3, K=3):
    """A generating model with every feature at work: the skill sets of two or more skills with
    unequal probabilities, state-dependent transitions that are not sticky, random policies."""
    rng = np.random.default_rng(seed)
    sets = np.array([[(m >> k) & 1 for k in range(K)] for m in range(1, 2 ** K)], dtype=bool)
    sets = sets[sets.sum(-1) >= 2]
    M = len(sets)
    trans = rng.dirichlet(np.ones(K), size=(M, S, K)) * sets[:, None, None, :]
    trans /= trans.sum(-1, keepdims=True)
    init = rng.dirichlet(np.ones(K), size=M) * sets
    logits = rng.normal(size=(K, S, A))
    return SkillProcess(log_policies=logits - np.log(np.exp(logits).sum(-1, keepdims=True)), skill_sets=sets,
                        skill_set_probs=rng.dirichlet(np.full(M, 0.3)),  # far from uniform: the sets' prior counts
                        initial_skill=init / init.sum(-1, keepdims=True), transitions=trans)


def cases(tiny, name):
    """A generating model and short, ragged demonstrations (padding exercised) to score."""
    if name == "random":
        rng = np.random.default_rng(1)
        lengths = (6, 2, 3, 2, 4, 2, 5, 3, 2, 2)
        return random_process(), Demonstrations([rng.integers(4, size=n) for n in lengths],
                                                [rng.integers(3, size=n) for n in lengths])
    return tiny[name].model, short_pieces(tiny[name])


@pytest.mark.parametrize("name", sorted(TINY) + ["random"])
def test_the_forward_algorithm_equals_enumeration_of_skill_sequences(name, tiny):
    model, pieces = cases(tiny, name)
    forward = model.log_likelihoods(pieces)
    exact = [brute_force(model, s, a)[0] for s, a in zip(pieces.states, pieces.actions)]
    np.testing.assert_allclose(forward, exact, rtol=1e-10)
    assert model.log_likelihood_per_step(pieces) == pytest.approx(sum(exact) / pieces.num_steps)


@pytest.mark.parametrize("name", sorted(TINY) + ["random"])
def test_viterbi_equals_the_most_probable_sequence_by_enumeration(name, tiny):
    model, pieces = cases(tiny, name)
    for path, s, a in zip(model.viterbi(pieces), pieces.states, pieces.actions):
        np.testing.assert_array_equal(path, brute_force(model, s, a)[1])


@pytest.mark.parametrize("name", sorted(TINY))
def test_the_oracle_scores_the_held_out_set_and_segments_the_training_set(name, tiny):
    world = tiny[name]
    oracle = world.oracle()
    assert oracle.heldout_ll == pytest.approx(world.model.log_likelihood_per_step(world.heldout))
    assert -np.log(world.mdp.num_actions) < oracle.heldout_ll < 0
    assert [len(p) for p in oracle.viterbi] == world.demos.lengths.tolist()
    truth = np.concatenate(world.demos.skills)
    assert oracle.viterbi_accuracy == pytest.approx(np.mean(np.concatenate(oracle.viterbi) == truth))
    assert oracle.viterbi_accuracy > 0.8


def test_the_state_independent_model_counts_the_true_switches():
    # a model whose switching already ignores the state (one set): from many of its own
    # demonstrations, state_independent gives back its transitions; its rows are the counted
    # frequencies exactly (checked on a hand count)
    rng = np.random.default_rng(0)
    K, S, A = 3, 4, 3
    trans = np.array([[0.8, 0.15, 0.05], [0.1, 0.7, 0.2], [0.3, 0.3, 0.4]])
    logits = rng.normal(size=(K, S, A))
    model = SkillProcess(log_policies=logits - np.log(np.exp(logits).sum(-1, keepdims=True)),
                         skill_sets=np.ones((1, K), bool), skill_set_probs=np.ones(1),
                         initial_skill=np.full((1, K), 1 / K), transitions=trans[None, None])
    demos = model.sample(grid_mdp(2), [400] * 50, rng)
    fitted = model.state_independent(demos)
    assert fitted.transitions.shape == (1, 1, K, K)
    np.testing.assert_allclose(fitted.transitions[0, 0], trans, atol=0.02)
    z = [np.array([0, 0, 1, 2]), np.array([2, 2, 0])]
    counts = np.array([[1, 1, 0], [0, 0, 1], [1, 0, 1]], float) + 1e-3
    np.testing.assert_allclose(model.state_independent(Demonstrations(z, z, z)).transitions[0, 0],
                               counts / counts.sum(-1, keepdims=True))
    with pytest.raises(ValueError, match="no true skills"):
        model.state_independent(Demonstrations(z, z))
    with pytest.raises(ValueError, match="trajectory 1's skills"):
        model.state_independent(Demonstrations(z, z, [z[0], np.array([2, 3, 0])]))


def test_sticky_switching_scores_below_the_truth_where_switching_depends_on_the_state():
    # the labyrinth's skills end on reaching their goal; under sticky switching with the true
    # policies the held-out likelihood is lower (on these sizes by about 0.07 nats per step)
    world = labyrinth(seed=0, depth=3, num_trajectories=300, num_heldout=300)
    oracle = world.oracle()
    assert oracle.sticky_heldout_ll < oracle.heldout_ll - 0.02
    assert oracle.sticky_heldout_ll == pytest.approx(
        world.model.state_independent(world.demos).log_likelihood_per_step(world.heldout))
    assert 0.5 < oracle.sticky_viterbi_accuracy <= 1.0


@pytest.mark.parametrize("name", sorted(TINY))
def test_the_experts_are_boltzmann_in_the_soft_q_of_the_domains_reward_weights(name, tiny):
    # pi(a | s) = exp(Q(s, a) - V(s)) with Q = r + gamma P V: then V(s) - gamma sum_s' P(s' | s, a) V(s')
    # = r(s, a) - log pi(a | s) for every action, S x A equations in S unknowns, solvable only at the truth
    world = tiny[name]
    mdp, log_pi = world.mdp, world.model.log_policies
    P, S, A = mdp.dense_transitions(), mdp.num_states, mdp.num_actions
    lhs = (np.eye(S)[:, None, :] - mdp.discount * P).reshape(S * A, S)
    for k, reward in enumerate(mdp.reward(world.domain.skill_weights)):
        rhs = (reward - log_pi[k]).reshape(S * A)
        V = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
        np.testing.assert_allclose(lhs @ V, rhs, atol=1e-7)


def test_the_generator_draws_from_the_distribution_the_oracle_scores():
    # depth 1: the entrance and two end nodes; moves are deterministic and every trajectory
    # starts at the entrance, so the actions determine the trajectory and the oracle's
    # p(actions | states) is the probability of the whole trajectory
    n = 20000
    world = labyrinth(seed=0, depth=1, num_trajectories=n, min_length=3, max_length=3, num_heldout=1,
                      port_end=0.9, travel_end=0.2)
    actions = np.stack(world.demos.actions)
    codes, counts = np.unique(actions @ np.array([16, 4, 1]), return_counts=True)
    outcomes = np.array(list(itertools.product(range(4), repeat=3)))
    states = []
    for a in outcomes:  # the states the actions lead to
        states.append([0])
        for action in a[:-1]:
            states[-1].append(int(world.mdp.successors[states[-1][-1], action, 0]))
    probs = np.exp(world.model.log_likelihoods(Demonstrations(states, list(outcomes))))
    assert probs.sum() == pytest.approx(1.0)
    observed = np.zeros(64)
    observed[codes] = counts / n
    z = np.abs(observed - probs) / np.sqrt(probs * (1 - probs) / n)
    assert z.max() < 4.5, (z.max(), outcomes[z.argmax()])


# ------------------------------------------------------------------------------ arguments
@pytest.mark.parametrize("make, kwargs, name", [
    (tabular_grid, dict(seed=-1), "seed"),
    (tabular_grid, dict(size=1), "size"),
    (tabular_grid, dict(num_modes=5), "num_modes"),
    (tabular_grid, dict(num_trajectories=0), "num_trajectories"),
    (tabular_grid, dict(length=1), "length"),
    (tabular_grid, dict(switch_rate=1.5), "switch_rate"),
    (tabular_grid, dict(goal_factor=0.5), "goal_factor"),
    (tabular_grid, dict(goal_size=3), "goal_size"),
    (tabular_grid, dict(inverse_temperature=0.0), "inverse_temperature"),
    (tabular_grid, dict(slip=-0.1), "slip"),
    (tabular_grid, dict(discount=1.0), "discount"),
    (labyrinth, dict(depth=0), "depth"),
    (labyrinth, dict(min_length=10, max_length=5), "max_length"),
    (labyrinth, dict(num_heldout=2.5), "num_heldout"),
    (labyrinth, dict(port_end=2.0), "port_end"),
    (labyrinth, dict(explore_scale=float("nan")), "explore_scale"),
    (rooms, dict(num_skills=9), "num_skills"),
    (rooms, dict(skills_per_trajectory=(2, 6)), "skills_per_trajectory"),
    (rooms, dict(switch_prob=-0.5), "switch_prob"),
    (rooms, dict(size=4), "size"),
    (swirl_grid, dict(size=1), "size"),
    (swirl_grid, dict(length=1), "length"),
    (swirl_grid, dict(switch_rate=0.0), "switch_rate"),
    (swirl_grid, dict(goal_factor=0.9), "goal_factor"),
    (swirl_grid, dict(pair_scale=-1.0), "pair_scale"),
    (swirl_grid, dict(inverse_temperature=-1.0), "inverse_temperature"),
    (swirl_grid, dict(discount=1.5), "discount"),
])
def test_bad_arguments_raise_a_value_error_naming_them(make, kwargs, name):
    with pytest.raises(ValueError, match=name):
        make(**kwargs)
