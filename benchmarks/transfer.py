"""Transfer: the skills' inferred rewards solved again in a changed world, against the expert
re-planned there, the demonstrated policies carried over, and unsegmented IRL.

For each domain and run: demonstrations of the paper's world (16 x 500 steps, seed = run) are
segmented by npbrs (the reward emission, the reproduction's settings) and by unsegmented IRL
(the ``single`` emission). Then, in each named world of the domain (``WORLDS``: the paper's and
changed ones with the same features), the paper's control evaluation replays every
demonstration from its first state, each step acting with the policy of its inferred skill
and scored with the true skill's reward (``npbrs.domains.control.evaluate_control``; shared
random numbers per run). The methods, per world:

- ``expert``: the true segmentation, the true rewards re-planned in the world (the ceiling);
- ``expert_carried``: the true skills' policies of the paper's world, unchanged (how much the
  change of world matters at all);
- ``true_seg_irl``: each true skill's reward fitted by MAP IRL (the reward emission's own fit,
  50 L-BFGS steps) on its true steps, re-solved in the world: what segmentation-then-IRL reaches
  with a perfect segmentation under the same prior;
- ``npbrs``: npbrs's inferred rewards re-solved in the world (``FitResult.policies(world)``);
- ``carried``: the same skills' policies carried over unchanged (each inferred reward's optimal
  policy in the paper's world, as a method that learns policies would keep them);
- ``cloned``: behaviour cloning of each inferred skill (its most frequent demonstrated action
  in every state it visited; elsewhere the carried policy);
- ``irl``: one reward for all steps (unsegmented IRL) re-solved in the world.

    python benchmarks/transfer.py --runs 3 --out benchmarks/results/transfer

prints a markdown table per domain and writes ``transfer.json`` and ``transfer.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

import numpy as np

METHODS = ("expert", "expert_carried", "true_seg_irl", "npbrs", "carried", "cloned", "irl")
LABELS = {"expert": "Expert re-planned", "expert_carried": "Expert's policies carried over",
          "true_seg_irl": "IRL on the true segmentation re-solved", "npbrs": "NPBRS rewards re-solved", "carried": "Policies carried over",
          "cloned": "Behaviour cloning", "irl": "Unsegmented IRL re-solved"}


def cloned_policies(mdp, demos, segmentation, fallback):
    """(K, S) each inferred skill's most frequent action per visited state; ``fallback`` elsewhere."""
    K, S, A = fallback.shape[0], mdp.num_states, mdp.num_actions
    counts = np.zeros((K, S, A))
    for s, a, z in zip(demos.states, demos.actions, segmentation):
        np.add.at(counts, (np.asarray(z), np.asarray(s), np.asarray(a)), 1.0)
    return np.where(counts.sum(-1) > 0, counts.argmax(-1), fallback).astype(np.int64)


def true_segmentation_rewards(domain, demos, prior_scale=None):
    """(K, D) MAP IRL weights of each true skill from its own steps (the reward emission's fit)."""
    import jax.numpy as jnp

    from npbrs.models.emissions import make_emission
    from npbrs.models.emissions import HMMData

    options = {"refit_steps": 50, **({"prior_scale": prior_scale} if prior_scale else {})}
    em = make_emission("reward", domain.mdp, **options)
    data = HMMData.from_demonstrations(demos)
    z = np.full(data.mask.shape, -1)
    for i, k in enumerate(demos.skills):
        z[i, :len(k)] = k
    weights = jnp.asarray(z[..., None] == np.arange(domain.num_skills), jnp.float64)
    return np.asarray(em.fit_point(data, weights)["theta"])


def one_run(name, run, args, worlds):
    from npbrs.domains.control import evaluate_control, expert_control
    from npbrs.domains.demos import Demonstrations, generate_demonstrations
    from npbrs.domains.registry import get_domain
    from npbrs.inference.driver.fit import fit
    from npbrs.inference.cli.reproduce import default_settings, run_segmentation

    domain = get_domain(name)
    demos = generate_demonstrations(domain, num_trajectories=args.trajectories, length=args.length, seed=run)
    settings = default_settings(name, quick=args.quick)
    fits = {}
    for method, emission in (("npbrs", "reward"), ("irl", "single")):
        s = settings["npbrs" if method == "npbrs" else "irl"]
        start = time.perf_counter()
        options = {**({"prior_scale": args.prior_scale} if args.prior_scale else {}),
                   **({"scale_prior": list(args.scale_prior)} if args.scale_prior else {})} or None
        config = {"emission": emission, "max_skills": s["max_skills"],
                  **({"emission_options": options} if options else {}),
                  **({"init_window": s["init_window"]} if "init_window" in s else {})}
        fits[method] = fit(domain.mdp, demos, config, num_chains=s["chains"], num_warmup=s["warmup"],
                           num_samples=s["samples"], seed=run, progress_bar=False)
        print(f"  {name} run {run}: {method} fit {time.perf_counter() - start:.0f} s, "
              f"{fits[method].num_skills} skills", flush=True)
    if args.save_runs:
        os.makedirs(args.save_runs, exist_ok=True)
        for method, result in fits.items():
            result.save(os.path.join(args.save_runs, f"{name}-{run}-{method}.nc"))
    npbrs, irl = fits["npbrs"], fits["irl"]
    carried = npbrs.policies(domain.mdp, greedy=True)
    # the segmentation the inferred skills act by: each step's most probable skill under the
    # run's posterior (FitResult.segment), or the best draw's, as npbrs reproduce scores
    labels = run_segmentation(npbrs, domain.mdp, args.segmentation)
    cloned = cloned_policies(domain.mdp, demos, labels, carried)
    # replay from the recorded start states and label timeline: the demonstrations themselves
    # belong to the paper's world, so they are used without their MDP fingerprint
    timeline = Demonstrations(demos.states, demos.actions, demos.skills)
    true_theta = true_segmentation_rewards(domain, demos, args.prior_scale)
    record = {}
    for world in worlds:
        changed = get_domain(name, world=world)
        mdp = changed.mdp
        scores = {"expert": expert_control(changed, timeline, seed=run)["reward"],
                  "expert_carried": evaluate_control(changed, timeline, demos.skills, domain.expert_policies(),
                                                     seed=run)["reward"],
                  "true_seg_irl": evaluate_control(changed, timeline, demos.skills, true_theta, seed=run)["reward"],
                  "npbrs": evaluate_control(changed, timeline, labels,
                                            npbrs.policies(mdp, greedy=True), seed=run)["reward"],
                  "carried": evaluate_control(changed, timeline, labels, carried, seed=run)["reward"],
                  "cloned": evaluate_control(changed, timeline, labels, cloned, seed=run)["reward"],
                  "irl": evaluate_control(changed, timeline, irl.segmentation, irl.policies(mdp, greedy=True),
                                          seed=run)["reward"]}
        record[world] = scores
        print(f"  {name} run {run} {world:>16}: " + ", ".join(f"{m} {v:.0f}" for m, v in scores.items()), flush=True)
    return {"run": run, "skills": int(npbrs.num_skills), "worlds": record,
            "wall_time": {m: float(f.wall_time) for m, f in fits.items()}}


def summarise(per_run, worlds):
    table = {}
    for world in worlds:
        table[world] = {}
        expert = np.array([r["worlds"][world]["expert"] for r in per_run])
        for m in METHODS:
            v = np.array([r["worlds"][world][m] for r in per_run])
            table[world][m] = {"mean": float(v.mean()), "sd": float(v.std(ddof=1)) if len(v) > 1 else None,
                               "of_expert": float(np.mean(v / expert))}
    return table


def markdown(results) -> str:
    lines = ["# Transfer: inferred rewards re-solved in changed worlds", "",
             results["description"], ""]
    for name, dom in results["domains"].items():
        lines += [f"## {name}", "", "Mean control reward per trajectory over runs (share of the re-planned "
                  "expert's, mean over runs):", "",
                  "| world | " + " | ".join(LABELS[m] for m in METHODS) + " |",
                  "|---|" + "---:|" * len(METHODS)]
        for world, row in dom["table"].items():
            cells = [f"{row[m]['mean']:.0f} ({100 * row[m]['of_expert']:.1f}%)" for m in METHODS]
            lines.append(f"| {world} | " + " | ".join(cells) + " |")
        lines += ["", "Targets in the changed worlds (NPBRS re-solved >= 95% of the expert, above the carried-over "
                  "policies, behaviour cloning and unsegmented IRL):", ""]
        for world, row in dom["table"].items():
            if world == "paper":
                continue
            share = row["npbrs"]["of_expert"]
            ahead = all(row["npbrs"]["mean"] > row[m]["mean"] for m in ("carried", "cloned", "irl"))
            lines.append(f"- {world}: {100 * share:.1f}% of the expert ({'met' if share >= 0.95 else 'not met'}); "
                         f"above the others: {'met' if ahead else 'not met'}")
        walls = [r["wall_time"]["npbrs"] for r in dom["runs"]]
        lines += ["", f"Runs: {len(dom['runs'])} (seeds {', '.join(str(r['run']) for r in dom['runs'])}); skills "
                  f"found {', '.join(str(r['skills']) for r in dom['runs'])}; NPBRS fit {np.mean(walls):.0f} s "
                  "per run (compilation included).", ""]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    p.add_argument("--domains", default="highway,quadcopter")
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--trajectories", type=int, default=16)
    p.add_argument("--length", type=int, default=500)
    p.add_argument("--quick", action="store_true", help="a few sweeps of one chain (a check that it runs)")
    p.add_argument("--prior-scale", type=float, default=None,
                   help="the reward prior's scale for both fits (default: the emission's, 10)")
    p.add_argument("--scale-prior", type=float, nargs=2, metavar=("A", "B"), default=None,
                   help="sample each skill's reward prior variance under InvGamma(A, B) in both fits "
                        "(the reward emission's scale_prior; default: the fixed scale)")
    p.add_argument("--segmentation", choices=("marginal", "best"), default="marginal",
                   help="the steps' skills npbrs's policies act by: each step's most probable skill under the "
                        "run's posterior (FitResult.segment; the default) or the best draw's segmentation")
    p.add_argument("--save-runs", metavar="DIR", help="also save every fit as DIR/DOMAIN-RUN-METHOD.nc")
    p.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "transfer"))
    args = p.parse_args(argv)
    from npbrs.domains.registry import get_domain
    import importlib

    results = {"description": f"{args.trajectories} demonstrations of {args.length} steps per run in the paper's "
                              "world; the reproduction's sampler settings (npbrs: 4 chains x (20 + 20) sweeps, "
                              "15 + 15 on the quadcopter); reward prior scale "
                              f"{args.prior_scale or 'the default (10)'}"
                              + (f", each skill's variance sampled under InvGamma{tuple(args.scale_prior)}"
                                 if args.scale_prior else "") + "; control reward as in the paper's Figures "
                              "7 and 10; each skill's policy from its posterior mean weights (FitResult.policies' "
                              "default); the inferred skills act by "
                              + ("the best draw's segmentation. " if args.segmentation == "best" else
                                 "each step's most probable skill under the run's posterior (FitResult.segment). ")
                              + f"Machine: {platform.machine()}, {os.cpu_count()} cores, shared with other jobs.",
               "settings": vars(args), "domains": {}}
    os.makedirs(args.out, exist_ok=True)
    for name in args.domains.split(","):
        get_domain(name)
        worlds = list(importlib.import_module(f"npbrs.domains.{name}").WORLDS)
        print(f"{name}: worlds {', '.join(worlds)}", flush=True)
        per_run = [one_run(name, r, args, worlds) for r in range(args.runs)]
        results["domains"][name] = {"worlds": worlds, "runs": per_run, "table": summarise(per_run, worlds)}
        with open(os.path.join(args.out, "transfer.json"), "w") as f:
            json.dump(results, f, indent=1)
        with open(os.path.join(args.out, "transfer.md"), "w") as f:
            f.write(markdown(results))
    print(markdown(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
