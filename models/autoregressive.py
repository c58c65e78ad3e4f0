"""The autoregressive emission: every skill is a VAR(1) model of the numeric state vector.

This is the BP-AR-HMM ("LDS") baseline of the paper (section II-E). With y(s) =
``mdp.state_vectors[s]`` (M numbers per state) and x_t = [y(s_t), 1] (M + 1), skill k says

    y(s_{t+1}) = W_k x_t + e_t,   e_t ~ N(0, Sigma_k),   W_k = [A_k, b_k]  (M, M + 1).

Step t of a trajectory emits the transition *out of* s_t, the one its action a_t (chosen under
the step's skill z_t) caused; the last step of a trajectory has no successor and gets
log-likelihood 0 under every skill. That value is the same for all skills, so it does not
affect the segmentation (the classic BP-AR-HMM lets z_t explain y_t given y_{t-1} instead,
which lags the skill sequence by one step here). Actions are not modelled.

Prior (matrix-normal inverse-Wishart, conjugate), as numpyro sites:

    Sigma_k ~ InverseWishart(nu0, s0 I)                        site "noise_cov" (K, M, M)
    W_k | Sigma_k ~ MatrixNormal(0, rows Sigma_k, columns v0 I)  site "dynamics" (K, M, M + 1)

(vec(W) ~ N(0, v0 I ⊗ Sigma)). Given the steps of a skill with weights w_t,

    S_xx = I / v0 + sum w x x^T,   S_yx = sum w y' x^T,   S_yy = sum w y' y'^T,
    M_n = S_yx S_xx^-1,   V_n = S_xx^-1,   nu_n = nu0 + sum w,
    S_n = s0 I + S_yy - M_n S_xx M_n^T,
    Sigma | steps ~ InverseWishart(nu_n, S_n),   W | Sigma, steps ~ MatrixNormal(M_n, Sigma, V_n),

and the update draws from this posterior exactly. The same draw, with its density, is the
data-driven proposal of a new skill.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .emissions import Emission, EmissionInfo, register_emission
from npbrs.domains.util.precision import float64_all

__all__ = ["AutoregressiveEmission", "MNIWPosterior"]


def _chol(m):
    return jnp.linalg.cholesky(0.5 * (m + jnp.swapaxes(m, -1, -2)))


class MNIWPosterior(NamedTuple):
    """Parameters of a matrix-normal inverse-Wishart distribution (batched over leading axes).

    mean (..., M, M + 1), column_cov (..., M + 1, M + 1), dof (...), scale (..., M, M):
    Sigma ~ InverseWishart(dof, scale), W | Sigma ~ MatrixNormal(mean, Sigma, column_cov).
    """

    mean: jax.Array
    column_cov: jax.Array
    dof: jax.Array
    scale: jax.Array

    def noise_dist(self):
        import numpyro.distributions as dist

        return dist.InverseWishart(self.dof, scale_tril=_chol(self.scale))

    def dynamics_dist(self, noise_cov):
        import numpyro.distributions as dist

        return dist.MatrixNormal(self.mean, _chol(noise_cov), _chol(self.column_cov))

    def sample(self, key):
        k1, k2 = jax.random.split(key)
        noise_cov = self.noise_dist().sample(k1)
        noise_cov = 0.5 * (noise_cov + jnp.swapaxes(noise_cov, -1, -2))
        dynamics = self.dynamics_dist(noise_cov).sample(k2)
        return {"dynamics": dynamics, "noise_cov": noise_cov}

    def log_prob(self, params):
        return (self.noise_dist().log_prob(params["noise_cov"])
                + self.dynamics_dist(params["noise_cov"]).log_prob(params["dynamics"]))


@register_emission("autoregressive")
class AutoregressiveEmission(Emission):
    """VAR(1) dynamics of the state vector per skill, with a conjugate MNIW prior.

    Params: ``{"dynamics": (K, M, M + 1) [A_k, b_k], "noise_cov": (K, M, M) Sigma_k}``.
    See the module docstring for the model.

    Args:
        state_vectors: (S, M) numbers describing every state (``mdp.state_vectors``).
        v0: prior variance of every coefficient of W (column covariance v0 I) given Sigma = I.
        nu0: inverse-Wishart degrees of freedom (default M + 2, so E[Sigma] = s0 I).
        s0: inverse-Wishart scale s0 I.
    """

    likelihood_of = "states"  # (a density of the state vectors, not a probability of actions)

    def __init__(self, state_vectors, v0: float = 10.0, nu0=None, s0: float = 1.0):
        y = np.asarray(state_vectors, dtype=np.float64)
        if y.ndim == 1:
            y = y[:, None]
        if y.ndim != 2 or y.shape[0] < 1 or y.shape[1] < 1:
            raise ValueError(f"state_vectors must have shape (S, M), got {y.shape}")
        if not np.all(np.isfinite(y)):
            s, m = (int(i) for i in np.argwhere(~np.isfinite(y))[0])
            raise ValueError(f"state_vectors[{s}, {m}] is not finite")
        M = y.shape[1]
        nu0 = M + 2.0 if nu0 is None else nu0
        if not (np.isfinite(v0) and v0 > 0):
            raise ValueError(f"v0 must be positive, got {v0!r}")
        if not (np.isfinite(s0) and s0 > 0):
            raise ValueError(f"s0 must be positive, got {s0!r}")
        if not (np.isfinite(nu0) and nu0 > M - 1):
            raise ValueError(f"nu0 must exceed M - 1 = {M - 1} (the state vectors have M = {M} entries), got {nu0!r}")
        self.state_vectors = jnp.asarray(y)
        self.dim = M
        self.v0, self.nu0, self.s0 = float(v0), float(nu0), float(s0)

    @classmethod
    def from_mdp(cls, mdp, **options):
        if getattr(mdp, "state_vectors", None) is None:
            raise ValueError(f"the autoregressive emission models numeric state vectors, but MDP {mdp.name!r} has "
                             f"no state_vectors; build the TabularMDP with state_vectors=(S, M) array")
        return cls(mdp.state_vectors, **options)

    # ------------------------------------------------------------------ prior and posterior
    def prior(self, batch=()) -> MNIWPosterior:
        """The MNIW prior (the posterior given no steps), batched over ``batch``."""
        M = self.dim
        return MNIWPosterior(jnp.zeros(batch + (M, M + 1)),
                             jnp.broadcast_to(self.v0 * jnp.eye(M + 1), batch + (M + 1, M + 1)),
                             jnp.full(batch, self.nu0), jnp.broadcast_to(self.s0 * jnp.eye(M), batch + (M, M)))

    def _regressors(self, data):
        """x_t = [y(s_t), 1] (N, T, M + 1), y'_t = y(s_{t+1}) (N, T, M), has_next (N, T)."""
        y = self.state_vectors[data.states]
        x = jnp.concatenate([y, jnp.ones(y.shape[:-1] + (1,))], -1)
        target = jnp.concatenate([y[:, 1:], y[:, -1:]], 1)
        has_next = data.mask & jnp.concatenate([data.mask[:, 1:], jnp.zeros_like(data.mask[:, :1])], 1)
        return x, target, has_next

    def posterior(self, data, weights) -> MNIWPosterior:
        """The MNIW posterior of each skill given its weighted steps; weights (N, T, K)."""
        x, target, has_next = self._regressors(data)
        w = weights * has_next[..., None]  # (N, T, K)
        M = self.dim
        Sxx = jnp.einsum("ntk,nti,ntj->kij", w, x, x) + jnp.eye(M + 1) / self.v0
        Syx = jnp.einsum("ntk,nti,ntj->kij", w, target, x)
        Syy = jnp.einsum("ntk,nti,ntj->kij", w, target, target)
        L = _chol(Sxx)
        # M_n = S_yx S_xx^-1 and V_n = S_xx^-1 through the Cholesky factor of S_xx
        mean = jnp.swapaxes(jax.scipy.linalg.cho_solve((L, True), jnp.swapaxes(Syx, -1, -2)), -1, -2)
        column_cov = jax.scipy.linalg.cho_solve((L, True), jnp.broadcast_to(jnp.eye(M + 1), Sxx.shape))
        scale = self.s0 * jnp.eye(M) + Syy - mean @ Syx.swapaxes(-1, -2)
        scale = 0.5 * (scale + jnp.swapaxes(scale, -1, -2))
        dof = self.nu0 + jnp.sum(w, axis=(0, 1))
        return MNIWPosterior(mean, 0.5 * (column_cov + jnp.swapaxes(column_cov, -1, -2)), dof, scale)

    # ------------------------------------------------------------------ the protocol
    def sample_params(self, K):
        import numpyro

        prior = self.prior((K,))
        noise_cov = numpyro.sample("noise_cov", prior.noise_dist().to_event(1))
        dynamics = numpyro.sample("dynamics", prior.dynamics_dist(noise_cov).to_event(1))
        return {"dynamics": dynamics, "noise_cov": noise_cov}

    def log_prior(self, params):
        return self.prior((params["noise_cov"].shape[0],)).log_prob(params)

    def log_likelihoods(self, params, data, cache=()):
        import numpyro.distributions as dist

        x, target, has_next = self._regressors(data)
        loc = jnp.einsum("kij,ntj->ntki", params["dynamics"], x)  # (N, T, K, M)
        ll = dist.MultivariateNormal(loc, scale_tril=_chol(params["noise_cov"])).log_prob(target[:, :, None, :])
        return jnp.where(has_next[..., None], ll, 0.0), cache

    def update(self, key, params, cache, data, weights, step):
        return self.posterior(data, weights).sample(key), cache, EmissionInfo(jnp.ones(()))

    def init_params(self, key, data, weights):
        return self.posterior(data, weights).sample(key)

    def propose(self, key, data, weights):
        post = self.posterior(data, weights[..., None])
        one = {k: v[0] for k, v in post.sample(key).items()}
        return one, self.log_proposal(one, data, weights)

    def log_proposal(self, params_one, data, weights):
        post = self.posterior(data, weights[..., None])
        return post.log_prob({k: v[None] for k, v in params_one.items()})[0]

    def describe(self):
        """The options that rebuild this emission with ``from_mdp``."""
        return {"name": self.name, "v0": self.v0, "nu0": self.nu0, "s0": self.s0}


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
