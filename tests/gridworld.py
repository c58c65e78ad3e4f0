"""A small gridworld with three corner-seeking reward skills, for tests of the sampler."""

import numpy as np

from npbrs.domains import TabularMDP
from npbrs.domains.domain import Domain

MOVES = [(-1, 0), (1, 0), (0, -1), (0, 1), (0, 0)]  # up, down, left, right, stay


def gridworld(size=4, slip=0.1, discount=0.9):
    """A size x size grid; moves slip to a uniformly random move with probability ``slip``.
    Features: being next in each of three corners (expected over the slip)."""
    S, A = size * size, len(MOVES)
    P = np.zeros((S, A, S))
    for r in range(size):
        for c in range(size):
            s = r * size + c
            for a in range(A):
                for b, (dr, dc) in enumerate(MOVES):
                    p = (1 - slip) * (a == b) + slip / A
                    r2, c2 = min(max(r + dr, 0), size - 1), min(max(c + dc, 0), size - 1)
                    P[s, a, r2 * size + c2] += p
    corners = [0, size - 1, S - 1]
    state_features = np.zeros((S, 3))
    for j, s in enumerate(corners):
        state_features[s, j] = 1.0
    features = np.einsum("sat,td->sad", P, state_features)
    mdp = TabularMDP.from_dense(P, features=features, feature_names=("top_left", "top_right", "bottom_right"),
                                discount=discount, name="gridworld",
                                state_vectors=np.array([[s // size, s % size] for s in range(S)], float))
    weights = 5.0 * np.eye(3)
    return Domain(name="gridworld", mdp=mdp, skill_names=("TL", "TR", "BR"), skill_weights=weights)


def ragged_policy_problem(seed=0, N=6, T=30, S=4, A=3, correct=0.9):
    """A random S-state MDP and N ragged demonstrations (lengths T, T - 3, T - 6, ...) of three
    skills in blocks of 10 steps, each acting "its" action with probability ``correct``
    (uniformly otherwise): a small problem for the policy emission's fits."""
    from npbrs.domains import Demonstrations

    rng = np.random.default_rng(seed)
    mdp = TabularMDP.from_dense(rng.dirichlet(np.ones(S), (S, A)))
    skills = [(np.arange(T - 3 * (i % 3)) // 10 + i) % 3 for i in range(N)]  # ragged
    actions = [np.where(rng.random(len(k)) < correct, k, rng.integers(0, A, len(k))) for k in skills]
    return mdp, Demonstrations([rng.integers(0, S, len(k)) for k in skills], actions, skills)
