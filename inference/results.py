"""Results of a fit: the best segmentation, its skills, the draws and label-invariant diagnostics."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np

__all__ = ["FitResult", "LABEL_INVARIANT"]

#: Scalars whose meaning does not depend on how skills are labelled: safe for R-hat and ESS
#: across chains (skill labels switch between chains).
LABEL_INVARIANT = ("log_joint", "num_skills", "num_switches")


def _chains(x, num_chains):
    x = np.asarray(x)
    return x if num_chains > 1 else x[None]


def _compact(z_rows: List[np.ndarray]):
    """Relabel slot indices to 0..n-1 in order of first appearance; returns (rows, slots)."""
    slots: List[int] = []
    for row in z_rows:
        for s in row:
            if s >= 0 and int(s) not in slots:
                slots.append(int(s))
    lookup = {s: i for i, s in enumerate(slots)}
    return [np.array([lookup[int(s)] for s in row], dtype=np.int64) for row in z_rows], np.array(slots, np.int64)


@dataclass(eq=False)
class FitResult:
    """What ``fit`` found.

    Attributes:
        segmentation: per trajectory, the skill (0..num_skills-1) of every step, from the
            highest-log-joint draw across chains (after warmup).
        num_skills: number of skills in that segmentation.
        skill_params: the emission parameters of those skills, {site: (num_skills, ...)},
            e.g. ``skill_params["theta"]`` the reward weights.
        skill_slots: the sampler's slot index of each skill.
        best_chain: the chain of the best draw; best_log_joint: its log joint.
        stats: per chain and draw (C, D): "log_joint", "num_skills", "num_switches", "accept".
        samples: posterior draws {site: (C, D, ...)} (emission parameters and features).
        config: the run's settings; fingerprint: the demonstrations' fingerprint.
        wall_time: seconds spent sampling, compilation included.
    """

    segmentation: List[np.ndarray]
    num_skills: int
    skill_params: Dict[str, np.ndarray]
    skill_slots: np.ndarray
    best_chain: int
    best_log_joint: float
    stats: Dict[str, np.ndarray]
    samples: Dict[str, np.ndarray]
    config: dict = field(default_factory=dict)
    fingerprint: str = ""
    wall_time: float = float("nan")

    @classmethod
    def from_mcmc(cls, mcmc, demos, config: Optional[dict] = None, wall_time: float = float("nan")) -> "FitResult":
        C = mcmc.num_chains
        last = mcmc.last_state
        best_lj = _chains(last.best_log_joint, C)
        chain = int(np.argmax(best_lj))
        best_z = _chains(last.best_z, C)[chain]
        rows = [best_z[i, :n] for i, n in enumerate(demos.lengths)]
        segmentation, slots = _compact(rows)
        best_params = {k: _chains(v, C)[chain][slots] for k, v in last.best_params.items()}
        draws = mcmc.get_samples(group_by_chain=True)
        extra = mcmc.get_extra_fields(group_by_chain=True)
        stats = {k: np.asarray(extra[k]) for k in ("log_joint", "num_skills", "num_switches", "accept")}
        samples = {k: np.asarray(v) for k, v in draws.items()}
        samples["features"] = np.asarray(extra["features"])
        return cls(segmentation=segmentation, num_skills=len(slots), skill_params=best_params, skill_slots=slots,
                   best_chain=chain, best_log_joint=float(best_lj[chain]), stats=stats, samples=samples,
                   config=dict(config or {}), fingerprint=demos.fingerprint(), wall_time=float(wall_time))

    @property
    def log_joint(self) -> np.ndarray:
        """(C, D) log joint density of every draw."""
        return self.stats["log_joint"]

    def _diagnostic(self, fn) -> Dict[str, float]:
        out = {}
        for name in LABEL_INVARIANT:
            x = np.asarray(self.stats[name], dtype=np.float64)
            if x.shape[1] < 4 or np.all(x == x.flat[0]):
                out[name] = float("nan") if x.shape[1] < 4 else (1.0 if fn.__name__ == "split_gelman_rubin"
                                                                  else float(x.size))
                continue
            out[name] = float(fn(x))
        return out

    @property
    def rhat(self) -> Dict[str, float]:
        """Split R-hat of the label-invariant scalars across chains (1.0 for a constant scalar)."""
        from numpyro.diagnostics import split_gelman_rubin

        return self._diagnostic(split_gelman_rubin)

    @property
    def ess(self) -> Dict[str, float]:
        """Effective sample size of the label-invariant scalars."""
        from numpyro.diagnostics import effective_sample_size

        return self._diagnostic(effective_sample_size)

    def to_arviz(self):
        """ArviZ InferenceData: posterior draws and label-invariant sample stats."""
        import arviz as az

        posterior = {k: v for k, v in self.samples.items()}
        for name in LABEL_INVARIANT:
            posterior[name] = self.stats[name]
        sample_stats = {"lp": self.stats["log_joint"], **{k: v for k, v in self.stats.items()}}
        return az.from_dict(posterior=posterior, sample_stats=sample_stats)

    def summary(self) -> str:
        """A short text summary: skills, segment lengths, diagnostics."""
        lengths = [len(s) for s in self.segmentation]
        switches = np.mean([np.sum(s[1:] != s[:-1]) for s in self.segmentation])
        counts = np.bincount(np.concatenate(self.segmentation), minlength=self.num_skills)
        lines = [f"{self.num_skills} skills in {len(lengths)} trajectories ({sum(lengths)} steps); "
                 f"{switches:.2f} switches per trajectory; best log joint {self.best_log_joint:.1f} (chain {self.best_chain})",
                 "steps per skill: " + ", ".join(f"{k}: {c}" for k, c in enumerate(counts))]
        rhat, ess = self.rhat, self.ess
        lines.append("label-invariant diagnostics: " + "; ".join(
            f"{n} R-hat {rhat[n]:.3f} ESS {ess[n]:.0f}" for n in LABEL_INVARIANT))
        return "\n".join(lines)
