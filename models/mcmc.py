"""The Metropolis-Hastings accept-or-keep step every sampler move shares.

``metropolis_accept`` draws the accept decision from a log acceptance ratio (a proposal that is
impossible, or whose ratio is NaN, is rejected); ``select`` keeps the new value of every leaf of
a pytree where the decision accepts and the old one elsewhere. A decision of shape (K,) selects
along the leading axis of (K, ...) leaves (one decision per skill).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["metropolis_accept", "select"]


def metropolis_accept(key, log_ratio, possible=True):
    """Accept with probability min(1, exp(log_ratio)) where ``possible``.

    Args:
        key: a PRNG key (one uniform per entry of ``log_ratio``).
        log_ratio: log acceptance ratio, any shape; NaN counts as -inf.
        possible: bool, broadcast to ``log_ratio``: False rejects whatever the ratio.
    Returns:
        (accept bool, acceptance probability min(1, exp(log_ratio)), 0 where impossible).
    """
    log_ratio = jnp.asarray(log_ratio)
    log_ratio = jnp.where(possible & ~jnp.isnan(log_ratio), log_ratio, -jnp.inf)
    accept = jnp.log(jax.random.uniform(key, log_ratio.shape)) < log_ratio
    return accept, jnp.exp(jnp.minimum(log_ratio, 0.0))


def select(accept, new, old):
    """The leaves of ``new`` where ``accept``, else those of ``old`` (pytrees of one structure).

    ``accept`` has the shape of the leaves' leading axes (a scalar, or (K,) for leaves (K, ...))."""
    accept = jnp.asarray(accept)

    def pick(x, y):
        x = jnp.asarray(x)
        return jnp.where(accept.reshape(accept.shape + (1,) * (x.ndim - accept.ndim)), x, y)

    return jax.tree.map(pick, new, old)
