"""The scalable open gridworld (npbrs.domains.gridworld): its dynamics and features against a
brute-force construction, and the soft solve on it against the dense NumPy reference."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from npbrs.domains import make_soft_solver
from npbrs.domains.gridworld import ACTIONS, goal_cells, open_gridworld

from test_solvers import numpy_soft_vi

# what the actions mean, written out independently of the module: (d_row, d_col), row 0 on top
DIRECTIONS = {"stay": (0, 0), "north": (-1, 0), "south": (1, 0), "east": (0, 1), "west": (0, -1)}


def brute_force(L, slip, num_features, seed):
    """Dense P[s, a, s'] and state features, cell by cell: a move goes where it is aimed with
    probability 1 - slip and to each perpendicular side with slip / 2; staying is certain; a
    move into the border stays put. Feature d: 1 - manhattan(s, goal_d) / (2 (L - 1))."""
    S = L * L
    P = np.zeros((S, len(ACTIONS), S))

    def cell(r, c, dr, dc):
        return min(max(r + dr, 0), L - 1) * L + min(max(c + dc, 0), L - 1)

    for r in range(L):
        for c in range(L):
            for a, name in enumerate(ACTIONS):
                dr, dc = DIRECTIONS[name]
                if (dr, dc) == (0, 0):
                    P[r * L + c, a, r * L + c] += 1.0
                    continue
                P[r * L + c, a, cell(r, c, dr, dc)] += 1.0 - slip
                for sr, sc in ((dc, dr), (-dc, -dr)):  # the two perpendicular directions
                    P[r * L + c, a, cell(r, c, sr, sc)] += slip / 2
    goals = goal_cells(L, num_features, seed)
    phi = np.zeros((S, num_features))
    for s in range(S):
        for d, g in enumerate(goals):
            phi[s, d] = 1.0 - (abs(s // L - g // L) + abs(s % L - g % L)) / (2.0 * (L - 1))
    return P, phi


@pytest.mark.parametrize("L, slip, num_features, seed", [(4, 0.1, 4, 0), (5, 0.3, 2, 7), (3, 0.0, 9, 1)])
def test_small_world_equals_brute_force_construction(L, slip, num_features, seed):
    mdp = open_gridworld(L, num_features=num_features, slip=slip, discount=0.9, seed=seed)
    P, phi = brute_force(L, slip, num_features, seed)
    assert (mdp.num_states, mdp.num_actions, mdp.num_features) == (L * L, 5, num_features)
    np.testing.assert_allclose(mdp.dense_transitions(), P, atol=1e-15)
    np.testing.assert_allclose(mdp.features, np.repeat(phi[:, None, :], 5, axis=1), atol=1e-15)
    np.testing.assert_array_equal(mdp.state_vectors, np.array([divmod(s, L) for s in range(L * L)], float))
    goals = goal_cells(L, num_features, seed)
    assert len(set(goals.tolist())) == num_features
    np.testing.assert_allclose(mdp.features[goals, 0, np.arange(num_features)], 1.0)
    assert mdp.discount == 0.9
    np.testing.assert_allclose(mdp.initial, 1.0 / (L * L))


def test_transitions_are_valid_probabilities_at_a_larger_size():
    L = 200
    mdp = open_gridworld(L, slip=0.25)
    probs, succ = mdp.probs, mdp.successors
    assert succ.shape == (L * L, 5, 3) and succ.min() >= 0 and succ.max() < L * L
    assert probs.min() >= 0
    np.testing.assert_allclose(probs.sum(-1), 1.0, atol=1e-12)
    # every successor with positive probability is the cell itself or one of its 4 neighbours
    rows, cols = np.divmod(np.arange(L * L), L)
    dist = np.abs(rows[succ] - rows[:, None, None]) + np.abs(cols[succ] - cols[:, None, None])
    assert np.all(dist[probs > 0] <= 1)
    # away from the border, north moves one row up with probability 1 - slip
    s = 5 * L + 7
    assert succ[s, ACTIONS.index("north"), 0] == s - L and probs[s, ACTIONS.index("north"), 0] == 0.75


def test_soft_solve_equals_dense_reference():
    mdp = open_gridworld(5, num_features=3, slip=0.2, discount=0.95, seed=3)
    P = mdp.dense_transitions()
    solver = make_soft_solver(mdp, tol=1e-12)
    theta = np.array([[5.0, 0.0, 0.0], [0.0, -2.0, 4.0], [1.0, 1.0, 1.0]])
    rewards = np.asarray(solver.rewards(theta))
    res = solver(rewards)
    for k in range(len(theta)):
        V_ref, Q_ref = numpy_soft_vi(P, rewards[k], mdp.discount)
        scale = np.abs(V_ref).max()
        np.testing.assert_allclose(np.asarray(res.V[k]), V_ref, rtol=1e-9, atol=1e-9 * scale)
        np.testing.assert_allclose(np.asarray(res.Q[k]), Q_ref, rtol=1e-9, atol=1e-9 * scale)
    assert np.all(np.asarray(res.residual) <= 1e-12)


@pytest.mark.parametrize("transpose", [False, True])
def test_policy_evaluation_solves_the_linear_system(transpose):
    """(I - gamma P_pi) x = b (or its transpose), as the Newton steps and the implicit
    derivatives use it, against a dense solve: its preconditioned GMRES must return the
    solution, not merely a Newton step that the next backup corrects.

    Through the solver's derivatives, whose tangent is dV = (I - gamma P_pi)^-1 sum_a pi_a dr_a
    at the fixed point's policy pi: a tangent dr(s, a) = b(s) gives x = dV (forward mode), and
    a cotangent b of V gives dr(s, a) = pi(s, a) x(s) with x the transposed system's solution
    (reverse mode). The rewards are made so that the fixed point's policy is a random one:
    r = log pi + V0 - gamma E[V0] has the soft values V0 and the Boltzmann policy pi."""
    mdp = open_gridworld(4, slip=0.3, discount=0.95, seed=1)
    rng = np.random.default_rng(0)
    pi = rng.dirichlet(np.ones(5), size=(2, 16))  # (K, S, A)
    b = rng.normal(size=(2, 16))
    with jax.enable_x64(True):
        # its derivatives' linear solves with the options of the solve this test once called directly
        # (relative tolerance 1e-13, a Neumann preconditioner of degree 4, GMRES(5), 40 restarts)
        solver = make_soft_solver(mdp, operator="sparse", grad_tol=1e-13, precondition_degree=4, krylov_dim=5,
                                  max_restarts=40)
        V0 = rng.normal(size=(2, 16))
        rewards = jnp.asarray(np.log(pi) + V0[..., None]) - 0.95 * solver.expected_next_value(jnp.asarray(V0))
        values = jax.jit(lambda r: solver(r).V)
        if transpose:
            V, pullback = jax.vjp(values, rewards)
            x = pullback(jnp.asarray(b))[0].sum(-1)  # sum_a pi(s, a) x(s) = x(s)
        else:
            V, x = jax.jvp(values, (rewards,), (jnp.broadcast_to(jnp.asarray(b)[..., None], rewards.shape),))
        res = solver(rewards)
    np.testing.assert_allclose(np.asarray(V), V0, rtol=1e-8, atol=1e-8)
    policy = np.exp(np.asarray(res.Q) - np.asarray(res.V)[..., None])  # the policy the derivatives use
    np.testing.assert_allclose(policy, pi, rtol=1e-7)
    P = mdp.dense_transitions()
    for k in range(2):
        M = np.eye(16) - 0.95 * np.einsum("sa,sat->st", policy[k], P)
        np.testing.assert_allclose(np.asarray(x[k]), np.linalg.solve(M.T if transpose else M, b[k]), rtol=1e-10,
                                   atol=1e-10)


@pytest.mark.parametrize("kwargs, message", [
    (dict(L=1), "L must be in 2..4096"),
    (dict(L=5000), "L must be in 2..4096"),
    (dict(L=4.0), "L must be an integer"),
    (dict(L=True), "L must be an integer"),
    (dict(L=4, num_features=0), "num_features must be in 1..16"),
    (dict(L=4, num_features=17), "num_features must be in 1..16"),
    (dict(L=4, slip=-0.1), "slip must lie in"),
    (dict(L=4, slip=1.5), "slip must lie in"),
    (dict(L=4, slip=float("nan")), "slip must lie in"),
    (dict(L=4, slip="0.1"), "slip must be a number"),
    (dict(L=4, discount=1.0), "discount must lie in"),
    (dict(L=4, discount=-0.5), "discount must lie in"),
    (dict(L=4, seed=-1), "seed must be at least 0"),
])
def test_bad_arguments_raise_value_errors_naming_them(kwargs, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(".", r"\.")):
        open_gridworld(**kwargs)
