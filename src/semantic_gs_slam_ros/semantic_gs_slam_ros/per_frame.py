"""The seed's per-frame subprocess mode, kept for comparison only (``bench/slam_streaming.py``).

The seed's server launched ``python slam.py`` once per frame: the new process imports the engine,
loads the latest checkpoint, reads the frame from disk, integrates it, and saves the checkpoint
again. This module is that child process::

    python -m semantic_gs_slam_ros.per_frame --work DIR --index I --config slam.yaml \\
        --intrinsics fx fy cx cy w h

It prints one JSON line: ``{"index", "add_frame_s", "total_s"}``. Our server never does this: it
keeps the engine in memory (:mod:`semantic_gs_slam_ros.session`).
"""

from __future__ import annotations

import argparse
import json
import os
import time

T_START = time.perf_counter()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", required=True)
    ap.add_argument("--index", type=int, required=True)
    ap.add_argument("--config", default="")
    ap.add_argument("--intrinsics", type=float, nargs=6, required=True, metavar=("FX", "FY", "CX", "CY", "W", "H"))
    ap.add_argument("--depth-scale", type=float, default=1000.0)
    a = ap.parse_args(argv)
    import numpy as np
    from PIL import Image

    from semantic_gs_slam.slam import SLAM
    from semantic_gs_slam_ros.engine import load_slam_config

    fx, fy, cx, cy, w, h = a.intrinsics
    config, _ = load_slam_config(a.config, (fx, fy, cx, cy, int(w), int(h)))
    ckpt = os.path.join(a.work, "checkpoint_per_frame")
    slam = SLAM.resume(ckpt, config) if a.index > 0 else SLAM(config)
    rgb = np.array(Image.open(os.path.join(a.work, "frames", f"frame{a.index:06d}.jpg")))
    depth = np.array(Image.open(os.path.join(a.work, "depths", f"depth{a.index:06d}.png"))).astype(np.float32)
    t0 = time.perf_counter()
    slam.add_frame(rgb, depth / a.depth_scale, None, float(a.index))
    t1 = time.perf_counter()
    slam.checkpoint(ckpt)
    print(json.dumps({"index": a.index, "add_frame_s": t1 - t0, "total_s": time.perf_counter() - T_START}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
