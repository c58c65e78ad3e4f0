"""Krylov solves of the policy evaluations (I - gamma P_pi) x = b: restarted GMRES for a batch of
systems in lock-step, right-preconditioned with a truncated Neumann series of gamma P_pi (see
:mod:`npbrs.domains.solvers`)."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from ..util.linalg import solve_upper
from ..util.compiling import jit
from .operators import Columns

_FLOAT32_RTOL = 1e-5  # the tightest relative residual asked of a float32 inner solve


# ----------------------------------------------------------------------------- Krylov
def _gmres(matvec, b, rtol, dim: int, max_cycles: int, basis=None):
    """Restarted GMRES(dim) from x = 0 for K systems at once: ||b_k - A_k x_k|| <= rtol ||b_k||.

    ``matvec`` maps (K, n) to (K, n) row by row; b is (K, n), rtol a scalar or (K,). The K
    systems iterate in lock-step with one shared step counter (under ``vmap`` a per-system
    counter would turn every basis update into a scatter), each freezing once converged.

    Givens rotations are accumulated in a small orthogonal matrix Omega per system, so the
    residual norm after Arnoldi step j is |beta * Omega[j, 0]| without a loop over past
    rotations. Orthogonalisation is one pass of classical Gram-Schmidt as two batched
    matrix-vector products: on CPU the basis is read from memory at each step and that, not
    the operator, is the cost of a step. A restart continues from the residual the Arnoldi
    relation gives (no extra matvec).

    The vectors may be float32 (``SoftSolver``'s ``krylov_precision``): the small Hessenberg
    arithmetic stays float64, and a restart normalises the new residual by its own norm rather
    than by the Givens estimate (in float32 the two drift apart at a million states, and
    GMRES(8) stagnated).

    ``basis`` is an optional (K, dim + 1, n) work array with finite entries, returned for
    reuse by the next call (rows not yet written in a cycle are masked out, so it needs no
    zeroing: allocating and clearing it costs as much as a few Arnoldi steps).
    Returns (x (K, n), matvecs (K,), relative residual estimates (K,), basis).
    """
    m = dim
    K, n = b.shape
    dtype = b.dtype  # the vectors' precision
    small = jnp.promote_types(dtype, jnp.float64)  # the Hessenberg's, inner products' and norms'

    def dots(Vb, w):
        return jnp.einsum("kjs,ks->kj", Vb, w).astype(small)

    def norm(w):
        return jnp.linalg.norm(w, axis=-1).astype(small)

    bnorm = norm(b)
    target = rtol * bnorm
    rows = jnp.arange(m + 1)
    ks = jnp.arange(K)
    if basis is None:
        basis = jnp.zeros((K, m + 1, n), dtype)

    def arnoldi(Vb, r, beta, live):
        R = jnp.zeros((K, m + 1, m), small)
        Om = jnp.broadcast_to(jnp.eye(m + 1, dtype=small), (K, m + 1, m + 1))
        v0 = r / jnp.where(beta > 0, beta, 1.0)[:, None].astype(dtype)
        live = live & (beta > target)

        def cond(c):
            return (c[3] < m) & jnp.any(c[6])

        def body(c):
            # each step first stores the vector made by the previous one and only then reads
            # the basis: with the opposite order XLA copies the whole basis every step
            Vb, R, Om, j, v, steps, live = c
            Vb = Vb.at[:, j].set(v)
            w = matvec(v)
            h = jnp.where(rows <= j, dots(Vb, w), 0.0)
            w = w - jnp.einsum("kj,kjs->ks", h.astype(dtype), Vb)
            hn = norm(w)
            col = jnp.einsum("kij,kj->ki", Om, h.at[:, j + 1].set(hn))
            x1, x2 = col[:, j], col[:, j + 1]
            rho = jnp.hypot(x1, x2)
            safe = jnp.where(rho > 0, rho, 1.0)
            cs = jnp.where(rho > 0, x1 / safe, 1.0)[:, None]
            sn = jnp.where(rho > 0, x2 / safe, 0.0)[:, None]
            row_j, row_j1 = Om[:, j], Om[:, j + 1]
            Om_new = Om.at[:, j].set(cs * row_j + sn * row_j1).at[:, j + 1].set(cs * row_j1 - sn * row_j)
            R_new = R.at[:, :, j].set(col.at[:, j].set(rho).at[:, j + 1].set(0.0))
            Om = jnp.where(live[:, None, None], Om_new, Om)
            R = jnp.where(live[:, None, None], R_new, R)
            steps = steps + live
            live = live & (beta * jnp.abs(Om[:, j + 1, 0]) > target)
            return Vb, R, Om, j + 1, w / jnp.where(hn > 0, hn, 1.0)[:, None].astype(dtype), steps, live

        init = (Vb, R, Om, jnp.asarray(0), v0, jnp.zeros(K, jnp.int32), live)
        Vb, R, Om, j, v, steps, _ = jax.lax.while_loop(cond, body, init)
        Vb = Vb.at[:, jnp.minimum(j, m)].set(v)  # row steps_k of a system that stopped last
        used = jnp.arange(m)[None, :] < steps[:, None]  # (K, m)
        Rm = jnp.where(used[:, :, None] & used[:, None, :], R[:, :m], jnp.eye(m, dtype=small))
        g = jnp.where(used, beta[:, None] * Om[:, :m, 0], 0.0)
        y = solve_upper(Rm, g)
        dx = jnp.einsum("kj,kjs->ks", jnp.pad(y, ((0, 0), (0, 1))).astype(dtype), Vb)
        # the residual without another matvec: b - A x = V (beta e1 - H y)
        # = g_j * sum_i Omega[j, i] v_i over the first j + 1 basis vectors, j = steps
        om_j = Om[ks, steps]  # (K, m + 1), zero beyond column j
        g_j = beta * om_j[:, 0]
        r = g_j[:, None].astype(dtype) * jnp.einsum("ki,kis->ks", jnp.where(rows[None, :] <= steps[:, None], om_j,
                                                                             0.0).astype(dtype), Vb)
        return Vb, dx, steps, r, jnp.abs(g_j)

    def cond(c):
        return (c[4] < max_cycles) & jnp.any(c[3] > target)

    def body(c):
        Vb, x, r, rnorm, cyc, nmv = c
        active = rnorm > target
        Vb, dx, steps, r_new, est = arnoldi(Vb, r, rnorm, active)
        if dtype != small:  # float32 vectors: restart from the residual's own norm, not the estimate
            est = norm(r_new)
        return (Vb, x + dx, jnp.where(active[:, None], r_new, r), jnp.where(active, est, rnorm), cyc + 1,
                nmv + steps)

    init = (basis, jnp.zeros_like(b), b, bnorm, jnp.asarray(0), jnp.zeros(K, jnp.int32))
    basis, x, _, rnorm, _, nmv = jax.lax.while_loop(cond, body, init)
    return x, nmv, rnorm / jnp.where(bnorm > 0, bnorm, 1.0), basis


def _policy_apply(op: Columns, pi, transpose: bool = False):
    """x -> P_pi x = sum_a pi_a E[x](., a), or x -> P_pi^T x; x (K, S) (``Columns.policy``)."""
    return op.policy(pi, transpose)


# (``_policy_solve`` and ``_soft_newton`` are jitted so that their traces are kept per argument
# shapes and static options: a fit calls them at dozens of sites, and again inside every vmap
# fold and implicit-derivative rule, and each trace ran the Python of the loops anew (a tiny
# fit traced GMRES 63 times, 34 since). Nested in an enclosing trace their code joins the
# enclosing program as before.)
@partial(jit, static_argnums=(1, 5, 6, 7, 8), static_argnames=("precision",))
def _policy_solve(op: Columns, gamma, pi, b, rtol, degree: int, dim: int, max_cycles: int,
                  transpose: bool = False, basis=None, precision: str = "float64"):
    """Solve (I - gamma P_pi) x = b (or its transpose) for K systems by GMRES,
    right-preconditioned with the truncated Neumann series M^-1 = sum_{k<degree} (gamma P_pi)^k.

    The preconditioned operator is I - (gamma P_pi)^degree: the bulk of the spectrum shrinks
    to (gamma |lambda|)^degree around 1, so GMRES needs fewer steps (and fewer
    orthogonalisations, which cost about as much as an operator application). The powers
    are taken in a ``fori_loop`` so that XLA materialises each application instead of fusing
    chains of them (which it compiles badly). Returns (x (K, S) in b's dtype, operator
    applications (K,), the GMRES work array for reuse).

    ``precision="float32"`` (``SoftSolver``'s ``krylov_precision``) solves in float32: the
    policy, the right-hand side and the basis (``basis`` must then be float32), to a relative
    residual of at least ``_FLOAT32_RTOL``.
    """
    out_dtype = b.dtype
    if precision == "float32":
        pi = tuple(p.astype(jnp.float32) for p in pi)
        b = b.astype(jnp.float32)
        rtol = jnp.maximum(rtol, _FLOAT32_RTOL)
    P = _policy_apply(op, pi, transpose)

    def power(y):
        return jax.lax.fori_loop(0, degree, lambda _, z: gamma * P(z), y)

    y, k, _, basis = _gmres(lambda y: y - power(y), b, rtol, dim, max_cycles, basis)
    # x = M^-1 y in Horner form, x <- y + gamma P x: one carry, so each application is one fused
    # pass (summing z <- gamma P z into a second carry gave the gathers two consumers, and XLA
    # wrote every gathered column to memory and read it back twice: 5 times the cost)
    x = jax.lax.fori_loop(0, degree - 1, lambda _, x: y + gamma * P(x), y)
    return x.astype(out_dtype), k * degree + degree - 1, basis
