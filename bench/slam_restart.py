#!/usr/bin/env python3
"""A restart on a saved map (``SLAM.from_map``) on the shared 7-Scenes kitchen: map the first half, save it, then
start a new engine on the saved map at frames of the second half and print, per start, how the first frame was
taken (relocalised or lost), the frames until mapping resumed, the pose error of the first frame and the largest
error over the frames that follow (from the first relocalised one when the first frame is lost), and the Gaussians
added.

Errors are given against the ground truth and against the ground truth in the map's frame ("in map": the pose of
the first run's frame nearest the camera moved by the ground-truth motion from there; the saved map carries the
first run's drift, several cm at the end of the first half, and the restart is right to keep it)::

    source scripts/env.sh && python bench/slam_restart.py ../shared/data/7scenes-redkitchen-0-499   # 160x120
    python bench/slam_restart.py ../shared/data/7scenes-redkitchen-0-499 --size 320x240 --starts 250,270,290
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time

import numpy as np


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", help="the 7-Scenes kitchen sequence folder (frames 0-499)")
    ap.add_argument("--size", default="160x120")
    ap.add_argument("--stride", type=int, default=6, help="the first run's stride over frames 0-249")
    ap.add_argument("--frontend", default="keyframe", choices=["keyframe", "render"])
    ap.add_argument("--iters", type=int, default=1, help="mapping.iters of both runs")
    ap.add_argument("--starts", default="250,262,270,290,320,350,400,450", help="first frames of the restarts")
    ap.add_argument("--follow", type=int, default=8, help="frames fed per restart (every 3rd from the start)")
    args = ap.parse_args(argv)
    from semantic_gs_slam.config import LoopConfig, MappingConfig, SlamConfig, TrackingConfig
    from semantic_gs_slam.geometry import pose_error
    from semantic_gs_slam.io.datasets import load_dataset, parse_size
    from semantic_gs_slam.slam import SLAM

    logging.basicConfig(level=logging.ERROR)
    ds = load_dataset(args.dataset, size=parse_size(args.size))
    cfg = SlamConfig(intrinsics=ds.intrinsics, threads=2, tracking=TrackingConfig(frontend=args.frontend),
                     mapping=MappingConfig(first_frame_iters=5 * args.iters, iters=args.iters,
                                           densify_every_frame=False),
                     loop=LoopConfig(enabled=False))
    first_idx = list(range(0, 250, args.stride))
    t0 = time.perf_counter()
    first = SLAM(cfg, initial_c2w=ds[0].gt_c2w)
    gts = []
    for i in first_idx:
        f = ds[i]
        gts.append(f.gt_c2w)
        first.add_frame(f.rgb, f.depth, None, f.timestamp)
    drift = [pose_error(p, g)[0] * 100 for p, g in zip(first.poses, gts, strict=True)]
    print(f"first run: frames 0-249 stride {args.stride} at {args.size}, {args.frontend} front end, "
          f"{len(first.map)} Gaussians, {time.perf_counter() - t0:.0f} s; its error at the last frame "
          f"{drift[-1]:.1f} cm (largest {max(drift):.1f} cm)")

    def in_map(gt: np.ndarray) -> np.ndarray:
        n = min(range(len(gts)), key=lambda j: float(np.linalg.norm(gts[j][:3, 3] - gt[:3, 3])))
        return first.poses[n] @ np.linalg.inv(gts[n]) @ gt

    print("| start | first frame | mapped from | first: GT cm / deg | first: in map cm / deg | after: in map max cm "
          "| Gaussians added | first frame s |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        first.save(tmp, ply=False)
        for s in [int(x) for x in args.starts.split(",")]:
            eng = SLAM.from_map(tmp, cfg)
            n0 = len(eng.map)
            errs, gts_err, t_first = [], [], 0.0
            for n, i in enumerate(range(s, min(s + 3 * args.follow, len(ds)), 3)):
                f = ds[i]
                t1 = time.perf_counter()
                pose = eng.add_frame(f.rgb, f.depth, None, f.timestamp)
                if n == 0:
                    t_first = time.perf_counter() - t1
                gts_err.append(pose_error(pose, f.gt_c2w))
                errs.append(pose_error(pose, in_map(f.gt_c2w)))
            src = eng.logs[0].pose_source
            mapped = next((s + 3 * lg.index for lg in eng.logs if lg.pose_source == "recovered"), None)
            after = [e[0] * 100 for e, lg in zip(errs, eng.logs, strict=True) if not lg.tracking_failed]
            if src == "lost":  # a later frame may still be relocalised: the error of the frames from then on
                print(f"| {s} | lost | {mapped if mapped is not None else 'never'} | - | - | "
                      f"{f'{max(after):.1f}' if after else '-'} | {len(eng.map) - n0} | {t_first:.1f} |", flush=True)
                continue
            print(f"| {s} | {src} | {mapped} | {gts_err[0][0] * 100:.1f} / {gts_err[0][1]:.1f} | "
                  f"{errs[0][0] * 100:.1f} / {errs[0][1]:.1f} | {max(after):.1f} | {len(eng.map) - n0} | "
                  f"{t_first:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
