"""Inference: ``sampler`` (the BP-HMM kernel and its moves), ``driver`` (fit, configuration, results and their
files), ``analysis`` (metrics, diagnostics, prediction, skills, plots) and ``cli`` (the npbrs command)."""

from .analysis.metrics import (confusion, hungarian_accuracy, hungarian_labelling, num_skills, num_switches,
                               paper_accuracy, paper_labelling)
from npbrs.models.emissions import make_emission
from .driver.fit import fit, resolve_config
from .driver.devices import device_mesh
from .driver.results import ConvergenceWarning, FitResult
from .driver.config import EmissionConfig, Hyperparameter, ModelConfig, PriorConfig, SamplerConfig
from .driver.runs import load, load_mdp, save_mdp
from .analysis.diagnostics import convergence, relabel, skill_summary
from .analysis.predictive import HeldOut, SkillProbabilities, log_predictive
from .analysis.plots import plot_segmentation, plot_skill_rewards, plot_trace, skill_styles
