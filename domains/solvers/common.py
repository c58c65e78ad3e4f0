"""What the soft and hard solvers share: the result of a solve, the checks of their inputs at the
Python boundary, and how a batch of systems is solved together (flattened to K systems, with a
``vmap``'s axis folded in, through one compiled program per solver kind and shapes)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..util.compiling import jit
from ..util.precision import float64_all

__all__ = ["SolveResult", "check_rewards"]


class SolveResult(NamedTuple):
    """Values of a Bellman solve.

    V: (..., S) state values. Q: (..., S, A) action values, with V = logsumexp_a Q (soft) or
    max_a Q (hard) exactly. num_iter: (...,) Newton / policy-iteration steps or sweeps used.
    residual: (...,) max-norm Bellman residual of the last iterate relative to max(1, max |V|).
    num_matvec: (...,) expected-next-value applications spent inside Krylov solves (0 for
    value iteration).
    """

    V: jax.Array
    Q: jax.Array
    num_iter: jax.Array
    residual: jax.Array
    num_matvec: jax.Array = 0


def _relative(diff, V):
    """Max-norm of diff relative to max(1, max |V|), per system: (K, S) -> (K,)."""
    return jnp.max(jnp.abs(diff), axis=-1) / jnp.maximum(1.0, jnp.max(jnp.abs(V), axis=-1))


# ------------------------------------------------------------------- input checking
def check_rewards(mdp, rewards, name: str = "rewards") -> np.ndarray:
    """Validate a reward table (..., S, A) at the Python boundary: shape and finiteness."""
    r = np.asarray(rewards, dtype=np.float64)
    S, A = mdp.num_states, mdp.num_actions
    if r.ndim < 2 or r.shape[-2:] != (S, A):
        raise ValueError(f"{name} must have shape (..., {S}, {A}) = (..., states, actions), got {r.shape}")
    bad = ~np.isfinite(r)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        lead, (s, a) = idx[:-2], idx[-2:]
        where = f"table {lead[0] if len(lead) == 1 else lead}, " if lead else ""
        raise ValueError(f"{name}: {where}state {s}, action {a} is not finite ({r[idx]})")
    return r


def _check_v0(v0, batch, S):
    v = np.asarray(v0, dtype=np.float64)
    if v.shape != tuple(batch) + (S,):
        raise ValueError(f"v0 must have shape {tuple(batch) + (S,)} to match the rewards, got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("v0 (the warm start) has non-finite values")
    return v


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _check_options(tol, max_iter, krylov_dim, max_restarts, degree):
    if int(degree) < 1:
        raise ValueError(f"precondition_degree must be >= 1, got {degree}")
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be positive, got {tol}")
    if int(max_iter) < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter}")
    if int(krylov_dim) < 1 or int(max_restarts) < 1:
        raise ValueError(f"krylov_dim and max_restarts must be >= 1, got {krylov_dim}, {max_restarts}")


# ------------------------------------------------------------- vmap folded into the batch
def fold_vmap(fn):
    """``fn(op, *arrays)``, every array (leaves of pytrees) and every output with a leading axis of
    K systems solved in lock-step, made to fold a ``vmap``'s mapped axis into that axis: under
    ``vmap`` (n-way) it runs once on n * K systems instead of being batched loop by loop.

    JAX batches a ``while_loop`` whose condition depends on the mapped values by running it until
    every member is done and masking each step's carry with a select; nested in the solver's
    Newton, GMRES and L-BFGS loops that doubles the work of a solve and grows the compiled
    program. The solver already solves its K systems together, so a vmapped call (the sampler's
    chains, a Jacobian's tangents) is simply more systems. The numbers can differ from a
    one-by-one solve in the last bits: a system that converged keeps iterating until the batch
    has (each iterate is a fixed point to the tolerance). An operator ``op`` (a pytree) that is
    itself mapped (dynamics that differ between members) is vmapped as usual."""

    def call(op, *args):
        leaves, treedef = jax.tree.flatten(op)  # (the operator's arrays, passed as leaves)
        unflat = lambda ls, *a: fn(jax.tree.unflatten(treedef, ls), *a)  # noqa: E731
        folded = jax.custom_batching.custom_vmap(unflat)

        @folded.def_vmap
        def rule(axis_size, in_batched, ls, *a):
            if any(in_batched[0]):
                in_axes = tuple(jax.tree.map(lambda b: 0 if b else None, ib) for ib in in_batched)
                out = jax.vmap(unflat, in_axes=in_axes)(ls, *a)
                return out, jax.tree.map(lambda _: True, out)

            def fold(x, batched):
                x = x if batched else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x))
                return x.reshape((axis_size * x.shape[1],) + x.shape[2:])

            # (through ``folded`` again, so that an enclosing vmap folds its axis in too)
            out = folded(ls, *[jax.tree.map(fold, x, b) for x, b in zip(a, in_batched[1:])])
            out = jax.tree.map(lambda x: x.reshape((axis_size, x.shape[0] // axis_size) + x.shape[1:]), out)
            return out, jax.tree.map(lambda _: True, out)

        return folded(leaves, *args)

    return call


# ------------------------------------------------------------------- the compiled batch
@jit
def _solve_batch(solver, r, v0):
    """A solver's ``_solve_batch``, compiled per solver kind, options and shapes (the solver's
    arrays are arguments: another MDP of the same shapes reuses the program)."""
    return solver._solve_batch(r, v0)


def _call_flat(solver, r, v0, S, A):
    """Call the solver's compiled solve on K = prod(batch) systems and restore the batch shape,
    so that every batch shape with the same number of systems shares one compiled program."""
    batch = r.shape[:-2]
    K = int(np.prod(batch, dtype=int))
    res = _solve_batch(solver, r.reshape(K, S, A), None if v0 is None else v0.reshape(K, S))
    return SolveResult(res.V.reshape(batch + (S,)), res.Q.reshape(batch + (S, A)), res.num_iter.reshape(batch),
                       res.residual.reshape(batch), res.num_matvec.reshape(batch))


def _flattened(core, r, v0, S, A):
    """Run a batched core on r (..., S, A) and v0 (..., S) or None, flattened to K systems."""
    batch = r.shape[:-2]
    K = int(np.prod(batch, dtype=int))
    v = jnp.zeros((K, S), r.dtype) if v0 is None else v0.reshape(K, S)
    V, Q, it, res, nmv = core(r.reshape(K, S, A), v)
    return SolveResult(V.reshape(batch + (S,)), Q.reshape(batch + (S, A)), it.reshape(batch), res.reshape(batch),
                       nmv.reshape(batch))


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
