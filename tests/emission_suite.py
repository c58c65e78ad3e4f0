"""The checks every emission model must pass to plug into the sampler unchanged.

Use from a test module::

    from emission_suite import check_emission
    def test_my_emission_follows_the_protocol():
        check_emission(MyEmission(...), data)
"""

import jax
import jax.numpy as jnp
import numpy as np
from numpyro import handlers
from numpyro.infer.util import log_density

from npbrs.inference.sampler.kernel import BPHMMKernel
from npbrs.models.emissions import Emission, EmissionInfo, HMMData


def _tree_close(a, b, **kw):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), **kw)


def check_emission(emission: Emission, data: HMMData, max_skills: int = 3, seed: int = 0, sweeps: int = 2,
                   sampler: bool = True):
    """Assert that ``emission`` follows the protocol of :mod:`npbrs.models.emissions`; with
    ``sampler``, also that the sampler runs ``sweeps`` sweeps with it and its log joint is the
    NumPyro model's (emission-independent code once the prior check above passes: a test may
    leave it to a fit it runs anyway)."""
    K = max_skills
    N, T = data.states.shape
    key = jax.random.PRNGKey(seed)

    # prior: the sites of sample_params and log_prior agree, per skill (compiled as one program:
    # run op by op, the distributions' code compiled a hundred tiny programs)
    def prior(rng_key):
        with handlers.seed(rng_seed=rng_key):
            tr = handlers.trace(lambda: emission.sample_params(K)).get_trace()
        params = {name: site["value"] for name, site in tr.items() if site["type"] == "sample"}
        site_lp = sum(jnp.sum(site["fn"].log_prob(site["value"])) for site in tr.values() if site["type"] == "sample")
        return params, site_lp, emission.log_prior(params)

    params, site_lp, lp = jax.jit(prior)(key)
    assert params, "sample_params must declare at least one sample site"
    for name, value in params.items():
        assert value.shape[0] == K, f"site {name!r} must have a leading axis of K={K}, got {value.shape}"
    assert lp.shape == (K,), f"log_prior must return shape ({K},), got {lp.shape}"
    np.testing.assert_allclose(float(jnp.sum(lp)), float(site_lp), rtol=1e-8, atol=1e-8)

    # likelihoods: (N, T, K), finite on real steps, independent of the cache (each piece is
    # compiled once and called twice, not run op by op: that compiled hundreds of one-operation
    # programs, a minute of the suite for the reward emission)
    cache = jax.jit(emission.init_cache, static_argnums=0)(K)
    log_likelihoods = jax.jit(emission.log_likelihoods)
    ll, cache = log_likelihoods(params, data, cache)
    assert ll.shape == (N, T, K), f"log_likelihoods must return (N, T, K) = {(N, T, K)}, got {ll.shape}"
    assert bool(jnp.all(jnp.isfinite(jnp.where(data.mask[..., None], ll, 0.0))))
    ll_again, _ = log_likelihoods(params, data, cache)
    np.testing.assert_allclose(np.asarray(ll_again), np.asarray(ll), rtol=1e-7, atol=1e-6)

    # update: jit-able, keeps shapes
    weights = jax.jit(lambda k, m: jax.nn.one_hot(jax.random.randint(k, (N, T), 0, K), K) * m[..., None])(key, data.mask)
    new, cache2, info = jax.jit(emission.update)(key, params, cache, data, weights, jnp.bool_(True))
    assert jax.tree.structure(new) == jax.tree.structure(params)
    for a, b in zip(jax.tree.leaves(new), jax.tree.leaves(params)):
        assert a.shape == b.shape and bool(jnp.all(jnp.isfinite(a)))
    assert isinstance(info, EmissionInfo) and info.accept.shape == ()

    # proposal: the returned log density is the one log_proposal gives (the three methods in one
    # program: XLA shares their common work, a third less compiling for the reward emission)
    w_one = weights[..., 0]
    other = jax.tree.map(lambda x: x[1], params)

    def proposals(key, data, w, other):
        one, log_q = emission.propose(key, data, w)
        return (one, log_q, emission.log_proposal(one, data, w), emission.propose_and_score(key, data, w, other),
                emission.log_proposal(other, data, w))

    one, log_q, log_q_again, (new2, lq_new, lq_other), lq_other_again = jax.jit(proposals)(key, data, w_one, other)
    np.testing.assert_allclose(float(log_q), float(log_q_again), rtol=1e-8, atol=1e-8)
    for name, value in one.items():
        assert value.shape == params[name].shape[1:]
    _tree_close(new2, one, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(float(lq_new), float(log_q), rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(float(lq_other), float(lq_other_again), rtol=1e-8, atol=1e-8)

    # point fits (split-merge moves): deterministic, parameter-shaped, finite
    if emission.supports_split_merge():
        w2 = weights[..., :2]
        fits = jax.jit(emission.fit_point)(data, w2)
        again = jax.jit(emission.fit_point)(data, w2, fits)
        for name, value in fits.items():
            assert value.shape == (2,) + params[name].shape[1:], f"fit_point: site {name!r} has shape {value.shape}"
            assert bool(jnp.all(jnp.isfinite(value))) and bool(jnp.all(jnp.isfinite(again[name])))
        _tree_close(jax.jit(emission.fit_point)(data, w2), fits, rtol=1e-12, atol=1e-12)

    if not sampler:
        return None
    # the sampler runs with it, and its log joint is the model's
    kernel = BPHMMKernel(emission, data, max_skills=K)
    state = kernel.init(key, 0, None, (), {})
    sweep = jax.jit(kernel.sweep)
    for _ in range(sweeps):
        state = sweep(state)
    model_lp = jax.jit(lambda p: log_density(kernel.model, (), {}, p)[0])(
        {"omega": state.omega, "features": state.features, "eta": state.eta, **state.params})
    np.testing.assert_allclose(float(state.log_joint), float(model_lp), rtol=1e-7)
    return state
