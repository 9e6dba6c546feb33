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
    python -m semantic_gs_slam.labels.names --map /tmp/kitchen_map --dataset SEQ --frame 465 --pixel 510 70 \
        --radius 0.3 --of-class wall --name tv
    python -m semantic_gs_slam.labels.names --map /tmp/kitchen_map --list

``--frame N --pixel U V`` (:func:`point_at_pixel`) is the point a person sees in one of the images the map was
built from: pixel (U, V) of the dataset's frame N, as the image file shows it, back-projected with that frame's
depth and the map's own pose of the frame (matched by time stamp).

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

from semantic_gs_slam.errors import MapFormatError, SlamError

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
                   layout: str = "auto") -> tuple[np.ndarray, float, int]:
    """Where pixel ``pixel`` of the dataset's frame ``frame`` is in the map's frame.

    The pixel is in the image file's own size (what a person sees when opening it); it is moved to the map's
    working size, its depth is the median of the frame's valid depth in a ``window`` x ``window`` patch there,
    and it is back-projected with the map's intrinsics and the map's own (estimated) pose of that frame, found
    by time stamp (``params.npz``'s ``timestamps``).

    Args:
        map_dir: folder with ``params.npz``. dataset: the sequence the map was built from. frame: its index
            there. pixel: (u, v), column and row. window: odd patch size. layout: as in ``load_dataset``.

    Returns:
        (point [3] float64 in the map's frame, depth in metres, the map's frame index).

    Raises:
        MapFormatError: an unreadable map, or one without time stamps or camera trajectory.
        DatasetError: an unreadable dataset.
        ValueError: a frame the map was not built from, a pixel outside the image, no depth around it.
    """
    from semantic_gs_slam.datasets import load_dataset
    from semantic_gs_slam.gaussian_map import load_params, trajectory_from_params

    if window < 1 or window % 2 == 0:
        raise ValueError(f"window must be odd and >= 1, got {window}")
    arrays = load_params(os.path.join(map_dir, "params.npz"))
    poses = trajectory_from_params(arrays)
    if "timestamps" not in arrays or len(arrays["timestamps"]) != len(poses):
        raise MapFormatError(f"{map_dir}: the map has no time stamp per frame, so its frames cannot be matched to "
                             "the dataset's (maps written before time stamps were saved): give --at X Y Z instead")
    stamps = np.asarray(arrays["timestamps"], np.float64)
    try:
        kmat = np.asarray(arrays["intrinsics"], np.float64).reshape(3, 3)
        width, height = int(arrays["org_width"]), int(arrays["org_height"])
    except (KeyError, ValueError) as exc:
        raise MapFormatError(f"{map_dir}: no camera intrinsics or size in the map ({exc})") from exc
    ds = load_dataset(dataset, layout, colour_calib="none")  # depth only: colour is not needed
    if not 0 <= frame < len(ds):
        raise ValueError(f"frame {frame} is not in the dataset ({len(ds)} frames: 0..{len(ds) - 1})")
    native = ds.native_intrinsics
    u, v = float(pixel[0]), float(pixel[1])
    if not (np.isfinite(u) and np.isfinite(v) and 0 <= u <= native.width - 1 and 0 <= v <= native.height - 1):
        raise ValueError(f"pixel ({pixel[0]}, {pixel[1]}) is outside frame {frame}'s {native.width}x{native.height} "
                         "image")
    t = ds.timestamps[frame]
    j = int(np.argmin(np.abs(stamps - t)))
    if abs(stamps[j] - t) > 1e-3:
        step = f"{stamps[1] - stamps[0]:.3f} s apart" if len(stamps) > 1 else "one frame"
        raise ValueError(f"dataset frame {frame} (t = {t:.3f} s) is not one of the map's {len(stamps)} frames (t = "
                         f"{stamps[0]:.3f} .. {stamps[-1]:.3f} s, {step}): pick a frame the run used")
    f = ds.resized(width, height)[frame]
    uw = (u + 0.5) * width / native.width - 0.5  # pixel-centre convention, as the intrinsics are scaled
    vw = (v + 0.5) * height / native.height - 0.5
    r, ui, vi = window // 2, int(round(uw)), int(round(vw))
    patch = f.depth[max(vi - r, 0):vi + r + 1, max(ui - r, 0):ui + r + 1]
    valid = patch[patch > 0]
    if valid.size == 0:
        raise ValueError(f"no depth around pixel ({pixel[0]}, {pixel[1]}) of frame {frame}: the sensor measured "
                         "nothing there; pick a pixel nearby, or give --at X Y Z")
    z = float(np.median(valid))
    pc = np.array([(uw - kmat[0, 2]) / kmat[0, 0] * z, (vw - kmat[1, 2]) / kmat[1, 1] * z, z])
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
                    "dataset frame instead of --at")
    ap.add_argument("--pixel", type=float, nargs=2, metavar=("U", "V"),
                    help="column and row in the frame's image file (its own size)")
    ap.add_argument("--dataset", help="the sequence the map was built from (for --frame)")
    ap.add_argument("--radius", type=float, default=0.12, help="metres around the point (default 0.12)")
    ap.add_argument("--of-class", action="append",
                    help=f"with --at: the class to take, repeatable; {UNLABELLED!r} = Gaussians without a class "
                         "(default: the most common non-structure class)")
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
        at = tuple(args.at) if args.at is not None else None
        if args.frame is not None and args.name is not None:
            p, z, j = point_at_pixel(args.map, args.dataset, args.frame, tuple(args.pixel))
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
