#!/usr/bin/env python3
"""Replay the labelling stage over a saved map: the label votes of a run with other label settings, in minutes
instead of a SLAM run (half an hour for the 250 kitchen frames on a loaded 2-core machine).

Usage::

    python bench/detector_replay.py --map MAP --dataset ../shared/data/7scenes-redkitchen-0-499 --out MAP_REPLAY \\
        [--start 0] [--stride 2] [--box-min-fill 0.25]
    python bench/detector_kitchen.py --map MAP_REPLAY --dataset ../shared/data/7scenes-redkitchen-0-499

What it keeps of the run: the Gaussians (centres, everything but their classes) and the camera trajectory. What it
does again, with the engine's own code: the run's frames (``--start``, ``--stride``: the run's own) go through a fresh
:class:`~semantic_gs_slam.labels.LabelStage` (``--labels onnx``: the installed detector, the label settings given
here) at the constant-velocity guess from the saved trajectory, as the run CLI labels a frame before tracking it;
each frame's labels vote with :meth:`GaussianMap.vote` for the Gaussians that existed at that frame (their
``timestep``), as the run's mapping does; each Gaussian's class is then its votes' majority (``min_votes`` or more
votes, as :meth:`GaussianMap.voted_features` sets them at keyframes; else the saved class). Not replayed: the
semantic loss that refines the classes after the last keyframe, and Gaussians that a run with other labels would
seed differently. ``--check``: only print how many Gaussians change class.

``--fills N`` (no map needed): for N frames from ``--start`` (every ``--stride``-th, the dataset's own poses), each
detection's share of its box's depth pixels that the instance it would name fills (the instance that fills most of
the box and lies 60 % inside it: what ``LabelConfig.box_min_fill`` judges), printed per class as a range with the
count at or above ``--box-min-fill``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np
import torch

from semantic_gs_slam.config import MappingConfig
from semantic_gs_slam.io.datasets import load_dataset
from semantic_gs_slam.labels import LabelConfig, LabelStage, box_instance, predict_pose
from semantic_gs_slam.mapping.gaussian_map import GaussianMap, load_params, trajectory_from_params


def replay(map_dir: str, dataset: str, size: tuple[int, int], start: int, stride: int,
           config: LabelConfig) -> tuple[dict[str, np.ndarray], dict[int, str], dict]:
    """(the map's arrays with ``semantic_ids`` and ``semantic_votes`` replayed, the class table, counts)."""
    arrays = load_params(os.path.join(map_dir, "params.npz"))
    with open(os.path.join(map_dir, "semantic.json"), encoding="utf-8") as fh:
        classes = {int(c["id"]): c["class"] for c in json.load(fh)["segmentation"]}
    poses = trajectory_from_params(arrays)
    ds = load_dataset(dataset, size=size)
    stage = LabelStage(config, ds.intrinsics)
    gm = GaussianMap()
    gm.params["means3D"] = torch.as_tensor(np.asarray(arrays["means3D"], np.float32))
    gm.class_slots = [int(s) for s in np.asarray(arrays["semantic_feature_ids"]).reshape(-1)]
    gm.votes = torch.zeros(len(gm.params["means3D"]), len(gm.class_slots))
    born = torch.as_tensor(np.asarray(arrays["timestep"]).reshape(-1))
    for j, c2w in enumerate(poses):
        f = ds[start + stride * j]
        sem = stage(f.rgb, f.depth, None, predict_pose(poses[:j], poses[0]), index=j)
        if sem is None:
            continue
        classes.update({k: v for k, v in stage.classes.items() if k not in classes})
        before = gm.votes
        gm.vote(torch.as_tensor(sem), torch.as_tensor(f.depth, dtype=torch.float32),
                torch.as_tensor(np.linalg.inv(c2w), dtype=torch.float32), ds.intrinsics)
        gm.votes = before + (gm.votes - before) * (born <= j).float()[:, None]  # Gaussians not there yet: no vote
    total = gm.votes.sum(1, keepdim=True)
    feats = torch.as_tensor(np.asarray(arrays["semantic_features"], np.float32))
    feats = torch.where(total >= MappingConfig().min_votes, gm.votes / total.clamp_min(1e-9), feats)
    ids = gm.labels_from_features(feats).numpy()
    old = np.asarray(arrays["semantic_ids"]).reshape(-1)
    out = dict(arrays)
    out["semantic_ids"] = ids.astype(old.dtype if ids.size == 0 or ids.max() < 256 else np.int64)
    out["semantic_votes"] = gm.votes.numpy().astype(np.float32)
    counts = {"gaussians": len(ids), "changed": int((ids != old).sum()), "frames": len(poses)}
    return out, classes, counts


def box_fills(dataset: str, size: tuple[int, int], start: int, stride: int, frames: int) -> dict[str, list[float]]:
    """Class -> the box fill of each of its detections that names an instance (see ``--fills``)."""
    from semantic_gs_slam.labels.onnx_model import COCO_BASE, COCO_NAMES

    ds = load_dataset(dataset, size=size)
    stage = LabelStage(LabelConfig(mode="onnx"), ds.intrinsics)
    out: dict[str, list[float]] = {}
    for j in range(frames):
        f = ds[start + stride * j]
        detections = stage.model(f.rgb)
        geo = stage.geometry.label(f.rgb, f.depth, f.gt_c2w).ids
        h, w = geo.shape
        for sem_id, _score, _mask, box in detections:
            x1, y1, x2, y2 = np.clip(np.round(box), 0, [w, h, w, h]).astype(int)
            found = box_instance(geo, (x1, y1, x2, y2))
            if found is None:
                continue
            seen = max(int(np.count_nonzero(f.depth[y1:y2, x1:x2] > 0)), 1)
            out.setdefault(COCO_NAMES[sem_id - COCO_BASE], []).append(float(found[1]) / seen)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--map", default="", help="map folder of a run (params.npz, semantic.json)")
    ap.add_argument("--dataset", required=True, help="the run's sequence")
    ap.add_argument("--out", default="", help="folder for the replayed map (a copy with new classes and votes)")
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--start", type=int, default=0, help="the run's --start")
    ap.add_argument("--stride", type=int, default=2, help="the run's --stride")
    ap.add_argument("--box-min-fill", type=float, default=LabelConfig().box_min_fill,
                    help="LabelConfig.box_min_fill (0: off, the labelling before the rule)")
    ap.add_argument("--check", action="store_true", help="only print how many Gaussians change class")
    ap.add_argument("--fills", type=int, default=0, metavar="N",
                    help="print the box fills of the detections in N frames from --start instead (no map needed)")
    args = ap.parse_args(argv)
    w, h = (int(x) for x in args.size.split("x"))
    t0 = time.perf_counter()
    if args.fills:
        fills = box_fills(args.dataset, (w, h), args.start, args.stride, args.fills)
        last = args.start + args.stride * (args.fills - 1)
        print(f"box fills, frames {args.start}-{last} (every {args.stride}), the dataset's poses:")
        for name, v in sorted(fills.items()):
            a = np.array(v)
            print(f"  {name:13s} {len(a):4d} detections  fill {a.min():.2f}-{a.max():.2f}  "
                  f">= {args.box_min_fill}: {int((a >= args.box_min_fill).sum())}")
        print(f"({time.perf_counter() - t0:.0f} s)")
        return 0
    if not args.map:
        ap.error("--map is required (except with --fills)")
    cfg = LabelConfig(mode="onnx", box_min_fill=args.box_min_fill)
    out, classes, counts = replay(args.map, args.dataset, (w, h), args.start, args.stride, cfg)
    print(f"replayed {counts['frames']} frames (box_min_fill {args.box_min_fill}): {counts['changed']} of "
          f"{counts['gaussians']} Gaussians changed class ({time.perf_counter() - t0:.0f} s)")
    if args.check or not args.out:
        return 0
    os.makedirs(args.out, exist_ok=True)
    np.savez_compressed(os.path.join(args.out, "params.npz"), **out)
    with open(os.path.join(args.out, "semantic.json"), "w", encoding="utf-8") as fh:
        json.dump({"segmentation": [{"id": k, "class": v} for k, v in sorted(classes.items())]}, fh)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
