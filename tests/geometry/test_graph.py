"""Connected components shared by the back end and the saved-map code (hand-worked cases)."""

import numpy as np

from rgbdslam.geometry.graph import components


def test_components_hand_worked():
    # 0-1-2 joined, 3 alone, 4-5 joined (given in reverse), 6 alone
    lab = components(7, [(2, 1), (0, 1), (5, 4)])
    assert lab.tolist() == [0, 0, 0, 1, 2, 2, 3]


def test_components_numbered_by_lowest_node():
    # the component of node 0 is met last by edge order; still label 0
    lab = components(4, [(3, 2), (1, 0)])
    assert lab.tolist() == [0, 0, 1, 1]


def test_components_empty_and_no_edges():
    assert components(0, []).tolist() == []
    assert components(3, []).tolist() == [0, 1, 2]
    assert np.asarray(components(2, [(0, 0)])).tolist() == [0, 1]
