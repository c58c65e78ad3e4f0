"""Inference: the BP-HMM MCMC kernel and its moves, fit, results, diagnostics, metrics, CLI."""

from .metrics import (confusion, hungarian_accuracy, hungarian_labelling, num_skills, num_switches,
                      paper_accuracy, paper_labelling)
from .fit import fit, make_emission
from .results import FitResult
