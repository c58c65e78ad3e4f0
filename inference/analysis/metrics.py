"""Segmentation metrics: how well inferred skill sequences agree with the true ones.

Every function takes skill sequences as a list of 1-D integer arrays (one per trajectory),
or as padded (N, T) arrays with a boolean ``mask`` of real steps. Labels are non-negative
integers; inferred labels are arbitrary, so agreement is measured after a labelling:

- the paper's (section IV): an inferred skill takes a true skill's label when more than 50%
  of its steps fall in that true skill, otherwise it is unmatched (shown grey, and wrong);
- one-to-one (Hungarian) matching that maximises the number of agreeing steps.
"""

from __future__ import annotations

from typing import Dict, List, Optional, Tuple

import numpy as np
from scipy.optimize import linear_sum_assignment

__all__ = ["confusion", "paper_labelling", "paper_accuracy", "hungarian_labelling", "hungarian_accuracy",
           "num_switches", "num_skills"]


def _sequences(seqs, mask=None, what: str = "labels") -> List[np.ndarray]:
    """Per-trajectory 1-D int64 arrays of the real steps."""
    if mask is not None:
        seqs, mask = np.asarray(seqs), np.asarray(mask, dtype=bool)
        if seqs.shape != mask.shape or seqs.ndim != 2:
            raise ValueError(f"{what} of shape {seqs.shape} and mask of shape {mask.shape} must be equal (N, T)")
        seqs = [row[m] for row, m in zip(seqs, mask)]
    out = []
    for i, seq in enumerate(seqs):
        arr = np.asarray(seq)
        if arr.ndim != 1:
            raise ValueError(f"trajectory {i}: {what} must be a 1-D sequence, got shape {arr.shape}")
        if arr.size and arr.dtype.kind not in "iu":
            if arr.dtype.kind != "f" or np.any(arr != np.round(arr)):
                raise ValueError(f"trajectory {i}: {what} must be integers, got {arr.dtype}")
        arr = arr.astype(np.int64)
        if np.any(arr < 0):
            t = int(np.argmax(arr < 0))
            raise ValueError(f"trajectory {i}, step {t}: label {arr[t]} in {what} is negative (pass a mask for padding)")
        out.append(arr)
    return out


def _paired(true, inferred, mask) -> Tuple[np.ndarray, np.ndarray]:
    true = _sequences(true, mask, "true labels")
    inferred = _sequences(inferred, mask, "inferred labels")
    if len(true) != len(inferred):
        raise ValueError(f"{len(true)} true trajectories but {len(inferred)} inferred trajectories")
    for i, (a, b) in enumerate(zip(true, inferred)):
        if len(a) != len(b):
            raise ValueError(f"trajectory {i}: {len(a)} true labels but {len(b)} inferred labels")
    if not true or sum(len(a) for a in true) == 0:
        raise ValueError("no steps to compare")
    return np.concatenate(true), np.concatenate(inferred)


def confusion(true, inferred, mask=None, num_true: Optional[int] = None,
              num_inferred: Optional[int] = None) -> np.ndarray:
    """Step counts of every (true, inferred) pair of labels.

    Args:
        true, inferred: per-trajectory label sequences (or (N, T) arrays with ``mask``).
        mask: optional (N, T) bool, real steps.
        num_true, num_inferred: matrix sizes (default: the largest label present + 1).
    Returns:
        (num_true, num_inferred) int64 matrix C, C[i, j] = steps with true label i, inferred j.
    """
    t, z = _paired(true, inferred, mask)
    num_true = int(t.max()) + 1 if num_true is None else int(num_true)
    num_inferred = int(z.max()) + 1 if num_inferred is None else int(num_inferred)
    if t.max() >= num_true or z.max() >= num_inferred:
        raise ValueError(f"labels reach {t.max()} (true) and {z.max()} (inferred), beyond the requested "
                         f"{num_true} x {num_inferred} matrix")
    C = np.zeros((num_true, num_inferred), dtype=np.int64)
    np.add.at(C, (t, z), 1)
    return C


def _paper_labelling(C: np.ndarray) -> Dict[int, Optional[int]]:
    labelling = {}
    for j in np.flatnonzero(C.sum(0)):
        i = int(np.argmax(C[:, j]))
        labelling[int(j)] = i if 2 * C[i, j] > C[:, j].sum() else None
    return labelling


def _hungarian_labelling(C: np.ndarray) -> Dict[int, Optional[int]]:
    present_true, present_inferred = np.flatnonzero(C.sum(1)), np.flatnonzero(C.sum(0))
    rows, cols = linear_sum_assignment(C[np.ix_(present_true, present_inferred)], maximize=True)
    matched = {int(present_inferred[c]): int(present_true[r]) for r, c in zip(rows, cols)}
    return {int(j): matched.get(int(j)) for j in present_inferred}


def _accuracy(C: np.ndarray, labelling: Dict[int, Optional[int]]) -> float:
    agree = sum(int(C[i, j]) for j, i in labelling.items() if i is not None)
    return agree / int(C.sum())


def paper_labelling(true, inferred, mask=None) -> Dict[int, Optional[int]]:
    """The paper's labelling: inferred label -> the true label holding more than half of its
    steps, or None (unmatched). Keys are the inferred labels present, in order."""
    return _paper_labelling(confusion(true, inferred, mask))


def paper_accuracy(true, inferred, mask=None) -> float:
    """Fraction of steps whose inferred label, under :func:`paper_labelling`, is the true one
    (steps of unmatched skills count as wrong)."""
    C = confusion(true, inferred, mask)
    return _accuracy(C, _paper_labelling(C))


def hungarian_labelling(true, inferred, mask=None) -> Dict[int, Optional[int]]:
    """One-to-one labelling maximising the number of agreeing steps: inferred label -> true
    label, or None for inferred labels left over when there are more of them than true ones.
    Keys are the inferred labels present, in order."""
    return _hungarian_labelling(confusion(true, inferred, mask))


def hungarian_accuracy(true, inferred, mask=None) -> float:
    """Fraction of steps that agree under :func:`hungarian_labelling`."""
    C = confusion(true, inferred, mask)
    return _accuracy(C, _hungarian_labelling(C))


def num_switches(seqs, mask=None) -> float:
    """Mean number of label changes between consecutive steps, per trajectory."""
    seqs = _sequences(seqs, mask)
    if not seqs:
        raise ValueError("no trajectories")
    return float(np.mean([np.count_nonzero(np.diff(s)) for s in seqs]))


def num_skills(seqs, mask=None) -> int:
    """Number of distinct labels used across all trajectories."""
    seqs = _sequences(seqs, mask)
    return int(np.unique(np.concatenate(seqs)).size) if seqs else 0
