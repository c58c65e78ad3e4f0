"""How much a learned initial-skill distribution could gain at most on the benchmark worlds
(issue 16's candidate "trajectories that all start in one place usually start with one skill").

For each world (seed 0), the true generating model's held-out log-likelihood per step (the
oracle) against the same model with its first-skill distribution replaced by the uniform one
over each trajectory's skill set (what the BP-HMM assumes). The difference bounds what learning
the initial distribution can add to npbrs's held-out score when everything else is right.

    python benchmarks/initial_skill_bound.py
"""

import numpy as np

from npbrs.domains import worlds


def main():
    for name in ["labyrinth", "rooms", "tabular_grid"]:
        w = getattr(worlds, name)(0)
        m = w.model
        base = m.log_likelihood_per_step(w.heldout)
        uniform = np.where(m.skill_sets, 1.0, 0.0)
        uniform /= uniform.sum(-1, keepdims=True)
        flat = worlds.SkillProcess(m.log_policies, m.skill_sets, m.skill_set_probs, uniform, m.transitions,
                                   m.skill_names)
        print(f"{name}: oracle {base:.4f} nats per step, with a uniform first skill "
              f"{flat.log_likelihood_per_step(w.heldout):.4f}; true first-skill distributions "
              f"{np.round(m.initial_skill, 2).tolist()[:3]}")


if __name__ == "__main__":
    main()
