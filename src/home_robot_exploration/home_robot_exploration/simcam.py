"""The simulated robot's RGB-D camera and the simulated home's ground truth (no ROS).

The camera rides on the base: ``height`` metres above the floor at the base's centre (plus
``forward_offset`` along its heading), looking along the heading, pitched down by ``tilt_deg``.
It renders :mod:`semantic_gs_slam.synthetic.scenes`'s home (the same scene the simulated world's objects
come from) with a pinhole of horizontal field of view ``hfov_deg``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from home_robot_exploration.errors import ConfigError
from home_robot_exploration.occupancy import OccupancyGrid


@dataclass(frozen=True)
class CameraConfig:
    """Mounting and image of the simulated camera.

    Attributes:
        width, height: image size (pixels).
        hfov_deg: horizontal field of view (degrees); square pixels.
        mount_height: camera height above the floor (m).
        tilt_deg: pitch down from horizontal (degrees).
        forward_offset: camera ahead of the base centre along the heading (m).
    """

    width: int = 300
    height: int = 170
    hfov_deg: float = 90.0
    mount_height: float = 1.0
    tilt_deg: float = 20.0
    forward_offset: float = 0.0

    def check(self) -> None:
        if not (8 <= self.width <= 4096 and 8 <= self.height <= 4096):
            raise ConfigError(f"image size must be within 8..4096 pixels, got {self.width}x{self.height}")
        if not 10.0 <= self.hfov_deg <= 170.0:
            raise ConfigError(f"hfov_deg must be in [10, 170], got {self.hfov_deg}")
        if not (0.05 <= self.mount_height <= 2.4) or not -89.0 <= self.tilt_deg <= 89.0:
            raise ConfigError(f"mount_height must be in [0.05, 2.4] m and tilt_deg in [-89, 89], got "
                              f"{self.mount_height}, {self.tilt_deg}")

    def k(self) -> np.ndarray:
        """[3, 3] pinhole intrinsics (principal point at the image centre)."""
        f = (self.width / 2.0) / math.tan(math.radians(self.hfov_deg) / 2.0)
        return np.array([[f, 0.0, (self.width - 1) / 2.0], [0.0, f, (self.height - 1) / 2.0], [0.0, 0.0, 1.0]])

    def c2w(self, x: float, y: float, yaw: float) -> np.ndarray:
        """[4, 4] camera-to-map pose (OpenCV camera: x right, y down, z forward) for a base pose."""
        t = math.radians(self.tilt_deg)
        fwd = np.array([math.cos(yaw) * math.cos(t), math.sin(yaw) * math.cos(t), -math.sin(t)])
        right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
        down = np.cross(fwd, right)
        out = np.eye(4)
        out[:3, 0], out[:3, 1], out[:3, 2] = right, down, fwd
        out[:3, 3] = [x + self.forward_offset * math.cos(yaw), y + self.forward_offset * math.sin(yaw),
                      self.mount_height]
        return out


def true_free_mask(grid: OccupancyGrid) -> np.ndarray:
    """[ny, nx] bool: cells of the simulated home whose centre is inside the room and under no
    furniture that reaches into the grid's obstacle band (the area exploration should see)."""
    from semantic_gs_slam.synthetic.scenes import ROOM, Box, home_layout

    cfg = grid.cfg
    cx, cy = grid.centre_of(*np.meshgrid(np.arange(grid.nx), np.arange(grid.ny), indexing="xy"))
    free = (cx > 0) & (cx < ROOM[0]) & (cy > 0) & (cy < ROOM[1])
    for s in home_layout():
        if isinstance(s, Box):
            if s.hi[2] < cfg.band_min_z or s.lo[2] > cfg.band_max_z:
                continue
            free &= ~((cx >= s.lo[0]) & (cx <= s.hi[0]) & (cy >= s.lo[1]) & (cy <= s.hi[1]))
        else:
            if s.z1 < cfg.band_min_z or s.z0 > cfg.band_max_z:
                continue
            free &= ~((cx - s.cx) ** 2 + (cy - s.cy) ** 2 <= s.r**2)
    return free


def coverage(grid: OccupancyGrid, truth: np.ndarray | None = None) -> float:
    """Fraction (0..1) of the true free area that the grid has seen free."""
    truth = true_free_mask(grid) if truth is None else truth
    return float(((grid.states() == 0) & truth).sum()) / max(1, int(truth.sum()))


@dataclass(frozen=True)
class OdometryConfig:
    """Errors of the simulated wheel odometry (what a real base's encoders do to its pose estimate).

    Attributes:
        trans_scale_error: systematic error of the distance travelled (0.02: 2 % too long, e.g. a
            wheel radius off by 2 %).
        rot_scale_error: systematic error of the angle turned (fraction).
        noise: standard deviation of a random error per update, as a fraction of that update's
            distance and angle.
        seed: random seed of the noise.
    """

    trans_scale_error: float = 0.02
    rot_scale_error: float = 0.02
    noise: float = 0.01
    seed: int = 0

    def check(self) -> None:
        for name in ("trans_scale_error", "rot_scale_error"):
            if not -0.5 <= getattr(self, name) <= 0.5:
                raise ConfigError(f"odometry {name} must be within [-0.5, 0.5], got {getattr(self, name)}")
        if not 0.0 <= self.noise <= 0.5:
            raise ConfigError(f"odometry noise must be within [0, 0.5], got {self.noise}")


class WheelOdometry:
    """Dead reckoning from successive true base poses with systematic and random errors.

    The first pose is taken as it is (the robot knows where it starts: the map frame); each later
    true motion (in the base frame) is scaled by the systematic errors, perturbed by the noise and
    integrated, so the estimate drifts with the distance travelled and the angle turned, like real
    wheel odometry.
    """

    def __init__(self, cfg: OdometryConfig | None = None) -> None:
        self.cfg = cfg or OdometryConfig()
        self.cfg.check()
        self._rng = np.random.default_rng(self.cfg.seed)
        self._true: tuple[float, float, float] | None = None
        self.pose: tuple[float, float, float] | None = None  # the estimate (x, y, yaw)

    def update(self, x: float, y: float, yaw: float) -> tuple[float, float, float]:
        """Feed the next true base pose; returns the odometry estimate (x, y, yaw)."""
        if self._true is None or self.pose is None:
            self._true = self.pose = (x, y, yaw)
            return self.pose
        tx, ty, tyaw = self._true
        c, s = math.cos(tyaw), math.sin(tyaw)
        fwd = c * (x - tx) + s * (y - ty)  # the true motion in the previous base frame
        side = -s * (x - tx) + c * (y - ty)
        dyaw = math.atan2(math.sin(yaw - tyaw), math.cos(yaw - tyaw))
        n = self.cfg.noise
        kt = 1.0 + self.cfg.trans_scale_error + (n * float(self._rng.standard_normal()) if n else 0.0)
        kr = 1.0 + self.cfg.rot_scale_error + (n * float(self._rng.standard_normal()) if n else 0.0)
        ex, ey, eyaw = self.pose
        c, s = math.cos(eyaw), math.sin(eyaw)
        self.pose = (ex + kt * (c * fwd - s * side), ey + kt * (s * fwd + c * side),
                     math.atan2(math.sin(eyaw + kr * dyaw), math.cos(eyaw + kr * dyaw)))
        self._true = (x, y, yaw)
        return self.pose
