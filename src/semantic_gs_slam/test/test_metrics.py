"""Semantic metrics on a hand-made confusion matrix."""

from __future__ import annotations

import math

import numpy as np
import pytest

from semantic_gs_slam.eval.metrics import ate_rmse, ate_sim3, class_iou, confusion, miou, rpe_rmse


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

    from semantic_gs_slam.eval.metrics import psnr, psnr_depth_masked

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

    from semantic_gs_slam.eval.metrics import psnr_split

    gt = torch.zeros(2, 2, 3)
    img = gt.clone()
    img[0, 0] = 0.1  # a pixel with depth, squared error 0.01
    img[1, 1] = 0.5  # the one without, squared error 0.25
    depth = torch.tensor([[1.0, 1.0], [1.0, 0.0]])
    with_d, without_d = psnr_split(img, gt, depth)
    assert with_d == pytest.approx(10 * math.log10(3 / 0.01), rel=1e-5)
    assert without_d == pytest.approx(10 * math.log10(1 / 0.25), rel=1e-5)
    assert math.isnan(psnr_split(img, gt, torch.ones(2, 2))[1])


def _path(n: int = 12) -> list[np.ndarray]:
    import torch

    from semantic_gs_slam.geometry import se3_exp

    return [se3_exp(torch.tensor([0.05 * i, 0.02 * i, -0.03 * i, 0.1 * i, 0.02 * i * i, -0.05 * i],
                                 dtype=torch.float64)).numpy() for i in range(n)]


def test_ate_with_scale_removes_a_similarity_and_reports_its_scale():
    import torch

    from semantic_gs_slam.geometry import se3_exp

    gt = _path()
    sim = se3_exp(torch.tensor([0.3, -0.2, 0.9, 1.0, 2.0, -0.5], dtype=torch.float64)).numpy()
    est = []
    for p in gt:  # the same trajectory in another frame and at 1.25x the size
        q = sim @ p
        q[:3, 3] = 1.25 * q[:3, 3]
        est.append(q)
    err, scale = ate_sim3(est, gt)
    assert err < 1e-9 and scale == pytest.approx(0.8)
    assert ate_rmse(est, gt) > 0.05  # a rigid alignment cannot remove the scale
    shifted = [p.copy() for p in gt]
    shifted[5][:3, 3] += [0.0, 0.0, 0.12]  # one position off by 12 cm: the RMSE over 12 frames is near 12 / sqrt(12)
    assert ate_sim3(shifted, gt)[0] == pytest.approx(0.12 / math.sqrt(12), rel=0.15)


def test_relative_pose_error_by_hand():
    gt = _path()
    assert rpe_rmse(gt, gt, 1) < 1e-12
    est = [p.copy() for p in gt]
    for p in est[6:]:  # a 3 cm jump between frames 5 and 6, then the same motion: one 1-step error of 3 cm
        p[:3, 3] += [0.03, 0.0, 0.0]
    assert rpe_rmse(est, gt, 1) == pytest.approx(math.sqrt(0.03**2 / 11), rel=1e-6)
    assert rpe_rmse(est, gt, 5) == pytest.approx(math.sqrt(5 * 0.03**2 / 7), rel=1e-6)  # 5 of 7 windows span it
    assert math.isnan(rpe_rmse(gt[:1], gt[:1], 1))
    with pytest.raises(ValueError, match="reference"):
        rpe_rmse(gt, gt[:3])
