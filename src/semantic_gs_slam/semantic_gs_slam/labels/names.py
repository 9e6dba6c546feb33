"""Names from people: "this is my mug" given to an instance id sticks in the saved map.

The geometry stage gives every object its own semantic id (named ``object``); naming one rewrites its
entry in the map's ``semantic.json`` (atomically), so the object-query server finds it by the new name
after its next reload. Usage::

    python -m semantic_gs_slam.labels.names --map /tmp/kitchen_map --id 131 --name "my mug"
    python -m semantic_gs_slam.labels.names --map /tmp/kitchen_map --list
"""

from __future__ import annotations

import argparse
import json
import os
import sys

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
    tmp = semantic_json + ".tmp"
    with open(tmp, "w") as fh:
        json.dump({"segmentation": [{"id": i, "class": c} for i, c in sorted(names.items())]}, fh, indent=1)
    os.replace(tmp, semantic_json)
    return old


def main(argv: list[str] | None = None) -> int:
    """Command line (see the module docstring); returns the exit code."""
    ap = argparse.ArgumentParser(description="Name an object instance of a saved map.")
    ap.add_argument("--map", required=True, help="map folder (semantic.json inside)")
    ap.add_argument("--id", type=int, help="semantic id of the instance")
    ap.add_argument("--name", help="the name people use for it, e.g. 'my mug'")
    ap.add_argument("--list", action="store_true", help="print the ids and names")
    args = ap.parse_args(argv)
    path = os.path.join(args.map, "semantic.json")
    try:
        if args.list:
            for i, c in sorted(read_names(path).items()):
                print(f"{i:5d} {c}")
            return 0
        if args.id is None or args.name is None:
            ap.error("give --id and --name (or --list)")
        old = name_instance(path, args.id, args.name)
        print(f"id {args.id}: {old!r} -> {args.name!r}")
    except (SlamError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
