#!/usr/bin/env python3
"""How the map's per-class fusion copes with flickering labels: the same synthetic sequence mapped with
clean labels and with labels that flicker from frame to frame.

Usage (from the repository root)::

    source scripts/env.sh && python bench/slam_label_noise.py                  # 160x90, 16 frames
    python bench/slam_label_noise.py --flip 0.3 --drop 0.2 --frames 24

In each noisy frame every object region (a connected region of one class) is, with probability
``--flip``, given another object class, and with probability ``--drop`` left unlabelled (0). The map
is evaluated against the clean labels (mIoU and per-class IoU of the rendered labels at every view),
with its Gaussian count and mapping time. Tracking uses the reference poses (``use_gt_pose``) so only
the labels differ.
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np

from semantic_gs_slam.config import SlamConfig, TrackingConfig
from semantic_gs_slam.eval.evaluate import evaluate
from semantic_gs_slam.io.datasets import load_dataset
from semantic_gs_slam.labels.geometry import connected_components
from semantic_gs_slam.slam import SLAM
from semantic_gs_slam.synthetic.scenes import CLASS_ID, generate

OBJECT_IDS = [CLASS_ID[c] for c in ("chair", "sofa", "bottle", "cup", "trash", "bin", "fridge", "table")]


def flicker(sem: np.ndarray, flip: float, drop: float, rng: np.random.Generator) -> np.ndarray:
    """``sem`` with whole object regions relabelled (``flip``) or unlabelled (``drop``)."""
    out = sem.copy()
    h, w = sem.shape
    for c in OBJECT_IDS:
        lab, n = connected_components(sem == c, np.ones((h, w - 1), bool), np.ones((h - 1, w), bool))
        for r in range(1, n + 1):
            u = rng.random()
            if u < flip:
                out[lab == r] = rng.choice([o for o in OBJECT_IDS if o != c])
            elif u < flip + drop:
                out[lab == r] = 0
    return out


def run(ds, noisy: bool, args: argparse.Namespace) -> dict:
    cfg = SlamConfig(intrinsics=ds.intrinsics, tracking=TrackingConfig(use_gt_pose=True), threads=args.threads)
    eng = SLAM(cfg, ds.classes)
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    for i in range(len(ds)):
        f = ds[i]
        sem = flicker(f.semantics, args.flip, args.drop, rng) if noisy else f.semantics
        eng.add_frame(f.rgb, f.depth, sem, f.timestamp, f.gt_c2w)
    wall = time.perf_counter() - t0
    res = evaluate(eng, ds, list(range(len(ds))))
    res["wall_s"] = wall
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=90)
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--flip", type=float, default=0.3)
    ap.add_argument("--drop", type=float, default=0.2)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        generate(tmp, frames=args.frames, width=args.width, height=args.height, span_deg=60.0)
        ds = load_dataset(tmp)
        clean = run(ds, False, args)
        noisy = run(ds, True, args)
    print(f"synthetic home {args.width}x{args.height}, {args.frames} frames, flip {args.flip}, drop {args.drop} "
          f"(poses from the reference)")
    print("| | clean labels | flickering labels |\n|---|---|---|")
    print(f"| semantic mIoU (vs clean) | {clean['miou']:.3f} | {noisy['miou']:.3f} |")
    print(f"| Gaussians | {clean['gaussians']} | {noisy['gaussians']} |")
    print(f"| mapping wall time (s) | {clean['wall_s']:.1f} | {noisy['wall_s']:.1f} |")
    print("per-class IoU, clean: " + ", ".join(f"{k} {v:.2f}" for k, v in clean["class_iou"].items()))
    print("per-class IoU, noisy: " + ", ".join(f"{k} {v:.2f}" for k, v in noisy["class_iou"].items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
