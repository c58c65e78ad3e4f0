"""Probability: HMM inference on arrays, emission models, and the BP-HMM NumPyro model."""

from .hmm import (batch_backward_sample, batch_forward_filter, batch_viterbi, backward_sample, forward_filter,
                  initial_counts, transition_counts, viterbi)
from .emissions import EMISSIONS, Emission, HMMData, PolicyEmission, get_emission_class, register_emission
from .bphmm import Hyper, bphmm_model
from .subgoal import SubgoalEmission, visited_states
from .autoregressive import AutoregressiveEmission
from .reward_emission import RewardEmission, SingleRewardEmission
from .reward import (PRIOR_SCALE, IRLFit, count_log_likelihood, count_log_likelihood_and_grad,
                     count_log_likelihood_and_values, count_table,
                     fisher_information, fit_reward, irl_fit, log_policy, log_posterior, log_prior, step_log_likelihoods)
from . import mcmc, reward_mala  # reward_mala.init / reward_mala.build_kernel: the reward move
from .reward_mala import RewardMALAInfo, RewardMALAState
