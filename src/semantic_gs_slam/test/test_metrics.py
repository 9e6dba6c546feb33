"""Semantic metrics on a hand-made confusion matrix."""

from __future__ import annotations

import math

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


def test_depth_masked_psnr_is_splatams_definition_by_hand():
    """SplaTAM / SGS-SLAM zero both images where depth is missing, take the MSE per channel over all pixels and
    average the channels' PSNR: worked out by hand on a 2x2 image, and never below ours where depth has holes."""
    import math

    import torch

    from semantic_gs_slam.metrics import psnr, psnr_depth_masked

    gt = torch.zeros(2, 2, 3)
    img = torch.zeros(2, 2, 3)
    img[0, 0] = torch.tensor([0.1, 0.2, 0.0])  # a pixel with depth: counted
    img[1, 1] = torch.tensor([0.5, 0.5, 0.5])  # a pixel without depth: ignored by the masked PSNR only
    img[0, 1, 2] = 0.05
    depth = torch.tensor([[1.0, 1.0], [1.0, 0.0]])
    mse = [0.1**2 / 4, 0.2**2 / 4, 0.05**2 / 4]  # per channel, over all 4 pixels
    want = sum(-10 * math.log10(m) for m in mse) / 3
    assert psnr_depth_masked(img, gt, depth) == pytest.approx(want, rel=1e-5)
    assert psnr_depth_masked(img, gt, depth) > psnr(img, gt)
    assert psnr_depth_masked(img, gt, torch.ones(2, 2)) < psnr_depth_masked(img, gt, depth)  # the hole counts now


def test_psnr_split_by_depth_by_hand():
    """PSNR over the pixels with depth and over those without, each its own MSE; NaN for an empty part."""
    import torch

    from semantic_gs_slam.metrics import psnr_split

    gt = torch.zeros(2, 2, 3)
    img = gt.clone()
    img[0, 0] = 0.1  # a pixel with depth, squared error 0.01
    img[1, 1] = 0.5  # the one without, squared error 0.25
    depth = torch.tensor([[1.0, 1.0], [1.0, 0.0]])
    with_d, without_d = psnr_split(img, gt, depth)
    assert with_d == pytest.approx(10 * math.log10(3 / 0.01), rel=1e-5)
    assert without_d == pytest.approx(10 * math.log10(1 / 0.25), rel=1e-5)
    assert math.isnan(psnr_split(img, gt, torch.ones(2, 2))[1])
