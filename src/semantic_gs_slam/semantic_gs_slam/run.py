"""Command line: run the SLAM engine over a dataset folder, save the map, optionally evaluate.

Usage::

    python -m semantic_gs_slam.run --dataset /tmp/home --out /tmp/home_map [--frames 60] [--eval]
    python -m semantic_gs_slam.run --dataset /tmp/home --out /tmp/home_map --checkpoint-every 10
    python -m semantic_gs_slam.run --dataset /tmp/home --out /tmp/home_map --resume   # after a crash
    python -m semantic_gs_slam.run --dataset /tmp/home --start 30 --out /tmp/home_map2 --start-map /tmp/home_map
        # continue a saved map in its frame (the first frames are relocalised in it)
    python -m semantic_gs_slam.run --dataset /tmp/home --out /tmp/home_map --device cuda --backend gsplat
    python -m semantic_gs_slam.run --dataset ../shared/data/7scenes-redkitchen-0-499 --out /tmp/kitchen \
        --size 320x240 --stride 2 --frames 120 --labels auto --eval   # a real camera (7-Scenes)
    python -m semantic_gs_slam.run --dataset rgbd_dataset_freiburg1_xyz --out /tmp/fr1 --size 320x240
        # TUM: the fr1 camera from the folder's name (or --camera tum-fr1, or --intrinsics fx,fy,cx,cy)

The camera's intrinsics and depth scale: ``--intrinsics`` / ``--depth-scale`` > ``--camera`` > the folder's
``cam.json`` > the preset the folder's name implies > the layout's own; one ``camera:`` line on stderr says which.

Prints a progress bar and one log line per frame (pose error when ground truth exists, Gaussians,
times) on stderr, and the evaluation table on stdout.

Bad frames lose nothing: a frame whose files cannot be read or whose images the engine refuses (a corrupt
JPEG, a depth image with almost no valid depth, ...) is skipped with a warning and listed at the end; after
:data:`MAX_BAD_IN_A_ROW` such frames in a row the run stops, saves the map of the frames mapped and exits
with 2. Ctrl-C finishes the frame in hand (or the refinement's iteration), saves the map so far (and a checkpoint
with ``--checkpoint-every``) and exits with 130; a second Ctrl-C quits at once.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import threading
import time

import numpy as np

from semantic_gs_slam.config import PROFILES, MappingConfig, RendererConfig, SlamConfig, TrackingConfig
from semantic_gs_slam.errors import MAX_BAD_IN_A_ROW, DatasetError, FrameError, SlamError
from semantic_gs_slam.geometry import pose_error
from semantic_gs_slam.io.datasets import CAMERAS, LAYOUTS, frame_indices, load_dataset, parse_intrinsics, parse_size
from semantic_gs_slam.labels import LABEL_MODES, LabelConfig, LabelStage, predict_pose
from semantic_gs_slam.slam import SLAM


class StopOnInterrupt:
    """While active (``with``), the first Ctrl-C (SIGINT) only sets :attr:`requested`, so the run can finish the
    frame in hand and save; a second one raises :class:`KeyboardInterrupt` at once. Outside the main thread
    (where Python cannot catch signals) it does nothing."""

    def __init__(self) -> None:
        self.requested = False
        self._old = None
        self._installed = False

    def __enter__(self) -> StopOnInterrupt:
        if threading.current_thread() is threading.main_thread():
            self._old = signal.signal(signal.SIGINT, self._on_sigint)
            self._installed = True
        return self

    def _on_sigint(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        # os.write, not print: a handler that prints while the interrupted code prints can fail (reentrant call)
        os.write(2, b"\ninterrupted: finishing this step, then saving the map so far (Ctrl-C again to quit at once)\n")

    def __exit__(self, *exc) -> bool:
        if self._installed:
            signal.signal(signal.SIGINT, self._old if self._old is not None else signal.default_int_handler)
            self._installed = False
        return False


def dataset_positions(stamps: list[float], ds_stamps: list[float], idx: list[int]) -> list[int]:
    """The position in ``idx`` of each of an engine's frames, matched by time stamp (frames may have been skipped,
    and a resumed engine's frames come from an earlier run over the same dataset).

    Raises:
        DatasetError: a frame of the engine that none of ``idx``'s frames has the time stamp of.
    """
    where = {round(float(ds_stamps[i]), 6): n for n, i in enumerate(idx)}
    out = []
    for t in stamps:
        n = where.get(round(float(t), 6))
        if n is None:
            raise DatasetError(f"the engine has a frame at t = {t:.6f} s that the selected dataset frames do not have "
                               "(resumed from another dataset, or with other --start/--stride?)")
        out.append(n)
    return out


def _skipped_summary(skipped: list[tuple[int, str]], total: int) -> str:
    shown = "; ".join(f"frame {i}: {why}" for i, why in skipped[:5])
    more = f"; and {len(skipped) - 5} more" if len(skipped) > 5 else ""
    return f"skipped {len(skipped)} of {total} frames that could not be used ({shown}{more})"


def _intrinsics_arg(text: str) -> tuple[float, float, float, float]:
    try:
        return parse_intrinsics(text)
    except DatasetError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from exc


def _depth_scale_arg(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not (np.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"depth scale must be a positive number of depth units per metre "
                                         f"(1000: millimetres, 5000: TUM), got {text!r}")
    return v


def add_camera_args(ap: argparse.ArgumentParser) -> None:
    """``--intrinsics``, ``--depth-scale``, ``--camera`` (the run and the benchmarks that read sequences take them;
    a malformed value is a usage error, exit code 2). Pass :func:`camera_kwargs` to ``load_dataset``."""
    ap.add_argument("--intrinsics", type=_intrinsics_arg, metavar="FX,FY,CX,CY",
                    help="the camera in pixels of the files' images; outranks every other source")
    ap.add_argument("--depth-scale", type=_depth_scale_arg, metavar="UNITS",
                    help="depth image units per metre (1000: mm, 5000: TUM); outranks every other source")
    ap.add_argument("--camera", default="auto", choices=list(CAMERAS),
                    help="a published camera (TUM RGB-D fr1/fr2/fr3), outranking cam.json; auto: the one the "
                         "folder's name implies (rgbd_dataset_freiburg1_xyz -> tum-fr1); none: no preset")


def camera_kwargs(args: argparse.Namespace) -> dict:
    """``load_dataset`` keyword arguments from :func:`add_camera_args`'s options."""
    return {"intrinsics": args.intrinsics, "depth_scale": args.depth_scale, "camera": args.camera}


def progress_line(done: int, total: int, width: int = 24) -> str:
    """``[#####.....]  12/60`` style bar."""
    fill = int(width * done / max(total, 1))
    return f"[{'#' * fill}{'.' * (width - fill)}] {done:4d}/{total}"


def build_config(args: argparse.Namespace, intrinsics) -> SlamConfig:
    """SlamConfig from the command line (and optional JSON overrides: a file or the JSON itself)."""
    cfg = SlamConfig(intrinsics=intrinsics, renderer=RendererConfig(backend=args.backend), device=args.device,
                     tracking=TrackingConfig(), mapping=MappingConfig(),
                     checkpoint_every=args.checkpoint_every,
                     checkpoint_dir=os.path.join(args.out, "checkpoint") if args.checkpoint_every else "",
                     threads=args.threads)
    if args.profile:
        cfg = cfg.with_profile(args.profile)
    if args.config:
        cfg = cfg.with_json(args.config)
    if args.keyframe_every:
        cfg.mapping.keyframe_every = args.keyframe_every
    if args.mapping_iters is not None:
        cfg.mapping.iters = args.mapping_iters
    if args.frontend:
        cfg.tracking.frontend = args.frontend
    if args.threaded:
        cfg.threaded = True
    return cfg


def label_frame(stage: LabelStage, eng: SLAM, f) -> np.ndarray | None:
    """The labels ``stage`` gives frame ``f`` (a :class:`~semantic_gs_slam.io.datasets.Frame`) at the engine's
    constant-velocity pose guess; their names go into ``eng.classes`` before the frame is added."""
    first = eng.initial_c2w if eng.initial_c2w is not None else f.gt_c2w
    guess = predict_pose(eng.poses, first)
    sem = stage(f.rgb, f.depth, f.semantics, guess, index=len(eng.poses), keyframe=eng.keyframe_expected(guess))
    if stage.mode != "dataset":
        eng.classes.update(stage.classes)
    return sem


def main(argv: list[str] | None = None) -> int:
    """Entry point (``semantic_gs_slam_run``); returns the exit code."""
    ap = argparse.ArgumentParser(description="Semantic Gaussian-splatting RGB-D SLAM over a dataset folder.")
    ap.add_argument("--dataset", required=True, help="folder in the replica / sgs / tum / 7scenes layout")
    ap.add_argument("--layout", default="auto", choices=["auto", *LAYOUTS])
    add_camera_args(ap)
    ap.add_argument("--colour-calib", default="auto",
                    help="colour registered to depth: auto (the folder's colour-calibration.json, else the layout's "
                         "default: 7-Scenes' Kinect), none (colour as recorded), or a calibration file")
    ap.add_argument("--out", required=True, help="output folder: params.npz, semantic.json, map.ply")
    ap.add_argument("--frames", type=int, default=0, help="use only the first N frames (0: all)")
    ap.add_argument("--stride", type=int, default=1, help="use every k-th frame")
    ap.add_argument("--start", "--first", type=int, default=0, help="first dataset frame")
    ap.add_argument("--size", default="", help="working size WIDTHxHEIGHT, e.g. 320x240 (default: the files')")
    ap.add_argument("--labels", default="auto", choices=list(LABEL_MODES),
                    help="per-pixel labels: the dataset's, from geometry, geometry + an ONNX COCO model, none; "
                         "auto = dataset when it has labels, else the installed COCO detector (python -m "
                         "semantic_gs_slam.models.fetch), else geometry")
    ap.add_argument("--onnx-model", default="", help="ONNX instance segmenter/detector with COCO classes "
                                                     "(--labels onnx/auto; default: the installed detector)")
    ap.add_argument("--labels-every", type=int, default=1,
                    help="geometry / onnx labels on every k-th frame only, and on frames expected to be keyframes "
                         "(faster, fewer Gaussians labelled)")
    ap.add_argument("--checkpoint-every", type=int, default=0, help="checkpoint into <out>/checkpoint every N frames")
    ap.add_argument("--resume", action="store_true", help="continue from <out>/checkpoint")
    ap.add_argument("--start-map", metavar="DIR", default="",
                    help="continue the saved map in DIR (params.npz, semantic.json) in its frame: frames are mapped "
                         "once one is relocalised in it (SLAM.from_map); the grown map is written to --out")
    ap.add_argument("--config", help="config overrides: a JSON file, or the JSON itself, e.g. "
                                     "'{\"mapping\": {\"iters\": 20}}'")
    ap.add_argument("--keyframe-every", type=int, default=0)
    ap.add_argument("--mapping-iters", type=int)
    ap.add_argument("--device", default="auto", help="torch device: auto (CUDA when present), cpu, cuda, cuda:N")
    ap.add_argument("--backend", default="auto", choices=["auto", "torch", "gsplat", "numba"],
                    help="renderer: torch tiles (any device, the reference), numba (compiled, CPU), gsplat (CUDA), "
                         "auto (gsplat on CUDA when it imports, numba on the CPU when it is installed)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--profile", default="", choices=["", *PROFILES],
                    help="named config overrides (config.PROFILES); realtime: every frame of a camera at its rate "
                         "on a CPU (frame-rate front end, mapping in a thread); --config and later flags outrank it")
    ap.add_argument("--frontend", choices=["render", "keyframe"], help="tracking.frontend (default: the config's)")
    ap.add_argument("--threaded", action="store_true", help="map in a worker thread (needs --frontend keyframe)")
    ap.add_argument("--refine-iters", type=int, default=0,
                    help="after the run, refine the map over all keyframes for N iterations (not counted in FPS)")
    ap.add_argument("--refine-seconds", type=float, default=0.0,
                    help="refine for at most S seconds after the run (with --refine-iters: whichever ends first; "
                         "alone: as many iterations as fit), the deferred frames first, coarse to fine "
                         "(mapping.refine_coarse_share)")
    ap.add_argument("--refine-poses", action=argparse.BooleanOptionalAction, default=None,
                    help="the refinement also optimises the poses of its views, keyframes and deferred frames (bundle "
                         "adjustment through the renderer; on real data it gives a sharper map and a better "
                         "trajectory); default: the profile's mapping.refine_poses (on with realtime)")
    ap.add_argument("--eval", action="store_true", help="print the evaluation table at the end")
    ap.add_argument("--quiet", action="store_true", help="no per-frame log lines")
    args = ap.parse_args(argv)
    if not (math.isfinite(args.refine_seconds) and args.refine_seconds >= 0):
        ap.error(f"--refine-seconds must be a finite number >= 0 (0: no time budget), got {args.refine_seconds}")
    if args.refine_poses and args.refine_iters <= 0 and args.refine_seconds <= 0:
        ap.error("--refine-poses needs --refine-iters N or --refine-seconds S (> 0): it says what the refinement "
                 "also optimises")
    if args.labels_every < 1:
        ap.error("--labels-every must be >= 1")
    if args.threads < 0 or args.refine_iters < 0:
        ap.error(f"--threads must be >= 0 (0: torch's own) and --refine-iters >= 0, got {args.threads} and "
                 f"{args.refine_iters}")
    try:  # the output folder, made now: a run is not mapped to be lost at the end on a folder it cannot write
        os.makedirs(args.out, exist_ok=True)
        probe = os.path.join(args.out, ".write_probe")
        with open(probe, "w") as fh:
            fh.write("ok")
        os.remove(probe)
    except OSError as exc:
        print(f"error: --out {args.out}: not a writable folder ({exc.strerror or exc})", file=sys.stderr)
        return 2
    if args.start_map and args.resume:
        ap.error("--start-map and --resume exclude each other: a checkpoint already holds the map it started on")
    try:
        ds = load_dataset(args.dataset, args.layout, size=parse_size(args.size) if args.size else None,
                          colour_calib=args.colour_calib, **camera_kwargs(args))
        print(ds.camera_line(), file=sys.stderr, flush=True)
        if ds.left_out:
            print(f"{args.dataset}: {ds.left_out}", file=sys.stderr, flush=True)
        idx = frame_indices(len(ds), args.start, args.stride, args.frames)
        cfg = build_config(args, ds.intrinsics)
        stage = LabelStage(LabelConfig(mode=args.labels, onnx_model=args.onnx_model, every=args.labels_every),
                           ds.intrinsics, ds.sem_paths is not None)
        ckpt = os.path.join(args.out, "checkpoint")
        if args.resume:
            eng = SLAM.resume(ckpt)
            print(f"resumed from {ckpt} at frame {len(eng.poses)}", file=sys.stderr)
        elif args.start_map:
            eng = SLAM.from_map(args.start_map, cfg, ds.classes)
            print(f"continuing the saved map {args.start_map} ({len(eng.map)} Gaussians, {len(eng.start_views)} "
                  "views): frames are mapped once one is relocalised in it", file=sys.stderr)
        else:
            eng = SLAM(cfg, ds.classes)
        stage.reserve_ids(eng.classes)  # after a resume: new instances must not reuse the map's ids
        t0 = time.perf_counter()
        before = len(eng.poses)
        start = dataset_positions(eng.timestamps, ds.timestamps, idx)[-1] + 1 if before else 0
        skipped: list[tuple[int, str]] = []
        stopped = ""  # why the frames stopped early ("" = all fed)
        bad_in_a_row = 0
        with StopOnInterrupt() as interrupt:
            for n, i in enumerate(idx[start:], start):
                if interrupt.requested:
                    stopped = f"stopped by Ctrl-C before frame {i}"
                    break
                try:
                    f = ds[i]
                    if stage.stateful:  # it keeps state across frames: check the frame first
                        eng.check_frame(f.rgb, f.depth, f.semantics)  # (0.6 ms at 320x240; add_frame checks too)
                    sem = label_frame(stage, eng, f)
                    pose = eng.add_frame(f.rgb, f.depth, sem, f.timestamp, f.gt_c2w)
                except (DatasetError, FrameError) as exc:  # this frame's files or images: skip it, lose nothing
                    skipped.append((i, str(exc)))
                    bad_in_a_row += 1
                    print(f"warning: frame {i} skipped: {exc}", file=sys.stderr, flush=True)
                    if bad_in_a_row >= MAX_BAD_IN_A_ROW:
                        stopped = f"{bad_in_a_row} frames in a row could not be used (the last, frame {i}: {exc})"
                        break
                    continue
                bad_in_a_row = 0
                lg = eng.logs[-1]
                err = ""
                if f.gt_c2w is not None:
                    et, er = pose_error(pose, f.gt_c2w)
                    err = f" err {et * 100:5.2f} cm {er:4.2f} deg"
                if not args.quiet:
                    print(f"{progress_line(n + 1, len(idx))} frame {i:5d}{' KF' if lg.keyframe else '   '} "
                          f"gaussians {lg.n_gaussians:7d} (+{lg.added} -{lg.pruned}) "
                          f"icp {lg.track_residual_m * 1000:5.2f} mm "
                          f"loss {lg.map_loss:6.4f} track {lg.track_s:5.2f} s map {lg.map_s:5.2f} s{err}"
                          f"{' TRACKING LOST' if lg.tracking_failed else ''}"
                          f"{' (not relocalised in the saved map yet)' if not eng.localised else ''}",
                          file=sys.stderr, flush=True)
            wall = time.perf_counter() - t0
            t_drain = time.perf_counter()
            eng.finish(timeout=600.0)  # SlamConfig.threaded: the mapping thread's queue (inline: nothing to wait for)
            if eng.cfg.threaded:
                st = eng.stats()
                resumed = f" (resumed on their own track: {st['resumed']})" if st["resumed"] else ""
                print(f"mapping thread drained in {time.perf_counter() - t_drain:.1f} s after the last frame; "
                      f"lost {st['lost_frames']}, recoveries {st['recoveries']}{resumed}, dropped {st['dropped']}",
                      file=sys.stderr)
            if interrupt.requested and not stopped:  # during the last frame
                stopped = "stopped by Ctrl-C"
            if skipped:
                print(_skipped_summary(skipped, len(idx) - start), file=sys.stderr)
            if not eng.poses:
                if interrupt.requested:
                    print(f"error: {stopped}; no frame was mapped, nothing to save", file=sys.stderr)
                    return 130
                first = skipped[0] if skipped else (idx[start] if start < len(idx) else -1, "no frames")
                raise DatasetError(f"no frame could be used, nothing to save (frame {first[0]}: {first[1]})")
            if (args.refine_iters > 0 or args.refine_seconds > 0) and not stopped:
                t1 = time.perf_counter()
                _, its = eng.refine(args.refine_iters if args.refine_iters > 0 else 10 ** 9, poses=args.refine_poses,
                                    should_stop=lambda: interrupt.requested, seconds=args.refine_seconds)
                poses = eng.cfg.mapping.refine_poses if args.refine_poses is None else args.refine_poses
                what = "the map and its views' poses" if poses else "the map"
                print(f"refined {what} over "
                      f"{len(eng.keyframes)} keyframes for {its} iterations in "
                      f"{time.perf_counter() - t1:.1f} s", file=sys.stderr)
                if interrupt.requested:
                    of = f" of {args.refine_iters}" if args.refine_iters > 0 else ""
                    stopped = f"refinement stopped by Ctrl-C after {its}{of} iterations"
            paths = eng.save(args.out)
            if stopped and eng.cfg.checkpoint_dir:  # so that --resume goes on from here
                eng.checkpoint(eng.cfg.checkpoint_dir)
        done = len(eng.poses) - before
        print(f"saved {', '.join(paths.values())}; {len(eng.map)} Gaussians; {done} frames in {wall:.1f} s "
              f"({done / max(wall, 1e-9):.2f} FPS)", file=sys.stderr)
        if stopped:
            then = ("continue with --resume" if interrupt.requested else
                    "fix or remove those files, then continue with --resume") if eng.cfg.checkpoint_dir else \
                "--checkpoint-every N would let --resume continue from there"
            print(f"error: {stopped}; the map of the {len(eng.poses)} frames mapped is saved, without --eval ({then})",
                  file=sys.stderr)
            return 130 if interrupt.requested else 2
        if args.eval:
            from semantic_gs_slam.eval.evaluate import evaluate, format_table

            used = dataset_positions(eng.timestamps, ds.timestamps, idx)
            res = evaluate(eng, ds, [idx[n] for n in used])
            res["fps"] = done / max(wall, 1e-9)
            print(format_table(res))
    except SlamError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
