#!/usr/bin/env python3
"""The map refinement's schedule (coarse to fine; the views' poses fixed or optimised), compared on one online
state of a real sequence.

Usage (from the repository root; the data stays outside the repository)::

    source scripts/env.sh && python bench/refine_schedule.py ../shared/data/7scenes-redkitchen-0-499 \\
        --frames 250 --stride 1 --shares 0,0.5,0.8 [--poses off,on]

Runs the engine once over the frames with the ``realtime`` profile (every frame fed as fast as it takes them, as
``bench/slam_real.py`` does), then refines a copy of that one state for each ``mapping.refine_coarse_share`` in
``--shares`` within the same time budget (``SLAM.refine(seconds=...)``: the deferred frames first, then the
iterations, the first share of the budget at half resolution), with the views' poses fixed or optimised too
(``--poses``: ``SLAM.refine(poses=...)``), and evaluates each map every ``--eval-every`` frames. Comparing copies
of one state leaves out the run-to-run spread of the threaded mapping (which frames became keyframes), so
differences of a tenth of a dB show. Printed per share and poses setting: iterations, PSNR, its change against the
first row, PSNR on the evaluated frames that were not views of the refinement (held out from it), SSIM, depth L1
and ATE. Timings depend on what else runs.
"""

from __future__ import annotations

import argparse
import copy
import sys
import time

import numpy as np
import torch

from semantic_gs_slam.config import SlamConfig
from semantic_gs_slam.eval.evaluate import evaluate
from semantic_gs_slam.eval.metrics import psnr
from semantic_gs_slam.io.datasets import frame_indices, load_dataset, parse_size
from semantic_gs_slam.io.exposure import to_frame
from semantic_gs_slam.slam import SLAM


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset", help="an RGB-D sequence folder (any layout the loaders read)")
    ap.add_argument("--frames", type=int, default=250)
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--start", type=int, default=0, help="first dataset frame")
    ap.add_argument("--size", default="320x240", help="working size WIDTHxHEIGHT")
    ap.add_argument("--seconds", type=float, default=30.0, help="the refinement's time budget")
    ap.add_argument("--shares", default="0,0.5,0.8", help="comma-separated mapping.refine_coarse_share values")
    ap.add_argument("--poses", default="on",
                    help="comma-separated off / on: the refinement keeps the views' poses or optimises them too")
    ap.add_argument("--eval-every", type=int, default=10)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    try:
        shares = [float(x) for x in args.shares.split(",")]
    except ValueError:
        ap.error(f"--shares must be comma-separated numbers, got {args.shares!r}")
    if not all(0 <= s < 1 for s in shares) or not args.seconds > 0:
        ap.error("every share must be in [0, 1) and --seconds > 0")
    poses = args.poses.split(",")
    if not poses or any(p not in ("off", "on") for p in poses):
        ap.error(f"--poses must be comma-separated off / on, got {args.poses!r}")
    ds = load_dataset(args.dataset, size=parse_size(args.size))
    idx = frame_indices(len(ds), args.start, args.stride, args.frames)
    eng = SLAM(SlamConfig(intrinsics=ds.intrinsics, threads=args.threads).with_profile("realtime"))
    frames = [ds[i] for i in idx]  # decoded up front, as bench/slam_real.py does
    t0 = time.perf_counter()
    for f in frames:
        eng.add_frame(f.rgb, f.depth, None, f.timestamp, f.gt_c2w)
    eng.finish(600.0)
    online = evaluate(eng, ds, idx, every=args.eval_every)
    print(f"sequence {args.dataset}: frames {idx[0]}..{idx[-1]} every {args.stride} ({len(idx)} frames), "
          f"{args.size}, {args.threads} threads; online run {time.perf_counter() - t0:.1f} s, "
          f"{len(eng.keyframes)} keyframes mapped online, {len(eng.backlog)} deferred frames, "
          f"PSNR {online['psnr']:.2f} dB; refinement budget {args.seconds:g} s")
    views = {kf.index for kf in eng.keyframes} | {i for i, *_ in eng.backlog}
    held = [n for n in range(0, len(idx), args.eval_every) if n not in views]
    print(f"{len(views)} views in the refinement; {len(held)} of the evaluated frames are not views")
    print("| coarse share | views' poses | iterations | PSNR (dB) | vs first row | PSNR, frames not views (dB) | SSIM "
          "| depth L1 (cm) | ATE (cm) |")
    print("|---|---|---|---|---|---|---|---|---|")
    base = None
    for share in shares:
        for pose in poses:
            run = copy.deepcopy(eng)
            run.cfg.mapping.refine_coarse_share = share
            _, done = run.refine(10 ** 9, poses=pose == "on", seconds=args.seconds)
            r = evaluate(run, ds, idx, every=args.eval_every)
            base = r["psnr"] if base is None else base
            held_psnr = float(np.mean([_psnr(run, ds, idx, n) for n in held])) if held else float("nan")
            print(f"| {share:g} | {pose} | {done} | {r['psnr']:.2f} | {r['psnr'] - base:+.2f} | {held_psnr:.2f} | "
                  f"{r['ssim']:.3f} | {r['depth_l1_cm']:.2f} | {r.get('ate_rmse_cm', float('nan')):.2f} |",
                  flush=True)
    return 0


def _psnr(eng: SLAM, ds, idx: list[int], n: int) -> float:
    """PSNR of the map rendered at engine frame ``n`` in that frame's exposure, as evaluate() counts it."""
    img = eng.render_view(eng.poses[n]).rgb.clamp(0, 1)
    exp = eng.exposure_of(n)
    if exp is not None:
        img = to_frame(img, exp)
    return psnr(img, torch.as_tensor(ds[idx[n]].rgb, device=eng.device))


if __name__ == "__main__":
    sys.exit(main())
