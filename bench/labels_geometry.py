#!/usr/bin/env python3
"""Accuracy and speed of the geometry labelling stage on the synthetic home (where truth exists).

Usage (from the repository root)::

    source scripts/env.sh && python bench/labels_geometry.py                    # 300x170, 30 frames
    python bench/labels_geometry.py --width 320 --height 240 --frames 60
    python bench/labels_geometry.py --write-figures     # also into docs/figures.md (block labels_geometry_300x170)

Renders the synthetic home's orbit (ground-truth poses and labels), labels every frame with
:class:`~semantic_gs_slam.labels.geometry.GeometryLabeller` at the true pose, and prints per-frame time,
class-agnostic object recall (a ground-truth object instance — a connected region of one object class —
counts when one predicted instance overlaps it with IoU >= 0.5, or >= 0.25), the mean best IoU, plane
IoU (floor, wall), the share of 'table' (support surface) pixels that lie on a table, counter, chair or
sofa, and id stability (a single-region object keeps its best-matching instance id from one frame to the
next). Timings depend on what else runs on the machine.
"""

from __future__ import annotations

import argparse
import statistics
import time

import figures
import numpy as np

from semantic_gs_slam.labels.geometry import (
    FIRST_INSTANCE_ID,
    FLOOR,
    TABLE,
    WALL,
    GeometryLabeller,
    connected_components,
)
from semantic_gs_slam.synthetic.scenes import CLASS_ID, HomeRenderer, default_intrinsics, trajectory

OBJECTS = ("chair", "sofa", "bottle", "cup", "trash", "bin", "fridge")


def gt_instances(sem: np.ndarray, min_px: int) -> list[tuple[str, np.ndarray]]:
    """(class name, mask) of every connected region of an object class with >= ``min_px`` pixels."""
    out = []
    h, w = sem.shape
    for name in OBJECTS:
        m = sem == CLASS_ID[name]
        if not m.any():
            continue
        lab, n = connected_components(m, np.ones((h, w - 1), bool), np.ones((h - 1, w), bool))
        for c in range(1, n + 1):
            r = lab == c
            if r.sum() >= min_px:
                out.append((name, r))
    return out


def best_match(pred: np.ndarray, mask: np.ndarray) -> tuple[int, float]:
    """The predicted instance id with the highest IoU against ``mask`` and that IoU (0, 0.0 if none)."""
    cand = np.unique(pred[mask])
    best, best_iou = 0, 0.0
    for c in cand[cand >= FIRST_INSTANCE_ID]:
        p = pred == c
        iou = float((p & mask).sum() / (p | mask).sum())
        if iou > best_iou:
            best, best_iou = int(c), iou
    return best, best_iou


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--width", type=int, default=300)
    ap.add_argument("--height", type=int, default=170)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--span-deg", type=float, default=120.0)
    figures.add_argument(ap)
    args = ap.parse_args()
    provenance = figures.Provenance.start() if args.write_figures else None
    k = default_intrinsics(args.width, args.height)
    traj = trajectory(args.frames, args.span_deg)
    renderer = HomeRenderer(0)
    lab = GeometryLabeller(k)
    min_px = int(lab.cfg.min_segment_fraction * k.width * k.height)
    times, ious, inter, union = [], [], np.zeros(3), np.zeros(3)
    top_ok = top_all = 0
    prev: dict[str, int] = {}
    same = pairs = 0
    for c2w in traj:
        rgb, depth, sem = renderer.render(c2w, k)
        t0 = time.perf_counter()
        pred = lab.label(rgb, depth, c2w).ids
        times.append(time.perf_counter() - t0)
        insts = gt_instances(sem, min_px)
        single = {n for n in OBJECTS if sum(1 for m, _ in insts if m == n) == 1}
        cur = {}
        for name, mask in insts:
            pid, iou = best_match(pred, mask)
            ious.append(iou)
            if name in single and iou >= 0.25:
                cur[name] = pid
        for name, pid in cur.items():
            if name in prev:
                pairs += 1
                same += pid == prev[name]
        prev = cur
        for j, (cls, gt) in enumerate(((FLOOR, "floor"), (WALL, "wall"))):
            p, g = pred == cls, sem == CLASS_ID[gt]
            inter[j] += (p & g).sum()
            union[j] += (p | g).sum()
        top = pred == TABLE
        top_all += int(top.sum())
        top_ok += int(np.isin(sem[top], [CLASS_ID[c] for c in ("table", "counter", "chair", "sofa")]).sum())
    iou_arr = np.array(ious)
    lines = [
        f"synthetic home {k.width}x{k.height}, {args.frames} frames, {len(ious)} ground-truth object regions "
        f"(>= {min_px} px)",
        "| metric | value |\n|---|---|",
        f"| labelling time per frame (median, ms) | {1000 * statistics.median(times):.0f} |",
        f"| object recall, IoU >= 0.5 | {(iou_arr >= 0.5).mean():.3f} |",
        f"| object recall, IoU >= 0.25 | {(iou_arr >= 0.25).mean():.3f} |",
        f"| mean best IoU per object region | {iou_arr.mean():.3f} |",
        f"| floor IoU | {inter[0] / max(union[0], 1):.3f} |",
        f"| wall IoU | {inter[1] / max(union[1], 1):.3f} |",
        f"| 'table' pixels on a table/counter/chair/sofa | {top_ok / max(top_all, 1):.3f} |",
        f"| instance id kept frame to frame | {same / max(pairs, 1):.3f} ({pairs} pairs) |",
        f"| instances created | {lab.next_id - FIRST_INSTANCE_ID} |",
    ]
    print("\n".join(lines))
    if provenance is not None:
        figures.write_block(f"labels_geometry_{k.width}x{k.height}", "\n\n".join(
            [lines[0] + ":", "\n".join(lines[1:])]), provenance)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
