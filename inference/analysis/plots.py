"""Figures: segmentations in the style of the paper's Figures 4 and 9, trace plots of the
label-invariant diagnostics, and the skills' reward weights.

Figures are drawn on matplotlib ``Figure`` objects with the Agg canvas (no pyplot, so the
caller's backend is left alone) and written as PNG files atomically (a temporary file, then a
rename).

Colours of a segmentation follow the paper's labelling (section IV-B): an inferred skill takes
the label of the true skill that covers more than 50% of its steps
(:func:`~npbrs.inference.analysis.metrics.paper_labelling`). When several inferred skills take the same
label, the one with the most steps is named after the true skill ("B") and the others get
numbered names ("B1", "B2", ...) in shades of the true skill's colour; inferred skills without a
majority are grey ("unmatched").
"""

from __future__ import annotations

import os
import tempfile
from typing import Dict, List, NamedTuple, Optional, Sequence

import numpy as np

from .diagnostics import shown_segmentation
from .metrics import paper_labelling

__all__ = ["SkillStyle", "skill_styles", "true_styles", "shown_segmentation", "run_styles", "skill_legend",
           "plot_segmentation", "plot_trace", "plot_skill_rewards", "plot_skill_probabilities"]

# tab10 without its grey, which is kept for unmatched skills
PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#bcbd22", "#17becf")
UNMATCHED = (0.62, 0.62, 0.62, 1.0)
PANELS = 16  # plot_segmentation: a panel per trajectory up to this many, one raster beyond
RASTER_ROW = 0.05  # plot_segmentation's raster: inches a row (a method's row, or the gap after a trajectory)
LABEL_PIXELS = 10  # plot_segmentation's raster: a trajectory label each while a trajectory is this many pixels tall
BARS = 24  # plot_skill_rewards: bars up to this many features, a heat map beyond
HEAT_TICKS = 28  # plot_skill_rewards' and plot_skill_ends' heat maps: column labels per 14 inches


class SkillStyle(NamedTuple):
    """How a skill is drawn: its displayed name, RGBA colour, and the true label it took (or None)."""

    name: str
    colour: tuple
    true_label: Optional[int]


def _rgba(colour) -> tuple:
    from matplotlib.colors import to_rgba

    return tuple(float(c) for c in to_rgba(colour))


def _shade(colour, n: int) -> tuple:
    """The n-th shade of a colour: n = 0 the colour itself, then alternately lighter and darker."""
    r, g, b, a = _rgba(colour)
    if n == 0:
        return (r, g, b, a)
    step = 0.3 * ((n + 1) // 2) / (1 + 0.3 * ((n + 1) // 2))  # 0.23, 0.375, 0.47, ... never reaching 1
    target = 1.0 if n % 2 else 0.0  # odd: towards white, even: towards black
    return tuple(c + step * (target - c) for c in (r, g, b)) + (a,)


def _names(labels: Optional[Sequence[str]], count: int) -> List[str]:
    if labels is None:  # true skills without names: their label values, not invented names
        return [f"true {j}" for j in range(count)]
    labels = [str(x) for x in labels]
    if len(labels) < count:
        raise ValueError(f"{len(labels)} label names for {count} true skills")
    return labels


def true_styles(true, labels: Optional[Sequence[str]] = None) -> Dict[int, SkillStyle]:
    """Styles of the true skills present: label j is named ``labels[j]`` (default "true j")."""
    present = np.unique(np.concatenate([np.asarray(z, dtype=np.int64) for z in true]))
    names = _names(labels, int(present.max()) + 1)
    return {int(j): SkillStyle(names[j], _rgba(PALETTE[j % len(PALETTE)]), int(j)) for j in present}


def skill_styles(true, inferred, labels: Optional[Sequence[str]] = None) -> Dict[int, SkillStyle]:
    """How to draw each inferred skill, under the paper's labelling against the true skills.

    Args:
        true: per-trajectory true skill sequences, or None (then every inferred skill gets its
            own colour and its label as its name).
        inferred: per-trajectory inferred skill sequences (the same lengths).
        labels: names of the true skills (default "true 0", "true 1", ...).
    Returns:
        {inferred label: SkillStyle} for every inferred label present.
    """
    z = [np.asarray(s, dtype=np.int64) for s in inferred]
    counts = np.bincount(np.concatenate(z)) if z else np.zeros(0, int)
    present = np.flatnonzero(counts)
    if true is None:
        return {int(k): SkillStyle(str(k), _rgba(PALETTE[i % len(PALETTE)]), None) for i, k in enumerate(present)}
    base = true_styles(true, labels)
    names = _names(labels, max(base) + 1)
    labelling = paper_labelling(true, z)
    styles = {}
    for j in sorted({t for t in labelling.values() if t is not None}):
        members = sorted((k for k, t in labelling.items() if t == j), key=lambda k: (-counts[k], k))
        for n, k in enumerate(members):
            colour = base[j].colour if j in base else _rgba(PALETTE[j % len(PALETTE)])
            variant = f"{names[j]}.{n}" if names[j][-1:].isdigit() else f"{names[j]}{n}"
            styles[k] = SkillStyle(names[j] if n == 0 else variant, _shade(colour, n), j)
    for k, t in labelling.items():
        if t is None:
            styles[k] = SkillStyle("unmatched", UNMATCHED, None)
    return dict(sorted(styles.items()))


def run_styles(result, labels: Optional[Sequence[str]] = None) -> Dict[int, SkillStyle]:
    """How a run's skills are drawn in every figure of the run: :func:`skill_styles` of
    :func:`shown_segmentation` against the run's true skills (when its demonstrations hold them),
    the styles of the report's segmentation figure.

    Args:
        result: a FitResult.
        labels: names of the true skills (default "true 0", "true 1", ...).
    Returns:
        {skill: SkillStyle} for every skill the shown segmentation uses (:func:`skill_legend`
        gives the others grey).
    """
    true = result.demos.skills if result.demos is not None else None
    return skill_styles(true, shown_segmentation(result)[0], labels)


def skill_legend(styles: Dict[int, SkillStyle], num_skills: int, with_true: bool = True):
    """Each of a run's skills' colour and legend name from its ``styles`` (:func:`run_styles`):
    skill k's colour, grey (``UNMATCHED``) for a skill without a style, and "skill k (its true
    skill's name)".

    Args:
        styles: {skill: SkillStyle}.
        num_skills: the run's number of skills.
        with_true: whether the styles' names are true skills' (else "skill k" alone).
    Returns:
        (colours, names), each a list of ``num_skills``.
    """
    colours = [styles[k].colour if k in styles else UNMATCHED for k in range(num_skills)]
    names = [f"skill {k}" + (f" ({styles[k].name})" if k in styles and with_true else "") for k in range(num_skills)]
    return colours, names


def save_figure(fig, path) -> None:
    """Write a figure as PNG atomically (a temporary file in the same folder, then a rename); every
    plot function here writes through it.

    Args:
        fig: a matplotlib Figure.
        path: the PNG file to write.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(suffix=".png", prefix=".tmp-", dir=folder)
    try:
        with os.fdopen(fd, "wb") as f:
            fig.savefig(f, format="png", dpi=fig.dpi, bbox_inches="tight")
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes the file private; a plot is not
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def _check_sequences(seqs, lengths, what):
    seqs = [np.asarray(s) for s in seqs]
    if lengths is not None:
        if len(seqs) != len(lengths):
            raise ValueError(f"{what} has {len(seqs)} trajectories, expected {len(lengths)}")
        for i, (s, n) in enumerate(zip(seqs, lengths)):
            if s.ndim != 1 or len(s) != n:
                raise ValueError(f"trajectory {i}: {what} has shape {s.shape}, expected ({n},)")
    for i, s in enumerate(seqs):
        if s.size and (s.dtype.kind not in "iu" or s.min() < 0):
            raise ValueError(f"trajectory {i}: {what} must hold non-negative integer labels")
    return seqs


def _ordinal(n: int) -> str:
    """2 -> "2nd", 11 -> "11th", 23 -> "23rd"."""
    suffix = "th" if n % 100 in (11, 12, 13) else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def plot_segmentation(true, inferred: Dict[str, Sequence], path, labels: Optional[Sequence[str]] = None,
                      trajectories: Optional[Sequence[int]] = None, title: Optional[str] = None) -> Dict[str, Dict]:
    """Draw segmentations as in the paper's Figures 4 and 9 and save them as a PNG.

    Per trajectory, one row per method (the true sequence first), each step coloured by its
    skill's label (see the module docstring). Up to ``PANELS`` trajectories get a panel each;
    more (behaviour data: hundreds of short trajectories) are stacked in one raster, a block of
    rows per trajectory and a white gap a row high after it, so that the picture stays a picture
    (200 panels were a PNG 12,000 pixels tall that took 6 s to draw); every trajectory is
    labelled while the labels fit (about 100), else every n-th, as the axis label says.

    Args:
        true: per-trajectory true skill sequences, or None.
        inferred: {method name: per-trajectory inferred skill sequences}.
        path: the PNG file to write.
        labels: names of the true skills (default "true 0", "true 1", ...).
        trajectories: which trajectories to draw (default all).
        title: optional figure title.
    Returns:
        {method name: {inferred label: SkillStyle}}, the styles used.
    """
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    if not inferred:
        raise ValueError("no inferred segmentations to plot")
    first = next(iter(inferred.values()))
    lengths = [len(s) for s in (true if true is not None else first)]
    true = None if true is None else _check_sequences(true, None, "true")
    methods = {name: _check_sequences(seqs, lengths, f"segmentation {name!r}") for name, seqs in inferred.items()}
    styles = {name: skill_styles(true, seqs, labels) for name, seqs in methods.items()}
    rows = ([("true", true, true_styles(true, labels))] if true is not None else []) + \
        [(name, methods[name], styles[name]) for name in methods]
    chosen = list(range(len(lengths))) if trajectories is None else [int(i) for i in trajectories]
    if not chosen:
        raise ValueError("no trajectories to plot")
    for i in chosen:
        if not 0 <= i < len(lengths):
            raise ValueError(f"trajectory {i} is outside 0..{len(lengths) - 1}")
    T = max(lengths[i] for i in chosen)

    def block(i):  # (rows, T, RGBA): trajectory i's rows, white past its end
        image = np.ones((len(rows), T, 4))
        for r, (_, seqs, style) in enumerate(rows):
            image[r, :lengths[i]] = [style[int(k)].colour for k in seqs[i]]
        return image

    if len(chosen) <= PANELS:
        row_h = 0.22
        fig = Figure(figsize=(10, len(chosen) * (len(rows) * row_h + 0.25) + 0.9), dpi=100)
        axes = fig.subplots(len(chosen), 1, squeeze=False)[:, 0]
        for ax, i in zip(axes, chosen):
            ax.imshow(block(i), aspect="auto", interpolation="nearest", extent=(0, T, len(rows), 0))
            ax.set_yticks(np.arange(len(rows)) + 0.5)
            ax.set_yticklabels([name for name, _, _ in rows], fontsize=7)
            ax.set_ylabel(f"{i}", rotation=0, ha="right", va="center", fontsize=8)
            ax.tick_params(axis="x", labelsize=7, labelbottom=ax is axes[-1])
            ax.set_xlim(0, T)
            for r in range(1, len(rows)):
                ax.axhline(r, color="white", linewidth=0.8)
        hspace = 0.35
    else:  # one raster: per trajectory its rows and a white gap row
        height = len(rows) + 1
        image = np.ones((len(chosen) * height, T, 4))
        for b, i in enumerate(chosen):
            image[b * height:b * height + len(rows)] = block(i)
        # RASTER_ROW inches a row: a trajectory's block (and its gap, a row high) a few pixels
        # tall, up to 14 inches in all
        fig = Figure(figsize=(10, min(14.0, 1.5 + RASTER_ROW * image.shape[0])), dpi=100)
        ax = fig.subplots()
        ax.imshow(image, aspect="auto", interpolation="nearest", extent=(0, T, image.shape[0], 0))
        fig.subplots_adjust(top=1 - 0.6 / fig.get_figheight())
        block = ax.get_position().height * fig.get_figheight() * fig.dpi / len(chosen)  # pixels a trajectory
        every = max(1, int(np.ceil(LABEL_PIXELS / block)))  # a label each while they fit
        ticks = np.arange(0, len(chosen), every)
        ax.set_yticks(ticks * height + len(rows) / 2)
        ax.set_yticklabels([str(chosen[b]) for b in ticks], fontsize=7)
        which = "trajectory" if every == 1 else f"trajectory (every {_ordinal(every)} labelled)"
        ax.set_ylabel(f"{which}; rows: {', '.join(name for name, _, _ in rows)}", fontsize=8)
        ax.tick_params(axis="x", labelsize=7)
        ax.set_xlim(0, T)
        axes, hspace = [ax], None
    axes[-1].set_xlabel("step")
    legend = {}
    for name, _, style in rows:
        for k, s in style.items():
            # with one method, its entries say which inferred skill each colour is
            label = f"{s.name}: skill {k}" if len(methods) == 1 and name != "true" else s.name
            legend.setdefault(label, (s, name != "true"))
    # true skills in order, each followed by its variants (B, B1, B2), then "unmatched"
    order = sorted(legend.items(), key=lambda e: (e[1][0].true_label is None, e[1][0].true_label or 0, e[1][1],
                                                  len(e[1][0].name), e[0]))
    fig.legend(handles=[Patch(color=s.colour, label=label) for label, (s, _) in order], loc="upper center",
               ncol=min(len(order), 8), fontsize=8, frameon=False, bbox_to_anchor=(0.5, 1.0))
    if title:
        fig.suptitle(title, y=1.03)
    fig.subplots_adjust(hspace=hspace, top=1 - 0.6 / fig.get_figheight())
    save_figure(fig, path)
    return styles


def plot_skill_probabilities(probs: Sequence[np.ndarray], path, trajectories: Optional[Sequence[int]] = None,
                             skill_names: Optional[Sequence[str]] = None, title: Optional[str] = None,
                             colours: Optional[Sequence] = None) -> None:
    """Per trajectory, the posterior probability of each skill at every step as stacked bands
    (``FitResult.segment(...).probs``), skill k in ``colours[k]`` (default the k-th palette
    colour), and what a row leaves to one (draws that put the step in a skill the run does not
    have) white; saved as a PNG.

    Args:
        probs: per trajectory, (T, K) probabilities (rows sum to at most one).
        path: the PNG file to write.
        trajectories: which to draw (default the first 8).
        skill_names: K names (default "skill 0", "skill 1", ...).
        title: optional figure title.
        colours: K colours, e.g. a run's (:func:`run_styles`, what ``npbrs segment --plot`` uses:
            the colours of the run's other figures).
    """
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    probs = [np.asarray(p, dtype=np.float64) for p in probs]
    if not probs:
        raise ValueError("no trajectories to plot")
    K = probs[0].shape[-1]
    for i, p in enumerate(probs):
        if p.ndim != 2 or p.shape[1] != K or np.any(p < -1e-9) or np.any(p.sum(-1) > 1 + 1e-6):
            raise ValueError(f"trajectory {i}: skill probabilities must be (T, {K}) non-negative with rows summing "
                             "to at most one")
    names = [f"skill {k}" for k in range(K)] if skill_names is None else [str(n) for n in skill_names]
    if len(names) != K:
        raise ValueError(f"{len(names)} skill names for {K} skills")
    chosen = list(range(min(len(probs), 8))) if trajectories is None else [int(i) for i in trajectories]
    for i in chosen:
        if not 0 <= i < len(probs):
            raise ValueError(f"trajectory {i} is outside 0..{len(probs) - 1}")
    colours = [PALETTE[k % len(PALETTE)] for k in range(K)] if colours is None else list(colours)
    if len(colours) != K:
        raise ValueError(f"{len(colours)} colours for {K} skills")
    colours = [_rgba(c) for c in colours]
    fig = Figure(figsize=(10, 0.8 * len(chosen) + 0.9), dpi=100)
    axes = fig.subplots(len(chosen), 1, squeeze=False)[:, 0]
    for ax, i in zip(axes, chosen):
        p = probs[i]
        steps = np.arange(p.shape[0] + 1)
        bands = np.vstack([p, p[-1:]])  # a step plot: each step's band spans [t, t + 1)
        ax.stackplot(steps, bands.T, colors=colours, step="post", linewidth=0)
        ax.set_xlim(0, p.shape[0])
        ax.set_ylim(0, 1)
        ax.set_yticks([0, 1])
        ax.tick_params(labelsize=7)
        ax.set_ylabel(f"{i}", rotation=0, ha="right", va="center", fontsize=8)
    axes[-1].set_xlabel("step")
    fig.legend(handles=[Patch(color=c, label=n) for c, n in zip(colours, names)], loc="upper center",
               ncol=min(K, 10), fontsize=8, frameon=False, bbox_to_anchor=(0.5, 1.0))
    if title:
        fig.suptitle(title, y=1.03)
    fig.subplots_adjust(hspace=0.45, top=1 - 0.6 / fig.get_figheight())
    save_figure(fig, path)


def plot_trace(result, path) -> None:
    """Trace plot of the label-invariant scalars (log joint, number of skills, switches): per
    scalar, each chain's density after warmup (left) and its sweeps (right: the warmup ones,
    when the result keeps them, at negative positions on a grey band, then the draws), one
    colour per chain.

    Args:
        result: a :class:`~npbrs.inference.driver.results.FitResult` (or an ArviZ InferenceData
            holding those variables in its posterior).
        path: the PNG file to write.
    """
    from matplotlib.figure import Figure

    from ..arviz_import import arviz
    from .diagnostics import LABEL_INVARIANT

    az = arviz()

    data = result.to_arviz() if hasattr(result, "to_arviz") else result
    chains = int(data.posterior.sizes["chain"])
    fig = Figure(figsize=(10, 2.3 * len(LABEL_INVARIANT) + 0.4), dpi=100)
    axes = fig.subplots(len(LABEL_INVARIANT), 2, squeeze=False)
    colours = [PALETTE[c % len(PALETTE)] for c in range(chains)]
    az.plot_trace(data, var_names=list(LABEL_INVARIANT), axes=axes, show=False, compact=False,
                  chain_prop={"color": colours}, trace_kwargs={"linewidth": 1.0, "alpha": 0.9},
                  plot_kwargs={"linewidth": 1.2})
    warmup = getattr(result, "warmup_stats", None) or {}
    for row, name in zip(axes, LABEL_INVARIANT):
        row[0].set_xlabel(name.replace("_", " "), fontsize=8)
        row[0].set_ylabel("density (after warmup)", fontsize=8)
        row[1].set_xlabel("sweep (warmup shaded, negative)" if name in warmup else "draw (after warmup)", fontsize=8)
        row[1].set_ylabel(name.replace("_", " "), fontsize=8)
        if name in warmup:  # the warmup sweeps before draw 0, on a grey band
            values = np.asarray(warmup[name], dtype=np.float64)
            W = values.shape[1]
            x = np.arange(-W, 0)
            for c in range(min(values.shape[0], chains)):
                row[1].plot(x, values[c], color=colours[c], linewidth=0.8, alpha=0.6)
            row[1].axvspan(-W - 0.5, -0.5, color="0.85", zorder=0, linewidth=0)
            row[1].set_xlim(-W - 0.5, max(row[1].get_xlim()[1], 0.5))
    from matplotlib.lines import Line2D

    fig.legend(handles=[Line2D([], [], color=c, label=f"chain {i}") for i, c in enumerate(colours)],
               loc="upper center", ncol=min(chains, 8), fontsize=8, frameon=False, bbox_to_anchor=(0.5, 1.0))
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.35 / fig.get_figheight()))
    save_figure(fig, path)


def plot_skill_ends(ends, path, skill_names: Optional[Sequence[str]] = None, title: Optional[str] = None) -> None:
    """Heat map of each skill's end probability in each state (a run with state-dependent ends:
    its skills' termination functions), skills in rows, states in columns.

    Args:
        ends: (K, S) probabilities (e.g. posterior means, ``skill_ends``).
        path: the PNG file to write.
        skill_names: K names (default "skill 0", ...).
        title: optional title.
    """

    ends = np.asarray(ends, dtype=np.float64)
    if ends.ndim != 2 or not np.all(np.isfinite(ends)) or np.any(ends < 0) or np.any(ends > 1):
        raise ValueError(f"ends must be (K, S) probabilities, got shape {ends.shape}")
    K, S = ends.shape
    names = [f"skill {k}" for k in range(K)] if skill_names is None else [str(s) for s in skill_names]
    if len(names) != K:
        raise ValueError(f"{len(names)} skill names for {K} skills")
    _heat_map(ends, path, names, "state entered", "end probability", "viridis", (0.0, 1.0), title)


def _heat_map(values, path, row_names, xlabel: str, label: str, cmap: str, limits, title=None, row_colours=None,
              column_names=None) -> None:
    """A (K, n) array as a heat map, skills in rows, at most 14 inches wide; ``limits``: the
    colour scale's (min, max); ``row_colours``: the row names' colours; ``column_names``: the
    columns' tick labels (default their indices), at most ``HEAT_TICKS`` per 14 inches, every
    column's or every n-th's (the axis label says which)."""
    from matplotlib.figure import Figure

    K, n = values.shape
    width = min(14.0, max(5.0, 2.0 + 0.06 * n))
    fig = Figure(figsize=(width, 1.2 + 0.45 * K), dpi=100)
    ax = fig.subplots()
    image = ax.imshow(values, aspect="auto", interpolation="nearest", cmap=cmap, vmin=limits[0], vmax=limits[1])
    ax.set_yticks(np.arange(K))
    ax.set_yticklabels(row_names, fontsize=8)
    for tick, colour in zip(ax.get_yticklabels(), row_colours or ()):
        tick.set_color(colour)
    every = max(1, int(np.ceil(n / max(3, int(HEAT_TICKS * width / 14.0)))))
    ticks = np.arange(0, n, every)
    ax.set_xticks(ticks)
    if column_names is not None:
        column_names = list(column_names)
        ax.set_xticklabels([str(column_names[d]) for d in ticks], rotation=90, fontsize=8)
    else:
        ax.set_xticklabels([str(d) for d in ticks], fontsize=8)
    ax.set_xlabel(xlabel if every == 1 else f"{xlabel} (every {_ordinal(every)} labelled)")
    fig.colorbar(image, ax=ax, label=label)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    save_figure(fig, path)


def plot_skill_rewards(theta, feature_names: Sequence[str], path, skill_names: Optional[Sequence[str]] = None,
                       title: Optional[str] = None, interval=None, colours: Optional[Sequence] = None,
                       coordinates=None) -> None:
    """Each skill's reward weights over the features: a bar chart up to ``BARS`` features (with
    the interval as error bars), beyond that (a reward weight per state: hundreds to millions of
    features) a heat map, skills in rows and features in columns, coloured by the weight on a
    scale symmetric about zero (the interval is not drawn there). With ``coordinates`` (a
    reward weight per state of a grid: each feature's state's 2-D coordinates) each skill's
    weights are drawn on the grid instead, a panel per skill on one colour scale symmetric
    about zero, cells without a state grey. Either way the PNG stays at most 14 inches wide:
    bars for 127 features were 25,000 pixels wide.

    Args:
        theta: (K, D) reward weights (e.g. posterior means).
        feature_names: D feature names.
        path: the PNG file to write.
        skill_names: K names (default "skill 0", ...).
        title: optional title.
        interval: optional (lower, upper), each (K, D): drawn as error bars (a credible interval).
        colours: optional K colours (default the palette in skill order).
        coordinates: optional (D, 2) numbers, feature d's position (row, column): e.g. for
            one-hot state features, ``mdp.state_vectors`` of the state each feature is 1 in.
    """
    from matplotlib.figure import Figure

    theta = np.asarray(theta, dtype=np.float64)
    if theta.ndim != 2:
        raise ValueError(f"theta must have shape (K, D), got {theta.shape}")
    K, D = theta.shape
    if len(feature_names) != D:
        raise ValueError(f"{len(feature_names)} feature names for {D} features")
    names = [f"skill {k}" for k in range(K)] if skill_names is None else [str(s) for s in skill_names]
    if len(names) != K:
        raise ValueError(f"{len(names)} skill names for {K} skills")
    colours = [PALETTE[k % len(PALETTE)] for k in range(K)] if colours is None else list(colours)
    if len(colours) != K:
        raise ValueError(f"{len(colours)} colours for {K} skills")
    if interval is not None:
        lower, upper = (np.asarray(x, dtype=np.float64) for x in interval)
        if lower.shape != (K, D) or upper.shape != (K, D):
            raise ValueError(f"interval bounds must have shape ({K}, {D})")
    if coordinates is not None:
        coordinates = np.asarray(coordinates, dtype=np.float64)
        if coordinates.shape != (D, 2) or not np.all(np.isfinite(coordinates)):
            raise ValueError(f"coordinates must be (D, 2) = ({D}, 2) finite numbers, a position per feature, "
                             f"got shape {coordinates.shape}")
        _reward_grids(theta, coordinates, path, names, colours, title)
        return
    if D > BARS:
        finite = np.abs(theta[np.isfinite(theta)])
        top = float(finite.max()) if finite.size and finite.max() > 0 else 1.0
        _heat_map(theta, path, names, "feature", "reward weight", "RdBu_r", (-top, top), title, colours,
                  feature_names)
        return
    fig = Figure(figsize=(min(14.0, max(5.0, 1.0 + 0.4 * K * D)), 3.5), dpi=100)
    ax = fig.subplots()
    width = 0.8 / K
    x = np.arange(D)
    for k in range(K):
        err = None
        if interval is not None:
            err = np.stack([np.maximum(theta[k] - lower[k], 0), np.maximum(upper[k] - theta[k], 0)])
        ax.bar(x - 0.4 + (k + 0.5) * width, theta[k], width, label=names[k], color=colours[k], yerr=err,
               error_kw={"elinewidth": 0.8, "capsize": 2, "ecolor": "black"})
    ax.axhline(0.0, color="black", linewidth=0.6)
    ax.set_xticks(x)
    ax.set_xticklabels(list(feature_names), rotation=20, ha="right")
    ax.set_ylabel("reward weight" + (" (mean, interval)" if interval is not None else ""))
    ax.legend(fontsize=8, frameon=False)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    save_figure(fig, path)


def _reward_grids(theta, coordinates, path, names, colours, title=None) -> None:
    """Each skill's weights (K, D) drawn at the features' (row, column) ``coordinates`` (D, 2):
    a panel per skill (4 to a row), a cell per feature where the coordinates are integers on a
    grid of modest size (cells without a feature grey), else a square marker per feature."""
    from matplotlib import colormaps
    from matplotlib.figure import Figure

    K, D = theta.shape
    finite = np.abs(theta[np.isfinite(theta)])
    top = float(finite.max()) if finite.size and finite.max() > 0 else 1.0
    cmap = colormaps["RdBu_r"].with_extremes(bad=(0.8, 0.8, 0.8, 1.0))
    low = coordinates.min(0)
    span = (coordinates.max(0) - low + 1).astype(np.int64)
    on_grid = bool(np.all(coordinates == np.round(coordinates))) and span.prod() <= max(16 * D, 4096)
    wide = span[1] / span[0]  # a panel's width over its height
    columns = min(K, 4 if wide <= 1.5 else 2 if wide <= 4 else 1)
    rows = -(-K // columns)
    panel = min(3.5 * max(1.0, wide), 12.5 / columns)  # inches wide
    height = float(np.clip(panel / wide, 0.6, 4.0))
    fig = Figure(figsize=(columns * panel + 1.5, rows * (height + 0.45) + 0.9), dpi=100, layout="constrained")
    axes = fig.subplots(rows, columns, squeeze=False)
    cells = (coordinates - low).astype(np.int64)
    image, drawn = None, []
    for k, ax in enumerate(axes.ravel()):
        if k >= K:
            ax.remove()
            continue
        drawn.append(ax)
        if on_grid:
            grid = np.full(tuple(span), np.nan)
            grid[cells[:, 0], cells[:, 1]] = theta[k]
            image = ax.imshow(grid, cmap=cmap, vmin=-top, vmax=top, interpolation="nearest",
                              extent=(low[1] - 0.5, low[1] + span[1] - 0.5, low[0] + span[0] - 0.5, low[0] - 0.5))
        else:
            image = ax.scatter(coordinates[:, 1], coordinates[:, 0], c=theta[k], cmap=cmap, vmin=-top, vmax=top,
                               marker="s", s=max(2.0, 4000.0 / D), linewidths=0)
            ax.invert_yaxis()
            ax.set_aspect("equal", adjustable="datalim")
        ax.set_title(names[k], fontsize=9, color=colours[k])
        ax.tick_params(labelsize=7)
    fig.supxlabel("the states' second coordinate (column)", fontsize=8)
    fig.supylabel("first coordinate (row)", fontsize=8)
    fig.colorbar(image, ax=drawn, label="reward weight", shrink=0.9)
    if title:
        fig.suptitle(title)
    save_figure(fig, path)
