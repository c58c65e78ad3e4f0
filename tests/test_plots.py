"""Figures: the paper's colour labelling of inferred skills, and PNG files written."""

import numpy as np
import pytest

from npbrs.inference.analysis.plots import (UNMATCHED, plot_segmentation, plot_skill_probabilities, plot_skill_rewards,
                                            plot_trace, skill_styles, true_styles)
from npbrs.inference.driver.results import FitResult

TRUE = [np.array([0, 0, 0, 0, 1, 1, 1, 1, 1, 1]), np.array([2, 2, 2, 2, 1, 1, 1, 1, 0, 0])]
# inferred 7 is mostly true 0; 3 (7 steps) and 5 (2 steps) are mostly true 1; 4 has true 2 only;
# 9 covers one step of true 1 and one of true 2: no majority
INFERRED = [np.array([7, 7, 7, 7, 3, 3, 3, 3, 5, 5]), np.array([4, 4, 4, 9, 9, 3, 3, 3, 7, 7])]


def test_inferred_skills_take_the_true_label_of_their_majority():
    styles = skill_styles(TRUE, INFERRED, labels=("A", "B", "C"))
    assert {k: s.name for k, s in styles.items()} == {3: "B", 4: "C", 5: "B1", 7: "A", 9: "unmatched"}
    assert {k: s.true_label for k, s in styles.items()} == {3: 1, 4: 2, 5: 1, 7: 0, 9: None}
    base = true_styles(TRUE, ("A", "B", "C"))
    assert styles[3].colour == base[1].colour and styles[7].colour == base[0].colour
    assert styles[9].colour == UNMATCHED
    # B1 is a lighter shade of B's colour: same hue, different from every other colour
    b, b1 = np.array(styles[3].colour[:3]), np.array(styles[5].colour[:3])
    assert np.all(b1 >= b) and not np.allclose(b, b1)
    room = b < 1
    fraction = (b1 - b)[room] / (1 - b)[room]  # the same blend towards white in every channel
    assert np.allclose(fraction, fraction[0])
    assert len({s.colour for s in styles.values()}) == 5


def test_without_true_skills_every_inferred_skill_has_its_own_colour():
    styles = skill_styles(None, INFERRED)
    assert [s.name for s in styles.values()] == ["3", "4", "5", "7", "9"]
    assert len({s.colour for s in styles.values()}) == 5


def is_png(path):
    with open(path, "rb") as f:
        head = f.read(8)
    from matplotlib.image import imread

    return head == b"\x89PNG\r\n\x1a\n" and imread(str(path)).ndim == 3


def test_plot_segmentation_writes_a_png(tmp_path):
    path = tmp_path / "segmentation.png"
    other = [np.zeros(10, int), np.ones(10, int)]
    styles = plot_segmentation(TRUE, {"NPBRS": INFERRED, "subgoal": other}, path, labels=("A", "B", "C"),
                               title="two methods")
    assert is_png(path) and styles["NPBRS"][5].name == "B1"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["segmentation.png"]  # no temporary left behind
    plot_segmentation(None, {"NPBRS": INFERRED}, tmp_path / "alone.png", trajectories=[1])
    assert is_png(tmp_path / "alone.png")
    with pytest.raises(ValueError, match="no trajectories to plot"):
        plot_segmentation(TRUE, {"NPBRS": INFERRED}, tmp_path / "none.png", trajectories=[])
    with pytest.raises(ValueError, match="trajectory 1: segmentation 'NPBRS' has shape \\(3,\\), expected \\(10,\\)"):
        plot_segmentation(TRUE, {"NPBRS": [INFERRED[0], np.zeros(3, int)]}, tmp_path / "bad.png")


def test_many_trajectories_are_drawn_as_one_raster_of_a_viewable_size(tmp_path):
    """Behaviour data (hundreds of short trajectories): one raster, not a panel per trajectory
    (200 panels made a PNG 12,000 pixels tall); every trajectory's colours are in it."""
    from matplotlib.image import imread

    from npbrs.inference.analysis.plots import PANELS

    N = 48
    assert PANELS < N
    rng = np.random.default_rng(0)
    true = [np.repeat([0, 1], 10) for _ in range(N)]
    true[-1] = np.full(20, 2)  # only the last trajectory has true skill 2
    inferred = [t.copy() for t in true]
    path = tmp_path / "many.png"
    styles = plot_segmentation(true, {"npbrs": inferred}, path, trajectories=rng.permutation(N))
    image = imread(str(path))
    assert image.shape[0] < 1000, image.shape  # a panel each: about 3,100 pixels
    colours = image[..., :3].reshape(-1, 3)
    for style in styles["npbrs"].values():  # each skill's colour is drawn, the last trajectory's too
        assert np.any(np.all(np.abs(colours - np.array(style.colour[:3])) < 0.02, axis=1)), style


def test_plot_trace_and_skill_rewards_write_pngs(tmp_path):
    rng = np.random.default_rng(0)
    C, D = 2, 30
    stats = {"log_joint": rng.normal(size=(C, D)), "num_skills": rng.integers(2, 5, (C, D)),
             "num_switches": rng.random((C, D)) * 5, "accept": np.ones((C, D))}
    result = FitResult(segmentation=TRUE, num_skills=3, skill_params={}, skill_slots=np.arange(3), best_chain=0,
                       best_log_joint=0.0, stats=stats, samples={})
    plot_trace(result, tmp_path / "trace.png")
    assert is_png(tmp_path / "trace.png")
    theta = np.array([[500.0, 0.0, 0.0, 0.0], [-500.0, 0.0, 10.0, 0.0], [-500.0, 10.0, 0.0, 0.0]])
    plot_skill_rewards(theta, ["collision", "left_lane", "right_lane", "on_verge"], tmp_path / "rewards.png",
                       skill_names=["A", "B", "C"])
    assert is_png(tmp_path / "rewards.png")
    with pytest.raises(ValueError, match="3 feature names for 4 features"):
        plot_skill_rewards(theta, ["a", "b", "c"], tmp_path / "bad.png")


def test_a_reward_per_state_is_drawn_as_a_heat_map_of_a_viewable_size(tmp_path):
    """One-hot state features (127 in the labyrinth, up to a million in a robot world): a heat
    map 14 inches wide (bars for 127 features were 25,000 pixels wide), its reddest cell the
    largest weight, its bluest the smallest."""
    from matplotlib import colormaps
    from matplotlib.image import imread

    from npbrs.inference.analysis.plots import BARS

    K, D = 3, 127
    assert D > BARS
    theta = np.zeros((K, D))
    theta[1, 40], theta[2, 90] = 8.0, -8.0
    plot_skill_rewards(theta, [f"s{d}" for d in range(D)], tmp_path / "states.png")
    image = imread(str(tmp_path / "states.png"))[..., :3]
    assert image.shape[1] <= 1500, image.shape
    image = image[:, :int(0.85 * image.shape[1])]  # the map, without its colour bar
    for value in (1.0, 0.0):  # the colour map's ends: +8 and -8
        target = np.array(colormaps["RdBu_r"](value)[:3])
        close = np.all(np.abs(image - target) < 0.02, axis=-1)
        rows, cols = np.nonzero(close)
        assert rows.size > 20, value  # a cell of the map, not a stray pixel
        assert np.ptp(cols) < image.shape[1] / D * 2 + 4  # one column wide
    plot_skill_rewards(np.ones((2, 10 ** 5)), [str(d) for d in range(10 ** 5)], tmp_path / "million.png")
    assert imread(str(tmp_path / "million.png")).shape[1] <= 1500


def test_the_report_draws_rewards_as_posterior_means_in_the_segmentations_colours(tmp_path):
    """The reward plot's bars are the posterior means with their interval (not the best draw's
    weights), each skill in the colour and name the segmentation plot gave it; true skills
    without names are called by their values, not invented letters."""
    from npbrs.domains.demos import Demonstrations
    from npbrs.inference.cli.main import reward_plot_inputs
    from npbrs.inference.driver.config import ModelConfig
    from npbrs.inference.analysis.diagnostics import skill_summary

    rng = np.random.default_rng(0)
    seg = [np.array([0, 0, 1, 1, 1, 2, 2]), np.array([2, 2, 2, 0, 0, 1, 1])]
    true = [np.array([1, 1, 0, 0, 0, 2, 2]), np.array([2, 2, 2, 1, 1, 0, 0])]
    demos = Demonstrations([np.arange(7), np.arange(7)], [np.zeros(7, int), np.ones(7, int)], true)
    theta = rng.normal(size=(1, 5, 3, 2))
    result = FitResult(segmentation=seg, num_skills=3, skill_params={"theta": theta[0, -1] + 100.0},
                       skill_slots=np.arange(3), best_chain=0, best_log_joint=0.0,
                       stats={"log_joint": np.zeros((1, 5))},
                       samples={"theta": theta, "skill_steps": np.ones((1, 5, 3), np.int64)},
                       config=ModelConfig().to_dict(), feature_names=("f", "g"), demos=demos,
                       chain_best_z=np.stack(seg)[None])
    styles = plot_segmentation(true, {"npbrs": seg}, tmp_path / "seg.png")["npbrs"]
    assert {k: s.name for k, s in styles.items()} == {0: "true 1", 1: "true 0", 2: "true 2"}
    names, mean, (lower, upper), colours, labels = reward_plot_inputs(result, styles)
    table = skill_summary(result, "theta")
    np.testing.assert_allclose(mean, table["mean"].to_numpy().reshape(3, 2))
    np.testing.assert_allclose(mean, theta[0].mean(0))  # not the best draw's (+100)
    assert np.all(lower <= mean) and np.all(mean <= upper)
    assert colours == [styles[k].colour for k in range(3)]
    assert labels == ["skill 0 (true 1)", "skill 1 (true 0)", "skill 2 (true 2)"] and names == ["f", "g"]
    plot_skill_rewards(mean, names, tmp_path / "r.png", skill_names=labels, interval=(lower, upper), colours=colours)
    assert is_png(tmp_path / "r.png")
    with pytest.raises(ValueError, match="interval bounds must have shape"):
        plot_skill_rewards(mean, names, tmp_path / "r.png", interval=(lower[:2], upper))


def _kept_figures(monkeypatch):
    """{path: the Figure written there}: plots.save_figure wrapped, so each figure is kept and written."""
    from npbrs.inference.analysis import plots

    kept, save = {}, plots.save_figure

    def keep(fig, path):
        kept[str(path)] = fig
        save(fig, path)

    monkeypatch.setattr(plots, "save_figure", keep)
    return kept


def _runs(flags):
    """(start, length) of the runs of True in a 1-D boolean array."""
    edges = np.diff(np.concatenate([[0], flags.astype(int), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return list(zip(starts, ends - starts))


def test_a_raster_of_many_trajectories_has_a_gap_between_them_and_labels_each(tmp_path, monkeypatch):
    """48 trajectories: a white gap of a few pixels between consecutive trajectories' rows (they
    ran together), and a tick label for every one (only every other one was labelled); far more
    than fit are labelled at a fixed stride, which the axis label says."""
    from matplotlib.image import imread

    kept = _kept_figures(monkeypatch)
    N = 48
    true = [np.repeat([0, 1], 10) for _ in range(N)]
    path = tmp_path / "many.png"
    plot_segmentation(true, {"npbrs": [t.copy() for t in true]}, path)
    image = imread(str(path))[..., :3]
    assert image.shape[0] < 1000, image.shape
    column = image[:, int(0.6 * image.shape[1])]  # step 12 of 20: skill 1 in every row
    colour = np.array(true_styles(true)[1].colour[:3])
    drawn = np.all(np.abs(column - colour) < 0.02, axis=-1)
    blocks = _runs(drawn)
    assert len(blocks) == N, len(blocks)  # each trajectory's rows apart from the next one's
    gaps = [b[0] - (a[0] + a[1]) for a, b in zip(blocks, blocks[1:])]
    assert min(gaps) >= 3, gaps
    assert np.all(column[blocks[0][0] + blocks[0][1]:blocks[0][0] + blocks[0][1] + gaps[0]] > 0.97)  # white
    ax = kept[str(path)].axes[0]
    assert [t.get_text() for t in ax.get_yticklabels()] == [str(i) for i in range(N)]
    assert min(t.get_fontsize() for t in ax.get_yticklabels()) >= 7
    assert "every" not in ax.get_ylabel()
    many = [np.repeat([0, 1], 10) for _ in range(400)]
    plot_segmentation(many, {"npbrs": many}, tmp_path / "400.png")
    ax = kept[str(tmp_path / "400.png")].axes[0]
    shown = [int(t.get_text()) for t in ax.get_yticklabels()]
    stride = shown[1] - shown[0]
    assert stride > 1 and shown == list(range(0, 400, stride)) and f"every {stride}" in ax.get_ylabel()


def test_a_reward_per_state_is_drawn_on_the_states_grid(tmp_path, monkeypatch):
    """One-hot rewards of a gridworld, given the states' 2-D coordinates: each skill's weights on
    the grid, a small multiple per skill (not a heat map of skills by 100 state columns);
    missing cells (walls) left blank."""
    kept = _kept_figures(monkeypatch)
    rows, cols = 4, 6
    cells = np.array([(r, c) for r in range(rows) for c in range(cols)], dtype=float)[:-1]  # a wall at (3, 5)
    D = len(cells)
    theta = np.zeros((3, D))
    theta[0, 5], theta[1, 18], theta[2, 7] = 8.0, -8.0, 3.0  # (0, 5), (3, 0), (1, 1)
    path = tmp_path / "grid.png"
    plot_skill_rewards(theta, [f"state{d}" for d in range(D)], path, skill_names=["A", "B", "C"],
                       coordinates=cells, title="reward per state")
    assert is_png(path)
    panels = [ax for ax in kept[str(path)].axes if ax.images and ax.get_label() != "<colorbar>"]
    assert [ax.get_title() for ax in panels] == ["A", "B", "C"]
    for ax, k, (r, c) in zip(panels, range(3), [(0, 5), (3, 0), (1, 1)]):
        grid = np.ma.filled(ax.images[0].get_array().astype(float), np.nan)
        assert grid.shape == (rows, cols)
        assert np.isnan(grid[3, 5])  # the wall
        assert grid[r, c] == theta[k].max() if k != 1 else grid[r, c] == -8.0
    with pytest.raises(ValueError, match="coordinates"):
        plot_skill_rewards(theta, [str(d) for d in range(D)], tmp_path / "bad.png", coordinates=cells[:5])


def test_a_heat_map_of_many_features_has_few_readable_tick_labels(tmp_path, monkeypatch):
    """Without coordinates a reward per state stays a heat map, its feature ticks a readable few
    (72 labels of 6 points were illegible)."""
    kept = _kept_figures(monkeypatch)
    for D in (60, 127, 5000):
        path = tmp_path / f"heat{D}.png"
        plot_skill_rewards(np.ones((2, D)), [f"state{d}" for d in range(D)], path)
        ax = kept[str(path)].axes[0]
        labels = [t for t in ax.get_xticklabels() if t.get_text()]
        assert 3 <= len(labels) <= 30, (D, len(labels))
        assert min(t.get_fontsize() for t in labels) >= 8
        assert all(t.get_text().startswith("state") for t in labels)


def test_skill_probabilities_take_the_colours_given(tmp_path, monkeypatch):
    """``npbrs segment --plot`` draws each skill in the run's colour (the report's), not the
    palette's k-th."""
    kept = _kept_figures(monkeypatch)
    probs = [np.tile([0.7, 0.2, 0.1], (5, 1))]
    colours = [UNMATCHED, (0.1, 0.2, 0.3, 1.0), (0.9, 0.5, 0.1, 1.0)]
    plot_skill_probabilities(probs, tmp_path / "p.png", colours=colours)
    fig = kept[str(tmp_path / "p.png")]
    bands = fig.axes[0].collections
    assert [tuple(b.get_facecolor()[0]) for b in bands] == [tuple(c) for c in colours]
    assert [tuple(h.get_facecolor()) for h in fig.legends[0].legend_handles] == [tuple(c) for c in colours]
    with pytest.raises(ValueError, match="2 colours for 3 skills"):
        plot_skill_probabilities(probs, tmp_path / "p.png", colours=colours[:2])
