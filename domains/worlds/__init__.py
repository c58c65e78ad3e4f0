"""Worlds that look like what researchers bring: tabular state rewards, many trajectories, noisy
experts and skill switching that depends on where the agent is, with their generating model and
an oracle.

Four generators, each ``f(seed, **sizes) -> World`` (the same seed gives the same data):

- :func:`tabular_grid`: a small gridworld (5 x 5, actions up, down, left, right, stay) with a
  reward per state and 2-3 modes, each seeking its own corner region; 200 trajectories x 500
  steps; about 5% switching per step, and a mode tends to end once its goal region is reached
  (the switching probability there is ``goal_factor`` times what it is elsewhere), as in the
  published switching-IRL gridworld benchmark and in real behaviour.
- :func:`labyrinth`: a binary-tree labyrinth of depth 6 (63 junctions, 64 end nodes; actions
  left child, right child, back to the parent, stay), 200 trajectories of 15-25 steps from the
  entrance, skills explore, go to the water port and go home, whose ends depend on reaching the
  port or the entrance, as in the mouse labyrinth data.
- :func:`rooms`: the four-room gridworld with 5 goal-seeking skills; each trajectory uses its
  own 2 or 3 of them (the beta process's setting), sticky switching, ragged lengths.
- :func:`swirl_grid`: the kind of the published switching-IRL (SWIRL) gridworld: 5 x 5, 2 modes
  (water and home) whose rewards are on (previous cell, cell) pairs, ends that depend on the
  cell, 200 trajectories x 500 steps with about 25 switches each. Its MDP
  (:func:`pair_grid_mdp`) has the pairs as states (105 of them), so that a reward on pairs is a
  weight per state; the demonstrations' states are those pairs (:func:`cell_view`: the same data
  on the cells, with a reward per cell).

Every world uses one-hot state features (a reward weight per state: what a new user without
features has; in :func:`swirl_grid` a state is a pair of cells), and its experts act by the
Boltzmann policy of their skill's reward scaled by an inverse temperature,
pi_k(a | s) = exp(Q_k(s, a) - V_k(s)) with the soft Q-function of ``inverse_temperature * reward``
(the library's soft value iteration): exactly the reward emission's model, with weights
``domain.skill_weights``.

The generating model (:class:`SkillProcess`): a trajectory draws its skill set m (except in
:func:`rooms`, always all skills), its first state from ``mdp.initial``, its first skill from
``initial_skill[m]``; at step t the agent in state s_t with skill z_t acts a_t ~ pi_{z_t}(. | s_t)
and moves to s_{t+1} ~ P(. | s_t, a_t); then the skill of step t + 1 is drawn from
``transitions[m, s_{t+1}, z_t]``, which may depend on the state just entered. Trajectory lengths
are drawn independently of everything else.

The oracle (:meth:`World.oracle`): the generating model's held-out log-likelihood per step (the
actions given the states, the skill set and skill sequence summed out by the forward algorithm;
the state dynamics are the same under every model and drop out, as in
``FitResult.log_predictive``) and its Viterbi segmentation's accuracy on the training set; and
the same for the true policies under state-independent (sticky) switching, the BP-HMM's own
kind, which bounds what a fit of it can reach where the truth's switching depends on the state. It is
computed here in NumPy because the library's HMM routines (``npbrs.models.hmm``) take one
transition matrix per trajectory, not one per state, and ``domains`` imports nothing from
``models``.
"""

from .base import Oracle, SkillProcess, World
from .grid_world import grid_mdp, tabular_grid
from .labyrinth_world import labyrinth, labyrinth_mdp
from .rooms_world import rooms, rooms_mdp
from .swirl_world import cell_view, pair_grid_mdp, swirl_grid

__all__ = ["World", "SkillProcess", "Oracle", "tabular_grid", "labyrinth", "rooms", "swirl_grid", "grid_mdp",
           "labyrinth_mdp", "rooms_mdp", "pair_grid_mdp", "cell_view", "WORLDS"]

WORLDS = {"tabular_grid": tabular_grid, "labyrinth": labyrinth, "rooms": rooms, "swirl_grid": swirl_grid}
