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
