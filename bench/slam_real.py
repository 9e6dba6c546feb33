#!/usr/bin/env python3
"""SLAM benchmark on a real RGB-D sequence (7-Scenes, TUM RGB-D, ... any layout the loaders read).

Usage (from the repository root; the data stays outside the repository, mind its licence)::

    source scripts/env.sh && python bench/slam_real.py ../shared/data/7scenes-redkitchen-0-499 \\
        --frames 500 --stride 1 --eval-every 10    # the real-camera targets: every frame, realtime, 30-s refinement
    python bench/slam_real.py <seq> --profile default --refine-seconds 0   # the engine's base settings, no refinement
    python bench/slam_real.py <seq> --frames 250 --stride 2          # all 500 frames, every 2nd
    python bench/slam_real.py <seq> --labels geometry                # with the geometry labelling stage
    python bench/slam_real.py <seq> --device cuda                    # on the GPU machine
    python bench/slam_real.py rgbd_dataset_freiburg1_xyz --first 0 --frames 300 --stride 1   # TUM fr1 camera
    python bench/slam_real.py <seq> --intrinsics 525,525,319.5,239.5 --depth-scale 5000     # any camera
    python bench/slam_real.py <seq> --depth-noise 2 --blur 1    # a noisier, blurrier camera (both trackers)
    python bench/slam_real.py <seq> --gain 0.3                  # exposure swinging by 30 % (both trackers)
    python bench/slam_real.py <seq> --holes 0.3                 # 30 % of the depth pixels dropped (both trackers)
    python bench/slam_real.py <seq> --frames 500 --stride 1 --gap 250:90   # 3 s of a 30-Hz camera missing
    python bench/slam_real.py <seq> --frames 500 --stride 1 --jump 150:240  # carried 240 frames on in no time
    python bench/slam_real.py <seq> --frames 250 --stride 1 --drop 0.5     # half the frames dropped unevenly
    python bench/slam_real.py <seq> --colour-lag 1              # colour 33 ms after its depth (both trackers)

Runs our engine over the frames and prints the camera used (``--intrinsics``, ``--depth-scale``, ``--camera`` as for
``python -m semantic_gs_slam.run``), ATE RMSE (aligned), RPE, PSNR (all pixels, and SplaTAM's depth-masked
protocol), depth L1, FPS, tracking
failures, frames lost and recovered (when the engine's ``stats()`` reports them; "n/a" otherwise), the per-frame
pose error every ``--curve-every`` frames, and, when ``open3d`` is importable
(``requirements/bench-real.in``), Open3D's KinectFusion-style frame-to-model tracker
(``open3d.t.pipelines.slam.Model``, depth only, ``--o3d-voxel`` voxels) on the same frames in the same
run, with the ratios. Frames that cannot be read or that the engine refuses (e.g. a covered lens: under 5 % of the
depth in range) are left out for both trackers and listed. Timings depend on what else runs on the machine.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time

import numpy as np

from semantic_gs_slam.config import PROFILES, Intrinsics, SlamConfig
from semantic_gs_slam.errors import ConfigError, DatasetError, FrameError
from semantic_gs_slam.eval.evaluate import evaluate
from semantic_gs_slam.eval.metrics import ate_rmse, rpe_rmse
from semantic_gs_slam.geometry import pose_error, umeyama_rigid
from semantic_gs_slam.io.datasets import frame_indices, load_dataset, parse_size
from semantic_gs_slam.io.degrade import DegradedDataset, drop_frames
from semantic_gs_slam.labels import LABEL_MODES, LabelConfig, LabelStage
from semantic_gs_slam.run import add_camera_args, camera_kwargs, label_frame
from semantic_gs_slam.slam import SLAM

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # bench/ is not a package: open3d_baseline beside it
from open3d_baseline import run_in_child  # noqa: E402

REALTIME_REFINE_S = 30.0  # --refine-seconds' default with the realtime profile (the targets' "within 30 s")


def aligned_errors(est: list[np.ndarray], gt: list[np.ndarray]) -> np.ndarray:
    """Per-frame position error (m) after the best rigid alignment of the whole trajectory."""
    e = np.stack([p[:3, 3] for p in est])
    g = np.stack([p[:3, 3] for p in gt])
    if len(e) < 3:
        return np.linalg.norm(e - g, axis=1)
    t = umeyama_rigid(e, g)
    return np.linalg.norm(e @ t[:3, :3].T + t[:3, 3] - g, axis=1)


def lost_summary(stats: dict, idx: list[int]) -> tuple[str, str]:
    """From ``SLAM.stats()``: ("lost / recovered" counts, one line of which frames), or ("n/a", "") when the engine
    does not report ``lost_frames`` (engine frame numbers) and ``recoveries`` ([lost_at, recovered_at] pairs)."""
    lost, rec = stats.get("lost_frames"), stats.get("recoveries")
    if lost is None or rec is None:
        return "n/a", ""

    def at(n: int) -> str:  # an engine frame number -> the dataset frame it was
        return str(idx[n]) if 0 <= n < len(idx) else f"#{n}"

    spans = ", ".join(f"{at(a)}->{at(b)}" for a, b in rec[:20]) + (f", and {len(rec) - 20} more" if len(rec) > 20
                                                                   else "")
    detail = (f"lost at dataset frames {', '.join(at(n) for n in lost[:20])}{' ...' if len(lost) > 20 else ''}"
              f"{'; recovered (lost at -> recovered at): ' + spans if rec else '; none recovered'}") if lost else ""
    rejoined = stats.get("rejoined_frames", 0)
    resumed = stats.get("resumed", [])
    reanchored = stats.get("reanchored", [])
    notes = ([f"{rejoined} lost frames re-posed in the map"] if rejoined else []) + \
        ([f"{len(resumed)} resumed mapping on their own track (not relocalised then): "
          f"{', '.join(f'{at(a)}->{at(b)}' for a, b in resumed[:20])}"] if resumed else []) + \
        ([f"{len(reanchored)} resumed track(s) later relocalised and moved into the map's frame: "
          + ", ".join(f"from {at(int(a))} at {at(int(b))} by {cm:.0f} cm, {deg:.1f} deg"
                      for a, b, cm, deg in reanchored[:20])] if reanchored else [])
    return f"{len(lost)} / {len(rec)}" + (f" ({'; '.join(notes)})" if notes else ""), detail


def engine_config(ds, args: argparse.Namespace) -> SlamConfig:
    """The engine's settings: the camera, ``--profile`` and ``--config``'s overrides."""
    cfg = SlamConfig(intrinsics=ds.intrinsics, threads=args.threads, device=args.device)
    cfg = cfg.with_profile(args.profile)
    return cfg.with_json(args.config) if args.config else cfg


def load_frames(ds, idx: list[int], cfg: SlamConfig) -> tuple[dict, list[tuple[int, str]]]:
    """Frames ``idx`` decoded (up front, for both trackers: the timing is theirs, not the JPEG decoder's), less those
    that cannot be read (DatasetError) or that the engine refuses (FrameError: e.g. a covered lens, under 5 % of
    the depth in range). Returns {index: frame} and [(index, why)] of the frames left out."""
    checker = SLAM(cfg)
    frames, refused = {}, []
    for i in idx:
        try:
            f = ds[i]
            checker.check_frame(f.rgb, f.depth)
        except (DatasetError, FrameError) as exc:
            refused.append((i, str(exc)))
            continue
        frames[i] = f
    return frames, refused


def steady_clock(frames: dict, idx: list[int], after: list[int]) -> dict:
    """``frames`` ({index: Frame}, fed in the order ``idx``) with the time jump before each frame of ``after`` taken
    out: that frame comes one median step after the frame before it, and every later frame by as much earlier."""
    import dataclasses

    t = np.array([frames[i].timestamp for i in idx], np.float64)
    steps = np.diff(t)
    jump_at = {n for n, i in enumerate(idx) if i in after and n > 0}
    usual = np.median([d for n, d in enumerate(steps, start=1) if n not in jump_at]) if len(steps) > len(jump_at) \
        else 1.0 / 30
    shift, out = 0.0, {}
    for n, i in enumerate(idx):
        if n in jump_at:
            shift += steps[n - 1] - usual
        out[i] = dataclasses.replace(frames[i], timestamp=float(t[n] - shift))
    return out


def run_ours(ds, idx: list[int], args: argparse.Namespace, frames: dict, decode_ms: float) -> dict:
    """Our engine over ``idx`` (``frames``: :func:`load_frames`'s, ``decode_ms`` a frame); returns poses, timings,
    failures and the evaluation."""
    eng = SLAM(engine_config(ds, args))
    stage = LabelStage(LabelConfig(mode=args.labels, every=args.labels_every), ds.intrinsics, ds.sem_paths is not None)
    label_s = 0.0
    frames = [frames[i] for i in idx]  # decoded up front, as for Open3D: a mapping thread gets no free time meanwhile
    proc = []  # per frame: labelling + SLAM seconds
    lag = []  # --rate: per frame, how late (s) it was handed to the engine after the camera would have sent it
    t_run = time.perf_counter()
    for n, (i, f) in enumerate(zip(idx, frames, strict=True)):
        if args.rate > 0:  # a camera's pace: frame n is sent at n / rate; a busy engine takes it late
            due = t_run + n / args.rate
            wait = due - time.perf_counter()
            if wait > 0:
                time.sleep(wait)
            lag.append(time.perf_counter() - due)
        t2 = time.perf_counter()
        sem = label_frame(stage, eng, f)
        label_s += time.perf_counter() - t2
        pose = eng.add_frame(f.rgb, f.depth, sem, f.timestamp, f.gt_c2w)
        proc.append(time.perf_counter() - t2)
        lg = eng.logs[-1]
        if not args.quiet:
            err = ""
            if f.gt_c2w is not None:
                et, er = pose_error(pose, f.gt_c2w)
                err = f" err {et * 100:6.2f} cm {er:5.2f} deg"
            print(f"ours {n + 1:4d}/{len(idx)} frame {i:5d}{' KF' if lg.keyframe else '   '} gaussians "
                  f"{lg.n_gaussians:7d} track {lg.track_s:5.2f} s map {lg.map_s:5.2f} s{err}"
                  f" agree {lg.track_agreement:4.0%}{' TRACKING LOST' if lg.tracking_failed else ''}"
                  f"{'  ' + lg.loop if lg.loop else ''}",
                  file=sys.stderr, flush=True)
    t1 = time.perf_counter()
    eng.finish(600.0)  # a mapping thread (SlamConfig.threaded) maps what is queued: counted in the FPS
    drain_s = time.perf_counter() - t1
    paced = {"run_s": t1 - t_run, "lag_max_s": max(lag), "lag_end_s": lag[-1]} if lag else None
    wall = sum(proc) + drain_s
    res = evaluate(eng, ds, idx, every=args.eval_every)
    online_poses = [p.copy() for p in eng.poses]  # the per-frame error curve is the online run's
    if args.refine_iters > 0 or args.refine_seconds > 0:  # map refinement after the run (not counted in FPS)
        t1 = time.perf_counter()
        # a time budget: the deferred frames get at most half, the first mapping.refine_coarse_share renders at
        # half resolution (SLAM.refine)
        _, res["refine_done"] = eng.refine(args.refine_iters if args.refine_iters > 0 else 10 ** 9,
                                           poses=args.refine_poses, seconds=max(args.refine_seconds, 0.0))
        res["refine_s"] = time.perf_counter() - t1
        res["refine_poses"] = eng.cfg.mapping.refine_poses if args.refine_poses is None else args.refine_poses
        res["refined"] = evaluate(eng, ds, idx, every=args.eval_every)
    # FPS over frames 1..n as bench/slam_synthetic.py and bench/slam_gpu.py count it (frame 0's initial mapping,
    # mapping.first_frame_iters iterations, printed apart), and over all frames
    res.update(fps=(len(idx) - 1) / max(sum(proc[1:]) + drain_s, 1e-9) if len(idx) > 1 else float("nan"),
               track_fps=(len(idx) - 1) / max(sum(proc[1:]), 1e-9) if len(idx) > 1 else float("nan"),
               drain_s=drain_s, dropped=len(eng.dropped_jobs), paced=paced,
               fps_all=len(idx) / wall, frame0_s=proc[0], decode_ms=decode_ms,
               wall_s=wall, label_ms=1000 * label_s / len(idx),
               lost=sum(lg.tracking_failed for lg in eng.logs), loops=list(eng.loops),
               poses=online_poses, keyframes=len(eng.keyframes),
               classes=len(eng.classes), labelled=float((eng.semantic_ids() > 0).mean()) if len(eng.map) else 0.0,
               stats=eng.stats())
    return res


def run_open3d(ds, idx: list[int], frames: dict, voxel: float, depth_max: float, device: str) -> dict | None:
    """Open3D's frame-to-model tracker (``t.pipelines.slam.Model``) on the same frames, in a child process
    (``bench/open3d_baseline.py``: a crash inside Open3D ends only that process and is reported). None without
    open3d, or when it crashed."""
    if importlib.util.find_spec("open3d") is None:
        print("open3d not importable: skipping the Open3D baseline (pip install -r requirements/bench-real.in)",
              file=sys.stderr)
        return None
    frames = [frames[i] for i in idx]  # decoded up front (load_frames): the timing is the tracker's, not the decoder's
    first = frames[0].gt_c2w if frames[0].gt_c2w is not None else np.eye(4)
    depth_mm = np.stack([(f.depth * 1000.0).round().astype(np.uint16) for f in frames])
    rgb8 = np.stack([(f.rgb * 255 + 0.5).astype(np.uint8) for f in frames])
    return run_in_child(depth_mm, rgb8, np.array(ds.intrinsics.as_matrix(), np.float64), first, voxel, depth_max,
                        device)


def main() -> int:
    """The benchmark; a dataset, option or file it cannot use is one ``error:`` line and exit code 2 (the engine's
    own failures keep their traceback)."""
    try:
        return _run()
    except (DatasetError, ConfigError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def _run() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset", help="sequence folder (7-Scenes seq, TUM RGB-D, Replica, ...)")
    ap.add_argument("--frames", type=int, default=60, help="frames used (0: all)")
    ap.add_argument("--stride", type=int, default=2)
    ap.add_argument("--start", "--first", type=int, default=0, help="first dataset frame")
    ap.add_argument("--size", default="320x240", help="working size WIDTHxHEIGHT")
    add_camera_args(ap)
    ap.add_argument("--labels", default="none", choices=list(LABEL_MODES), help="labelling stage (default none)")
    ap.add_argument("--labels-every", type=int, default=1, help="geometry / onnx labels on every k-th frame only")
    ap.add_argument("--config", help="SlamConfig overrides: a JSON file, or the JSON itself, e.g. "
                    "'{\"tracking\": {\"icp_iters\": 20}}'")
    ap.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--eval-every", type=int, default=1, help="render-evaluate every k-th frame")
    ap.add_argument("--curve-every", type=int, default=20, help="per-frame error rows every k-th frame")
    ap.add_argument("--o3d-voxel", type=float, default=0.02, help="Open3D TSDF voxel (m)")
    ap.add_argument("--o3d-depth-max", type=float, default=3.0)
    ap.add_argument("--no-open3d", action="store_true")
    ap.add_argument("--open3d-only", action="store_true", help="only the Open3D baseline (minutes, not hours)")
    ap.add_argument("--refine-iters", type=int, default=0,
                    help="after the run, refine the map over all keyframes for N iterations (not counted in FPS)")
    ap.add_argument("--rate", type=float, default=0.0,
                    help="hand the frames to the engine at a camera's pace (Hz; 0: as fast as it takes them) and "
                         "report how late they were taken")
    ap.add_argument("--refine-seconds", type=float, default=None,
                    help="refine for at most this many seconds after the run (with --refine-iters: whichever ends "
                         f"first); default {REALTIME_REFINE_S:g} with the realtime profile and no --refine-iters, "
                         "else 0")
    ap.add_argument("--profile", default="realtime", choices=list(PROFILES),
                    help="a named SlamConfig profile (config.PROFILES) under --config's overrides: realtime (the "
                         "default: every frame of a real camera at its rate) or default (the engine's base settings)")
    ap.add_argument("--refine-poses", action=argparse.BooleanOptionalAction, default=None,
                    help="the refinement also optimises the poses of its views, keyframes and deferred frames (bundle "
                         "adjustment through the renderer); default: the profile's mapping.refine_poses (on with "
                         "realtime)")
    ap.add_argument("--depth-noise", type=float, default=0.0,
                    help="add this many times a Kinect v1's depth noise (0.0012 + 0.0019 (z - 0.4)^2 m) to every "
                         "frame's depth, ours and Open3D's alike (a noisier camera; 0: as recorded)")
    ap.add_argument("--colour-lag", type=int, default=0, metavar="N",
                    help="give each frame the colour of the recorded frame N later (a colour shutter that does not "
                         "fire with the depth's: a moving camera's colour off its depth)")
    ap.add_argument("--blur", type=int, default=0,
                    help="average each frame's colour with the N recorded frames on either side (motion blur)")
    ap.add_argument("--gain", type=float, default=0.0,
                    help="swing each frame's exposure: colour times 1 + G sin(2 pi i / 60) for recorded frame i (an "
                         "auto-exposure changing its mind every 2 s at 30 Hz; 0: as recorded)")
    ap.add_argument("--holes", type=float, default=0.0,
                    help="drop this fraction of each frame's depth pixels at random (a speckled time-of-flight or "
                         "stereo camera; both trackers; 0: as recorded)")
    ap.add_argument("--gap", action="append", default=[], metavar="FIRST:COUNT",
                    help="leave out COUNT recorded frames from dataset frame FIRST on (a stream that stalled; both "
                         "trackers; may be repeated)")
    ap.add_argument("--jump", action="append", default=[], metavar="FIRST:COUNT",
                    help="as --gap, but the frames after it are stamped as if no time had passed (a steady clock: "
                         "the camera carried elsewhere in no time, a kidnapping the frame times do not tell)")
    ap.add_argument("--drop", type=float, default=0.0, metavar="P",
                    help="leave out each selected frame but the first with probability P, at random (seeded: "
                         "repeatable): a stream that drops frames unevenly (both trackers; 0: none)")
    ap.add_argument("--quiet", action="store_true", help="no per-frame lines")
    ap.add_argument("--colour-calib", default="auto",
                    help="auto (the dataset's own or the layout's default), none (colour as recorded), or a file")
    args = ap.parse_args()
    if args.config:  # a typo is named before any frame is read
        try:
            SlamConfig(intrinsics=Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)).with_json(args.config)
        except ConfigError as exc:
            ap.error(f"--config: {exc}")
    if args.refine_seconds is None:  # the real-camera targets: the map judged 30 s after the last frame
        args.refine_seconds = REALTIME_REFINE_S if args.profile == "realtime" and args.refine_iters <= 0 else 0.0
    if args.refine_poses and args.refine_iters <= 0 and args.refine_seconds <= 0:
        ap.error("--refine-poses needs --refine-iters N or --refine-seconds S (> 0)")
    if args.labels_every < 1:
        ap.error("--labels-every must be >= 1")
    ds = load_dataset(args.dataset, size=parse_size(args.size) if args.size else None,
                      colour_calib=args.colour_calib, **camera_kwargs(args))
    if args.depth_noise or args.blur or args.gain or args.holes or args.colour_lag:
        if not args.depth_noise >= 0 or args.blur < 0 or not 0 <= args.gain < 1 or not 0 <= args.holes < 1:
            ap.error("--depth-noise and --blur must be >= 0, --gain and --holes in [0, 1)")
        ds = DegradedDataset(ds, args.depth_noise, args.blur, args.gain, holes=args.holes, colour_lag=args.colour_lag)
        print(f"frames degraded: {ds.describe()}")
    idx = frame_indices(len(ds), args.start, args.stride, args.frames)
    jumps = []  # --jump's (FIRST, COUNT)
    for gap in [("--gap", g) for g in args.gap] + [("--jump", g) for g in args.jump]:
        opt, gap = gap
        try:
            first, count = (int(v) for v in gap.split(":"))
        except ValueError:
            ap.error(f"{opt} {gap!r}: expected FIRST:COUNT, two integers")
        if first < 0 or count < 1:
            ap.error(f"{opt} {gap!r}: need FIRST >= 0 and COUNT >= 1")
        left = [i for i in idx if not first <= i < first + count]
        if len(left) < 2:
            ap.error(f"{opt} {gap!r} leaves fewer than 2 frames")
        print(f"{opt[2:]}: dataset frames {first}..{first + count - 1} left out ({len(idx) - len(left)} of the "
              f"selected){'; the frames after it keep a steady clock' if opt == '--jump' else ''}")
        if opt == "--jump":
            jumps.append((first, count))
        idx = left
    if args.drop:
        if not 0 <= args.drop < 1:
            ap.error(f"--drop {args.drop}: need 0 <= P < 1")
        kept = drop_frames(idx, args.drop)
        print(f"dropped at random: {len(idx) - len(kept)} of the {len(idx)} selected frames")
        idx = kept
    if ds.poses is None:
        print("the sequence has no reference poses: ATE cannot be computed", file=sys.stderr)
        return 2
    t1 = time.perf_counter()
    frames, refused = load_frames(ds, idx, engine_config(ds, args))
    decode_s = time.perf_counter() - t1
    if refused:  # left out for both trackers, so that they see the same frames
        print(f"{len(refused)} frames left out (for both trackers): "
              + "; ".join(f"{i}: {why}" for i, why in refused[:5]) + (" ..." if len(refused) > 5 else ""))
        idx = [i for i in idx if i in frames]
        if len(idx) < 2:
            print("fewer than 2 usable frames: nothing to compare", file=sys.stderr)
            return 2
    if jumps:  # marked on the frames fed (after --drop and the frames left out): the first one past each jump
        after = []
        for first, count in jumps:
            n = next((n for n in range(1, len(idx)) if idx[n - 1] < first and idx[n] >= first + count), None)
            if n is None:
                print(f"--jump {first}:{count}: no frame fed on both sides of it; the clock is left as recorded",
                      file=sys.stderr)
            else:
                after.append(idx[n])
        frames = steady_clock(frames, idx, after)
    gts = [ds.poses[i] for i in idx]
    k = ds.intrinsics
    print(f"sequence {args.dataset}: frames {idx[0]}..{idx[-1]} every {args.stride} ({len(idx)} frames), "
          f"{k.width}x{k.height}, device {args.device}, labels {args.labels}")
    refine = (f"{args.refine_iters} iterations" if args.refine_iters > 0 else "") + \
        (" or " if args.refine_iters > 0 and args.refine_seconds > 0 else "") + \
        (f"{args.refine_seconds:g} s" if args.refine_seconds > 0 else "")
    print(f"profile {args.profile}; map refinement after the last frame: {refine or 'none'}")
    print(ds.camera_line())
    if ds.left_out:
        print(ds.left_out)
    o3 = None if args.no_open3d else run_open3d(ds, idx, frames, args.o3d_voxel, args.o3d_depth_max, args.device)
    if args.open3d_only:
        if o3 is None:
            return 2
        e = aligned_errors(o3["poses"], gts)
        print(f"Open3D {o3['version']} t.pipelines.slam.Model ({o3['device']}, {args.o3d_voxel * 100:.0f} cm voxels): "
              f"ATE {100 * ate_rmse(o3['poses'], gts):.2f} cm, {o3['fps']:.1f} FPS, {o3['lost']} failures")
        print("| frame | Open3D aligned (cm) |\n|---|---|")
        for n in range(0, len(idx), max(1, args.curve_every)):
            print(f"| {idx[n]} | {e[n] * 100:.2f} |")
        return 0
    ours = run_ours(ds, idx, args, frames, 1000 * decode_s / (len(frames) + len(refused)))
    ate_o = ours["ate_rmse_cm"]
    rows = [("ATE RMSE (cm, aligned)", f"{ate_o:.2f}"), ("PSNR (dB)", f"{ours['psnr']:.2f}"),
            ("SSIM", f"{ours['ssim']:.3f}"), ("depth L1 (cm)", f"{ours['depth_l1_cm']:.2f}"),
            ("FPS", f"{ours['fps']:.2f}"),
            ("FPS of add_frame alone (mapping thread still busy: drained in the FPS above)",
             f"{ours['track_fps']:.2f} (drain {ours['drain_s']:.1f} s, {ours['dropped']} map updates dropped)"),
            *([(f"paced at {args.rate:g} Hz (camera time {(len(idx) - 1) / args.rate:.1f} s)",
                f"run {ours['paced']['run_s']:.1f} s, frames taken up to {ours['paced']['lag_max_s']:.2f} s late "
                f"({ours['paced']['lag_end_s']:.2f} s at the last), map complete {ours['drain_s']:.1f} s after it")]
              if ours["paced"] else []),
            ("FPS, all frames (frame 0's initial mapping included)", f"{ours['fps_all']:.2f} (frame 0: "
             f"{ours['frame0_s']:.1f} s)"),
            ("tracking failures reported", str(ours["lost"])),
            ("frames lost / recovered (the engine's stats)", lost_summary(ours["stats"], idx)[0]),
            *([("depth roughness of the last reference (1/m); keyframes smoothed as noisy",
                f"{ours['stats']['reference_roughness']:.4f}; {ours['stats']['noisy_references']}")]
              if "noisy_references" in ours["stats"] else []),
            ("drift found and corrected (loop closures)", f"{len(ours['loops'])}" + (
                f", largest {max(x['found_cm'] for x in ours['loops']):.1f} cm / "
                f"{max(x['found_deg'] for x in ours['loops']):.2f} deg" if ours["loops"] else "")),
            ("Gaussians", str(ours["gaussians"])), ("labelling ms/frame", f"{ours['label_ms']:.0f}"),
            ("label classes in the map", str(ours["classes"])),
            ("Gaussians with a label", f"{100 * ours['labelled']:.1f} %")]
    masked = f"{ours['psnr_masked']:.2f}"
    if "refined" in ours:
        r = ours["refined"]
        if ours["refine_poses"]:
            rows[0] = ("ATE RMSE (cm, aligned)", f"{ate_o:.2f} (refined: {r['ate_rmse_cm']:.2f})")
        rows[1:4] = [("PSNR (dB)", f"{ours['psnr']:.2f} (refined: {r['psnr']:.2f})"),
                     ("SSIM", f"{ours['ssim']:.3f} (refined: {r['ssim']:.3f})"),
                     ("depth L1 (cm)", f"{ours['depth_l1_cm']:.2f} (refined: {r['depth_l1_cm']:.2f})")]
        masked += f" (refined: {r['psnr_masked']:.2f})"
        views = f" and {ours['stats'].get('caught_up', 0)} deferred frames" if ours["stats"].get("caught_up") else ""
        print(f"refined: {ours['refine_done']} Adam iterations over all {ours['keyframes']} keyframes{views} after the "
              "run"
              f"{', their poses too' if ours['refine_poses'] else ''}, {ours['refine_s']:.0f} s (not counted in FPS; "
              "the per-frame error curve is the online run's)")
    rows.insert(2, ("PSNR (dB), SplaTAM's protocol (pixels without depth zeroed)", masked))
    rows.insert(3, ("PSNR (dB), pixels with depth / without", f"{ours['psnr_with_depth']:.2f} / "
                    f"{ours['psnr_without_depth']:.2f}"))
    rows.insert(1, ("RPE RMSE (cm, one frame step: how smooth)", f"{ours['rpe_cm']:.2f}"))
    print("\n| metric | ours |" + (" Open3D |" if o3 else "") + "\n|---|---|" + ("---|" if o3 else ""))
    o3_ate = 100 * ate_rmse(o3["poses"], gts) if o3 else float("nan")
    for name, val in rows:
        extra = ""
        if o3 and name.startswith("ATE"):
            extra = f" {o3_ate:.2f} |"
        elif o3 and name.startswith("RPE"):
            extra = f" {100 * rpe_rmse(o3['poses'], gts, 1):.2f} |"
        elif o3 and name == "FPS":
            extra = f" {o3['fps']:.2f} |"
        elif o3 and name.startswith("tracking failures"):
            extra = f" {o3['lost']} |"
        elif o3:
            extra = " - |"
        print(f"| {name} | {val} |{extra}")
    print(f"\nFPS: frames 1..n, labelling and SLAM until the map is complete (a mapping thread drained); decoding the "
          f"files, {ours['decode_ms']:.0f} ms a frame, up front and not counted, as for Open3D")
    if o3:
        print(f"Open3D {o3['version']} t.pipelines.slam.Model ({o3['device']}, {args.o3d_voxel * 100:.0f} cm voxels, "
              f"depth only): ATE ratio ours/Open3D {ate_o / o3_ate:.2f}, RPE ratio ours/Open3D "
              f"{ours['rpe_cm'] / (100 * rpe_rmse(o3['poses'], gts, 1)):.2f}, speed ratio ours/Open3D "
              f"{ours['fps'] / o3['fps']:.3f}")
    detail = lost_summary(ours["stats"], idx)[1]
    if detail:
        print(detail)
    e_ours = aligned_errors(ours["poses"], gts)
    e_o3 = aligned_errors(o3["poses"], gts) if o3 else None
    print("\nper-frame pose error (cm; 'anchored' = first frame on the reference, 'aligned' = whole trajectory "
          "aligned)")
    print("| frame | ours anchored | ours rot (deg) | ours aligned |" + (" Open3D aligned |" if o3 else ""))
    print("|---|---|---|---|" + ("---|" if o3 else ""))
    for n in list(range(0, len(idx), max(1, args.curve_every))) + ([len(idx) - 1] if (len(idx) - 1) %
                                                                   max(1, args.curve_every) else []):
        et, er = pose_error(ours["poses"][n], gts[n])
        print(f"| {idx[n]} | {et * 100:.2f} | {er:.2f} | {e_ours[n] * 100:.2f} |"
              + (f" {e_o3[n] * 100:.2f} |" if o3 else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
