"""Emission models follow the protocol; the registry takes user emissions."""

import jax.numpy as jnp
import numpy as np
import pytest

from emission_suite import check_emission
from npbrs.models.emissions import EMISSIONS, Emission, HMMData, PolicyEmission, get_emission_class


def small_data(S=4, A=3, N=3, T=12, seed=0):
    rng = np.random.default_rng(seed)
    mask = np.ones((N, T), bool)
    mask[0, T - 3:] = False
    return HMMData(jnp.asarray(rng.integers(0, S, (N, T)), jnp.int32),
                   jnp.asarray(rng.integers(0, A, (N, T)), jnp.int32), jnp.asarray(mask))


def test_policy_emission_follows_the_protocol():
    check_emission(PolicyEmission(4, 3), small_data())


def test_policy_update_is_the_exact_dirichlet_conditional():
    import jax

    data = small_data()
    em = PolicyEmission(4, 3, concentration=0.7)
    weights = jax.nn.one_hot(jnp.zeros(data.states.shape, int), 2) * data.mask[..., None]
    keys = jax.random.split(jax.random.PRNGKey(0), 3000)
    params = {"policy": jnp.full((2, 4, 3), 1 / 3)}
    draws = jax.vmap(lambda k: em.update(k, params, (), data, weights, 0)[0]["policy"])(keys)
    counts = np.zeros((4, 3))
    np.add.at(counts, (np.asarray(data.states)[np.asarray(data.mask)], np.asarray(data.actions)[np.asarray(data.mask)]), 1)
    a = 0.7 + counts
    mean = a / a.sum(-1, keepdims=True)
    sd = np.sqrt(mean * (1 - mean) / (a.sum(-1, keepdims=True) + 1))
    np.testing.assert_array_less(np.abs(np.asarray(draws[:, 0]).mean(0) - mean), 5 * sd / np.sqrt(len(keys)))
    # skill 1 has no steps: its policy is drawn from the prior
    np.testing.assert_allclose(np.asarray(draws[:, 1]).mean(0), 1 / 3, atol=0.03)


def test_unknown_emission_names_are_rejected_with_the_known_ones():
    with pytest.raises(ValueError, match="unknown emission 'rewards'.*policy"):
        get_emission_class("rewards")
    assert "policy" in EMISSIONS


@pytest.mark.parametrize("name", sorted(n for n, c in EMISSIONS.items() if c.__module__.startswith("npbrs.")))
def test_each_registered_emissions_declared_capabilities_are_what_its_methods_take(name):
    """The sampler reads an emission's capabilities from its flags, never from its signatures:
    here the flags are checked against the signatures, so that a method that gains or loses a
    keyword without its flag (or the reverse) fails."""
    import inspect

    cls = get_emission_class(name)
    update = inspect.signature(cls.update).parameters
    assert cls.tunes_in_update == ("tune" in update), name
    assert cls.tune is not None or not cls.tunes_in_update, f"{name}: tunes_in_update without a tune"
    # (a property where it depends on the options, the reward's: true with MALA, so update takes it)
    can_solve = cls.solves_in_update if isinstance(cls.solves_in_update, bool) else True
    assert can_solve == ("redraw_unused" in update), name
    assert cls.reports_solves == ("with_ok" in inspect.signature(cls.log_likelihoods).parameters), name
    if cls.supports_greedy_merge():
        taken = inspect.signature(cls.fit_evidence).parameters
        assert cls.fits_without_evidence == ("with_evidence" in taken), name
        assert cls.fits_with_likelihoods == ("with_likelihoods" in taken), name
    else:
        assert not (cls.fits_without_evidence or cls.fits_with_likelihoods), name


class UserEmission(Emission):
    """An emission written against the protocol alone, declaring no capability: the policy
    emission's numbers, a ``tune`` that counts its calls in the cache, and an ``update`` and a
    ``fit_evidence`` that take nothing beyond the protocol's arguments."""

    def __init__(self, num_states, num_actions):
        self.policy = PolicyEmission(num_states, num_actions)

    def sample_params(self, K):
        return self.policy.sample_params(K)

    def log_prior(self, params):
        return self.policy.log_prior(params)

    def init_cache(self, K):
        return {"tuned": jnp.zeros((), jnp.int32)}

    def log_likelihoods(self, params, data, cache=()):
        return self.policy.log_likelihoods(params, data)[0], cache

    def update(self, key, params, cache, data, weights, adapt):
        params, _, info = self.policy.update(key, params, (), data, weights, adapt)
        return params, cache, info

    def tune(self, params, cache, data, weights):
        return {"tuned": cache["tuned"] + 1}

    def propose(self, key, data, weights):
        return self.policy.propose(key, data, weights)

    def log_proposal(self, params_one, data, weights):
        return self.policy.log_proposal(params_one, data, weights)

    def fit_point(self, data, weights, init=None):
        return self.policy.fit_point(data, weights)

    def fit_evidence(self, data, weights, init=None):
        return self.policy.fit_evidence(data, weights)


def test_an_emission_that_declares_no_capability_runs_with_the_defaults():
    """The sampler runs a user's emission without the capability flags: its ``tune`` is called
    before ``update`` in each warmup sweep (never in a sampling sweep) and ``update`` is not passed
    ``tune``; the greedy merges and splits call its ``fit_evidence`` without ``with_evidence`` or
    ``with_likelihoods`` and take the fits' likelihoods from ``log_likelihoods``, and birth/death
    and split-merge call ``log_likelihoods`` without ``with_ok``. (A keyword the emission does not
    take would be a TypeError while the sweep is traced.)"""
    import jax

    from npbrs.inference.sampler import BPHMMKernel

    em = UserEmission(4, 3)
    assert not (em.tunes_in_update or em.solves_in_update or em.fits_without_evidence or em.fits_with_likelihoods
                or em.reports_solves)
    moves = {"greedy_merge": 1, "greedy_split": 1, "greedy_from": 0.0, "split_merge": 1, "birth_death": 1}
    kernel = BPHMMKernel(em, small_data(), max_skills=3, moves=moves)
    state = kernel.init(jax.random.PRNGKey(0), 2, None, (), {})
    sweep = jax.jit(kernel.sweep)
    tuned = []
    for _ in range(3):
        state = sweep(state)
        tuned.append(int(state.cache["tuned"]))
    assert tuned == [1, 2, 2]  # the two warmup sweeps, not the sampling one
