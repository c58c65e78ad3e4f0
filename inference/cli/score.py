"""``npbrs segment``, ``npbrs score`` and ``npbrs compare``: the fitted skills of new
demonstrations, their held-out log-likelihood, and ArviZ model comparison.

    npbrs segment run.nc new.npz --domain highway -o labels.npz [--plot labels.png]
    npbrs score run.nc held_out.npz --domain highway
    npbrs compare reward.nc subgoal.nc single.nc --domain highway
"""

from __future__ import annotations

import os

from .arguments import add_world_arguments, at_least, command_error, load_world_mdp, output_problem

__all__ = ["add_parsers"]


def _world(p):
    add_world_arguments(p, "the run was fitted in")
    p.add_argument("--samples", type=at_least(1), default=None,
                   help="Monte Carlo samples of a trajectory's skill set and transition weights per draw")
    p.add_argument("--seed", type=at_least(0), default=0, help="seed of those samples (0)")


def add_parsers(sub):
    p = sub.add_parser("score", help="held-out log-likelihood of new demonstrations under a saved run",
                       description="The posterior predictive log-likelihood of demonstrations that were not in "
                                   "the fit, per trajectory and per step (nats), with Monte Carlo standard errors: "
                                   "the skill sequence summed out, each trajectory's skill set and transition "
                                   "weights integrated (FitResult.log_predictive).")
    p.add_argument("run", help="the run file (.nc) written by npbrs fit")
    p.add_argument("demos", help="held-out demonstrations (.npz)")
    _world(p)
    p.add_argument("--draws", type=at_least(1), default=100, help="posterior draws used (100)")
    p.set_defaults(func=score_command)
    p = sub.add_parser("segment", help="the run's skills at every step of new demonstrations",
                       description="Posterior probabilities of the run's skills at every step of demonstrations "
                                   "(new ones: each trajectory's skill set and transition weights integrated under "
                                   "the BP-HMM's predictive), averaged over the run's draws with chains relabelled "
                                   "(FitResult.segment). Writes an .npz with labels (N, T; -1 on padding), probs "
                                   "(N, T, K; 0 on padding; a row sums to below one where some draws put the step in a skill the "
                                   "run's best draw does not have) and lengths (N), labelled as the run's segmentation.")
    p.add_argument("run", help="the run file (.nc) written by npbrs fit")
    p.add_argument("demos", help="demonstrations to segment (.npz)")
    _world(p)
    p.add_argument("--draws", type=at_least(1), default=100, help="posterior draws used (100)")
    p.add_argument("-o", "--output", required=True, help="the labels file to write (.npz)")
    p.add_argument("--overwrite", action="store_true", help="replace the output files if they exist")
    p.add_argument("--plot", metavar="PNG", help="also draw the first trajectories' skill probabilities")
    p.set_defaults(func=segment_command)
    p = sub.add_parser("compare", help="rank saved runs of the same demonstrations with ArviZ (PSIS-LOO)",
                       description="ArviZ's compare table (PSIS leave-one-out, one trajectory at a time) of runs "
                                   "fitted to the same demonstrations, e.g. different emissions; each run's "
                                   "pointwise log-likelihood is computed when the file does not hold it.")
    p.add_argument("runs", nargs="+", help="run files (.nc); at least two")
    _world(p)
    p.set_defaults(func=compare_command)


def _run_and_demos(args):
    """(mdp, run, demonstrations, predictive options) of ``segment`` and ``score``."""
    from npbrs.domains.demos import Demonstrations

    from ..driver.runs import load

    options = {"num_draws": args.draws, "seed": args.seed}
    if args.samples is not None:
        options["num_samples"] = args.samples
    return load_world_mdp(args), load(args.run), Demonstrations.load(args.demos), options


def score_command(args) -> int:
    try:
        mdp, run, demos, options = _run_and_demos(args)
        out = run.log_predictive(mdp, demos, **options)
    except (OSError, ValueError) as e:
        return command_error("score", e)
    print(f"held-out log-likelihood: {out.per_step:.4f} ± {out.per_step_se:.4f} nats per step "
          f"({len(out.per_trajectory)} trajectories, {out.num_steps} steps, {out.num_draws} posterior draws)")
    print("per trajectory: " + ", ".join(f"{v:.2f} ± {s:.2f}" for v, s in zip(out.per_trajectory,
                                                                              out.per_trajectory_se)))
    return 0


def segment_command(args) -> int:
    import numpy as np

    from npbrs.domains.util.files import atomic_write

    for path, what in ((args.output, "labels file"), (args.plot, "plot")):
        problem = output_problem(path, what, overwrite=args.overwrite) if path else ""
        if problem:  # (before any work)
            return command_error("segment", problem)
    try:
        mdp, run, demos, options = _run_and_demos(args)
        out = run.segment(mdp, demos, **options)
        lengths = np.asarray(demos.lengths)
        N, T, K = len(lengths), int(lengths.max()), run.num_skills
        labels, probs = np.full((N, T), -1, np.int64), np.zeros((N, T, K))
        for i, (z, p) in enumerate(zip(out.labels, out.probs)):
            labels[i, :len(z)], probs[i, :len(z)] = z, p
        def write(tmp):
            with open(tmp, "wb") as f:
                np.savez(f, labels=labels, probs=probs, lengths=lengths)

        atomic_write(args.output, write, suffix=".npz.tmp")
        if args.plot:  # each skill in the colour of the run's other figures (npbrs report's)
            from ..analysis import plots
            from .texts import skills_used

            colours, names = plots.skill_legend(plots.run_styles(run), K, run.demos is not None
                                                and run.demos.skills is not None)
            plots.plot_skill_probabilities(out.probs, args.plot, skill_names=names, colours=colours,
                                           title=f"{os.path.basename(args.demos)}: skills of "
                                                 f"{os.path.basename(args.run)}; most probable: "
                                                 f"{skills_used(out.labels, K, 'its', listed=False)}")
    except (OSError, ValueError) as e:
        return command_error("segment", e)
    from .texts import skills_used, truth_scores

    switches = [int(np.count_nonzero(np.diff(z))) for z in out.labels]
    used = np.bincount(np.concatenate(out.labels), minlength=K)
    print(f"segmented {N} trajectories ({int(lengths.sum())} steps); each step's most probable skill: "
          + skills_used(out.labels, K, "the run's") + "; steps per skill "
          + ", ".join(f"{k}: {n}" for k, n in enumerate(used) if n) + f"; {np.mean(switches):.2f} switches per trajectory")
    if demos.skills is not None:
        print(truth_scores(demos.skills, out.labels))
    confident = float(np.mean(np.concatenate([p.max(-1) for p in out.probs]) > 0.9))
    other = 1.0 - float(np.mean(np.concatenate([p.sum(-1) for p in out.probs])))
    print(f"{confident:.0%} of the steps have a skill of probability above 0.9"
          + (f"; {other:.1%} of the probability is on skills the run's best draw does not have" if other > 1e-3 else ""))
    print(f"wrote {args.output}" + (f" and {args.plot}" if args.plot else ""))
    return 0


def _likelihood_of(run) -> str:
    """What a saved run's likelihood is a probability of (its emission's ``likelihood_of``)."""
    from npbrs.models.emissions import EMISSIONS

    cls = EMISSIONS.get(run.emission.get("name"))
    return getattr(cls, "likelihood_of", "actions")


def compare_command(args) -> int:
    from ..arviz_import import arviz
    from ..driver.runs import load

    az = arviz()

    if len(args.runs) < 2:
        return command_error("compare", "compare needs at least two runs")
    seen = {}
    for path in args.runs:
        real = os.path.realpath(path)
        if real in seen:
            return command_error("compare", f"{path} is given twice (as {seen[real]}); compare ranks different runs")
        seen[real] = path
    try:
        mdp = load_world_mdp(args)
        runs = {}
        for path in args.runs:
            name = os.path.splitext(os.path.basename(path))[0]
            runs[name if name not in runs else path] = load(path)
        # (the checks before any computation: a run's log-likelihoods cost about as much as its fit)
        first = next(iter(runs))
        for name, run in runs.items():
            if run.fingerprint != runs[first].fingerprint:
                raise ValueError(f"{name} and {first} were fitted to different demonstrations (fingerprints "
                                 f"{run.fingerprint[:12]}..., {runs[first].fingerprint[:12]}...); compare ranks runs "
                                 "of the same demonstrations")
        kinds = {name: _likelihood_of(run) for name, run in runs.items()}
        if len(set(kinds.values())) > 1:
            said = {"actions": "a probability of the actions given the states",
                    "states": "a density of the states' vectors"}
            raise ValueError("the runs' likelihoods are of different things, so their scores cannot be ranked: "
                             + "; ".join(f"{name} ({runs[name].emission.get('name')}): {said.get(k, k)}"
                                         for name, k in kinds.items()))
        names = list(runs)
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                if runs[a].equals(runs[b]):
                    raise ValueError(f"{a} and {b} hold the same run; compare ranks different runs")
        for run in runs.values():
            if run.log_likelihood is None:
                options = {"seed": args.seed}
                if args.samples is not None:
                    options["num_samples"] = args.samples
                run.add_log_likelihood(mdp, **options)
        table = az.compare({name: run.to_arviz() for name, run in runs.items()})
    except (OSError, ValueError) as e:
        return command_error("compare", e)
    print(table.to_string())
    return 0
