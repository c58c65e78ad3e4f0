"""One fit of one benchmark world with changed options: a quick probe of what a model change
might do, before it is built into the defaults and measured by ``bench_worlds.py``.

    python benchmarks/probe_worlds.py labyrinth 2 '{"emission_options": {"prior_scale": 1.0}}'

Arguments: the world (``tabular_grid``, ``labyrinth``, ``rooms``; seed 0, full size), the number
of chains, and ``fit``'s keyword overrides as JSON (everything else: ``fit``'s defaults). Prints
one JSON line: skills found (and true), one-to-one accuracy (and the oracle's), switches found
over true, held-out log-likelihood per step (20 Monte Carlo samples a draw; and the oracle's),
R-hat of the label-invariant scalars, wall seconds of the fit and peak memory (MB; ``fit_peak_mb``
at the fit's end, as ``bench_worlds.py`` measures it, ``peak_mb`` after scoring the held-out set too).

``{"init_segmentation": "truth"}`` starts every chain from the true segmentation (how far the
sampler then moves away from it, and what it scores, tell segmentation errors from the rest).

An optional fourth argument, fit seeds such as ``0,1,2,3``, fits once per seed (a JSON line
each) and ends with a line of their means and standard deviations: one fit seed's score moves a
lot on these worlds (rooms' best draw 0.72-0.89 over fit seeds 0-3, ``benchmarks/NOTES.md``,
session 39), so judge a change over several. "hungarian" is the best draw's one-to-one accuracy,
"hungarian_sampler" that of the labels counted over the sampler's draws (``skill_probabilities``),
"chain_hungarian" each chain's own counted labels' and "chain_log_joint" each chain's mean log
joint over its sampling sweeps (chains that end in different regions pool into worse labels than
their best: ``benchmarks/NOTES.md``, session 43).

    python benchmarks/probe_worlds.py rooms 4 '{}' 0,1,2,3
"""

import json
import resource
import sys
import time

import numpy as np


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) not in (3, 4):
        raise SystemExit(__doc__)
    from npbrs.domains.worlds import WORLDS
    from npbrs.inference import fit
    from npbrs.inference.analysis.metrics import hungarian_accuracy, num_switches

    name, chains, overrides = argv[0], int(argv[1]), json.loads(argv[2])
    world = WORLDS[name](seed=0)
    oracle = world.oracle()
    if overrides.get("init_segmentation") == "truth":
        overrides = {**overrides, "init_segmentation": world.demos.skills}
    seeds = [int(x) for x in argv[3].split(",")] if len(argv) == 4 else [None]
    rows = []
    for seed in seeds:
        options = dict(overrides) if seed is None else {**overrides, "seed": seed}
        start = time.perf_counter()
        result = fit(world.mdp, world.demos, num_chains=chains, progress_bar=False, **options)
        wall = time.perf_counter() - start
        fit_peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # the fit's, before the scoring
        held = result.log_predictive(world.mdp, world.heldout, num_samples=20)
        counts = np.asarray(result.step_skill_counts)  # each chain's own counted labels, in its own slots
        chain_labels = [[counts[c, i, :len(t)].argmax(-1) for i, t in enumerate(world.demos.skills)]
                        for c in range(counts.shape[0])]
        row = dict(
            world=name, chains=chains, overrides=json.loads(argv[2]), seed=seed, skills=int(result.num_skills),
            true_skills=int(world.model.num_skills),
            hungarian=round(hungarian_accuracy(world.demos.skills, result.segmentation), 3),
            hungarian_sampler=round(hungarian_accuracy(world.demos.skills, result.skill_probabilities().labels), 3),
            oracle_hungarian=round(hungarian_accuracy(world.demos.skills, oracle.viterbi), 3),
            switch_ratio=round(num_switches(result.segmentation) / num_switches(world.demos.skills), 2),
            heldout_ll=round(float(held.per_step), 4), oracle_heldout_ll=round(oracle.heldout_ll, 4),
            sticky_heldout_ll=round(oracle.sticky_heldout_ll, 4),
            rhat={k: round(float(v), 3) for k, v in result.rhat.items()}, wall_s=round(wall),
            chain_hungarian=[round(hungarian_accuracy(world.demos.skills, z), 3) for z in chain_labels],
            chain_log_joint=[round(float(v)) for v in np.mean(result.stats["log_joint"], axis=1)],
            fit_peak_mb=round(fit_peak), peak_mb=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))
        rows.append(row)
        print(json.dumps(row), flush=True)
    if len(rows) > 1:
        def spread(values):
            return [round(float(np.mean(values)), 4), round(float(np.std(values, ddof=1)), 4)]

        print(json.dumps(dict(
            world=name, chains=chains, overrides=json.loads(argv[2]), seeds=seeds, mean_sd=dict(
                skills=spread([r["skills"] for r in rows]), hungarian=spread([r["hungarian"] for r in rows]),
                hungarian_sampler=spread([r["hungarian_sampler"] for r in rows]),
                switch_ratio=spread([r["switch_ratio"] for r in rows]),
                heldout_ll=spread([r["heldout_ll"] for r in rows]),
                rhat_max=spread([max(r["rhat"].values()) for r in rows]), wall_s=spread([r["wall_s"] for r in rows])),
            oracle_hungarian=rows[0]["oracle_hungarian"], oracle_heldout_ll=rows[0]["oracle_heldout_ll"])),
            flush=True)


if __name__ == "__main__":
    main()
