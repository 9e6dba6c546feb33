"""Synthetic home generator: a procedural room rendered into an RGB-D + semantic sequence.

The home is the robot's demo home (the bundled map ``data/`` is built from it by our SLAM, see
:mod:`semantic_gs_slam.synthetic.demo_map`): a 6 m x 5 m x 2.5 m room, z up, metres, with furniture, small
objects, class names and ids that fit the robot's named locations
(``decision_maker/config/locations.yaml``). Surfaces carry a procedural texture (multi-scale value
noise and stripes, with fixed Lambert shading) so tracking has something to lock onto. Colour is
averaged over each pixel's area (3 x 3 rays), as a camera integrates light.

Output (Replica as NICE-SLAM ships it, plus semantics)::

    <out>/results/frame%06d.jpg      RGB
    <out>/results/depth%06d.png      16-bit depth, metres * 6553.5
    <out>/semantic/semantic%06d.png  8-bit semantic ids (0 = none)
    <out>/traj.txt                   one 4x4 camera-to-world matrix per line (16 numbers)
    <out>/cam.json                   intrinsics
    <out>/semantic.json              {"segmentation": [{"id": .., "class": ..}, ...]}

Usage: ``python -m semantic_gs_slam.synthetic --out /tmp/home --frames 60 --width 300 --height 170``
"""

from __future__ import annotations

import argparse
import json
import os
from dataclasses import dataclass

import numpy as np

from semantic_gs_slam.config import Intrinsics
from semantic_gs_slam.geometry import look_at

# id, class, base rgb
CLASSES: list[tuple[int, str, tuple[float, float, float]]] = [
    (1, "floor", (0.55, 0.45, 0.35)),
    (2, "wall", (0.85, 0.85, 0.80)),
    (3, "counter", (0.60, 0.60, 0.65)),
    (4, "table", (0.50, 0.30, 0.15)),
    (5, "chair", (0.35, 0.20, 0.10)),
    (6, "sofa", (0.20, 0.30, 0.60)),
    (7, "bottle", (0.10, 0.60, 0.20)),
    (8, "cup", (0.90, 0.90, 0.95)),
    (9, "trash", (0.70, 0.65, 0.30)),
    (10, "bin", (0.25, 0.25, 0.25)),
    (11, "fridge", (0.92, 0.92, 0.92)),
]
CLASS_ID = {name: i for i, name, _ in CLASSES}
ROOM = (6.0, 5.0, 2.5)  # x, y, z extent; the ceiling is labelled "wall"
DEPTH_SCALE = 6553.5


@dataclass(frozen=True)
class Box:
    """Axis-aligned solid box."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    cls: str


@dataclass(frozen=True)
class Cylinder:
    """Vertical solid cylinder (capped)."""

    cx: float
    cy: float
    r: float
    z0: float
    z1: float
    cls: str


def home_layout() -> list[Box | Cylinder]:
    """The furniture and objects of the home (the room shell is implicit)."""
    s: list[Box | Cylinder] = [
        Box((3.8, 0.0, 0.0), (6.0, 0.6, 0.9), "counter"),
        Box((5.3, 1.0, 0.0), (6.0, 1.8, 1.8), "fridge"),
        Box((1.9, 2.1, 0.72), (3.1, 2.9, 0.76), "table"),
    ]
    for lx, ly in [(1.95, 2.15), (3.05, 2.15), (1.95, 2.85), (3.05, 2.85)]:
        s.append(Box((lx - 0.025, ly - 0.025, 0.0), (lx + 0.025, ly + 0.025, 0.72), "table"))
    for cx, cy, back in [(2.5, 1.7, "y"), (2.5, 3.3, "Y"), (3.6, 2.5, "X")]:
        s.append(Box((cx - 0.22, cy - 0.22, 0.42), (cx + 0.22, cy + 0.22, 0.46), "chair"))
        if back == "y":
            s.append(Box((cx - 0.22, cy - 0.24, 0.46), (cx + 0.22, cy - 0.20, 0.95), "chair"))
        elif back == "Y":
            s.append(Box((cx - 0.22, cy + 0.20, 0.46), (cx + 0.22, cy + 0.24, 0.95), "chair"))
        else:
            s.append(Box((cx + 0.20, cy - 0.22, 0.46), (cx + 0.24, cy + 0.22, 0.95), "chair"))
        for dx in (-0.2, 0.2):
            for dy in (-0.2, 0.2):
                s.append(Cylinder(cx + dx, cy + dy, 0.015, 0.0, 0.42, "chair"))
    s += [
        Box((0.3, 4.0, 0.0), (2.3, 4.9, 0.45), "sofa"),
        Box((0.3, 4.7, 0.45), (2.3, 4.9, 0.9), "sofa"),
        Cylinder(5.2, 0.3, 0.035, 0.9, 1.15, "bottle"),
        Cylinder(4.6, 0.35, 0.04, 0.9, 1.0, "cup"),
        Cylinder(2.8, 2.6, 0.04, 0.76, 0.86, "cup"),
        Box((2.2, 2.4, 0.76), (2.35, 2.55, 0.82), "trash"),
        Cylinder(5.6, 4.5, 0.18, 0.0, 0.5, "bin"),
    ]
    return s


class _Noise:
    """3-D value noise on a lattice (trilinear), deterministic for a seed."""

    def __init__(self, seed: int, size: int = 64) -> None:
        self.table = np.random.default_rng(seed).random((size, size, size)).astype(np.float64)
        self.size = size

    def __call__(self, p: np.ndarray) -> np.ndarray:
        """p [N, 3] in lattice units -> [N] in [0, 1]."""
        i = np.floor(p).astype(np.int64)
        f = p - i
        f = f * f * (3 - 2 * f)
        out = np.zeros(len(p))
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    w = (f[:, 0] if dx else 1 - f[:, 0]) * (f[:, 1] if dy else 1 - f[:, 1]) \
                        * (f[:, 2] if dz else 1 - f[:, 2])
                    idx = (i + np.array([dx, dy, dz])) % self.size
                    out += w * self.table[idx[:, 0], idx[:, 1], idx[:, 2]]
        return out


class HomeRenderer:
    """Ray-caster of the home: RGB, depth (metres, along the optical axis) and semantic ids."""

    def __init__(self, seed: int = 0) -> None:
        self.shapes = home_layout()
        self.noise = _Noise(seed)
        self.colour = {i: np.array(c) for i, _, c in CLASSES}
        self.light = np.array([0.3, 0.5, 1.0]) / np.linalg.norm([0.3, 0.5, 1.0])

    def render(self, c2w: np.ndarray, k: Intrinsics, supersample: int = 1
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Render one view.

        Args:
            c2w: [4, 4] camera-to-world pose (OpenCV camera).
            k: intrinsics.
            supersample: odd s >= 1: colour is the mean of s x s rays spread over each pixel's area (a
                camera integrates light over the pixel; one ray per pixel aliases the fine texture into
                view-dependent noise), depth and label come from the ray through the pixel centre.

        Returns:
            rgb [H, W, 3] float in [0, 1], depth [H, W] metres (z), semantic ids [H, W] uint8.
        """
        if supersample < 1 or supersample % 2 == 0:
            raise ValueError(f"supersample must be an odd integer >= 1, got {supersample}")
        if supersample > 1:
            s, c = supersample, supersample // 2
            rgb, depth, sem = self.render(c2w, k.scaled(s))
            return (rgb.reshape(k.height, s, k.width, s, 3).mean((1, 3)), depth[c::s, c::s], sem[c::s, c::s])
        v, u = np.meshgrid(np.arange(k.height), np.arange(k.width), indexing="ij")
        dirs_c = np.stack([(u - k.cx) / k.fx, (v - k.cy) / k.fy, np.ones_like(u, dtype=float)], -1).reshape(-1, 3)
        d = dirs_c @ c2w[:3, :3].T  # world directions with unit z-component in camera
        o = np.broadcast_to(c2w[:3, 3], d.shape)
        n = len(d)
        t_best = np.full(n, np.inf)
        normal = np.zeros((n, 3))
        cls = np.zeros(n, dtype=np.int64)
        # room shell (inside of the box): exits
        with np.errstate(divide="ignore", invalid="ignore"):
            for ax in range(3):
                for side, val in ((1, ROOM[ax]), (-1, 0.0)):
                    t = (val - o[:, ax]) / d[:, ax]
                    ok = (t > 1e-6) & (t < t_best) & (np.sign(d[:, ax]) == side)
                    t_best[ok] = t[ok]
                    nn = np.zeros(3)
                    nn[ax] = -side
                    normal[ok] = nn
                    cls[ok] = CLASS_ID["floor"] if (ax == 2 and side == -1) else CLASS_ID["wall"]
            for s in self.shapes:
                if isinstance(s, Box):
                    lo, hi = np.array(s.lo), np.array(s.hi)
                    t1, t2 = (lo - o) / d, (hi - o) / d
                    tmin_ax = np.minimum(t1, t2)
                    tmax = np.nanmin(np.maximum(t1, t2), 1)
                    tmin = np.nanmax(tmin_ax, 1)
                    ok = (tmax >= tmin) & (tmin > 1e-6) & (tmin < t_best)
                    if not ok.any():
                        continue
                    ax = np.nanargmax(tmin_ax[ok], 1)
                    nn = np.zeros((ok.sum(), 3))
                    nn[np.arange(len(ax)), ax] = -np.sign(d[ok, ax])
                    t_best[ok], normal[ok], cls[ok] = tmin[ok], nn, CLASS_ID[s.cls]
                else:
                    dx, dy = o[:, 0] - s.cx, o[:, 1] - s.cy
                    a = d[:, 0] ** 2 + d[:, 1] ** 2
                    b = 2 * (dx * d[:, 0] + dy * d[:, 1])
                    c = dx**2 + dy**2 - s.r**2
                    disc = b * b - 4 * a * c
                    t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
                    z = o[:, 2] + t * d[:, 2]
                    ok = (disc > 0) & (t > 1e-6) & (z >= s.z0) & (z <= s.z1) & (t < t_best)
                    if ok.any():
                        p = o[ok] + t[ok, None] * d[ok]
                        nn = np.stack([p[:, 0] - s.cx, p[:, 1] - s.cy, np.zeros(len(p))], 1) / s.r
                        t_best[ok], normal[ok], cls[ok] = t[ok], nn, CLASS_ID[s.cls]
                    tc = (s.z1 - o[:, 2]) / d[:, 2]
                    pc = o + tc[:, None] * d
                    okc = (d[:, 2] < 0) & (tc > 1e-6) & ((pc[:, 0] - s.cx) ** 2 + (pc[:, 1] - s.cy) ** 2 <= s.r**2) \
                        & (tc < t_best)
                    t_best[okc], normal[okc], cls[okc] = tc[okc], np.array([0.0, 0.0, 1.0]), CLASS_ID[s.cls]
        p = o + t_best[:, None] * d
        base = np.stack([self.colour[int(c)] for c in range(12) if c in self.colour])
        base = np.concatenate([np.zeros((1, 3)), base])[cls]
        tex = 0.55 * self.noise(p * 6.0) + 0.3 * self.noise(p * 23.0 + 17.0) \
            + 0.15 * (np.sin(p.sum(1) * 40) * 0.5 + 0.5)
        shade = 0.55 + 0.45 * np.abs(normal @ self.light)
        rgb = np.clip(base * (0.55 + 0.75 * tex)[:, None] * shade[:, None], 0, 1)
        depth = t_best  # direction has unit camera-z, so t is the z depth
        return (rgb.reshape(k.height, k.width, 3), depth.reshape(k.height, k.width),
                cls.reshape(k.height, k.width).astype(np.uint8))


def trajectory(n: int, span_deg: float = 120.0) -> list[np.ndarray]:
    """A smooth camera path: an orbit around the dining table (1.8 m x 1.5 m ellipse, 1.3-1.5 m high),
    looking at the table with a slow pan, so every view has furniture at several depths and
    orientations (views of only a wall and the floor leave ICP a free direction)."""
    poses = []
    centre = np.array([2.7, 2.5])
    for i in range(n):
        s = i / max(n - 1, 1)
        th = np.radians(-90.0 + span_deg * s)
        pos = np.array([centre[0] + 1.8 * np.cos(th), centre[1] + 1.5 * np.sin(th), 1.4 + 0.1 * np.sin(3 * th)])
        pan = 0.25 * np.sin(2 * th)  # a function of the orbit angle: motion per frame stays small
        look = np.array([centre[0] - pos[0], centre[1] - pos[1]])
        yaw = np.arctan2(look[1], look[0]) + pan
        target = np.array([pos[0] + 2.0 * np.cos(yaw), pos[1] + 2.0 * np.sin(yaw), 0.45])
        poses.append(look_at(pos, target))
    return poses


def default_intrinsics(width: int, height: int) -> Intrinsics:
    """Replica-like camera: f = W / 2 (90 degrees horizontal field of view), centred principal point."""
    return Intrinsics(width, height, width / 2.0, width / 2.0, (width - 1) / 2.0, (height - 1) / 2.0)


_RENDERERS: dict[int, HomeRenderer] = {}


def _render_job(job: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One view for :func:`generate` (a top-level function, so worker processes can run it)."""
    seed, c2w, k, supersample = job
    if seed not in _RENDERERS:
        _RENDERERS[seed] = HomeRenderer(seed)
    return _RENDERERS[seed].render(c2w, k, supersample)


def _write_frames(out: str, views, depth_noise: float, missing_depth: float, rng: np.random.Generator) -> None:
    from PIL import Image

    for i, (rgb, depth, sem) in enumerate(views):
        if depth_noise > 0:
            depth = depth * (1 + depth_noise * rng.standard_normal(depth.shape))
        if missing_depth > 0:
            depth = np.where(rng.random(depth.shape) < missing_depth, 0.0, depth)
        Image.fromarray((rgb * 255 + 0.5).astype(np.uint8)).save(os.path.join(out, "results", f"frame{i:06d}.jpg"),
                                                                 quality=95)
        d16 = np.clip(depth * DEPTH_SCALE + 0.5, 0, 65535).astype(np.uint16)
        Image.fromarray(d16).save(os.path.join(out, "results", f"depth{i:06d}.png"))
        Image.fromarray(sem).save(os.path.join(out, "semantic", f"semantic{i:06d}.png"))


def generate(out: str, frames: int = 60, width: int = 300, height: int = 170, seed: int = 0,
             depth_noise: float = 0.0, missing_depth: float = 0.0, span_deg: float = 120.0,
             supersample: int = 3, workers: int = 4) -> Intrinsics:
    """Write a synthetic sequence (layout in the module docstring).

    Args:
        out: output folder (created).
        frames: number of frames.
        width, height: image size; f = width / 2.
        seed: texture and noise seed.
        depth_noise: std of multiplicative depth noise (0.01 = 1 %).
        missing_depth: fraction of depth pixels set to 0 (missing).
        span_deg: how far around the ellipse the camera travels.
        supersample: rays per pixel side for colour (odd; 1 = point-sampled, aliased texture).
        workers: at most this many worker processes (also capped by the CPU count).

    Returns:
        The intrinsics used.
    """
    k = default_intrinsics(width, height)
    rng = np.random.default_rng(seed + 1)
    os.makedirs(os.path.join(out, "results"), exist_ok=True)
    os.makedirs(os.path.join(out, "semantic"), exist_ok=True)
    poses = trajectory(frames, span_deg)
    jobs = [(seed, c2w, k, supersample) for c2w in poses]
    workers = min(os.cpu_count() or 1, workers, len(jobs))
    if workers > 1 and len(jobs) * k.width * k.height * supersample**2 > 2_000_000:  # else not worth processes
        import multiprocessing

        with multiprocessing.get_context("spawn").Pool(workers) as pool:
            views = pool.imap(_render_job, jobs)
            _write_frames(out, views, depth_noise, missing_depth, rng)
    else:
        _write_frames(out, map(_render_job, jobs), depth_noise, missing_depth, rng)
    with open(os.path.join(out, "traj.txt"), "w") as fh:
        for p in poses:
            fh.write(" ".join(f"{x:.10f}" for x in p.reshape(-1)) + "\n")
    with open(os.path.join(out, "cam.json"), "w") as fh:
        json.dump({"width": k.width, "height": k.height, "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy,
                   "depth_scale": DEPTH_SCALE}, fh, indent=1)
    with open(os.path.join(out, "semantic.json"), "w") as fh:
        json.dump({"segmentation": [{"id": i, "class": c} for i, c, _ in CLASSES]}, fh, indent=1)
    return k


def main(argv: list[str] | None = None) -> None:
    """Command line entry (``semantic_gs_slam_synth``)."""
    ap = argparse.ArgumentParser(description="Write a synthetic home RGB-D + semantic sequence (Replica layout).")
    ap.add_argument("--out", required=True)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--width", type=int, default=300)
    ap.add_argument("--height", type=int, default=170)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--depth-noise", type=float, default=0.0)
    ap.add_argument("--missing-depth", type=float, default=0.0)
    ap.add_argument("--span-deg", type=float, default=120.0)
    ap.add_argument("--supersample", type=int, default=3,
                    help="odd; colour averages s x s rays per pixel (1: one ray, aliased texture)")
    a = ap.parse_args(argv)
    generate(a.out, a.frames, a.width, a.height, a.seed, a.depth_noise, a.missing_depth, a.span_deg, a.supersample)
    print(f"wrote {a.frames} frames {a.width}x{a.height} to {a.out}")


if __name__ == "__main__":
    main()
