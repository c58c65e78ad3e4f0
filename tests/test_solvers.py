import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from npbrs.domains import (TabularMDP, greedy_policy, make_soft_solver, next_value_operator,
                           soft_value_iteration, value_iteration)


def random_mdp(seed, S=12, A=3, D=4, gamma=0.9, density=0.4):
    rng = np.random.default_rng(seed)
    P = rng.random((S, A, S)) * (rng.random((S, A, S)) < density)
    P[np.arange(S), :, rng.integers(0, S, S)] += 0.05  # every row has mass
    P /= P.sum(-1, keepdims=True)
    return TabularMDP.from_dense(P, features=rng.normal(size=(S, A, D)), discount=gamma), P


def numpy_soft_vi(P, r, gamma, iters=20000):
    """Plain dense soft value iteration, run to convergence in float64."""
    V = np.zeros(P.shape[0])
    for _ in range(iters):
        Q = r + gamma * P @ V
        m = Q.max(-1)
        V_new = m + np.log(np.exp(Q - m[:, None]).sum(-1))
        if np.max(np.abs(V_new - V)) < 1e-14 * max(1.0, np.abs(V_new).max()):
            V = V_new
            break
        V = V_new
    return V, r + gamma * P @ V


@pytest.fixture(scope="module")
def problem():
    """A random MDP, its dense P, one solver, and reward tables from small to large (the
    Boltzmann policies range from near-uniform to near-deterministic)."""
    mdp, P = random_mdp(0, gamma=0.95)
    rng = np.random.default_rng(10)
    R = np.stack([scale * rng.normal(size=(mdp.num_states, mdp.num_actions)) for scale in (0.01, 1.0, 30.0)])
    return mdp, P, make_soft_solver(mdp, tol=1e-12), R


def test_soft_value_iteration_equals_dense_numpy_reference(problem):
    mdp, P, solver, R = problem
    res = solver(R)
    for k in range(len(R)):
        V_ref, Q_ref = numpy_soft_vi(P, R[k], mdp.discount)
        np.testing.assert_allclose(res.V[k], V_ref, rtol=1e-8, atol=1e-8 * np.abs(V_ref).max())
        np.testing.assert_allclose(res.Q[k], Q_ref, rtol=1e-8, atol=1e-8 * np.abs(V_ref).max())
    # V is exactly logsumexp(Q), so Q - V is a normalised log-policy
    np.testing.assert_allclose(np.exp(np.asarray(res.Q - res.V[..., None])).sum(-1), 1.0, atol=1e-12)
    assert np.all(np.asarray(res.residual) <= 1e-12)


@pytest.mark.parametrize("method, operator", [("newton", "dense"), ("vi", "sparse")])
def test_other_methods_and_operators_equal_the_reference(method, operator):
    mdp, P = random_mdp(2, gamma=0.99)
    r = 5.0 * np.random.default_rng(3).normal(size=(mdp.num_states, mdp.num_actions))
    V_ref, Q_ref = numpy_soft_vi(P, r, mdp.discount)
    res = soft_value_iteration(mdp, r, tol=1e-12, method=method, operator=operator)
    np.testing.assert_allclose(res.V, V_ref, rtol=1e-8, atol=1e-8 * np.abs(V_ref).max())
    np.testing.assert_allclose(res.Q, Q_ref, rtol=1e-8, atol=1e-8 * np.abs(V_ref).max())


def test_batched_solves_equal_single_solves_and_warm_starts_agree(problem):
    mdp, _, solver, R = problem
    batch = solver(R)
    for k in range(len(R)):
        one = solver(R[k])
        np.testing.assert_allclose(batch.V[k], one.V, rtol=1e-11)
    warm = solver(R * 1.001, batch.V)
    cold = solver(R * 1.001)
    np.testing.assert_allclose(warm.V, cold.V, rtol=1e-10)
    assert np.all(np.asarray(warm.num_iter) <= np.asarray(cold.num_iter))
    # leading batch dimensions of any rank
    grid = solver(R.reshape(3, 1, *R.shape[1:]))
    np.testing.assert_allclose(grid.V[:, 0], batch.V, rtol=1e-11)


def test_a_vmapped_solve_is_one_batched_solve_with_the_same_values_and_derivatives(problem):
    """Under vmap the solver folds the mapped axis into its own batch (``fold_vmap``): one solve
    of n x K systems, not a loop batched step by step. Values, reverse-mode gradients and
    forward-mode Jacobians (whose tangents are a vmap too) equal the unmapped ones, and a
    mapped operator (dynamics that differ between members) falls back to a plain vmap."""
    mdp, _, solver, R = problem
    S, D = mdp.num_states, mdp.num_features
    R2 = jnp.asarray(np.stack([R, 0.5 * R[::-1]]))  # (2, 3, S, A)
    np.testing.assert_allclose(jax.jit(jax.vmap(lambda r: solver(r).V))(R2), solver(R2).V, rtol=1e-10)
    loops = [line.split("= while[")[0] for line in str(jax.make_jaxpr(jax.vmap(lambda r: solver(r).V))(R2)).splitlines()
             if "= while[" in line]  # each while loop's results
    # folded: the solve's loops carry the 2 x 3 systems as one axis of 6
    assert loops and any(f"f64[6,{S}]" in out for out in loops) and not any("[2,3," in out for out in loops)
    # nested maps (the chains around a Jacobian's tangents) fold too: 2 x 2 x 3 systems as 12
    R4 = jnp.stack([R2, R2])
    loops = [line.split("= while[")[0] for line in
             str(jax.make_jaxpr(jax.vmap(jax.vmap(lambda r: solver(r).V)))(R4)).splitlines() if "= while[" in line]
    assert any(f"f64[12,{S}]" in out for out in loops) and not any("[2," in out for out in loops)
    # reverse mode under vmap (the transposed derivative solve) against the unmapped batch's
    # gradient (the loss is a sum over the members, so its gradient stacks theirs)
    w = jnp.asarray(np.random.default_rng(5).normal(size=(3, S)))
    loss = lambda r: jnp.sum(w * solver(r).V)  # noqa: E731
    np.testing.assert_allclose(jax.jit(jax.vmap(jax.grad(loss)))(R2), jax.jit(jax.grad(loss))(R2), rtol=1e-8,
                               atol=1e-10)
    # forward mode: jacfwd maps the tangent directions (the derivative solve under vmap); its
    # product with a direction is that direction's plain jvp
    rng = np.random.default_rng(6)
    theta, e = jnp.asarray(rng.normal(size=(3, D))), jnp.asarray(rng.normal(size=(3, D)))
    f = lambda th: jnp.sum(w * solver(solver.rewards(th)).V, -1)  # noqa: E731
    jac = jax.jit(jax.jacfwd(f))(theta)  # (3, 3, D)
    np.testing.assert_allclose(jnp.einsum("ikd,kd->i", jac, e), jax.jit(lambda t, v: jax.jvp(f, (t,), (v,))[1])(theta, e),
                               rtol=1e-8, atol=1e-10)
    # a mapped operator: the solver's arrays stacked twice (the same dynamics), mapped with the rewards
    stacked = jax.tree.map(lambda x: jnp.stack([x, x]), solver)
    mapped = jax.jit(jax.vmap(lambda sv, r: sv(r).V))(stacked, R2)
    np.testing.assert_allclose(mapped, solver(R2).V, rtol=1e-10)


def test_solver_is_pure_and_jittable_inside_lax_loops(problem):
    mdp, _, solver, R = problem

    @jax.jit
    def chain(R):
        def step(v, r):
            res = solver(r, v)
            return res.V, res.V

        return jax.lax.scan(step, jnp.zeros(mdp.num_states), R)[1]

    np.testing.assert_allclose(chain(jnp.asarray(R)), solver(R).V, rtol=1e-10)


def test_the_solves_are_traced_once_per_shape_not_at_every_site(monkeypatch):
    """The Newton loop and the GMRES solve run their Python once per (shapes, options, JAX
    context), not again at every solve site, ``vmap`` fold and derivative rule: a solve under
    ``vmap`` and a forward-mode Jacobian (the sampler's chains and the Fisher information),
    differentiated, ran the Newton loop's Python 7 times and GMRES's 19 before the solves' traces
    were kept (``_soft_newton`` and ``_policy_solve`` are jitted), 4 and 10 after (a tiny fit: 63
    GMRES traces before, 34 after). The bounds leave a little room for JAX's own contexts."""
    from npbrs.domains.solvers import krylov, soft

    calls = {"backup": 0, "gmres": 0}
    # (the Newton loop's soft backups: two a trace, before the loop and in its body)
    for module, name, key in ((soft, "_soft_backup", "backup"), (krylov, "_gmres", "gmres")):
        original = getattr(module, name)

        def counted(*args, _original=original, _key=key, **kwargs):
            calls[_key] += 1
            return _original(*args, **kwargs)

        monkeypatch.setattr(module, name, counted)
    # (shapes no other test uses: the kept traces are per process)
    mdp, _ = random_mdp(3, S=13, A=2, D=3)
    solver = make_soft_solver(mdp)
    r = jnp.asarray(np.random.default_rng(0).normal(size=(2, 13, 2)))

    def loss(r):
        V = jax.vmap(lambda x: solver(x).V)(r)  # folded into one batched solve
        J = jax.jacfwd(lambda x: solver(x).V)(r)  # the tangents folded in
        return jnp.sum(V ** 2) + jnp.sum(J)

    with jax.enable_x64(True):  # as inside npbrs's entry points (traces are kept per context)
        assert jax.jit(jax.grad(loss)).lower(r) is not None
    assert calls["backup"] <= 10 and calls["gmres"] <= 13, calls


@pytest.mark.parametrize("name", ["highway", "quadcopter"])
def test_factored_next_value_operator_equals_successor_gather(name):
    from npbrs.domains import get_domain

    mdp = get_domain(name).mdp
    V = np.random.default_rng(0).normal(size=(2, mdp.num_states))
    factored = next_value_operator(mdp, "factored")(jnp.asarray(V))
    sparse = next_value_operator(mdp, "sparse")(jnp.asarray(V))
    np.testing.assert_allclose(factored, sparse, atol=1e-12)
    # and the expected value is exactly what the successor arrays say
    direct = (V[:, mdp.successors] * mdp.probs).sum(-1)
    np.testing.assert_allclose(sparse, direct, atol=1e-12)


@pytest.mark.parametrize("transpose", [False, True])
def test_the_policy_operator_folds_shared_successors_and_equals_the_dense_matrix(transpose):
    from npbrs.domains.solvers import Columns, predecessors, successor_union

    mdp, P = random_mdp(4, S=12, A=4, density=0.15)
    S, A, B = mdp.successors.shape
    union, slot = successor_union(mdp.successors, mdp.probs)
    used = mdp.probs > 0
    s, a, b = np.nonzero(used)
    # every used (state, action, slot) points at its successor among the state's distinct ones,
    # and each state's distinct successors are exactly the union of its actions'
    np.testing.assert_array_equal(union[slot[a, b, s], s], mdp.successors[s, a, b])
    for state in range(S):
        assert set(union[:, state]) == set(mdp.successors[state][used[state]])
    op = Columns(mdp, "sparse")
    assert op._union is not None and op._union.shape[0] == union.shape[0] < A * B  # the folded form is used
    rng = np.random.default_rng(5)
    pi = rng.random((A, 3, S))
    pi /= pi.sum(0)
    x = rng.normal(size=(3, S))
    P_pi = np.einsum("aks,sat->kst", pi, P)
    expected = np.einsum("kst,ks->kt", P_pi, x) if transpose else np.einsum("kst,kt->ks", P_pi, x)
    folded = op.policy(tuple(jnp.asarray(p) for p in pi), transpose)(jnp.asarray(x))
    np.testing.assert_allclose(folded, expected, atol=1e-13)
    # a denser MDP's fold would hold too many terms (distinct successors x (action, slot)):
    # it keeps the per-action form, as does an MDP whose actions share no successors
    assert Columns(random_mdp(4, S=12, A=4, density=0.4)[0], "sparse")._union is None
    if transpose:
        # the transpose gathers over each state's predecessors; where a state has more than
        # max_in_degree of them (a hub) the operator keeps the scatter form, which agrees too
        assert op._pred is not None and predecessors(union, 1) is None
        saved, op._pred = op._pred, None
        scattered = op.policy(tuple(jnp.asarray(p) for p in pi), transpose)(jnp.asarray(x))
        np.testing.assert_allclose(scattered, expected, atol=1e-13)
        op._pred = saved
    op._union = None  # the per-action form
    per_action = op.policy(tuple(jnp.asarray(p) for p in pi), transpose)(jnp.asarray(x))
    np.testing.assert_allclose(per_action, expected, atol=1e-13)


@pytest.mark.parametrize("folded", [False, True])
def test_float32_inner_solves_reach_the_float64_fixed_point_with_accurate_derivatives(problem, folded):
    """krylov_precision="float32" solves each Newton step's linear system in float32; the
    iteration and its convergence test stay float64, so the solution is the same fixed point
    to the tolerance and the step count grows by at most one; derivatives (their solves in
    float32 too, refined once in float64: at float32's 1e-5 alone an IRL gradient near its
    optimum was wrong by its own size) agree with float64's to 1e-9. Both operator forms: per action, and folded onto distinct successors."""
    from npbrs.domains.solvers.soft import FLOAT32_FROM_STATES

    if folded:
        mdp, P = random_mdp(4, S=12, A=4, density=0.15, gamma=0.95)
        R = np.stack([s * np.random.default_rng(11).normal(size=(12, 4)) for s in (0.01, 1.0, 30.0)])
    else:
        mdp, P, _, R = problem
    s64 = make_soft_solver(mdp, tol=1e-12, krylov_precision="float64")
    s32 = make_soft_solver(mdp, tol=1e-12, krylov_precision="float32")
    assert (s32._op._union is not None) == folded
    r64, r32 = s64(R), s32(R)
    for k in range(len(R)):
        V_ref, Q_ref = numpy_soft_vi(P, R[k], mdp.discount)
        np.testing.assert_allclose(r32.V[k], V_ref, rtol=1e-8, atol=1e-8 * np.abs(V_ref).max())
        np.testing.assert_allclose(r32.Q[k], Q_ref, rtol=1e-8, atol=1e-8 * np.abs(V_ref).max())
    assert r32.V.dtype == jnp.float64 and np.all(np.asarray(r32.residual) <= 1e-12)
    assert np.all(np.asarray(r32.num_iter) <= np.asarray(r64.num_iter) + 1)
    # a warm start from a nearby solution converges in a step or two, as in float64
    warm = s32(R * 1.01, r32.V)
    assert np.all(np.asarray(warm.num_iter) <= 3) and np.all(np.asarray(warm.residual) <= 1e-12)
    g = [jax.grad(lambda r, s=s: (s(r).V ** 2).sum())(jnp.asarray(R[1])) for s in (s64, s32)]
    np.testing.assert_allclose(g[1], g[0], rtol=1e-9, atol=1e-9 * float(jnp.abs(g[0]).max()))
    # forward mode too (a tangent solve), against a central finite difference of the values
    dr = np.random.default_rng(12).normal(size=R[1].shape)
    _, tangent = jax.jvp(lambda r: s32(r).V, (jnp.asarray(R[1]),), (jnp.asarray(dr),))
    _, tangent64 = jax.jvp(lambda r: s64(r).V, (jnp.asarray(R[1]),), (jnp.asarray(dr),))
    np.testing.assert_allclose(tangent, tangent64, rtol=1e-9, atol=1e-9 * float(jnp.abs(tangent64).max()))
    h = 1e-6
    fd = (np.asarray(s64(R[1] + h * dr).V) - np.asarray(s64(R[1] - h * dr).V)) / (2 * h)
    np.testing.assert_allclose(tangent, fd, rtol=1e-4, atol=1e-4 * np.abs(fd).max())
    # and reverse mode (the transposed solve) against the same difference of (V^2).sum()
    fd_loss = ((np.asarray(s64(R[1] + h * dr).V) ** 2).sum() - (np.asarray(s64(R[1] - h * dr).V) ** 2).sum()) / (2 * h)
    np.testing.assert_allclose(float(jnp.vdot(g[1], dr)), fd_loss, rtol=1e-4)
    # "auto" is float32 from FLOAT32_FROM_STATES states on, float64 below
    assert make_soft_solver(mdp).krylov_precision == "float64"
    assert FLOAT32_FROM_STATES > mdp.num_states
    with pytest.raises(ValueError, match="krylov_precision"):
        make_soft_solver(mdp, krylov_precision="half")


@pytest.mark.slow
def test_float32_krylov_solves_do_not_stagnate_at_a_million_states():
    """At a million states a float32 GMRES(8) restarted from its Givens estimate of the residual
    norm stagnated (409 operator applications against 121); restarts now normalise by the
    residual's own norm."""
    from npbrs.domains.gridworld import open_gridworld

    mdp = open_gridworld(1000)
    theta = np.zeros((1, mdp.num_features))
    theta[0, 0] = 5.0
    solver = make_soft_solver(mdp, krylov_dim=8)
    assert solver.krylov_precision == "float32"
    res = solver(np.asarray(solver.rewards(theta)))
    assert np.asarray(res.residual).max() <= 1e-10
    assert int(np.asarray(res.num_matvec)[0]) <= 160, np.asarray(res.num_matvec)


def test_hard_solver_greedy_policy_is_the_best_of_all_deterministic_policies():
    rng = np.random.default_rng(7)
    S, A, gamma = 3, 2, 0.9
    P = rng.random((S, A, S))
    P /= P.sum(-1, keepdims=True)
    r = rng.normal(size=(S, A))
    mdp = TabularMDP.from_dense(P, features=np.eye(S * A).reshape(S, A, S * A), discount=gamma)
    values = {}
    for policy in itertools.product(range(A), repeat=S):
        Ppi = P[np.arange(S), policy]
        values[policy] = np.linalg.solve(np.eye(S) - gamma * Ppi, r[np.arange(S), policy])
    best = max(values, key=lambda p: values[p].sum())
    # the optimal policy dominates every other one in every state
    assert all(np.all(values[best] >= v - 1e-12) for v in values.values())
    for method in ("policy", "vi"):
        res = value_iteration(mdp, r, method=method)
        np.testing.assert_allclose(res.V, values[best], atol=1e-9)
        assert tuple(greedy_policy(res.Q)) == best


def test_bad_input_names_the_problem():
    mdp, P = random_mdp(9, S=4, A=2)
    solver = make_soft_solver(mdp)
    r = np.zeros((4, 2))
    with pytest.raises(ValueError, match="shape"):
        solver(np.zeros((4, 3)))
    bad = r.copy()
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match="state 2, action 1 is not finite"):
        solver(bad)
    with pytest.raises(ValueError, match="table 1, state 0, action 0"):
        soft_value_iteration(mdp, np.stack([r, np.where(np.eye(4, 2) > 0, np.inf, 0.0)]))
    with pytest.raises(ValueError, match="v0 must have shape"):
        solver(r, np.zeros(5))
    with pytest.raises(ValueError, match="v0"):
        solver(r, np.full(4, np.nan))
    with pytest.raises(ValueError, match="discount"):
        mdp.with_discount(1.0)
    with pytest.raises(ValueError, match="discount"):
        mdp.with_discount(-0.1)
    with pytest.raises(ValueError, match="method"):
        make_soft_solver(mdp, method="magic")
    with pytest.raises(ValueError, match="operator"):
        make_soft_solver(mdp, operator="magic")
    with pytest.raises(ValueError, match="factored"):
        make_soft_solver(mdp, operator="factored")
    with pytest.raises(ValueError, match="tol"):
        make_soft_solver(mdp, tol=0.0)


def test_a_looser_copy_of_a_solver_solves_to_its_tolerance_and_loosens_only(problem):
    """``with_tolerance`` (the search's solves, ``RewardEmission.for_search``): a copy with the
    looser tolerance (its derivatives' a tenth of it) that shares the MDP's arrays, works
    inside jit on a traced solver, reaches the dense reference within its tolerance (by
    value and by gradient) in fewer iterations, and never tightens the original's."""
    mdp, P, solver, R = problem
    loose = solver.with_tolerance(1e-6)
    assert (loose.tol, loose.grad_tol) == (1e-6, 1e-7) and (solver.tol, solver.grad_tol) == (1e-12, 1e-11)
    assert solver.with_tolerance(1e-14).tol == 1e-12 and solver.with_tolerance(1e-6, 1e-13).grad_tol == 1e-11
    got = jax.jit(lambda s, r: s.with_tolerance(1e-6)(r))(solver, jnp.asarray(R))
    tight = solver(R)
    for k in range(len(R)):
        V_ref, _ = numpy_soft_vi(P, R[k], mdp.discount)
        np.testing.assert_allclose(got.V[k], V_ref, rtol=1e-5, atol=1e-5 * np.abs(V_ref).max())
    assert np.all(np.asarray(got.num_iter) <= np.asarray(tight.num_iter))
    assert np.sum(np.asarray(got.num_iter) + np.asarray(got.num_matvec)) < np.sum(np.asarray(tight.num_iter) + np.asarray(tight.num_matvec))
    # the derivative's linear solves at the looser tolerance: the gradient of a smooth function of V
    w = np.random.default_rng(4).normal(size=mdp.num_states)
    g = [jax.grad(lambda r, s=s: jnp.sum(s(r).V * w))(jnp.asarray(R[1])) for s in (solver, loose)]
    np.testing.assert_allclose(g[1], g[0], rtol=1e-5, atol=1e-6 * np.abs(np.asarray(g[0])).max())
    with pytest.raises(ValueError, match="tol"):
        solver.with_tolerance(0.0)
    with pytest.raises(ValueError, match="grad_tol"):
        solver.with_tolerance(1e-6, -1.0)


def test_at_values_is_the_solve_at_its_own_values_with_the_same_derivatives(problem):
    """``SoftSolver.at_values``: at a solve's V, one backup gives the solve's Q and V (residual
    below the tolerance) and holds no nonlinear solve; its forward- and reverse-mode derivatives
    are the solve's, against the dense reference's finite differences too. Away from the fixed
    point its residual says so. (Checked to fail with the derivative rule's right-hand side
    taken from one action's reward tangent, and with the given V returned for the backup's.)"""
    mdp, P, solver, R = problem
    S = mdp.num_states
    solved = solver(R)
    at_values = jax.jit(solver.at_values)
    at = at_values(R, solved.V)
    np.testing.assert_allclose(at.V, solved.V, rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(at.Q, solved.Q, rtol=1e-11, atol=1e-11)
    np.testing.assert_allclose(np.exp(np.asarray(at.Q - at.V[..., None])).sum(-1), 1.0, atol=1e-12)
    assert np.all(np.asarray(at.residual) <= 1e-11) and np.all(np.asarray(at.num_iter) == 0)
    # its program holds no loop: no solve
    assert "while" not in str(jax.make_jaxpr(lambda r, v: solver.at_values(r, v).Q)(R, solved.V))
    off = at_values(R, solved.V + 1.0)
    assert np.asarray(off.residual).min() > 1e-6  # (relative to |V|)
    # (its V is the backup's, logsumexp Q: a normalised policy away from the fixed point too)
    np.testing.assert_allclose(np.exp(np.asarray(off.Q - off.V[..., None])).sum(-1), 1.0, atol=1e-12)
    # derivatives: forward mode (the tangent solve) against central differences of the dense
    # reference's log-policies, and reverse mode (the transposed solve) against forward mode
    w = np.random.default_rng(7).normal(size=R.shape)
    dr = np.random.default_rng(8).normal(size=R.shape)
    h, fd = 1e-6, 0.0
    for k in range(len(R)):
        up, down = (numpy_soft_vi(P, R[k] + sign * h * dr[k], mdp.discount) for sign in (1.0, -1.0))
        fd += np.sum(w[k] * ((up[1] - up[0][:, None]) - (down[1] - down[0][:, None]))) / (2 * h)

    def derivatives(r, d, v):
        loss = lambda r_: jnp.sum(w * (lambda a: a.Q - a.V[..., None])(solver.at_values(r_, v)))  # noqa: E731
        return jax.jvp(loss, (r,), (d,))[1], jnp.sum(jax.grad(loss)(r) * d)

    forward, reverse = jax.jit(derivatives)(jnp.asarray(R), jnp.asarray(dr), solved.V)
    np.testing.assert_allclose(forward, fd, rtol=1e-5)
    np.testing.assert_allclose(reverse, forward, rtol=1e-8)
    with pytest.raises(ValueError, match="V must have shape"):
        solver.at_values(R, np.zeros((3, S + 1)))
    with pytest.raises(ValueError, match="V .*non-finite"):
        solver.at_values(R[0], np.full(S, np.nan))
