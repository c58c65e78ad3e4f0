"""Inference: the BP-HMM MCMC kernel and its moves, fit, results, diagnostics, metrics, CLI."""

from .metrics import (confusion, hungarian_accuracy, hungarian_labelling, num_skills, num_switches,
                      paper_accuracy, paper_labelling)
from .fit import device_mesh, fit, make_emission
from .results import FitResult
from .config import EmissionConfig, Hyperparameter, ModelConfig, PriorConfig, SamplerConfig
from .runs import load, load_mdp, save_mdp
from .diagnostics import convergence, relabel, skill_summary
from .predictive import HeldOut, SkillProbabilities, log_predictive
from .plots import plot_segmentation, plot_skill_rewards, plot_trace, skill_styles
