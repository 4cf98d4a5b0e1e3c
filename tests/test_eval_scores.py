"""BOP greedy matching, recall and AR (pixie.eval.scores) against hand-computed cases."""

from __future__ import annotations

import numpy as np
import pytest

from pixie.eval import pose_error as errors
from pixie.eval import scores as M


# ---------------------------------------------------------------------------- matching, recall


def test_count_matches_greedy_bop_rules():
    # Two estimates (sorted by score) and two GT instances.
    err = np.array([[1.0, 2.0], [1.5, 9.0]])
    valid = np.array([True, True])
    # th 3: est0 takes gt0 (smaller error), est1 then can only take gt1 with 9 -> no.
    # th 10: est1 takes gt1.  th 1.2: only est0/gt0.  th 0.5: nothing. Strictly below.
    np.testing.assert_array_equal(M.count_matches(err, valid, [0.5, 1.0, 1.2, 3.0, 10.0]), [0, 0, 1, 1, 2])
    # An invalid GT cannot be matched.
    np.testing.assert_array_equal(M.count_matches(err, np.array([False, True]), [3.0, 10.0]), [1, 1])
    # A GT is not consumed by an estimate above the threshold.
    err2 = np.array([[5.0], [1.0]])
    np.testing.assert_array_equal(M.count_matches(err2, np.array([True]), [2.0]), [1])
    assert M.count_matches(np.zeros((0, 1)), np.array([True]), [1.0]).tolist() == [0]


def test_recall_and_average_recall():
    e = np.array([0.01, 0.12, 0.26, np.inf])
    r = M.recall_at(e, errors.MSSD_THRESHOLDS)
    np.testing.assert_allclose(r, [0.25, 0.25, 0.5, 0.5, 0.5, 0.75, 0.75, 0.75, 0.75, 0.75])
    assert M.average_recall(r) == pytest.approx(0.575)
    np.testing.assert_allclose(M.mspd_thresholds(1280), np.arange(10, 101, 10))
