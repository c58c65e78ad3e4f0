"""The reward emission's moves: the update of the skills' weights, its warmup tuning, and the
data-driven proposal of a new skill.

Moves on theta_k (``update``):

- ``"mala"`` (default): Metropolis-adjusted Langevin steps with the implicit gradient of the
  soft Bellman fixed point, a diagonal preconditioner from the Fisher information and a step
  size per skill, both tuned during warmup only (then frozen, so the chain is a valid MCMC).
  A skill with no steps is drawn exactly from the prior.
- ``"map"``: the paper's maximum a posteriori IRL step (warm-started L-BFGS). This makes the
  sampler a *stochastic EM*, not MCMC: its draws are not posterior samples.

With a sampled prior variance (``scale_prior``) the move on theta_k is followed by a joint move
of its magnitude, (theta_k, sigma_k^2) -> (c theta_k, c^2 sigma_k^2), and then sigma_k^2 from its
exact conditional.

The data-driven proposal of a new skill from weighted steps (a birth's window) fits IRL from
theta = 0 with a fixed number of L-BFGS steps (deterministic in the steps, so its density can
be evaluated in the reverse move) and draws theta from a Gaussian around the fit whose
covariance is the inverse Fisher information plus prior precision (a Laplace approximation),
inflated by ``proposal_inflation``. With ``proposal_broad_weight`` w > 0 the proposal is the
defensive mixture (1 - w) N(fit, C) + w N(fit, s^2 C), s = ``proposal_broad_scale``: its
draws stay near the fit, but a reverse move's density of a value many standard deviations
from the fit (a split-merge's current rewards, when the reverse split allocates the steps
differently) is about log w - D log s - d^2 / (2 s^2) instead of -d^2 / 2.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from npbrs.domains.util import linalg
from npbrs.domains.util.precision import float64_all
from ..emissions import EmissionInfo
from ..mcmc import metropolis_accept, select
from .irl import fit_reward
from .likelihood import count_log_likelihood_and_values, fisher_information
from .mala import build_kernel, unevaluated
from .prior import log_prior, prior_curvature

__all__ = ["RewardMoves"]


class RewardMoves:
    """The reward emission's update, tuning and proposals (a part of
    :class:`npbrs.models.reward.emission.RewardEmission`)."""

    # ------------------------------------------------------------------ the update
    def update(self, key, params, cache, data, weights, adapt, tune=False, redraw_unused=True):
        """The reward move (MALA, then with a sampled prior variance the magnitude move and
        sigma^2 | theta), or the MAP refit (``update="map"``). ``tune`` (a bool, not
        batched over chains): refresh the MALA preconditioner first, as :meth:`tune` does, from
        the Fisher information at the skills' current weights; here the move's first pass has
        solved each skill at them already, so the refresh costs only the tangent solves.
        ``redraw_unused`` (a bool, not batched): the skills without steps get prior draws (else
        they keep their parameters, also an exact move). With MALA (:attr:`solves_in_update`)
        the draws come before the move, whose first pass solves every skill, so that the
        returned cache holds the values of the returned weights (:meth:`log_likelihoods` with
        ``solved``)."""
        theta = params["theta"]
        K, D = theta.shape
        counts = self.counts(data, weights)  # (K, S, A)
        has_steps = jnp.sum(counts, axis=(1, 2)) > 0
        k_prior, k_move = jax.random.split(key)
        if not self.scale_prior:
            prior_draw = {"theta": self.prior_scale * (jax.random.normal(k_prior, (K, D)) if self.prior_df is None
                                                       else jax.random.t(k_prior, self.prior_df, (K, D)))}
        else:  # a skill without steps draws (sigma^2, theta) from the prior
            k_prior, k_var, k_var0 = jax.random.split(k_prior, 3)
            sigma2_0 = self._variance_prior().sample(k_var0, (K,))
            prior_draw = {"theta": jnp.sqrt(sigma2_0)[:, None] * jax.random.normal(k_prior, (K, D)), "sigma2": sigma2_0}
        drawn = ~has_steps & redraw_unused
        # the unused skills' weights, drawn or kept, before the move: its first pass solves them
        start = jax.tree.map(lambda d, p: jnp.where(drawn.reshape((K,) + (1,) * (d.ndim - 1)), d, p), prior_draw, params)
        if self.update_kind == "map":
            new, _, V, _, _ = fit_reward(self.solver, counts, theta, cache["V"], self._scales(params), self.map_steps,
                                         epsilon=self.epsilon, temperature=self.temperature, prior_df=self.prior_df)
            accept = jnp.ones(K)
            cache = {**cache, "V": V}
            out = {"theta": new}
        else:  # (MALA never moves a skill without steps: its start comes back as it went in)
            k_move, k_rescale = jax.random.split(k_move) if self.scale_prior else (k_move, None)
            new, cache, accept, log_density = self.mala(k_move, start["theta"], counts, cache, adapt,
                                                         self._scales(start), has_steps, tune)
            out = {"theta": new}
            if self.scale_prior:  # (nor does the magnitude move)
                out["theta"], out["sigma2"], cache = self._rescale(k_rescale, new, start["sigma2"], log_density,
                                                                   counts, cache, adapt, has_steps)
        if self.scale_prior:  # sigma^2 | theta exactly (the moves' own sigma^2 is not kept)
            out["sigma2"] = self._variance_conditional(out["theta"]).sample(k_var)
        # the skills without steps: their start, drawn or kept
        out = jax.tree.map(lambda n, s0: jnp.where(has_steps.reshape((K,) + (1,) * (n.ndim - 1)), n, s0), out, start)
        info = EmissionInfo(jnp.sum(jnp.where(has_steps, accept, 0.0)) / jnp.maximum(jnp.sum(has_steps), 1))
        return out, cache, info

    def tune(self, params, cache, data, weights):
        """The MALA preconditioner from the Fisher information at the skills' current weights:
        per coordinate 1 / sqrt(F_dd + 1 / sigma^2) in the cache's "scale" (a Student t prior:
        its curvature at the current weights for 1 / sigma^2, :func:`prior_curvature`). The sampler calls
        this in warmup only, every ``tune_every`` sweeps (D tangent solves a skill: the most
        expensive part of a warmup sweep with many features); the sampling sweeps keep it fixed.
        The sampler asks :meth:`update` for it instead (``tune``), where the skills' values are
        solved already; this one solves for them."""
        theta = params["theta"]
        scale = self._preconditioner(theta, self._scales(params), self.counts(data, weights), cache["V"])
        return {**cache, "scale": scale}

    def _preconditioner(self, theta, prior_scale, counts, V, solved=False):
        """:meth:`tune`'s per-coordinate scales (K, D) at weights theta (K, D), by this
        emission's solver; ``solved``: V are their soft values already (no solve)."""
        fisher = jax.vmap(lambda t, c, v: jnp.diag(fisher_information(self.solver, t, c, v, self.temperature,
                                                                      solved)))(theta, counts, V)
        scale = jnp.asarray(prior_scale)
        curvature = prior_curvature(theta, scale[..., None] if jnp.ndim(scale) else scale, self.prior_df)
        return 1.0 / jnp.sqrt(jnp.maximum(fisher, 0.0) + curvature)


    def mala(self, key, theta, counts, cache, adapt, prior_scale, active, tune=False):
        """``mala_steps`` steps of the reward move (:mod:`npbrs.models.reward.mala`) after a first
        pass that solves every skill at ``theta``, with the cache's preconditioner (refreshed
        during warmup by :meth:`tune`, or here where ``tune`` is true: after the first pass, from
        its values, at the search's tolerance as :meth:`tune`); in warmup each skill's step size
        follows its acceptance rate towards ``target_accept``.

        Args:
            key: a PRNG key; theta: (K, D) weights; counts: (K, S, A) the skills' count tables.
            cache: the emission's cache (``V``, ``log_step``, ``scale``: :meth:`init_cache`).
            adapt: whether the step sizes adapt (warmup); prior_scale: sigma, scalar or (K,).
            active: (K,) bool, the skills that move (those with steps).
            tune: False, or a bool (traced or not): refresh the preconditioner after the first pass.
        Returns:
            (theta (K, D), cache with the weights' values V, the step sizes and the
            preconditioner, mean acceptance rate per skill (K,), log density (K,)).
        """
        kernel = build_kernel(self.solver, prior_scale, temperature=self.temperature,
                              epsilon=self.epsilon, prior_df=self.prior_df)
        search = self.for_search()

        def step(carry, x):
            key, evaluate = x
            state, log_step, acc_sum, scale = carry
            # the first pass solves every skill (the values of the weights returned, moved or not),
            # the steps only the skills with steps (``active``): the others are never moved
            state, info = kernel(key, state, counts, jnp.exp(log_step), scale ** 2, active | evaluate, evaluate)
            log_step = jnp.where(adapt & active & ~evaluate,
                                 log_step + 0.3 * (info.acceptance_rate - self.target_accept), log_step)
            if tune is not False:  # (the first pass's values are the weights' own: no solve)
                scale = jax.lax.cond(evaluate & tune, lambda s: search._preconditioner(s.theta, prior_scale, counts,
                                                                                      s.V, solved=True),
                                     lambda s: scale, state)
            return (state, log_step, acc_sum + info.acceptance_rate, scale), None

        # the chain's start (mala.init) is the loop's first pass: one compiled solve for both
        init = (unevaluated(theta, cache["V"]), cache["log_step"], jnp.zeros(theta.shape[0]),
                cache["scale"])
        keys = jnp.concatenate([key[None], jax.random.split(key, self.mala_steps)])
        (state, log_step, acc_sum, scale), _ = jax.lax.scan(step, init, (keys, jnp.arange(self.mala_steps + 1) == 0))
        return (state.theta, {**cache, "V": state.V, "log_step": log_step, "scale": scale}, acc_sum / self.mala_steps,
                state.log_density)

    def _rescale(self, key, theta, sigma2, log_density, counts, cache, adapt, active=True):
        """A joint move of each skill's magnitude: (theta, sigma^2) -> (c theta, c^2 sigma^2),
        log c ~ N(0, h^2). The prior of theta given sigma cancels (with the Jacobian c^(D+2)),
        so the ratio is L(c theta) / L(theta) IG(c^2 sigma^2) / IG(sigma^2) c^2: the weights that
        the skill's steps leave alone (most of them, with one weight per state) move with the
        scale instead of holding it where it is. h is tuned in warmup to accept 40%."""
        K = theta.shape[0]
        ll_old = log_density - log_prior(theta, jnp.sqrt(sigma2)[:, None])
        k_c, k_acc = jax.random.split(key)
        log_c = jnp.exp(cache["log_rescale"]) * jax.random.normal(k_c, (K,))
        c = jnp.exp(log_c)
        prop, s2_prop = theta * c[:, None], sigma2 * c ** 2
        ll_new, V_new, ok = count_log_likelihood_and_values(self.solver, prop, counts, cache["V"], self.temperature,
                                                            self.epsilon)
        prior = self._variance_prior()
        log_ratio = ll_new - ll_old + prior.log_prob(s2_prop) - prior.log_prob(sigma2) + 2.0 * log_c
        accept, rate = metropolis_accept(k_acc, log_ratio, ok & active)  # (``active``: the skills with steps)
        theta, sigma2, V = select(accept, (prop, s2_prop, V_new), (theta, sigma2, cache["V"]))
        log_rescale = jnp.where(adapt & active, cache["log_rescale"] + 0.3 * (rate - 0.4), cache["log_rescale"])
        return theta, sigma2, {**cache, "V": V, "log_rescale": log_rescale}

    # ------------------------------------------------------------------ data-driven proposal
    def proposal(self, data, weights, init=None):
        """Mean (D,) and Cholesky factor (D, D) of the Laplace proposal fitted to steps weighted by
        ``weights`` (N, T): the IRL fit (from one skill's params ``init`` when given) and its
        posterior covariance (see :meth:`laplace`), inflated by ``proposal_inflation``."""
        D = self.num_features
        one = None if init is None else {"theta": init["theta"][None]}
        mean, _, precision, _ = self.laplace(self.counts(data, weights)[None], one)
        cov = linalg.spd_inverse(precision[0]) * self.proposal_inflation ** 2
        chol = linalg.cholesky(0.5 * (cov + cov.T) + 1e-12 * jnp.eye(D))
        return mean[0], chol

    def _draw(self, key, mean, chol, broad_weight):
        """A draw of the proposal around mean; broad_weight 0: the narrow Gaussian only."""
        if broad_weight == 0:
            return mean + chol @ jax.random.normal(key, mean.shape)
        k_pick, k_draw = jax.random.split(key)
        scale = jnp.where(jax.random.bernoulli(k_pick, broad_weight), self.proposal_broad_scale, 1.0)
        return mean + scale * (chol @ jax.random.normal(k_draw, mean.shape))

    def _log_q(self, one, mean, chol):
        """log-density of the (mixture) proposal around mean at one skill's params (with the
        conditional density of its sigma^2 given theta, when sampled)."""
        theta = one["theta"]
        w = self.proposal_broad_weight
        lq = linalg.mvn_log_prob(theta, mean, chol)
        if w > 0:
            broad = linalg.mvn_log_prob(theta, mean, self.proposal_broad_scale * chol)
            lq = jnp.logaddexp(jnp.log1p(-w) + lq, jnp.log(w) + broad)
        if self.scale_prior:
            lq = lq + self._variance_conditional(theta).log_prob(one["sigma2"])
        return lq

    def _propose_one(self, key, mean, chol):
        if not self.scale_prior:
            return {"theta": self._draw(key, mean, chol, self.proposal_broad_weight)}
        k_theta, k_var = jax.random.split(key)
        theta = self._draw(k_theta, mean, chol, self.proposal_broad_weight)
        return {"theta": theta, "sigma2": self._variance_conditional(theta).sample(k_var)}

    def init_params(self, key, data, weights):
        """A starting point: each skill's IRL fit to its weighted steps (``start="fit"``, or
        "auto" with many features), or a draw of the Laplace proposal (the narrow component
        only) around it. (K, D)."""
        if self.starts_at_fit:  # the proposal's mean, every skill in one batched fit
            return self._point(self.laplace(self.counts(data, weights))[0])
        keys = jax.random.split(key, weights.shape[-1])
        return self._point(jax.vmap(lambda k, w: self._draw(k, *self.proposal(data, w), 0.0), in_axes=(0, 2))(
            keys, weights))

    def propose(self, key, data, weights):
        mean, chol = self.proposal(data, weights)
        one = self._propose_one(key, mean, chol)
        return one, self._log_q(one, mean, chol)

    def propose_and_score(self, key, data, weights, other_one, init=None):
        mean, chol = self.proposal(data, weights, init)
        one = self._propose_one(key, mean, chol)
        return one, self._log_q(one, mean, chol), self._log_q(other_one, mean, chol)

    def log_proposal(self, params_one, data, weights):
        return self._log_q(params_one, *self.proposal(data, weights))


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
