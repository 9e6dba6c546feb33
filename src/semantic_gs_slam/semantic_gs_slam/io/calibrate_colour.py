"""``python -m semantic_gs_slam.io.calibrate_colour DATASET``: estimate where a recording's colour camera sits
relative to its depth camera and write the calibration file the dataset loaders read.

The command line of :mod:`semantic_gs_slam.io.colour_registration` (kept apart from it: the loaders in
:mod:`semantic_gs_slam.io.datasets` use the registration, and this command uses the loaders).
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from semantic_gs_slam.errors import DatasetError
from semantic_gs_slam.io.colour_registration import CALIB_FILE, ColourCalib, estimate, save, scaled
from semantic_gs_slam.io.datasets import load_dataset, parse_size


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m semantic_gs_slam.io.calibrate_colour",
                                 description="Estimate where the colour camera of an RGB-D recording sits relative to "
                                             "its depth camera (colour edges against depth discontinuities) and write "
                                             "the calibration the dataset loaders read.")
    ap.add_argument("dataset", help="sequence folder (7-Scenes, TUM RGB-D, ...)")
    ap.add_argument("--frames", type=int, default=25, help="frames used, spread over the sequence (default 25)")
    ap.add_argument("--size", default="320x240", help="working size for the search (default 320x240)")
    ap.add_argument("--out", help=f"file to write (default: DATASET/{CALIB_FILE})")
    ap.add_argument("--dry-run", action="store_true", help="print, write nothing")
    args = ap.parse_args(argv)
    if args.frames < 1:
        ap.error(f"--frames must be >= 1, got {args.frames}")
    try:
        ds = load_dataset(args.dataset, colour_calib="none")
        w, h = parse_size(args.size)
        small = ds.resized(w, h)
        n = max(1, min(args.frames, len(ds)))
        picks = np.linspace(0, len(ds) - 1, n).round().astype(int)
        frames, unreadable = [], []
        for i in picks:
            try:
                f = small[int(i)]
            except DatasetError as exc:  # a damaged frame: use the others
                print(f"left out: {exc}", file=sys.stderr)  # names the file
                unreadable.append(int(i))
                continue
            frames.append((f.rgb.mean(-1).astype(np.float32), f.depth))
        if not frames:
            raise DatasetError(f"none of the {len(picks)} frames picked could be read (the first: "
                               f"{ds.rgb_paths[unreadable[0]]})")
        k = small.intrinsics
        est = estimate(frames, k.fx, k.fy, k.cx, k.cy)
        nat = ds.native_intrinsics
        calib = scaled(est.calib, nat.width / w, nat.height / h)
        calib = ColourCalib(round(calib.fx, 2), round(calib.fy, 2), round(calib.cx, 2), round(calib.cy, 2),
                            round(calib.tx, 4), round(calib.ty, 4), 0.0, nat.width, nat.height)
    except DatasetError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"edge alignment over {est.frames} frames: {est.score_identity:.4f} as recorded -> "
          f"{est.score:.4f} registered")
    print(f"colour camera (native {nat.width}x{nat.height}): fx {calib.fx} fy {calib.fy} cx {calib.cx} cy {calib.cy}; "
          f"depth->colour t = ({calib.tx}, {calib.ty}, {calib.tz}) m")
    if est.score <= est.score_identity * 1.02:
        print("the colour already looks registered to the depth; no file written")
        return 0
    if not args.dry_run:
        out = args.out or os.path.join(args.dataset, CALIB_FILE)
        try:
            save(calib, out, note=f"estimated by semantic_gs_slam.io.colour_registration on {est.frames} frames "
                                  f"(edge alignment {est.score_identity:.4f} -> {est.score:.4f})")
        except OSError as exc:
            print(f"error: cannot write {out}: {exc.strerror or exc}", file=sys.stderr)
            return 2
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
