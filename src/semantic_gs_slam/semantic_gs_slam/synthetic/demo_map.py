"""Build the bundled demo map (``data/params.npz`` + ``data/semantic.json``) with our own SLAM.

The synthetic home (:mod:`semantic_gs_slam.synthetic.scenes`) is rendered along a full 360-degree orbit
around the dining table, so every object of the room (the bottle and cup on the counter, the bin
in the corner, the fridge, ...) is seen at least once; the engine maps it frame by frame exactly as
the streaming server does, then refines the map offline over all keyframes (the map is built
once, so spending a minute more on it is worth it). The evaluation table is printed at the end.

Usage (from the repository root, after ``make setup``)::

    source scripts/env.sh
    python -m semantic_gs_slam.synthetic.demo_map --out data          # about 7 minutes on 2 CPU cores

The result is deterministic for a given torch build (fixed seeds, 2 threads).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

import torch

from semantic_gs_slam.config import SlamConfig
from semantic_gs_slam.eval.evaluate import evaluate, format_table
from semantic_gs_slam.io.datasets import load_dataset
from semantic_gs_slam.slam import SLAM
from semantic_gs_slam.synthetic.scenes import generate


def build(out: str, frames: int = 180, width: int = 300, height: int = 170, refine_iters: int = 300,
          threads: int = 2, work: str | None = None, quiet: bool = False) -> dict:
    """Render the 360-degree sequence, run SLAM over it, refine, save the map into ``out``.

    Args:
        out: output folder (``params.npz`` and ``semantic.json`` are written; no ``.ply``).
        frames: frames along the orbit (2 degrees apart for 180).
        width, height: image size.
        refine_iters: offline refinement iterations over all keyframes after the run.
        threads: torch threads.
        work: where to write the rendered sequence (default: a temporary folder, removed after).
        quiet: no per-frame lines.

    Returns:
        The evaluation results of the final map (see :func:`semantic_gs_slam.eval.evaluate.evaluate`).
    """
    torch.set_num_threads(threads)
    with tempfile.TemporaryDirectory(prefix="demo_map_") as tmp:
        seq = work or os.path.join(tmp, "home360")
        t0 = time.perf_counter()
        generate(seq, frames, width, height, span_deg=360.0 * (frames - 1) / frames)
        print(f"rendered {frames} frames {width}x{height} in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        ds = load_dataset(seq)
        eng = SLAM(SlamConfig(intrinsics=ds.intrinsics, threads=threads), ds.classes)
        t0 = time.perf_counter()
        for i in range(len(ds)):
            f = ds[i]
            eng.add_frame(f.rgb, f.depth, f.semantics, f.timestamp, f.gt_c2w)
            if not quiet and (i % 10 == 0 or i == len(ds) - 1):
                print(f"frame {i + 1}/{len(ds)}: {len(eng.map)} Gaussians, {time.perf_counter() - t0:.0f} s",
                      file=sys.stderr, flush=True)
        if refine_iters > 0:
            eng.refine(refine_iters)
        res = evaluate(eng, ds, list(range(len(ds))), every=max(1, len(ds) // 30))
        eng.save(out, ply=False)
    return res


def main(argv: list[str] | None = None) -> int:
    """Command line entry."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="data", help="output folder (default: data)")
    ap.add_argument("--frames", type=int, default=180)
    ap.add_argument("--width", type=int, default=300)
    ap.add_argument("--height", type=int, default=170)
    ap.add_argument("--refine-iters", type=int, default=300)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work", help="keep the rendered sequence in this folder")
    ap.add_argument("--quiet", action="store_true")
    a = ap.parse_args(argv)
    res = build(a.out, a.frames, a.width, a.height, a.refine_iters, a.threads, a.work, a.quiet)
    print(format_table(res))
    print(f"map written to {a.out}/params.npz and {a.out}/semantic.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
