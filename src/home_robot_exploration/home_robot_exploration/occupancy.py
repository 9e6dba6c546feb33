"""A 2-D occupancy grid (map frame, z up, metres) updated from depth images (no ROS).

Each depth pixel (a subsample of them) is back-projected to a world point. A point below
``floor_max_z`` is floor: the cells on the 2-D segment from the camera to it are free, its own cell
too. A point inside the obstacle band ``[band_min_z, band_max_z]`` (what the base would hit) marks
its cell occupied and the cells before it free. Points above the band (ceiling, high shelves) and
points beyond ``max_range_m`` update nothing. Evidence is accumulated in log-odds per cell, at most
one free and one hit update per cell per frame (a hit wins in its own frame); a cell never touched
is unknown.

Grid layout matches ``nav_msgs/OccupancyGrid``: ``cells[iy, ix]``, row-major with x fastest,
cell ``(ix, iy)`` covers ``[ox + ix * res, ox + (ix + 1) * res)`` in x (same for y).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from home_robot_exploration.errors import ConfigError, FrameError

UNKNOWN, FREE, OCCUPIED = -1, 0, 100


@dataclass(frozen=True)
class GridConfig:
    """Occupancy grid geometry and sensor model.

    Attributes:
        resolution: cell side (m).
        origin_x, origin_y: map-frame position of the lower-left corner of cell (0, 0) (m).
        width_m, height_m: extent in x and y (m).
        floor_max_z: points lower than this are floor (m).
        band_min_z, band_max_z: points in this height band are obstacles (m).
        max_range_m: depth beyond this is ignored (m).
        pixel_stride: use every n-th pixel in both image directions.
        hit_logodds, free_logodds: evidence of one hit (> 0) / one free pass (< 0).
        clamp_logodds: |log-odds| is clamped to this (keeps the grid able to change its mind).
    """

    resolution: float = 0.05
    origin_x: float = -2.0
    origin_y: float = -2.0
    width_m: float = 12.0
    height_m: float = 12.0
    floor_max_z: float = 0.08
    band_min_z: float = 0.08
    band_max_z: float = 1.6
    max_range_m: float = 6.0
    pixel_stride: int = 3
    hit_logodds: float = 0.9
    free_logodds: float = -0.4
    clamp_logodds: float = 4.0

    def check(self) -> None:
        """Raise :class:`ConfigError` when a value is unusable."""
        if not (0.005 <= self.resolution <= 1.0):
            raise ConfigError(f"resolution must be in [0.005, 1] m, got {self.resolution}")
        if not (self.width_m > 0 and self.height_m > 0):
            raise ConfigError(f"width_m and height_m must be > 0, got {self.width_m}, {self.height_m}")
        cells = (self.width_m / self.resolution) * (self.height_m / self.resolution)
        if cells > 4e6:
            raise ConfigError(f"grid of {cells:.0f} cells is too large (at most 4e6)")
        if not self.band_min_z < self.band_max_z:
            raise ConfigError(f"band_min_z ({self.band_min_z}) must be < band_max_z ({self.band_max_z})")
        if self.floor_max_z > self.band_min_z:
            raise ConfigError(f"floor_max_z ({self.floor_max_z}) must be <= band_min_z ({self.band_min_z})")
        if not self.max_range_m > 0 or self.pixel_stride < 1:
            raise ConfigError(f"max_range_m must be > 0 and pixel_stride >= 1, got {self.max_range_m}, "
                              f"{self.pixel_stride}")
        if not (self.hit_logodds > 0 > self.free_logodds and self.clamp_logodds > 0):
            raise ConfigError("need hit_logodds > 0 > free_logodds and clamp_logodds > 0")


class OccupancyGrid:
    """Log-odds occupancy grid; see the module docstring."""

    def __init__(self, cfg: GridConfig | None = None) -> None:
        self.cfg = cfg or GridConfig()
        self.cfg.check()
        self.nx = int(round(self.cfg.width_m / self.cfg.resolution))
        self.ny = int(round(self.cfg.height_m / self.cfg.resolution))
        self.logodds = np.zeros((self.ny, self.nx), dtype=np.float32)  # [ny, nx]
        self.observed = np.zeros((self.ny, self.nx), dtype=bool)  # [ny, nx]
        self.frames = 0

    # --- coordinates --------------------------------------------------------------------------------

    def cell_of(self, x: float | np.ndarray, y: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map-frame metres -> integer cell indices (ix, iy); may lie outside the grid."""
        r = self.cfg.resolution
        return (np.floor((np.asarray(x) - self.cfg.origin_x) / r).astype(np.int64),
                np.floor((np.asarray(y) - self.cfg.origin_y) / r).astype(np.int64))

    def centre_of(self, ix: int | np.ndarray, iy: int | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cell indices -> map-frame metres of the cell centre."""
        r = self.cfg.resolution
        return (self.cfg.origin_x + (np.asarray(ix) + 0.5) * r, self.cfg.origin_y + (np.asarray(iy) + 0.5) * r)

    def inside(self, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
        return (ix >= 0) & (ix < self.nx) & (iy >= 0) & (iy < self.ny)

    # --- state --------------------------------------------------------------------------------------

    def states(self) -> np.ndarray:
        """[ny, nx] int8: -1 unknown, 0 free, 100 occupied (``nav_msgs/OccupancyGrid`` values)."""
        out = np.full((self.ny, self.nx), UNKNOWN, dtype=np.int8)
        out[self.observed & (self.logodds <= 0)] = FREE
        out[self.observed & (self.logodds > 0)] = OCCUPIED
        return out

    def free_area_m2(self) -> float:
        return float(((self.logodds <= 0) & self.observed).sum()) * self.cfg.resolution**2

    def mark_free_disc(self, x: float, y: float, radius: float) -> None:
        """Cells within ``radius`` of (x, y) are free (where the robot stands, the floor is free)."""
        ix, iy = self.cell_of(x, y)
        n = int(np.ceil(radius / self.cfg.resolution))
        dx, dy = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1), indexing="xy")
        keep = (dx**2 + dy**2) * self.cfg.resolution**2 <= radius**2
        cx, cy = ix + dx[keep], iy + dy[keep]
        ok = self.inside(cx, cy)
        cx, cy = cx[ok], cy[ok]
        self.observed[cy, cx] = True
        self.logodds[cy, cx] = np.minimum(self.logodds[cy, cx], self.cfg.free_logodds)

    # --- update -------------------------------------------------------------------------------------

    def integrate(self, depth: np.ndarray, k: np.ndarray, c2w: np.ndarray) -> int:
        """Add one depth image.

        Args:
            depth: [H, W] metres along the optical axis; 0, NaN or inf = no return.
            k: [3, 3] pinhole intrinsics (fx, fy, cx, cy).
            c2w: [4, 4] camera-to-map pose, OpenCV camera (x right, y down, z forward).

        Returns:
            The number of depth points used.

        Raises:
            FrameError: wrong shapes or a non-finite pose.
        """
        depth = np.asarray(depth, dtype=np.float64)
        k, c2w = np.asarray(k, dtype=np.float64), np.asarray(c2w, dtype=np.float64)
        if depth.ndim != 2 or k.shape != (3, 3) or c2w.shape != (4, 4):
            raise FrameError(f"need depth [H, W], K [3, 3], c2w [4, 4]; got {depth.shape}, {k.shape}, {c2w.shape}")
        if not (np.isfinite(c2w).all() and np.isfinite(k).all()) or k[0, 0] <= 0 or k[1, 1] <= 0:
            raise FrameError("the camera pose or intrinsics are not finite / positive")
        cfg = self.cfg
        s = cfg.pixel_stride
        d = depth[::s, ::s]
        v, u = np.meshgrid(np.arange(0, depth.shape[0], s), np.arange(0, depth.shape[1], s), indexing="ij")
        ok = np.isfinite(d) & (d > 0) & (d <= cfg.max_range_m)
        d, u, v = d[ok], u[ok], v[ok]
        pc = np.stack([(u - k[0, 2]) / k[0, 0] * d, (v - k[1, 2]) / k[1, 1] * d, d], 1)  # [N, 3] camera
        pw = pc @ c2w[:3, :3].T + c2w[:3, 3]  # [N, 3] map
        z = pw[:, 2]
        is_floor = z < cfg.floor_max_z
        is_hit = (z >= cfg.band_min_z) & (z <= cfg.band_max_z)
        use = is_floor | is_hit
        pw, is_hit = pw[use], is_hit[use]
        self.frames += 1
        if len(pw) == 0:
            return 0
        o = c2w[:2, 3]
        seg = pw[:, :2] - o  # [N, 2]
        length = np.linalg.norm(seg, axis=1)
        step = cfg.resolution * 0.5
        n_max = int(np.ceil(length.max() / step)) + 1
        t = np.arange(n_max) * step  # [S]
        # free samples along each segment: up to the end (floor) or one cell short of it (hit)
        stop = np.where(is_hit, length - cfg.resolution, length)  # [N]
        valid = t[None, :] <= stop[:, None]  # [N, S]
        unit = seg / np.maximum(length, 1e-9)[:, None]
        sx = o[0] + unit[:, 0:1] * t[None, :]
        sy = o[1] + unit[:, 1:2] * t[None, :]
        fx, fy = self.cell_of(sx[valid], sy[valid])
        free_idx = self._flat_unique(fx, fy)
        hx, hy = self.cell_of(pw[is_hit, 0], pw[is_hit, 1])
        hit_idx = self._flat_unique(hx, hy)
        free_idx = np.setdiff1d(free_idx, hit_idx, assume_unique=True)
        lo = self.logodds.reshape(-1)
        ob = self.observed.reshape(-1)
        lo[free_idx] += cfg.free_logodds
        lo[hit_idx] += cfg.hit_logodds
        np.clip(lo, -cfg.clamp_logodds, cfg.clamp_logodds, out=lo)
        ob[free_idx] = True
        ob[hit_idx] = True
        return int(len(pw))

    def _flat_unique(self, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
        ok = self.inside(ix, iy)
        return np.unique(iy[ok] * self.nx + ix[ok])
