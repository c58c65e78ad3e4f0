"""What a fit means: segmentation metrics, label-invariant diagnostics, held-out prediction, the skills' policies, plots."""

from .metrics import (confusion, hungarian_accuracy, hungarian_labelling, num_skills, num_switches, paper_accuracy,
                      paper_labelling)
from .diagnostics import convergence, relabel, relabelled_draws, skill_summary
from .predictive import (HeldOut, SkillProbabilities, log_predictive, pointwise_log_likelihood, segment,
                         skill_probabilities)
from .skills import skill_options, skill_parameters, skill_policies
from .plots import (plot_segmentation, plot_skill_probabilities, plot_skill_rewards, plot_trace, skill_styles,
                    true_styles)
