"""npbrs with ``fit``'s defaults on real behaviour: mice in a labyrinth, against published figures.

The data (``water_restricted.npz``, described by the README beside it): 200 trajectories of 22
steps of water-restricted mice in a 127-node binary-tree labyrinth (actions: left child, right
child, back to the parent, stay), split into 160 training and 40 validation trajectories as DIRL
(Ashwood, Jha and Pillow, NeurIPS 2022) published them. Many paths recur: 31 of the validation
trajectories equal a training one step for step (``meta.validation_in_train``); every figure
here, the published ones included, scores them as held out.

It fits the training trajectories with ``fit(mdp, demos)`` (every default but ``--num-chains``,
2 by default) in ``TabularMDP.from_dense(transitions, discount=0.7)`` (one reward weight per
state, one-hot state features; DIRL's best discount), scores the validation trajectories with
``FitResult.log_predictive`` and reports:

- ``heldout_ll``: nats per validation step (the actions given the states), ``heldout_se`` its
  Monte Carlo standard error (``HeldOut.per_step_se``); ``heldout_ll_even_names``: the same
  draws scored with the Boltzmann policy's even split among equivalent actions (the convention
  of the published reward models), and ``action_names`` what the fit learned of the names
  (:mod:`npbrs.models.names`): the difference of the two is the names' share;
- ``skills``: ``FitResult.num_skills`` (the best draw's segmentation), ``labelled_skills``: the
  skills that the per-step labels of the training trajectories use (each step's most probable
  skill over the sampler's draws, ``FitResult.skill_probabilities().labels``);
- ``wall_s``: the fit's wall time, compilation included (JAX's persistent cache off);
- ``rhat_max``: the largest R-hat of the label-invariant scalars (``FitResult.rhat``), every
  R-hat and ESS beside it.

Beside it, for scale:

- ``published``: the README's table of published figures (DIRL, MaxEnt IRL, uniform actions),
  parsed from the README (``published_figures``), with the README's behaviour-cloning figures;
- ``behaviour_cloning``: a table of action frequencies given the state and the previous action
  (a trajectory's first step has a previous action of its own, "none"), add-0.5 smoothing,
  fitted on the training trajectories and scored on the validation ones; and given the state
  alone (no reward model: computed in a moment, no fit);
- ``state_action_rewards``: npbrs with one reward weight per (state, action) pair (one-hot
  (state, action) features), ``fit``'s defaults otherwise (skipped by ``--no-references``).

    python benchmarks/bench_real.py --data ../shared/data/labyrinth/water_restricted.npz
        [--json benchmarks/results/bench_real.json] [--seed 0] [--num-chains 2]
        [--trajectories N] [--no-references] [--num-warmup W --num-samples S] [--note TEXT]

``--trajectories N`` uses only the first N training and N validation trajectories, and
``--num-warmup``/``--num-samples`` shorten the fits (for tests: not a measurement). It prints a
table and writes the JSON at PATH (default ``benchmarks/results/bench_real.json``). Times are
absolute wall-clock seconds on whatever machine runs this; the JSON records the load average
before and after each fit and ``--note`` (what else was running).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
import sys
import time
import warnings
from datetime import datetime, timezone

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from runinfo import run_info  # noqa: E402

DEFAULT_JSON = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "bench_real.json")
DISCOUNT = 0.7  # DIRL's best
ACTION_NAMES = ("left", "right", "back", "stay")
SMOOTHING = 0.5  # added to every count of the behaviour-cloning tables


# --------------------------------------------------------------------------------- the data
def load(path: str, trajectories: int = None) -> dict:
    """The arrays of ``water_restricted.npz``; with ``trajectories``, only the first N training
    and N validation trajectories."""
    with np.load(path) as data:
        arrays = {k: np.asarray(data[k]) for k in ("transitions", "states", "actions", "train", "validation")}
    if trajectories is not None:
        arrays["train"] = arrays["train"][:trajectories]
        arrays["validation"] = arrays["validation"][:trajectories]
    return arrays


def demonstrations(arrays: dict, split: str):
    from npbrs.domains import Demonstrations

    idx = arrays[split]
    return Demonstrations(list(arrays["states"][idx]), list(arrays["actions"][idx]))


def repeated(arrays: dict) -> int:
    """How many validation trajectories equal (states and actions) a training trajectory."""
    seen = {(arrays["states"][i].tobytes(), arrays["actions"][i].tobytes()) for i in arrays["train"]}
    return sum((arrays["states"][i].tobytes(), arrays["actions"][i].tobytes()) in seen for i in arrays["validation"])


def published_figures(readme: str) -> dict:
    """The README's published figures: ``table`` {model: nats per step} (its table of published
    figures, in order) and ``behaviour_cloning`` {"state_and_previous_action", "state"} (the
    sentence after it). Raises ValueError when the README no longer reads as expected."""
    section = readme.split("## Published figures", 1)
    if len(section) != 2:
        raise ValueError("the README has no '## Published figures' section")
    table = {}
    for line in section[1].splitlines():
        row = re.fullmatch(r"\|\s*(.+?)\s*\|\s*(-?\d+\.\d+)\s*\|", line.strip())
        if row:
            table[row.group(1)] = float(row.group(2))
    cloning = re.search(r"previous action\s.*?scores\s+(-\d+\.\d+);\s+given the state alone,\s+(-\d+\.\d+)",
                        section[1], re.S)
    if not table or cloning is None:
        raise ValueError("the README's published figures did not parse (table rows '| model | -0.569 |' and "
                         "the behaviour-cloning sentence)")
    return {"table": table, "behaviour_cloning": {"state_and_previous_action": float(cloning.group(1)),
                                                  "state": float(cloning.group(2))}}


# --------------------------------------------------------------------------------- behaviour cloning
def behaviour_cloning(arrays: dict, previous_action: bool = True) -> float:
    """Nats per validation step of a table of action frequencies given the state (and the
    previous action: a trajectory's first step has the category "none" of its own), with
    ``SMOOTHING`` added to every count, fitted on the training trajectories."""
    S, A, _ = arrays["transitions"].shape
    states, actions = arrays["states"], arrays["actions"]

    def context(idx):
        s, a = states[idx], actions[idx]
        if not previous_action:
            return s, np.zeros_like(s)
        before = np.concatenate([np.full((len(idx), 1), A), a[:, :-1]], axis=1)  # A: "none"
        return s, before

    counts = np.zeros((S, A + 1, A))
    np.add.at(counts, (*context(arrays["train"]), actions[arrays["train"]]), 1.0)
    probs = (counts + SMOOTHING) / (counts + SMOOTHING).sum(-1, keepdims=True)
    val = arrays["validation"]
    return float(np.log(probs[(*context(val), actions[val])]).mean())


# --------------------------------------------------------------------------------- npbrs
def state_action_features(S: int, A: int):
    """(S, A, S*A) one-hot (state, action) features and their names."""
    names = tuple(f"state{s}_{ACTION_NAMES[a] if A == len(ACTION_NAMES) else a}" for s in range(S) for a in range(A))
    return np.eye(S * A).reshape(S, A, S * A), names


def _finite(x):
    x = float(x)
    return x if np.isfinite(x) else None


def fit_and_score(mdp, train, validation, fit_options: dict, predictive: dict) -> dict:
    """``fit``'s defaults (but ``fit_options``) on ``train``, scored on ``validation``."""
    from npbrs.inference import fit

    load_before = os.getloadavg()[0]
    start = time.perf_counter()
    result = fit(mdp, train, progress_bar=False, **fit_options)
    wall = time.perf_counter() - start
    with warnings.catch_warnings():  # (that some validation trajectories equal training ones: meta says how many)
        warnings.filterwarnings("ignore", message="log_predictive: .* are ones the run was fitted to")
        held = result.log_predictive(mdp, validation, **predictive)
        # the same draws scored with the even split among equivalent actions (the Boltzmann
        # policy's, as the published reward models score them): the names' share of the score
        even = dataclasses.replace(result, emission=dict(result.emission, action_names="uniform"))
        held_even = even.log_predictive(mdp, validation, **predictive)
    labels = result.skill_probabilities().labels
    rhat, ess = result.rhat, result.ess
    finite = [v for v in rhat.values() if np.isfinite(v)]
    return {"heldout_ll": float(held.per_step), "heldout_se": float(held.per_step_se),
            "heldout_ll_even_names": float(held_even.per_step), "action_names": result.action_names,
            "skills": int(result.num_skills), "labelled_skills": int(len(np.unique(np.concatenate(labels)))),
            "wall_s": round(wall, 2), "rhat_max": max(finite) if finite else None,
            "rhat": {k: _finite(v) for k, v in rhat.items()}, "ess": {k: _finite(v) for k, v in ess.items()},
            # (ArviZ's R-hat; ``rhat`` is the nested one where chains share a start: FitResult.rhat)
            "rank_rhat_max": max((v for v in result.rank_rhat.values() if np.isfinite(v)), default=None),
            "superchains": [int(s) for s in result.superchains],
            "switching": result.switching, "num_features": int(mdp.num_features),
            "load_before": round(load_before, 2), "load_after": round(os.getloadavg()[0], 2)}


# --------------------------------------------------------------------------------- output
def _fmt(x, spec):
    return "—" if x is None else format(x, spec)


def table(out: dict) -> str:
    lines = ["| model | nats per step | s.e. | skills (labelled) | wall s | R-hat max |",
             "|---|---:|---:|---:|---:|---:|"]

    def npbrs_row(name, r):
        lines.append(f"| {name} | {r['heldout_ll']:.3f} | {r['heldout_se']:.1e} | {r['skills']} "
                     f"({r['labelled_skills']}) | {r['wall_s']:.0f} | {_fmt(r['rhat_max'], '.3f')} |")

    npbrs_row("npbrs, a reward per state (fit's defaults)", out)
    if out.get("heldout_ll_even_names") is not None:
        lines.append(f"| the same draws, equivalent actions named evenly (the Boltzmann policy's split) "
                     f"| {out['heldout_ll_even_names']:.3f} | | | | |")
    if out.get("state_action_rewards"):
        npbrs_row("npbrs, a reward per (state, action) [not a state reward]", out["state_action_rewards"])
    bc = out["behaviour_cloning"]
    lines.append(f"| behaviour cloning: state and previous action [not a reward model] "
                 f"| {bc['state_and_previous_action']:.3f} | | | | |")
    lines.append(f"| behaviour cloning: state alone [not a reward model] | {bc['state']:.3f} | | | | |")
    if out.get("published"):
        for model, value in out["published"]["table"].items():
            lines.append(f"| published: {model} | {value:.3f} | | | | |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("--data", required=True, metavar="NPZ", help="water_restricted.npz (its README.md beside it)")
    p.add_argument("--json", default=DEFAULT_JSON, metavar="PATH",
                   help="where to write the figures (default: benchmarks/results/bench_real.json)")
    p.add_argument("--seed", type=int, default=0, help="the fits' seed (default 0)")
    p.add_argument("--num-chains", type=int, default=2, help="chains per fit (default 2)")
    p.add_argument("--trajectories", type=int, metavar="N",
                   help="only the first N training and N validation trajectories (for tests)")
    p.add_argument("--no-references", action="store_true",
                   help="skip the fit with a reward per (state, action)")
    p.add_argument("--num-warmup", type=int, help="warmup sweeps (default: fit's; shorter for tests)")
    p.add_argument("--num-samples", type=int, help="sampling sweeps (default: fit's; shorter for tests)")
    p.add_argument("--note", default="", help="what else was running on the machine")
    args = p.parse_args(argv)
    if args.trajectories is not None and args.trajectories < 2:
        p.error("--trajectories: at least 2")
    os.environ["NPBRS_CACHE_DIR"] = "off"  # every fit compiles as on a new machine: its wall time says so

    from npbrs.domains import TabularMDP

    arrays = load(args.data, args.trajectories)
    readme = os.path.join(os.path.dirname(os.path.abspath(args.data)), "README.md")
    published = None
    if os.path.exists(readme):
        with open(readme) as f:
            published = published_figures(f.read())
    train, validation = demonstrations(arrays, "train"), demonstrations(arrays, "validation")
    fit_options = {"num_chains": args.num_chains, "seed": args.seed}
    fit_options.update({k: v for k, v in (("num_warmup", args.num_warmup), ("num_samples", args.num_samples))
                        if v is not None})
    short = args.num_warmup is not None or args.num_samples is not None
    predictive = {"num_draws": 4, "num_samples": 8} if short else {}

    import jax
    import numpyro

    meta = {**run_info(), "date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "jax": jax.__version__,
            "numpyro": numpyro.__version__, "data": os.path.basename(args.data), "seed": args.seed,
            "fit_options": fit_options, "predictive_options": predictive, "discount": DISCOUNT,
            "train_trajectories": train.num_trajectories, "train_steps": train.num_steps,
            "validation_trajectories": validation.num_trajectories, "validation_steps": validation.num_steps,
            "validation_in_train": repeated(arrays),
            "persistent_cache": False, "note": args.note,
            "load": "1-minute load average before and after each fit in its row"}
    print(f"bench_real: {train.num_trajectories} training trajectories ({train.num_steps} steps), "
          f"{validation.num_trajectories} validation ({validation.num_steps} steps, {meta['validation_in_train']} "
          f"of them equal to a training one); fit {fit_options}", flush=True)

    mdp = TabularMDP.from_dense(arrays["transitions"], discount=DISCOUNT)
    out = fit_and_score(mdp, train, validation, fit_options, predictive)
    print(f"state rewards: {out['heldout_ll']:.3f} nats per step, {out['skills']} skills, {out['wall_s']:.0f} s",
          flush=True)
    out["published"] = published
    out["behaviour_cloning"] = {"state_and_previous_action": behaviour_cloning(arrays),
                                "state": behaviour_cloning(arrays, previous_action=False),
                                "smoothing": SMOOTHING, "first_step_previous_action": "none (its own category)"}
    out["state_action_rewards"] = None
    if not args.no_references:
        S, A, _ = arrays["transitions"].shape
        features, names = state_action_features(S, A)
        mdp_sa = TabularMDP.from_dense(arrays["transitions"], features=features, feature_names=names,
                                       discount=DISCOUNT)
        out["state_action_rewards"] = fit_and_score(mdp_sa, train, validation, fit_options, predictive)
        print(f"state-action rewards: {out['state_action_rewards']['heldout_ll']:.3f} nats per step", flush=True)
    out["meta"] = meta

    print(table(out))
    if short or args.trajectories is not None:
        print("(short fits or a subset of the data: a smoke test, not a measurement)")
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    with open(args.json, "w") as f:
        json.dump(out, f, indent=1)
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
