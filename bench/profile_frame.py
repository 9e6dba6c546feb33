#!/usr/bin/env python3
"""Where a SLAM frame's milliseconds go, on any torch device.

Usage (from the repository root)::

    python bench/profile_frame.py --device cpu --size 300x170 --frames 24           # CPU, 2 threads
    python bench/profile_frame.py --device cuda --backend gsplat --size 1200x680     # on a GPU
    python bench/profile_frame.py --dataset <7-Scenes folder> --size 320x240 --stride 2 --frames 60

Runs the engine over the synthetic home (generated first, not timed) or a recorded sequence (``--dataset``,
decoded first, not timed) and prints:

1. a stage table: inclusive milliseconds per frame of each stage of ``SLAM.add_frame`` (frame upload,
   tracking = model render + ICP, label votes, densification, keyframe = loop check + densification +
   mapping optimisation + pruning), split into keyframes and other frames. On CUDA each stage is
   bracketed by ``torch.cuda.synchronize`` (``--no-sync`` turns that off), so a stage's time includes its
   queued GPU work; the brackets cost a little, so compare with the FPS line (no brackets).
2. ``torch.profiler`` over frames ``--profile-from``..+``--profile-frames``: the operators with the most
   self CPU time and (on CUDA) the most device time, and per frame the kernel launches and the host
   synchronisations (``cudaStreamSynchronize``, ``cudaMemcpy*`` device->host, ``cudaDeviceSynchronize``).

Frame 0 (the first keyframe's long mapping and, on CUDA, warm-up) is left out of every figure.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable

import torch

from semantic_gs_slam.config import RendererConfig, SlamConfig
from semantic_gs_slam.devices import resolve_device
from semantic_gs_slam.errors import ConfigError
from semantic_gs_slam.io.datasets import load_dataset
from semantic_gs_slam.run import add_camera_args, camera_kwargs
from semantic_gs_slam.synthetic.scenes import generate


class StageTimer:
    """Inclusive wall time per named stage and frame; nested stages each get their own figure."""

    def __init__(self, device: torch.device, sync: bool) -> None:
        self.device = device
        self.sync = sync and device.type == "cuda"
        self.frame: dict[str, float] = collections.defaultdict(float)
        self.frames: list[tuple[bool, dict[str, float]]] = []

    def _barrier(self) -> None:
        if self.sync:
            torch.cuda.synchronize(self.device)

    def wrap(self, name: str, fn: Callable) -> Callable:
        """``fn`` timed under ``name`` (and labelled for the profiler)."""

        def timed(*args, **kwargs):
            self._barrier()
            t = time.perf_counter()
            try:
                with torch.profiler.record_function(name):
                    return fn(*args, **kwargs)
            finally:
                self._barrier()
                self.frame[name] += time.perf_counter() - t

        return timed

    def end_frame(self, keyframe: bool) -> None:
        self.frames.append((keyframe, dict(self.frame)))
        self.frame.clear()

    def table(self) -> str:
        """Mean ms per frame of each stage for keyframes, other frames and all frames (frame 0 left out)."""
        rows = self.frames[1:]
        names: list[str] = []
        for _, d in rows:
            names += [n for n in d if n not in names]
        groups = {"keyframes": [d for kf, d in rows if kf], "other frames": [d for kf, d in rows if not kf],
                  "all": [d for _, d in rows]}
        head = "| stage | " + " | ".join(f"{g} ({len(v)}) ms" for g, v in groups.items()) + " |"
        lines = [head, "|---|" + "---|" * len(groups)]
        for n in names:
            cells = [f"{1000 * sum(d.get(n, 0.0) for d in v) / max(len(v), 1):.1f}" for v in groups.values()]
            lines.append(f"| {n} | " + " | ".join(cells) + " |")
        return "\n".join(lines)


def instrument(eng, timer: StageTimer) -> Callable[[], None]:
    """Wrap the engine's stages (instance attributes and the functions the engine's modules call) with ``timer``.

    Returns:
        a function that puts the engine modules' functions back (the instance's wrappers go with the instance).
    """
    import importlib

    # each function is wrapped in the module that calls it (slam.py orchestrates; the steps live in mapping/, loop/)
    callers = {"icp": "semantic_gs_slam.slam", "fit_exposure": "semantic_gs_slam.mapping.steps",
               "mapping_loss": "semantic_gs_slam.mapping.steps", "find_loops": "semantic_gs_slam.loop.closing"}
    saved = {(mod, fn): getattr(mod, fn) for fn, mod in ((fn, importlib.import_module(m)) for fn, m in callers.items())
             if hasattr(mod, fn)}

    for attr, name in [("add_frame", "frame (total)"), ("_tensors", "upload"), ("_track", "track"),
                       ("_densify", "densify"), ("_map_keyframe", "keyframe"), ("_close_loop", "keyframe.loop"),
                       ("optimise", "keyframe.optimise"), ("_window", "keyframe.window")]:
        setattr(eng, attr, timer.wrap(name, getattr(eng, attr)))
    eng.map.vote = timer.wrap("vote", eng.map.vote)
    eng.map.prune = timer.wrap("keyframe.prune", eng.map.prune)
    eng.map.add_from_frame = timer.wrap("densify.add", eng.map.add_from_frame)
    eng.render_view = timer.wrap("render_view (track, densify)", eng.render_view)
    eng._render = timer.wrap("render (every render)", eng._render)
    for (mod, fn), orig in saved.items():
        setattr(mod, fn, timer.wrap(fn, orig))

    def restore() -> None:
        for (mod, fn), orig in saved.items():
            setattr(mod, fn, orig)

    return restore


def profiler_report(prof, frames: int, device: torch.device, top: int) -> str:
    """Top operators and per-frame launch / sync counts from a finished ``torch.profiler.profile``."""
    ka = prof.key_averages()
    out = [f"torch.profiler over {frames} frames"]
    out.append(ka.table(sort_by="self_cpu_time_total", row_limit=top, max_name_column_width=60))
    if device.type == "cuda":
        out.append(ka.table(sort_by="self_cuda_time_total" if hasattr(ka[0], "self_cuda_time_total")
                            else "self_device_time_total", row_limit=top, max_name_column_width=60))
        counts = collections.Counter()
        for e in ka:
            if e.key in ("cudaLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernel", "cuLaunchKernelEx"):
                counts["kernel launches"] += e.count
            elif e.key in ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize"):
                counts["synchronisations"] += e.count
            elif e.key.startswith("cudaMemcpy"):
                counts["memcpy calls"] += e.count
        out.append("per frame: " + ", ".join(f"{k} {v / frames:.0f}" for k, v in sorted(counts.items())))
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="auto")
    ap.add_argument("--backend", default="auto", choices=["auto", "torch", "gsplat", "numba"])
    ap.add_argument("--size", default="300x170", help="WIDTHxHEIGHT of the generated sequence")
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="processes generating the data")
    ap.add_argument("--supersample", type=int, default=1,
                    help="synthetic colour rays per pixel side (odd; 1 like bench/slam_gpu.py: 3 takes ~10x longer)")
    ap.add_argument("--data", default="", help="folder for the generated sequence (kept; default: temp)")
    ap.add_argument("--dataset", default="", help="profile a recorded sequence instead (any layout load_dataset "
                    "reads, e.g. 7-Scenes), resized to --size; frames --start, --start + --stride, ...")
    ap.add_argument("--start", type=int, default=0)
    add_camera_args(ap)
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--no-sync", action="store_true", help="no device synchronisation around stages")
    ap.add_argument("--profile-from", type=int, default=8, help="first frame under torch.profiler")
    ap.add_argument("--profile-frames", type=int, default=8, help="frames under torch.profiler (0: none)")
    ap.add_argument("--top", type=int, default=25, help="operators listed per table")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="override a SlamConfig field, e.g. tracking.icp_iters=8 (repeatable)")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    w, h = (int(v) for v in a.size.lower().split("x"))
    if a.dataset:
        ds = load_dataset(a.dataset, size=(w, h), **camera_kwargs(a))
        print(ds.camera_line(), file=sys.stderr)
        idx = list(range(a.start, len(ds), a.stride))[:a.frames]
    else:
        root = a.data or tempfile.mkdtemp(prefix="slam_profile_")
        data = os.path.join(root, f"home_{w}x{h}_{a.frames}")
        if not os.path.isfile(os.path.join(data, "traj.txt")):
            t = time.perf_counter()
            generate(data, a.frames, w, h, supersample=a.supersample, workers=a.workers,
                     span_deg=120.0 * a.frames / 60.0)
            print(f"generated {a.frames} frames {w}x{h} in {time.perf_counter() - t:.1f} s (not timed)",
                  file=sys.stderr, flush=True)
        ds = load_dataset(data)
        idx = list(range(len(ds)))
    dev = resolve_device(a.device)
    cfg = SlamConfig(intrinsics=ds.intrinsics, device=a.device, renderer=RendererConfig(backend=a.backend),
                     threads=a.threads)
    try:
        cfg = cfg.with_overrides(a.set)
    except ConfigError as exc:
        ap.error(str(exc))
    frames = [ds[i] for i in idx]

    from semantic_gs_slam.slam import SLAM

    if len(frames) < 2:
        ap.error(f"need at least 2 frames (frame 0 is left out of every figure), got {len(frames)}")
    # the profiler window, clipped to the frames there are
    prof_range = range(max(a.profile_from, 1), min(a.profile_from + a.profile_frames, len(frames)))
    eng = SLAM(cfg, ds.classes)
    timer = StageTimer(dev, not a.no_sync)
    restore = instrument(eng, timer)
    prof = None
    walls = []
    try:
        for i, f in enumerate(frames):
            if len(prof_range) and i == prof_range.start:
                acts = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA]
                                                                if dev.type == "cuda" else [])
                prof = torch.profiler.profile(activities=acts)
                prof.__enter__()
            t = time.perf_counter()
            eng.add_frame(f.rgb, f.depth, f.semantics, f.timestamp, f.gt_c2w)
            if dev.type == "cuda":
                torch.cuda.synchronize(dev)
            walls.append(time.perf_counter() - t)
            timer.end_frame(eng.logs[-1].keyframe)
            if prof is not None and i == prof_range[-1]:
                prof.__exit__(None, None, None)
                print(profiler_report(prof, len(prof_range), dev, a.top), flush=True)
                prof = None
    finally:
        if prof is not None:
            prof.__exit__(None, None, None)
        restore()
    name = f"CPU, {torch.get_num_threads()} threads"
    if dev.type == "cuda":
        with contextlib.suppress(Exception):
            name = torch.cuda.get_device_name(dev)
    print(f"\n{name}, backend {eng.backend.__name__ if hasattr(eng.backend, '__name__') else eng.backend}, "
          f"{w}x{h}, {len(frames)} frames, {len(eng.map)} Gaussians at the end, stages "
          f"{'synchronised' if timer.sync else 'not synchronised'}")
    rest = walls[1:]
    prof_set = set(prof_range)
    clean = [t for i, t in enumerate(walls) if i > 0 and i not in prof_set]
    print(f"frame 0: {walls[0] * 1000:.0f} ms; frames 1..n: median {1000 * statistics.median(rest):.1f} ms, "
          f"mean {1000 * statistics.mean(rest):.1f} ms ({1 / statistics.mean(rest):.2f} FPS)"
          + (f"; outside the profiler window {1 / statistics.mean(clean):.2f} FPS" if clean else ""))
    print(timer.table())
    return 0


if __name__ == "__main__":
    sys.exit(main())
