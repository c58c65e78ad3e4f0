"""Results of a fit: the best segmentation, its skills, the draws and label-invariant
diagnostics, and their ArviZ form (what a saved run file holds).

**ArviZ form** (:meth:`FitResult.to_arviz`; :meth:`FitResult.save` writes it to netCDF-4 with
the h5netcdf engine, ``npbrs.inference.load`` reads it back): an ``InferenceData`` with groups

- ``posterior``: the draws, dims (chain, draw, ...): every emission parameter site (e.g.
  ``theta`` (chain, draw, skill, theta_dim_0)), ``features`` (chain, draw, trajectory, skill),
  ``skill_steps`` (chain, draw, skill: steps assigned to each skill slot), sampled
  hyperparameters, and the label-invariant scalars ``log_joint``, ``num_skills``, ``num_switches``;
- ``sample_stats``: ``lp`` (the log joint) and every per-draw scalar of the kernel
  (``log_joint``, ``num_skills``, ``num_switches``, ``accept``, ...);
- in ``posterior``, ``sample_stats`` and ``log_likelihood``, the coordinate ``superchain``
  (chain): the chains that share a start (:attr:`FitResult.superchains`; a chain restarted at
  warmup's end shares the start of the chain whose state it continued from), what the nested
  R-hat groups;
- ``constant_data``: the best segmentation ``segmentation`` (trajectory, step; -1 on padding)
  with ``lengths`` (trajectory), its skills' parameters ``best_<site>`` (skill, ...), their
  sampler slots ``skill_slots`` (skill), and each chain's best segmentation in slot labels
  ``chain_best_z`` (chain, trajectory, step), and ``step_skill_counts`` (chain, trajectory, step,
  slot: in how many of the chain's sampling sweeps each step was in each skill slot, what
  ``FitResult.skill_probabilities`` reads); its attributes hold the run's description:
  ``npbrs_format`` ("npbrs-run"), ``npbrs_version`` (1), ``config`` (the
  :class:`~npbrs.inference.driver.config.ModelConfig` as JSON), ``emission`` (the emission's
  ``describe()`` as JSON), ``fingerprint`` (of the demonstrations), ``feature_names`` (JSON),
  ``best_chain``, ``best_log_joint``, ``wall_time``, ``mdp_fingerprint`` (of the MDP fitted in;
  ``observed_data``'s attribute ``mdp_fingerprint`` is the demonstrations' own, when recorded);
- ``observed_data`` (when the result carries them): the demonstrations, ``states``, ``actions``
  and, when known, ``skills`` (trajectory, step; -1 on padding) with ``lengths``;
- ``warmup_sample_stats`` (when known): the label-invariant scalars of the warmup sweeps
  (chain, draw);
- ``log_likelihood`` (after ``FitResult.add_log_likelihood``): ``demonstrations`` (chain, draw,
  trajectory), each trajectory's log-likelihood under each draw, its skill set and transition
  weights integrated (what ``az.loo`` and ``az.compare`` read).

The files of a run (reading saved runs, checkpoints, MDP files) are
:mod:`npbrs.inference.driver.runs`, which imports this module (never the other way).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np

from npbrs.domains.util.files import atomic_write
from npbrs.domains.util.precision import float64_all

from ..analysis.diagnostics import (LABEL_INVARIANT, ConvergenceWarning, convergence_warning,
                                     label_invariant_diagnostic, shares_start, summary, superchain_ids,
                                     unconverged)
from .config import ModelConfig

#: ``fit``'s draws entry counting each step's skill slots over the sampling sweeps (C, N, T, K)
STEP_COUNTS = "step_skill_counts"

__all__ = ["FitResult", "ConvergenceWarning", "LABEL_INVARIANT", "label_invariant_diagnostic", "unconverged", "RUN_FORMAT",
           "RUN_VERSION", "NETCDF_ENGINE", "trajectory_rows"]


#: The ArviZ form's format name and version (``constant_data`` attributes), and the netCDF engine.
RUN_FORMAT, RUN_VERSION = "npbrs-run", 1
NETCDF_ENGINE = "h5netcdf"


def _chains(x, num_chains):
    x = np.asarray(x)
    return x if num_chains > 1 else x[None]


def trajectory_rows(z, lengths) -> Optional[List[np.ndarray]]:
    """Per-trajectory int64 rows of a padded (N, T) array (None stays None)."""
    if z is None:
        return None
    z = np.asarray(z)
    return [z[i, :n].astype(np.int64) for i, n in enumerate(lengths)]


def _padded(rows, pad=-1) -> np.ndarray:
    T = max(len(r) for r in rows)
    out = np.full((len(rows), T), pad, dtype=np.int64)
    for i, r in enumerate(rows):
        out[i, :len(r)] = r
    return out


def _site_dims(name: str, shape, param_sites) -> list:
    if name == "features":
        return ["trajectory", "skill"]
    if name in ("skill_steps", "end_mean"):
        return ["skill"]
    if name == "ends":
        return ["skill", "state"]
    if name in param_sites and len(shape) >= 1:
        return ["skill"] + [f"{name}_dim_{i}" for i in range(len(shape) - 1)]
    return [f"{name}_dim_{i}" for i in range(len(shape))]


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
            highest-log-joint draw across chains (after warmup): one posterior sample, whose
            boundaries jitter; each step's most probable skill over all the draws is
            :meth:`skill_probabilities`' ``labels``.
        num_skills: number of skills in that segmentation.
        skill_params: the emission parameters of those skills, {site: (num_skills, ...)},
            e.g. ``skill_params["theta"]`` the reward weights.
        skill_slots: the sampler's slot index of each skill.
        best_chain: the chain of the best draw; best_log_joint: its log joint.
        stats: per chain and draw (C, D): "log_joint", "num_skills", "num_switches", "accept"
            and any other per-draw scalar the kernel reports (e.g. "greedy_merges" and
            "greedy_splits", the warmup's greedy moves kept so far).
        samples: posterior draws {site: (C, D, ...)}: the emission parameters (skill slots on
            axis 2), "features" (C, D, N, K), "skill_steps" (C, D, K) the steps assigned to
            each slot, and sampled hyperparameters.
        config: the run's :class:`~npbrs.inference.driver.config.ModelConfig` as plain data
            (:attr:`model_config` parses it); fingerprint: the demonstrations' fingerprint.
        wall_time: seconds spent sampling, compilation included (summed over resumed pieces).
        emission: the emission's ``describe()``.
        feature_names: the MDP's reward feature names (for per-skill summaries).
        chain_best_z: (C, N, T) every chain's best segmentation in slot labels (-1 on padding).
        demos: the demonstrations, when known.
        init_segmentation: per trajectory, the segmentation every chain started from when
            ``fit`` was given one (relabelled 0, 1, ... in order of value); None for the
            default start from random windows. ``fit(..., init_segmentation=...)`` with it
            repeats the run.
        warmup_stats: the label-invariant scalars of the warmup sweeps, {name: (C, W)} (trace
            plots shade them); None when unknown.
        mdp_fingerprint: ``TabularMDP.fingerprint()`` of the MDP the run was fitted in ("" when
            unknown, e.g. a run saved before it was recorded); :meth:`check_mdp` compares it.
        log_likelihood: (C, D, N) each fitted trajectory's log-likelihood under each draw, once
            :meth:`add_log_likelihood` has computed it (saved as the ArviZ ``log_likelihood``
            group, which ``az.loo`` and ``az.compare`` read); None before.
        run_length: for a run whose length was chosen by convergence (``max_samples`` above
            ``samples``, see :class:`~npbrs.inference.driver.config.SamplerConfig`): the sampling
            sweeps drawn ("samples"), the R-hat of each label-invariant scalar at the end
            ("rhat"; None where undefined, e.g. a scalar constant in every draw), the rule that stopped the run ("stopped": "converged", "max_samples" or
            "time_budget") and the settings ("target_rhat", "max_samples", "time_budget");
            None for a run of fixed length.
        truncation: for a run whose skill slots grew (``fit(..., grow=True)``): the slots of
            each fit in turn ("max_skills", e.g. [8, 16]), the skills each found ("skills"),
            the share of its sampling draws that used every slot ("saturated") and its switching
            model ("switching"; under "auto" the sticky fits come first, then any with
            state-dependent ends); None otherwise.
        switching: for a run whose switching model ``fit`` chose (``switching="auto"``, the
            default): the log evidence of the sticky fit's skill sequences under each model
            ("sticky", "state"; :func:`~npbrs.models.bphmm.switching_log_evidence`), their
            difference ("log_bayes_factor", state over sticky), the margin it had to pass
            ("margin") and the model of this result ("chosen"); None otherwise.
        action_names: for a run whose emission learns which of several equivalent actions the
            demonstrator names (the reward emission's ``action_names="learned"``, the default;
            :mod:`npbrs.models.names`): the sets of equivalent actions the demonstrations visit
            ("sets"), the log Bayes factor of learned over uniform names ("log_bayes_factor")
            and a line for the summary ("text"); None otherwise.
        restart: for a run of several chains with ``restart_margin`` on (see
            :class:`~npbrs.inference.driver.config.SamplerConfig`): the margin ("margin"), each
            chain's score at the end of warmup ("scores", its log joint averaged over the last
            tenth of the warmup sweeps) and the chain whose state each continued from ("from"; its own
            number where it kept its own); None otherwise.
        step_skill_counts: (C, N, T, K) in how many of a chain's sampling sweeps each step of
            the demonstrations was in each skill slot (0 on padding); what
            :meth:`skill_probabilities` reads. None for a run that did not keep them (a run saved,
            or a checkpoint written, before they were kept).

    The methods :meth:`policies`, :meth:`options`, :meth:`segment`, :meth:`log_predictive` and
    :meth:`add_log_likelihood` are shortcuts to the functions of :mod:`npbrs.inference.analysis`
    (imported when called: the analysis imports this module, not the other way).
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
    emission: dict = field(default_factory=dict)
    feature_names: tuple = ()
    chain_best_z: Optional[np.ndarray] = None
    demos: Optional[object] = None
    init_segmentation: Optional[List[np.ndarray]] = None
    log_likelihood: Optional[np.ndarray] = None
    mdp_fingerprint: str = ""
    warmup_stats: Optional[Dict[str, np.ndarray]] = None
    run_length: Optional[dict] = None
    truncation: Optional[dict] = None
    restart: Optional[dict] = None
    switching: Optional[dict] = None
    action_names: Optional[dict] = None
    step_skill_counts: Optional[np.ndarray] = None

    @classmethod
    def from_states(cls, last_state, draws: Dict[str, np.ndarray], demos, *, config: Optional[dict] = None,
                    emission: Optional[dict] = None, feature_names=(), wall_time: float = float("nan"),
                    sample_names=(), init_segmentation=None, mdp_fingerprint: str = "",
                    warmup_stats: Optional[Dict[str, np.ndarray]] = None,
                    run_length: Optional[dict] = None, restart: Optional[dict] = None) -> "FitResult":
        """Assemble a result from the chains' last kernel states and their draws.

        Args:
            last_state: the kernel state of every chain, leaves (C, ...) (``best_log_joint``,
                ``best_z``, ``best_params`` are used).
            draws: {name: (C, D, ...)}; per-draw scalars become ``stats`` unless named in
                ``sample_names``, the rest ``samples``.
            init_segmentation: the (N, T) start the chains were given (-1 on padding), if any.
        """
        best_lj = np.asarray(last_state.best_log_joint)
        chain = int(np.argmax(best_lj))
        # (a fit padded to a shape bucket has more trajectories and steps than the demonstrations)
        N, T = len(demos.lengths), int(np.max(demos.lengths))
        chain_best_z = np.asarray(last_state.best_z).astype(np.int64)[:, :N, :T]
        rows = trajectory_rows(chain_best_z[chain], demos.lengths)
        segmentation, slots = _compact(rows)
        best_params = {k: np.asarray(v)[chain][slots] for k, v in last_state.best_params.items()}
        draws = {k: np.asarray(v) for k, v in draws.items()}
        counts = draws.pop(STEP_COUNTS, None)
        if "features" in draws:
            draws["features"] = draws["features"][:, :, :N]
        stats = {k: v for k, v in draws.items() if v.ndim == 2 and k not in sample_names}
        samples = {k: v for k, v in draws.items() if k not in stats}
        return cls(segmentation=segmentation, num_skills=len(slots), skill_params=best_params, skill_slots=slots,
                   best_chain=chain, best_log_joint=float(best_lj[chain]), stats=stats, samples=samples,
                   config=dict(config or {}), fingerprint=demos.fingerprint(), wall_time=float(wall_time),
                   emission=dict(emission or {}), feature_names=tuple(feature_names), chain_best_z=chain_best_z,
                   demos=demos, init_segmentation=None if init_segmentation is None else
                   trajectory_rows(np.asarray(init_segmentation)[:N, :T], demos.lengths),
                   mdp_fingerprint=str(mdp_fingerprint or ""),
                   warmup_stats=None if not warmup_stats else {k: np.asarray(v) for k, v in warmup_stats.items()},
                   run_length=None if run_length is None else dict(run_length),
                   restart=None if restart is None else dict(restart),
                   step_skill_counts=None if counts is None else counts[:, :N, :T])

    @property
    def model_config(self) -> ModelConfig:
        """The run's :class:`~npbrs.inference.driver.config.ModelConfig`."""
        return ModelConfig.from_dict(self.config)

    @property
    def num_chains(self) -> int:
        return int(np.shape(self.stats["log_joint"])[0])

    @property
    def num_draws(self) -> int:
        return int(np.shape(self.stats["log_joint"])[1])

    def save(self, path) -> None:
        """Write this result's ArviZ form (:meth:`to_arviz`) to a netCDF file, atomically (a
        temporary file, then a rename); read it back with ``npbrs.inference.load``."""
        idata = self.to_arviz()
        atomic_write(path, lambda tmp: idata.to_netcdf(tmp, engine=NETCDF_ENGINE), suffix=".nc.tmp")

    def equals(self, other: "FitResult", wall_time: bool = False) -> bool:
        """Whether two results hold the same segmentation, draws, parameters and description
        (bit for bit; ``wall_time`` compared only when asked)."""
        if not isinstance(other, FitResult):
            return False

        def same(a, b):
            a, b = np.asarray(a), np.asarray(b)
            return a.shape == b.shape and np.array_equal(a, b, equal_nan=a.dtype.kind == "f" and b.dtype.kind == "f")

        def same_dict(a, b):
            return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)

        return (len(self.segmentation) == len(other.segmentation)
                and all(same(a, b) for a, b in zip(self.segmentation, other.segmentation))
                and self.num_skills == other.num_skills and same_dict(self.skill_params, other.skill_params)
                and same(self.skill_slots, other.skill_slots) and self.best_chain == other.best_chain
                and same(self.best_log_joint, other.best_log_joint) and same_dict(self.stats, other.stats)
                and same_dict(self.samples, other.samples) and self.config == other.config
                and self.fingerprint == other.fingerprint and self.emission == other.emission
                and self.mdp_fingerprint == other.mdp_fingerprint
                and ((self.warmup_stats is None) == (other.warmup_stats is None))
                and (self.warmup_stats is None or same_dict(self.warmup_stats, other.warmup_stats))
                and tuple(self.feature_names) == tuple(other.feature_names)
                and ((self.chain_best_z is None) == (other.chain_best_z is None))
                and (self.chain_best_z is None or same(self.chain_best_z, other.chain_best_z))
                and ((self.demos is None) == (other.demos is None))
                and (self.demos is None or self.demos == other.demos)
                and ((self.init_segmentation is None) == (other.init_segmentation is None))
                and (self.init_segmentation is None
                     or (len(self.init_segmentation) == len(other.init_segmentation)
                         and all(same(a, b) for a, b in zip(self.init_segmentation, other.init_segmentation))))
                and ((self.log_likelihood is None) == (other.log_likelihood is None))
                and (self.log_likelihood is None or same(self.log_likelihood, other.log_likelihood))
                and ((self.step_skill_counts is None) == (other.step_skill_counts is None))
                and (self.step_skill_counts is None or same(self.step_skill_counts, other.step_skill_counts))
                and json.dumps(self.run_length, sort_keys=True) == json.dumps(other.run_length, sort_keys=True)
                and json.dumps(self.truncation, sort_keys=True) == json.dumps(other.truncation, sort_keys=True)
                and json.dumps(self.restart, sort_keys=True) == json.dumps(other.restart, sort_keys=True)
                and json.dumps(self.switching, sort_keys=True) == json.dumps(other.switching, sort_keys=True)
                and json.dumps(self.action_names, sort_keys=True) == json.dumps(other.action_names, sort_keys=True)
                and (not wall_time or same(self.wall_time, other.wall_time)))

    @property
    def log_joint(self) -> np.ndarray:
        """(C, D) log joint density of every draw."""
        return self.stats["log_joint"]

    @property
    def superchains(self) -> np.ndarray:
        """(C,) the superchain of each chain: the chains that share a start (a chain restarted at
        warmup's end joins the superchain of the chain whose state it continued from; without
        restarts every chain is its own), named by the chain of it that kept its own state
        (:func:`npbrs.inference.analysis.diagnostics.superchain_ids`)."""
        return superchain_ids(self.restart, self.num_chains)

    @property
    def rhat(self) -> Dict[str, float]:
        """The R-hat of the label-invariant scalars the run is judged by: where chains share a
        start (:attr:`superchains`), the nested R-hat over the superchains
        (:func:`npbrs.inference.analysis.diagnostics.nested_rhat`; NaN for every scalar where
        every chain shares one start); otherwise ArviZ's rank-normalised split R-hat across
        chains (:attr:`rank_rhat`). NaN where undefined (a constant scalar, fewer than 4 draws)."""
        ids = self.superchains
        if shares_start(ids):
            return label_invariant_diagnostic(self.stats, "nested_rhat", ids)
        return label_invariant_diagnostic(self.stats, "rhat")

    @property
    def rank_rhat(self) -> Dict[str, float]:
        """Rank-normalised split R-hat (ArviZ) of the label-invariant scalars across chains, shared
        starts or not (the :attr:`rhat` of a run whose chains all kept their own starts); NaN
        where undefined (a constant scalar, fewer than 4 draws)."""
        return label_invariant_diagnostic(self.stats, "rhat")

    @property
    def ess(self) -> Dict[str, float]:
        """Bulk effective sample size (ArviZ) of the label-invariant scalars; NaN where undefined."""
        return label_invariant_diagnostic(self.stats, "ess")

    def convergence_warning(self, rhat: Optional[Dict[str, float]] = None,
                            ess: Optional[Dict[str, float]] = None,
                            rank_rhat: Optional[Dict[str, float]] = None) -> str:
        """What :func:`npbrs.inference.analysis.diagnostics.convergence_warning` says of this run
        ("" when it has converged); ``rhat``, ``ess``, ``rank_rhat``: the run's, where the
        caller has them."""
        return convergence_warning(self, rhat, ess, rank_rhat)

    def check_mdp(self, mdp) -> None:
        """Raise ValueError unless ``mdp`` is the MDP the run was fitted in (when the run knows it)."""
        if self.mdp_fingerprint and hasattr(mdp, "fingerprint") and mdp.fingerprint() != self.mdp_fingerprint:
            raise ValueError(f"the run was fitted in another MDP than {getattr(mdp, 'name', 'this one')!r} (MDP "
                             f"fingerprint {self.mdp_fingerprint[:12]}..., this one {mdp.fingerprint()[:12]}...); "
                             "use policies(mdp) to carry the skills' rewards into a changed world")

    def policies(self, mdp, *, greedy: bool = False, rewards: str = "mean", emission=None) -> np.ndarray:
        """The found skills' policies in ``mdp``: the MDP of the fit, or a changed one with the
        same reward features (transfer: the inferred rewards are solved again there).

        Args:
            mdp: a TabularMDP.
            greedy: the optimal action of each skill's reward in every state, (K, S) int,
                instead of the Boltzmann action probabilities the model assigns the skill
                (temperature and epsilon included), (K, S, A). For control, acting in a
                (changed) world, use ``greedy=True``: the Boltzmann policies describe how the
                demonstrator acted, noise included, and act worse than the optimal ones.
            rewards: "mean" (default): each skill's posterior mean parameters over the draws,
                chains matched to the run's skills. Rewards are linear in their weights, so
                the optimal policy of the posterior mean reward is the policy with the highest
                posterior expected return; a single draw's weights carry that draw's noise
                along directions the demonstrations leave open, which a changed world can
                expose. "best": the best draw's (``skill_params``).
            emission: the emission instance, for a run fitted with one.
        Raises:
            ValueError: ``mdp`` has other reward features than the run (or, for an emission
                without rewards, another number of states or actions).
        """
        from ..analysis.skills import skill_policies

        return skill_policies(self, mdp, greedy=greedy, rewards=rewards, emission=emission)

    def options(self, mdp, demos=None, *, prior_strength: float = 2.0, rewards: str = "mean", emission=None):
        """The found skills as options (initiation set, termination probability per state,
        Boltzmann and greedy policy), estimated from the run's best segmentation of its
        demonstrations, or from the most probable skills of ``demos`` (:meth:`segment`); see
        :mod:`npbrs.domains.options` for how; the policies are those of :meth:`policies` with
        ``rewards``. A run with state-dependent ends (``switching="state"``) gives each option
        the posterior mean of its skill's ends instead of the counts' estimate. Returns a list of
        :class:`~npbrs.domains.options.Option`, one per skill, in the order of ``segmentation``."""
        from ..analysis.skills import skill_options

        return skill_options(self, mdp, demos, prior_strength=prior_strength, rewards=rewards, emission=emission)

    def log_predictive(self, mdp, demos, **options):
        """The held-out log-likelihood of demonstrations that were not in the fit: per
        trajectory and per step, with Monte Carlo standard errors (a
        :class:`~npbrs.inference.analysis.predictive.HeldOut`; options: ``num_samples``, ``num_draws``,
        ``seed``, ``emission``; see :func:`npbrs.inference.analysis.predictive.log_predictive`)."""
        from ..analysis.predictive import log_predictive

        return log_predictive(self, mdp, demos, **options)

    def skill_probabilities(self):
        """Each fitted step's posterior skill probabilities counted over the sampler's own draws
        (:func:`npbrs.inference.analysis.predictive.skill_probabilities`)."""
        from ..analysis.predictive import skill_probabilities

        return skill_probabilities(self)

    def segment(self, mdp, demos=None, **options):
        """Posterior probabilities of this run's skills at every step of new demonstrations (or,
        with ``demos=None``, of the fitted ones), averaged over the draws: a
        :class:`~npbrs.inference.analysis.predictive.SkillProbabilities` (``probs`` per trajectory (T, L),
        ``labels`` the most probable skill); options ``num_samples``, ``num_draws``, ``seed``,
        ``emission`` (see :func:`npbrs.inference.analysis.predictive.segment`)."""
        from ..analysis.predictive import segment

        return segment(self, mdp, demos, **options)

    def add_log_likelihood(self, mdp, **options) -> np.ndarray:
        """Compute and keep :attr:`log_likelihood` (C, D, N), so that ``az.loo(result.to_arviz())``
        and ``az.compare`` work (options: ``num_samples``, ``seed``, ``emission``; see
        :func:`npbrs.inference.analysis.predictive.pointwise_log_likelihood`). Returns it.
        It costs about as much as the fit: a forward pass per draw, trajectory and Monte Carlo
        sample (``num_samples``), every draw of every chain."""
        from ..analysis.predictive import pointwise_log_likelihood

        self.log_likelihood = pointwise_log_likelihood(self, mdp, **options)
        return self.log_likelihood

    def to_arviz(self):
        """ArviZ InferenceData: draws, label-invariant sample stats, the best segmentation and
        the run's description (the layout of saved runs: see the module docstring).

        The groups of the sampling draws (``posterior``, ``sample_stats``, ``log_likelihood``)
        carry a coordinate ``superchain`` along ``chain``: each chain's superchain
        (:attr:`superchains`), the chains that share a start because a restart at warmup's end
        moved some onto another's state (without restarts, each chain its own). Group by it
        with xarray (``idata.posterior["log_joint"].groupby("superchain").mean()``) or compute the
        nested R-hat the run is judged by with
        ``npbrs.inference.analysis.diagnostics.nested_rhat(idata.posterior["log_joint"].values,
        idata.posterior["superchain"].values)``; ArviZ's own ``az.rhat`` compares chains and does
        not read it. (``warmup_sample_stats`` has none: the chains' warmups started apart.)"""
        import xarray as xr

        from ..arviz_import import arviz

        az = arviz()
        C, D = np.shape(self.stats["log_joint"])
        chain_draw = {"chain": np.arange(C), "draw": np.arange(D), "superchain": ("chain", self.superchains)}
        sites = set(self.skill_params)
        posterior = {name: (["chain", "draw"] + _site_dims(name, v.shape[2:], sites), np.asarray(v))
                     for name, v in self.samples.items()}
        for name in LABEL_INVARIANT:
            posterior[name] = (["chain", "draw"], np.asarray(self.stats[name]))
        sample_stats = {"lp": (["chain", "draw"], np.asarray(self.stats["log_joint"]))}
        sample_stats.update({k: (["chain", "draw"], np.asarray(v)) for k, v in self.stats.items()})
        constant = {"segmentation": (["trajectory", "step"], _padded(self.segmentation)),
                    "lengths": (["trajectory"], np.array([len(s) for s in self.segmentation], np.int64)),
                    "skill_slots": (["skill"], np.asarray(self.skill_slots, np.int64))}
        for name, v in self.skill_params.items():
            v = np.asarray(v)
            constant["best_" + name] = (["skill"] + [f"{name}_dim_{i}" for i in range(v.ndim - 1)], v)
        if self.init_segmentation is not None:
            constant["init_segmentation"] = (["trajectory", "step"], _padded(self.init_segmentation))
        if self.chain_best_z is not None:
            constant["chain_best_z"] = (["chain", "trajectory", "step"], np.asarray(self.chain_best_z, np.int64))
        if self.step_skill_counts is not None:
            constant[STEP_COUNTS] = (["chain", "trajectory", "step", "slot"], np.asarray(self.step_skill_counts, np.int32))
        attrs = {"npbrs_format": RUN_FORMAT, "npbrs_version": RUN_VERSION,
                 "config": json.dumps(self.config, sort_keys=True),
                 "emission": json.dumps(self.emission, sort_keys=True),
                 "fingerprint": self.fingerprint, "feature_names": json.dumps(list(self.feature_names)),
                 "best_chain": int(self.best_chain), "best_log_joint": float(self.best_log_joint),
                 "wall_time": float(self.wall_time), "mdp_fingerprint": str(self.mdp_fingerprint or "")}
        if self.run_length is not None:
            attrs["run_length"] = json.dumps(self.run_length, sort_keys=True)
        if self.truncation is not None:
            attrs["truncation"] = json.dumps(self.truncation, sort_keys=True)
        if self.restart is not None:
            attrs["restart"] = json.dumps(self.restart, sort_keys=True)
        if self.switching is not None:
            attrs["switching"] = json.dumps(self.switching, sort_keys=True)
        if self.action_names is not None:
            attrs["action_names"] = json.dumps(self.action_names, sort_keys=True)
        groups = {"posterior": xr.Dataset(posterior, coords=chain_draw),
                  "sample_stats": xr.Dataset(sample_stats, coords=chain_draw),
                  "constant_data": xr.Dataset(constant, attrs=attrs)}
        if self.demos is not None:
            demos = self.demos
            observed = {"states": (["trajectory", "step"], _padded(demos.states)),
                        "actions": (["trajectory", "step"], _padded(demos.actions)),
                        "lengths": (["trajectory"], demos.lengths)}
            if demos.skills is not None:
                observed["skills"] = (["trajectory", "step"], _padded(demos.skills))
            groups["observed_data"] = xr.Dataset(observed, attrs={"mdp_fingerprint": demos.mdp_fingerprint or ""})
        if self.warmup_stats:
            W = next(iter(self.warmup_stats.values())).shape[1]
            groups["warmup_sample_stats"] = xr.Dataset(
                {k: (["chain", "draw"], np.asarray(v)) for k, v in self.warmup_stats.items()},
                coords={"chain": chain_draw["chain"], "draw": np.arange(W)})
        if self.log_likelihood is not None:
            groups["log_likelihood"] = xr.Dataset(
                {"demonstrations": (["chain", "draw", "trajectory"], np.asarray(self.log_likelihood))},
                coords=chain_draw)
        return az.InferenceData(**groups)

    @classmethod
    def from_arviz(cls, idata) -> "FitResult":
        """The result stored in an ``InferenceData`` written by :meth:`to_arviz`; ValueError
        when it is not one."""
        from npbrs.domains.demos import Demonstrations

        if "constant_data" not in idata.groups() or idata.constant_data.attrs.get("npbrs_format") != RUN_FORMAT:
            raise ValueError("not an npbrs run (no constant_data group with npbrs_format = 'npbrs-run')")
        const = idata.constant_data
        attrs = const.attrs
        if int(attrs["npbrs_version"]) > RUN_VERSION:
            raise ValueError(f"run format version {attrs['npbrs_version']} is newer than this npbrs reads "
                             f"({RUN_VERSION})")
        lengths = np.asarray(const["lengths"].values)
        seg = np.asarray(const["segmentation"].values)
        segmentation = trajectory_rows(seg, lengths)
        skill_params = {name[5:]: np.asarray(const[name].values) for name in const.data_vars
                        if name.startswith("best_")}
        samples = {name: np.asarray(v.values) for name, v in idata.posterior.data_vars.items()
                   if name not in LABEL_INVARIANT}
        stats = {name: np.asarray(v.values) for name, v in idata.sample_stats.data_vars.items() if name != "lp"}
        demos = None
        if "observed_data" in idata.groups():
            obs = idata.observed_data
            n = np.asarray(obs["lengths"].values)
            cols = {k: [np.asarray(obs[k].values)[i, :m] for i, m in enumerate(n)]
                    for k in ("states", "actions", "skills") if k in obs.data_vars}
            demos = Demonstrations(**cols, mdp_fingerprint=str(obs.attrs.get("mdp_fingerprint", "")) or None)
        return cls(segmentation=segmentation, num_skills=len(const["skill_slots"]), skill_params=skill_params,
                   skill_slots=np.asarray(const["skill_slots"].values), best_chain=int(attrs["best_chain"]),
                   best_log_joint=float(attrs["best_log_joint"]), stats=stats, samples=samples,
                   config=json.loads(attrs["config"]), fingerprint=str(attrs["fingerprint"]),
                   wall_time=float(attrs["wall_time"]), emission=json.loads(attrs["emission"]),
                   feature_names=tuple(json.loads(attrs["feature_names"])),
                   chain_best_z=(np.asarray(const["chain_best_z"].values) if "chain_best_z" in const else None),
                   demos=demos, init_segmentation=(trajectory_rows(const["init_segmentation"].values, lengths)
                                                   if "init_segmentation" in const else None),
                   log_likelihood=(np.asarray(idata.log_likelihood["demonstrations"].values)
                                   if "log_likelihood" in idata.groups() else None),
                   mdp_fingerprint=str(attrs.get("mdp_fingerprint", "")),
                   warmup_stats=({k: np.asarray(v.values) for k, v in idata.warmup_sample_stats.data_vars.items()}
                                 if "warmup_sample_stats" in idata.groups() else None),
                   run_length=json.loads(attrs["run_length"]) if "run_length" in attrs else None,
                   truncation=json.loads(attrs["truncation"]) if "truncation" in attrs else None,
                   restart=json.loads(attrs["restart"]) if "restart" in attrs else None,
                   switching=json.loads(attrs["switching"]) if "switching" in attrs else None,
                   action_names=json.loads(attrs["action_names"]) if "action_names" in attrs else None,
                   step_skill_counts=np.asarray(const[STEP_COUNTS].values) if STEP_COUNTS in const else None)

    def summary(self) -> str:
        """A short text summary: skills, segment lengths, how the run went, diagnostics
        (:func:`npbrs.inference.analysis.diagnostics.summary`)."""
        return summary(self)

float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
