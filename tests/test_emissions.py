"""Emission models follow the protocol; the registry takes user emissions."""

import jax.numpy as jnp
import numpy as np
import pytest

from emission_suite import check_emission
from npbrs.models.emissions import EMISSIONS, HMMData, PolicyEmission, get_emission_class


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
