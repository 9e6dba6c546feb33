#!/usr/bin/env python3
"""Check a real-sequence map's answers against the images: where the object database says a thing is,
drawn into dataset frames with the dataset's own poses, and compared with the depth seen there.

Usage (after a run on a real sequence, e.g. ``python -m semantic_gs_slam.run --dataset <seq> --out MAP
--labels geometry ...`` and, optionally, names given by place with ``semantic_gs_slam.labels.names``)::

    python bench/slam_real_answer.py --map MAP --dataset ../shared/data/7scenes-redkitchen-0-499 \\
        --names cup,table --frames 0,300 --out /tmp/answers.png

For each name the answer is what ``object_query_server`` serves (``ObjectDatabase.query``, the same
code). For each frame it prints the pixel the answer projects to and the difference between the
answer's depth and the dataset depth at that pixel (median of a 9x9 window): a few centimetres means
the answer sits on the surface the camera saw there. The map must be in the dataset's frame (our CLI
anchors its first frame on the dataset's first pose). The PNG shows the frames side by side with the
answers marked. The dataset stays outside the repository (mind its licence).
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np
from PIL import Image, ImageDraw

from semantic_gs_slam.io.datasets import load_dataset
from semantic_gs_slam.run import add_camera_args, camera_kwargs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--map", required=True, help="map folder (params.npz, semantic.json)")
    ap.add_argument("--dataset", required=True, help="the sequence the map was built from")
    ap.add_argument("--names", default="cup,table", help="comma-separated object names to ask for")
    ap.add_argument("--frames", default="0", help="comma-separated dataset frame indices to draw into")
    ap.add_argument("--out", default="", help="PNG with the frames side by side and the answers marked")
    add_camera_args(ap)
    args = ap.parse_args(argv)
    from object_query.semantic_map import ObjectDatabase  # the object-query server's own code

    db = ObjectDatabase.from_files(os.path.join(args.map, "params.npz"), os.path.join(args.map, "semantic.json"))
    ds = load_dataset(args.dataset, **camera_kwargs(args))
    print(ds.camera_line(), file=sys.stderr)
    k = ds.intrinsics
    answers = {}
    print("| name | answer (x, y, z) | " + " | ".join(f"frame {f}: pixel, depth difference" for f in
                                                     args.frames.split(",")) + " |")
    print("|---|---|" + "---|" * len(args.frames.split(",")))
    tiles = []
    rows: dict[str, list[str]] = {}
    for name in [n.strip() for n in args.names.split(",") if n.strip()]:
        r = db.query(name)
        answers[name] = np.array(r.position) if r.found else None
        rows[name] = [f"{name}", "not found: " + r.message if not r.found else
                      "({:.3f}, {:.3f}, {:.3f})".format(*r.position)]
    for fi in [int(f) for f in args.frames.split(",")]:
        f = ds[fi]
        if f.gt_c2w is None:
            print(f"frame {fi} has no pose in the dataset", file=sys.stderr)
            return 2
        img = Image.fromarray(np.asarray(f.rgb if f.rgb.dtype == np.uint8 else (f.rgb * 255).astype(np.uint8)))
        draw = ImageDraw.Draw(img)
        w2c = np.linalg.inv(f.gt_c2w)
        for name, pos in answers.items():
            if pos is None:
                continue
            pc = w2c[:3, :3] @ pos + w2c[:3, 3]
            u, v = k.fx * pc[0] / pc[2] + k.cx, k.fy * pc[1] / pc[2] + k.cy
            if pc[2] <= 0.1 or not (0 <= u < k.width and 0 <= v < k.height):
                rows[name].append("not in view")
                continue
            ui, vi = int(round(u)), int(round(v))
            win = f.depth[max(vi - 4, 0):vi + 5, max(ui - 4, 0):ui + 5]
            seen = float(np.median(win[win > 0])) if (win > 0).any() else float("nan")
            rows[name].append(f"({ui}, {vi}), {100 * (pc[2] - seen):+.1f} cm")
            draw.ellipse([u - 7, v - 7, u + 7, v + 7], outline=(255, 255, 0), width=3)
            draw.text((u + 9, v - 9), name, fill=(255, 255, 0))
        draw.text((6, 4), f"frame {fi}", fill=(255, 255, 255))
        tiles.append(img)
    for cells in rows.values():
        print("| " + " | ".join(cells) + " |")
    if args.out and tiles:
        sheet = Image.new("RGB", (sum(t.width for t in tiles), max(t.height for t in tiles)))
        x = 0
        for t in tiles:
            sheet.paste(t, (x, 0))
            x += t.width
        sheet.save(args.out)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
