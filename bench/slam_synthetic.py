#!/usr/bin/env python3
"""SLAM benchmark on the synthetic home: generates the sequence, runs the engine, prints the table.

Usage (from the repository root)::

    source scripts/env.sh && python bench/slam_synthetic.py                 # 300x170, 60 frames
    python bench/slam_synthetic.py --width 600 --height 340 --frames 30
    python bench/slam_synthetic.py --renderer-only                          # renderer ms only

Prints renderer timings (forward, forward+backward) for the first keyframe's map, then per-frame
progress (stderr) and the evaluation table: ATE RMSE (cm, aligned), PSNR, SSIM, depth L1 (cm),
semantic mIoU, FPS (wall time of add_frame over the sequence), Gaussian count. Timings depend on
what else runs on the machine.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time

import numpy as np
import torch

from semantic_gs_slam.config import MappingConfig, RendererConfig, SlamConfig
from semantic_gs_slam.errors import ConfigError
from semantic_gs_slam.eval.evaluate import evaluate, format_table
from semantic_gs_slam.io.datasets import load_dataset
from semantic_gs_slam.render import render
from semantic_gs_slam.slam import SLAM
from semantic_gs_slam.synthetic.scenes import generate


def renderer_timing(eng: SLAM, c2w: np.ndarray, reps: int = 7) -> tuple[float, float]:
    """Median forward and forward+backward milliseconds of a full render at ``c2w``."""
    w2c = torch.as_tensor(np.linalg.inv(c2w), dtype=torch.float32, device=eng.device)
    fwd, both = [], []
    for _ in range(reps):
        t0 = time.perf_counter()
        with torch.no_grad():
            render(eng.map.gaussians(), w2c, eng.k, eng.cfg.renderer)
        t1 = time.perf_counter()
        out = render(eng.map.gaussians(), w2c, eng.k, eng.cfg.renderer)
        (out.rgb.sum() + out.depth.sum() + out.semantic.sum()).backward()
        t2 = time.perf_counter()
        fwd.append(t1 - t0)
        both.append(t2 - t1)
    return 1000 * statistics.median(fwd), 1000 * statistics.median(both)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--width", type=int, default=300)
    ap.add_argument("--height", type=int, default=170)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--span-deg", type=float, default=120.0)
    ap.add_argument("--keyframe-every", type=int, default=MappingConfig.keyframe_every)
    ap.add_argument("--mapping-iters", type=int, default=MappingConfig.iters,
                    help="Adam iterations per keyframe (default: the device's, config.DEVICE_DEFAULTS)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--data", help="existing dataset folder (default: generate into a temp folder)")
    ap.add_argument("--out", help="where to save the map (default: temp folder)")
    ap.add_argument("--renderer-only", action="store_true")
    ap.add_argument("--device", default="auto", help="torch device: auto (CUDA when present), cpu, cuda, cuda:N")
    ap.add_argument("--backend", default="auto", choices=["auto", "torch", "gsplat", "numba"], help="renderer back-end")
    ap.add_argument("--count-syncs", action="store_true",
                    help="print host synchronisations per frame (device_guard.DeviceGuard; slows the run)")
    ap.add_argument("--refine-iters", type=int, default=0, help="also evaluate after an offline map refinement")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                    help="config override, e.g. --set mapping.radius_factor=0.45 (repeatable)")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    tmp = tempfile.mkdtemp(prefix="slam_bench_")
    data = a.data or os.path.join(tmp, "home")
    if not a.data:
        t = time.perf_counter()
        generate(data, a.frames, a.width, a.height, span_deg=a.span_deg)
        print(f"generated {a.frames} frames {a.width}x{a.height} in {time.perf_counter() - t:.1f} s", file=sys.stderr)
    ds = load_dataset(data)
    cfg = SlamConfig(intrinsics=ds.intrinsics, mapping=MappingConfig(keyframe_every=a.keyframe_every,
                                                                     iters=a.mapping_iters), threads=a.threads,
                     device=a.device, renderer=RendererConfig(backend=a.backend))
    try:
        cfg = cfg.with_overrides(a.set)
    except ConfigError as exc:
        ap.error(str(exc))
    eng = SLAM(cfg, ds.classes)
    n = min(a.frames, len(ds))
    frames = [ds[i] for i in range(n)]  # decode up front: FPS counts the engine only
    t0 = time.perf_counter()
    f = frames[0]
    eng.add_frame(f.rgb, f.depth, f.semantics, f.timestamp, f.gt_c2w)
    fwd, both = renderer_timing(eng, f.gt_c2w)
    print(f"renderer {a.width}x{a.height}, {len(eng.map)} Gaussians: forward {fwd:.1f} ms, "
          f"forward+backward {both:.1f} ms (median of 7, {a.threads} threads)")
    if a.renderer_only:
        return 0
    guard = None
    if a.count_syncs:
        from semantic_gs_slam.device_guard import DeviceGuard

        guard = DeviceGuard()
        guard.__enter__()
    t0 = time.perf_counter()
    for i in range(1, n):
        f = frames[i]
        eng.add_frame(f.rgb, f.depth, f.semantics, f.timestamp, f.gt_c2w)
        lg = eng.logs[-1]
        syncs = f" host syncs {guard.end_frame()}" if guard else ""
        print(f"frame {i:3d}{' KF' if lg.keyframe else '   '} gaussians {lg.n_gaussians:6d} "
              f"track {lg.track_s:.2f} s map {lg.map_s:.2f} s{syncs}", file=sys.stderr, flush=True)
    wall = time.perf_counter() - t0
    if guard:
        guard.__exit__(None, None, None)
        print(f"host synchronisations per frame: mean {statistics.mean(guard.syncs_per_frame):.1f}, "
              f"max {max(guard.syncs_per_frame)}; where: {guard.sync_sites.most_common(5)} (timings include "
              "the guard's overhead)")
    res = evaluate(eng, ds, list(range(n)), every=max(1, n // 20))
    res["fps"] = (n - 1) / wall
    track = [lg.track_s for lg in eng.logs[1:]]
    kf_map = [lg.map_s for lg in eng.logs[1:] if lg.keyframe]
    other = [lg.map_s for lg in eng.logs[1:] if not lg.keyframe]
    print(f"sequence {a.width}x{a.height}, {n} frames, keyframe every {a.keyframe_every}, "
          f"{eng.cfg.mapping.iters} mapping iterations, {a.threads} threads")
    print(format_table(res))
    print(f"tracking ms/frame: median {1000 * statistics.median(track):.0f}, mean {1000 * statistics.mean(track):.0f}; "
          f"mapping ms/keyframe: median {1000 * statistics.median(kf_map):.0f}, "
          f"mean {1000 * statistics.mean(kf_map):.0f}; "
          f"densify ms/other frame: median {1000 * statistics.median(other or [0]):.0f}")
    med = statistics.median(track) + statistics.median(other or [0]) * (1 - 1 / a.keyframe_every) \
        + statistics.median(kf_map) / a.keyframe_every
    print(f"FPS from the medians (less sensitive to other load on the machine): {1 / med:.2f}; "
          f"FPS excludes frame 0's {cfg.mapping.first_frame_iters}-iteration initial mapping")
    if a.refine_iters > 0:
        t1 = time.perf_counter()
        eng.refine(a.refine_iters)
        res2 = evaluate(eng, ds, list(range(n)), every=max(1, n // 20))
        res2["fps"] = res["fps"]
        print(f"after {a.refine_iters} refinement iterations over all {len(eng.keyframes)} keyframes "
              f"({time.perf_counter() - t1:.1f} s, not in FPS):")
        print(format_table(res2))
    out = a.out or os.path.join(tmp, "map")
    eng.save(out)
    print(f"map written to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
