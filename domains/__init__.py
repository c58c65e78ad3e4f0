"""Worlds and data: tabular MDPs and their Bellman solvers, the paper's highway and quadcopter
domains as gymnasium environments, experts, demonstrations and control evaluation."""

from .mdp import TabularMDP
from .solvers import (HardSolver, SoftSolver, SolveResult, boltzmann_log_policy, greedy_policy,
                      make_hard_solver, make_soft_solver, next_value_operator, soft_value_iteration,
                      value_iteration)
from .demos import Demonstrations, generate_demonstrations
from .registry import DOMAINS, get_domain, register_domain
from .highway import HighwayEnv, highway  # registers npbrs/Highway-v0
from .quadcopter import QuadcopterEnv, quadcopter  # registers npbrs/Quadcopter-v0
from .experts import policy_return, policy_values, q_learning
from .control import evaluate_control, expert_control, replay, skill_policies
from .options import Option, OptionRun, estimate_options, run_option
