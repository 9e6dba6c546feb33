"""Compiled CPU accumulation of one ICP step's normal equations (numba): the fast path of tracking on a CPU.

:func:`semantic_gs_slam.tracking.tracker.icp_normal_equations` is the reference: about ninety fixed-shape tensor
operations over every live point, whose per-call overhead, not arithmetic, sets a CPU step's time (~4 ms at
20 k points). :func:`normal_equations_numba` computes the same sums in one pass over the points (float64,
in point order, one thread: the result does not depend on the machine's thread count):

* geometry: each live point, moved by the estimate, projected into the model view and rounded to a pixel;
  the point-to-plane residual ``r = n . (x - q)`` against that pixel's model vertex ``q`` and normal ``n``
  (closer than ``icp_max_dist``), Huber weight, Jacobian ``[x x n, n]``;
* photometry (finest level only): bilinear model intensity and gradient at the projection, residual against
  the live intensity, Jacobian through the projection.

It returns ``A`` [6, 6], ``b`` [6] and the four counts the step's statistics need. :func:`icp_step_numba` then
adds the prior, solves and updates the pose in numpy (the tensor tail of
:func:`semantic_gs_slam.tracking.tracker._icp_step`, a dozen small torch calls, cost as much as the sums themselves).

numba is optional (without it, ``tracking.icp_backend: auto`` keeps the reference).
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

from semantic_gs_slam.config import Intrinsics, TrackingConfig

__all__ = ["icp_step_numba", "normal_equations_numba"]


@functools.cache
def _kernel():
    """The compiled kernel (:mod:`semantic_gs_slam.tracking.numba_kernels`, which imports numba: only when used)."""
    from semantic_gs_slam.tracking import numba_kernels as nk

    return nk.icp_accumulate


def normal_equations_numba(est: Tensor, lp: Tensor, lvalid: Tensor, il: Tensor | None, vm: Tensor, nm: Tensor,
                           nvalid: Tensor, col: Tensor | None, w2c_g: Tensor, k: Intrinsics, cfg: TrackingConfig,
                           photometric: bool) -> tuple[Tensor, Tensor, Tensor]:
    """The data terms of one ICP step (see :func:`semantic_gs_slam.tracking.tracker.icp_normal_equations`), CPU only.

    Args:
        est: [4, 4] float64 estimate (camera to world). lp: [M, 3] live camera points. lvalid: [M] bool.
        il: [M] live intensity or None. vm, nm: [H*W, 3] model world vertices and normals. nvalid: [H*W] bool.
        col: [H*W, 4] model intensity, d/du, d/dv, usable; or None. w2c_g: [4, 4] the model's camera.
        photometric: add the photometric term (needs ``il`` and ``col``).

    Returns:
        ``A`` [6, 6], ``b`` [6] (float64 tensors) and ``[correspondences, sum of squared geometric residuals,
        residuals within 3 sigma, points on a usable model pixel]`` [4].
    """
    photometric = bool(photometric and col is not None and il is not None)

    def arr(t: Tensor | None, shape: tuple[int, ...], dtype=np.float64) -> np.ndarray:
        return np.zeros(shape, dtype) if t is None else t.detach().contiguous().numpy()

    a = np.zeros((6, 6))
    b = np.zeros(6)
    stats = np.zeros(4)
    _kernel()(arr(est, (4, 4)), arr(w2c_g, (4, 4)), arr(lp, (0, 3)), arr(lvalid, (0,), np.bool_),
              arr(il if photometric else None, (1,)), arr(vm, (0, 3)), arr(nm, (0, 3)), arr(nvalid, (0,), np.bool_),
              arr(col if photometric else None, (1, 4)), float(k.fx), float(k.fy), float(k.cx), float(k.cy),
              int(k.width), int(k.height), float(cfg.icp_max_dist), float(cfg.icp_sigma_geo), 0.0,
              float(cfg.geometric_weight), photometric, float(cfg.icp_sigma_col), float(cfg.photometric_weight), a, b,
              stats, 0.0)
    return torch.from_numpy(a), torch.from_numpy(b), torch.from_numpy(stats)


def _so3_log(r: np.ndarray) -> np.ndarray:
    """Axis-angle [3] of a rotation [3, 3]: :func:`semantic_gs_slam.tracking.tracker._so3_log` in numpy (checked with
    the whole step by ``test_tracking.py::test_numba_icp_step_equals_the_reference_step``)."""
    c = min(1.0, max(-1.0, (np.trace(r) - 1) / 2))
    th = np.arccos(c)
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    return v * (0.5 if th < 1e-6 else th / (2 * max(np.sin(th), 1e-12)))


def _se3_exp(xi: np.ndarray) -> np.ndarray:
    """[4, 4] of xi = (rotation vector, translation): :func:`semantic_gs_slam.geometry.se3_exp` in numpy (checked
    with the whole step, as :func:`_so3_log`)."""
    w = xi[:3]
    theta2 = float(w @ w)
    theta = np.sqrt(theta2 + 1e-24)
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    small = theta2 < 1e-10
    a = 1 - theta2 / 6 if small else np.sin(theta) / theta
    b = 0.5 - theta2 / 24 if small else (1 - np.cos(theta)) / (theta2 + 1e-24)
    t = np.eye(4)
    t[:3, :3] = np.eye(3) + a * k + b * (k @ k)
    t[:3, 3] = xi[3:]
    return t


def icp_step_numba(est: Tensor, lp: Tensor, lvalid: Tensor, il: Tensor | None, vm: Tensor, nm: Tensor,
                   nvalid: Tensor, col: Tensor | None, w2c_g: Tensor, prior_w: Tensor, k: Intrinsics,
                   cfg: TrackingConfig, photometric: bool) -> tuple[Tensor, Tensor]:
    """One whole ICP step on the CPU: :func:`normal_equations_numba`, then the prior toward the model's camera, the
    6x6 solve and the pose update in numpy. Arguments as there, plus ``prior_w`` [6, 6] (information of the prior).

    Returns:
        the new estimate [4, 4] and ``[correspondences, residual RMS (m), largest step component, agreement]`` [4]
        (float64 tensors), as :func:`semantic_gs_slam.tracking.tracker._icp_step`.
    """
    a, b, sums = (x.numpy() for x in normal_equations_numba(est, lp, lvalid, il, vm, nm, nvalid, col, w2c_g, k, cfg,
                                                            photometric))
    e = est.detach().numpy()
    d = e @ w2c_g.detach().numpy()
    prior = np.concatenate([_so3_log(d[:3, :3]), d[:3, 3]])
    pw = prior_w.detach().numpy()
    a = a + pw
    b = b - pw @ prior
    a = a + np.eye(6) * (1e-9 * np.diagonal(a).mean())
    xi = np.linalg.solve(a, b)
    n_in = sums[0]
    stats = np.array([n_in, np.sqrt(sums[1] / max(n_in, 1.0)), np.abs(xi).max(), sums[2] / max(sums[3], 1.0)])
    return torch.from_numpy(_se3_exp(xi) @ e), torch.from_numpy(stats)
