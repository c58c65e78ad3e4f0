"""Bellman solvers on a :class:`~npbrs.domains.TabularMDP`: soft (maximum causal entropy)
and hard value iteration, in JAX, batched over reward tables, differentiable.

Soft:  Q(s, a) = r(s, a) + gamma * E[V(s') | s, a],  V(s) = logsumexp_a Q(s, a).
Hard:  the same with max in place of logsumexp.

How the soft fixed point is found (``method="newton"``, the default). Value iteration
contracts by gamma per sweep, so a relative tolerance of 1e-10 at gamma = 0.95 takes about 450
sweeps. Newton's method on F(V) = V - logsumexp(r + gamma E[V]) is soft policy iteration: the
Jacobian is I - gamma P_pi with pi = softmax(Q), and a Newton step evaluates the current
Boltzmann policy. It takes 5-7 steps from V = 0 and 2-3 from the previous solution after a
small change of the rewards. Each step's linear system is solved inexactly (Eisenstat-Walker
forcing terms) by restarted GMRES, right-preconditioned with a truncated Neumann series of
gamma P_pi: an iteration costs a couple of expected-next-value applications and no exp/log,
and the clustered spectrum of gamma P_pi (1, a few slow modes, the rest well inside the unit
disc) needs tens of them, not hundreds.

Derivatives are implicit: the fixed point's tangent solves (I - gamma P_pi) dV = sum_a pi dr
with the same GMRES (``jax.lax.custom_linear_solve``, whose transpose is the adjoint solve
(I - gamma P_pi)^T lambda = g for reverse mode), and dQ = dr + gamma E[dV]; no loop is
differentiated. Forward and reverse mode both work (so do Hessians, forward over reverse).

Batches. K reward tables are solved together in lock-step, with one shared loop counter and
each system frozen once it has converged (its result does not depend on the others). Pass a
batch rather than ``vmap`` a solver: under ``vmap`` every loop counter becomes per-system and
every basis update a scatter, about twice as slow.

Layout, for XLA on CPU: inside the loops a Q-table is a tuple of A arrays (K, S), not an
(K, S, A) array (element-wise work over separate columns fuses far better than small
reductions over a minor axis); successor gathers are unrolled over (action, slot), since a
reduction over a gathered axis compiles to code an order of magnitude slower. Where a state's
actions share successors (a gridworld's moves and slips reach the same few cells), a policy
evaluation first folds the policy onto each state's distinct successors (``Columns.policy``):
on an open gridworld that is 5 gathers per application instead of 15, and a solve at a million
states took 3.1-3.6 s instead of 5.6 s (``benchmarks/bench_scale.py``).

Precision. On large MDPs (``krylov_precision="auto"``: from 50,000 states) the Newton steps'
linear systems are solved in float32: a step only needs its solve to a relative 0.3 to 1e-5,
and the float64 iteration around it (values, backups, the residual that decides convergence)
reaches the same fixed point to the tolerance. Every application and orthogonalisation then
moves half the bytes: 4 tables at a million states took 1.5 s instead of 2.9 s, one table 0.67
s. Derivatives' solves run in float32 too, with one step of iterative refinement (the residual in
float64, its correction solved in float32 again: a relative 1e-5 of 1e-5): a log-likelihood's
gradient sums large terms that cancel near its optimum, and float32's 1e-5 alone left it wrong
by its own size there (an IRL fit's line search then failed step after step).

Transposes. A policy's transpose P_pi^T (the adjoint solve of a gradient) gathers over each
state's predecessors (:func:`predecessors`, precomputed with the fold) rather than scattering
along its successors: XLA's scatter-add on CPU made a transposed solve 3-5 times the forward
one (1.9 s against 0.34 s at 10^5 states, 4 tables, float64); it now costs the same.
"""

from .common import SolveResult, check_rewards, fold_vmap
from .operators import Columns, next_value_operator, predecessors, successor_union
from .soft import SoftSolver, make_soft_solver
from .hard import HardSolver, make_hard_solver
from .convenience import boltzmann_log_policy, greedy_policy, soft_value_iteration, value_iteration

__all__ = ["next_value_operator", "soft_value_iteration", "value_iteration", "SolveResult",
           "boltzmann_log_policy", "greedy_policy", "make_soft_solver", "make_hard_solver",
           "SoftSolver", "HardSolver", "check_rewards"]
