"""The prior of a skill's reward weights: a Gaussian, a Student t per weight, or a sampled scale.

Rewards are in nats per step (the Boltzmann temperature is folded into theta), so
the prior's sigma says how deterministic a skill may be. The likelihood of an optimal (hence
near-deterministic) demonstrator keeps growing along the direction of its reward: the data fix
the direction and the prior fixes the scale. With 16 x 200 expert steps the MAP weights come out
at 3-12 sigma on the highway and quadcopter domains (quadcopter skill A: sigma = 1 gives
theta = (12.9, 0.15, -0.23), sigma = 10 gives (97, 0.5, -0.3), sigma = 100 gives (481, 1.0,
-0.4)), with the same optimal policies and held-out log-likelihoods of -0.35, -0.26 and -0.24
nats per step (uniform: -1.39). The default sigma = 10 (``PRIOR_SCALE``) puts a decisive
step (a one-sigma weight on a feature that differs by one between two actions) at e^10, about
20000 : 1, which is as deterministic as demonstrations of an optimal agent look, while keeping
Q-gaps at tens rather than hundreds of nats: a much wider prior gains almost no likelihood but
makes every misassigned step cost hundreds of nats (extreme acceptance ratios for birth, death
and split-merge moves) and MALA's steps (which scale with the smallest posterior standard
deviation) relatively smaller.

With many weights (one per state) ``prior_scale="auto"`` narrows the Gaussian
(:func:`auto_prior_scale`) and ``prior_df="auto"`` makes each weight's prior a Student t
(:func:`auto_prior_df`). :class:`RewardPrior` is the reward emission's part that states its prior
(the sites ``theta`` and, with a sampled scale, ``sigma2``).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist

from npbrs.domains.util.precision import float64_all

__all__ = ["PRIOR_SCALE", "AUTO_SCALE", "AUTO_SCALE_FEATURES", "START_FIT_FEATURES", "AUTO_DF", "AUTO_T_SCALE",
           "log_prior", "check_prior_df", "prior_grad", "prior_curvature", "auto_prior_df", "auto_prior_scale",
           "RewardPrior"]

PRIOR_SCALE = 10.0
# prior_scale="auto" (the default): sigma = AUTO_SCALE for up to AUTO_SCALE_FEATURES weights (the
# paper's domains: 3 and 4 features), and beyond them sigma^2 D held at AUTO_SCALE^2 x
# AUTO_SCALE_FEATURES (sigma = 20 / sqrt(D)): one weight per state wants a far narrower prior
# (docs/design.md, "Priors for many reward weights")
AUTO_SCALE, AUTO_SCALE_FEATURES = 10.0, 4
# start="auto" starts each skill at its IRL fit when the reward has more weights than this (one
# weight per state: a draw around the fit in that many dimensions lands far below it), and draws
# around the fit otherwise (a handful of features: the paper's domains, where starting at the
# fit gave the quadcopter a fourth skill in 2 of 10 runs)
START_FIT_FEATURES = 16
# prior_df="auto" (the default): for rewards of more than START_FIT_FEATURES weights, each weight's
# prior is a Student t of AUTO_DF degrees of freedom and (with prior_scale="auto") scale
# AUTO_T_SCALE; a Gaussian otherwise (see auto_prior_df)
AUTO_DF, AUTO_T_SCALE = 2.0, 0.5


def log_prior(theta, prior_scale=PRIOR_SCALE, prior_df=None) -> jax.Array:
    """log Normal(theta; 0, prior_scale^2 I) summed over features, () or (K,); with ``prior_df``
    nu (a Python float), each weight's prior is instead a Student t of nu degrees of freedom and
    scale ``prior_scale`` (the Gaussian's scale mixture over sigma^2 ~ InvGamma(nu/2, nu s^2/2)):
    a heavy-tailed, sparsity-favouring prior, for one weight per state."""
    import numpyro.distributions as dist

    theta = jnp.asarray(theta, jnp.float64)
    if prior_df is None:
        return jnp.sum(dist.Normal(0.0, prior_scale).log_prob(theta), axis=-1)
    return jnp.sum(dist.StudentT(float(prior_df), 0.0, prior_scale).log_prob(theta), axis=-1)


def check_prior_df(prior_df):
    """``prior_df`` as :func:`log_prior` takes it: None (the Gaussian) or a positive float; a
    ValueError naming it otherwise."""
    if prior_df is None:
        return None
    if isinstance(prior_df, (bool, str)) or not (np.ndim(prior_df) == 0 and np.isfinite(prior_df) and prior_df > 0):
        raise ValueError(f"prior_df must be None (a Gaussian prior) or a positive number, got {prior_df!r}")
    return float(prior_df)


def prior_grad(theta, prior_scale=PRIOR_SCALE, prior_df=None) -> jax.Array:
    """The gradient of :func:`log_prior` in theta (the shape of theta; ``prior_scale`` broadcast
    against it)."""
    if prior_df is None:
        return -theta / prior_scale ** 2
    nu = float(prior_df)
    return -(nu + 1.0) * theta / (nu * prior_scale ** 2 + theta ** 2)


def prior_curvature(theta, prior_scale=PRIOR_SCALE, prior_df=None) -> jax.Array:
    """Minus the second derivative of :func:`log_prior` per weight (the shape of theta), the
    prior's part of a Laplace precision and of the MALA preconditioner: 1 / sigma^2 for the
    Gaussian; for the Student t, (nu + 1)(nu s^2 - theta^2) / (nu s^2 + theta^2)^2, negative in
    its tails, floored at a hundredth of its value at 0 (a stand-in that keeps the precision
    positive; the moves themselves stay exact)."""
    theta = jnp.asarray(theta, jnp.float64)
    if prior_df is None:
        return jnp.broadcast_to(1.0 / jnp.asarray(prior_scale, jnp.float64) ** 2, theta.shape)
    nu, s2 = float(prior_df), jnp.asarray(prior_scale, jnp.float64) ** 2
    peak = (nu + 1.0) / (nu * s2)
    return jnp.maximum((nu + 1.0) * (nu * s2 - theta ** 2) / (nu * s2 + theta ** 2) ** 2, 0.01 * peak)

def auto_prior_df(num_features: int):
    """The reward prior's degrees of freedom for ``prior_df="auto"``: None (a Gaussian prior) for
    up to ``START_FIT_FEATURES`` (16) weights, ``AUTO_DF`` (2: a Student t per weight) beyond.

    With one weight per state, a skill's rewards are sparse (a goal, a few states to avoid) and
    its steps leave most states' weights unconstrained. Under a Gaussian prior wide enough for the
    goal's weight those weights wander by +-2 nats, and steps near another skill's bump switch to
    it; a t prior of scale 0.5 holds them near 0 and still lets the goal's weight reach 5. On the
    four-room world, started from the true segmentation, the sampler's labels then score 0.938
    (Gaussian: 0.906; the true model's Viterbi 0.953); from ``fit``'s start (4 chains, fit
    seeds 0-3) 0.863 against 0.790, and held-out -1.198 nats per step against the Gaussian's
    -1.216 (the oracle -1.169), at the same cost; the grid scores as before and the labyrinth's
    held-out within 0.005 of before (``docs/design.md``: priors for many reward weights)."""
    D = int(num_features)
    if D < 1:
        raise ValueError(f"num_features must be at least 1, got {num_features!r}")
    return AUTO_DF if D > START_FIT_FEATURES else None


def auto_prior_scale(num_features: int) -> float:
    """The reward prior's sigma for ``prior_scale="auto"``: ``AUTO_SCALE`` (10) for up to
    ``AUTO_SCALE_FEATURES`` (4) weights, then sigma = 10 sqrt(4 / D), which keeps the prior's
    expected |theta|^2 = D sigma^2 at 400 however many weights there are.

    With one weight per state, a skill's Occam factor grows with its prior variance per
    visited state: at sigma 10 the four-room world's true skills lose to lumped multi-goal
    rewards along every path of single moves, at sigma 1-2 they do not (``docs/design.md``)."""
    D = int(num_features)
    if D < 1:
        raise ValueError(f"num_features must be at least 1, got {num_features!r}")
    return AUTO_SCALE * math.sqrt(min(1.0, AUTO_SCALE_FEATURES / D))


class RewardPrior:
    """The reward emission's prior (a part of :class:`npbrs.models.reward.emission.RewardEmission`,
    which sets ``prior_scale``, ``prior_df``, ``scale_prior`` and ``num_features``)."""

    def _variance_prior(self):
        return dist.InverseGamma(*self.scale_prior)

    def _scales(self, params):
        """The prior's sigma: (K,) sampled, or the fixed ``prior_scale``."""
        return jnp.sqrt(params["sigma2"]) if self.scale_prior else self.prior_scale

    def _variance_conditional(self, theta):
        """The exact conditional of sigma^2 given weights (..., D): InvGamma(a + D/2, b + |theta|^2 / 2)."""
        a, b = self.scale_prior
        return dist.InverseGamma(a + 0.5 * theta.shape[-1], b + 0.5 * jnp.sum(theta ** 2, axis=-1))

    def sample_params(self, K):
        if not self.scale_prior:
            base = (dist.Normal(0.0, self.prior_scale) if self.prior_df is None
                    else dist.StudentT(self.prior_df, 0.0, self.prior_scale))
            theta = numpyro.sample("theta", base.expand([K, self.num_features]).to_event(2))
            return {"theta": theta}
        sigma2 = numpyro.sample("sigma2", self._variance_prior().expand([K]).to_event(1))
        theta = numpyro.sample("theta", dist.Normal(0.0, jnp.sqrt(sigma2)[:, None]).expand(
            [K, self.num_features]).to_event(2))
        return {"theta": theta, "sigma2": sigma2}

    def log_prior(self, params):
        scale = self._scales(params)
        lp = log_prior(params["theta"], jnp.asarray(scale)[..., None] if self.scale_prior else scale, self.prior_df)
        if self.scale_prior:
            lp = lp + self._variance_prior().log_prob(params["sigma2"])
        return lp


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
