#!/usr/bin/env python3
"""What the COCO detector costs the streaming SLAM server: milliseconds per labelled frame and frames per second
with and without it, through the server's own engine code (``semantic_gs_slam_ros.engine.make_engine``'s
``EngineAdapter`` + ``LabelStage``), on 2 cores.

    source scripts/env.sh && python bench/detector_cost.py ../shared/data/7scenes-redkitchen-0-499 \\
        [--frames 40] [--every 1 4] [--threads 2]

A. The labelling stage alone on the frames (320x240): the detector's call (letterbox, onnxruntime, decoding) and
   the whole stage (geometry + detector, naming) against geometry only, in ms per labelled frame (median, p90).
B. The engine over the same frames (decoded beforehand) with ``labels: geometry`` and ``labels: auto`` (the installed
   detector), for each ``--every`` k (labels on every k-th frame and the expected keyframes): FPS over frames 1..n and
   the ratio to geometry only, in the same run. The synthetic home (``--home``) instead prints what the detector makes
   of the simulator's rendered objects (the simulator keeps its exact labels either way).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time

import numpy as np


def _ms(xs: list[float]) -> str:
    xs = sorted(xs)
    return f"{1000 * statistics.median(xs):6.1f} ms (p90 {1000 * xs[int(0.9 * (len(xs) - 1))]:6.1f})"


def part_a(frames, k, model: str) -> None:
    from semantic_gs_slam.labels import LabelConfig, LabelStage
    from semantic_gs_slam.labels.onnx_model import OnnxSegmenter

    det = OnnxSegmenter(model, 0.4)
    geo = LabelStage(LabelConfig(mode="geometry"), k)
    full = LabelStage(LabelConfig(mode="onnx"), k)
    t_det, t_geo, t_full = [], [], []
    for f in frames:
        t0 = time.perf_counter()
        det(f.rgb)
        t1 = time.perf_counter()
        geo(f.rgb, f.depth, None, f.gt_c2w)
        t2 = time.perf_counter()
        full(f.rgb, f.depth, None, f.gt_c2w)
        t3 = time.perf_counter()
        t_det.append(t1 - t0)
        t_geo.append(t2 - t1)
        t_full.append(t3 - t2)
    print(f"A. per labelled frame ({len(frames)} frames, {k.width}x{k.height}, onnxruntime {det.provider}):")
    print(f"   detector alone (letterbox 416, NanoDet-g, GFL decode + NMS) {_ms(t_det)}")
    print(f"   geometry only                                            {_ms(t_geo)}")
    print(f"   geometry + detector (the stage with labels: auto)        {_ms(t_full)}")
    print(f"   -> the detector adds {1000 * (statistics.median(t_full) - statistics.median(t_geo)):.1f} ms per "
          "labelled frame")


def part_b(frames, k, threads: int, everies: list[int]) -> None:
    from semantic_gs_slam.config import SlamConfig
    from semantic_gs_slam.labels import LabelConfig, LabelStage
    from semantic_gs_slam.slam import SLAM
    from semantic_gs_slam_ros.engine import EngineAdapter

    print(f"B. engine + labels through the server's EngineAdapter ({len(frames)} frames, {threads} threads; the two "
          "engines take turns frame by frame, so both see the same machine load):")
    for every in everies:
        runs = {}
        for mode in ("geometry", "auto"):
            eng = SLAM(SlamConfig(intrinsics=k, threads=threads, device="cpu"))
            runs[mode] = (eng, EngineAdapter(eng, LabelStage(LabelConfig(mode=mode, every=every), k)), [])
        for f in frames:
            for eng, ad, times in runs.values():
                t0 = time.perf_counter()
                ad.add_frame(f.rgb, f.depth, None, f.timestamp, f.gt_c2w if not eng.poses else None)
                times.append(time.perf_counter() - t0)
        fps = {m: (len(t) - 1) / sum(t[1:]) for m, (_e, _a, t) in runs.items()}
        for mode, (eng, ad, _t) in runs.items():
            names = sorted(set(eng.classes.values()) - {"floor", "wall", "ceiling", "table", "object"})
            ratio = f" ({fps[mode] / fps['geometry']:.2f}x of geometry only)" if mode == "auto" else ""
            print(f"   every {every}: labels {ad.labels.mode:8s} {fps[mode]:5.2f} FPS{ratio}; classes named: "
                  f"{', '.join(names) or '-'}", flush=True)


def home(threads: int) -> None:
    """What the detector makes of the synthetic home's rendered frames."""
    from semantic_gs_slam.labels.onnx_model import COCO_BASE, COCO_NAMES, OnnxSegmenter
    from semantic_gs_slam.models.fetch import installed_detector
    from semantic_gs_slam.synthetic.scenes import HomeRenderer, default_intrinsics, trajectory

    det = OnnxSegmenter(installed_detector(), 0.4, threads=threads)
    k = default_intrinsics(320, 240)
    seen: dict[str, list[float]] = {}
    poses = trajectory(24, 360.0)
    views: dict[str, set[int]] = {}
    for j, c2w in enumerate(poses):
        rgb, _depth, _sem = HomeRenderer(0).render(c2w, k)
        for sid, sc, _m, _b in det((np.clip(rgb, 0, 1) * 255).astype(np.uint8)):
            seen.setdefault(COCO_NAMES[sid - COCO_BASE], []).append(sc)
            views.setdefault(COCO_NAMES[sid - COCO_BASE], set()).add(j)
    print(f"synthetic home, {len(poses)} views around the room at 320x240, score >= 0.4:")
    for n, s in sorted(seen.items(), key=lambda x: -len(x[1])):
        print(f"   {n:14s} {len(s):3d} detections in {len(views[n]):2d} views (best score {max(s):.2f})")
    if not seen:
        print("   nothing")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset", nargs="?", help="an RGB-D sequence (the shared kitchen)")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--stride", type=int, default=2)
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--every", type=int, nargs="+", default=[1, 4])
    ap.add_argument("--skip-b", action="store_true", help="only the stage's cost (part A)")
    ap.add_argument("--home", action="store_true", help="what the detector sees in the synthetic home, then stop")
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)
    from semantic_gs_slam.models.fetch import HOW_TO_ADD, installed_detector

    model = installed_detector()
    if not model:
        print(f"no COCO detector installed: {HOW_TO_ADD}", file=sys.stderr)
        return 2
    if args.home:
        home(args.threads)
        return 0
    if not args.dataset or not os.path.isdir(args.dataset):
        ap.error("give the sequence folder (e.g. ../shared/data/7scenes-redkitchen-0-499)")
    from semantic_gs_slam.io.datasets import load_dataset

    w, h = (int(x) for x in args.size.split("x"))
    ds = load_dataset(args.dataset, size=(w, h))
    frames = [ds[i] for i in range(0, min(len(ds), args.frames * args.stride), args.stride)]
    print(f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} cores seen, load "
          f"{os.getloadavg()[0]:.1f}, model {model}")
    part_a(frames, ds.intrinsics, model)
    if not args.skip_b:
        part_b(frames, ds.intrinsics, args.threads, args.every)
    return 0


if __name__ == "__main__":
    sys.exit(main())
