"""Names from people: "this is my mug" given to an instance id sticks in the saved map.

The geometry stage gives every object its own semantic id (named ``object``); naming one rewrites its
entry in the map's ``semantic.json`` (atomically), so the object-query server finds it by the new name
after its next reload. With ``map_ids: class`` (the default: every geometry instance is class
``object``) an id names every object at once, so a thing is named by *place* instead: the Gaussians of
one class within a radius of a point (where the person pointed, or where the robot looked) get a new
id with the given name, in ``params.npz`` and ``semantic.json``. Usage::

    python -m semantic_gs_slam.labels.names --map /tmp/kitchen_map --id 131 --name "my mug"
    python -m semantic_gs_slam.labels.names --map /tmp/kitchen_map --at 0.37 -0.05 1.62 --name cup
    python -m semantic_gs_slam.labels.names --map /tmp/kitchen_map --at 0.28 -1.33 3.01 --radius 0.25 \
        --of-class object --of-class unlabelled --name tv
    python -m semantic_gs_slam.labels.names --map /tmp/kitchen_map --dataset SEQ --frame 464 --pixel 484 85 \
        --radius 0.3 --of-class wall --of-class object --of-class unlabelled --name tv
    python -m semantic_gs_slam.labels.names --map /tmp/kitchen_map --list

``--frame N --pixel U V`` (:func:`point_at_pixel`) is the point a person sees in one of the images the map was
built from: pixel (U, V) of the colour image file of the dataset's frame N (its 0-based position in the frames the
loader keeps, as ``--start`` counts: the file's own number when none is left out; where colour is not registered to
depth, as on 7-Scenes, through the same colour calibration the run used), with that frame's depth and the map's
own pose of the frame (matched by time stamp, and checked against the dataset's pose when both have one).

Gaussians that no labelling gave a class keep id 0; ``unlabelled`` names them as a class (a TV screen gives
the depth camera nothing, so the geometry layer cannot cut it out, but its Gaussians are seeded at the depth
around it and can be named by place).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence

import numpy as np

from semantic_gs_slam.errors import DatasetError, MapFormatError, SlamError

MAX_NAME = 64


def read_names(semantic_json: str) -> dict[int, str]:
    """id -> class name of a ``semantic.json``.

    Raises:
        MapFormatError: missing file or not the ``{"segmentation": [{"id", "class"}]}`` schema.
    """
    if not os.path.isfile(semantic_json):
        raise MapFormatError(f"no semantic.json at {semantic_json}")
    try:
        with open(semantic_json) as fh:
            return {int(e["id"]): str(e["class"]) for e in json.load(fh)["segmentation"]}
    except (ValueError, KeyError, TypeError) as exc:
        raise MapFormatError(f"{semantic_json}: not in the {{'segmentation': [{{'id', 'class'}}]}} schema "
                             f"({exc})") from exc


def name_instance(semantic_json: str, instance_id: int, name: str) -> str:
    """Give semantic id ``instance_id`` the name ``name`` in ``semantic_json``; returns the old name.

    Raises:
        MapFormatError: unreadable file, an id the map does not have.
        ValueError: an empty or over-long name.
    """
    name = " ".join(name.split())
    if not name or len(name) > MAX_NAME:
        raise ValueError(f"a name must have 1 to {MAX_NAME} characters, got {name!r}")
    names = read_names(semantic_json)
    if instance_id not in names:
        raise MapFormatError(f"{semantic_json} has no id {instance_id} (known: {sorted(names)[:20]} ...)")
    old = names[instance_id]
    names[instance_id] = name
    _write_names(semantic_json, names)
    return old


def _write_names(semantic_json: str, names: dict[int, str]) -> None:
    tmp = semantic_json + ".tmp"
    with open(tmp, "w") as fh:
        json.dump({"segmentation": [{"id": i, "class": c} for i, c in sorted(names.items())]}, fh, indent=1)
    os.replace(tmp, semantic_json)


STRUCTURE = ("floor", "wall", "ceiling")
UNLABELLED = "unlabelled"  # the class name of id 0 (Gaussians no labelling gave a class) for ``of_class``


def name_at(map_dir: str, point: tuple[float, float, float], name: str, radius: float = 0.12,
            of_class: str | Sequence[str] | None = None) -> tuple[int, int, str]:
    """Name the thing at ``point``: Gaussians of one class within ``radius`` metres of it get a new id called
    ``name`` (``params.npz``'s ``semantic_ids`` and ``semantic.json``, each replaced atomically;
    ``semantic.json`` first, so a reader never sees an id without a name).

    Args:
        map_dir: folder with ``params.npz`` and ``semantic.json``.
        point: world coordinates (the map's frame), metres.
        name: the name people use.
        radius: metres around ``point``.
        of_class: the class to take (e.g. ``object``; every id with that name), or several; ``unlabelled``
            (:data:`UNLABELLED`) takes the Gaussians without a class (id 0) unless the map has a class of that
            name. Default: the most common class near the point that is not floor, wall or ceiling (never id 0).

    Returns:
        (new id, Gaussians renamed, the class or classes they had, comma-separated).

    Raises:
        MapFormatError: unreadable files; no Gaussian of that class near the point.
        ValueError: a bad name, radius or point.
    """
    name = " ".join(name.split())
    if not name or len(name) > MAX_NAME:
        raise ValueError(f"a name must have 1 to {MAX_NAME} characters, got {name!r}")
    p = np.asarray(point, np.float64).reshape(-1)
    if p.shape != (3,) or not np.all(np.isfinite(p)) or not radius > 0:
        raise ValueError(f"need a finite point (x, y, z) and a radius > 0, got {point} and {radius}")
    sj = os.path.join(map_dir, "semantic.json")
    pz = os.path.join(map_dir, "params.npz")
    names = read_names(sj)
    try:
        with np.load(pz, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise MapFormatError(f"{pz}: not a readable map ({exc})") from exc
    if "means3D" not in arrays or "semantic_ids" not in arrays:
        raise MapFormatError(f"{pz} has no means3D / semantic_ids")
    ids = np.asarray(arrays["semantic_ids"]).reshape(-1)
    if ids.dtype.kind not in "iu":
        raise MapFormatError(f"{pz}: semantic_ids must be integers, got {ids.dtype}")
    where = f"({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f})"
    near = np.linalg.norm(arrays["means3D"].astype(np.float64) - p, axis=1) < radius
    if of_class is not None:
        wanted = [of_class] if isinstance(of_class, str) else list(of_class)
        if not wanted:
            raise ValueError("of_class: give at least one class name, or None")
        classes: list[str] = []
        want: list[int] = []
        for c in wanted:
            ids_c = [i for i, n in names.items() if n == c] or ([0] if c == UNLABELLED else [])
            if not ids_c:
                raise MapFormatError(f"the map has no class {c!r} (classes: {sorted(set(names.values()))}, "
                                     f"or {UNLABELLED!r} for Gaussians without one)")
            classes.append(c)
            want.extend(ids_c)
    else:
        cand, counts = np.unique(ids[near], return_counts=True)
        ok = [(n, int(i)) for i, n in zip(cand, counts, strict=True) if i > 0 and names.get(int(i)) not in STRUCTURE]
        if not ok:
            raise MapFormatError(f"nothing but floor, wall or ceiling within {radius} m of {where}")
        want = [max(ok)[1]]
        classes = [names.get(want[0], str(want[0]))]
    sel = near & np.isin(ids, want)
    if not sel.any():
        raise MapFormatError(f"no Gaussian of class {', '.join(map(repr, classes))} within {radius} m of {where}")
    new_id = max([*names, int(ids.max(initial=0))]) + 1
    names[new_id] = name
    _write_names(sj, names)
    out = ids.astype(np.int64) if new_id > np.iinfo(ids.dtype).max else ids.copy()
    out[sel] = new_id
    arrays["semantic_ids"] = out.reshape(np.asarray(arrays["semantic_ids"]).shape)  # [N] or [N, 1], as saved
    tmp = pz + ".tmp.npz"
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, pz)
    return new_id, int(sel.sum()), ", ".join(classes)


def point_at_pixel(map_dir: str, dataset: str, frame: int, pixel: tuple[float, float], window: int = 5,
                   layout: str = "auto", colour_calib: str = "auto") -> tuple[np.ndarray, float, int]:
    """Where the thing a person sees at pixel ``pixel`` of the colour image file of the dataset's frame ``frame`` is
    in the map's frame.

    The depth pixel that shows the same thing is found through the colour calibration (where colour is not
    registered to depth, e.g. 7-Scenes; else the pixel is moved to the depth image's size). Its depth is the
    median of the frame's valid depth in a ``window`` x ``window`` patch at the map's working size; the point is on
    the colour camera's ray through the pixel at that depth, moved by the map's own (estimated) pose of that frame,
    found by time stamp (``params.npz``'s ``timestamps``).

    Args:
        map_dir: folder with ``params.npz``.
        dataset: the sequence the map was built from.
        frame: the frame's position in the dataset's frame list (0-based; what ``--start``/``--stride`` count).
        pixel: (u, v), column and row in the frame's colour image file.
        window: odd patch size (depth pixels at the working size).
        layout: as in :func:`~semantic_gs_slam.datasets.load_dataset`.
        colour_calib: as in :func:`~semantic_gs_slam.datasets.load_dataset`: the one the run used.

    Returns:
        (point [3] float64 in the map's frame, depth in metres, the map's frame index).

    Raises:
        MapFormatError: an unreadable map, or one without time stamps, camera trajectory or intrinsics.
        DatasetError: an unreadable dataset.
        ValueError: a frame the map was not built from (or a dataset it was not built from), a pixel outside the
            image, no depth there.
    """
    from PIL import Image

    from semantic_gs_slam.io.colour_registration import colour_coords, scaled
    from semantic_gs_slam.io.datasets import load_dataset, scale_intrinsics
    from semantic_gs_slam.mapping.gaussian_map import load_params, trajectory_from_params

    if window < 1 or window % 2 == 0:
        raise ValueError(f"window must be odd and >= 1, got {window}")
    arrays = load_params(os.path.join(map_dir, "params.npz"))
    poses = trajectory_from_params(arrays)
    try:
        stamps = np.asarray(arrays["timestamps"], np.float64).reshape(-1)
        kmat = np.asarray(arrays["intrinsics"], np.float64).reshape(3, 3)
        width, height = int(arrays["org_width"]), int(arrays["org_height"])
    except KeyError as exc:
        what = ("no time stamp per frame, so its frames cannot be matched to the dataset's (maps written before time "
                "stamps were saved): give --at X Y Z instead") if exc.args[0] == "timestamps" else f"no {exc}"
        raise MapFormatError(f"{map_dir}: the map has {what}") from exc
    except (TypeError, ValueError) as exc:
        raise MapFormatError(f"{map_dir}: the map's time stamps, intrinsics or size are malformed ({exc})") from exc
    if len(stamps) != len(poses) or not len(poses):
        raise MapFormatError(f"{map_dir}: {len(poses)} camera poses but {len(stamps)} time stamps in the map")
    ds = load_dataset(dataset, layout, colour_calib=colour_calib)
    if not 0 <= frame < len(ds):
        raise ValueError(f"frame {frame} is not in the dataset ({len(ds)} frames: 0..{len(ds) - 1})")
    t = ds.timestamps[frame]
    j = int(np.argmin(np.abs(stamps - t)))
    if abs(stamps[j] - t) > 1e-3:
        step = f"{stamps[1] - stamps[0]:.3f} s apart" if len(stamps) > 1 else "one frame"
        raise ValueError(f"dataset frame {frame} (t = {t:.3f} s) is not one of the map's {len(stamps)} frames (t = "
                         f"{stamps[0]:.3f} .. {stamps[-1]:.3f} s, {step}): pick a frame the run used")
    native = ds.native_intrinsics
    k = scale_intrinsics(native, width, height)
    if not np.allclose([k.fx, k.fy, k.cx, k.cy], [kmat[0, 0], kmat[1, 1], kmat[0, 2], kmat[1, 2]], rtol=1e-4,
                       atol=1e-3):
        raise ValueError(f"the map's camera (fx {kmat[0, 0]:.2f}, cx {kmat[0, 2]:.2f} at {width}x{height}) is not this "
                         f"dataset's (fx {k.fx:.2f}, cx {k.cx:.2f}): was the map built from {dataset}?")
    gt = arrays.get("gt_w2c_all_frames")
    if gt is not None and ds.poses is not None and len(gt) == len(poses) and np.all(np.isfinite(gt[j])):
        if np.abs(np.asarray(gt[j], np.float64) @ ds.poses[frame] - np.eye(4)).max() > 1e-3:
            raise ValueError(f"dataset frame {frame}'s reference pose is not the one the map recorded for it: the map "
                             f"was built from another sequence than {dataset}")
    try:
        with Image.open(ds.rgb_paths[frame]) as im:
            cw, ch = im.size
    except OSError as exc:
        raise DatasetError(f"{ds.rgb_paths[frame]}: unreadable image ({exc})") from exc
    u, v = float(pixel[0]), float(pixel[1])
    if not (np.isfinite(u) and np.isfinite(v) and 0 <= u <= cw - 1 and 0 <= v <= ch - 1):
        raise ValueError(f"pixel ({pixel[0]}, {pixel[1]}) is outside frame {frame}'s {cw}x{ch} colour image")
    depth = ds.resized(width, height)[frame].depth  # [H, W] metres at the map's working size
    c = ds.colour_calib
    if c is None:  # colour registered to depth: the colour file's pixels are the depth camera's, at the file's size
        fx_c, fy_c = k.fx * cw / width, k.fy * ch / height
        cx_c, cy_c = (k.cx + 0.5) * cw / width - 0.5, (k.cy + 0.5) * ch / height - 0.5
        tx = ty = tz = 0.0
        ui, vi = int(round((u + 0.5) * width / cw - 0.5)), int(round((v + 0.5) * height / ch - 0.5))
        ui, vi = min(max(ui, 0), width - 1), min(max(vi, 0), height - 1)
    else:  # the colour camera at the colour file's own size; the depth pixel it sees nearest to the pixel (the
        # front-most of equally near ones: the colour camera sees the nearer surface)
        cal = scaled(c, cw / (c.width or cw), ch / (c.height or ch))
        fx_c, fy_c, cx_c, cy_c, tx, ty, tz = cal.fx, cal.fy, cal.cx, cal.cy, cal.tx, cal.ty, cal.tz
        cu, cv = colour_coords(depth, k.fx, k.fy, k.cx, k.cy, cal)
        d2 = np.where(depth > 0, (cu - u) ** 2 + (cv - v) ** 2, np.inf)
        best = float(d2.min())
        near = d2 <= best + 1.0
        cand = np.where(near, depth, np.inf)
        vi, ui = np.unravel_index(int(np.argmin(cand)), depth.shape)
        if not np.isfinite(best) or best > (2.0 * cw / width) ** 2:
            raise ValueError(f"no depth at pixel ({pixel[0]}, {pixel[1]}) of frame {frame}'s colour image: the depth "
                             "camera measured nothing there; pick a pixel nearby, or give --at X Y Z")
    r = window // 2
    patch = depth[max(vi - r, 0):vi + r + 1, max(ui - r, 0):ui + r + 1]
    d0 = float(depth[vi, ui])
    # the patch's depths on the pixel's own surface (a thin chair rail's, not the floor's behind it)
    valid = patch[(patch > 0) & (np.abs(patch - d0) < 0.05 + 0.02 * d0)] if d0 > 0 else patch[patch > 0]
    if valid.size == 0:
        raise ValueError(f"no depth around pixel ({pixel[0]}, {pixel[1]}) of frame {frame}: the sensor measured "
                         "nothing there; pick a pixel nearby, or give --at X Y Z")
    z = float(np.median(valid))
    zc = z + tz  # on the colour camera's ray through the pixel, at that depth (depth-camera point = colour - t)
    pc = np.array([(u - cx_c) / fx_c * zc - tx, (v - cy_c) / fy_c * zc - ty, z])
    c2w = poses[j]
    return c2w[:3, :3] @ pc + c2w[:3, 3], z, j


def main(argv: list[str] | None = None) -> int:
    """Command line (see the module docstring); returns the exit code."""
    ap = argparse.ArgumentParser(description="Name an object instance of a saved map.")
    ap.add_argument("--map", required=True, help="map folder (semantic.json inside)")
    ap.add_argument("--id", type=int, help="semantic id of the instance")
    ap.add_argument("--name", help="the name people use for it, e.g. 'my mug'")
    ap.add_argument("--at", type=float, nargs=3, metavar=("X", "Y", "Z"),
                    help="name the thing at this point of the map's frame instead of an id")
    ap.add_argument("--frame", type=int, help="with --pixel and --dataset: name the thing seen at a pixel of this "
                    "frame instead of --at (its 0-based position in the dataset's frame list, as --start counts)")
    ap.add_argument("--pixel", type=float, nargs=2, metavar=("U", "V"),
                    help="column and row in the frame's colour image file (its own size)")
    ap.add_argument("--dataset", help="the sequence the map was built from (for --frame)")
    ap.add_argument("--colour-calib", default="auto",
                    help="for --frame: the colour calibration the run used (auto, none or a file, as the run's)")
    ap.add_argument("--radius", type=float, default=0.12, help="metres around the point (default 0.12)")
    ap.add_argument("--of-class", action="append",
                    help=f"with --at or --frame: the class to take, repeatable; {UNLABELLED!r} = Gaussians without a "
                         "class (default: the most common non-structure class)")
    ap.add_argument("--list", action="store_true", help="print the ids and names")
    args = ap.parse_args(argv)
    path = os.path.join(args.map, "semantic.json")
    try:
        if args.list:
            for i, c in sorted(read_names(path).items()):
                print(f"{i:5d} {c}")
            return 0
        by_pixel = (args.frame, args.pixel, args.dataset)
        if any(a is not None for a in by_pixel) and (not all(a is not None for a in by_pixel) or args.at is not None):
            ap.error("--frame, --pixel and --dataset go together, instead of --at")
        if args.id is not None and (args.at is not None or args.frame is not None):
            ap.error("give --id, or a place (--at, or --frame/--pixel/--dataset), not both")
        at = tuple(args.at) if args.at is not None else None
        if args.frame is not None and args.name is not None:
            p, z, j = point_at_pixel(args.map, args.dataset, args.frame, tuple(args.pixel),
                                     colour_calib=args.colour_calib)
            at = tuple(round(float(c), 4) for c in p)
            print(f"frame {args.frame}, pixel ({args.pixel[0]:g}, {args.pixel[1]:g}): {z:.3f} m deep -> "
                  f"({at[0]:.3f}, {at[1]:.3f}, {at[2]:.3f}) in the map (its frame {j}'s pose)")
        if at is not None and args.name is not None:
            new_id, n, was = name_at(args.map, at, args.name, args.radius, args.of_class)
            print(f"{n} Gaussians of {was!r} within {args.radius} m of {at} -> id {new_id} {args.name!r}")
            return 0
        if args.id is None or args.name is None:
            ap.error("give --id and --name, --at X Y Z and --name, or --frame N --pixel U V --dataset DIR and --name "
                     "(or --list)")
        old = name_instance(path, args.id, args.name)
        print(f"id {args.id}: {old!r} -> {args.name!r}")
    except (SlamError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
