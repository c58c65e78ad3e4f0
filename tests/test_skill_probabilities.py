"""``FitResult.skill_probabilities``: each fitted step's skill probabilities counted from the
sampler's own draws (``step_skill_counts``, kept by ``fit`` over the sampling sweeps), against
the chains' draws themselves and against ``segment``, which recomputes them independently (the
forward filter and smoother on a subset of the draws, the transition weights integrated out)."""

import numpy as np
import pytest

from gridworld import ragged_policy_problem
from npbrs.inference import fit, load
from npbrs.inference.analysis.diagnostics import relabel

MDP, DEMOS = ragged_policy_problem(correct=0.8)
# (the greedy moves off: their compilation is not what this tests)
CONFIG = {"emission": "policy", "max_skills": 3, "moves": {"greedy_merge": 0, "greedy_split": 0}}
KW = dict(num_chains=2, num_warmup=6, seed=5, progress_bar=False)


@pytest.mark.parametrize("method", ["vectorized", "sequential"])
def test_one_sampling_sweep_counts_exactly_its_skill_sequences(method):
    """With one sampling sweep, a chain's counts are its (only, hence best) draw's skill
    sequences, one-hot, zero on padding; the probabilities are the chains' mapped labels
    averaged."""
    result = fit(MDP, DEMOS, {**CONFIG, "chain_method": method}, num_samples=1, **KW)
    counts = result.step_skill_counts
    C, K = 2, 3
    N, T = len(DEMOS.lengths), int(max(DEMOS.lengths))
    assert counts.shape == (C, N, T, K) and counts.dtype == np.int32
    z = result.chain_best_z  # (C, N, T), -1 on padding
    np.testing.assert_array_equal(counts, (z[..., None] == np.arange(K)).astype(np.int32))
    mapping = relabel(result)
    probs = result.skill_probabilities()
    for i, m in enumerate(DEMOS.lengths):
        expected = np.zeros((m, result.num_skills))
        for c in range(C):
            skill = mapping[c, z[c, i, :m]]
            expected[np.flatnonzero(skill >= 0), skill[skill >= 0]] += 1.0 / C
        np.testing.assert_allclose(probs.probs[i], expected, atol=1e-15)
        np.testing.assert_array_equal(probs.labels[i], np.argmax(expected, -1))


def test_the_counts_agree_with_segment_and_label_the_planted_skills(tmp_path, monkeypatch):
    # (both estimates are Monte Carlo ones: mean gap 0.006, largest 0.053; 0.032 and 0.26 while
    # segment weighted each draw by the fitted trajectory's likelihood again, counting it twice)
    result = fit(MDP, DEMOS, CONFIG, num_samples=600, **KW)
    counts = result.step_skill_counts
    # every sampling sweep counts each real step once per chain, and nothing else
    total = counts.sum(-1)
    for i, m in enumerate(DEMOS.lengths):
        assert np.all(total[:, i, :m] == 600) and np.all(total[:, i, m:] == 0)
    ours = result.skill_probabilities()
    theirs = result.segment(MDP, num_draws=200, num_samples=64)
    diff = np.concatenate([np.abs(a - b).ravel() for a, b in zip(ours.probs, theirs.probs)])
    assert diff.mean() < 0.015 and diff.max() < 0.15, (diff.mean(), diff.max())
    agree = np.mean(np.concatenate(ours.labels) == np.concatenate(theirs.labels))
    assert agree > 0.96, agree
    from npbrs.inference.analysis.metrics import hungarian_accuracy

    assert hungarian_accuracy(DEMOS.skills, ours.labels) > 0.9
    # the report's segmentation plot (npbrs report --plots; no MDP there) draws these labels,
    # or the best draw's for a run without the counts
    from npbrs.inference.analysis import plots
    from npbrs.inference.cli.main import save_plots

    drawn = []
    monkeypatch.setattr(plots, "plot_trace", lambda *a, **k: None)
    monkeypatch.setattr(plots, "plot_segmentation", lambda true, inferred, *a, **k: drawn.append(inferred["npbrs"]) or {
        "npbrs": {}})
    save_plots(result, tmp_path)
    assert all(np.array_equal(a, b) for a, b in zip(drawn[-1], ours.labels))
    assert not all(np.array_equal(a, b) for a, b in zip(ours.labels, result.segmentation))  # (they differ here)
    # kept with the saved run; a run without them (saved before they were kept) says what to use
    result.save(tmp_path / "run.nc")
    again = load(tmp_path / "run.nc")
    np.testing.assert_array_equal(again.step_skill_counts, counts)
    result.step_skill_counts = None
    result.save(tmp_path / "old.nc")
    old = load(tmp_path / "old.nc")
    with pytest.raises(ValueError, match="segment"):
        old.skill_probabilities()
    save_plots(old, tmp_path)
    assert all(np.array_equal(a, b) for a, b in zip(drawn[-1], result.segmentation))


def test_a_bucketed_run_counts_only_the_demonstrations_steps():
    result = fit(MDP, DEMOS, {**CONFIG, "bucket": True}, num_samples=3, **KW)
    N, T = len(DEMOS.lengths), int(max(DEMOS.lengths))
    assert result.step_skill_counts.shape == (2, N, T, 3)
    assert int(result.step_skill_counts.sum()) == 2 * 3 * sum(DEMOS.lengths)
