"""Compiled CPU accumulation of one ICP step's normal equations (numba): the fast path of tracking on a CPU.

:func:`semantic_gs_slam.tracking.icp_normal_equations` is the reference: about ninety fixed-shape tensor
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
:func:`semantic_gs_slam.tracking._icp_step`, a dozen small torch calls, cost as much as the sums themselves).

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
def _kernel():  # pragma: no cover - compiled (its twin is tracking.icp_normal_equations)
    import numba

    @numba.njit(cache=True, nogil=True)
    def accumulate(est, w2c_g, lp, lvalid, il, vm, nm, nvalid, col, fx, fy, cx, cy, width, height, max_dist, sg,
                   w_geo, photometric, sc, w_col, a, b, stats):
        jac = np.zeros(6)
        n_close = 0.0
        rr = 0.0
        n_agree = 0.0
        n_ok = 0.0
        for m in range(lp.shape[0]):
            if not lvalid[m]:
                continue
            p0, p1, p2 = lp[m, 0], lp[m, 1], lp[m, 2]
            x0 = est[0, 0] * p0 + est[0, 1] * p1 + est[0, 2] * p2 + est[0, 3]
            x1 = est[1, 0] * p0 + est[1, 1] * p1 + est[1, 2] * p2 + est[1, 3]
            x2 = est[2, 0] * p0 + est[2, 1] * p1 + est[2, 2] * p2 + est[2, 3]
            c0 = w2c_g[0, 0] * x0 + w2c_g[0, 1] * x1 + w2c_g[0, 2] * x2 + w2c_g[0, 3]
            c1 = w2c_g[1, 0] * x0 + w2c_g[1, 1] * x1 + w2c_g[1, 2] * x2 + w2c_g[1, 3]
            c2 = w2c_g[2, 0] * x0 + w2c_g[2, 1] * x1 + w2c_g[2, 2] * x2 + w2c_g[2, 3]
            if not c2 > 1e-3:  # (also false for NaN)
                continue
            z = c2
            uf = fx * c0 / z + cx
            vf = fy * c1 / z + cy
            if not (uf > -1.0 and uf < width + 1.0 and vf > -1.0 and vf < height + 1.0):
                continue
            u = np.rint(uf)  # round half to even, as torch.round
            v = np.rint(vf)
            if u < 0 or u >= width or v < 0 or v >= height:
                continue
            pix = int(v) * width + int(u)
            if nvalid[pix]:
                n_ok += 1.0
                n0, n1, n2 = nm[pix, 0], nm[pix, 1], nm[pix, 2]
                d0, d1, d2 = x0 - vm[pix, 0], x1 - vm[pix, 1], x2 - vm[pix, 2]
                if np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) < max_dist:
                    r = d0 * n0 + d1 * n1 + d2 * n2
                    ar = abs(r)
                    w = (1.0 if ar < sg else sg / max(ar, 1e-30)) * (w_geo / (sg * sg))
                    jac[0] = x1 * n2 - x2 * n1
                    jac[1] = x2 * n0 - x0 * n2
                    jac[2] = x0 * n1 - x1 * n0
                    jac[3], jac[4], jac[5] = n0, n1, n2
                    for i in range(6):
                        wi = w * jac[i]
                        b[i] -= wi * r
                        for j in range(i + 1):
                            a[i, j] += wi * jac[j]
                    n_close += 1.0
                    rr += r * r
                    if ar < 3 * sg:
                        n_agree += 1.0
            if photometric and uf >= 0 and uf < width - 1 and vf >= 0 and vf < height - 1:
                u0 = np.floor(uf)
                v0 = np.floor(vf)
                fu, fv = uf - u0, vf - v0
                q00 = int(v0) * width + int(u0)
                w00, w01, w10, w11 = (1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv
                q01, q10, q11 = q00 + 1, q00 + width, q00 + width + 1
                s0 = w00 * col[q00, 0] + w01 * col[q01, 0] + w10 * col[q10, 0] + w11 * col[q11, 0]
                s1 = w00 * col[q00, 1] + w01 * col[q01, 1] + w10 * col[q10, 1] + w11 * col[q11, 1]
                s2 = w00 * col[q00, 2] + w01 * col[q01, 2] + w10 * col[q10, 2] + w11 * col[q11, 2]
                s3 = w00 * col[q00, 3] + w01 * col[q01, 3] + w10 * col[q10, 3] + w11 * col[q11, 3]
                if s3 > 0.999:
                    rc = s0 - il[m]
                    # d I / d camera point, then to the world point through the model camera's rotation
                    e0 = s1 * fx / z
                    e1 = s2 * fy / z
                    e2 = -(s1 * fx * c0 + s2 * fy * c1) / (z * z)
                    g0 = e0 * w2c_g[0, 0] + e1 * w2c_g[1, 0] + e2 * w2c_g[2, 0]
                    g1 = e0 * w2c_g[0, 1] + e1 * w2c_g[1, 1] + e2 * w2c_g[2, 1]
                    g2 = e0 * w2c_g[0, 2] + e1 * w2c_g[1, 2] + e2 * w2c_g[2, 2]
                    jac[0] = x1 * g2 - x2 * g1
                    jac[1] = x2 * g0 - x0 * g2
                    jac[2] = x0 * g1 - x1 * g0
                    jac[3], jac[4], jac[5] = g0, g1, g2
                    arc = abs(rc)
                    wc = (1.0 if arc < sc else sc / max(arc, 1e-30)) * (w_col / (sc * sc))
                    for i in range(6):
                        wi = wc * jac[i]
                        b[i] -= wi * rc
                        for j in range(i + 1):
                            a[i, j] += wi * jac[j]
        for i in range(6):
            for j in range(i):
                a[j, i] = a[i, j]
        stats[0] = n_close
        stats[1] = rr
        stats[2] = n_agree
        stats[3] = n_ok

    return accumulate


def normal_equations_numba(est: Tensor, lp: Tensor, lvalid: Tensor, il: Tensor | None, vm: Tensor, nm: Tensor,
                           nvalid: Tensor, col: Tensor | None, w2c_g: Tensor, k: Intrinsics, cfg: TrackingConfig,
                           photometric: bool) -> tuple[Tensor, Tensor, Tensor]:
    """The data terms of one ICP step (see :func:`semantic_gs_slam.tracking.icp_normal_equations`), CPU only.

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
              int(k.width), int(k.height), float(cfg.icp_max_dist), float(cfg.icp_sigma_geo),
              float(cfg.geometric_weight), photometric, float(cfg.icp_sigma_col), float(cfg.photometric_weight), a, b,
              stats)
    return torch.from_numpy(a), torch.from_numpy(b), torch.from_numpy(stats)


def _so3_log(r: np.ndarray) -> np.ndarray:
    """Axis-angle [3] of a rotation [3, 3] (as :func:`semantic_gs_slam.tracking._so3_log`)."""
    c = min(1.0, max(-1.0, (np.trace(r) - 1) / 2))
    th = np.arccos(c)
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    return v * (0.5 if th < 1e-6 else th / (2 * max(np.sin(th), 1e-12)))


def _se3_exp(xi: np.ndarray) -> np.ndarray:
    """[4, 4] of xi = (rotation vector, translation), as :func:`semantic_gs_slam.geometry.se3_exp`."""
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
        (float64 tensors), as :func:`semantic_gs_slam.tracking._icp_step`.
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
