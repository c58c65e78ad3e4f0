import numpy as np
import pytest

from npbrs.inference import (confusion, hungarian_accuracy, hungarian_labelling, num_skills, num_switches, paper_accuracy,
                             paper_labelling)

TRUE = [np.array([0, 0, 0, 0, 1, 1, 1, 1]), np.array([2, 2, 2, 2, 2, 0, 0, 0])]


def test_a_permuted_perfect_segmentation_scores_one():
    inferred = [np.array([5, 5, 5, 5, 3, 3, 3, 3]), np.array([1, 1, 1, 1, 1, 5, 5, 5])]
    assert paper_labelling(TRUE, inferred) == {1: 2, 3: 1, 5: 0}
    assert hungarian_labelling(TRUE, inferred) == {1: 2, 3: 1, 5: 0}
    assert paper_accuracy(TRUE, inferred) == 1.0
    assert hungarian_accuracy(TRUE, inferred) == 1.0


def test_more_inferred_skills_than_true_ones():
    # true skill 0 is split into inferred 0 and 4: the paper's labelling maps both to 0,
    # one-to-one matching can give it only one of them
    inferred = [np.array([0, 0, 4, 4, 1, 1, 1, 1]), np.array([2, 2, 2, 2, 2, 4, 4, 4])]
    assert paper_labelling(TRUE, inferred) == {0: 0, 1: 1, 2: 2, 4: 0}
    assert paper_accuracy(TRUE, inferred) == 1.0
    assert hungarian_labelling(TRUE, inferred) == {0: None, 1: 1, 2: 2, 4: 0}
    assert hungarian_accuracy(TRUE, inferred) == 14 / 16


def test_an_inferred_skill_without_a_majority_is_unmatched():
    # inferred 3 covers 2 steps of true 1 and 2 of true 2: exactly half is not a majority
    inferred = [np.array([0, 0, 0, 0, 1, 1, 3, 3]), np.array([3, 3, 2, 2, 2, 0, 0, 0])]
    assert paper_labelling(TRUE, inferred) == {0: 0, 1: 1, 2: 2, 3: None}
    assert paper_accuracy(TRUE, inferred) == 12 / 16
    # one-to-one: 0->0 (7), 1->1 (2), 2->2 (3) leaves 3 over; or 3->1 or 3->2 with the same total
    assert hungarian_accuracy(TRUE, inferred) == 12 / 16


def test_a_wrong_majority_label_counts_its_minority_as_wrong():
    true = [np.array([0, 0, 0, 1, 1, 1])]
    inferred = [np.array([0, 0, 0, 0, 0, 1])]  # 0 holds 3 of true 0 and 2 of true 1
    assert paper_labelling(true, inferred) == {0: 0, 1: 1}
    assert paper_accuracy(true, inferred) == 4 / 6
    assert hungarian_accuracy(true, inferred) == 4 / 6


def test_confusion_counts_pairs():
    inferred = [np.array([0, 0, 4, 4, 1, 1, 1, 1]), np.array([2, 2, 2, 2, 2, 4, 4, 4])]
    C = confusion(TRUE, inferred)
    assert C.shape == (3, 5)
    expected = np.zeros((3, 5), int)
    expected[0, 0], expected[0, 4], expected[1, 1], expected[2, 2] = 2, 5, 4, 5
    np.testing.assert_array_equal(C, expected)
    assert confusion(TRUE, inferred, num_true=4, num_inferred=8).shape == (4, 8)


def test_padded_arrays_with_a_mask_equal_the_ragged_lists():
    inferred = [np.array([0, 0, 4, 4, 1, 1, 1]), np.array([2, 2, 2, 0, 0])]
    true = [t[:len(z)] for t, z in zip(TRUE, inferred)]
    mask = np.array([[1] * 7 + [0], [1] * 5 + [0] * 3], bool)
    true_pad = np.array([np.r_[t, [-1] * (8 - len(t))] for t in true])
    inferred_pad = np.array([np.r_[z, [-1] * (8 - len(z))] for z in inferred])
    for metric in (paper_accuracy, hungarian_accuracy, paper_labelling, confusion):
        assert np.all(metric(true_pad, inferred_pad, mask) == metric(true, inferred))
    assert num_switches(inferred_pad, mask) == num_switches(inferred) == (2 + 1) / 2
    assert num_skills(inferred_pad, mask) == num_skills(inferred) == 4


def test_switches_and_skills():
    assert num_switches(TRUE) == 1.0
    assert num_switches([np.array([0, 1, 0, 1]), np.array([3, 3])]) == 1.5
    assert num_skills(TRUE) == 3


@pytest.mark.parametrize("true, inferred, message", [
    ([np.array([0, 1, 1])], [np.array([0, 1])], "trajectory 0: 3 true labels but 2 inferred"),
    ([np.array([0, 1]), np.array([1, 1])], [np.array([0, 1]), np.array([1, -1])], "trajectory 1, step 1"),
    ([np.array([0, 1])], [np.array([0, 0.5])], "trajectory 0"),
    ([np.array([0, 1])], [np.array([0, 1]), np.array([0, 1])], "1 true trajectories but 2 inferred"),
])
def test_bad_input_names_the_trajectory(true, inferred, message):
    with pytest.raises(ValueError, match=message):
        paper_accuracy(true, inferred)
