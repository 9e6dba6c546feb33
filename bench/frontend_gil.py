#!/usr/bin/env python3
"""The engine's per-frame tracking path, alone and beside a thread that holds the GIL.

Usage (from the repository root; the data stays outside the repository)::

    source scripts/env.sh && python bench/frontend_gil.py ../shared/data/7scenes-redkitchen-0-499 --size 640x480

With the ``realtime`` profile the keyframe front end tracks every frame in the caller's thread while a mapping
thread works beside it. Each time the tracking thread lets the GIL go (a NumPy operation on a large array, a
compiled kernel), it waits to get it back for as long as the other thread keeps it: up to the interpreter's
switch interval (5 ms) when that thread runs Python (a mapping thread launching GPU kernels, a ROS executor's
callbacks). This measures that cost on the CPU, without a GPU: the stages of ``SLAM.add_frame``'s tracking path
(``_host_frame``: the frame's checks and conversion; ``_fe_frame``: the front end's shrink; ``_track_keyframe``:
the live points and the ICP against the reference, and a new reference when coverage drops), per frame, on
``--frames`` frames after the first,

* alone;
* beside a thread running small PyTorch operations (they release the GIL, as a CPU mapping thread's do);
* beside a thread running pure Python (it keeps the GIL until the switch interval forces it off).

Printed: milliseconds per frame per stage and in all, and each condition's ratio to the frame alone.
"""

from __future__ import annotations

import argparse
import os
import sys
import threading
import time

import numpy as np

from semantic_gs_slam.config import SlamConfig
from semantic_gs_slam.io.datasets import load_dataset, parse_size
from semantic_gs_slam.slam import SLAM

STAGES = ("host frame", "shrink", "track")


def _python_loop(stop: threading.Event) -> None:
    x = 0
    while not stop.is_set():
        for _ in range(1000):
            x += 1


def _torch_loop(stop: threading.Event) -> None:
    import torch

    a = torch.ones(16)
    while not stop.is_set():
        a = (a * 1.0001 + 0.1).clamp(0, 10)


def run(frames: list, k, threads: int) -> np.ndarray:
    """[frames - 1, 3] seconds per stage of the tracking path for frames 1.. (frame 0 is the first reference)."""
    cfg = SlamConfig(intrinsics=k, threads=threads).with_profile("realtime")
    eng = SLAM(cfg)
    f = frames[0]
    eng.add_frame(f.rgb, f.depth, None, 0.0)
    eng.finish(600.0)
    out = []
    lost_frames = 0
    for n, f in enumerate(frames[1:], 1):
        t0 = time.perf_counter()
        host = eng._host_frame(f.rgb, f.depth, None)
        t1 = time.perf_counter()
        depth, rgb = eng._fe_frame(host[1], host[0])
        t2 = time.perf_counter()
        c2w, _, _, lost, _, coverage = eng._track_keyframe(n, rgb, depth)
        eng.poses.append(c2w)  # the next frame's constant-velocity guess
        if not lost and coverage < cfg.tracking.frontend_new_keyframe_coverage:
            eng._fe_add_keyframe(n, depth, rgb)  # a new reference, as add_frame takes one
        t3 = time.perf_counter()
        out.append((t1 - t0, t2 - t1, t3 - t2))
        lost_frames += int(lost)
    if lost_frames:
        print(f"({lost_frames} frames lost: their relocalisation is in the figures)", file=sys.stderr)
    return np.array(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset", help="an RGB-D sequence folder (any layout the loaders read)")
    ap.add_argument("--size", default="640x480", help="camera size WIDTHxHEIGHT (default 640x480)")
    ap.add_argument("--frames", type=int, default=60, help="frames tracked after the first (every one in order)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    ds = load_dataset(args.dataset, size=parse_size(args.size))
    frames = [ds[i] for i in range(min(args.frames + 1, len(ds)))]
    run(frames[:6], ds.intrinsics, args.threads)  # compiled kernels loaded (numba's cache) before timing
    print(f"sequence {args.dataset}: frames 1..{len(frames) - 1}, {args.size}, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.1f}, switch interval {sys.getswitchinterval() * 1000:g} ms")
    print("| beside the tracking thread | " + " | ".join(f"{s} (ms)" for s in STAGES) + " | all (ms) | ratio |")
    print("|---|" + "---|" * (len(STAGES) + 2))
    base = None
    for name, loop in (("nothing", None), ("small PyTorch operations", _torch_loop),
                       ("pure Python", _python_loop)):
        stop = threading.Event()
        th = None if loop is None else threading.Thread(target=loop, args=(stop,), daemon=True)
        if th is not None:
            th.start()
        try:
            t = run(frames, ds.intrinsics, args.threads) * 1000
        finally:
            stop.set()
            if th is not None:
                th.join(5.0)
        per = t.mean(0)
        total = float(t.sum(1).mean())
        base = base or total
        print(f"| {name} | " + " | ".join(f"{v:.1f}" for v in per) + f" | {total:.1f} | {total / base:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
