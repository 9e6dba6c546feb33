"""Semantic metrics on a hand-made confusion matrix."""

from __future__ import annotations

import numpy as np
import pytest

from semantic_gs_slam.metrics import class_iou, confusion, miou


def test_class_iou_and_miou_by_hand():
    gt = np.array([1, 1, 1, 2, 2, 0, 3])
    pred = np.array([1, 1, 2, 2, 2, 3, 1])  # label 0 in the ground truth is ignored
    conf = confusion(pred, gt, 4)
    ious = class_iou(conf)
    # class 1: 2 right, 1 missed, 1 false (from class 3) -> 2/4; class 2: 2 right, 1 false -> 2/3; class 3: 0/1
    assert ious == pytest.approx({1: 0.5, 2: 2 / 3, 3: 0.0})
    assert miou(conf) == pytest.approx((0.5 + 2 / 3 + 0.0) / 3)
    assert np.isnan(miou(np.zeros((4, 4), np.int64)))
