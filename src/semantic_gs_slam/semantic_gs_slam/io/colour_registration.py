"""Colour registered to depth: where a second, uncalibrated colour camera saw each depth pixel.

Many RGB-D recordings (7-Scenes' Kinect v1 among them) store the colour camera's image as it was, not
re-projected into the depth camera. The two cameras differ in focal length (7-Scenes: about 530 against
585 px), principal point and position (a few centimetres apart), so a depth pixel and the colour pixel
at the same (u, v) see different things: on 7-Scenes up to 16 px apart at 320x240 near the image
edges. Gaussians seeded from depth then take colours from the wrong place, and every view disagrees.

:class:`ColourCalib` describes the colour camera relative to the depth camera (pinhole intrinsics at
the native image size, and the translation from the depth to the colour camera; no rotation, which
on a rigid RGB-D sensor is a fraction of a degree). :func:`register` re-samples a colour image into
the depth camera's pixels using each pixel's depth. :func:`estimate` finds the calibration from the
frames themselves, by aligning colour edges with depth discontinuities; ``python -m
semantic_gs_slam.io.calibrate_colour DATASET`` (:mod:`semantic_gs_slam.io.calibrate_colour`) runs it and writes the
calibration file the dataset loaders read (``colour-calibration.json`` beside the frames, or any path a user gives).

NumPy, and torch only for the shared hole filling (no ROS).
"""

from __future__ import annotations

import functools
import json
import math
import os
from dataclasses import asdict, dataclass

import numpy as np
import torch

from semantic_gs_slam.errors import DatasetError
from semantic_gs_slam.geometry import fill_depth_holes

CALIB_FILE = "colour-calibration.json"  # beside a dataset's frames; read by the loaders when present
FAR = 1e3  # metres assumed where depth is missing and cannot be filled (no depth in the whole image)


@dataclass(frozen=True)
class ColourCalib:
    """The colour camera relative to the depth camera, at the native image size.

    A depth-camera point ``p`` (metres) is seen by the colour camera at ``p + t``, projected with
    ``fx, fy, cx, cy``.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    tx: float = 0.0
    ty: float = 0.0
    tz: float = 0.0
    width: int = 0  # the image size these intrinsics are for (0: the dataset's native size)
    height: int = 0

    def check(self) -> ColourCalib:
        """Self, or :class:`DatasetError` naming what is wrong."""
        vals = asdict(self)
        if not all(math.isfinite(float(v)) for v in vals.values()):
            raise DatasetError(f"colour calibration has a non-finite value: {vals}")
        if self.fx <= 0 or self.fy <= 0:
            raise DatasetError(f"colour calibration needs positive focal lengths, got fx={self.fx} fy={self.fy}")
        if max(abs(self.tx), abs(self.ty), abs(self.tz)) > 0.5:
            raise DatasetError(f"colour calibration: a {max(abs(self.tx), abs(self.ty), abs(self.tz)):.2f} m "
                               "translation between the cameras of one sensor is not plausible (metres expected)")
        return self


# Estimated on 7-Scenes redkitchen (25 frames over 0-499, 320x240) with :func:`estimate`: edge alignment 0.195 ->
# 0.331. Checked against the reference poses (one frame's colour projected into another through depth, 37 pairs):
# mean difference 10.7 -> 7.3 grey levels, and a search on that check itself moves it by less than 0.2 %. 7-Scenes
# was recorded with one Kinect v1, whose colour camera (nominally 525 px) sits about 2.5 cm beside the depth camera.
SEVEN_SCENES_COLOUR = ColourCalib(526.3, 526.3, 318.9, 235.0, -0.0235, 0.011, 0.0, 640, 480)


def load(path: str) -> ColourCalib:
    """A calibration file (JSON with ``fx fy cx cy`` and optionally ``tx ty tz width height``).

    Raises:
        DatasetError: missing or malformed file, implausible values.
    """
    if not os.path.isfile(path):
        raise DatasetError(f"colour calibration file not found: {path}")
    try:
        with open(path, encoding="utf-8") as f:
            d = json.load(f)
        known = {k: d[k] for k in ("fx", "fy", "cx", "cy", "tx", "ty", "tz", "width", "height") if k in d}
        calib = ColourCalib(**{k: (int(v) if k in ("width", "height") else float(v)) for k, v in known.items()})
    except (OSError, ValueError, TypeError) as exc:
        raise DatasetError(f"{path}: not a colour calibration (JSON with fx, fy, cx, cy[, tx, ty, tz]): {exc}") from exc
    return calib.check()


def save(calib: ColourCalib, path: str, note: str = "") -> None:
    """Write the calibration to ``path`` whole or not at all (a temporary file, then renamed: the loaders read it).

    Raises:
        OSError: the folder is missing or not writable, or ``path`` is a folder.
    """
    d = asdict(calib)
    if note:
        d["note"] = note
    tmp = f"{path}.tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        json.dump(d, f, indent=1)
        f.write("\n")
    try:
        os.replace(tmp, path)
    except OSError:
        os.remove(tmp)
        raise


@functools.lru_cache(maxsize=4)
def _pixel_grid(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices [h, w] float64 (read-only: shared between calls)."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    v.flags.writeable = False
    u.flags.writeable = False
    return v, u


def colour_coords(depth: np.ndarray, fx: float, fy: float, cx: float, cy: float, calib: ColourCalib
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Where the colour camera sees each depth pixel: (u, v) [H, W] float32 in colour pixels.

    Args:
        depth: [H, W] metres (0: missing; those pixels take the depth of their valid surroundings,
            :func:`~semantic_gs_slam.geometry.fill_depth_holes`, or a far depth in an image without depth).
        fx, fy, cx, cy: the depth camera's intrinsics at this size.
        calib: the colour camera at this size (see :func:`scaled`).
    """
    h, w = depth.shape
    filled = fill_depth_holes(torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))).numpy()
    z = np.where(filled > 0, filled, FAR).astype(np.float64)
    v, u = _pixel_grid(h, w)
    x = (u - cx) / fx * z + calib.tx
    y = (v - cy) / fy * z + calib.ty
    zc = np.maximum(z + calib.tz, 1e-6)
    return (calib.fx * x / zc + calib.cx).astype(np.float32), (calib.fy * y / zc + calib.cy).astype(np.float32)


def scaled(calib: ColourCalib, sx: float, sy: float) -> ColourCalib:
    """``calib`` for images scaled by ``sx``, ``sy`` (pixel-centre convention, as the dataset's resize)."""
    return ColourCalib(calib.fx * sx, calib.fy * sy, (calib.cx + 0.5) * sx - 0.5, (calib.cy + 0.5) * sy - 0.5,
                       calib.tx, calib.ty, calib.tz,
                       round(calib.width * sx) if calib.width else 0, round(calib.height * sy) if calib.height else 0)


def bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``img`` [H, W, C] (or [H, W]) sampled at float pixel coordinates ``u``, ``v`` [h, w] (clamped at the border).

    torch's ``grid_sample`` (corner-aligned, border padding): at 640x480 a ninth of the time of
    :func:`bilinear_reference`, which it matches to float rounding (integer images: within 1 where the
    truncation to the integer type falls on the other side).
    """
    h, w = img.shape[:2]
    chans = img.reshape(h, w, -1)
    t = torch.from_numpy(np.ascontiguousarray(chans)).permute(2, 0, 1)[None].float()  # [1, C, H, W]
    gx = torch.from_numpy(np.clip(u, 0.0, w - 1.0).astype(np.float32, copy=False)) * (2.0 / max(w - 1, 1)) - 1.0
    gy = torch.from_numpy(np.clip(v, 0.0, h - 1.0).astype(np.float32, copy=False)) * (2.0 / max(h - 1, 1)) - 1.0
    grid = torch.stack([gx, gy], -1)[None]  # [1, h, w, 2] in [-1, 1]
    out = torch.nn.functional.grid_sample(t, grid, mode="bilinear", padding_mode="border", align_corners=True)
    out = out[0].permute(1, 2, 0).numpy()  # [h, w, C] float32
    return out.reshape(u.shape + img.shape[2:]).astype(img.dtype)


def bilinear_reference(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """:func:`bilinear` in NumPy (the reference)."""
    h, w = img.shape[:2]
    u = np.clip(u, 0.0, w - 1.0)
    v = np.clip(v, 0.0, h - 1.0)
    u0 = np.minimum(np.floor(u).astype(np.int64), w - 2 if w > 1 else 0)
    v0 = np.minimum(np.floor(v).astype(np.int64), h - 2 if h > 1 else 0)
    a = (u - u0)[..., None].astype(np.float32)
    b = (v - v0)[..., None].astype(np.float32)
    u1, v1 = np.minimum(u0 + 1, w - 1), np.minimum(v0 + 1, h - 1)
    top = img[v0, u0] * (1 - a) + img[v0, u1] * a
    bot = img[v1, u0] * (1 - a) + img[v1, u1] * a
    return (top * (1 - b) + bot * b).astype(img.dtype)


def register(rgb: np.ndarray, depth: np.ndarray, fx: float, fy: float, cx: float, cy: float,
             calib: ColourCalib) -> np.ndarray:
    """The colour image [H', W', 3] re-sampled into the depth camera's pixels: [H, W, 3] like ``depth`` [H, W].

    Pixels the colour camera did not see keep the nearest border colour.
    """
    u, v = colour_coords(depth, fx, fy, cx, cy, calib)
    return bilinear(rgb, u, v)


# ----------------------------------------------------------------------------------------- estimation


def _grad_mag(img: np.ndarray) -> np.ndarray:
    """Sobel gradient magnitude of a 2-D float image (zero on the one-pixel border)."""
    g = np.zeros_like(img)
    p = img
    gx = (p[:-2, 2:] + 2 * p[1:-1, 2:] + p[2:, 2:]) - (p[:-2, :-2] + 2 * p[1:-1, :-2] + p[2:, :-2])
    gy = (p[2:, :-2] + 2 * p[2:, 1:-1] + p[2:, 2:]) - (p[:-2, :-2] + 2 * p[:-2, 1:-1] + p[:-2, 2:])
    g[1:-1, 1:-1] = np.hypot(gx, gy)
    return g


def _box_blur(img: np.ndarray, r: int) -> np.ndarray:
    """Separable box blur of radius ``r`` (edge-padded)."""
    k = 2 * r + 1
    p = np.pad(img, r, mode="edge")
    c = np.cumsum(np.pad(p, ((0, 0), (1, 0))), axis=1)
    p = (c[:, k:] - c[:, :-k]) / k
    c = np.cumsum(np.pad(p, ((1, 0), (0, 0))), axis=0)
    return (c[k:] - c[:-k]) / k


def depth_edges(depth: np.ndarray, jump: float = 0.03, margin: int = 4) -> np.ndarray:
    """[H, W] float32: depth discontinuities (a step above ``jump`` of the depth between valid neighbours),
    blurred by a pixel or two so that a nearly aligned colour edge still scores; 0 within ``margin`` of the border."""
    d = depth
    e = np.zeros(d.shape, bool)
    both = (d[:, 1:] > 0) & (d[:, :-1] > 0)
    e[:, 1:] |= both & (np.abs(d[:, 1:] - d[:, :-1]) > jump * d[:, 1:])
    both = (d[1:] > 0) & (d[:-1] > 0)
    e[1:] |= both & (np.abs(d[1:] - d[:-1]) > jump * d[1:])
    out = _box_blur(_box_blur(e.astype(np.float32), 1), 1)
    if margin:
        out[:margin], out[-margin:], out[:, :margin], out[:, -margin:] = 0, 0, 0, 0
    return out.astype(np.float32)


def alignment(frames: list[tuple[np.ndarray, np.ndarray]], fx: float, fy: float, cx: float, cy: float,
              calib: ColourCalib, edges: list[np.ndarray] | None = None) -> float:
    """Mean normalised correlation between the registered colour's edges and the depth's discontinuities.

    Args:
        frames: (grey colour image [H', W'] float32, depth [H, W] metres) pairs at one size.
        fx, fy, cx, cy: the depth camera at that size. calib: the colour camera at that size.
        edges: :func:`depth_edges` of each frame's depth, when the caller scores many calibrations (None: computed).
    """
    tot = 0.0
    for n, (grey, depth) in enumerate(frames):
        de = depth_edges(depth) if edges is None else edges[n]
        ce = _grad_mag(register(grey[..., None], depth, fx, fy, cx, cy, calib)[..., 0])
        den = math.sqrt(float((ce * ce).sum()) * float((de * de).sum()))
        tot += float((ce * de).sum()) / den if den > 0 else 0.0
    return tot / max(len(frames), 1)


@dataclass
class Estimate:
    calib: ColourCalib
    score_identity: float  # alignment with colour taken as registered (same pixels)
    score: float  # alignment with ``calib``
    frames: int


def estimate(frames: list[tuple[np.ndarray, np.ndarray]], fx: float, fy: float, cx: float, cy: float,
             start: ColourCalib | None = None, rounds: int = 6) -> Estimate:
    """Find the colour camera that best aligns colour edges with depth discontinuities.

    Coordinate search over (focal, cx, cy, tx, ty) with halving steps from several starts (the depth
    camera's own intrinsics, and 90-95 % of its focal length with the colour camera 2.5 cm either side,
    a Kinect-like rig); one focal length for both axes and no depth-axis translation (both are barely
    observable from edges). Works at the frames' size;
    the result is for that size (:func:`scaled` moves it).

    Args:
        frames: (grey colour image, depth in metres) pairs, a dozen or more spread over the sequence.
        fx, fy, cx, cy: the depth camera at that size.
        start: first guess (default: the depth camera's own intrinsics, i.e. colour taken as registered).

    Raises:
        DatasetError: no frames, or no depth discontinuity to align with.
    """
    if not frames:
        raise DatasetError("colour registration needs at least one frame")
    edges = [depth_edges(d) for _, d in frames]  # once: the search scores a few hundred calibrations
    if not any(e.any() for e in edges):
        raise DatasetError("no depth discontinuities in these frames: nothing to align the colour with")
    ratio = fy / fx

    def calib_of(q: np.ndarray) -> ColourCalib:
        return ColourCalib(float(q[0]), float(q[0]) * ratio, float(q[1]), float(q[2]), float(q[3]), float(q[4]))

    def score(q: np.ndarray) -> float:
        return alignment(frames, fx, fy, cx, cy, calib_of(q), edges)

    def search(p: np.ndarray, best: float, rounds: int) -> tuple[np.ndarray, float]:
        steps = np.array([8.0 * px, 4.0 * px, 4.0 * px, 0.02, 0.02])
        for _ in range(rounds):
            for i in range(5):
                for m in (-2.0, -1.0, 1.0, 2.0):
                    q = p.copy()
                    q[i] += m * steps[i]
                    s = score(q)
                    if s > best:
                        best, p = s, q
            steps = steps / 2
        return p, best

    px = fx / 585.0  # one pixel of a 640-wide Kinect image, at the frames' size
    ident = np.array([fx, cx, cy, 0.0, 0.0])
    s_ident = score(ident)
    # the search has local optima (the baseline and the principal point trade off): a few starts, the best refined
    starts = [np.array([start.fx, start.cx, start.cy, start.tx, start.ty])] if start else \
        [ident] + [np.array([fx * r, cx, cy, t, 0.0]) for r in (0.9, 0.95) for t in (-0.025, 0.0, 0.025)]
    tried = [search(p, score(p), 3) for p in starts]
    p, best = max(tried, key=lambda pb: pb[1])
    p, best = search(p, best, rounds)
    return Estimate(calib_of(p), s_ident, best, len(frames))
