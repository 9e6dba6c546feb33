#!/usr/bin/env python3
"""SLAM quality / speed table on any torch device, and streaming at camera rate.

Usage (from the repository root; ``bench/gpu.sh`` runs it on a CUDA machine)::

    python bench/slam_gpu.py --device cuda --backend gsplat                 # 300x170, 600x340, 1200x680
    python bench/slam_gpu.py --device cpu --backend torch --sizes 120x68 --frames 6 --skip-stream

For each image size: generates the synthetic home sequence (not timed), runs the engine frame by
frame (tracking every frame, densification, keyframe mapping), and prints one table row: frame 0
(the first keyframe's long mapping) as its own figure, FPS and median ms over frames 1..n, host
synchronisations per frame (``--count-syncs``), ATE RMSE, PSNR, mIoU, Gaussians and peak GPU memory.
Then (unless ``--skip-stream``) the streaming figures: the largest size fed at ``--rate`` Hz into the
ROS server's core (:class:`semantic_gs_slam_ros.session.StreamingSession`, the same code
``run_gs_slam_server`` runs, without DDS): frames processed vs skipped, backlog (lag), and the time
from the last frame to the map written (what triggers the object-query reload), and the reload itself
(``object_query``'s ``ObjectDatabase.from_files`` on that map, without the service's DDS round trip).

Timing: frames are decoded up front; each ``add_frame`` returns a host pose, so it ends with the
device's work done (``torch.cuda.synchronize`` is called anyway around frame 0).
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import statistics
import sys
import tempfile
import threading
import time
from dataclasses import dataclass

import numpy as np
import torch

from semantic_gs_slam.config import DEVICE_DEFAULTS, Intrinsics, MappingConfig, RendererConfig, SlamConfig
from semantic_gs_slam.devices import resolve_device
from semantic_gs_slam.errors import ConfigError
from semantic_gs_slam.eval.evaluate import evaluate
from semantic_gs_slam.io.datasets import load_dataset
from semantic_gs_slam.slam import SLAM
from semantic_gs_slam.synthetic.scenes import generate

TARGETS = "target at 1200x680 on one GPU: >= 30 FPS, ATE <= 0.5 cm, PSNR >= 34 dB, mIoU >= 0.92"


@dataclass
class Row:
    """One line of the table."""

    size: str
    frames: int
    frame0_s: float
    fps: float
    ms_median: float
    syncs_per_frame: float  # NaN when not counted
    ate_cm: float
    psnr: float
    miou: float
    gaussians: int
    peak_mem_mb: float  # NaN on the CPU


def parse_size(s: str) -> tuple[int, int]:
    """``"1200x680"`` -> (1200, 680)."""
    try:
        w, h = (int(v) for v in s.lower().split("x"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"size must be WIDTHxHEIGHT, got {s!r}") from exc
    return w, h


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def make_sequence(root: str, width: int, height: int, frames: int, supersample: int, workers: int) -> str:
    """Generate (once) the synthetic home at this size; returns the folder."""
    out = os.path.join(root, f"home_{width}x{height}_{frames}")
    if not os.path.isfile(os.path.join(out, "traj.txt")):
        t = time.perf_counter()
        generate(out, frames, width, height, supersample=supersample, workers=workers,
                 span_deg=120.0 * frames / 60.0)  # the benchmark's camera speed: 2 degrees per frame
        print(f"generated {frames} frames {width}x{height} in {time.perf_counter() - t:.1f} s (not timed)",
              file=sys.stderr, flush=True)
    return out


def run_size(data: str, device: str, backend: str, threads: int, count_syncs: bool,
             mapping: MappingConfig | None = None, sets: list[str] | None = None) -> Row:
    """Run the engine over one generated sequence and measure it."""
    ds = load_dataset(data)
    dev = resolve_device(device)
    cfg = SlamConfig(intrinsics=ds.intrinsics, device=device, renderer=RendererConfig(backend=backend),
                     mapping=mapping or MappingConfig(), threads=threads).with_overrides(sets or [])
    frames = [ds[i] for i in range(len(ds))]
    if dev.type == "cuda":
        torch.cuda.reset_peak_memory_stats(dev)
    eng = SLAM(cfg, ds.classes)
    guard = None
    if count_syncs:
        from semantic_gs_slam.device_guard import DeviceGuard

        guard = DeviceGuard()
        guard.__enter__()
    try:
        _sync(dev)
        t0 = time.perf_counter()
        f = frames[0]
        eng.add_frame(f.rgb, f.depth, f.semantics, f.timestamp, f.gt_c2w)
        _sync(dev)
        frame0 = time.perf_counter() - t0
        if guard:
            guard.end_frame()
        times = []
        t_all = time.perf_counter()
        for f in frames[1:]:
            t = time.perf_counter()
            eng.add_frame(f.rgb, f.depth, f.semantics, f.timestamp, f.gt_c2w)
            times.append(time.perf_counter() - t)
            if guard:
                guard.end_frame()
        _sync(dev)
        wall = time.perf_counter() - t_all
    finally:
        if guard:
            guard.__exit__(None, None, None)
    peak = torch.cuda.max_memory_allocated(dev) / 2**20 if dev.type == "cuda" else float("nan")
    res = evaluate(eng, ds, list(range(len(frames))), every=max(1, len(frames) // 10))
    k = ds.intrinsics
    syncs = statistics.mean(guard.syncs_per_frame[1:]) if guard and len(guard.syncs_per_frame) > 1 else float("nan")
    return Row(f"{k.width}x{k.height}", len(frames), frame0, (len(frames) - 1) / max(wall, 1e-9),
               1000 * statistics.median(times) if times else float("nan"), syncs, res.get("ate_rmse_cm", float("nan")),
               res["psnr"], res.get("miou", float("nan")), len(eng.map), peak)


def device_name(device: str) -> str:
    """Human-readable name of the device the engine runs on."""
    dev = resolve_device(device)
    if dev.type == "cuda":
        return f"{torch.cuda.get_device_name(dev)} (CUDA {torch.version.cuda})"
    return f"CPU, {torch.get_num_threads()} threads"


def format_table(rows: list[Row], title: str) -> str:
    """Markdown table of :class:`Row` s under a title line."""
    lines = [title, "",
             "| size | frames | frame 0 (s) | FPS (frames 1..n) | median ms/frame | host syncs/frame | ATE (cm) | "
             "PSNR (dB) | mIoU | Gaussians | peak GPU MiB |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r.size} | {r.frames} | {r.frame0_s:.2f} | {r.fps:.2f} | {r.ms_median:.1f} | "
                     f"{r.syncs_per_frame:.0f} | {r.ate_cm:.2f} | {r.psnr:.2f} | {r.miou:.3f} | {r.gaussians} | "
                     f"{r.peak_mem_mb:.0f} |")
    return "\n".join(lines).replace("| nan |", "| - |")


def streaming(data: str, device: str, backend: str, threads: int, rate: float) -> str:
    """Feed the sequence at ``rate`` Hz into the streaming session; returns the report lines."""
    try:
        from semantic_gs_slam_ros.engine import EngineAdapter
        from semantic_gs_slam_ros.lag import LagAction
        from semantic_gs_slam_ros.session import SessionConfig, StreamingSession
    except ImportError as exc:  # e.g. a GPU image without the ROS package's Python dependencies
        return f"streaming: skipped ({exc})"
    ds = load_dataset(data)
    k = ds.intrinsics
    frames = [ds[i] for i in range(len(ds))]
    rgb8 = [(np.clip(f.rgb, 0, 1) * 255 + 0.5).astype(np.uint8) for f in frames]
    work = tempfile.mkdtemp(prefix="slam_stream_")
    cfg = SlamConfig(intrinsics=k, device=device, renderer=RendererConfig(backend=backend), threads=threads)
    eng = EngineAdapter(SLAM(cfg, ds.classes))
    scfg = SessionConfig(work_dir=work, width=k.width, height=k.height, use_semantic=True, checkpoint_every=0)
    map_at: list[float] = []
    written: list[tuple[str, str]] = []

    def on_map(params: str, semantic: str) -> None:
        map_at.append(time.perf_counter())
        written.append((params, semantic))

    session = StreamingSession(scfg, eng, on_map=on_map)
    result: list = []
    runner = threading.Thread(target=lambda: result.append(session.run(poll=0.01)), daemon=True)
    runner.start()
    subscribed, skipped, max_backlog = True, 0, 0
    t0 = time.perf_counter()
    for i, f in enumerate(frames):
        due = t0 + i / rate
        time.sleep(max(0.0, due - time.perf_counter()))
        act = session.lag_action()
        if act is LagAction.UNSUBSCRIBE:
            subscribed = False
        elif act is LagAction.RESUBSCRIBE:
            subscribed = True
        if not subscribed:
            skipped += 1
            continue
        stamp = 1000.0 + i / rate
        session.on_image("rgb", stamp, rgb8[i])
        session.on_image("depth", stamp, f.depth)
        session.on_image("semantic", stamp, f.semantics)
        max_backlog = max(max_backlog, session.progress().backlog)
    t_last = time.perf_counter()
    session.data_transfer_done()
    runner.join(timeout=600)
    p = session.progress()
    res = result[0] if result else None
    to_map = (map_at[-1] - t_last) if map_at else float("nan")
    return (f"streaming {k.width}x{k.height} at {rate:g} Hz, {len(frames)} frames ({len(frames) / rate:.1f} s): "
            f"processed {p.processed}, skipped {skipped + p.refused + sum(p.dropped.values())} "
            f"(paused {skipped}, refused {p.refused}, unmatched {sum(p.dropped.values())}); "
            f"largest backlog {max_backlog} frames ({max_backlog / rate:.2f} s of lag); "
            f"last frame -> map written {to_map:.2f} s; "
            f"{'ok' if res is not None and res.success else 'FAILED: ' + (res.message if res else 'timeout')}.\n"
            + (object_query_reload(*written[-1]) if written else "object_query reload: no map was written"))


def object_query_reload(params: str, semantic: str) -> str:
    """Time what ``object_query_server``'s reload service runs on the written map (``ObjectDatabase.from_files``:
    read both files, split the instances); the service's DDS round trip is not included."""
    try:
        from object_query.semantic_map import DatabaseConfig, ObjectDatabase
    except ImportError as exc:
        return f"object_query reload: skipped ({exc})"
    t = time.perf_counter()
    db = ObjectDatabase.from_files(params, semantic, DatabaseConfig())
    took = time.perf_counter() - t
    return (f"object_query reload of that map (ObjectDatabase.from_files, what object_query_server's reload service "
            f"runs; its DDS round trip not included): {took:.2f} s, {len(db.names())} classes")


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="auto")
    ap.add_argument("--backend", default="auto", choices=["auto", "torch", "gsplat", "numba"])
    ap.add_argument("--sizes", type=parse_size, nargs="+", default=[(300, 170), (600, 340), (1200, 680)])
    ap.add_argument("--frames", type=int, default=60, help="frames per size (the first is frame 0)")
    ap.add_argument("--supersample", type=int, default=1, help="synthetic colour rays per pixel side (odd)")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="processes generating the data")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--data", default="", help="folder for the generated sequences (kept; default: temp)")
    ap.add_argument("--count-syncs", action="store_true", help="count host synchronisations per frame (slower)")
    ap.add_argument("--rate", type=float, default=30.0, help="streaming rate (Hz)")
    ap.add_argument("--skip-stream", action="store_true")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                    help="override a SlamConfig field in the table's runs, e.g. mapping.iters=6 (repeatable)")
    ap.add_argument("--baseline", action="store_true",
                    help="also run the largest size with the CPU's values of the device-dependent settings "
                         "(config.DEVICE_DEFAULTS) and print the FPS ratio")
    a = ap.parse_args(argv)
    try:
        SlamConfig(intrinsics=Intrinsics(2, 2, 1.0, 1.0, 0.5, 0.5)).with_overrides(a.set).check()
    except ConfigError as exc:
        ap.error(str(exc))
    torch.set_num_threads(a.threads)
    root = a.data or tempfile.mkdtemp(prefix="slam_gpu_")
    rows = []
    for w, h in a.sizes:
        data = make_sequence(root, w, h, a.frames, a.supersample, a.workers)
        rows.append(run_size(data, a.device, a.backend, a.threads, a.count_syncs, sets=a.set))
        print(format_table(rows[-1:], f"{rows[-1].size} done"), file=sys.stderr, flush=True)
    try:
        import gsplat

        gv = f"gsplat {gsplat.__version__}"
    except ImportError:
        gv = "no gsplat"
    title = (f"{device_name(a.device)}, torch {torch.__version__}, {gv}, backend {a.backend}, "
             f"{dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M} UTC; {TARGETS}"
             + (f"; settings {' '.join(a.set)}" if a.set else ""))
    print(format_table(rows, title))
    if a.baseline:
        cpu = [f"{sec}.{name}={val}" for sec, vals in DEVICE_DEFAULTS["cpu"].items() for name, val in vals.items()]
        base = run_size(make_sequence(root, *a.sizes[-1], a.frames, a.supersample, a.workers), a.device, a.backend,
                        a.threads, a.count_syncs, sets=cpu + a.set)
        base.size += " (CPU settings)"
        print(format_table([base], f"baseline, the same run with the CPU's values: {' '.join(cpu)}"))
        print(f"FPS at {rows[-1].size}: {rows[-1].fps:.2f} with this device's settings, {base.fps:.2f} with the "
              f"CPU's (ratio {rows[-1].fps / max(base.fps, 1e-9):.2f})")
    if not a.skip_stream:
        w, h = a.sizes[-1]
        print(streaming(make_sequence(root, w, h, a.frames, a.supersample, a.workers), a.device, a.backend,
                        a.threads, a.rate))
    return 0


if __name__ == "__main__":
    sys.exit(main())
