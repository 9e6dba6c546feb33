"""Image and trajectory metrics: PSNR (ours, and SplaTAM's depth-masked one), SSIM, depth L1, semantic mIoU,
ATE RMSE (aligned)."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from semantic_gs_slam.devices import numba_available
from semantic_gs_slam.eval.metrics_numba import ssim_numba
from semantic_gs_slam.geometry import umeyama_similarity

_WINDOWS: dict[tuple, Tensor] = {}


def _window(size: int, sigma: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    key = (size, sigma, dtype, device)
    if key not in _WINDOWS:
        x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
        g = torch.exp(-x * x / (2 * sigma * sigma))
        _WINDOWS[key] = g / g.sum()
    return _WINDOWS[key]


def ssim(a: Tensor, b: Tensor, size: int = 11, sigma: float = 1.5, fast: bool | None = None) -> Tensor:
    """Mean SSIM of two images [H, W, C] in [0, 1] (Gaussian window, separable, 'same' zero padding).

    Args:
        fast: True = the compiled CPU kernel (:mod:`semantic_gs_slam.eval.metrics_numba`; float32 CPU images, ``b``
            without gradient), False = :func:`ssim_reference`, None = the kernel where it applies and numba is
            installed.
    """
    if fast is None:
        fast = (a.device.type == "cpu" and b.device.type == "cpu" and a.dtype == b.dtype == torch.float32
                and not b.requires_grad and a.ndim == 3 and size % 2 == 1 and numba_available())
    if fast:
        return ssim_numba(a, b, _window(size, sigma, torch.float32, torch.device("cpu")))
    return ssim_reference(a, b, size, sigma)


def ssim_reference(a: Tensor, b: Tensor, size: int = 11, sigma: float = 1.5) -> Tensor:
    """:func:`ssim` in grouped convolutions (any device and dtype; differentiable in both images): the reference."""
    x = a.permute(2, 0, 1)[None]
    y = b.permute(2, 0, 1)[None]
    c = x.shape[1]
    g = _window(size, sigma, a.dtype, a.device)
    gx = g.view(1, 1, 1, -1).repeat(c, 1, 1, 1)
    gy = g.view(1, 1, -1, 1).repeat(c, 1, 1, 1)

    def blur(t: Tensor) -> Tensor:
        return F.conv2d(F.conv2d(t, gx, padding=(0, size // 2), groups=c), gy, padding=(size // 2, 0), groups=c)

    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return s.mean()


def psnr(a: Tensor, b: Tensor) -> float:
    """PSNR in dB of images in [0, 1]."""
    mse = float(((a - b) ** 2).mean())
    return float("inf") if mse == 0 else 10 * math.log10(1.0 / mse)


def psnr_depth_masked(a: Tensor, b: Tensor, depth: Tensor) -> float:
    """PSNR in dB as SplaTAM and SGS-SLAM report it: both images [H, W, C] multiplied by the valid-depth mask
    (``depth`` [H, W] > 0), the MSE taken per channel over *all* pixels (so pixels without depth count as
    perfect), the PSNR averaged over channels. Higher than :func:`psnr` wherever depth has holes; kept
    beside it so figures can be compared with those papers' tables."""
    m = (depth > 0).to(a.dtype)[..., None]
    mse = (((a - b) * m) ** 2).reshape(-1, a.shape[-1]).mean(0).clamp_min(1e-20)  # [C]
    return float((-10 * torch.log10(mse)).mean())


def psnr_split(a: Tensor, b: Tensor, depth: Tensor) -> tuple[float, float]:
    """PSNR in dB of images [H, W, C] in [0, 1] over the pixels with depth (``depth`` [H, W] > 0) and over those
    without, each its own MSE; NaN for a part with no pixel. A real depth camera leaves 5-20 % of a frame without
    depth (near limit, shadows, dark surfaces): this says where the image error is."""
    has = depth > 0
    with_d, without_d = (psnr(a[m], b[m]) if bool(m.any()) else float("nan") for m in (has, ~has))
    return with_d, without_d


def depth_l1(pred: Tensor, gt: Tensor) -> float:
    """Mean |pred - gt| in metres over pixels with gt > 0."""
    m = gt > 0
    return float((pred - gt).abs()[m].mean()) if bool(m.any()) else float("nan")


def confusion(pred: np.ndarray, gt: np.ndarray, n: int) -> np.ndarray:
    """Confusion matrix [n, n] (rows gt) of integer label images, ignoring gt label 0."""
    m = gt > 0
    return np.bincount(gt[m].astype(np.int64) * n + pred[m].astype(np.int64), minlength=n * n).reshape(n, n)


def class_iou(conf: np.ndarray) -> dict[int, float]:
    """IoU of every class present in the ground truth (rows of ``conf``), by class index."""
    inter = np.diag(conf).astype(np.float64)
    union = conf.sum(0) + conf.sum(1) - inter
    return {int(c): float(inter[c] / max(union[c], 1)) for c in np.flatnonzero(conf.sum(1) > 0)}


def miou(conf: np.ndarray) -> float:
    """Mean IoU over classes present in the ground truth."""
    ious = class_iou(conf)
    return float(np.mean(list(ious.values()))) if ious else float("nan")


def ate_rmse(est_c2w: list[np.ndarray], gt_c2w: list[np.ndarray]) -> float:
    """Absolute trajectory error (m): RMSE of camera positions after the best rigid alignment."""
    return _ate(est_c2w, gt_c2w, with_scale=False)[0]


def ate_sim3(est_c2w: list[np.ndarray], gt_c2w: list[np.ndarray]) -> tuple[float, float]:
    """Absolute trajectory error (m) after the best similarity alignment (rotation, translation and scale), and that
    scale: for references whose metric scale is itself an estimate (structure from motion)."""
    return _ate(est_c2w, gt_c2w, with_scale=True)


def _ate(est_c2w: list[np.ndarray], gt_c2w: list[np.ndarray], with_scale: bool) -> tuple[float, float]:
    e = np.stack([p[:3, 3] for p in est_c2w])
    g = np.stack([p[:3, 3] for p in gt_c2w])
    if len(e) < 3:
        return float(np.sqrt(((e - g) ** 2).sum(1).mean())), 1.0
    t, s = umeyama_similarity(e, g, with_scale)
    ea = s * e @ t[:3, :3].T + t[:3, 3]
    return float(np.sqrt(((ea - g) ** 2).sum(1).mean())), s


def rpe_rmse(est_c2w: list[np.ndarray], gt_c2w: list[np.ndarray], step: int = 1) -> float:
    """Relative pose error (m): RMSE over i of the translation of ``inv(E_i^-1 E_{i+step}) @ G_i^-1 G_{i+step}``,
    how much each ``step``-frame motion differs from the reference's (no alignment needed; drift does not add up).
    NaN with fewer than ``step + 1`` poses."""
    if len(est_c2w) != len(gt_c2w):
        raise ValueError(f"{len(est_c2w)} estimated poses against {len(gt_c2w)} reference poses")
    errs = [np.linalg.norm((np.linalg.inv(np.linalg.inv(est_c2w[i]) @ est_c2w[i + step])
                            @ np.linalg.inv(gt_c2w[i]) @ gt_c2w[i + step])[:3, 3])
            for i in range(len(est_c2w) - step)]
    return float(np.sqrt(np.mean(np.square(errs)))) if errs else float("nan")
