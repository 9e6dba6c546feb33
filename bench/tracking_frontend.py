#!/usr/bin/env python3
"""The frame-rate tracking front end alone on a real RGB-D sequence, beside Open3D's tracker in the same run.

Usage (from the repository root; the data stays outside the repository)::

    source scripts/env.sh && PYTHONPATH=$PYTHONPATH:$PWD/.bench-open3d python bench/tracking_frontend.py \\
        ../shared/data/7scenes-redkitchen-0-499 --ranges 0:250,250:500 --strides 1,2,6

For every frame range and stride, the front end (:mod:`semantic_gs_slam.tracking_frontend`) tracks every selected
frame against a reference model that is rebuilt every ``--keyframe-every`` tracked frames (or sooner, when the
share of the frame's points the reference covers drops below ``--keyframe-coverage``) from the sensor's own depth
at that frame and its tracked pose: a stand-in for the depth rendered from the map, so this measures the tracker
alone (frame-to-keyframe odometry; no map, no loop closure). The first frame is put on its reference pose, as
Open3D's. Printed per run: ATE RMSE (aligned, as bench/slam_real.py), FPS (wall clock over the frames after the
first, decoding excluded: frames are decoded up front, as for Open3D), CPU seconds per frame, lost and relocalised
frames, and Open3D's ``t.pipelines.slam.Model`` (bench/slam_real.py's ``run_open3d``) on the same frames, with the
ratios. Timings depend on what else runs on the machine: the load is printed.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace

import numpy as np

from semantic_gs_slam.datasets import frame_indices, load_dataset, parse_size
from semantic_gs_slam.metrics import ate_rmse, rpe_rmse
from semantic_gs_slam.tracking_frontend import FrameTracker, FrontendConfig, build_reference

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from slam_real import run_open3d  # noqa: E402  (bench/ is not a package)


def run_front_end(frames: list, k, cfg: FrontendConfig, every: int, min_cov: float, use_rgb: bool) -> dict:
    """Track ``frames`` (decoded :class:`~semantic_gs_slam.datasets.Frame` s) with keyframe references from the
    sensor depth; returns poses, timings and counts."""
    first = frames[0].gt_c2w if frames[0].gt_c2w is not None else np.eye(4)
    tr = FrameTracker(k, cfg)
    f0 = frames[0]
    rgb0 = f0.rgb if use_rgb else None
    tr.set_reference(build_reference(f0.depth, first, k, cfg, rgb=rgb0, keyframe_id=0))
    tr.track_frame(f0.depth, rgb0, guess_c2w=first)  # compiles / warms the kernels (not timed)
    tr = FrameTracker(k, cfg)
    poses, lost, reloc, kfs, steps = [first], 0, 0, 1, 0
    t0, c0 = time.perf_counter(), time.process_time()
    tr.set_reference(build_reference(f0.depth, first, k, cfg, rgb=rgb0, keyframe_id=0))
    since_kf, was_lost = 0, False
    track_s = ref_s = 0.0
    for n, f in enumerate(frames[1:], start=1):
        rgb = f.rgb if use_rgb else None
        t1 = time.perf_counter()
        res = tr.track_frame(f.depth, rgb, guess_c2w=poses[-1] if n == 1 else None)
        t2 = time.perf_counter()
        track_s += t2 - t1
        steps += res.steps
        if tr.lost:
            lost += 1
            poses.append(poses[-1])  # a lost frame keeps the last trusted pose
            was_lost = True
            continue
        if was_lost:
            reloc += 1
            was_lost = False
        poses.append(res.c2w)
        since_kf += 1
        if since_kf >= every or res.quality.coverage < min_cov:
            tr.set_reference(build_reference(f.depth, res.c2w, k, cfg, rgb=rgb, keyframe_id=n))
            kfs += 1
            since_kf = 0
            ref_s += time.perf_counter() - t2
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    m = len(frames) - 1
    return {"poses": poses, "fps": m / wall, "cpu_ms": 1000 * cpu / m, "track_ms": 1000 * track_s / m,
            "ref_ms": 1000 * ref_s / max(kfs - 1, 1), "lost": lost, "relocalised": reloc, "keyframes": kfs,
            "steps": steps / m}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset", help="sequence folder (7-Scenes, TUM RGB-D, Replica, ...)")
    ap.add_argument("--ranges", default="0:250", help="comma-separated START:STOP frame ranges")
    ap.add_argument("--strides", default="1,2,6", help="comma-separated strides")
    ap.add_argument("--size", default="320x240", help="working size WIDTHxHEIGHT")
    ap.add_argument("--keyframe-every", type=int, default=10, help="new reference every K tracked frames")
    ap.add_argument("--keyframe-coverage", type=float, default=0.7,
                    help="... or sooner, once the reference covers fewer of the frame's points than this")
    ap.add_argument("--config", help="JSON of FrontendConfig overrides, e.g. {\"sigma_geo\": 0.02}")
    ap.add_argument("--rgb", action="store_true", help="pass colour (photometric term when photometric_weight > 0)")
    ap.add_argument("--no-open3d", action="store_true")
    ap.add_argument("--o3d-voxel", type=float, default=0.02)
    ap.add_argument("--o3d-depth-max", type=float, default=3.0)
    args = ap.parse_args()
    cfg = FrontendConfig()
    if args.config:
        over = json.loads(args.config)
        cfg = replace(cfg, **{key: tuple(v) if isinstance(v, list) else v for key, v in over.items()})
    cfg.check()
    if args.keyframe_every < 1:
        ap.error("--keyframe-every must be >= 1")
    ds = load_dataset(args.dataset, size=parse_size(args.size))
    if ds.poses is None:
        print("the sequence has no reference poses: ATE cannot be computed", file=sys.stderr)
        return 2
    k = ds.intrinsics
    load = os.getloadavg()[0]
    print(f"sequence {args.dataset}, {k.width}x{k.height}, keyframe every {args.keyframe_every} (or coverage < "
          f"{args.keyframe_coverage}), config {cfg}, load {load:.1f} on {os.cpu_count()} cores")
    print("\n| frames | stride | n | ours ATE (cm) | Open3D ATE (cm) | ATE ratio | ours RPE (cm) | ours FPS | Open3D FPS "
          "| ours CPU ms/frame | ours lost / relocalised | Open3D failures | keyframes | steps/frame | load |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for rng in args.ranges.split(","):
        start, stop = (int(x) for x in rng.split(":"))
        for stride in (int(s) for s in args.strides.split(",")):
            idx = frame_indices(len(ds), start, stride, 0, stop)
            frames = [ds[i] for i in idx]
            gts = [ds.poses[i] for i in idx]
            ours = run_front_end(frames, k, cfg, args.keyframe_every, args.keyframe_coverage, args.rgb)
            ate = 100 * ate_rmse(ours["poses"], gts)
            o3 = None if args.no_open3d else run_open3d(ds, idx, args.o3d_voxel, args.o3d_depth_max, "cpu")
            o3_ate = 100 * ate_rmse(o3["poses"], gts) if o3 else float("nan")
            print(f"| {start}-{stop - 1} | {stride} | {len(idx)} | {ate:.2f} | {o3_ate:.2f} | {ate / o3_ate:.2f} | "
                  f"{100 * rpe_rmse(ours['poses'], gts, 1):.2f} | {ours['fps']:.1f} | "
                  f"{o3['fps'] if o3 else float('nan'):.1f} | {ours['cpu_ms']:.1f} | {ours['lost']} / "
                  f"{ours['relocalised']} | {o3['lost'] if o3 else '-'} | {ours['keyframes']} | {ours['steps']:.1f} | "
                  f"{os.getloadavg()[0]:.1f} |", flush=True)
    print("\nFPS: wall clock over frames 1..n (tracking and rebuilding the reference; frames decoded up front, as for "
          "Open3D). Reference built from the sensor depth at the keyframe (a stand-in for the rendered map).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
