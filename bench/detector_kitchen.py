#!/usr/bin/env python3
"""The COCO detector on the shared 7-Scenes kitchen: the true positions of its objects, the named map's instances
against them (precision, recall, the mugs' distances), an overlay of detections and a top view of the named map.

Usage (after ``python -m semantic_gs_slam.run --dataset $D --out MAP --size 320x240 --stride 2 --frames 250
--labels auto`` with the detector installed)::

    python bench/detector_kitchen.py --map MAP --dataset ../shared/data/7scenes-redkitchen-0-499 \\
        --overlay docs/img/detector_overlay.jpg --top docs/img/detector_topview.png --sheet /tmp/instances.jpg

**True positions.** :data:`TRUTH` lists the kitchen's objects as a person marked them: a frame and a pixel of the
object in that frame (the frame as the run reads it: 320x240, colour registered to depth), and the class. The
object's position is the median of the depth pixels of its nearest surface in a small window there (depths within
4 cm of the window's 20th percentile), back-projected and moved by the dataset's own pose of that frame; an object
marked in several frames takes the mean, and the spread between its frames is printed (it says how well the poses
and depths agree). These are the surfaces the camera sees, as a map's Gaussians are.

**Matching.** A named instance of the map (``ObjectDatabase``, the object-query server's code) is *true* when a
true object of its class lies within the class's radius of its centre (:data:`RADIUS`), measured to the object's
marks or to their mean, whichever is nearer (a large object, the 2 m table top or the wide screen, is marked at
several places); recall counts the true objects that some instance of their class matches. The last line gives
precision, recall, and how many mugs and tvs were found. ``--start``: the run's first frame, for a map of part of the
sequence. ``--sheet`` draws each named instance into the frame that sees
its centre best, to check by eye the instances that match nothing (a real object not in :data:`TRUTH`, or a
false one). The dataset stays outside the repository (non-commercial licence).
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
from PIL import Image, ImageDraw

from semantic_gs_slam.io.datasets import load_dataset

#: (object, class, frame, u, v): a pixel of the object in that frame at 320x240 (colour registered to depth)
TRUTH: list[tuple[str, str, int, int, int]] = [
    ("mug A (white, yellow rim)", "cup", 0, 199, 88),
    ("mug A (white, yellow rim)", "cup", 300, 32, 117),
    ("mug B (white, printed)", "cup", 300, 267, 158),
    ("mug B (white, printed)", "cup", 340, 199, 124),
    ("tv (wall screen)", "tv", 280, 262, 14),
    ("tv (wall screen)", "tv", 460, 280, 45),
    ("dining table", "dining table", 300, 160, 200),
    ("dining table", "dining table", 0, 220, 160),
    ("dining table", "dining table", 0, 140, 125),  # more of its 2 m top: a large object is matched by any mark
    ("dining table", "dining table", 0, 285, 110),
    ("dining table", "dining table", 300, 40, 200),
    ("dining table", "dining table", 300, 270, 130),
    ("dining table", "dining table", 400, 80, 170),
    ("dining table", "dining table", 400, 260, 185),
    ("chair left of the table (frame 0)", "chair", 0, 118, 85),
    ("chair behind the table", "chair", 0, 240, 88),
    ("chair near the camera (frame 0)", "chair", 0, 230, 222),
    ("chair behind the table", "chair", 300, 116, 103),
    ("chair right of the table (frame 300)", "chair", 300, 285, 115),
]
RADIUS = {"cup": 0.15, "bottle": 0.15, "tv": 0.5, "chair": 0.5, "dining table": 0.5}
DEFAULT_RADIUS = 0.3


def true_marks(ds, window: int = 4) -> dict[str, tuple[str, np.ndarray]]:
    """Object -> (class, its marks' positions [M, 3] in the map's frame), one row per line of :data:`TRUTH`."""
    pts: dict[str, list[np.ndarray]] = {}
    cls: dict[str, str] = {}
    k = ds.intrinsics
    for name, c, fi, u, v in TRUTH:
        f = ds[fi]
        for r in (window, 2 * window, 4 * window):  # screens often have no depth: widen the window
            d = f.depth[max(v - r, 0):v + r + 1, max(u - r, 0):u + r + 1]
            vv, uu = np.mgrid[max(v - r, 0):v + r + 1, max(u - r, 0):u + r + 1]
            vv, uu = vv[:d.shape[0], :d.shape[1]], uu[:d.shape[0], :d.shape[1]]
            ok = d > 0
            if ok.sum() >= 5:
                break
        else:
            raise SystemExit(f"no depth around ({u}, {v}) of frame {fi} for {name}")
        near = ok & (d < np.percentile(d[ok], 20) + 0.04)
        z = d[near]
        p = np.stack([(uu[near] - k.cx) / k.fx * z, (vv[near] - k.cy) / k.fy * z, z], -1)
        pc = np.median(p, 0)
        c2w = f.gt_c2w
        pts.setdefault(name, []).append(c2w[:3, :3] @ pc + c2w[:3, 3])
        cls[name] = c
    return {name: (cls[name], np.array(ps)) for name, ps in pts.items()}


def true_positions(ds, window: int = 4) -> dict[str, tuple[str, np.ndarray, float]]:
    """Object -> (class, position [3]: the mean of its marks, spread between its marks in metres)."""
    out = {}
    for name, (c, arr) in true_marks(ds, window).items():
        spread = float(np.linalg.norm(arr - arr.mean(0), axis=1).max()) if len(arr) > 1 else 0.0
        out[name] = (c, arr.mean(0), spread)
    return out


def distance_to(centre: np.ndarray, marks: np.ndarray) -> float:
    """Metres from an instance's centre to a marked object: to the mean of its marks or to its nearest mark, whichever
    is nearer (a large object, a 2 m table or a wide screen, is marked at several places and matched by any)."""
    d = [float(np.linalg.norm(centre - marks.mean(0)))] + [float(np.linalg.norm(centre - m)) for m in marks]
    return min(d)


def overlay(ds, model: str, frames: list[int], out: str, score: float) -> None:
    """Detections drawn on the frames (320x240, as the run sees them), tiled 3 across."""
    from semantic_gs_slam.labels.onnx_model import COCO_BASE, COCO_NAMES, OnnxSegmenter

    det = OnnxSegmenter(model, score)
    tiles = []
    for fi in frames:
        f = ds[fi]
        rgb = f.rgb if f.rgb.dtype == np.uint8 else (np.clip(f.rgb, 0, 1) * 255).astype(np.uint8)
        img = Image.fromarray(rgb).resize((480, 360), Image.Resampling.BILINEAR)
        dr = ImageDraw.Draw(img)
        for sid, sc, _m, b in det(rgb):
            name = COCO_NAMES[sid - COCO_BASE]
            b = [float(x) * 1.5 for x in b]
            col = {"cup": (255, 40, 40), "tv": (60, 160, 255), "chair": (60, 220, 60),
                   "dining table": (255, 200, 0)}.get(name, (255, 255, 255))
            dr.rectangle(b, outline=col, width=2)
            dr.rectangle([b[0], b[1], b[0] + 7 * len(name) + 34, b[1] + 12], fill=(0, 0, 0))
            dr.text((b[0] + 2, b[1]), f"{name} {sc:.2f}", fill=col)
        dr.text((4, 346), f"frame {fi}", fill=(255, 255, 255))
        tiles.append(img)
    cols = 3
    rows = (len(tiles) + cols - 1) // cols
    sheet = Image.new("RGB", (480 * cols, 360 * rows))
    for j, t in enumerate(tiles):
        sheet.paste(t, ((j % cols) * 480, (j // cols) * 360))
    sheet.save(out, quality=85)


def top_view(db, truth: dict, out: str, t: np.ndarray) -> None:
    """The named map from above (``t``: the gravity-aligned frame, x right, y up the image), instances' centres with
    their labels (boxes for those under 1.5 m across), true positions as crosses."""
    insts = [i for i in db.all_instances() if i.name not in ("floor", "wall", "ceiling", "object", "table")]

    def g(p) -> np.ndarray:
        return t[:3, :3] @ np.asarray(p, np.float64) + t[:3, 3]

    pts = np.array([g(i.centre) for i in insts] + [g(p) for _c, p, _s in truth.values()])
    lo, hi = pts.min(0) - 0.5, pts.max(0) + 0.5
    scale = 640 / max(hi[0] - lo[0], hi[1] - lo[1])
    w, h = int((hi[0] - lo[0]) * scale) + 20, int((hi[1] - lo[1]) * scale) + 40

    def px(p: np.ndarray) -> tuple[float, float]:
        return 10 + (p[0] - lo[0]) * scale, h - 30 - (p[1] - lo[1]) * scale

    img = Image.new("RGB", (w, h), (250, 250, 250))
    dr = ImageDraw.Draw(img)
    cols = {"cup": (220, 30, 30), "tv": (30, 110, 230), "chair": (30, 160, 30), "dining table": (200, 150, 0)}
    for i in sorted(insts, key=lambda i: -i.point_count):
        col = cols.get(i.name, (120, 120, 120))
        corners = np.array([g([x, y, z]) for x in (i.bbox_min[0], i.bbox_max[0]) for y in (i.bbox_min[1],
                            i.bbox_max[1]) for z in (i.bbox_min[2], i.bbox_max[2])])
        if np.ptp(corners[:, :2], 0).max() < 1.5:
            a, b = px(corners.min(0)), px(corners.max(0))
            dr.rectangle([a[0], b[1], b[0], a[1]], outline=col, width=1)
        cx, cy = px(g(i.centre))
        dr.ellipse([cx - 3, cy - 3, cx + 3, cy + 3], fill=col)
        dr.text((cx + 5, cy - 6), i.label, fill=col)
    for name, (_c, p, _s) in truth.items():
        cx, cy = px(g(p))
        dr.line([cx - 6, cy - 6, cx + 6, cy + 6], fill=(0, 0, 0), width=2)
        dr.line([cx - 6, cy + 6, cx + 6, cy - 6], fill=(0, 0, 0), width=2)
        dr.text((cx + 6, cy + 4), name.split(" (")[0], fill=(60, 60, 60))
    dr.text((10, h - 22), f"named map from above (floor plane, 1 m = {scale:.0f} px): dots = instances (boxes: "
            "their extent), x = true positions", fill=(0, 0, 0))
    img.save(out)


def sheet_of_instances(ds, db, poses: list[np.ndarray | None], out: str) -> None:
    """Each named instance drawn into the frame whose view of it is most central (and not occluded); ``poses``: per
    dataset frame, the run's camera-to-world pose or None."""
    k = ds.intrinsics
    insts = [i for i in db.all_instances() if i.name not in ("floor", "wall", "ceiling", "object", "table")]
    tiles = []
    cache: dict[int, object] = {}
    for inst in insts:
        c = np.array(inst.centre)
        cands = []
        for fi, c2w in enumerate(poses):
            if fi % 2 or c2w is None:  # the run's frames only
                continue
            p = np.linalg.inv(c2w) @ np.append(c, 1.0)
            if p[2] < 0.3:
                continue
            u, v = k.fx * p[0] / p[2] + k.cx, k.fy * p[1] / p[2] + k.cy
            if not (20 <= u < k.width - 20 and 20 <= v < k.height - 20):
                continue
            cands.append(((u - k.width / 2) ** 2 + (v - k.height / 2) ** 2, fi, u, v, p[2]))
        best = None
        for cand in sorted(cands)[:8]:  # the most central views in which the depth there is the centre's: not hidden
            _o, fi, u, v, z = cand
            f = cache.setdefault(fi, ds[fi])
            d = f.depth[int(v) - 2:int(v) + 3, int(u) - 2:int(u) + 3]
            if (d > 0).any() and np.abs(d[d > 0] - z).min() < 0.1:
                best = cand
                break
        if best is None:
            best = min(cands) if cands else None
        if best is None:
            continue
        _o, fi, u, v, z = best
        f = cache.setdefault(fi, ds[fi])
        rgb = f.rgb if f.rgb.dtype == np.uint8 else (np.clip(f.rgb, 0, 1) * 255).astype(np.uint8)
        img = Image.fromarray(rgb)
        dr = ImageDraw.Draw(img)
        dr.ellipse([u - 6, v - 6, u + 6, v + 6], outline=(255, 0, 0), width=2)
        dr.rectangle([0, 0, 319, 12], fill=(0, 0, 0))
        dr.text((2, 0), f"{inst.label} ({inst.point_count} pts) frame {fi}", fill=(255, 255, 0))
        tiles.append(img)
    cols = 4
    rows = max(1, (len(tiles) + cols - 1) // cols)
    sheet = Image.new("RGB", (320 * cols, 240 * rows))
    for j, t in enumerate(tiles):
        sheet.paste(t, ((j % cols) * 320, (j // cols) * 240))
    sheet.save(out, quality=85)


def gravity_transform(map_dir: str) -> np.ndarray:
    """4x4 transform from the map's frame to one with z up and the floor at z = 0: the floor Gaussians' plane (least
    squares) gives up, oriented towards the rest of the map; x stays the map's x as far as it can."""
    return _gravity(map_dir)[0]


def _gravity(map_dir: str) -> tuple[np.ndarray, dict]:
    import json

    from semantic_gs_slam.mapping.gaussian_map import load_params

    arrays = load_params(os.path.join(map_dir, "params.npz"))
    with open(os.path.join(map_dir, "semantic.json"), encoding="utf-8") as fh:
        sem = json.load(fh)
    names = {int(c["id"]): c["class"] for c in sem["segmentation"]} if "segmentation" in sem else {}
    ids = np.asarray(arrays["semantic_ids"]).reshape(-1)
    means = np.asarray(arrays["means3D"], np.float64)
    floor = np.isin(ids, [i for i, n in names.items() if n == "floor"])
    if floor.sum() < 100:
        raise SystemExit(f"{map_dir}: too few floor Gaussians ({int(floor.sum())}) to find up")
    pts = means[floor]
    c = pts.mean(0)
    up = np.linalg.svd(pts - c, full_matrices=False)[2][-1]
    if (means.mean(0) - c) @ up < 0:
        up = -up
    x = np.array([1.0, 0.0, 0.0]) - up[0] * up
    x /= np.linalg.norm(x)
    rot = np.stack([x, np.cross(up, x), up])  # rows: new x, y, z in the old frame
    t = np.eye(4)
    t[:3, :3] = rot
    t[:3, 3] = -rot @ c
    return t, arrays


def gravity_aligned_copy(map_dir: str, out_dir: str) -> np.ndarray:
    """A copy of the map in :func:`gravity_transform`'s frame, as a robot's map is (the planner's approach poses are
    in x, y). The Gaussians are isotropic, so only their centres move. Returns the transform applied."""
    import shutil

    t, arrays = _gravity(map_dir)
    os.makedirs(out_dir, exist_ok=True)
    out = dict(arrays)
    means = np.asarray(arrays["means3D"], np.float64)
    out["means3D"] = (means @ t[:3, :3].T + t[:3, 3]).astype(np.asarray(arrays["means3D"]).dtype)
    np.savez_compressed(os.path.join(out_dir, "params.npz"), **out)
    shutil.copy(os.path.join(map_dir, "semantic.json"), os.path.join(out_dir, "semantic.json"))
    return t


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--map", help="map folder (params.npz, semantic.json) of a run with --labels auto")
    ap.add_argument("--dataset", required=True, help="the kitchen sequence")
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--model", default="", help="ONNX detector for --overlay (default: the installed one)")
    ap.add_argument("--score", type=float, default=0.4, help="score threshold for --overlay")
    ap.add_argument("--overlay", default="", help="write detections on a few frames to this image")
    ap.add_argument("--overlay-frames", default="0,220,300,340,400,480")
    ap.add_argument("--top", default="", help="write a top view of the named map to this PNG")
    ap.add_argument("--sheet", default="", help="write each named instance in a frame that sees it to this image")
    ap.add_argument("--start", type=int, default=0, help="the run's first frame (its --start), for --sheet")
    ap.add_argument("--z-up", default="", help="write a copy of the map with z up and the floor at z = 0 here (for "
                    "plan_command: its approach poses are in x, y)")
    args = ap.parse_args(argv)
    w, h = (int(x) for x in args.size.split("x"))
    ds = load_dataset(args.dataset, size=(w, h))
    t0 = time.perf_counter()
    marks = true_marks(ds)
    truth = true_positions(ds)
    print("True positions (dataset depth and poses, the map's frame; the mean of an object's marks):")
    for name, (c, p, s) in truth.items():
        print(f"  {name:40s} {c:13s} ({p[0]:6.3f}, {p[1]:6.3f}, {p[2]:6.3f})  {len(marks[name][1])} mark(s), "
              f"spread {s * 100:4.1f} cm")
    if args.overlay:
        from semantic_gs_slam.models.fetch import installed_detector

        model = args.model or installed_detector()
        if not model:
            print("no detector installed (python -m semantic_gs_slam.models.fetch)", file=sys.stderr)
            return 2
        overlay(ds, model, [int(x) for x in args.overlay_frames.split(",")], args.overlay, args.score)
        print(f"overlay: {args.overlay}")
    if not args.map:
        return 0
    from object_query.names import load_synonyms
    from object_query.semantic_map import ObjectDatabase

    synonyms = load_synonyms(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "src", "object_query",
                                          "config", "synonyms.yaml"))  # the server's bundled synonyms
    db = ObjectDatabase.from_files(os.path.join(args.map, "params.npz"), os.path.join(args.map, "semantic.json"),
                                   synonyms=synonyms)
    named = [i for i in db.all_instances() if i.name not in ("floor", "wall", "ceiling", "object", "table")]
    print(f"\nNamed instances of the map ({len(named)}; plane classes and unnamed objects left out):")
    matched: dict[str, list[str]] = {}
    tp = 0
    per_class: dict[str, list[int]] = {}
    for inst in named:
        r = RADIUS.get(inst.name, DEFAULT_RADIUS)
        hits = [(distance_to(np.array(inst.centre), m), n) for n, (c, m) in marks.items() if c == inst.name]
        hits = [x for x in hits if x[0] <= r]
        ok = bool(hits)
        tp += ok
        per_class.setdefault(inst.name, [0, 0])
        per_class[inst.name][0] += ok
        per_class[inst.name][1] += 1
        if ok:
            d, n = min(hits)
            matched.setdefault(n, []).append(f"{inst.label} {d * 100:.1f} cm")
        c = inst.centre
        print(f"  {inst.label:18s} ({c[0]:6.3f}, {c[1]:6.3f}, {c[2]:6.3f}) {inst.point_count:6d} pts  "
              f"{'matches ' + min(hits)[1] + f' at {min(hits)[0] * 100:.1f} cm' if ok else 'matches no marked object'}")
    print(f"\nprecision against the marked objects: {tp}/{len(named)} "
          f"({100 * tp / max(len(named), 1):.0f} %; instances matching nothing: check them on --sheet)")
    for c, (a, n) in sorted(per_class.items()):
        print(f"  {c:13s} {a}/{n}")
    print("recall of the marked objects:")
    classes = sorted({c for c, _p, _s in truth.values()})
    n_found = 0
    for c in classes:
        objs = [n for n, (cc, _p, _s) in truth.items() if cc == c]
        found = [n for n in objs if n in matched]
        n_found += len(found)
        print(f"  {c:13s} {len(found)}/{len(objs)}  " + "; ".join(f"{n}: {', '.join(matched[n])}" for n in found))
    mugs = [n for n, (c, _p, _s) in truth.items() if c == "cup"]
    tvs = [n for n, (c, _p, _s) in truth.items() if c == "tv"]
    print(f"precision {tp}/{len(named)} ({100 * tp / max(len(named), 1):.0f} %), recall {n_found}/{len(truth)} "
          f"({100 * n_found / max(len(truth), 1):.0f} %); mugs found {sum(n in matched for n in mugs)}/{len(mugs)}, "
          f"tv found {sum(n in matched for n in tvs)}/{len(tvs)} (a map of part of the run sees only some)")
    for q in ("cup", "mug", "tv", "television", "chair", "dining table", "table"):
        r = db.query(q)
        print(f"  query {q!r}: " + (f"({r.position[0]:.3f}, {r.position[1]:.3f}, {r.position[2]:.3f}) {r.message[:60]}"
                                    if r.found else "not found: " + r.message[:80]))
    if args.top:
        top_view(db, truth, args.top, gravity_transform(args.map))
        print(f"top view: {args.top}")
    if args.sheet:
        from semantic_gs_slam.mapping.gaussian_map import load_params, trajectory_from_params

        poses = trajectory_from_params(load_params(os.path.join(args.map, "params.npz")))
        # the map's frame j is dataset frame start + 2 j (stride 2): index the dataset the same way
        full = [None] * (args.start + 2 * len(poses))
        for j, p in enumerate(poses):
            full[args.start + 2 * j] = p
        sheet_of_instances(ds, db, full, args.sheet)
        print(f"instances sheet: {args.sheet}")
    if args.z_up:
        t = gravity_aligned_copy(args.map, args.z_up)
        print(f"z-up copy: {args.z_up} (transform rows {np.round(t[:3], 3).tolist()})")
        for name, (c, p, _s) in truth.items():
            if c == "cup":
                q = t[:3, :3] @ p + t[:3, 3]
                print(f"  {name} in the z-up copy: ({q[0]:.3f}, {q[1]:.3f}, {q[2]:.3f})")
    print(f"({time.perf_counter() - t0:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
