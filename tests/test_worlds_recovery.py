"""Planted recovery on small versions of the three benchmark world kinds, with ``fit``'s defaults
for one-hot rewards (each skill starts at its IRL fit: ``start="auto"`` above 16 reward weights,
on an initial segmentation of 5-step windows: the reward emission's ``init_window``) and a short
run (2 chains, 30 + 30 sweeps): the skills found and the share of steps they label right under
one-to-one matching.

What these small worlds show with the default reward prior (``prior_scale="auto"``: sigma
20 / sqrt(D) here, 3.2-4.0; fit seeds 0 / 1 / 2), the levels the tests hold so that a regression
shows: the grid's two modes are found, labelled nearly as well as by the generating model's own
Viterbi segmentation (0.948 / 0.933 / 0.949 against 0.98); rooms' three skills mostly (0.869 /
0.852 / 0.845 against the oracle's 0.97); the labyrinth's three skills are found, but labelled
little better than by its most common skill alone (0.735 / 0.698 / 0.671; the oracle 0.91: the
start and the mixing, and switching that depends on the state, which the sticky BP-HMM lacks;
``switching="state"`` has it, and ``tests/test_termination.py`` checks that a fit with it finds
where the small labyrinth's skills end). A fit with one skill slot scores each world's most
common skill's share and fails all three.

Two chains, not one: one chain's accuracy on small rooms spreads from 0.56 to 0.90 over fit
seeds (10 of 24 seeds under the floor of 0.75), so a change that moves one seed's rounding
would fail the test without changing the distribution; the best draw of two chains is above
0.75 for 11 of 12 seeds.

The default switching is "auto": the labyrinth's and the grid's default fits
are refitted with state-dependent ends (their sticky fits' skill sequences favour them), rooms'
stay sticky; the tests check the choice, and the last one how it was made."""

import dataclasses
import os

import numpy as np
import pytest

from npbrs.domains.worlds import labyrinth, rooms, tabular_grid
from npbrs.inference import fit
from npbrs.inference.analysis.metrics import hungarian_accuracy

SMALL = {
    # 40 free cells, 3 goal-seeking skills, each trajectory with its own 2 or 3 of them
    "rooms": lambda: rooms(seed=1, size=7, num_skills=3, num_trajectories=24, min_length=40, max_length=80,
                           num_heldout=2),
    # 31 nodes: explore, go to the water port, go home; skills end on reaching their goals
    "labyrinth": lambda: labyrinth(seed=1, depth=4, num_trajectories=80, num_heldout=2),
    # 25 cells, 2 modes that end mostly in their goal corners
    "tabular_grid": lambda: tabular_grid(seed=1, size=5, num_modes=2, num_trajectories=16, length=150,
                                         num_heldout=2),
}
# (the least one-to-one accuracy, the most common true skill's share of the steps)
FLOOR = {"rooms": (0.75, 0.387), "labyrinth": (0.6, 0.545), "tabular_grid": (None, 0.553)}
# the switching model fit's default ("auto") chooses: the labyrinth's and the grid's skills end
# at their goals (the sticky fits' log Bayes factors of state ends about +64 and +16), rooms'
# switch at random (about -10)
CHOSEN = {"rooms": "sticky", "labyrinth": "state", "tabular_grid": "state"}
SETTINGS = dict(num_chains=2, num_warmup=30, num_samples=30, seed=0, progress_bar=False)
_FITS = {}


def default_fit(name):
    """(world, fit's default fit of it), once per module."""
    if name not in _FITS:
        world = SMALL[name]()
        _FITS[name] = world, fit(world.mdp, world.demos, **SETTINGS)
    return _FITS[name]


@pytest.mark.parametrize("name", sorted(SMALL))
def test_a_default_fit_recovers_the_planted_skills_of_each_world_kind(name):
    world, result = default_fit(name)
    assert world.mdp.num_features > 16  # the one-hot defaults are what is tested
    truth = world.demos.skills
    steps = np.concatenate(truth)
    least, majority = FLOOR[name]
    assert np.max(np.bincount(steps)) / steps.size == pytest.approx(majority, abs=0.001)
    assert result.emission["start"] == "auto"
    assert result.switching["chosen"] == CHOSEN[name] == result.config["prior"]["switching"]
    found = hungarian_accuracy(truth, result.segmentation)
    K = world.model.num_skills
    if least is None:  # as well as the oracle, with the true number of skills or one more
        assert K <= result.num_skills <= K + 1
        assert found > hungarian_accuracy(truth, world.oracle().viterbi) - 0.05
    else:
        assert 2 <= result.num_skills <= K + 2
        assert found > least


def test_auto_switching_refits_from_the_sticky_fit_and_records_why(tmp_path):
    """The labyrinth's default fit ("auto") is a fit with state-dependent ends started from the
    segmentation of the sticky fit that fit(switching="sticky") gives with the same seed and a
    quarter of the sampling sweeps (the sticky fit stops at the decision), its record the
    evidence of that fit's skill sequences (its log Bayes factor past the margin); the record
    is in the summary and survives saving. (Checked to fail: the margin's comparison turned
    round; the state fit started from its own random windows; the decision after all the
    sampling sweeps.)"""
    from npbrs.inference import load
    from npbrs.inference.driver.strategies import SWITCHING_MARGIN, switching_evidence

    world, result = default_fit("labyrinth")
    sticky = fit(world.mdp, world.demos, {"switching": "sticky"}, **dict(SETTINGS, num_samples=SETTINGS["num_samples"] // 4))
    assert sticky.switching is None and sticky.config["prior"]["switching"] == "sticky"
    evidence = switching_evidence(sticky, world.mdp, world.demos, sticky.model_config.prior)
    assert evidence["log_bayes_factor"] > SWITCHING_MARGIN
    assert result.switching == dict(evidence, margin=SWITCHING_MARGIN, chosen="state")
    # (it refines the sticky fit's skills: a quarter of the warmup, no sticky phase, no greedy moves)
    assert result.config["sampler"]["warmup"] == SETTINGS["num_warmup"] // 4
    moves = result.config["sampler"]["moves"]
    assert moves["sticky_phase"] == 0.0 and moves["greedy_merge"] == moves["greedy_split"] == 0
    assert len(result.init_segmentation) == len(sticky.segmentation)
    for a, b in zip(result.init_segmentation, sticky.segmentation):
        np.testing.assert_array_equal(a, b)
    assert "switching chosen: state" in result.summary()
    result.save(tmp_path / "run.nc")
    assert load(tmp_path / "run.nc").equals(result)


def test_auto_switching_that_stays_sticky_draws_what_the_sticky_fit_draws():
    """Rooms' default fit ("auto") decides after a quarter of its sampling sweeps, stays
    sticky, and goes on: its draws are the sticky fit's, bit for bit. (Checked to fail: a
    sweep drawn and dropped at the decision.)"""
    world, result = default_fit("rooms")
    assert result.switching["chosen"] == "sticky"
    sticky = fit(world.mdp, world.demos, {"switching": "sticky"}, **SETTINGS)
    assert sticky.switching is None
    assert result.equals(dataclasses.replace(sticky, switching=result.switching))


def test_auto_switching_resumes_its_state_fit_from_its_own_checkpoint(tmp_path, monkeypatch):
    """With checkpoints, "auto" keeps the state fit's at state_stage_path: a run that stops in
    the state fit (here a failed checkpoint write) resumes from it, after the sticky fit's
    finished checkpoint, and ends equal to the uninterrupted run; a new run refuses to overwrite
    the interrupted one's. (``fit`` keeps a finished run's checkpoints, as it does one's; ``npbrs
    fit`` removes both once it has saved the run.)"""
    import npbrs.inference.driver.runs as runs
    from npbrs.inference.driver.strategies import state_stage_path

    world, whole = default_fit("labyrinth")
    path = tmp_path / "run.checkpoint.npz"
    stage = state_stage_path(path)
    assert stage == str(tmp_path / "run.checkpoint.state.npz")
    write = runs.write_checkpoint
    written = []

    def failing(p, **kwargs):
        written.append(os.fspath(p))
        if os.fspath(p) == stage and written.count(stage) == 2:
            raise OSError("disk full")
        write(p, **kwargs)

    monkeypatch.setattr(runs, "write_checkpoint", failing)
    with pytest.raises(OSError, match="disk full"):
        fit(world.mdp, world.demos, {"checkpoint_every": 10}, checkpoint_path=path, **SETTINGS)
    assert path.exists() and os.path.exists(stage)  # (the sticky fit's, stopped at the decision, and the state fit's)
    with pytest.raises(ValueError, match="interrupted run"):
        fit(world.mdp, world.demos, checkpoint_path=path, **SETTINGS)
    monkeypatch.setattr(runs, "write_checkpoint", write)
    resumed = fit(world.mdp, world.demos, {"checkpoint_every": 10}, checkpoint_path=path, resume=True, **SETTINGS)
    assert resumed.equals(whole) and resumed.switching == whole.switching


def test_a_sticky_auto_fit_resumed_after_its_decision_keeps_it(tmp_path, monkeypatch):
    """Rooms' auto fit stays sticky after a quarter of its sampling sweeps; stopped later (a
    failed checkpoint write) and resumed, it does not decide again on more draws (no evidence
    is computed): it ends equal to the uninterrupted run, its switching record included.
    (Checked to fail: the decision not read back from the checkpoint.)"""
    import npbrs.inference.driver.strategies as strategies
    import npbrs.inference.driver.runs as runs

    world, whole = default_fit("rooms")
    path = tmp_path / "run.checkpoint.npz"
    write = runs.write_checkpoint
    written = []

    def failing(p, **kwargs):
        written.append(os.fspath(p))
        if len(written) == 5:  # (sweep 50 of 60: past the decision, at 30 + 7)
            raise OSError("disk full")
        write(p, **kwargs)

    monkeypatch.setattr(runs, "write_checkpoint", failing)
    with pytest.raises(OSError, match="disk full"):
        fit(world.mdp, world.demos, {"checkpoint_every": 10}, checkpoint_path=path, **SETTINGS)
    monkeypatch.setattr(runs, "write_checkpoint", write)
    evidence, scored = strategies.switching_evidence, []
    monkeypatch.setattr(strategies, "switching_evidence", lambda *a: scored.append(1) or evidence(*a))
    resumed = fit(world.mdp, world.demos, {"checkpoint_every": 10}, checkpoint_path=path, resume=True, **SETTINGS)
    assert not scored and resumed.switching["chosen"] == "sticky"
    assert resumed.equals(whole) and resumed.switching == whole.switching


def test_a_default_fit_records_the_names_of_equivalent_actions_and_scores_with_them(tmp_path):
    """The labyrinth's nodes have equivalent actions (a leaf's three ways of staying, the root's
    two): the default fit records the names' factor fitted to its demonstrations (sets, log
    Bayes factor, the summary's line), keeps it through saving, and its held-out score is the
    same run's with uniform names plus the factor's exact term."""
    import dataclasses

    from npbrs.inference import load
    from npbrs.models.names import ActionNames

    world, result = default_fit("labyrinth")
    names = ActionNames.fit(world.mdp, world.demos)
    assert result.emission["action_names"] == "learned"
    assert result.action_names["sets"] == [np.flatnonzero(s).tolist() for s in names.counts.sets] != []
    assert result.action_names["log_bayes_factor"] == pytest.approx(names.log_bayes_factor)
    assert result.action_names["text"] in result.summary()
    result.save(tmp_path / "run.nc")
    assert load(tmp_path / "run.nc").action_names == result.action_names
    uniform = dataclasses.replace(result, emission=dict(result.emission, action_names="uniform"))
    a, b = (r.log_predictive(world.mdp, world.heldout, num_samples=4, num_draws=2) for r in (result, uniform))
    np.testing.assert_allclose(a.per_trajectory - b.per_trajectory, names.heldout_correction(world.mdp, world.heldout))
