"""npbrs.domains.util.linalg, the plain-XLA Cholesky, triangular solves, log determinant, inverse
and Gaussian log density, against NumPy's and SciPy's LAPACK routines: batched, ragged sizes
from 1 to 40, float64 and float32; NaN for a matrix that is not positive definite (as
jnp.linalg.cholesky); and the programs call no library kernel (the reason they exist)."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.stats

from npbrs.domains.util import linalg


def spd(rng, *shape, scale=1.0):
    D = shape[-1]
    B = rng.normal(size=shape) * scale
    return B @ np.swapaxes(B, -1, -2) + 0.1 * np.eye(D)


@pytest.mark.parametrize("D", [1, 2, 5, 40])
def test_against_lapack(D):
    rng = np.random.default_rng(D)
    A = spd(rng, 3, 2, D, D)  # (two batch axes)
    L = np.asarray(linalg.cholesky(A))
    np.testing.assert_allclose(L, np.linalg.cholesky(A), rtol=1e-10, atol=1e-12)
    assert np.all(np.triu(L, 1) == 0)
    np.testing.assert_allclose(np.asarray(linalg.spd_logdet(A)), np.linalg.slogdet(A)[1], rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(np.asarray(linalg.spd_inverse(A)), np.linalg.inv(A), rtol=1e-8, atol=1e-8)
    b = rng.normal(size=(3, 2, D))
    lower = np.asarray(linalg.solve_lower(L, b))
    upper = np.asarray(linalg.solve_upper(np.swapaxes(L, -1, -2), b))
    for i in np.ndindex(3, 2):
        np.testing.assert_allclose(lower[i], scipy.linalg.solve_triangular(L[i], b[i], lower=True), rtol=1e-9,
                                   atol=1e-10)
        np.testing.assert_allclose(upper[i], scipy.linalg.solve_triangular(L[i].T, b[i], lower=False), rtol=1e-9,
                                   atol=1e-10)
    mean = rng.normal(size=D)
    x = rng.normal(size=(4, D))  # (points broadcast against one factor)
    np.testing.assert_allclose(np.asarray(linalg.mvn_log_prob(x, mean, L[0, 0])),
                               scipy.stats.multivariate_normal(mean, A[0, 0]).logpdf(x), rtol=1e-10)


def test_float32_not_positive_definite_and_no_library_kernel():
    rng = np.random.default_rng(0)
    A = spd(rng, 6, 6).astype(np.float32)
    L = linalg.cholesky(jnp.asarray(A, jnp.float32))
    assert L.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(L), np.linalg.cholesky(A.astype(np.float64)), rtol=2e-4, atol=2e-5)
    # an indefinite matrix: NaN from the first column that fails, as jnp.linalg.cholesky gives
    bad = np.asarray(linalg.cholesky(np.diag([1.0, -1.0, 2.0])))
    assert np.isfinite(bad[0, 0]) and np.isnan(bad[1, 1]) and np.isnan(linalg.spd_logdet(np.diag([1.0, -1.0])))
    for fn in (linalg.cholesky, linalg.spd_logdet, linalg.spd_inverse, lambda a: linalg.solve_upper(a, a[0])):
        text = jax.jit(fn).lower(jnp.eye(5)).as_text()
        assert not re.findall(r"custom_call", text)
