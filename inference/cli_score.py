"""``npbrs score`` and ``npbrs compare``: held-out log-likelihood and ArviZ model comparison.

    npbrs score run.nc held_out.npz --domain highway
    npbrs compare reward.nc subgoal.nc single.nc --domain highway
"""

from __future__ import annotations

import os

from .cli_generate import _at_least

__all__ = ["add_parsers"]


def _world(p):
    from .cli import add_world_arguments

    add_world_arguments(p, "the run was fitted in")
    p.add_argument("--samples", type=_at_least(1), default=None,
                   help="Monte Carlo samples of a trajectory's skill set and transition weights per draw")
    p.add_argument("--seed", type=_at_least(0), default=0, help="seed of those samples (0)")


def add_parsers(sub):
    p = sub.add_parser("score", help="held-out log-likelihood of new demonstrations under a saved run",
                       description="The posterior predictive log-likelihood of demonstrations that were not in "
                                   "the fit, per trajectory and per step (nats), with Monte Carlo standard errors: "
                                   "the skill sequence summed out, each trajectory's skill set and transition "
                                   "weights integrated (FitResult.log_predictive).")
    p.add_argument("run", help="the run file (.nc) written by npbrs fit")
    p.add_argument("demos", help="held-out demonstrations (.npz)")
    _world(p)
    p.add_argument("--draws", type=_at_least(1), default=100, help="posterior draws used (100)")
    p.set_defaults(func=score_command)
    p = sub.add_parser("compare", help="rank saved runs of the same demonstrations with ArviZ (PSIS-LOO)",
                       description="ArviZ's compare table (PSIS leave-one-out, one trajectory at a time) of runs "
                                   "fitted to the same demonstrations, e.g. different emissions; each run's "
                                   "pointwise log-likelihood is computed when the file does not hold it.")
    p.add_argument("runs", nargs="+", help="run files (.nc); at least two")
    _world(p)
    p.set_defaults(func=compare_command)


def score_command(args) -> int:
    from npbrs.domains.demos import Demonstrations

    from .cli import _error, load_world_mdp
    from .runs import load

    try:
        mdp, run, demos = load_world_mdp(args), load(args.run), Demonstrations.load(args.demos)
        options = {"num_draws": args.draws, "seed": args.seed}
        if args.samples is not None:
            options["num_samples"] = args.samples
        out = run.log_predictive(mdp, demos, **options)
    except (OSError, ValueError) as e:
        return _error("score", e)
    print(f"held-out log-likelihood: {out.per_step:.4f} ± {out.per_step_se:.4f} nats per step "
          f"({len(out.per_trajectory)} trajectories, {out.num_steps} steps, {out.num_draws} posterior draws)")
    print("per trajectory: " + ", ".join(f"{v:.2f} ± {s:.2f}" for v, s in zip(out.per_trajectory,
                                                                              out.per_trajectory_se)))
    return 0


def compare_command(args) -> int:
    import arviz as az

    from .cli import _error, load_world_mdp
    from .runs import load

    if len(args.runs) < 2:
        return _error("compare", "compare needs at least two runs")
    try:
        mdp = load_world_mdp(args)
        runs = {}
        for path in args.runs:
            run = load(path)
            if run.log_likelihood is None:
                options = {"seed": args.seed}
                if args.samples is not None:
                    options["num_samples"] = args.samples
                run.add_log_likelihood(mdp, **options)
            name = os.path.splitext(os.path.basename(path))[0]
            runs[name if name not in runs else path] = run
        fingerprints = {run.fingerprint for run in runs.values()}
        if len(fingerprints) > 1:
            raise ValueError("the runs were fitted to different demonstrations; compare needs the same ones")
        table = az.compare({name: run.to_arviz() for name, run in runs.items()})
    except (OSError, ValueError) as e:
        return _error("compare", e)
    print(table.to_string())
    return 0
