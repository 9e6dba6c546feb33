#!/usr/bin/env python3
"""The frame-rate tracking front end alone on a real RGB-D sequence, beside Open3D's tracker in the same run.

Usage (from the repository root; the data stays outside the repository)::

    source scripts/env.sh && PYTHONPATH=$PYTHONPATH:$PWD/.bench-open3d python bench/tracking_frontend.py \\
        ../shared/data/7scenes-redkitchen-0-499 --ranges 0:250,250:500 --strides 1,2,6

For every frame range and stride, the front end (:mod:`semantic_gs_slam.tracking.frontend`) tracks every selected
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

from semantic_gs_slam.eval.metrics import ate_rmse, rpe_rmse
from semantic_gs_slam.io.datasets import frame_indices, load_dataset, parse_size
from semantic_gs_slam.run import add_camera_args, camera_kwargs
from semantic_gs_slam.tracking.frontend import FrameTracker, FrontendConfig, build_reference

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from slam_real import run_open3d  # noqa: E402  (bench/ is not a package)


class _Decoded:
    """The dataset's frames ``idx`` decoded once, for both trackers (``run_open3d`` indexes it like a dataset)."""

    def __init__(self, ds, idx: list[int]):
        self.intrinsics = ds.intrinsics
        self.frames = {i: ds[i] for i in idx}

    def __getitem__(self, i: int):
        return self.frames[i]


class _TsdfReference:
    """A fused map as the reference: every trusted frame integrated at its tracked pose into Open3D's TSDF
    (``t.pipelines.slam.Model``, as ``run_open3d`` builds it), the reference depth raycast from it at the keyframe.
    Measures the tracker against a fused model (what a rendered map gives), not Open3D's tracker."""

    def __init__(self, k, voxel: float, depth_max: float):
        import open3d as o3d
        import open3d.core as o3c

        self.o3d, self.o3c, self.depth_max = o3d, o3c, depth_max
        intr = o3c.Tensor(np.array(k.as_matrix(), np.float64))
        dev = o3c.Device("CPU:0")
        self.model = o3d.t.pipelines.slam.Model(voxel, 16, 40000, o3c.Tensor(np.eye(4)), dev)
        self.inp = o3d.t.pipelines.slam.Frame(k.height, k.width, intr, dev)
        self.ray = o3d.t.pipelines.slam.Frame(k.height, k.width, intr, dev)
        self.n = 0

    def integrate(self, f, c2w: np.ndarray) -> None:
        o3d, o3c = self.o3d, self.o3c
        depth_mm = np.ascontiguousarray((f.depth * 1000.0).round().astype(np.uint16))
        self.inp.set_data_from_image("depth", o3d.t.geometry.Image(o3c.Tensor(depth_mm)))
        self.inp.set_data_from_image("color", o3d.t.geometry.Image(o3c.Tensor(
            np.ascontiguousarray((f.rgb * 255 + 0.5).astype(np.uint8)))))
        self.model.update_frame_pose(self.n, o3c.Tensor(np.ascontiguousarray(c2w)))
        self.model.integrate(self.inp, 1000.0, self.depth_max, 8.0)
        self.n += 1

    def depth(self) -> np.ndarray:
        """[H, W] metres raycast at the last integrated pose (0: no surface)."""
        self.model.synthesize_model_frame(self.ray, 1000.0, 0.1, self.depth_max, 8.0, False)
        d = self.ray.get_data_as_image("depth").as_tensor().numpy()[..., 0].astype(np.float64) / 1000.0
        return np.where(np.isfinite(d) & (d > 0.1) & (d < self.depth_max - 1e-3), d, 0.0)


def run_front_end(frames: list, k, cfg: FrontendConfig, every: int, min_cov: float, use_rgb: bool,
                  tsdf: _TsdfReference | None = None) -> dict:
    """Track ``frames`` (decoded :class:`~semantic_gs_slam.datasets.Frame` s) with keyframe references from the
    sensor depth (or raycast from ``tsdf``, which then integrates every trusted frame); returns poses, timings and
    counts."""
    first = frames[0].gt_c2w if frames[0].gt_c2w is not None else np.eye(4)
    tr = FrameTracker(k, cfg)
    f0 = frames[0]
    rgb0 = f0.rgb if use_rgb else None
    tr.set_reference(build_reference(f0.depth, first, k, cfg, rgb=rgb0, keyframe_id=0))
    tr.track_frame(f0.depth, rgb0, guess_c2w=first)  # compiles / warms the kernels (not timed)
    tr = FrameTracker(k, cfg)
    poses, lost, reloc, kfs, steps = [first], 0, 0, 1, 0
    t0, c0 = time.perf_counter(), time.process_time()
    if tsdf is not None:
        tsdf.integrate(f0, first)
    tr.set_reference(build_reference(f0.depth if tsdf is None else tsdf.depth(), first, k, cfg, rgb=rgb0,
                                     keyframe_id=0))
    since_kf, was_lost = 0, False
    track_s = 0.0
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
        if tsdf is not None:
            tsdf.integrate(f, res.c2w)
        if since_kf >= every or res.quality.coverage < min_cov:
            tr.set_reference(build_reference(f.depth if tsdf is None else tsdf.depth(), res.c2w, k, cfg, rgb=rgb,
                                             keyframe_id=n))
            kfs += 1
            since_kf = 0
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    m = len(frames) - 1
    return {"poses": poses, "fps": m / wall, "cpu_ms": 1000 * cpu / m, "track_ms": 1000 * track_s / m, "lost": lost,
            "relocalised": reloc, "keyframes": kfs,
            "steps": steps / m}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset", help="sequence folder (7-Scenes, TUM RGB-D, Replica, ...)")
    ap.add_argument("--ranges", default="0:250", help="comma-separated START:STOP frame ranges")
    ap.add_argument("--strides", default="1,2,6", help="comma-separated strides")
    ap.add_argument("--size", default="320x240", help="working size WIDTHxHEIGHT")
    add_camera_args(ap)
    ap.add_argument("--keyframe-every", type=int, default=10, help="new reference every K tracked frames")
    ap.add_argument("--keyframe-coverage", type=float, default=0.5,
                    help="... or sooner, once the reference covers fewer of the frame's points than this")
    ap.add_argument("--config", help="JSON of FrontendConfig overrides, e.g. {\"sigma_geo\": 0.02}")
    ap.add_argument("--no-rgb", action="store_true", help="depth only (no photometric term)")
    ap.add_argument("--reference", default="sensor", choices=["sensor", "tsdf"],
                    help="reference depth: the keyframe's sensor depth, or raycast from a TSDF that integrates every "
                         "tracked frame at our pose (Open3D's voxel grid as a stand-in for the rendered map)")
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
    ds = load_dataset(args.dataset, size=parse_size(args.size), **camera_kwargs(args))
    print(ds.camera_line(), file=sys.stderr)
    if ds.poses is None:
        print("the sequence has no reference poses: ATE cannot be computed", file=sys.stderr)
        return 2
    k = ds.intrinsics
    load = os.getloadavg()[0]
    print(f"sequence {args.dataset}, {k.width}x{k.height}, reference {args.reference}, "
          f"keyframe every {args.keyframe_every} (or coverage < "
          f"{args.keyframe_coverage}), config {cfg}, load {load:.1f} on {os.cpu_count()} cores")
    print("\n| frames | stride | n | ours ATE (cm) | Open3D ATE (cm) | ATE ratio | ours RPE (cm) | ours FPS "
          "| ours FPS, tracking only | Open3D FPS | ours CPU ms/frame | ours lost / relocalised | Open3D failures "
          "| keyframes | steps/frame | load |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for rng in args.ranges.split(","):
        start, stop = (int(x) for x in rng.split(":"))
        for stride in (int(s) for s in args.strides.split(",")):
            idx = frame_indices(len(ds), start, stride, 0, stop)
            dec = _Decoded(ds, idx)
            frames = [dec[i] for i in idx]
            gts = [ds.poses[i] for i in idx]
            tsdf = _TsdfReference(k, args.o3d_voxel, args.o3d_depth_max) if args.reference == "tsdf" else None
            ours = run_front_end(frames, k, cfg, args.keyframe_every, args.keyframe_coverage, not args.no_rgb, tsdf)
            ate = 100 * ate_rmse(ours["poses"], gts)
            o3 = None if args.no_open3d else run_open3d(dec, idx, dec.frames, args.o3d_voxel, args.o3d_depth_max, "cpu")
            o3_ate = 100 * ate_rmse(o3["poses"], gts) if o3 else float("nan")
            print(f"| {start}-{stop - 1} | {stride} | {len(idx)} | {ate:.2f} | {o3_ate:.2f} | {ate / o3_ate:.2f} | "
                  f"{100 * rpe_rmse(ours['poses'], gts, 1):.2f} | {ours['fps']:.1f} | {1000 / ours['track_ms']:.1f} | "
                  f"{o3['fps'] if o3 else float('nan'):.1f} | {ours['cpu_ms']:.1f} | {ours['lost']} / "
                  f"{ours['relocalised']} | {o3['lost'] if o3 else '-'} | {ours['keyframes']} | {ours['steps']:.1f} | "
                  f"{os.getloadavg()[0]:.1f} |", flush=True)
    print("\nFPS: wall clock over frames 1..n (tracking and rebuilding the reference; frames decoded up front, as for "
          "Open3D; with --reference tsdf, integrating every frame into the TSDF is included). CPU ms/frame: this "
          "process's CPU time per frame (less sensitive to the load than FPS).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
