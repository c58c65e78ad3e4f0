"""Is rooms' lumped pair of skills the model's preference or a barrier the search cannot cross?

Fits the rooms world (seed 0) with ``fit``'s defaults, takes the sampler's counted labels
(``skill_probabilities().labels``) and scores segmentations by the greedy moves' own score,
:func:`npbrs.inference.sampler.greedy.merge_score` (log p(x, z, F) with eta, omega and each
skill's reward integrated out: the reward by the emission's Laplace evidence; ``--evidence``
chooses "laplace" or "calibrated"). Each segmentation is also "cleaned" by hard EM: fit every
used skill to its steps, relabel every trajectory by the Viterbi path under a sticky chain (stay
probability ``--stay``) over the skills the trajectory may use, repeat. Rows:

- the found segmentation, and the same after hard EM;
- the found one with its most lumped skill split by trajectory (each trajectory's steps of that
  skill go to the true skill most of them belong to), after hard EM;
- the true model's Viterbi segmentation (the oracle), and each of its skill pairs merged (the
  pair the found run lumped also after hard EM).

A found state that scores near the oracle after cleaning, with every split of its lump lower,
is a local mode the warmup's greedy split cannot leave (``benchmarks/NOTES.md``, session 45).

    python benchmarks/rooms_modes.py [--seed 0] [--chains 4] [--evidence laplace] [--stay 0.96] [--init-skills 4]

(Session 45's table: ``--init-skills 4``. From ``fit``'s default start, every slot since then, fit
seed 0 finds the five skills and no lump.)
"""

from __future__ import annotations

import argparse

import numpy as np


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=0, help="fit seed")
    parser.add_argument("--chains", type=int, default=4)
    parser.add_argument("--evidence", choices=("laplace", "calibrated"), default="laplace")
    parser.add_argument("--stay", type=float, default=0.96, help="hard EM's probability of staying in a skill")
    parser.add_argument("--init-skills", type=int, default=None,
                        help="the fit's starting skills (default: fit's; 4, half of the slots, was the default "
                             "before session 45 and lumps on fit seed 0)")
    args = parser.parse_args(argv)

    import jax
    import jax.numpy as jnp

    from npbrs.domains.worlds import WORLDS
    from npbrs.inference import fit, make_emission
    from npbrs.inference.analysis.metrics import hungarian_accuracy
    from npbrs.inference.sampler.greedy import merge_score
    from npbrs.models.bphmm import Hyper
    from npbrs.models.emissions import HMMData
    from npbrs.models.hmm import batch_viterbi

    world = WORLDS["rooms"](seed=0)
    result = fit(world.mdp, world.demos, num_chains=args.chains, seed=args.seed, progress_bar=False,
                 init_skills=args.init_skills)
    prior = result.model_config.prior
    data = HMMData.from_demonstrations(world.demos)
    N, T = data.mask.shape
    K = result.num_skills + 2
    lengths = world.demos.lengths

    def padded(rows):
        z = np.full((N, T), -1)
        for i, row in enumerate(rows):
            z[i, :len(row)] = row
        return z

    truth = padded(world.demos.skills)
    emission = make_emission("reward", world.mdp, t_evidence=args.evidence).for_search()

    with jax.enable_x64(True):
        values = [getattr(prior, name) for name in ("alpha", "kappa", "gamma")]
        hyper = Hyper(*(jnp.float64(float(getattr(v, "value", v))) for v in values))
        print("switching:", (result.switching or {}).get("chosen", prior.switching),
              "alpha, kappa, gamma:", [float(v) for v in hyper])
        merge_score_of = jax.jit(lambda features, z: merge_score(emission, data, hyper, features, z))

        @jax.jit
        def relabel(z, allowed, log_trans):
            """One hard-EM round: every used skill refitted to its steps, then each trajectory's
            Viterbi path under them."""
            onehot = jax.nn.one_hot(z, K, dtype=jnp.float64) * data.mask[..., None]
            params, _ = emission.fit_evidence(data, onehot, with_evidence=False)
            log_lik, _ = emission.log_likelihoods(params, data, emission.init_cache(K))
            return batch_viterbi(jnp.zeros((N, K)), log_trans, log_lik, data.mask, allowed)[0]

        def features_of(z):
            return (np.asarray(jax.nn.one_hot(jnp.asarray(z), K) * data.mask[..., None]).sum(1) > 0).astype(float)

        def score(z):
            return float(merge_score_of(jnp.asarray(features_of(z)), jnp.asarray(z, jnp.int32)))

        def hard_em(z, sweeps=4):
            allowed = jnp.asarray(features_of(z) > 0)
            log_trans = jnp.broadcast_to(jnp.where(jnp.eye(K, dtype=bool), np.log(args.stay),
                                                   np.log1p(-args.stay)), (N, K, K))
            z = jnp.asarray(z, jnp.int32)
            for _ in range(sweeps):
                z = relabel(z, allowed, log_trans)
            return np.asarray(z)

        def row(name, z):
            acc = hungarian_accuracy(world.demos.skills, [z[i, :m] for i, m in enumerate(lengths)])
            used = int(np.sum(features_of(z).sum(0) > 0))
            switches = int(np.sum((z[:, 1:] != z[:, :-1]) & (z[:, 1:] >= 0)))
            print(f"{name:<44} score {score(z):10.1f}  one-to-one {acc:.3f}  skills {used}  switches {switches}",
                  flush=True)

        found = padded(result.skill_probabilities().labels)
        confusion = np.zeros((world.model.num_skills, K), int)
        np.add.at(confusion, (truth[data.mask], found[data.mask]), 1)
        print("true skill (rows) by found skill (columns):\n", confusion)
        lump = int(np.argmax(np.sort(confusion, axis=0)[-2]))  # the found skill with the largest second true skill
        a, b = np.argsort(confusion[:, lump])[-2:]
        row("found", found)
        cleaned = hard_em(found)
        row("found, hard EM", cleaned)
        split = found.copy()
        free = result.num_skills
        for i in range(N):
            steps = found[i] == lump
            if np.sum(steps & (truth[i] == a)) > np.sum(steps & (truth[i] == b)):
                split[i, steps] = free
        row(f"found, skill {lump} split by trajectory", split)
        row(f"found, skill {lump} split by trajectory, hard EM", hard_em(split))
        oracle = padded(world.oracle().viterbi)
        row("oracle Viterbi", oracle)
        for j in range(world.model.num_skills):
            for k in range(j + 1, world.model.num_skills):
                merged = np.where(oracle == k, j, oracle)
                row(f"oracle Viterbi, skills {j} and {k} merged", merged)
                if {j, k} == {int(a), int(b)}:
                    row(f"oracle Viterbi, skills {j} and {k} merged, hard EM", hard_em(merged))


if __name__ == "__main__":
    main()
