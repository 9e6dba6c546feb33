#!/usr/bin/env python3
"""Generate the bundled sample map ``data/params.npz`` + ``data/semantic.json``.

A synthetic home (one 6 m × 5 m room, z up, map frame, metres) as a semantic Gaussian map in the
SplaTAM / SGS-SLAM layout. Gaussians are sampled on object surfaces with a few millimetres of
spread, plus ~1 % floaters (near-transparent Gaussians at random places with random labels, as
real Gaussian-splatting maps have). Deterministic: the same seed gives the same bytes.

Layout (x to the right, y up the page)::

    y=5 +------------------------------------------+
        | sofa (0.3-2.3, 4.0-4.9)        bin (5.6,4.5)
        |
        |  chair (2.5,3.3)
        |  table (1.9-3.1, 2.1-2.9) + trash, cup
        |  chair (2.5,1.7)              chair (3.6,2.5)
        |                              fridge (5.3-6.0, 1.0-1.8)
        | home (0.5,0.5)   kitchen counter (3.8-6.0, 0.0-0.6) + bottle, cup
    y=0 +------------------------------------------+ x=6

Usage: ``python scripts/make_sample_map.py [--out data] [--seed 7]``
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

# id, class, rgb colour
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
ID = {name: i for i, name, _ in CLASSES}
COLOUR = {i: c for i, _, c in CLASSES}


def box_surface(rng: np.random.Generator, lo, hi, density: float, faces: str = "xXyYzZ") -> np.ndarray:
    """Points on the faces of an axis-aligned box [lo, hi]; ``faces`` picks which (x=-x face, X=+x…)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    size = hi - lo
    out = []
    for f in faces:
        axis = "xyz".index(f.lower())
        u, v = [a for a in range(3) if a != axis]
        area = size[u] * size[v]
        n = max(1, int(area * density))
        p = np.empty((n, 3))
        p[:, u] = lo[u] + rng.random(n) * size[u]
        p[:, v] = lo[v] + rng.random(n) * size[v]
        p[:, axis] = hi[axis] if f.isupper() else lo[axis]
        out.append(p)
    return np.concatenate(out)


def cylinder_surface(rng: np.random.Generator, centre, radius: float, z0: float, z1: float, density: float,
                     top: bool = True) -> np.ndarray:
    """Points on the side (and top disc) of a vertical cylinder."""
    n_side = max(1, int(2 * np.pi * radius * (z1 - z0) * density))
    a = rng.random(n_side) * 2 * np.pi
    z = z0 + rng.random(n_side) * (z1 - z0)
    side = np.stack([centre[0] + radius * np.cos(a), centre[1] + radius * np.sin(a), z], 1)
    if not top:
        return side
    n_top = max(1, int(np.pi * radius**2 * density))
    r = radius * np.sqrt(rng.random(n_top))
    b = rng.random(n_top) * 2 * np.pi
    disc = np.stack([centre[0] + r * np.cos(b), centre[1] + r * np.sin(b), np.full(n_top, z1)], 1)
    return np.concatenate([side, disc])


def build_home(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Surface points [N, 3] and their semantic ids [N] of the synthetic home."""
    parts: list[tuple[np.ndarray, str]] = []

    def add(points: np.ndarray, name: str) -> None:
        parts.append((points, name))

    add(box_surface(rng, (0, 0, 0), (6, 5, 0), 500, "Z"), "floor")
    for lo, hi, face in [((0, 0, 0), (0, 5, 2.5), "x"), ((6, 0, 0), (6, 5, 2.5), "X"),
                         ((0, 0, 0), (6, 0, 2.5), "y"), ((0, 5, 0), (6, 5, 2.5), "Y")]:
        add(box_surface(rng, lo, hi, 150, face), "wall")
    add(box_surface(rng, (3.8, 0.0, 0.0), (6.0, 0.6, 0.9), 2500, "xXYZ"), "counter")
    add(box_surface(rng, (5.3, 1.0, 0.0), (6.0, 1.8, 1.8), 1500, "xyYZ"), "fridge")
    # table: top slab + four legs
    add(box_surface(rng, (1.9, 2.1, 0.72), (3.1, 2.9, 0.76), 3000), "table")
    for lx, ly in [(1.95, 2.15), (3.05, 2.15), (1.95, 2.85), (3.05, 2.85)]:
        add(box_surface(rng, (lx - 0.025, ly - 0.025, 0), (lx + 0.025, ly + 0.025, 0.72), 3000, "xXyY"), "table")
    # chairs: seat + back
    for cx, cy, back in [(2.5, 1.7, "y"), (2.5, 3.3, "Y"), (3.6, 2.5, "X")]:
        add(box_surface(rng, (cx - 0.22, cy - 0.22, 0.42), (cx + 0.22, cy + 0.22, 0.46), 3000), "chair")
        if back == "y":
            add(box_surface(rng, (cx - 0.22, cy - 0.24, 0.46), (cx + 0.22, cy - 0.20, 0.95), 3000), "chair")
        elif back == "Y":
            add(box_surface(rng, (cx - 0.22, cy + 0.20, 0.46), (cx + 0.22, cy + 0.24, 0.95), 3000), "chair")
        else:
            add(box_surface(rng, (cx + 0.20, cy - 0.22, 0.46), (cx + 0.24, cy + 0.22, 0.95), 3000), "chair")
        for dx in (-0.2, 0.2):
            for dy in (-0.2, 0.2):
                add(cylinder_surface(rng, (cx + dx, cy + dy), 0.015, 0, 0.42, 3000, top=False), "chair")
    # sofa: base + back + arms
    add(box_surface(rng, (0.3, 4.0, 0.0), (2.3, 4.9, 0.45), 1500), "sofa")
    add(box_surface(rng, (0.3, 4.7, 0.45), (2.3, 4.9, 0.9), 1500), "sofa")
    # small objects
    add(cylinder_surface(rng, (5.2, 0.3), 0.035, 0.9, 1.15, 40000), "bottle")
    add(cylinder_surface(rng, (4.6, 0.35), 0.04, 0.9, 1.0, 40000), "cup")
    add(cylinder_surface(rng, (2.8, 2.6), 0.04, 0.76, 0.86, 40000), "cup")
    add(box_surface(rng, (2.2, 2.4, 0.76), (2.35, 2.55, 0.82), 40000), "trash")
    add(cylinder_surface(rng, (5.6, 4.5), 0.18, 0.0, 0.5, 8000, top=False), "bin")

    means = np.concatenate([p for p, _ in parts])
    ids = np.concatenate([np.full(len(p), ID[n], dtype=np.int64) for p, n in parts])
    return means, ids


def make_sample_map(seed: int = 7, floater_fraction: float = 0.01) -> dict[str, np.ndarray]:
    """The SplaTAM-layout arrays of the sample map (see module docstring)."""
    rng = np.random.default_rng(seed)
    means, ids = build_home(rng)
    means = means + rng.normal(0.0, 0.003, means.shape)  # a few mm of spread
    n_float = int(len(means) * floater_fraction)
    f_means = rng.random((n_float, 3)) * np.array([6.0, 5.0, 2.5])
    f_ids = rng.choice([i for i, _, _ in CLASSES], n_float)
    n = len(means) + n_float
    means = np.concatenate([means, f_means]).astype(np.float32)
    ids = np.concatenate([ids, f_ids])
    colours = np.array([COLOUR[int(i)] for i in ids]) + rng.normal(0, 0.03, (n, 3))
    opac = np.concatenate([rng.normal(4.0, 0.5, len(ids) - n_float), rng.normal(-5.0, 1.0, n_float)])
    return {
        "means3D": means,  # [N, 3]
        "rgb_colors": np.clip(colours, 0, 1).astype(np.float32),  # [N, 3]
        "semantic_ids": ids.astype(np.uint8),  # [N] (SGS-SLAM saves uint8)
        "logit_opacities": opac.astype(np.float32)[:, None],  # [N, 1]
        "log_scales": np.full((n, 1), np.log(0.008), np.float32),  # [N, 1] isotropic
        "unnorm_rotations": np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1)),  # [N, 4] wxyz
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    here = os.path.dirname(os.path.abspath(__file__))
    ap.add_argument("--out", default=os.path.join(here, "..", "data"), help="output folder (default: data/)")
    ap.add_argument("--seed", type=int, default=7)
    opts = ap.parse_args()
    os.makedirs(opts.out, exist_ok=True)
    arrays = make_sample_map(opts.seed)
    np.savez_compressed(os.path.join(opts.out, "params.npz"), **arrays)
    with open(os.path.join(opts.out, "semantic.json"), "w") as fh:
        json.dump({"segmentation": [{"id": i, "class": c} for i, c, _ in CLASSES]}, fh, indent=1)
        fh.write("\n")
    size = os.path.getsize(os.path.join(opts.out, "params.npz"))
    print(f"wrote {len(arrays['means3D'])} Gaussians, {len(CLASSES)} classes to {opts.out} ({size / 1e6:.2f} MB)")


if __name__ == "__main__":
    main()
