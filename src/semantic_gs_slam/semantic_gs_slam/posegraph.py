"""Keyframe pose graph: relative-pose constraints between keyframes and their least-squares solution.

Plain NumPy (no torch, no ROS): the engine (:mod:`semantic_gs_slam.slam`) adds one *sequential*
edge per new keyframe (its tracked motion from the previous keyframe) and one *loop* edge whenever
a keyframe registers against a much older keyframe it overlaps (:mod:`semantic_gs_slam.loop`).
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


def optimise(poses: list[np.ndarray], edges: list[Edge], fixed: int = 0, iters: int = 10,
             tol: float = 1e-7) -> tuple[list[np.ndarray], float, float]:
    """Gauss-Newton over all poses but ``fixed`` (the gauge).

    Jacobians are central differences of :func:`edge_residual` (12 residual evaluations per edge and
    iteration: cheap next to a rendered frame for the few hundred keyframes of a room); the normal
    equations are solved densely ([6N, 6N]).

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
    cur = [np.asarray(p, np.float64).copy() for p in poses]
    before = total_cost(cur, edges)
    if n < 2 or not edges:
        return cur, before, before
    eps = 1e-6
    for _ in range(iters):
        h = np.zeros((6 * n, 6 * n))
        b = np.zeros(6 * n)
        for e in edges:
            r = edge_residual(cur[e.i], cur[e.j], e.rel)
            jac = np.zeros((6, 12))
            for side, node in ((0, e.i), (1, e.j)):
                for c in range(6):
                    d = np.zeros(6)
                    d[c] = eps
                    plus, minus = pose_exp(d) @ cur[node], pose_exp(-d) @ cur[node]
                    if side == 0:
                        rp, rm = edge_residual(plus, cur[e.j], e.rel), edge_residual(minus, cur[e.j], e.rel)
                    else:
                        rp, rm = edge_residual(cur[e.i], plus, e.rel), edge_residual(cur[e.i], minus, e.rel)
                    jac[:, 6 * side + c] = (rp - rm) / (2 * eps)
            w = e.weights()
            idx = np.r_[6 * e.i:6 * e.i + 6, 6 * e.j:6 * e.j + 6]
            jw = jac.T * w
            h[np.ix_(idx, idx)] += jw @ jac
            b[idx] -= jw @ r
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
    return cur, before, total_cost(cur, edges)
