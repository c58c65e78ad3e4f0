"""At the end of warmup, a chain far behind the best (by its log joint over the last tenth of
warmup) continues from the best chain's state with its own random key
(``SamplerConfig.restart_margin``, 50 nats by default); chains within the margin keep their own
states."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gridworld import ragged_policy_problem
from npbrs.inference import fit, load
from npbrs.inference.analysis.diagnostics import superchain_ids
from npbrs.inference.driver.config import SamplerConfig
from npbrs.inference.driver.chains import Chains, restart_lagging, warmup_scores
from npbrs.inference.driver.compiled import Compiled
from npbrs.inference.sampler import BPHMMKernel
from npbrs.models.emissions import PolicyEmission
from test_kernel import planted_policy_data
from test_reward_fit import _compiling


def _chain(state, c):
    return jax.tree.map(lambda x: np.asarray(x)[c], state)


def _same(a, b):
    return all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def test_the_score_is_the_mean_log_joint_of_warmups_last_tenth():
    log_joint = np.arange(2 * 25, dtype=float).reshape(2, 25) ** 2
    np.testing.assert_allclose(warmup_scores(log_joint), [(23 ** 2 + 24 ** 2) / 2, (48 ** 2 + 49 ** 2) / 2])
    np.testing.assert_allclose(warmup_scores(log_joint[:, :7]), log_joint[:, 6])  # at least the last sweep


def test_chains_beyond_the_margin_take_the_best_chains_state_and_keep_their_keys():
    data, z_true = planted_policy_data(seed=1, N=6, T=40)
    kernel = BPHMMKernel(PolicyEmission(4, 3), data, max_skills=5)
    compiled = Compiled(kernel, ())
    keys = jax.random.split(jax.random.PRNGKey(2), 3)
    # chain 0 starts at the planted segmentation, chains 1 and 2 from random windows
    planted = compiled.init(keys, 4, jnp.asarray(np.where(np.asarray(data.mask), z_true, -1)))
    windows = compiled.init(keys, 4)
    state = jax.tree.map(lambda a, b: np.concatenate([a[:1], b[1:]]), planted, windows)
    scores = [-100.0, -130.0, -200.0]  # chain 1 within a margin of 50, chain 2 beyond it
    for method in ("vectorized", "sequential"):
        chains = Chains(compiled, method, jax.tree.map(jnp.asarray, state))
        record = restart_lagging(chains, scores, 50.0)
        out = chains.state()
        assert record == {"margin": 50.0, "scores": scores, "from": [0, 1, 0]}, (method, record)
        np.testing.assert_array_equal(superchain_ids(record, 3), [0, 1, 0])  # chain 2 shares chain 0's start
        for c, source in enumerate(record["from"]):
            assert _same(_chain(out, c)._replace(rng_key=0), _chain(state, source)._replace(rng_key=0)), (method, c)
            np.testing.assert_array_equal(_chain(out, c).rng_key, _chain(state, c).rng_key)  # its own key
    # a margin no chain exceeds moves none; nor do scores none of which is finite; a chain whose
    # score is not finite lags a finite best
    for margin, values, expected in ((101.0, scores, [0, 1, 2]), (50.0, [np.nan] * 3, [0, 1, 2]),
                                     (50.0, [np.nan, -5.0, -10.0], [1, 1, 2])):
        chains = Chains(compiled, "vectorized", jax.tree.map(jnp.asarray, state))
        assert restart_lagging(chains, values, margin)["from"] == expected
        if expected == [0, 1, 2]:
            assert _same(chains.state(), state)


MDP, DEMOS = ragged_policy_problem(correct=0.8)
# (the greedy moves off: their compilation is not what this tests)
CONFIG = dict(emission="policy", max_skills=3, moves={"greedy_merge": 0, "greedy_split": 0})
KW = dict(num_chains=2, num_warmup=6, num_samples=4, seed=5, progress_bar=False)


def test_a_fit_restarts_a_lagging_chain_at_warmups_end_and_records_it(tmp_path):
    for bad in (-1.0, float("nan"), "wide", True):
        with pytest.raises(ValueError, match="restart_margin"):
            SamplerConfig(restart_margin=bad)
    off = fit(MDP, DEMOS, dict(CONFIG, restart_margin=0), **KW)
    assert off.restart is None
    assert fit(MDP, DEMOS, CONFIG, **dict(KW, num_chains=1)).restart is None
    assert SamplerConfig().restart_margin == 50.0  # on by default
    # every chain behind the best moves (a margin of ~0); none moves at a huge margin
    # the restart reads the scores the sweeps record and moves states on the host: a run that
    # restarts compiles nothing that the run without restarts has not compiled
    tight, compiles = _compiling(fit, MDP, DEMOS, dict(CONFIG, restart_margin=1e-9), **KW)
    assert compiles == [], f"the restart compiled {len(compiles)} programs ({sum(compiles):.2f} s)"
    loose = fit(MDP, DEMOS, dict(CONFIG, restart_margin=1e9), **KW)
    assert loose.restart["from"] == [0, 1] and loose.restart["scores"] == tight.restart["scores"]
    for name, v in off.stats.items():  # nothing moved: the run without the check's draws
        np.testing.assert_array_equal(loose.stats[name], v)
    scores = tight.restart["scores"]
    # the scores are the last warmup sweep's log joints (6 sweeps: their last tenth is one)
    np.testing.assert_array_equal(scores, tight.warmup_stats["log_joint"][:, -1])
    best = int(np.argmax(scores))
    other = 1 - best
    assert scores[other] < scores[best], scores  # (this seed's chains end warmup apart)
    assert tight.restart["from"] == [best, best] and tight.restart["margin"] == 1e-9
    # the best chain's draws are the run without restarts'; the other's are not, and its first
    # draw comes from the best chain's end-of-warmup state
    for name in ("log_joint", "num_switches"):
        np.testing.assert_array_equal(tight.stats[name][best], off.stats[name][best])
    assert not np.array_equal(tight.stats["log_joint"][other], off.stats["log_joint"][other])
    # (with its own key it goes its own way from there)
    assert not np.array_equal(tight.stats["log_joint"][other], tight.stats["log_joint"][best])
    np.testing.assert_array_equal(tight.warmup_stats["log_joint"], off.warmup_stats["log_joint"])
    assert "continued from chain" in tight.summary() and "continued from" not in loose.summary()
    # both chains now share the best chain's start: one superchain, whose nested R-hat is
    # undefined, so the run has not shown that it converged (ArviZ's R-hat is still shown beside)
    np.testing.assert_array_equal(tight.superchains, [best, best])
    np.testing.assert_array_equal(loose.superchains, [0, 1])
    text = tight.summary()
    assert f"chains 0 and 1 share a start (chain {other} continued from chain {best}'s state at warmup's end" in text
    assert "nested R-hat undefined: every chain shares one start" in text
    assert all(np.isnan(v) for v in tight.rhat.values())
    assert "every chain shares one start" in tight.convergence_warning().splitlines()[0]
    assert "share a start" not in loose.summary()
    np.testing.assert_equal(loose.rhat, loose.rank_rhat)  # (NaN where undefined, alike)
    # kept with the saved run, and the sequential chains do the same
    path = tmp_path / "run.nc"
    tight.save(path)
    again = load(path)
    assert again.restart == tight.restart and again.equals(tight)
    np.testing.assert_array_equal(again.to_arviz().posterior["superchain"].values, [best, best])
    sequential = fit(MDP, DEMOS, dict(CONFIG, restart_margin=1e-9, chain_method="sequential"), **KW)
    assert sequential.restart["from"] == tight.restart["from"]
    np.testing.assert_allclose(sequential.restart["scores"], scores, rtol=1e-9)
