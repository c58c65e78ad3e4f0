"""Worlds and data: tabular MDPs and their Bellman solvers, the paper's highway and quadcopter
domains as gymnasium environments, experts, demonstrations and control evaluation."""

from .mdp import TabularMDP
from .solvers import (SolveResult, boltzmann_log_policy, greedy_policy, next_value_operator,
                      soft_value_iteration, value_iteration)
from .demos import Demonstrations, generate_demonstrations
from .registry import DOMAINS, get_domain, register_domain
