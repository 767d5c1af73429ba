"""Eq. 9, 12 and 17 utilities, per-node PRR and Jain's index against hand values."""

import numpy as np
import pytest

from cv2x_marl.utility import jain_fairness, normalised_gain, per_node_prr, utility_log, utility_sum


def test_utilities_hand_values() -> None:
    p = np.array([[0.5, 0.25, 0.0, 0.9]])
    mask = np.array([[True, True, True, False]])
    assert utility_sum(p, mask)[0] == pytest.approx(0.75)
    # log(0.5) + log(0.25) + log(p_min = 1e-3)
    assert utility_log(p, mask)[0] == pytest.approx(np.log(0.5) + np.log(0.25) + np.log(1e-3))
    assert utility_log(p, mask, p_min=0.1)[0] == pytest.approx(np.log(0.5) + np.log(0.25) + np.log(0.1))
    assert per_node_prr(p, mask)[0] == pytest.approx(0.25)


def test_normalised_gain_eq17() -> None:
    assert normalised_gain(-8.0, -10.0) == pytest.approx(0.2)  # utility rose from -10 to -8: +20 %
    assert normalised_gain(0.6, 0.5) == pytest.approx(0.2)
    assert np.isnan(normalised_gain(1.0, 0.0))


def test_jain() -> None:
    assert jain_fairness([1.0, 1.0, 1.0, 1.0]) == pytest.approx(1.0)
    assert jain_fairness([1.0, 0.0, 0.0, 0.0]) == pytest.approx(0.25)
    assert jain_fairness([1.0, 2.0]) == pytest.approx(9 / 10)
