#!/usr/bin/env python3
"""Replay a mapping-while-exploring run offline: SLAM on its frames, scored frame by frame.

``make demo-explore`` (``demo_explore --map-dir DIR``) leaves in DIR the SLAM server's work folder
(``work/``: the frames it received, ``completed.jsonl``) and ``camera_poses.npz`` (the camera's true
and wheel-odometry poses by stamp). This runs the engine over those frames with the odometry as its
prior, as the server does, and prints each frame's pose source and error against the truth, the
ATE of SLAM and of the odometry alone (translation and rotation), the time per frame, and where the
object database puts the bottle, the cup and the trash in the replayed map against the simulator's
truth. ``--true-poses`` maps with the true poses instead (the objects' error without pose error).
``--config`` takes a JSON of SlamConfig sections to try other settings on the same frames::

    source scripts/env.sh && python bench/slam_explore_replay.py /tmp/explore_map
    python bench/slam_explore_replay.py /tmp/explore_map --config '{"tracking": {"prior_sigma_rot": 0.2}}'

Frames are the work folder's JPEG colour and PNG depth, so figures differ slightly from the live run.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np


def load(run_dir: str) -> tuple[list[dict], dict[int, np.ndarray], dict[int, np.ndarray]]:
    with open(os.path.join(run_dir, "work", "completed.jsonl"), encoding="utf-8") as fh:
        frames = [json.loads(line) for line in fh if line.strip()]
    with np.load(os.path.join(run_dir, "camera_poses.npz")) as z:
        stamps, truth, odom = z["stamps_ns"], z["truth"], z["odometry"]
    return frames, dict(zip(stamps.tolist(), truth, strict=True)), dict(zip(stamps.tolist(), odom, strict=True))


def nearest(poses: dict[int, np.ndarray], stamp: float, tol_ns: int = 5_000_000) -> np.ndarray | None:
    ns = int(round(stamp * 1e9))
    key = min(poses, key=lambda k: abs(k - ns), default=None)
    if key is None or abs(key - ns) > tol_ns or np.isnan(poses[key]).any():
        return None
    return poses[key]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run_dir", help="the --map-dir of a demo_explore run")
    ap.add_argument("--config", default="",
                    help="SlamConfig overrides: a JSON file, or the JSON itself, e.g. '{\"tracking\": {...}}'")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--true-poses", action="store_true",
                    help="map with the simulator's true poses (no tracking): the objects' error without pose error")
    ap.add_argument("--min-motion", default="0.05,5", help="metres,degrees: skip still frames like the server")
    args = ap.parse_args(argv)

    from PIL import Image

    from semantic_gs_slam.config import Intrinsics, SlamConfig
    from semantic_gs_slam.geometry import pose_error
    from semantic_gs_slam.slam import SLAM
    from semantic_gs_slam.synthetic.scenes import CLASSES

    frames, truth, odom = load(args.run_dir)
    with np.load(os.path.join(args.run_dir, "params.npz")) as z:
        k = z["intrinsics"]
        w, h = int(z["org_width"]), int(z["org_height"])
    cfg = SlamConfig(intrinsics=Intrinsics(w, h, float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])),
                     threads=args.threads, device="cpu")
    if args.config:
        cfg = cfg.with_json(args.config)
    if args.true_poses:
        cfg.tracking.use_gt_pose = True
    eng = SLAM(cfg, {i: n for i, n, _ in CLASSES if i > 0})
    min_m, min_deg = (float(v) for v in args.min_motion.split(","))
    last = None
    est_err, odo_err, times = [], [], []
    est_rot, odo_rot = [], []
    print(" frame  source     SLAM err  (deg)   odom err  (deg)   ms", file=sys.stderr)
    for f in frames:
        t, o = nearest(truth, f["stamp"]), nearest(odom, f["stamp"])
        if t is None or o is None:
            continue
        if last is not None:
            rel = np.linalg.inv(last) @ o
            ang = np.degrees(np.arccos(np.clip((np.trace(rel[:3, :3]) - 1) / 2, -1, 1)))
            if np.linalg.norm(rel[:3, 3]) < min_m and ang < min_deg:
                continue
        last = o
        rgb = np.asarray(Image.open(os.path.join(args.run_dir, "work", f["rgb"])).convert("RGB"))
        depth = np.asarray(Image.open(os.path.join(args.run_dir, "work", f["depth"]))).astype(np.float32) / 1000.0
        sem_p = os.path.join(args.run_dir, "work", f["rgb"].replace("frames/frame", "semantics/semantic")
                             .replace(".jpg", ".png"))
        sem = np.asarray(Image.open(sem_p)).astype(np.int64) if os.path.isfile(sem_p) else None
        t0 = time.perf_counter()
        est = eng.add_frame(rgb, depth, sem, f["stamp"], gt_c2w=t if args.true_poses else None, odom_c2w=o)
        times.append(time.perf_counter() - t0)
        est_err.append(float(np.linalg.norm(est[:3, 3] - t[:3, 3])))
        odo_err.append(float(np.linalg.norm(o[:3, 3] - t[:3, 3])))
        est_rot.append(pose_error(est, t)[1])
        odo_rot.append(pose_error(o, t)[1])
        lg = eng.logs[-1]
        print(f"{lg.index:6d}  {lg.pose_source:9s} {est_err[-1] * 100:7.2f} cm {est_rot[-1]:5.1f}  "
              f"{odo_err[-1] * 100:7.2f} cm {odo_rot[-1]:5.1f} {times[-1] * 1000:6.0f}", file=sys.stderr)

    def rmse(e: list[float]) -> float:
        return float(np.sqrt(np.mean(np.square(e)))) * 100 if e else float("nan")

    sources = [lg.pose_source for lg in eng.logs]
    print(f"frames {len(est_err)}; SLAM ATE {rmse(est_err):.2f} cm (max {max(est_err, default=0) * 100:.2f}); "
          f"rotation max {max(est_rot, default=0):.1f} deg; "
          f"odometry alone {rmse(odo_err):.2f} cm (max {max(odo_err, default=0) * 100:.2f}, rotation max "
          f"{max(odo_rot, default=0):.1f} deg); odometry-only poses {sources.count('odometry')} (ICP failed) + "
          f"{sources.count('odometry_refused')} (refused by the gate); {np.mean(times) * 1000:.0f} ms per frame, "
          f"{len(eng.map)} Gaussians")
    print(object_errors(eng))
    return 0


def object_errors(eng) -> str:
    """Each graspable object's position in the replayed map (the object database's largest instance, the one the
    object memory serves) against the simulator's truth, as ``demo_explore`` prints it."""
    import tempfile

    from home_robot_exploration.demo_explore import object_errors as truth_lines
    from object_query.semantic_map import ObjectDatabase

    with tempfile.TemporaryDirectory() as tmp:
        eng.save(tmp, ply=False)
        db = ObjectDatabase.from_files(os.path.join(tmp, "params.npz"), os.path.join(tmp, "semantic.json"))
    found = {name: list(ans.position) for name in ("bottle", "cup", "trash") if (ans := db.query(f"{name}#1")).found}
    return "objects vs truth:\n" + "\n".join(truth_lines(found))


if __name__ == "__main__":
    raise SystemExit(main())
