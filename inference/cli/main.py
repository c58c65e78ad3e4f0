"""The ``npbrs`` command line: ``generate``, ``fit``, ``report``, ``segment``, ``score``, ``compare`` and ``demo``.

    npbrs generate highway --trajectories 16 --length 500 -o demos.npz
    npbrs fit demos.npz --domain highway [--config model.toml] -o run.nc [--resume]
    npbrs report run.nc --plots plots/
    npbrs segment run.nc new.npz --domain highway -o labels.npz
    npbrs score run.nc held_out.npz --domain highway
    npbrs compare reward.nc single.nc --domain highway
    npbrs demo [--quick] [--out DIR]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import warnings
from typing import Optional

from npbrs.domains.util.precision import float64_all

from . import generate, reproduce, score
from .texts import skills_used, truth_scores
from .arguments import (add_world_arguments, at_least, command_error, device_count, folder_problem, load_world_mdp,
                        output_problem)

__all__ = ["build_parser", "main", "compilation_cache_dir", "DEMO_CONFIG", "QUICK_DEMO_CONFIG"]

#: The demo's model: the reward emission on 8 highway trajectories of 200 steps, sized to
#: finish in a few minutes on two cores (measurements: ``docs/speed.md``). ``--quick`` is
#: a tiny run of the same pipeline (tests).
DEMO_CONFIG = {"emission": {"name": "reward"}, "max_skills": 6, "prior": {"alpha": 1.0, "kappa": 20.0, "gamma": 1.0},
               "sampler": {"chains": 2, "warmup": 60, "samples": 60, "seed": 0, "init_window": 25}}
DEMO_DATA = {"num_trajectories": 8, "length": 200}
QUICK_DEMO_CONFIG = {"emission": {"name": "reward"}, "max_skills": 3,
                     "sampler": {"chains": 1, "warmup": 3, "samples": 4, "seed": 0, "init_window": 10}}
QUICK_DEMO_DATA = {"num_trajectories": 3, "length": 30}
# `npbrs report` prints every reward weight up to plots.BARS features (the plot draws them as
# bars then), else each skill's REPORT_TOP largest
REPORT_TOP = 10


def compilation_cache_dir(environ=None) -> Optional[str]:
    """npbrs's compilation cache folder (:func:`npbrs.inference.driver.compiled.compilation_cache_dir`)."""
    from ..driver.compiled import compilation_cache_dir as folder

    return folder(environ)


def use_compilation_cache() -> Optional[str]:
    from ..driver.compiled import use_compilation_cache as use

    return use()


# ------------------------------------------------------------------------------------ fit
@contextlib.contextmanager
def _summary_says_convergence():
    """The commands print the run's summary, whose convergence lines say what ``fit``'s
    ConvergenceWarning says: no second copy on stderr."""
    from npbrs.inference.driver.results import ConvergenceWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        yield


def _add_fit(sub):
    p = sub.add_parser("fit", help="segment demonstrations into skills (BP-HMM MCMC) and save the run",
                       description="Fit the BP-HMM to demonstrations and write the run (ArviZ netCDF). The model "
                                   "comes from --config (TOML, see npbrs.inference.driver.config); the options below "
                                   "override it. A checkpoint RUN.nc.checkpoint.npz is written every "
                                   "--checkpoint-every sweeps and on Ctrl-C; --resume continues from it.")
    p.add_argument("demos", help="demonstrations file (.npz: states, actions, lengths[, skills])")
    add_world_arguments(p)
    p.add_argument("--config", help="model configuration (TOML)")
    p.add_argument("--emission", help="emission model name (overrides the config)")
    p.add_argument("--max-skills", type=at_least(1), help="truncation: skill slots (overrides the config)")
    p.add_argument("--chains", type=at_least(1), help="number of chains")
    p.add_argument("--samples", type=at_least(1), help="sweeps kept per chain")
    p.add_argument("--warmup", type=at_least(0), help="warmup sweeps per chain")
    p.add_argument("--seed", type=at_least(0), help="random seed")
    p.add_argument("--max-samples", type=at_least(1), metavar="N",
                   help="choose the run length by convergence: keep sampling (half of --samples at a time) until "
                        "every label-invariant R-hat is at most --target-rhat, or N sweeps are kept per chain")
    p.add_argument("--target-rhat", type=float, help="the R-hat a run extended with --max-samples stops at (1.05)")
    p.add_argument("--time-budget", type=float, metavar="SECONDS",
                   help="stop extending a --max-samples run after this many seconds (default: no budget)")
    p.add_argument("--restart-margin", type=float, metavar="NATS",
                   help="at warmup's end, chains whose log joint is more than NATS below the best chain's "
                        "continue from its state (default 50; 0: off; see SamplerConfig.restart_margin)")
    p.add_argument("--grow", action="store_true",
                   help="while every skill slot is in use in most draws, refit with twice the slots from the "
                        "run's segmentation (up to 64; fit's grow=True; no checkpoints then)")
    p.add_argument("--switching", choices=("sticky", "state", "auto"),
                   help="how skills end: 'sticky' (the paper's BP-HMM), 'state' (each skill ends with a "
                        "probability per state entered, as when it ends at its goal) or 'auto' (the default: "
                        "the sticky fit, refitted with state ends when its skills favour them; overrides the "
                        "config)")
    p.add_argument("-o", "--output", required=True, help="the run file to write (.nc)")
    p.add_argument("--overwrite", action="store_true", help="replace the output if it exists (else it is refused)")
    p.add_argument("--init-from", metavar="RUN", help="start every chain from the segmentation of a saved run (.nc)")
    p.add_argument("--resume", action="store_true", help="continue from the output's checkpoint if there is one")
    p.add_argument("--checkpoint-every", type=at_least(0), default=100,
                   help="sweeps between checkpoints (100; 0: no checkpoints)")
    p.add_argument("--devices", type=device_count, metavar="N|all",
                   help="run on N of JAX's devices (or all): chains spread over them first, the rest shard the "
                        "trajectories (see fit's devices=; on several hosts, after jax.distributed.initialize())")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=fit_command)
    return p


def checkpoint_path_for(output) -> str:
    """Where ``npbrs fit -o OUTPUT`` keeps its checkpoint."""
    return os.fspath(output) + ".checkpoint.npz"


def _load_world(args):
    from npbrs.domains.demos import Demonstrations

    return load_world_mdp(args), Demonstrations.load(args.demos)


def fit_command(args) -> int:
    from ..driver.fit import fit, resolve_config

    problem = output_problem(args.output, "run", overwrite=args.overwrite)
    if problem:  # (before any work: a missing folder or a run that would be lost)
        return command_error("fit", problem)
    use_compilation_cache()
    try:
        mdp, demos = _load_world(args)
        init = None
        if args.init_from is not None:
            from ..driver.runs import load

            init = load(args.init_from).segmentation
    except (OSError, ValueError) as e:
        return command_error("fit", e)
    if args.grow and args.resume:
        return command_error("fit", "--grow refits with more skill slots and keeps no checkpoint to --resume")
    checkpoint = checkpoint_path_for(args.output) if (args.checkpoint_every > 0 or args.resume) and not args.grow \
        else None
    if args.resume and checkpoint and os.path.exists(checkpoint):
        print(f"resuming from {checkpoint}")
    try:
        with _summary_says_convergence():
            config = resolve_config(args.config, emission=args.emission, max_skills=args.max_skills,
                                    checkpoint_every=args.checkpoint_every or None, max_samples=args.max_samples,
                                    target_rhat=args.target_rhat, time_budget=args.time_budget,
                                    restart_margin=args.restart_margin, grow=args.grow or None,
                                    switching=args.switching)
            result = fit(mdp, demos, config, num_chains=args.chains, num_samples=args.samples,
                         num_warmup=args.warmup, seed=args.seed, progress_bar=not args.no_progress,
                         checkpoint_path=checkpoint, resume=args.resume, init_segmentation=init, devices=args.devices)
    except (OSError, ValueError) as e:  # a missing or unreadable --config among them
        message = str(e)
        if args.config and message.startswith("emission.options") and os.fspath(args.config) not in message:
            message = f"{args.config}: {message}"  # an emission option of the config file
        return command_error("fit", message)
    except KeyboardInterrupt:
        where = (f"; the checkpoint {checkpoint} is kept: run the same command with --resume to continue"
                 if checkpoint else "")
        print(f"\ninterrupted{where}", file=sys.stderr)
        return 130
    result.save(args.output)
    if checkpoint:
        from ..driver.strategies import state_stage_path

        for path in (checkpoint, state_stage_path(checkpoint)):  # (switching="auto"'s state fit's too)
            if os.path.exists(path):
                os.remove(path)
    print(result.summary())
    print(f"wrote {args.output}")
    return 0


# ------------------------------------------------------------------------------------ report
def _add_report(sub):
    p = sub.add_parser("report", help="summarise a saved run: segmentation, convergence, per-skill rewards",
                       description="Print a saved run's segmentation summary, the R-hat and ESS of the "
                                   "label-invariant scalars (log joint, number of skills, switches) and the "
                                   "per-skill reward weights with credible intervals (chains relabelled by "
                                   "Hungarian matching); optionally save plots.")
    p.add_argument("run", help="the run file (.nc) written by npbrs fit")
    p.add_argument("--plots", metavar="DIR", help="save trace.png, segmentation.png and (for rewards) "
                                                  "skill_rewards.png in DIR")
    p.add_argument("--prob", type=float, default=0.9, help="credible interval mass (0.9)")
    world = p.add_mutually_exclusive_group()
    world.add_argument("--domain", help="the registered domain the run was fitted in (optional): with a reward "
                                        "weight per state and states of 2-D coordinates (a grid), skill_rewards.png "
                                        "draws each skill's rewards on the grid")
    world.add_argument("--mdp", help="the MDP file the run was fitted in (optional; as --domain)")
    p.set_defaults(func=report_command)
    return p


def report_command(args) -> int:
    import numpy as np
    import pandas as pd

    from ..analysis import diagnostics
    from ..driver.runs import load_run

    if not 0.0 < args.prob < 1.0:
        return command_error("report", f"--prob must be between 0 and 1 (a credible interval's mass), got {args.prob}")
    problem = folder_problem(args.plots) if args.plots else ""
    if problem:
        return command_error("report", problem)
    try:
        result = load_run(args.run)
        mdp = load_world_mdp(args) if args.domain or args.mdp else None
        if mdp is not None:
            result.check_mdp(mdp)
    except (OSError, ValueError) as e:
        return command_error("report", e)
    print(result.summary())
    # (the summary's first lines count the skills of the segmentation the figures draw)
    from ..analysis.diagnostics import shown_segmentation

    shown, _ = shown_segmentation(result)
    if result.demos is not None and result.demos.skills is not None:
        counted = getattr(result, "step_skill_counts", None) is not None
        print(truth_scores(result.demos.skills, shown, result.segmentation if counted else None))
    print("\nconvergence of the label-invariant scalars:")
    with pd.option_context("display.width", 120, "display.max_columns", 20):
        print(diagnostics.convergence(result).to_string())
        if "theta" in result.skill_params:
            from ..analysis.plots import BARS

            D = np.shape(result.skill_params["theta"])[-1]
            top = None if D <= BARS else REPORT_TOP  # a reward per state: the largest weights
            which = "" if top is None else f", the {top} largest in magnitude of {D} (all: skill_summary)"
            print(f"\nreward weights per skill (mean, {args.prob:.0%} interval; chains relabelled{which}):")
            print(diagnostics.skill_summary(result, "theta", prob=args.prob, top=top).to_string())
    if args.plots:
        os.makedirs(args.plots, exist_ok=True)  # (one level: its parent was checked above)
        for name, path in save_plots(result, args.plots, mdp=mdp).items():
            print(f"wrote the {name} plot {path}")
        from ..analysis.plots import BARS

        if mdp is None and "theta" in result.skill_params and np.shape(result.skill_params["theta"])[-1] > BARS:
            print("(a heat map of many reward weights; with a weight per state, give the run's --domain or --mdp "
                  "to draw them on the states' grid)")
    return 0


def save_plots(result, directory, skill_names=None, mdp=None) -> dict:
    """A run's trace, segmentation (each step's most probable skill counted over the draws,
    :meth:`FitResult.skill_probabilities`, or the best draw's for a run without the counts:
    :func:`~npbrs.inference.analysis.diagnostics.shown_segmentation`; against the true skills when
    known) and, for rewards, skill reward plots (with ``mdp``, the MDP of the run, a reward per
    state of 2-D states on their grid), and for a run with state-dependent ends its skills' end
    probabilities, as PNG files in ``directory``; every figure colours a skill alike
    (:func:`~npbrs.inference.analysis.plots.run_styles`). Returns {plot: path}."""
    from ..analysis import diagnostics, plots

    paths = {name: os.path.join(directory, f"{name.replace(' ', '_')}.png")
             for name in ("trace", "segmentation", "skill rewards", "skill ends")}
    plots.plot_trace(result, paths["trace"])
    true = result.demos.skills if result.demos is not None else None
    shown, what = diagnostics.shown_segmentation(result)
    title = f"npbrs: {what}: " + skills_used(shown, result.num_skills, "the best draw's", listed=False)
    styles = plots.plot_segmentation(true, {"npbrs": shown}, paths["segmentation"], labels=skill_names,
                                     title=title)["npbrs"]
    if "theta" in result.skill_params:
        names, mean, interval, colours, labels = reward_plot_inputs(result, styles, with_true=true is not None)
        cells = None if mdp is None else state_cells(mdp, len(names))
        drawn = "posterior mean and 90% interval" if len(names) <= plots.BARS and cells is None else \
            "posterior mean"  # (a heat map or a grid)
        plots.plot_skill_rewards(mean, names, paths["skill rewards"], skill_names=labels, interval=interval,
                                 colours=colours, title=f"reward weights: {drawn}", coordinates=cells)
    else:
        del paths["skill rewards"]
    if "ends" in result.samples:
        from ..analysis.skills import skill_ends

        plots.plot_skill_ends(skill_ends(result)[0], paths["skill ends"], skill_names=skill_names,
                              title="end probability on entering each state: posterior mean")
    else:
        del paths["skill ends"]
    return paths


def reward_plot_inputs(result, styles, with_true: bool = True, prob: float = 0.9):
    """What the report's reward plot draws: feature names, each skill's posterior mean weights
    (K, D) and ``prob`` interval (chains matched; the best draw's where no draw holds the
    skill), and each skill's colour and name from the segmentation plot's ``styles``."""
    import numpy as np

    from ..analysis import plots
    from ..analysis.diagnostics import skill_summary

    K, D = np.shape(result.skill_params["theta"])
    names = list(result.feature_names) or [f"phi{d}" for d in range(D)]
    table = skill_summary(result, "theta", prob=prob, names=names)
    best = np.asarray(result.skill_params["theta"], dtype=np.float64)
    mean, lower, upper = (np.where(np.isnan(v), best, v) for v in
                          (table[col].to_numpy(dtype=np.float64).reshape(K, D) for col in ("mean", "lower", "upper")))
    colours, labels = plots.skill_legend(styles, K, with_true)
    return names, mean, (lower, upper), colours, labels


def state_cells(mdp, num_features: int):
    """Each reward feature's state's 2-D coordinates, where the features are one-hot state
    features (a reward weight per state) and the states have 2-D coordinates
    (``mdp.state_vectors`` of 2 columns, e.g. a grid's (row, column)); else None.

    Args:
        mdp: the run's TabularMDP.
        num_features: the run's number of reward weights per skill.
    Returns:
        (num_features, 2) coordinates, or None.
    """
    import numpy as np

    cells = getattr(mdp, "state_vectors", None)
    features = np.asarray(mdp.features)
    if cells is None or np.shape(cells)[1] != 2 or features.shape[-1] != num_features or len(cells) != num_features:
        return None  # (one-hot state features: a feature per state)
    phi = features[:, 0]
    if not (np.all(features == phi[:, None]) and np.all((phi == 0) | (phi == 1)) and np.all(phi.sum(1) == 1)
            and np.all(phi.sum(0) == 1)):
        return None
    return np.asarray(cells, dtype=np.float64)[np.argmax(phi, axis=0)]  # feature d: the state it is 1 in


# ------------------------------------------------------------------------------------ demo
def _add_demo(sub):
    p = sub.add_parser("demo", help="the whole pipeline on the highway: generate, fit, score, plot",
                       description="Generate highway demonstrations with three known skills, segment them with "
                                   "the BP-HMM, print the skills found, the segmentation accuracy against the "
                                   "true skills and the control rewards (expert vs npbrs), and save the run, "
                                   "its configuration and a segmentation plot.")
    p.add_argument("--quick", action="store_true", help="a tiny version (seconds after compilation)")
    p.add_argument("--out", default="npbrs-demo", help="output directory (npbrs-demo)")
    p.add_argument("--emission", help="emission model (default: reward)")
    p.add_argument("--seed", type=at_least(0), default=0, help="random seed (0)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=demo_command)
    return p


def demo_command(args) -> int:
    from npbrs.domains.demos import generate_demonstrations
    from npbrs.domains.registry import get_domain

    from ..analysis.metrics import hungarian_accuracy, num_switches, paper_accuracy
    from ..driver.config import ModelConfig
    from ..driver.fit import fit
    from .reproduce import run_segmentation

    problem = folder_problem(args.out)
    if problem:
        return command_error("demo", problem)
    print(f"npbrs demo: writing demos.npz, config.toml, run.nc and segmentation.png into "
          f"{os.path.abspath(args.out)} (--out chooses another folder)")
    use_compilation_cache()
    data = QUICK_DEMO_DATA if args.quick else DEMO_DATA
    config = ModelConfig.from_dict(QUICK_DEMO_CONFIG if args.quick else DEMO_CONFIG)
    sampler = dict(config.sampler.to_dict(), seed=args.seed)
    config = config.replace(sampler=sampler,
                            emission={"name": args.emission, "options": {}} if args.emission else config.emission)
    os.makedirs(args.out, exist_ok=True)
    domain = get_domain("highway")
    demos = generate_demonstrations(domain, seed=args.seed, **data)
    demos_path, config_path, run_path = (os.path.join(args.out, n) for n in ("demos.npz", "config.toml", "run.nc"))
    demos.save(demos_path)
    config.to_toml(config_path)
    print(f"{demos.num_trajectories} highway demonstrations of {data['length']} steps, skills "
          f"{', '.join(domain.skill_names)} ({num_switches(demos.skills):.2f} switches per trajectory): {demos_path}")
    sampler = config.sampler
    print(f"model: {config.emission.name} emission, up to {config.max_skills} skills, {sampler.chains} "
          f"chain{'s' if sampler.chains > 1 else ''} x ({sampler.warmup} warmup + {sampler.samples}) sweeps: "
          f"{config_path}")
    try:
        with _summary_says_convergence():
            result = fit(domain.mdp, demos, config, progress_bar=not args.no_progress)
    except ValueError as e:
        return command_error("demo", e)
    result.save(run_path)
    print(f"\n{result.summary()}")
    if result.convergence_warning():
        print("(the demo's chains are short, so its convergence diagnostics fail, as the lines above say; "
              "npbrs fit's defaults run 4 chains of 200 warmup and 200 sampling sweeps: docs/fitting.md)")
    # scored as the tables are: each step's most probable skill under the run's posterior
    labels = run_segmentation(result, domain.mdp)
    print(f"\nsegmentation vs the true skills (each step's most probable skill): "
          f"{skills_used(labels, result.num_skills, 'the best draw', listed=False)} (true: {domain.num_skills}); accuracy {paper_accuracy(demos.skills, labels):.3f} (paper's >50% "
          f"labelling), {hungarian_accuracy(demos.skills, labels):.3f} (one-to-one; the best draw's "
          f"{hungarian_accuracy(demos.skills, result.segmentation):.3f}); switches per trajectory "
          f"{num_switches(labels):.2f} (true {num_switches(demos.skills):.2f})")
    _control_table(domain, demos, result, labels)
    from ..analysis import plots

    path = os.path.join(args.out, "segmentation.png")
    plots.plot_segmentation(demos.skills, {"npbrs": labels}, path, labels=domain.skill_names)
    print(f"\nsegmentation plot: {path}")
    print(f"run: {run_path} (npbrs report {run_path} --plots {args.out})")
    return 0


def _control_table(domain, demos, result, labels) -> None:
    """Mean true reward per trajectory when replaying the demonstrations with the expert and
    with the inferred skills (their rewards' optimal policies, or the policies themselves),
    each step acting with the skill of ``labels``."""
    from npbrs.domains.control import evaluate_control, expert_control

    if "theta" in result.skill_params:
        skills = result.skill_params["theta"]
    elif "policy" in result.skill_params:
        skills = result.skill_params["policy"].argmax(-1)  # (K, S) the policies' greedy actions
    else:
        print(f"\ncontrol: the {result.emission.get('name')} emission gives no policies to act with")
        return
    rows = [("expert", expert_control(domain, demos)),
            ("npbrs", evaluate_control(domain, demos, labels, skills))]
    print("\ncontrol: the demonstrations replayed with each method's skills, scored with the true rewards")
    print(f"{'method':<8} {'reward per trajectory':>22} {'switches':>9} {'skills':>7}")
    for name, r in rows:
        print(f"{name:<8} {r['reward']:>22.1f} {r['switches']:>9.2f} {r['skills']:>7d}")
    expert, npbrs = rows[0][1]["reward"], rows[1][1]["reward"]
    if expert > 0:
        print(f"npbrs's skills earn {npbrs / expert:.1%} of the expert's reward on these demonstrations. The demo is "
              "a short run (see its model line above); the paper's tables, 16 trajectories of 500 steps with "
              "4 chains (docs/reproducing.md), reach about 99%.")


# ------------------------------------------------------------------------------------ main
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="npbrs", description="Nonparametric Bayesian reward segmentation")
    sub = parser.add_subparsers(dest="command", required=True)
    generate.add_parser(sub)
    _add_fit(sub)
    _add_report(sub)
    _add_demo(sub)
    score.add_parsers(sub)
    reproduce.add_parser(sub)
    # no prefix matching: `--chain 2` is an error, not `--chains 2`
    for p in [parser, *sub.choices.values()]:
        p.allow_abbrev = False
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
