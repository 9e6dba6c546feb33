#!/usr/bin/env python3
"""How far apart two reference trajectories of the same real sequence are, and ours from each.

Usage (from the repository root)::

    python bench/reference_agreement.py ../shared/data/7scenes-redkitchen-0-499 \\
        --second PGT/pgt/sfm/7scenes/redkitchen_train.txt --offset-from PGT/pgt/dslam/7scenes/redkitchen_train.txt \\
        --sequence seq-01 --stride 2 --frames 250 [--map RUN/map/params.npz]

The dataset's own reference poses (7-Scenes: KinectFusion's, of the depth camera) are compared with a second
reference for the same frames, e.g. the structure-from-motion pseudo ground truth of Brachmann et al., "On the
Limits of Pseudo Ground Truth in Visual Camera Re-localisation" (ICCV 2021; files in the public repository
``tsattler/visloc_pseudo_gt_limitations``, folder ``pgt/``, BSD-3-Clause; COLMAP convention, colour camera). The
second reference's camera may sit elsewhere on the rig (7-Scenes: the colour camera, ~2.5 cm to the side): the fixed
offset between the two is fitted from ``--offset-from``, a file of the dataset's own poses in the second file's
camera (that repository's ``pgt/dslam`` files), else taken as none. ``--map`` adds a SLAM run's trajectory (a
``params.npz`` written by ``python -m semantic_gs_slam.run --out RUN`` with the same ``--start/--stride/--frames``).

Prints ATE (rigid and with scale) and RPE over 1 and 5 frame steps for each pair. Nothing is downloaded; the data
and the pose files stay outside the repository.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from semantic_gs_slam.errors import SlamError
from semantic_gs_slam.eval.metrics import ate_rmse, ate_sim3, rpe_rmse
from semantic_gs_slam.geometry import fixed_offset, pose_error
from semantic_gs_slam.io.datasets import frame_indices, load_colmap_poses, load_dataset
from semantic_gs_slam.mapping.gaussian_map import load_params, trajectory_from_params


def row(name: str, a: list[np.ndarray], b: list[np.ndarray]) -> str:
    """One table line: ATE rigid, ATE with scale (and the scale), RPE over 1 and 5 steps, in cm."""
    sim, scale = ate_sim3(a, b)
    return (f"| {name} | {100 * ate_rmse(a, b):.2f} | {100 * sim:.2f} ({scale:.3f}) | {100 * rpe_rmse(a, b, 1):.2f} | "
            f"{100 * rpe_rmse(a, b, 5):.2f} |")


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the exit code."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset", help="sequence folder with the dataset's reference poses (7-Scenes, TUM, ...)")
    ap.add_argument("--second", required=True,
                    help="second reference, COLMAP text convention (NAME QW QX QY QZ TX TY TZ)")
    ap.add_argument("--offset-from", default="", help="the dataset's poses in the second file's camera and format "
                    "(fits the fixed camera offset; default: none)")
    ap.add_argument("--sequence", default="seq-01", help="prefix of the frames' names in the pose files")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--stride", type=int, default=1)
    ap.add_argument("--frames", type=int, default=0, help="frames used (0: all)")
    ap.add_argument("--map", default="", help="a SLAM run's params.npz over the same frames")
    a = ap.parse_args(argv)
    try:
        ds = load_dataset(a.dataset)
        idx = frame_indices(len(ds), a.start, a.stride, a.frames)
        ref = [ds.poses[i] for i in idx]
        second = load_colmap_poses(a.second)
        names = [f"{a.sequence}/frame-{i:06d}.color.png" for i in idx]
        missing = [n for n in names if n not in second]
        if missing:
            ap.error(f"{len(missing)} of {len(names)} frames are not in {a.second} (first: {missing[0]}); "
                     "check --sequence")
        sec = [second[n] for n in names]
        offset = np.eye(4)
        if a.offset_from:
            same = load_colmap_poses(a.offset_from)
            if not all(n in same for n in names):
                ap.error(f"not every frame chosen is in {a.offset_from}; check --sequence")
            offset = fixed_offset(ref, [same[n] for n in names])
        ours = None
        if a.map:
            ours = trajectory_from_params(load_params(a.map))
            if len(ours) != len(idx):
                ap.error(f"{a.map} holds {len(ours)} poses, the frames chosen are {len(idx)}: give the run's "
                         "--start/--stride/--frames")
    except SlamError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    cm, deg = pose_error(np.eye(4), offset)
    print(f"{len(idx)} frames ({a.sequence}, dataset frames {idx[0]}..{idx[-1]} every {a.stride}); the second "
          f"reference's camera is {100 * cm:.2f} cm / {deg:.2f} deg from the dataset's"
          + (" (fitted)" if a.offset_from else " (assumed the same)"))
    print("\n| trajectories compared | ATE rigid (cm) | ATE with scale (cm) (scale) | RPE 1 step (cm) "
          "| RPE 5 steps (cm) |")
    print("|---|---|---|---|---|")
    print(row("dataset reference vs second reference", [p @ offset for p in ref], sec))
    if ours is not None:
        print(row("ours vs dataset reference", ours, ref))
        print(row("ours vs second reference", [p @ offset for p in ours], sec))
    return 0


if __name__ == "__main__":
    sys.exit(main())
