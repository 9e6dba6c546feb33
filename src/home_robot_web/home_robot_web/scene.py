"""What the page's 3-D view draws, prepared once here (no ROS): map points, robot path.

The map is the SLAM map the live view shows (``params.npz`` of SplaTAM / SGS-SLAM: Gaussian centres
and colours). The page draws each Gaussian's centre as a coloured point, which a phone draws
fluently; the robot, its path and the object memory's objects are drawn over it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from home_robot_web.errors import ConfigError


def map_points(path: str, max_points: int = 20000, min_opacity: float = 0.3) -> dict[str, Any]:
    """The ``map`` event of the page: at most ``max_points`` Gaussian centres with their colours.

    Args:
        path: the map file (``means3D`` [N, 3], ``rgb_colors`` [N, 3] in 0..1, optional
            ``logit_opacities`` [N, 1]).
        max_points: an even subsample of the opaque ones, at most this many (>= 1).
        min_opacity: fainter Gaussians are left out (0 keeps all).

    Returns:
        ``{"type": "map", "n": N, "xyz": [x0, y0, z0, x1, ...] (cm, integers), "rgb": [r0, g0, b0, ...] (0..255)}``.

    Raises:
        ConfigError: unreadable file, missing keys, wrong shapes, ``max_points < 1``.
    """
    if max_points < 1:
        raise ConfigError(f"max_map_points must be >= 1, got {max_points}")
    try:
        with np.load(path) as d:
            means = np.asarray(d["means3D"], np.float64)  # [N, 3]
            rgb = np.asarray(d["rgb_colors"], np.float64)  # [N, 3]
            logit = np.asarray(d["logit_opacities"], np.float64).reshape(-1) if "logit_opacities" in d.files \
                else np.full(len(means), 10.0)  # [N]
    except (OSError, KeyError, ValueError) as exc:
        raise ConfigError(f"cannot read the map {path!r}: {exc}") from exc
    if means.ndim != 2 or means.shape[1] != 3 or rgb.shape != means.shape or logit.shape != (len(means),):
        raise ConfigError(f"the map {path!r} has mismatched shapes: means3D {means.shape}, rgb_colors {rgb.shape}")
    keep = (1.0 / (1.0 + np.exp(-logit)) >= min_opacity) & np.isfinite(means).all(1) & np.isfinite(rgb).all(1)
    means, rgb = means[keep], rgb[keep]
    if len(means) > max_points:
        idx = np.linspace(0, len(means) - 1, max_points).astype(np.int64)
        means, rgb = means[idx], rgb[idx]
    xyz = np.round(means * 100.0).astype(np.int64).reshape(-1)
    col = np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.int64).reshape(-1)
    return {"type": "map", "n": int(len(means)), "xyz": xyz.tolist(), "rgb": col.tolist()}


class Path2D:
    """The robot's path: a point is added when the robot moved at least ``min_step_m``; at most
    ``max_points`` are kept (the oldest go first)."""

    def __init__(self, min_step_m: float = 0.05, max_points: int = 2000) -> None:
        self.min_step_m, self.max_points = min_step_m, max_points
        self.points: list[tuple[float, float]] = []

    def add(self, x: float, y: float) -> bool:
        """Add a pose; returns whether the path changed."""
        if self.points and math.hypot(self.points[-1][0] - x, self.points[-1][1] - y) < self.min_step_m:
            return False
        self.points.append((x, y))
        if len(self.points) > self.max_points:
            del self.points[: len(self.points) - self.max_points]
        return True


def yaw_of(qx: float, qy: float, qz: float, qw: float) -> float:
    """Heading (rad) of a quaternion, about +z."""
    return math.atan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))
