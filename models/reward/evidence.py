"""The evidence of a skill's steps under the reward emission, for the warmup's greedy merges and
splits: IRL fits and the Laplace approximation at them, F + I / sigma^2 for the posterior
precision (F: the Fisher information); under a Student t prior optionally calibrated per weight
(``t_evidence="calibrated"``), and with a sampled prior scale the scale mixture integrated over
sigma^2. The fits and precisions are also the data-driven proposal's (:mod:`.moves`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from npbrs.domains.util import linalg
from npbrs.domains.util.precision import float64_all
from .irl import fit_reward
from .likelihood import fisher_information, log_policy, step_log_likelihoods
from .prior import log_prior, prior_curvature

__all__ = ["RewardEvidence"]


class RewardEvidence:
    """The reward emission's fits and evidences (a part of
    :class:`npbrs.models.reward.emission.RewardEmission`)."""

    def fit_point(self, data, weights, init=None):
        """IRL fits (M, D) to weighted steps (N, T, M): ``refit_steps`` L-BFGS steps from
        ``init``, or ``fit_steps`` from theta = 0 (:meth:`laplace`'s fits, at the fixed prior
        scale)."""
        return self._point(self._laplace_fit(self.counts(data, weights), init)[0])

    def _point(self, theta):
        """Params at fitted weights: sigma^2, when sampled, at its conditional mode given them."""
        if not self.scale_prior:
            return {"theta": theta}
        cond = self._variance_conditional(theta)
        return {"theta": theta, "sigma2": cond.rate / (cond.concentration + 1.0)}

    def laplace(self, counts, init=None, at_sampled_scale=False):
        """IRL fits (M, D) to count tables (M, S, A), ``refit_steps`` L-BFGS steps from ``init``
        (or ``fit_steps`` from theta = 0), their log-likelihoods (M,), the posterior precisions
        (M, D, D) at the fits, F + I / sigma^2 (F: the Fisher information, the observed one's
        stand-in), symmetrised, and the sigma (M,) of the fits' prior. Shared by the proposal
        and the evidence. With ``at_sampled_scale`` (a sampled prior variance) the fit is
        refitted, ``fit_steps`` steps, at sigma^2 = (b + |theta|^2 / 2) / (a + D / 2) of the
        first fit (where the Student-t prior's gradient is the Gaussian's): one compiled fit for
        both passes."""
        fit, log_lik, V, scale = self._laplace_fit(counts, init, at_sampled_scale)
        return fit, log_lik, self._laplace_precision(fit, counts, V, scale), scale

    def _laplace_fit(self, counts, init=None, at_sampled_scale=False):
        """:meth:`laplace`'s fits: (theta (M, D), log_lik (M,), V (M, S), scale (M,))."""
        M, D = counts.shape[0], self.num_features
        theta0 = jnp.zeros((M, D)) if init is None else init["theta"]
        steps = self.fit_steps if init is None else self.refit_steps
        fit_at = lambda theta, v, scale, n: fit_reward(self.solver, counts, theta, v, scale, n,  # noqa: E731
                                                       epsilon=self.epsilon, temperature=self.temperature,
                                                       prior_df=self.prior_df)[:3]
        scale = jnp.full((M,), self.prior_scale)
        if not at_sampled_scale:
            fit, log_lik, V = fit_at(theta0, jnp.zeros((M, self.num_states)), scale, steps)
            return fit, log_lik, V, scale
        a, b = self.scale_prior

        def one(carry, first):
            theta, _, V, scale = carry
            scale = jnp.where(first, scale, jnp.sqrt((b + 0.5 * jnp.sum(theta ** 2, -1)) / (a + 0.5 * D)))
            return (*fit_at(theta, V, scale, max(steps, self.fit_steps)), scale), None

        (fit, log_lik, V, scale), _ = jax.lax.scan(
            one, (theta0, jnp.zeros(M), jnp.zeros((M, self.num_states)), scale), jnp.array([True, False]))
        return fit, log_lik, V, scale

    def _laplace_precision(self, fit, counts, V, scale):
        """:meth:`laplace`'s precisions (M, D, D) at its fits."""
        # (at the fits' own values: no solve, only the tangent solves)
        F = fisher_information(self.solver, fit, counts, V, self.temperature, solved=True)  # (M, D, D)
        curvature = prior_curvature(fit, scale[:, None], self.prior_df)  # (M, D): 1 / sigma^2 for a Gaussian
        precision = F + jax.vmap(jnp.diag)(curvature)
        return 0.5 * (precision + jnp.swapaxes(precision, -1, -2))

    def fit_evidence(self, data, weights, init=None, with_evidence=True, with_likelihoods=False):
        """IRL fits (M, D) to weighted steps (N, T, M) and each skill's Laplace log evidence at
        its fit, log p(steps | theta) + log p0(theta) + D/2 log 2 pi - 1/2 log det(precision)
        (see :meth:`laplace`); with a sampled prior variance, sigma^2 integrated out too
        (:meth:`scale_mixture_evidence`). ``with_evidence`` (a bool, or a traced one): where
        false, the fits only, their log evidences NaN (no Fisher information computed), so
        that one compiled call serves fits and evidences (the greedy split's allocation).
        ``with_likelihoods``: also the fits' per-step log-likelihoods (N, T, M), from the fits'
        own soft values (one backup each, no solve)."""
        counts = self.counts(data, weights)
        M = counts.shape[0]
        theta, log_lik, V, scale = self._laplace_fit(counts, init, at_sampled_scale=bool(self.scale_prior))

        def evidence(_):
            precision = self._laplace_precision(theta, counts, V, scale)
            if not self.scale_prior:
                logdet = linalg.spd_logdet(precision)
                return (log_lik + self.log_prior({"theta": theta}) + 0.5 * self.num_features * jnp.log(2 * jnp.pi)
                        - 0.5 * logdet + (self._t_laplace_correction(theta, precision, scale)
                                          if self.t_evidence == "calibrated" else 0.0))
            return self.scale_mixture_evidence(theta, log_lik, precision, scale ** 2)

        if with_evidence is True:
            log_ev = evidence(None)
        else:
            log_ev = jax.lax.cond(with_evidence, evidence, lambda _: jnp.full((M,), jnp.nan), None)
        if not with_likelihoods:
            return self._point(theta), log_ev
        log_pi, _ = log_policy(self.solver, theta, V, self.temperature, self.epsilon, solved=True)
        return self._point(theta), log_ev, step_log_likelihoods(log_pi, data.states, data.actions, data.mask)

    def _t_laplace_correction(self, theta, precision, scale):
        """(M,) what a Student t prior's Laplace evidence misses: the Laplace approximation of
        the t density's own integral (1) is t(0) sqrt(2 pi / h0) (h0: its curvature at 0), short
        by c = -log of that (0.32 nats for 2 degrees of freedom, whatever the scale) for every
        weight the data leave to the prior, which with one weight per state is most of them: a
        skill's evidence came out tens of nats low, and a split's two skills twice that. Each
        weight adds c times the prior's share of its precision, h0 / (F_dd + h0): c where the
        data say nothing, 0 where they decide the weight (checked against importance sampling in
        ``tests/test_greedy.py``). 0 for a Gaussian prior, whose Laplace evidence is exact
        without data."""
        if self.prior_df is None:
            return jnp.zeros(theta.shape[0])
        nu, s = self.prior_df, jnp.asarray(scale, jnp.float64)[:, None]
        zero = jnp.zeros((1, 1))
        h0 = prior_curvature(zero, s, nu)  # (M, 1)
        c = -(log_prior(zero, 1.0, nu) + 0.5 * jnp.log(2 * jnp.pi / prior_curvature(zero, 1.0, nu)))[0, 0]  # scale-free
        F_diag = jnp.diagonal(precision, axis1=-2, axis2=-1) - prior_curvature(theta, s, nu)
        return c * jnp.sum(h0 / (jnp.maximum(F_diag, 0.0) + h0), -1)

    # the coarse grid of log sigma^2 that finds the peak of the evidence's integrand
    _LOG_VARIANCE_NODES = np.linspace(-16.0, 16.0, 257)

    def scale_mixture_evidence(self, theta, log_lik, precision, s2_fit):
        """The log evidence (M,) with sigma^2 ~ InvGamma(a, b) integrated out. The likelihood is
        taken as the quadratic around the fit theta, made at prior variance ``s2_fit`` (M,): its
        gradient there is theta / s2_fit (the fit's stationarity), its curvature the Fisher
        information F = precision - I / s2_fit. Its integral against Normal(0, sigma^2 I) is
        closed-form for every sigma^2,

            log ev(sigma^2) = c0 - D/2 log sigma^2 - 1/2 log det P + 1/2 h' P^-1 h,
            P = F + I / sigma^2, h = precision theta, c0 = log L - h' theta + 1/2 theta' F theta,

        (one eigendecomposition of F serves every sigma^2), and the integral over sigma^2 is a
        trapezoid rule in log sigma^2, 257 nodes on +-10 sd around the integrand's peak (found on
        a coarse grid of [-16, 16] and one Newton step). With the prior's variance pinned at
        s2_fit it is the fixed-scale Laplace evidence."""
        D = self.num_features
        F = precision - jnp.eye(D) / s2_fit[:, None, None]
        lam, Q = jnp.linalg.eigh(0.5 * (F + jnp.swapaxes(F, -1, -2)))
        lam = jnp.maximum(lam, 0.0)  # (M, D)
        h = jnp.einsum("mde,me->md", precision, theta)
        c0 = log_lik - jnp.sum(h * theta, -1) + 0.5 * jnp.einsum("md,mde,me->m", theta, F, theta)
        hq2 = jnp.einsum("mde,md->me", Q, h) ** 2  # (M, D)
        prior = self._variance_prior()

        def log_integrand(u):  # u: (J, M) values of log sigma^2 -> (J, M)
            inv = jnp.exp(-u)[..., None]
            per = (c0 - 0.5 * D * u - 0.5 * jnp.sum(jnp.log(lam + inv), -1) + 0.5 * jnp.sum(hq2 / (lam + inv), -1))
            return per + prior.log_prob(jnp.exp(u)) + u  # the prior's density in log sigma^2

        # a coarse grid finds the peak, one Newton step by central differences centres it
        # (exact for a quadratic), and the trapezoid rule runs on +-10 sd around it
        coarse = jnp.broadcast_to(jnp.asarray(self._LOG_VARIANCE_NODES)[:, None], (257, theta.shape[0]))
        f = log_integrand(coarse)
        j = jnp.clip(jnp.argmax(f, axis=0), 1, 255)
        cols = jnp.arange(theta.shape[0])
        step = coarse[1, 0] - coarse[0, 0]
        d1 = (f[j + 1, cols] - f[j - 1, cols]) / (2 * step)
        d2 = (f[j + 1, cols] - 2 * f[j, cols] + f[j - 1, cols]) / step ** 2
        curved = d2 < -1e-12
        peak = jnp.where(curved, coarse[j, cols] - d1 / jnp.where(curved, d2, -1.0), coarse[j, cols])
        sd = jnp.clip(jnp.where(curved, 1.0 / jnp.sqrt(-jnp.where(curved, d2, -1.0)), 4.0), 1e-4, 4.0)
        x = jnp.linspace(-10.0, 10.0, 257)
        fine = peak[None] + x[:, None] * sd[None]
        ends = (jnp.arange(257) == 0) | (jnp.arange(257) == 256)
        log_du = jnp.log(jnp.where(ends, 0.5, 1.0) * (x[1] - x[0]))[:, None] + jnp.log(sd)[None]
        return jax.scipy.special.logsumexp(log_integrand(fine) + log_du, axis=0)


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
