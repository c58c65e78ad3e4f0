"""Lines the commands print about a segmentation: the skills it uses, and its scores against the
true skills when they are known."""

from __future__ import annotations

__all__ = ["skills_used", "truth_scores"]


def skills_used(labels, num_skills: int, whose: str, listed: bool = True) -> str:
    """How many of a run's skills a segmentation uses, in words ("3 of the best draw's 4 skills
    (0, 1, 2; skill 3 is no step's most probable)"): what report and segment print and title
    their figures with.

    Args:
        labels: per-trajectory skill sequences.
        num_skills: how many skills there are.
        whose: whose skills they are ("the best draw's", "the run's").
        listed: whether to list the skills used (and those not).
    Returns:
        the words.
    """
    import numpy as np

    used = [int(k) for k in np.unique(np.concatenate([np.asarray(z, dtype=np.int64) for z in labels]))]
    text = f"{len(used)} of {whose} {num_skills} skill{'' if num_skills == 1 else 's'}"
    if not listed:
        return text
    rest = [k for k in range(num_skills) if k not in used]
    unused = f"; skill{'s' if len(rest) > 1 else ''} {', '.join(map(str, rest))} {'are' if len(rest) > 1 else 'is'} " \
             "no step's most probable" if rest else ""
    return f"{text} ({', '.join(map(str, used))}{unused})"


def truth_scores(true, labels, best=None) -> str:
    """A segmentation scored against the true skills, in words: the paper's accuracy (an inferred
    skill takes the true skill of more than half its steps), the one-to-one (Hungarian) accuracy
    and the switches per trajectory, the truth's too.

    Args:
        true: per-trajectory true skills.
        labels: per-trajectory inferred skills (the same lengths).
        best: optionally the best draw's segmentation, whose one-to-one accuracy is added.
    Returns:
        the line.
    """
    import numpy as np

    from ..analysis.metrics import hungarian_accuracy, num_switches, paper_accuracy

    count = len(np.unique(np.concatenate([np.asarray(z) for z in true])))
    than_best = "" if best is None else f"; the best draw's {hungarian_accuracy(true, best):.3f}"
    return (f"against the true skills ({count}): accuracy {paper_accuracy(true, labels):.3f} (paper's >50% "
            f"labelling), {hungarian_accuracy(true, labels):.3f} (one-to-one{than_best}); switches per trajectory "
            f"{num_switches(labels):.2f} (true {num_switches(true):.2f})")
