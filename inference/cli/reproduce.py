"""Reproduce the paper's evaluation: the control tables (Figures 7 and 10) and the segmentation
plots (Figures 4 and 9).

Every run draws fresh demonstrations (seed ``seed + r``) and segments them with each method,
all under the same BP-HMM and sampler, with only the emission changed (section IV-A):

- ``npbrs``: the reward emission (``"reward"``: Boltzmann policies of linear rewards);
- ``subgoal``: the subgoal emission (``"subgoal"``), goals among the states the run's
  demonstrations visit (BNIRL), optionally only the ``max_candidates`` most visited;
- ``irl``: unsegmented maximum-entropy IRL (``"single"``: one reward for every step);
- ``lds``: the autoregressive emission (``"autoregressive"``, the BP-AR-HMM); it models no
  actions, so it gives a segmentation but no policy, and has no control score.

Per run and method: the control reward per trajectory (the demonstrations replayed acting with
the inferred skills' optimal policies, scored with the true skills' rewards; the expert is the
true segmentation with the true rewards; every method shares the random numbers of the run's
seed), the mean number of skill switches per trajectory, the number of skills, the
segmentation accuracy under the paper's >50% labelling and under one-to-one (Hungarian)
matching, and the wall time of the fit (emission construction and compilation included).
Every score is of the run's per-step most probable skills (``FitResult.segment``: the skill
probabilities averaged over the posterior draws), the estimate that labels the most steps right
in expectation; the best draw's segmentation is scored beside it (``segmentation="best"``
scores only that). The table gives the mean and standard deviation over runs.

    result = reproduce("highway", 500, runs=10)
    print(format_markdown(result))
    save_json(result, "highway-500.json")
"""

from __future__ import annotations

import copy
import json
import os
import time
from typing import Callable, Dict, Optional, Sequence

import numpy as np

from npbrs.domains.util.files import atomic_write

from .arguments import at_least

__all__ = ["reproduce", "default_settings", "run_segmentation", "format_markdown", "switching_lines", "save_json",
           "load_json", "add_parser", "reproduce_command", "METHODS", "SEGMENTATIONS", "EMISSIONS", "ROWS", "COLUMNS",
           "PAPER", "QUICK_DATA"]

#: How a run's segmentation is read off its posterior (see :func:`reproduce`).
SEGMENTATIONS = ("marginal", "best")
#: The methods compared, and the emission each one fits.
METHODS = ("npbrs", "subgoal", "irl", "lds")
EMISSIONS = {"npbrs": "reward", "subgoal": "subgoal", "irl": "single", "lds": "autoregressive"}
#: Table columns (the expert first) and rows: (key, label).
COLUMNS = {"expert": "Expert", "npbrs": "NPBRS", "subgoal": "Subgoal", "irl": "IRL", "lds": "LDS"}
ROWS = (("reward", "Reward"), ("switches", "Skill switches"), ("skills", "Skills"),
        ("paper_accuracy", "Accuracy (paper labelling)"), ("hungarian_accuracy", "Accuracy (Hungarian)"),
        ("wall_time", "Wall time (s)"))
_FORMATS = {"reward": "{:.0f}", "switches": "{:.2f}", "skills": "{:.1f}", "paper_accuracy": "{:.3f}",
            "hungarian_accuracy": "{:.3f}", "wall_time": "{:.0f}"}

#: The paper's tables for trajectories of 500 steps (Figure 7: highway; Figure 10: quadcopter).
PAPER = {
    "highway": {"figure": 7, "reward": {"expert": 39093, "npbrs": 37832, "subgoal": -5660, "irl": -14453},
                "switches": {"expert": 7.13, "npbrs": 9.2, "subgoal": 45.11, "irl": 0},
                "skills": {"expert": 3, "npbrs": 7.8, "subgoal": 3.4, "irl": 1}},
    "quadcopter": {"figure": 10, "reward": {"expert": 82616, "npbrs": 79501, "subgoal": -30045, "irl": 139},
                   "switches": {"expert": 6.81, "npbrs": 9.47, "subgoal": 88.95, "irl": 0},
                   "skills": {"expert": 3, "npbrs": 8.2, "subgoal": 2.6, "irl": 1}},
}

#: The data of a ``quick`` reproduction (a check that the pipeline runs, in minutes).
QUICK_DATA = {"runs": 1, "num_trajectories": 2, "length": 40}

# Sampler settings per method, sized so that 10 runs of 16 x 500 highway steps of all four
# methods take about 30 minutes on two shared CPU cores, most of it compiling each run's
# samplers (the demonstrations are constants of the compiled sweep: every run compiles afresh).
_SETTINGS = {
    "npbrs": {"chains": 4, "warmup": 20, "samples": 20, "max_skills": 8, "emission_options": {}},
    "subgoal": {"chains": 1, "warmup": 50, "samples": 50, "max_skills": 8, "emission_options": {}},
    "irl": {"chains": 1, "warmup": 25, "samples": 25, "max_skills": 1, "emission_options": {}},
    "lds": {"chains": 1, "warmup": 50, "samples": 50, "max_skills": 8, "emission_options": {}},
}
# The quadcopter (11664 states) doubles the cost of a reward sweep: fewer sweeps for NPBRS.
# Its demonstrations visit ~5000 states: the subgoal's goal candidates are the 1000 most
# visited (one soft solve each when the emission is built).
_DOMAIN_SETTINGS = {"quadcopter": {"npbrs": {"warmup": 15, "samples": 15},
                                   "subgoal": {"emission_options": {"max_candidates": 1000}}}}
_QUICK = {"chains": 1, "warmup": 1, "samples": 2, "init_window": 10}
#: Keys a method's settings may hold; the last ones are passed to ``fit`` as they are.
_SETTING_KEYS = ("chains", "warmup", "samples", "max_skills", "emission_options", "alpha", "kappa", "gamma",
                 "init_skills", "init_window", "moves", "switching")


def default_settings(domain_name: str, quick: bool = False) -> Dict[str, dict]:
    """The sampler settings of every method for a domain: {method: {chains, warmup, samples,
    max_skills, emission_options[, alpha, kappa, gamma, init_skills, init_window, moves, switching]}}.

    Args:
        domain_name: the domain (its own overrides apply, e.g. the quadcopter's subgoal candidates).
        quick: a few sweeps of one chain and at most 3 skills (a check that everything runs).
    """
    out = copy.deepcopy(_SETTINGS)
    for method, override in _DOMAIN_SETTINGS.get(domain_name, {}).items():
        out[method].update(copy.deepcopy(override))
    if quick:
        for method, s in out.items():
            s.update(_QUICK, max_skills=min(s["max_skills"], 3))
    return out


def _merge_settings(domain_name: str, methods, settings, quick: bool) -> Dict[str, dict]:
    out = default_settings(domain_name, quick)
    for method, override in (settings or {}).items():
        if method not in METHODS:
            raise ValueError(f"settings.{method}: unknown method; expected one of {', '.join(METHODS)}")
        if not isinstance(override, dict):
            raise ValueError(f"settings.{method}: expected a dict of sampler settings, got {override!r}")
        for key in override:
            if key not in _SETTING_KEYS:
                raise ValueError(f"settings.{method}.{key}: unknown setting; expected one of "
                                 f"{', '.join(_SETTING_KEYS)}")
        out[method].update(copy.deepcopy(override))
    return {m: out[m] for m in methods}


# ------------------------------------------------------------------------------ one run
def _fit_method(method: str, domain, demos, setting: dict, seed: int):
    """(FitResult, the emission for subgoal's reward tables or None, wall seconds)."""
    from ..driver.fit import fit

    options = dict(setting.get("emission_options") or {})
    extra = {k: setting[k] for k in _SETTING_KEYS[5:] if k in setting}
    start = time.perf_counter()
    emission = EMISSIONS[method]
    if method == "subgoal":
        from npbrs.models.subgoal import SubgoalEmission, visited_states

        # the prior's support is the states these demonstrations visit (BNIRL)
        candidates = visited_states(demos, options.pop("max_candidates", None))
        emission = SubgoalEmission(domain.mdp, candidates=candidates, **options)
        options = None
    config = dict(extra, emission=emission, max_skills=setting["max_skills"])
    if options:
        config["emission_options"] = options
    result = fit(domain.mdp, demos, config, num_chains=setting["chains"], num_warmup=setting["warmup"],
                 num_samples=setting["samples"], seed=seed, progress_bar=False)
    return result, (emission if method == "subgoal" else None), time.perf_counter() - start


def _skill_rewards(method: str, domain, result, emission) -> Optional[np.ndarray]:
    """The inferred skills' reward tables (K, S, A), or None for a method without rewards."""
    if method in ("npbrs", "irl"):
        return domain.mdp.reward(result.skill_params["theta"])
    if method == "subgoal":
        return np.asarray(emission.goal_rewards(np.asarray(result.skill_params["goal"])))
    return None


def run_segmentation(result, mdp, segmentation: str = "marginal", emission=None):
    """The run's segmentation by ``segmentation``: "marginal", each step's most probable skill
    under the run's posterior (``FitResult.segment``: the skill probabilities averaged over the
    draws, the estimate that maximises the expected number of correctly labelled steps), or
    "best", the best draw's (``FitResult.segmentation``). The tables and
    ``benchmarks/transfer.py`` score by it."""
    if segmentation not in ("marginal", "best"):
        raise ValueError(f"segmentation must be 'marginal' or 'best', got {segmentation!r}")
    if segmentation == "best" or result.num_skills < 2:
        return result.segmentation
    return result.segment(mdp, emission=emission).labels


def _run(domain, run: int, seed: int, length: int, num_trajectories: int, switch_prob: float, settings: dict,
         plots_dir, bar, segmentation: str = "marginal") -> dict:
    """Every method's scores on one set of demonstrations (plain data); ``bar`` counts the fits."""
    from npbrs.domains.control import evaluate_control, expert_control
    from npbrs.domains.demos import generate_demonstrations

    from ..analysis.metrics import hungarian_accuracy, num_skills, num_switches, paper_accuracy

    demos = generate_demonstrations(domain, num_trajectories=num_trajectories, length=length,
                                    switch_prob=switch_prob, seed=seed)
    true = demos.skills
    expert = expert_control(domain, demos, seed=seed)
    record = {"run": run, "seed": seed,
              "expert": {"reward": expert["reward"], "rewards": expert["rewards"].tolist(),
                         "switches": num_switches(true), "skills": num_skills(true), "paper_accuracy": 1.0,
                         "hungarian_accuracy": 1.0, "wall_time": None},
              "methods": {}}
    segmentations = {}
    for method, setting in settings.items():
        bar.set_postfix_str(f"run {run}: {method}")
        result, emission, wall = _fit_method(method, domain, demos, setting, seed)
        rewards = _skill_rewards(method, domain, result, emission)

        def scores(seg):
            out = {"reward": None, "rewards": None}
            if rewards is not None:
                control = evaluate_control(domain, demos, seg, rewards, seed=seed)
                out = {"reward": control["reward"], "rewards": control["rewards"].tolist()}
            return dict(out, switches=num_switches(seg), paper_accuracy=paper_accuracy(true, seg),
                        hungarian_accuracy=hungarian_accuracy(true, seg))

        start = time.perf_counter()
        seg = run_segmentation(result, domain.mdp, segmentation, emission)
        record["methods"][method] = dict(scores(seg), skills=int(result.num_skills), wall_time=wall,
                                         segment_time=time.perf_counter() - start,
                                         best_log_joint=float(result.best_log_joint),
                                         switching=getattr(result, "switching", None))
        if segmentation != "best":  # the best draw's segmentation too, for comparison
            best = scores(result.segmentation)
            best.pop("rewards")
            record["methods"][method]["best_draw"] = best
        segmentations[COLUMNS[method]] = seg
        bar.update(1)
    if plots_dir is not None:
        from ..analysis.plots import plot_segmentation

        os.makedirs(plots_dir, exist_ok=True)
        path = os.path.join(os.fspath(plots_dir), f"{domain.name}-{length}-run{run}.png")
        plot_segmentation(true, segmentations, path, labels=domain.skill_names,
                          title=f"{domain.name}, {num_trajectories} trajectories of {length} steps, run {run} "
                                f"(seed {seed})")
        record["plot"] = path
    return record


# ------------------------------------------------------------------------------ the table
def _summary(values) -> Optional[dict]:
    values = [v for v in values if v is not None]
    if not values:
        return None
    arr = np.asarray(values, dtype=np.float64)
    return {"mean": float(arr.mean()), "sd": float(arr.std(ddof=1)) if arr.size > 1 else None, "n": int(arr.size)}


def _table(per_run, methods) -> dict:
    """{row: {column: {"mean", "sd", "n"} or None}} over the runs."""
    columns = ("expert",) + tuple(methods)
    table = {}
    for row, _ in ROWS:
        table[row] = {}
        for col in columns:
            table[row][col] = _summary([(r["expert"] if col == "expert" else r["methods"][col])[row]
                                        for r in per_run])
    return table


def _targets(table, methods) -> list:
    """The reproduction's targets for NPBRS, each {"target", "value", "met"} (met None: not measured)."""
    def mean(row, col):
        cell = table.get(row, {}).get(col)
        return None if cell is None else cell["mean"]

    out = []
    if "npbrs" not in methods:
        return out
    expert_reward, reward = mean("reward", "expert"), mean("reward", "npbrs")
    ratio = reward / expert_reward if reward is not None and expert_reward not in (None, 0) else None
    out.append({"target": "NPBRS reward >= 98% of the expert's",
                "value": None if ratio is None else f"{100 * ratio:.1f}%",
                "met": None if ratio is None else bool(ratio >= 0.98)})
    skills = mean("skills", "npbrs")
    out.append({"target": "NPBRS finds <= 4 skills on average", "value": None if skills is None else f"{skills:.1f}",
                "met": None if skills is None else bool(skills <= 4)})
    switches, expert_switches = mean("switches", "npbrs"), mean("switches", "expert")
    rel = (switches - expert_switches) / expert_switches if switches is not None and expert_switches else None
    out.append({"target": "NPBRS switches within 25% of the expert's",
                "value": None if rel is None else f"{switches:.2f} vs {expert_switches:.2f} ({100 * rel:+.0f}%)",
                "met": None if rel is None else bool(abs(rel) <= 0.25)})
    acc = mean("paper_accuracy", "npbrs")
    out.append({"target": "NPBRS accuracy (paper labelling) >= 0.90", "value": None if acc is None else f"{acc:.3f}",
                "met": None if acc is None else bool(acc >= 0.90)})
    others = [m for m in ("subgoal", "irl") if m in methods and mean("reward", m) is not None]
    ahead = None if reward is None or not others else all(reward > mean("reward", m) for m in others)
    out.append({"target": "NPBRS reward above " + " and ".join(COLUMNS[m] for m in others or ("subgoal", "irl")),
                "value": None if ahead is None else ", ".join(f"{COLUMNS[m]} {mean('reward', m):.0f}" for m in others),
                "met": ahead})
    return out


def _assemble(setup: dict, per_run: list) -> dict:
    methods = setup["methods"]
    table = _table(per_run, methods) if per_run else {}
    return dict(setup, runs_done=len(per_run), table=table, targets=_targets(table, methods) if per_run else [],
                paper=PAPER.get(setup["domain"]) if setup["length"] == 500 else None, per_run=per_run)


# ------------------------------------------------------------------------------ the driver
def reproduce(domain_name: str, length: int, runs: int = 10, num_trajectories: int = 16, seed: int = 0,
              methods: Sequence[str] = METHODS, settings: Optional[Dict[str, dict]] = None, plots_dir=None,
              progress: bool = True, switch_prob: float = 0.02, quick: bool = False, previous: Optional[dict] = None,
              on_run: Optional[Callable[[dict], None]] = None, segmentation: str = "marginal") -> dict:
    """The paper's Figure 7/10 table (with segmentation accuracy and wall time) over ``runs`` runs.

    Args:
        domain_name: a registered domain ("highway", "quadcopter").
        length: steps per trajectory (the paper: 128 and 500).
        runs: number of runs; run r uses demonstrations, sampler and control seed ``seed + r``.
        num_trajectories: demonstrations per run (16).
        seed: the first run's seed.
        methods: a subset of ``METHODS`` ("npbrs", "subgoal", "irl", "lds").
        settings: per-method overrides of :func:`default_settings`, e.g.
            ``{"npbrs": {"chains": 2, "samples": 100}, "subgoal": {"emission_options":
            {"max_candidates": 500}}}``.
        plots_dir: write each run's segmentation plot (true skills and every method) there.
        progress: a progress bar over runs x methods.
        switch_prob: probability of a skill switch per step in the demonstrations.
        quick: the default settings of a quick check (:func:`default_settings`).
        previous: an earlier result of the same setup (e.g. :func:`load_json`); its runs are
            kept and only the missing ones are run.
        on_run: called with the result so far after every run (e.g. to save partial results).
        segmentation: the segmentation every method is scored by: "marginal" (default), each
            step's most probable skill under the run's posterior (``FitResult.segment``: the
            estimate with the most correctly labelled steps expected; a run's record also holds
            its best draw's scores, "best_draw"), or "best", the best draw's
            (``FitResult.segmentation``).
    Returns:
        a dict of plain data: the setup ("domain", "length", "num_trajectories", "runs", "seed",
        "switch_prob", "methods", "settings", "segmentation"), "runs_done", "table" {row: {column: {"mean", "sd",
        "n"} or None}} with rows ``ROWS`` and columns "expert" and the methods, "targets" (the
        reproduction's targets for NPBRS), "paper" (the paper's table, for length 500) and
        "per_run" (every run's scores per method, with per-trajectory rewards).
    """
    from npbrs.domains.registry import get_domain

    methods = tuple(methods)
    unknown = [m for m in methods if m not in METHODS]
    if unknown or not methods or len(set(methods)) != len(methods):
        raise ValueError(f"methods must be distinct names among {', '.join(METHODS)}, got {list(methods)}")
    if int(runs) < 1:
        raise ValueError(f"runs must be at least 1, got {runs}")
    if segmentation not in SEGMENTATIONS:
        raise ValueError(f"segmentation must be one of {', '.join(SEGMENTATIONS)}, got {segmentation!r}")
    domain = get_domain(domain_name)
    setup = {"domain": domain_name, "length": int(length), "num_trajectories": int(num_trajectories),
             "runs": int(runs), "seed": int(seed), "switch_prob": float(switch_prob), "methods": list(methods),
             "settings": _merge_settings(domain_name, methods, settings, quick), "segmentation": segmentation}
    setup = json.loads(json.dumps(setup))  # plain data, as a JSON round trip gives it back
    per_run = []
    if previous is not None:
        # (results made before the setting existed scored the best draw's segmentation)
        previous = {"segmentation": "best", **previous}
        mismatch = [k for k in setup if k != "runs" and previous.get(k) != setup[k]]
        if mismatch:
            raise ValueError(f"the previous result has another setup (differs in {', '.join(mismatch)}); "
                             f"run without it or with the same options")
        per_run = [r for r in previous.get("per_run", []) if r["run"] < runs]
    done = {r["run"] for r in per_run}

    from tqdm.auto import tqdm

    todo = [r for r in range(runs) if r not in done]
    bar = tqdm(total=len(todo) * len(methods), disable=not progress, unit="fit", dynamic_ncols=True)
    try:
        for r in todo:
            per_run.append(_run(domain, r, int(seed) + r, int(length), int(num_trajectories), float(switch_prob),
                                setup["settings"], plots_dir, bar, segmentation))
            per_run.sort(key=lambda rec: rec["run"])
            if on_run is not None:
                on_run(_assemble(setup, per_run))
    finally:
        bar.close()
    return _assemble(setup, per_run)


# ------------------------------------------------------------------------------ output
def _cell(cell, row) -> str:
    if cell is None:
        return "—"
    text = _FORMATS[row].format(cell["mean"])
    if cell["sd"] is not None:
        text += " ± " + _FORMATS[row].format(cell["sd"])
    return text


_SEGMENTATION_TEXT = {
    "marginal": "Each method's segmentation is its run's most probable skill at every step (the skill "
                "probabilities averaged over the posterior draws, `FitResult.segment`).",
    "best": "Each method's segmentation is its run's best draw's (`FitResult.segmentation`)."}


def _best_draw_lines(result: dict, columns) -> list:
    """Markdown lines: the reward, switches and accuracy of the best draw's segmentation, where
    the runs hold them (a reproduction scored by the posterior marginals)."""
    rows = (("reward", "Reward"), ("switches", "Skill switches"), ("hungarian_accuracy", "Accuracy (Hungarian)"))
    cols = [c for c in columns if c != "expert" and result["per_run"]
            and all("best_draw" in r["methods"][c] for r in result["per_run"])]
    if not cols:
        return []
    lines = ["", "Scored by each run's best draw's segmentation instead:", "",
             "| | " + " | ".join(COLUMNS[c] for c in cols) + " |", "|---|" + "---:|" * len(cols)]
    for row, label in rows:
        cells = [_cell(_summary([r["methods"][c]["best_draw"][row] for r in result["per_run"]]), row) for c in cols]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def switching_lines(result: dict) -> list:
    """The Markdown lines saying which switching model ``fit``'s "auto" chose in each method's
    runs of a reproduction ``result``, and the log Bayes factors of state-dependent ends it
    decided by (nothing for runs that fixed the model)."""
    lines = []
    for method in result["methods"]:
        made = [r["methods"][method]["switching"] for r in result.get("per_run", [])
                if method in r["methods"] and r["methods"][method].get("switching")]
        if made:
            chosen = [m["chosen"] for m in made]
            factors = [m["log_bayes_factor"] for m in made]
            counts = ", ".join(f"{c} in {chosen.count(c)}" for c in ("sticky", "state") if c in chosen)
            lines.append(f"- {COLUMNS[method]}: {counts} of {len(made)} runs (log Bayes factors of state ends over "
                         f"sticky switching {min(factors):+.1f} to {max(factors):+.1f} nats; state needs more than "
                         f"{made[0]['margin']:g})")
    return ["", "Switching model chosen by `fit` (`switching=\"auto\"`, its default):", ""] + lines if lines else []


def format_markdown(result: dict) -> str:
    """The result as markdown: the table (mean ± sd over runs), the paper's, the targets, the settings."""
    columns = ["expert"] + list(result["methods"])
    lines = [f"# Reproduction: {result['domain']}, {result['num_trajectories']} trajectories of {result['length']} "
             f"steps", "",
             f"{result['runs_done']} of {result['runs']} runs (seeds {result['seed']}..."
             f"{result['seed'] + result['runs'] - 1}); mean ± sd over runs. Reward: mean true reward per "
             f"trajectory when the demonstrations are replayed acting with each method's inferred skills; skill "
             f"switches per trajectory; skills found; segmentation accuracy under the paper's >50% labelling and "
             f"under one-to-one matching; wall time of each fit, compilation included. LDS gives no policy, so "
             f"no reward. " + _SEGMENTATION_TEXT[result.get("segmentation", "best")], ""]
    if result["table"]:
        lines += ["| | " + " | ".join(COLUMNS[c] for c in columns) + " |",
                  "|---|" + "---:|" * len(columns)]
        for row, label in ROWS:
            lines.append(f"| {label} | " + " | ".join(_cell(result["table"][row].get(c), row) for c in columns) + " |")
    else:
        lines.append("(no runs finished yet)")
    paper = result.get("paper")
    if paper:
        cols = [c for c in columns if c in paper["reward"]]
        lines += ["", f"The paper (Figure {paper['figure']}, 10 runs):", "",
                  "| | " + " | ".join(COLUMNS[c] for c in cols) + " |", "|---|" + "---:|" * len(cols)]
        for row, label in ROWS[:3]:
            lines.append(f"| {label} | " + " | ".join(f"{paper[row][c]:g}" for c in cols) + " |")
    lines += _best_draw_lines(result, columns)
    if result["targets"]:
        lines += ["", "Targets:", ""]
        for t in result["targets"]:
            mark = {True: "met", False: "NOT met", None: "not measured"}[t["met"]]
            lines.append(f"- {t['target']}: {mark}" + (f" ({t['value']})" if t["value"] is not None else ""))
    lines += switching_lines(result)
    lines += ["", "Settings (per run; chains x (warmup + samples) sweeps):", "",
              "| method | emission | chains | warmup | samples | max skills | other |",
              "|---|---|---:|---:|---:|---:|---|"]
    for method in result["methods"]:
        s = result["settings"][method]
        other = {k: v for k, v in s.items() if k not in ("chains", "warmup", "samples", "max_skills") and v}
        lines.append(f"| {COLUMNS[method]} | {EMISSIONS[method]} | {s['chains']} | {s['warmup']} | {s['samples']} | "
                     f"{s['max_skills']} | {json.dumps(other) if other else ''} |")
    return "\n".join(lines) + "\n"


def _write_atomic(path, text: str) -> None:
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    os.makedirs(directory, exist_ok=True)

    def write(tmp):
        with open(tmp, "w") as f:
            f.write(text)

    atomic_write(path, write, suffix=".tmp")


def save_json(result: dict, path) -> None:
    """Write a result as JSON (atomically: a temporary file, then a rename)."""
    _write_atomic(path, json.dumps(result, indent=1, allow_nan=False) + "\n")


def load_json(path) -> dict:
    """A result written by :func:`save_json`."""
    with open(path) as f:
        result = json.load(f)
    missing = [k for k in ("domain", "length", "methods", "settings", "table", "per_run") if k not in result]
    if missing:
        raise ValueError(f"{path}: not a reproduction result (missing {', '.join(missing)})")
    return result


# ------------------------------------------------------------------------------ command line
def configure_parser(parser, default_output: Optional[str] = None):
    """The options of ``npbrs reproduce`` (and of ``benchmarks/reproduce.py``) on ``parser``.

    Args:
        default_output: a directory; when given, --json, --markdown and --plots default to
            DIR/{domain}-{length}.json, .md and DIR/{domain}-{length}/.
    """
    parser.add_argument("--domain", choices=("highway", "quadcopter"), default="highway", help="the domain (highway)")
    parser.add_argument("--length", type=int, choices=(128, 500), default=500,
                        help="steps per trajectory, as in the paper (500)")
    parser.add_argument("--runs", type=at_least(1), default=10, help="runs, each with new demonstrations (10)")
    parser.add_argument("--trajectories", type=at_least(1), default=16, help="trajectories per run (16)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first run (0); run r uses seed + r")
    parser.add_argument("--methods", nargs="+", choices=METHODS, default=list(METHODS),
                        help="methods to compare (all: npbrs subgoal irl lds)")
    where = f" (default {default_output}/DOMAIN-LENGTH.json)" if default_output else ""
    parser.add_argument("--json", metavar="PATH", help="write the result as JSON" + where)
    parser.add_argument("--markdown", metavar="PATH", help="write the table as markdown" + where.replace("json", "md"))
    parser.add_argument("--plots", metavar="DIR", help="write each run's segmentation plot there"
                        + (f" (default {default_output}/DOMAIN-LENGTH/)" if default_output else ""))
    parser.add_argument("--resume", action="store_true",
                        help="keep the runs already in the --json file (same setup) and run the others")
    parser.add_argument("--quick", action="store_true",
                        help=f"a quick check: {QUICK_DATA['runs']} run of {QUICK_DATA['num_trajectories']} "
                             f"trajectories of {QUICK_DATA['length']} steps, one chain, a few sweeps")
    parser.add_argument("--segmentation", choices=SEGMENTATIONS, default="marginal",
                        help="score each method by its run's per-step most probable skills (marginal, the "
                             "default) or by its best draw's segmentation (best)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(func=reproduce_command, default_output=default_output)
    return parser


def add_parser(subparsers):
    """Add the ``reproduce`` command to an ``add_subparsers()`` object."""
    parser = subparsers.add_parser(
        "reproduce", help="the paper's control and segmentation tables (Figures 7 and 10) and plots (4 and 9)",
        description="Run NPBRS (reward emission), the subgoal baseline, unsegmented IRL and the LDS baseline on "
                    "fresh demonstrations per run; print the table of control reward, skill switches, skills, "
                    "segmentation accuracy and wall time (mean ± sd over runs), optionally as JSON and markdown, "
                    "with per-run segmentation plots. Results are written after every run.")
    return configure_parser(parser)


def reproduce_command(args) -> int:
    import sys

    data = dict(QUICK_DATA) if args.quick else {"runs": args.runs, "num_trajectories": args.trajectories,
                                                "length": args.length}
    stem = f"{args.domain}-{data['length']}"
    out = args.default_output
    json_path = args.json or (os.path.join(out, stem + ".json") if out else None)
    md_path = args.markdown or (os.path.join(out, stem + ".md") if out else None)
    plots = args.plots or (os.path.join(out, stem) if out else None)
    previous = None
    if args.resume:
        if json_path is None:
            print("npbrs reproduce: error: --resume needs --json", file=sys.stderr)
            return 2
        if os.path.exists(json_path):
            previous = load_json(json_path)

    def write(result):
        if json_path:
            save_json(result, json_path)
        if md_path:
            _write_atomic(md_path, format_markdown(result))

    try:
        result = reproduce(args.domain, data["length"], runs=data["runs"], num_trajectories=data["num_trajectories"],
                           seed=args.seed, methods=args.methods, plots_dir=plots, progress=not args.no_progress,
                           quick=args.quick, previous=previous, on_run=write, segmentation=args.segmentation)
    except ValueError as e:
        print(f"npbrs reproduce: error: {e}", file=sys.stderr)
        return 2
    write(result)
    print(format_markdown(result))
    for what, path in (("JSON", json_path), ("markdown", md_path), ("plots", plots)):
        if path:
            print(f"wrote the {what} {path}")
    return 0
