"""Keyframe pose graph: relative-pose constraints between keyframes and their least-squares solution.

Plain NumPy (no torch, no ROS): the engine (:mod:`semantic_gs_slam.slam`) adds one *sequential*
edge per new keyframe (its tracked motion from the previous keyframe) and one *loop* edge whenever
a keyframe registers against a much older keyframe it overlaps (:mod:`semantic_gs_slam.loop.detection`).
:func:`optimise` then spreads the loop's disagreement over the chain of keyframes.

Conventions: poses are camera-to-world ``[4, 4]`` float64; an edge ``(i, j, rel)`` says
``inv(T_i) @ T_j == rel``; its residual is ``log(inv(rel) @ inv(T_i) @ T_j)`` as (rotation vector,
translation) [6], weighted by ``1 / sigma^2`` per component. Updates are left-multiplied
(``T <- exp(delta) @ T``, world frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def so3_log(r: np.ndarray) -> np.ndarray:
    """Rotation vector [3] of a rotation matrix [3, 3] (safe near 0 and near pi)."""
    c = float(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))
    th = float(np.arccos(c))
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if th < 1e-6:
        return 0.5 * v
    if np.pi - th < 1e-4:  # near pi: axis from the symmetric part
        ax = np.sqrt(np.clip((np.diag(r) + 1.0) / 2.0, 0.0, None))
        i = int(np.argmax(ax))
        ax = (r[i] + r[:, i]) / 2.0
        ax[i] = ax[i] if ax[i] > 0 else 1.0
        ax = ax / np.linalg.norm(ax)
        return th * ax
    return v * th / (2.0 * np.sin(th))


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix [3, 3] of a rotation vector [3] (Rodrigues)."""
    th = float(np.linalg.norm(w))
    k = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if th < 1e-9:
        return np.eye(3) + k
    return np.eye(3) + np.sin(th) / th * k + (1.0 - np.cos(th)) / th**2 * (k @ k)


def pose_exp(xi: np.ndarray) -> np.ndarray:
    """[4, 4] from (rotation vector, translation) [6] (the same split as the tracker's ``se3_exp``)."""
    t = np.eye(4)
    t[:3, :3] = so3_exp(xi[:3])
    t[:3, 3] = xi[3:]
    return t


def pose_log(t: np.ndarray) -> np.ndarray:
    """Inverse of :func:`pose_exp`: (rotation vector, translation) [6] of a [4, 4] rigid transform."""
    return np.concatenate([so3_log(t[:3, :3]), t[:3, 3]])


@dataclass
class Edge:
    """A relative-pose constraint ``inv(T_i) @ T_j == rel`` between nodes ``i`` and ``j``."""

    i: int
    j: int
    rel: np.ndarray  # [4, 4]
    sigma_rot: float  # radians
    sigma_trans: float  # metres
    kind: str = "sequential"  # "sequential" (tracked motion) | "loop" (registration against an old keyframe)

    def weights(self) -> np.ndarray:
        """Per-component information [6] (1 / sigma^2)."""
        return np.array([self.sigma_rot**-2] * 3 + [self.sigma_trans**-2] * 3)


def edge_residual(ti: np.ndarray, tj: np.ndarray, rel: np.ndarray) -> np.ndarray:
    """Residual [6] of an edge at poses ``ti``, ``tj`` (zero when they agree with ``rel``)."""
    return pose_log(np.linalg.inv(rel) @ np.linalg.inv(ti) @ tj)


def total_cost(poses: list[np.ndarray], edges: list[Edge]) -> float:
    """Sum of weighted squared residuals."""
    return float(sum((edge_residual(poses[e.i], poses[e.j], e.rel) ** 2 * e.weights()).sum() for e in edges))


def _rigid_inv(t: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms [..., 4, 4]."""
    out = np.zeros_like(t)
    rt = np.swapaxes(t[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -(rt @ t[..., :3, 3, None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def _so3_log_batch(r: np.ndarray) -> np.ndarray:
    """:func:`so3_log` of rotations [M, 3, 3] -> [M, 3] (rows near pi fall back to the scalar version)."""
    c = np.clip((np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    th = np.arccos(c)
    v = np.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], -1)
    small = th < 1e-6
    scale = np.where(small, 0.5, th / (2.0 * np.sin(np.where(small, 1.0, th))))
    out = v * scale[:, None]
    for i in np.nonzero(np.pi - th < 1e-4)[0]:
        out[i] = so3_log(r[i])
    return out


def _residuals(ti: np.ndarray, tj: np.ndarray, rel_inv: np.ndarray) -> np.ndarray:
    """:func:`edge_residual` of stacks [M, 4, 4] (``rel_inv``: the edges' inverted ``rel``) -> [M, 6]."""
    e = rel_inv @ _rigid_inv(ti) @ tj
    return np.concatenate([_so3_log_batch(e[:, :3, :3]), e[:, :3, 3]], -1)


def optimise(poses: list[np.ndarray], edges: list[Edge], fixed: int = 0, iters: int = 10,
             tol: float = 1e-7) -> tuple[list[np.ndarray], float, float]:
    """Gauss-Newton over all poses but ``fixed`` (the gauge).

    Jacobians are central differences of the edge residuals, evaluated for all edges at once
    (12 perturbations each, batched NumPy); the normal equations are solved densely ([6N, 6N]):
    about 10 ms per iteration for the 70 keyframes and 125 edges of a room.

    Args:
        poses: N camera-to-world [4, 4] start poses.
        edges: constraints between them.
        fixed: index of the pose held fixed.
        iters: at most this many Gauss-Newton steps.
        tol: stop when the largest update component is below this.

    Returns:
        (optimised poses, cost before, cost after).

    Raises:
        ValueError: an edge names a pose that does not exist.
    """
    n = len(poses)
    for e in edges:
        if not (0 <= e.i < n and 0 <= e.j < n) or e.i == e.j:
            raise ValueError(f"edge ({e.i}, {e.j}) does not join two of the {n} poses")
    cur = np.stack([np.asarray(p, np.float64) for p in poses]) if n else np.zeros((0, 4, 4))
    before = total_cost(list(cur), edges)
    if n < 2 or not edges:
        return list(cur), before, before
    ii = np.array([e.i for e in edges])
    jj = np.array([e.j for e in edges])
    rel_inv = _rigid_inv(np.stack([e.rel for e in edges]))
    w = np.stack([e.weights() for e in edges])  # [M, 6]
    eps = 1e-6
    steps = np.stack([pose_exp(d) for d in np.concatenate([np.eye(6), -np.eye(6)]) * eps])  # [12, 4, 4]
    m = len(edges)
    for _ in range(iters):
        ti, tj = cur[ii], cur[jj]
        r = _residuals(ti, tj, rel_inv)  # [M, 6]
        jac = np.zeros((m, 6, 12))
        for side in (0, 1):
            base = ti if side == 0 else tj
            pert = steps[None] @ base[:, None]  # [M, 12, 4, 4]: +eps on each of 6, then -eps
            a = np.repeat(ti[:, None], 12, 1) if side == 1 else pert
            b = np.repeat(tj[:, None], 12, 1) if side == 0 else pert
            rr = _residuals(a.reshape(-1, 4, 4), b.reshape(-1, 4, 4), np.repeat(rel_inv, 12, 0)).reshape(m, 12, 6)
            jac[:, :, 6 * side:6 * side + 6] = np.swapaxes((rr[:, :6] - rr[:, 6:]) / (2 * eps), 1, 2)
        jw = np.swapaxes(jac, 1, 2) * w[:, None, :]  # [M, 12, 6]
        blocks = jw @ jac  # [M, 12, 12]
        grads = -(jw @ r[:, :, None])[..., 0]  # [M, 12]
        h = np.zeros((6 * n, 6 * n))
        b = np.zeros(6 * n)
        for k in range(m):
            idx = np.r_[6 * ii[k]:6 * ii[k] + 6, 6 * jj[k]:6 * jj[k] + 6]
            h[np.ix_(idx, idx)] += blocks[k]
            b[idx] += grads[k]
        g = slice(6 * fixed, 6 * fixed + 6)
        h[g, :] = 0.0
        h[:, g] = 0.0
        h[g, g] = np.eye(6)
        b[g] = 0.0
        h += 1e-9 * np.eye(6 * n) * max(float(np.mean(np.diag(h))), 1e-12)
        dx = np.linalg.solve(h, b)
        for k in range(n):
            if k != fixed:
                cur[k] = pose_exp(dx[6 * k:6 * k + 6]) @ cur[k]
        if float(np.abs(dx).max()) < tol:
            break
    return list(cur), before, total_cost(list(cur), edges)
