"""Frame-rate tracking front end: projective point-to-plane ICP of every live frame against a reference model.

The reference model is a keyframe's view of the map: its depth (and optionally normals and colour) rendered in the
keyframe's camera, plus that camera's pose. It is cheap to query (one pixel lookup per live point), so the front
end can track every frame while a mapping back end refines the map and publishes a new reference now and then.

* :func:`build_reference` turns a keyframe view into a :class:`ReferenceModel`: a pyramid of world vertex and normal
  maps (each level half the size of the one below), and at the finest level an intensity image with its gradients.
* :func:`prepare_live` turns a live RGB-D frame into a :class:`LiveFrame`: camera-frame points per pyramid level.
* :func:`track` estimates the live pose coarse to fine by Gauss-Newton on Huber-weighted point-to-plane residuals
  (plus an optional photometric term at the finest level), with a weak prior toward the initial guess, and scores
  the result (:class:`TrackQuality`: coverage, agreement, residual, condition of the normal equations) as trusted
  or lost.
* :func:`relocalise` tries the nearest keyframes' poses and perturbed guesses around them and accepts the best
  result by the same score.
* :class:`FrameTracker` keeps the state of one camera (reference, constant-velocity guess, lost flag); its
  reference swap is guarded by a lock, so a mapping thread may publish while the tracking thread runs.

The per-step sums are computed by the compiled kernel :func:`semantic_gs_slam.tracking.numba_kernels.icp_accumulate`
(``nogil=True``: a mapping thread runs beside it) and, as the reference, by :func:`normal_equations_reference`
(vectorised NumPy, the same sums in another order); ``test_tracking_frontend.py`` checks that they agree.
All arrays are NumPy (float64 poses and points): tracking on a CPU touches no torch tensor.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from semantic_gs_slam.config import Intrinsics
from semantic_gs_slam.devices import numba_available
from semantic_gs_slam.errors import ConfigError, FrameError, TrackingError
from semantic_gs_slam.tracking.icp_numba import _se3_exp, _so3_log

__all__ = ["FrameTracker", "FrontendConfig", "LiveFrame", "ModelLevel", "ReferenceModel", "RelocalisationError",
           "TrackQuality", "TrackResult", "build_reference", "downsample_frame", "normal_equations",
           "normal_equations_reference", "perturbed_guesses", "prepare_live", "relocalise", "track"]


class RelocalisationError(TrackingError):
    """No candidate pose of :func:`relocalise` was trusted by the tracking-quality score."""


@dataclass(frozen=True)
class FrontendConfig:
    """Settings of the front end's ICP and of its lost/trusted decision.

    Levels are numbered from the finest (0, the image size) up; per-level tuples list the finest level first.
    """

    levels: int = 3  # pyramid levels (each halves the image)
    iters: tuple[int, ...] = (3, 4, 6)  # Gauss-Newton steps per level (finest first); a level stops earlier once a
    # step's largest component is below min_step (on the kitchen, (6, 6, 8) gave the same ATE at 1.5x the time)
    point_stride: tuple[int, ...] = (2, 1, 1)  # live points: every k-th pixel of that level's image (finest first)
    max_dist: tuple[float, ...] = (0.05, 0.10, 0.20)  # metres; associations farther apart are rejected (per level)
    sigma_geo: float = 0.01  # metres; Huber threshold and scale of point-to-plane residuals (the least: see below)
    sigma_geo_z2: float = 0.002  # 1/m; a point z metres deep in the reference has the scale max(sigma_geo,
    # sigma_geo_z2 * z^2): a depth sensor's noise grows with the square of the depth (0: the same everywhere)
    photometric_weight: float = 1.0  # weight of the intensity term at the finest level when colour is given (0:
    # geometry only); on the kitchen (frames 0-249) ATE 2.50 -> 1.64 cm at stride 1, 2.18 -> 1.76 at stride 2
    sigma_col: float = 0.05  # intensity units; Huber threshold and scale of the intensity residuals
    prior_sigma_trans: float = 0.2  # metres; weak prior toward the initial guess (keeps free directions still)
    prior_sigma_rot: float = 0.2  # radians
    min_step: float = 1e-5  # a level ends once a step's largest component (rad or m) is below this
    depth_min: float = 0.1  # metres; live and model depth outside [depth_min, depth_max] is not used
    depth_max: float = 4.0
    model_smoothing: int = 1  # the reference depth is averaged over this window (odd; 1: off), over neighbours
    # within depth_jump of the centre only (no blur across edges): sensor depth as a stand-in for a rendered map
    noisy_smoothing: int = 3  # ... and over this window (odd; 1: never) when the depth is rougher than:
    noisy_roughness: float = 0.0015  # 1/m; depth_roughness() above which a reference counts as noisy (0: never). A
    # Kinect v1 at 320 x 240 reads 0.0007, with its noise added once more 0.0014, twice 0.0025 (kitchen, 0-499)
    trust_z2_per_roughness: float = 2.5  # the trust test (agreement) of a frame tracked against a reference whose
    # depth_roughness() is r judges its points at max(sigma_geo_z2, this * r) z^2 instead of sigma_geo_z2 z^2: a
    # noisier camera's residuals at its own noise (the weights, and so the pose, are unchanged). A Kinect v1
    # (r 0.0007) stays at sigma_geo_z2; 0: off
    speckle_fill: float = 0.02  # a reference whose depth has more isolated holes than this fraction of its pixels
    # (depth_speckle: a hole with 3 or 4 of its 4 neighbours valid) has them filled (fill_isolated_holes) before its
    # normals: a normal needs its neighbours, so 30 % of pixels dropped at random left a sixth of the normals. A
    # Kinect v1 at 320 x 240 reads 0.001-0.002 (kitchen); 0: never
    normal_radius: int = 2  # normals from central differences over this many pixels (finest level; 1 coarser)
    depth_jump: float = 0.05  # a neighbour more than this fraction of the depth away breaks the normal / pyramid cell
    min_correspondences: int = 200  # fewer at the finest level: lost
    min_coverage: float = 0.25  # lost when fewer of the live points with depth find a close model point
    min_agreement: float = 0.8  # lost when fewer of the points landing on the model are within 3 scales
    max_condition: float = 1e5  # lost when the Jacobi-scaled normal equations are worse conditioned (a lone plane)
    backend: str = "auto"  # "numba" (compiled kernel), "numpy" (the reference) or "auto" (numba when installed)

    def check(self) -> None:
        """Raise :class:`ConfigError` when a value is out of range."""
        if self.levels < 1:
            raise ConfigError(f"levels must be >= 1, got {self.levels}")
        for name in ("iters", "point_stride", "max_dist"):
            if len(getattr(self, name)) != self.levels:
                raise ConfigError(f"{name} needs one value per level ({self.levels}), got {getattr(self, name)}")
        if any(i < 0 for i in self.iters) or any(s < 1 for s in self.point_stride):
            raise ConfigError("iters must be >= 0 and point_stride >= 1")
        if not all(d > 0 for d in self.max_dist) or not self.sigma_geo > 0 or not self.sigma_col > 0:
            raise ConfigError("max_dist, sigma_geo and sigma_col must be > 0")
        if not (math.isfinite(self.sigma_geo_z2) and self.sigma_geo_z2 >= 0):
            raise ConfigError(f"sigma_geo_z2 must be a finite number >= 0, got {self.sigma_geo_z2}")
        if not (self.prior_sigma_trans > 0 and self.prior_sigma_rot > 0):
            raise ConfigError("prior sigmas must be > 0")
        if not 0 <= self.depth_min < self.depth_max:
            raise ConfigError(f"need 0 <= depth_min < depth_max, got {self.depth_min}, {self.depth_max}")
        for name in ("model_smoothing", "noisy_smoothing"):
            if getattr(self, name) < 1 or getattr(self, name) % 2 == 0:
                raise ConfigError(f"{name} must be an odd window >= 1, got {getattr(self, name)}")
        if not (math.isfinite(self.trust_z2_per_roughness) and self.trust_z2_per_roughness >= 0):
            raise ConfigError(f"trust_z2_per_roughness must be a finite number >= 0, got "
                              f"{self.trust_z2_per_roughness}")
        if not (math.isfinite(self.noisy_roughness) and self.noisy_roughness >= 0):
            raise ConfigError(f"noisy_roughness must be a finite number >= 0, got {self.noisy_roughness}")
        if not 0 <= self.speckle_fill <= 1:
            raise ConfigError(f"speckle_fill must be in [0, 1], got {self.speckle_fill}")
        if self.normal_radius < 1:
            raise ConfigError(f"normal_radius must be >= 1, got {self.normal_radius}")
        if self.backend not in ("auto", "numba", "numpy"):
            raise ConfigError(f"backend must be 'auto', 'numba' or 'numpy', got {self.backend!r}")


@dataclass
class ModelLevel:
    """One pyramid level of a reference model, flattened to pixels."""

    k: Intrinsics  # the level's camera
    vm: np.ndarray  # [H*W, 3] float64 world vertices
    nm: np.ndarray  # [H*W, 3] float64 world unit normals
    nvalid: np.ndarray  # [H*W] bool: vertex and normal usable
    col: np.ndarray | None  # [H*W, 4] float64 intensity, d/du, d/dv, usable (1/0); finest level only, or None


@dataclass
class ReferenceModel:
    """A keyframe's view of the map as the front end queries it."""

    c2w: np.ndarray  # [4, 4] float64 the keyframe's camera
    w2c: np.ndarray  # [4, 4] float64 its inverse
    levels: list[ModelLevel]  # finest first
    keyframe_id: int = -1  # the caller's id of the keyframe (e.g. its frame index)
    roughness: float = 0.0  # depth_roughness() of its depth (1/m; 0: not measured)
    smoothing: int = 1  # the window its depth was averaged over (1: raw)
    speckle: float = 0.0  # depth_speckle() of its depth (its isolated holes were filled above cfg.speckle_fill)


@dataclass
class LiveFrame:
    """A live frame's points per pyramid level (finest first)."""

    points: list[np.ndarray]  # per level [M_l, 3] float64 camera-frame points (z = 0: no depth)
    valid: list[np.ndarray]  # per level [M_l] bool
    intensity: np.ndarray | None  # [M_0] float64 intensity of the finest level's points, or None


@dataclass
class TrackQuality:
    """How far a tracked pose can be trusted (all figures at the finest level's last step)."""

    correspondences: int  # live points with a close model point
    coverage: float  # correspondences / live points with depth
    agreement: float  # of the live points landing on a usable model pixel, the share within 3 scales (sigma_geo)
    residual: float  # RMS point-to-plane residual (m)
    condition: float  # condition number of the Jacobi-scaled 6x6 normal equations (inf: singular)
    trusted: bool  # every figure within FrontendConfig's limits
    reason: str = ""  # why not trusted ("" when trusted)


@dataclass
class TrackResult:
    """The outcome of :func:`track` or :func:`relocalise`."""

    c2w: np.ndarray  # [4, 4] float64 estimated pose
    quality: TrackQuality
    steps: int = 0  # Gauss-Newton steps taken over all levels
    keyframe_id: int = -1  # the reference model it was tracked against


# ---------------------------------------------------------------- inputs

def _check_pose(name: str, c2w: np.ndarray) -> np.ndarray:
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
        raise FrameError(f"{name} must be a finite [4, 4] pose, got shape {c2w.shape}")
    return c2w


def _check_shape(name: str, img: np.ndarray | None, k: Intrinsics, channels: int | None) -> np.ndarray | None:
    """``img`` as an array of the camera's shape and a float type (else FrameError); None stays None."""
    if img is None:
        return None
    img = np.asarray(img)
    want = (k.height, k.width) if channels is None else (k.height, k.width, channels)
    if img.shape != want:
        raise FrameError(f"{name} must have shape {list(want)} (the camera's {k.width}x{k.height}), got "
                         f"{list(img.shape)}")
    if not np.issubdtype(img.dtype, np.floating):
        raise FrameError(f"{name} must be a float array (metres / [0, 1] colour), got {img.dtype}")
    return img


def _check_image(name: str, img: np.ndarray | None, k: Intrinsics, channels: int | None) -> np.ndarray | None:
    img = _check_shape(name, img, k, channels)
    if img is None:
        return None
    if not np.isfinite(img).all():
        raise FrameError(f"{name} has NaN or infinite values")
    return img.astype(np.float64, copy=False)


def _use_numba(cfg: FrontendConfig) -> bool:
    if cfg.backend == "numba":
        if not numba_available():
            raise ConfigError("backend 'numba' needs the numba package; set it to 'auto' or 'numpy'")
        return True
    return cfg.backend == "auto" and numba_available()


def _pyramid_cameras(k: Intrinsics, levels: int) -> list[Intrinsics]:
    cams = [k]
    for _ in range(1, levels):
        c = cams[-1]
        if c.width < 8 or c.height < 8:
            raise ConfigError(f"{levels} pyramid levels shrink a {k.width}x{k.height} image below 8 pixels")
        cams.append(Intrinsics(c.width // 2, c.height // 2, c.fx / 2, c.fy / 2, (c.cx + 0.5) / 2 - 0.5,
                               (c.cy + 0.5) / 2 - 0.5))
    return cams


def _half_depth(depth: np.ndarray, jump: float) -> np.ndarray:
    """[H/2, W/2] depth: the mean of each 2x2 cell whose four pixels have depth and agree within ``jump`` of the
    depth; 0 elsewhere (no averaging across an edge)."""
    h, w = depth.shape[0] // 2 * 2, depth.shape[1] // 2 * 2
    c = depth[:h, :w].reshape(h // 2, 2, w // 2, 2).transpose(0, 2, 1, 3).reshape(h // 2, w // 2, 4)
    lo, hi = c.min(-1), c.max(-1)
    mean = c.mean(-1)
    return np.where((lo > 0) & (hi - lo < jump * mean), mean, 0.0)


def _half(depth: np.ndarray, jump: float, fast: bool) -> np.ndarray:
    if not fast:
        return _half_depth(depth, jump)
    out = np.empty((depth.shape[0] // 2, depth.shape[1] // 2))
    _fast().half_depth(depth, float(jump), out)
    return out


def downsample_frame(depth: np.ndarray, rgb: np.ndarray | None, k: Intrinsics, times: int, cfg: FrontendConfig
                     ) -> tuple[np.ndarray, np.ndarray | None, Intrinsics]:
    """Halve a frame ``times`` times for the front end (e.g. a 640x480 camera tracked at 320x240).

    Args:
        depth: [H, W] metres (0: none); a 2x2 cell keeps the mean of its depths when all four agree within
            ``cfg.depth_jump`` of it, else 0 (no averaging across an edge).
        rgb: [H, W, 3] in [0, 1] or None; the mean of each 2x2 cell.
        k: the camera of ``depth``.

    Returns:
        depth [H / 2^times, W / 2^times] float64, rgb likewise (or None), and their camera.
    """
    cams = _pyramid_cameras(k, times + 1)
    depth, rgb = np.asarray(depth), None if rgb is None else np.asarray(rgb)
    if times > 0 and rgb is not None and _use_numba(cfg) and rgb.shape == depth.shape + (3,):
        # one compiled call: beside a thread that keeps the GIL, each NumPy operation below waits to get it back
        # (bench/frontend_gil.py)
        h, w = depth.shape[0] >> times, depth.shape[1] >> times
        out_d, out_c = np.empty((h, w)), np.empty((h, w, 3))
        _fast().shrink_frame(np.ascontiguousarray(depth), np.ascontiguousarray(rgb), times, float(cfg.depth_jump),
                             out_d, out_c)
        return out_d, out_c, cams[-1]
    depth = np.ascontiguousarray(depth, dtype=np.float64)
    rgb = None if rgb is None else np.asarray(rgb, np.float64)
    for _ in range(times):
        depth = _half(depth, cfg.depth_jump, _use_numba(cfg))
        if rgb is not None:
            h, w = rgb.shape[0] // 2 * 2, rgb.shape[1] // 2 * 2
            c = rgb[:h, :w]  # four strided sums: a quarter of the time of reshape(...).mean(axis=(1, 3))
            rgb = (c[0::2, 0::2] + c[1::2, 0::2] + c[0::2, 1::2] + c[1::2, 1::2]) * 0.25
    return depth, rgb, cams[-1]


ROUGHNESS_MIN_PIXELS = 500  # depth_roughness: fewer usable pixels are no evidence (0.0)


def depth_roughness(depth: np.ndarray, jump: float = 0.05, min_pixels: int = ROUGHNESS_MIN_PIXELS) -> float:
    """How noisy a depth image is: the median over pixels of |d - the mean of its 4 neighbours| / d^2 (1/m), where
    the 4 neighbours have depth within ``jump`` times d (no edges). A depth sensor's noise grows with d^2, so this is
    about the same near and far; 0.0 when fewer than ``min_pixels`` pixels qualify (no evidence). NumPy, the
    reference of the compiled :func:`~semantic_gs_slam.tracking.frontend_numba.depth_roughness` that
    :func:`build_reference` calls when numba is there.

    Args:
        depth: [H, W] metres, 0 = missing.
    """
    c = depth[1:-1, 1:-1]
    nbs = (depth[:-2, 1:-1], depth[2:, 1:-1], depth[1:-1, :-2], depth[1:-1, 2:])
    ok = c > 0
    for nb in nbs:
        ok &= (nb > 0) & (np.abs(nb - c) < jump * c)
    if int(ok.sum()) < min_pixels:
        return 0.0
    cc = c[ok]
    lap = cc - 0.25 * sum(nb[ok] for nb in nbs)
    return float(np.median(np.abs(lap) / (cc * cc)))


def depth_speckle(depth: np.ndarray) -> float:
    """The fraction of the pixels of ``depth`` [H, W] (metres, 0 = missing) that are isolated holes: no depth, and
    3 or 4 of their 4 neighbours with depth. A structured-light camera's holes are regions (edges, out of range,
    shiny surfaces): a Kinect v1 reads 0.001-0.002; pixels dropped at random read about their fraction times 0.6."""
    v = depth > 0
    p = np.pad(v, 1)
    nb = p[:-2, 1:-1].astype(np.int8) + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:]
    return float(((~v) & (nb >= 3)).mean())


def fill_isolated_holes(depth: np.ndarray, jump: float = 0.05) -> np.ndarray:
    """``depth`` [H, W] with each hole that has 4 or more of its 8 neighbours with depth, all within ``jump`` times
    their mean of each other (one surface: no hole at an edge is filled), set to that mean; one pass."""
    h, w = depth.shape
    p = np.pad(depth, 1)
    nb = np.stack([p[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx])
    ok = nb > 0  # [8, H, W]
    n = ok.sum(0)
    mean = np.where(ok, nb, 0.0).sum(0) / np.maximum(n, 1)
    spread = np.where(ok, nb, -np.inf).max(0) - np.where(ok, nb, np.inf).min(0)
    fill = (depth <= 0) & (n >= 4) & (spread <= jump * mean)
    return np.where(fill, mean, depth)


def _fill_holes(depth: np.ndarray, cfg: FrontendConfig, fast: bool) -> np.ndarray:
    """:func:`fill_isolated_holes` of ``depth`` [H, W] float64 with depth outside ``cfg``'s range taken as missing,
    compiled when ``fast`` (one call, the GIL let go once)."""
    if fast:
        out = np.empty_like(depth)
        _fast().fill_isolated_holes(np.ascontiguousarray(depth), float(cfg.depth_min), float(cfg.depth_max),
                                    float(cfg.depth_jump), out)
        return out
    return fill_isolated_holes(np.where((depth >= cfg.depth_min) & (depth <= cfg.depth_max), depth, 0.0),
                               cfg.depth_jump)


def _smooth_depth(depth: np.ndarray, size: int, jump: float) -> np.ndarray:
    """``depth`` [H, W] averaged over a ``size`` x ``size`` window, over the neighbours with depth within ``jump``
    times the centre's (edges stay sharp); pixels without depth stay 0."""
    if size <= 1:
        return depth
    r = size // 2
    h, w = depth.shape
    pad = np.pad(depth, r)
    num = np.zeros_like(depth)
    den = np.zeros_like(depth)
    lim = jump * depth
    for dy in range(size):
        for dx in range(size):
            nb = pad[dy:dy + h, dx:dx + w]
            use = (nb > 0) & (np.abs(nb - depth) < lim)
            num += np.where(use, nb, 0.0)
            den += use
    return np.where(depth > 0, num / np.maximum(den, 1.0), 0.0)


def _backproject(depth: np.ndarray, k: Intrinsics) -> np.ndarray:
    """[H, W, 3] camera-frame points of ``depth`` [H, W]."""
    h, w = depth.shape
    u = (np.arange(w, dtype=np.float64) - k.cx) / k.fx
    v = (np.arange(h, dtype=np.float64) - k.cy) / k.fy
    return np.stack([depth * u[None, :], depth * v[:, None], depth], -1)


def _normals(vc: np.ndarray, valid: np.ndarray, r: int, jump: float) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame unit normals [H, W, 3] (facing the camera) of a vertex map by central differences over ``r``
    pixels, and where they are usable [H, W] (the four neighbours valid and not across a depth jump)."""
    h, w = valid.shape
    n = np.zeros_like(vc)
    ok = np.zeros_like(valid)
    dx = vc[r:-r, 2 * r:] - vc[r:-r, :-2 * r]  # [H-2r, W-2r, 3]
    dy = vc[2 * r:, r:-r] - vc[:-2 * r, r:-r]
    c = np.cross(dx, dy)
    norm = np.linalg.norm(c, axis=-1)
    z = vc[r:-r, r:-r, 2]
    lim = 2 * r * jump * z
    good = (valid[r:-r, r:-r] & valid[r:-r, 2 * r:] & valid[r:-r, :-2 * r] & valid[2 * r:, r:-r]
            & valid[:-2 * r, r:-r] & (norm > 1e-12) & (np.abs(dx[..., 2]) < lim) & (np.abs(dy[..., 2]) < lim))
    c = c / np.maximum(norm, 1e-12)[..., None]
    c = np.where((c * vc[r:-r, r:-r]).sum(-1, keepdims=True) > 0, -c, c)  # facing the camera
    n[r:-r, r:-r] = np.where(good[..., None], c, 0.0)
    ok[r:-r, r:-r] = good
    return n, ok


def _intensity(rgb: np.ndarray) -> np.ndarray:
    return rgb.mean(-1)


def build_reference(depth: np.ndarray, c2w: np.ndarray, k: Intrinsics, cfg: FrontendConfig,
                    rgb: np.ndarray | None = None, normals: np.ndarray | None = None,
                    keyframe_id: int = -1, roughness: float | None = None) -> ReferenceModel:
    """The reference model of a keyframe view (depth rendered from the map, or a sensor depth as a stand-in).

    The depth is averaged over ``cfg.model_smoothing`` pixels, or over ``cfg.noisy_smoothing`` when its
    :func:`depth_roughness` exceeds ``cfg.noisy_roughness`` (a noisier camera than a Kinect v1: a single raw image
    is then too noisy a reference to track against; the model records both).

    Args:
        depth: [H, W] metres along the optical axis, 0 = no surface.
        c2w: [4, 4] the keyframe's camera-to-world pose.
        k: the camera (H x W as ``depth``).
        cfg: front-end settings (levels, depth range, normal radius).
        rgb: [H, W, 3] colour in [0, 1] of the view, or None (no photometric term).
        normals: [H, W, 3] camera-frame unit normals of the view (e.g. rendered), or None (from the depth).
            Used at the finest level; coarser levels take theirs from the depth.
        keyframe_id: the caller's id of the keyframe, carried into :class:`TrackResult`.
        roughness: the depth's :func:`depth_roughness` when already known (a keyframe's reference rebuilt at a
            moved pose: its depth is the same), or None (measured here when a setting needs it).

    Returns:
        :class:`ReferenceModel`.

    Raises:
        FrameError: a shape, dtype or non-finite value is wrong.
        ConfigError: ``cfg`` is invalid.
    """
    cfg.check()
    c2w = _check_pose("c2w", c2w)
    d = _check_image("depth", depth, k, None)
    rgb = _check_image("rgb", rgb, k, 3)
    normals = _check_image("normals", normals, k, 3)
    d = np.where((d >= cfg.depth_min) & (d <= cfg.depth_max), d, 0.0)
    window, rough = cfg.model_smoothing, 0.0
    fast = _use_numba(cfg)
    smooth_noisy = cfg.noisy_roughness > 0 and cfg.noisy_smoothing > window
    if roughness is not None:
        rough = float(roughness)
    elif smooth_noisy or cfg.trust_z2_per_roughness > 0:
        rough = (_fast().depth_roughness(np.ascontiguousarray(d), float(cfg.depth_jump), ROUGHNESS_MIN_PIXELS) if fast
                 else depth_roughness(d, cfg.depth_jump, ROUGHNESS_MIN_PIXELS))
    if smooth_noisy and rough > cfg.noisy_roughness:
        window = cfg.noisy_smoothing
    speckle = 0.0
    if cfg.speckle_fill > 0:
        speckle = _fast().depth_speckle(np.ascontiguousarray(d)) if fast else depth_speckle(d)
    if speckle > cfg.speckle_fill:  # after the roughness: a filled hole is its neighbours' mean, not a measurement
        d = _fill_holes(d, cfg, fast)
    d = _smooth_depth(d, window, cfg.depth_jump)
    r, t = c2w[:3, :3], c2w[:3, 3]
    levels = []
    for lv, cam in enumerate(_pyramid_cameras(k, cfg.levels)):
        if lv > 0:
            d = _half(d, cfg.depth_jump, fast)
        valid = d > 0
        rad = cfg.normal_radius if lv == 0 else 1
        if fast:
            n_px = cam.width * cam.height
            vw, nw, nok = np.empty((n_px, 3)), np.empty((n_px, 3)), np.empty(n_px, np.bool_)
            _fast().model_level(d, float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy), c2w, rad,
                                float(cfg.depth_jump), vw, nw, nok)
        else:
            vc = _backproject(d, cam)
            nc, nok2 = _normals(vc, valid, rad, cfg.depth_jump)
            vw = np.where(valid.reshape(-1, 1), vc.reshape(-1, 3) @ r.T + t, 0.0)
            nw = nc.reshape(-1, 3) @ r.T
            nok = nok2.reshape(-1)
        if lv == 0 and normals is not None:
            nok = (valid & (np.abs(np.linalg.norm(normals, axis=-1) - 1) < 1e-2)).reshape(-1)
            nw = np.where(nok[:, None], normals.reshape(-1, 3) @ r.T, 0.0)
        col = None
        if lv == 0 and rgb is not None and cfg.photometric_weight > 0:
            im = _intensity(rgb)
            gx = np.zeros_like(im)
            gy = np.zeros_like(im)
            gx[:, 1:-1] = 0.5 * (im[:, 2:] - im[:, :-2])
            gy[1:-1] = 0.5 * (im[2:] - im[:-2])
            okc = valid.copy()
            okc[:, 1:-1] &= valid[:, 2:] & valid[:, :-2]
            okc[1:-1] &= valid[2:] & valid[:-2]
            okc[:, [0, -1]] = False
            okc[[0, -1]] = False
            col = np.ascontiguousarray(np.stack([im, gx, gy, okc.astype(np.float64)], -1).reshape(-1, 4))
        levels.append(ModelLevel(cam, np.ascontiguousarray(vw), np.ascontiguousarray(nw),
                                 np.ascontiguousarray(nok), col))
    return ReferenceModel(c2w, np.linalg.inv(c2w), levels, keyframe_id, rough, window, speckle)


def prepare_live(depth: np.ndarray, k: Intrinsics, cfg: FrontendConfig, rgb: np.ndarray | None = None,
                 fill_holes: bool = False) -> LiveFrame:
    """The live frame's points per pyramid level.

    Args:
        depth: [H, W] metres, 0 = missing. k: the camera. cfg: front-end settings.
        rgb: [H, W, 3] colour in [0, 1], or None (no photometric term).
        fill_holes: fill the isolated holes first (:func:`fill_isolated_holes`; a speckled camera, whose coarser
            levels would otherwise keep almost no point: a coarse cell needs its four pixels).

    Returns:
        :class:`LiveFrame`.

    Raises:
        FrameError: a shape, dtype or non-finite value is wrong.
    """
    cfg.check()
    fast = _use_numba(cfg)
    if fill_holes:
        depth = _fill_holes(_check_image("depth", depth, k, None), cfg, fast)
    if fast:
        return _prepare_live_fast(depth, k, cfg, rgb)
    d = _check_image("depth", depth, k, None)
    rgb = _check_image("rgb", rgb, k, 3)
    d = np.where((d >= cfg.depth_min) & (d <= cfg.depth_max), d, 0.0)
    pts, val = [], []
    il = None
    for lv, cam in enumerate(_pyramid_cameras(k, cfg.levels)):
        if lv > 0:
            d = _half(d, cfg.depth_jump, fast)
        s = cfg.point_stride[lv]
        if fast:
            m = (-(-cam.height // s)) * (-(-cam.width // s))
            p, ok = np.empty((m, 3)), np.empty(m, np.bool_)
            _fast().live_points(d, float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy), s, p, ok)
        else:
            p = np.ascontiguousarray(_backproject(d, cam)[::s, ::s].reshape(-1, 3))
            ok = p[:, 2] > 0
        pts.append(p)
        val.append(ok)
        if lv == 0 and rgb is not None and cfg.photometric_weight > 0:
            il = np.ascontiguousarray(_intensity(rgb)[::s, ::s].reshape(-1))
    return LiveFrame(pts, val, il)


def _prepare_live_fast(depth: np.ndarray, k: Intrinsics, cfg: FrontendConfig, rgb: np.ndarray | None) -> LiveFrame:
    """:func:`prepare_live` in one compiled call (:func:`~semantic_gs_slam.tracking.frontend_numba.live_frame`): the
    GIL is let go once, not once per NumPy operation (``bench/frontend_gil.py``); the same checks and errors."""
    depth = _check_shape("depth", depth, k, None)
    rgb = _check_shape("rgb", rgb, k, 3)
    cams = _pyramid_cameras(k, cfg.levels)
    sizes = [(-(-c.height // s)) * (-(-c.width // s)) for c, s in zip(cams, cfg.point_stride, strict=True)]
    offsets = np.cumsum([0, *sizes]).astype(np.int64)
    pts, ok = np.empty((int(offsets[-1]), 3)), np.empty(int(offsets[-1]), np.bool_)
    intensity = rgb is not None and cfg.photometric_weight > 0
    il = np.empty(sizes[0] if intensity else 1)
    bad_depth, bad_rgb = _fast().live_frame(
        np.ascontiguousarray(depth), np.zeros((1, 1, 3)) if rgb is None else np.ascontiguousarray(rgb),
        rgb is not None, float(cfg.depth_min), float(cfg.depth_max), float(cfg.depth_jump),
        np.array([c.fx for c in cams], np.float64), np.array([c.fy for c in cams], np.float64),
        np.array([c.cx for c in cams], np.float64), np.array([c.cy for c in cams], np.float64),
        np.array(cfg.point_stride, np.int64), offsets, intensity, pts, ok, il)
    if bad_depth:
        raise FrameError("depth has NaN or infinite values")
    if bad_rgb:
        raise FrameError("rgb has NaN or infinite values")
    return LiveFrame([pts[a:b] for a, b in zip(offsets[:-1], offsets[1:], strict=True)],
                     [ok[a:b] for a, b in zip(offsets[:-1], offsets[1:], strict=True)], il if intensity else None)


# ---------------------------------------------------------------- the normal equations

@functools.cache
def _kernel():
    from semantic_gs_slam.tracking import numba_kernels as nk

    return nk.icp_accumulate


@functools.cache
def _fast():
    """The front end's compiled kernels (:mod:`semantic_gs_slam.tracking.frontend_numba`; imports numba)."""
    from semantic_gs_slam.tracking import frontend_numba as fk

    return fk


def normal_equations(est: np.ndarray, points: np.ndarray, valid: np.ndarray, intensity: np.ndarray | None,
                     level: ModelLevel, w2c: np.ndarray, max_dist: float, cfg: FrontendConfig,
                     photometric: bool, gate_z2: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The sums of one Gauss-Newton step by the compiled kernel (``icp_accumulate``, ``nogil``).

    Args:
        est: [4, 4] float64 estimate (camera to world). points: [M, 3] float64 camera-frame live points.
        valid: [M] bool. intensity: [M] float64 live intensity, or None. level: the model level.
        w2c: [4, 4] the model's world-to-camera. max_dist: association gate (m).
        cfg: weights and scales. photometric: add the intensity term (needs ``intensity`` and ``level.col``).
        gate_z2: 1/m; a point z metres deep is associated up to max(``max_dist``, this * z^2) away (0: ``max_dist``;
            the trust test of a noisy camera's frame widens it, :func:`track`).

    Returns:
        ``A`` [6, 6], ``b`` [6] of ``A xi = b`` (xi = rotation vector, translation, applied on the left) and
        ``[correspondences, sum of squared residuals, residuals within 3 sigma, points on a usable model pixel]``
        [4], all float64.
    """
    photometric = bool(photometric and intensity is not None and level.col is not None)
    a = np.zeros((6, 6))
    b = np.zeros(6)
    stats = np.zeros(4)
    k = level.k
    _kernel()(est, w2c, points, valid, intensity if photometric else np.zeros(1),
              level.vm, level.nm, level.nvalid, level.col if photometric else np.zeros((1, 4)),
              float(k.fx), float(k.fy), float(k.cx), float(k.cy), int(k.width), int(k.height), float(max_dist),
              float(cfg.sigma_geo), float(cfg.sigma_geo_z2), 1.0, photometric, float(cfg.sigma_col),
              float(cfg.photometric_weight), a, b, stats, float(gate_z2))
    return a, b, stats


def normal_equations_reference(est: np.ndarray, points: np.ndarray, valid: np.ndarray,
                               intensity: np.ndarray | None, level: ModelLevel, w2c: np.ndarray, max_dist: float,
                               cfg: FrontendConfig, photometric: bool, gate_z2: float = 0.0
                               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`normal_equations` in vectorised NumPy (the reference; arguments and returns as there)."""
    photometric = bool(photometric and intensity is not None and level.col is not None)
    k = level.k
    x = points @ est[:3, :3].T + est[:3, 3]  # [M, 3] world
    c = x @ w2c[:3, :3].T + w2c[:3, 3]  # [M, 3] model camera
    front = valid & (c[:, 2] > 1e-3)
    z = np.where(front, c[:, 2], 1.0)
    uf = k.fx * c[:, 0] / z + k.cx
    vf = k.fy * c[:, 1] / z + k.cy
    u, v = np.rint(uf), np.rint(vf)
    inside = front & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
    pix = np.where(inside, v * k.width + u, 0).astype(np.int64)
    on = inside & level.nvalid[pix]
    n = level.nm[pix]
    diff = x - level.vm[pix]
    close = on & (np.linalg.norm(diff, axis=-1) < np.maximum(max_dist, gate_z2 * z * z))
    r = np.where(close, (diff * n).sum(-1), 0.0)
    sg = np.maximum(cfg.sigma_geo, cfg.sigma_geo_z2 * z * z)  # [M] each residual's scale
    w = np.where(np.abs(r) < sg, 1.0, sg / np.maximum(np.abs(r), 1e-30)) / (sg * sg) * close
    jac = np.concatenate([np.cross(x, n), n], -1)  # [M, 6]
    a = (jac * w[:, None]).T @ jac
    b = -(jac * w[:, None]).T @ r
    if photometric:
        col = level.col
        inb = inside & (uf >= 0) & (uf < k.width - 1) & (vf >= 0) & (vf < k.height - 1)
        u0 = np.where(inb, np.floor(uf), 0.0)
        v0 = np.where(inb, np.floor(vf), 0.0)
        fu, fv = (uf - u0)[:, None], (vf - v0)[:, None]
        q = (v0 * k.width + u0).astype(np.int64)
        smp = ((1 - fu) * (1 - fv) * col[q] + fu * (1 - fv) * col[q + 1] + (1 - fu) * fv * col[q + k.width]
               + fu * fv * col[q + k.width + 1])  # [M, 4]
        use = inb & (smp[:, 3] > 0.999)
        rc = np.where(use, smp[:, 0] - intensity, 0.0)
        du = np.stack([k.fx / z, np.zeros_like(z), -k.fx * c[:, 0] / (z * z)], -1)
        dv = np.stack([np.zeros_like(z), k.fy / z, -k.fy * c[:, 1] / (z * z)], -1)
        g = (smp[:, 1:2] * du + smp[:, 2:3] * dv) @ w2c[:3, :3]  # [M, 3] dI / d world point
        jc = np.concatenate([np.cross(x, g), g], -1)
        sc = cfg.sigma_col
        wc = np.where(np.abs(rc) < sc, 1.0, sc / np.maximum(np.abs(rc), 1e-30)) * cfg.photometric_weight / (sc * sc)
        wc = wc * use
        a = a + (jc * wc[:, None]).T @ jc
        b = b - (jc * wc[:, None]).T @ rc
    stats = np.array([close.sum(), (r * r).sum(), (close & (np.abs(r) < 3 * sg)).sum(), on.sum()], np.float64)
    return a, b, stats


def _condition(a: np.ndarray) -> float:
    """Condition number of ``a`` [6, 6] after Jacobi scaling (unit diagonal): units of rotation and translation
    drop out; large when the view leaves a direction free (a lone plane, a corridor)."""
    dg = np.diagonal(a)
    if not (dg > 0).all():
        return float("inf")
    s = 1.0 / np.sqrt(dg)
    ev = np.linalg.eigvalsh(a * s[:, None] * s[None, :])
    return float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")


# ---------------------------------------------------------------- tracking

def track(live: LiveFrame, model: ReferenceModel, guess_c2w: np.ndarray, cfg: FrontendConfig,
          levels: Sequence[int] | None = None) -> TrackResult:
    """The live frame's pose by coarse-to-fine projective ICP against ``model``, scored.

    Minimises ``sum_i rho(n_i . (T x_i - q_i)) / s_g^2 (+ w_c sum rho(I_m(pi(T x_i)) - I_l,i) / s_c^2)
    + |log(T guess^-1)|^2_prior`` over ``T`` (Huber ``rho``), with ``q_i``, ``n_i`` the model vertex and normal at
    the pixel the live point ``x_i`` projects to in the model camera.

    Args:
        live: :func:`prepare_live`'s points (the same ``cfg.levels``).
        model: :func:`build_reference`'s model.
        guess_c2w: [4, 4] initial estimate (e.g. constant velocity from the last two poses).
        cfg: front-end settings.
        levels: the levels to run, coarse to fine (default: all, coarsest first). The quality is scored at the
            last one.

    Returns:
        :class:`TrackResult` (its ``quality.trusted`` says lost or not; a lost result still carries the estimate).

    Raises:
        FrameError: ``guess_c2w`` is not a finite [4, 4] pose.
        ConfigError: ``cfg`` is invalid or the live frame and model have other level counts.
    """
    cfg.check()
    guess = _check_pose("guess_c2w", guess_c2w)
    if len(live.points) != len(model.levels) or len(model.levels) != cfg.levels:
        raise ConfigError(f"live frame ({len(live.points)}), model ({len(model.levels)}) and cfg ({cfg.levels}) "
                          "must have the same number of pyramid levels")
    prior_w = np.diag([1 / cfg.prior_sigma_rot**2] * 3 + [1 / cfg.prior_sigma_trans**2] * 3)
    guess_inv = np.linalg.inv(guess)
    order = list(reversed(range(cfg.levels))) if levels is None else list(levels)
    if not order:
        raise ConfigError("track needs at least one pyramid level to run")
    score_z2 = max(cfg.sigma_geo_z2, cfg.trust_z2_per_roughness * model.roughness)  # the trust test's scale
    # ... and its association gate: a point it judges within 3 scales is not cut by max_dist (a noisy camera's far
    # points; a Kinect's test is unchanged)
    gate_z2 = 3.0 * score_z2 if score_z2 > cfg.sigma_geo_z2 else 0.0
    if _use_numba(cfg):  # every level and the score in one compiled call (frontend_numba.icp_track)
        return _track_fast(live, model, guess, guess_inv, np.diagonal(prior_w).copy(), order, cfg, score_z2,
                           gate_z2)
    sums = normal_equations_reference
    est = guess.copy()
    steps = 0
    for lv in order:
        lvl = model.levels[lv]
        il = live.intensity if lv == 0 else None
        for _ in range(cfg.iters[lv]):
            a, b, st = sums(est, live.points[lv], live.valid[lv], il, lvl, model.w2c, cfg.max_dist[lv], cfg,
                            lv == 0)
            if st[0] < 6:  # nothing to solve for: the next level (or the score) says why
                break
            d = est @ guess_inv
            prior = np.concatenate([_so3_log(d[:3, :3]), d[:3, 3]])
            h = a + prior_w
            xi = np.linalg.solve(h + np.eye(6) * (1e-9 * np.diagonal(h).mean()), b - prior_w @ prior)
            est = _se3_exp(xi) @ est
            steps += 1
            if np.abs(xi).max() < cfg.min_step:
                break
    last = order[-1]  # scored at the final estimate on the last level
    a, _, st = sums(est, live.points[last], live.valid[last], live.intensity if last == 0 else None,
                    model.levels[last], model.w2c, cfg.max_dist[last],
                    cfg if score_z2 == cfg.sigma_geo_z2 else replace(cfg, sigma_geo_z2=score_z2), last == 0, gate_z2)
    n_live = max(int(live.valid[last].sum()), 1)
    q = _quality(a, st, n_live, cfg)
    return TrackResult(est, q, steps, model.keyframe_id)


def _track_fast(live: LiveFrame, model: ReferenceModel, guess: np.ndarray, guess_inv: np.ndarray,
                prior_diag: np.ndarray, order: list[int], cfg: FrontendConfig, score_z2: float, gate_z2: float
                ) -> TrackResult:
    """:func:`track`'s levels and score in one compiled call (:func:`~semantic_gs_slam.tracking.frontend_numba.
    icp_track`): the GIL is let go once per frame, not once per level and once for the score
    (``bench/frontend_gil.py``)."""
    lv = model.levels
    photometric = bool(cfg.photometric_weight > 0 and live.intensity is not None and lv[0].col is not None)
    est = guess.copy()
    a, b, st = np.zeros((6, 6)), np.zeros(6), np.zeros(4)
    steps, n_live = _fast().icp_track(
        est, guess_inv, prior_diag, model.w2c, tuple(live.points), tuple(live.valid),
        live.intensity if photometric else np.zeros(1), tuple(m.vm for m in lv), tuple(m.nm for m in lv),
        tuple(m.nvalid for m in lv), lv[0].col if photometric else np.zeros((1, 4)),
        np.array([m.k.fx for m in lv], np.float64), np.array([m.k.fy for m in lv], np.float64),
        np.array([m.k.cx for m in lv], np.float64), np.array([m.k.cy for m in lv], np.float64),
        np.array([m.k.width for m in lv], np.int64), np.array([m.k.height for m in lv], np.int64),
        np.array(cfg.max_dist, np.float64), float(cfg.sigma_geo), float(cfg.sigma_geo_z2), photometric,
        float(cfg.sigma_col),
        float(cfg.photometric_weight), np.array(cfg.iters, np.int64), float(cfg.min_step), np.array(order, np.int64),
        a, b, st, float(score_z2), float(gate_z2))
    return TrackResult(est, _quality(a, st, max(int(n_live), 1), cfg), int(steps), model.keyframe_id)


def _quality(a: np.ndarray, st: np.ndarray, n_live: int, cfg: FrontendConfig) -> TrackQuality:
    n = int(st[0])
    coverage = n / n_live
    agreement = float(st[2] / max(st[3], 1.0))
    residual = float(np.sqrt(st[1] / max(n, 1)))
    cond = _condition(a) if n >= 6 else float("inf")
    reasons = []
    if n < cfg.min_correspondences:
        reasons.append(f"{n} correspondences < {cfg.min_correspondences}")
    if coverage < cfg.min_coverage:
        reasons.append(f"coverage {coverage:.2f} < {cfg.min_coverage}")
    if agreement < cfg.min_agreement:
        reasons.append(f"agreement {agreement:.2f} < {cfg.min_agreement}")
    if not cond <= cfg.max_condition:
        reasons.append(f"condition {cond:.3g} > {cfg.max_condition:.3g}")
    return TrackQuality(n, coverage, agreement, residual, cond, not reasons, "; ".join(reasons))


def _score(q: TrackQuality) -> float:
    """One number to rank candidate poses: coverage times agreement (both in [0, 1])."""
    return q.coverage * q.agreement


def perturbed_guesses(c2w: np.ndarray, angles_deg: Sequence[float] = (10.0,),
                      shifts_m: Sequence[float] = (0.1,)) -> list[np.ndarray]:
    """``c2w`` [4, 4] and poses around it: turned by each angle about the camera's x and y axes (both signs), and
    moved by each shift along the camera's three axes (both signs): 1 + 4 len(angles) + 6 len(shifts) poses."""
    c2w = _check_pose("c2w", c2w)
    out = [c2w]
    for ang in angles_deg:
        for axis in (0, 1):
            for sgn in (-1.0, 1.0):
                xi = np.zeros(6)
                xi[axis] = sgn * np.radians(ang)
                out.append(c2w @ _se3_exp(xi))  # about the camera's own axis (right-multiplied)
    for s in shifts_m:
        for axis in range(3):
            for sgn in (-1.0, 1.0):
                xi = np.zeros(6)
                xi[3 + axis] = sgn * s
                out.append(c2w @ _se3_exp(xi))
    return out


def relocalise(live: LiveFrame, models: Sequence[ReferenceModel], cfg: FrontendConfig,
               extra_guesses: Sequence[np.ndarray] = (), angles_deg: Sequence[float] = (10.0,),
               shifts_m: Sequence[float] = (0.1,), refine_best: int = 3) -> TrackResult:
    """Find a lost frame's pose against the map's keyframe views.

    Every model is tried from its own camera's pose and :func:`perturbed_guesses` around it (and from each of
    ``extra_guesses``, e.g. the last trusted pose), on the coarse levels only; the ``refine_best`` best by coverage
    times agreement are then tracked on all levels, and the best trusted one is returned.

    Args:
        live: :func:`prepare_live`'s points. models: candidate keyframe models (e.g. the nearest few).
        cfg: front-end settings. extra_guesses: [4, 4] poses tried against every model besides its own.
        angles_deg, shifts_m: the perturbations (see :func:`perturbed_guesses`).
        refine_best: how many coarse results to track on all levels.

    Returns:
        :class:`TrackResult` with ``quality.trusted`` True.

    Raises:
        RelocalisationError: no candidate was trusted (the message gives the best one's quality).
        ValueError: ``models`` is empty.
    """
    if not models:
        raise ValueError("relocalise needs at least one reference model")
    coarse = list(reversed(range(1, cfg.levels))) or [0]
    cands = []
    for m in models:
        guesses = perturbed_guesses(m.c2w, angles_deg, shifts_m) + [_check_pose("guess", g) for g in extra_guesses]
        for g in guesses:
            r = track(live, m, g, cfg, levels=coarse)
            cands.append((_score(r.quality), r.c2w, m))
    cands.sort(key=lambda c: -c[0])
    best = None
    for _, pose, m in cands[:max(1, refine_best)]:
        r = track(live, m, pose, cfg)
        if r.quality.trusted and (best is None or _score(r.quality) > _score(best.quality)):
            best = r
        elif best is None or not best.quality.trusted:
            if best is None or _score(r.quality) > _score(best.quality):
                best = r
    if best is None or not best.quality.trusted:
        q = best.quality if best is not None else None
        raise RelocalisationError(f"no trusted pose among {len(cands)} guesses against {len(models)} keyframe(s)"
                                  + (f"; best: {q.reason}" if q is not None else ""))
    return best


# ---------------------------------------------------------------- one camera's state

@dataclass
class FrameTracker:
    """One camera's front end: the current reference, the last poses (constant-velocity guess) and the lost flag.

    :meth:`set_reference` may be called from another thread (a mapping back end publishing a new keyframe view)
    while :meth:`track_frame` runs in the tracking thread: the swap is atomic under ``_lock``.
    """

    k: Intrinsics
    cfg: FrontendConfig = field(default_factory=FrontendConfig)
    keep_models: int = 8  # keyframe models kept for relocalisation (most recent)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)  # guards _models
    _models: list[ReferenceModel] = field(default_factory=list, repr=False)  # newest last; [-1] is the reference
    _poses: list[np.ndarray] = field(default_factory=list, repr=False)  # last two trusted poses (tracking thread)
    lost: bool = False  # the last frame was not trusted (tracking thread)

    def __post_init__(self) -> None:
        self.cfg.check()
        self.k.check()

    def set_reference(self, model: ReferenceModel) -> None:
        """Make ``model`` the reference for the next frames (and keep it for relocalisation)."""
        with self._lock:
            self._models = (self._models + [model])[-self.keep_models:]

    @property
    def reference(self) -> ReferenceModel | None:
        """The current reference model (None before the first :meth:`set_reference`)."""
        with self._lock:
            return self._models[-1] if self._models else None

    def guess(self) -> np.ndarray:
        """The constant-velocity guess for the next frame ([4, 4]; the reference's pose before any frame).

        Raises:
            TrackingError: no reference and no pose yet.
        """
        if len(self._poses) >= 2:
            p0, p1 = self._poses[-2], self._poses[-1]
            return p1 @ np.linalg.inv(p0) @ p1
        if self._poses:
            return self._poses[-1].copy()
        ref = self.reference
        if ref is None:
            raise TrackingError("no reference model yet: call set_reference first")
        return ref.c2w.copy()

    def track_frame(self, depth: np.ndarray, rgb: np.ndarray | None = None,
                    guess_c2w: np.ndarray | None = None) -> TrackResult:
        """Track one live frame against the current reference; relocalise against the kept models once lost.

        Args:
            depth: [H, W] metres. rgb: [H, W, 3] in [0, 1] or None. guess_c2w: [4, 4] or None (constant velocity).

        Returns:
            :class:`TrackResult`; when ``quality.trusted`` is False the frame is lost (its pose is the estimate,
            not to be mapped) and :attr:`lost` is set.

        Raises:
            TrackingError: no reference model yet. FrameError: bad input.
        """
        with self._lock:
            models = list(self._models)
        if not models:
            raise TrackingError("no reference model yet: call set_reference first")
        live = prepare_live(depth, self.k, self.cfg, rgb)
        g = self.guess() if guess_c2w is None else _check_pose("guess_c2w", guess_c2w)
        res = track(live, models[-1], g, self.cfg)
        if not res.quality.trusted:
            nearest = sorted(models, key=lambda m: np.linalg.norm(m.c2w[:3, 3] - g[:3, 3]))[:3]
            try:
                res = relocalise(live, nearest, self.cfg, extra_guesses=[g])
            except RelocalisationError:
                self.lost = True
                return res
            self._poses = []  # the velocity is unknown after a relocalisation
        self.lost = False
        self._poses = (self._poses + [res.c2w])[-2:]
        return res

    def with_config(self, **changes) -> FrameTracker:
        """A new tracker with ``cfg`` fields changed (same camera, no state)."""
        return FrameTracker(self.k, replace(self.cfg, **changes), self.keep_models)
