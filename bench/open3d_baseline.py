#!/usr/bin/env python3
"""Open3D's frame-to-model tracker (``open3d.t.pipelines.slam.Model``, KinectFusion-style, depth only), the baseline
the real-data benchmarks compare against, run in a process of its own.

Open3D 0.20 sometimes ends with a segmentation fault inside its TSDF range estimation on 7-Scenes stretches (seen on
the kitchen's frames 250-499 at strides 2 and 3 with degraded frames); a crash there must not take the engine's
figures with it. So ``bench/slam_real.py`` (:func:`run_open3d`) writes the decoded frames to a file, runs this
script on it and reads the poses back; a crash is reported as one line and the benchmark goes on without the
Open3D column.

Usage (what :func:`run_open3d` runs)::

    python bench/open3d_baseline.py IN.npz OUT.npz --voxel 0.02 --depth-max 3.0 --device cpu

``IN.npz``: ``depth_mm`` [N, H, W] uint16 millimetres, ``rgb8`` [N, H, W, 3] uint8, ``k`` [3, 3] intrinsics,
``first`` [4, 4] the first frame's camera-to-world pose. ``OUT.npz``: ``poses`` [N, 4, 4] camera-to-world, ``fps``,
``lost`` (frames Open3D's odometry refused: the previous pose kept), ``version``, ``device``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np


def track(depth_mm: np.ndarray, rgb8: np.ndarray, k: np.ndarray, first: np.ndarray, voxel: float,
          depth_max: float, device: str) -> dict:
    """Open3D's tracker over the frames (in this process). Returns poses [N, 4, 4], fps, lost, version, device."""
    import open3d as o3d
    import open3d.core as o3c

    dev = o3c.Device("CUDA:0" if device == "cuda" and o3d.core.cuda.is_available() else "CPU:0")
    n_frames, h, w = depth_mm.shape
    intr = o3c.Tensor(np.asarray(k, np.float64))
    t_cur = o3c.Tensor(np.eye(4))
    model = o3d.t.pipelines.slam.Model(voxel, 16, 40000, t_cur, dev)
    inp = o3d.t.pipelines.slam.Frame(h, w, intr, dev)
    ray = o3d.t.pipelines.slam.Frame(h, w, intr, dev)
    poses, lost = [], 0
    t0 = time.perf_counter()
    for n in range(n_frames):
        inp.set_data_from_image("depth", o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth_mm[n]))).to(dev))
        inp.set_data_from_image("color", o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(rgb8[n]))).to(dev))
        if n > 0:
            try:
                r = model.track_frame_to_model(inp, ray, 1000.0, depth_max, 0.07)
                t_cur = t_cur @ r.transformation
            except RuntimeError as exc:  # Open3D reports a failed odometry this way
                lost += 1
                print(f"open3d frame {n}: tracking failed ({exc}); keeping the previous pose", file=sys.stderr)
        poses.append(first @ t_cur.cpu().numpy())
        model.update_frame_pose(n, t_cur)
        model.integrate(inp, 1000.0, depth_max, 8.0)
        model.synthesize_model_frame(ray, 1000.0, 0.1, depth_max, 8.0, False)
    wall = time.perf_counter() - t0
    return {"poses": np.stack(poses), "fps": n_frames / wall, "lost": lost, "version": o3d.__version__,
            "device": str(dev)}


def exit_reason(code: int) -> str:
    """A child's return code in words: 'a segmentation fault (signal 11)', 'exit code 1', ..."""
    if code >= 0:
        return f"exit code {code}"
    import signal

    try:
        name = signal.Signals(-code).name
    except ValueError:
        name = f"signal {-code}"
    what = {"SIGSEGV": "a segmentation fault", "SIGABRT": "an abort", "SIGKILL": "a kill (out of memory?)",
            "SIGBUS": "a bus error"}.get(name, name)
    return f"{what} (signal {-code})"


def run_in_child(depth_mm: np.ndarray, rgb8: np.ndarray, k: np.ndarray, first: np.ndarray, voxel: float,
                 depth_max: float, device: str) -> dict | None:
    """:func:`track` in a child process (this file run as a script, the same interpreter and environment). Returns
    its result, or None (one line on stderr says why) when the child did not finish: Open3D crashed, or is not
    installed."""
    with tempfile.TemporaryDirectory(prefix="open3d-baseline-") as tmp:
        src, out = os.path.join(tmp, "in.npz"), os.path.join(tmp, "out.npz")
        np.savez(src, depth_mm=depth_mm, rgb8=rgb8, k=np.asarray(k, np.float64), first=np.asarray(first, np.float64))
        cmd = [sys.executable, os.path.abspath(__file__), src, out, "--voxel", repr(voxel), "--depth-max",
               repr(depth_max), "--device", device]
        code = subprocess.run(cmd, check=False).returncode
        if code != 0 or not os.path.isfile(out):
            print(f"Open3D's tracker ended with {exit_reason(code)} after its frames were handed over: no Open3D "
                  f"column in this run (the engine's figures are unaffected; run it again, or --no-open3d)",
                  file=sys.stderr)
            return None
        with np.load(out) as z:
            return {"poses": list(z["poses"]), "fps": float(z["fps"]), "lost": int(z["lost"]),
                    "version": str(z["version"]), "device": str(z["device"])}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("input", help="IN.npz: depth_mm, rgb8, k, first")
    ap.add_argument("output", help="OUT.npz: poses, fps, lost, version, device")
    ap.add_argument("--voxel", type=float, default=0.02)
    ap.add_argument("--depth-max", type=float, default=3.0)
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    args = ap.parse_args()
    with np.load(args.input) as z:
        depth_mm, rgb8, k, first = z["depth_mm"], z["rgb8"], z["k"], z["first"]
    if depth_mm.ndim != 3 or rgb8.shape != depth_mm.shape + (3,) or depth_mm.dtype != np.uint16 \
            or rgb8.dtype != np.uint8 or k.shape != (3, 3) or first.shape != (4, 4):
        print(f"error: {args.input}: expected depth_mm [N, H, W] uint16, rgb8 [N, H, W, 3] uint8, k [3, 3], "
              f"first [4, 4]; got {depth_mm.shape} {depth_mm.dtype}, {rgb8.shape} {rgb8.dtype}, {k.shape}, "
              f"{first.shape}", file=sys.stderr)
        return 2
    res = track(depth_mm, rgb8, k, first, args.voxel, args.depth_max, args.device)
    np.savez(args.output, **res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
