"""Small dense linear algebra in plain XLA operations: a Cholesky factor, triangular solves, the
log determinant and inverse of a symmetric positive definite matrix, and a Gaussian's log
density given its Cholesky factor; batched over leading axes.

Why not ``jnp.linalg``: on the CPU those lower to LAPACK kernels (XLA custom calls). In jaxlib
before 0.11.2 a LAPACK kernel splits a batch over XLA's intra-op thread pool and blocks until
the parts are done, so programs that run side by side on every core can hang
(:mod:`npbrs.inference.threads`). The matrices here are a reward's D x D posterior
precision (D features: a few, or one per state, ~10^2) and GMRES's m x m triangular factor (m
tens), where a loop over the columns costs next to nothing, so npbrs's fits keep their programs
free of library kernels and run their chains on every core. Each routine is a ``fori_loop``
over one dimension (one small compiled body, however large D is).

A matrix that is not positive definite gives NaN entries in its factor, as ``jnp.linalg.cholesky``
does.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["cholesky", "solve_lower", "solve_upper", "spd_logdet", "spd_inverse", "mvn_log_prob"]


def cholesky(a):
    """The lower Cholesky factor L (..., D, D) of symmetric positive definite ``a`` (..., D, D),
    a = L L^T (only ``a``'s lower triangle is read). Column j by column j: L[j:, j] =
    (a[j:, j] - L[j:, :j] L[j, :j]) / L[j, j], L[j, j] = sqrt(a[j, j] - |L[j, :j]|^2)."""
    a = jnp.asarray(a)
    D = a.shape[-1]
    rows = jnp.arange(D)

    def column(j, L):
        # L's columns j and later are still zero, so full rows give the sums over k < j
        v = jnp.take(a, j, axis=-1) - jnp.einsum("...ik,...k->...i", L, jnp.take(L, j, axis=-2))
        d = jnp.sqrt(jnp.take(v, j, axis=-1))[..., None]
        col = jnp.where(rows >= j, v / d, 0.0)
        return jax.lax.dynamic_update_index_in_dim(L, col[..., :, None], j, axis=-1)

    return jax.lax.fori_loop(0, D, column, jnp.zeros_like(a))


def _substitute(t, b, order):
    # x solving t x = b for triangular t (..., D, D) and b (..., D), rows taken in ``order``:
    # the unknowns not yet solved are zero, so a full row's dot product sums the solved ones
    D = t.shape[-1]

    def row(i, x):
        r = order(i)
        t_r = jnp.take(t, r, axis=-2)
        value = (jnp.take(b, r, axis=-1) - jnp.sum(t_r * x, -1)) / jnp.take(t_r, r, axis=-1)
        return jax.lax.dynamic_update_index_in_dim(x, value[..., None], r, axis=-1)

    t, b = jnp.asarray(t), jnp.asarray(b)
    x = jnp.zeros(jnp.broadcast_shapes(t.shape[:-1], b.shape), jnp.result_type(t, b))
    return jax.lax.fori_loop(0, D, row, x)


def solve_lower(L, b):
    """x (..., D) with L x = b, L (..., D, D) lower triangular (its upper triangle must be zero)."""
    return _substitute(L, b, lambda i: i)


def solve_upper(U, b):
    """x (..., D) with U x = b, U (..., D, D) upper triangular (its lower triangle must be zero)."""
    D = jnp.shape(U)[-1]
    return _substitute(U, b, lambda i: D - 1 - i)


def spd_logdet(a):
    """log det a (...,) of symmetric positive definite ``a`` (..., D, D), from its Cholesky factor."""
    L = cholesky(a)
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(L, axis1=-2, axis2=-1)), -1)


def spd_inverse(a):
    """The inverse (..., D, D) of symmetric positive definite ``a``: L^-T L^-1 with a = L L^T."""
    L = cholesky(a)
    eye = jnp.eye(a.shape[-1], dtype=L.dtype)
    # row i of X: L^-1 e_i (the identity's rows as a batch of right-hand sides), so X = L^-T
    X = solve_lower(L[..., None, :, :], jnp.broadcast_to(eye, L.shape))
    return jnp.einsum("...ik,...jk->...ij", X, X)


def mvn_log_prob(x, mean, chol):
    """log N(x; mean, chol chol^T) (...,) for a lower-triangular ``chol`` (..., D, D)."""
    z = solve_lower(chol, jnp.asarray(x) - mean)
    D = jnp.shape(chol)[-1]
    return (-0.5 * jnp.sum(z ** 2, -1) - jnp.sum(jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), -1)
            - 0.5 * D * jnp.log(2 * jnp.pi))
