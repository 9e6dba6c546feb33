"""Loading a semantic Gaussian map and computing object centres (no ROS).

Map files follow the SplaTAM / SGS-SLAM layout:

* ``params.npz``: ``means3D`` [N, 3] float, ``semantic_ids`` [N] integer (other keys ignored);
* ``semantic.json``: ``{"segmentation": [{"id": 1, "class": "chair"}, ...]}``.
"""

from __future__ import annotations

import json
import math
import os
import zipfile
from dataclasses import dataclass

import numpy as np

from object_query.errors import MapLoadError


@dataclass(frozen=True)
class SemanticMap:
    """A loaded map: Gaussian centres with their semantic ids, and the id → class table."""

    means: np.ndarray  # [N, 3] float64, map frame, metres
    semantic_ids: np.ndarray  # [N] int64
    classes: dict[int, str]  # semantic id -> lower-cased class name


@dataclass(frozen=True)
class QueryResult:
    """Answer to "where is <name>?" in the shape of the ObjectQuery service."""

    found: bool
    position: tuple[float, float, float]
    message: str


def load_semantic_map(map_path: str, semantic_path: str) -> SemanticMap:
    """Load ``params.npz`` and ``semantic.json``.

    Args:
        map_path: path of the ``.npz`` archive.
        semantic_path: path of the ``.json`` class table.

    Returns:
        The map, with means as float64 [N, 3] and ids as int64 [N].

    Raises:
        MapLoadError: a file is missing or malformed; the message names the file and the problem.
    """
    if not os.path.isfile(map_path):
        raise MapLoadError(f"map file not found: map_path={map_path!r}")
    if not os.path.isfile(semantic_path):
        raise MapLoadError(f"semantic file not found: semantic_path={semantic_path!r}")
    try:
        with np.load(map_path, allow_pickle=False) as npz:
            missing = [k for k in ("means3D", "semantic_ids") if k not in npz.files]
            if missing:
                raise MapLoadError(
                    f"{map_path}: missing key(s) {missing}; found {sorted(npz.files)}"
                )
            means = np.asarray(npz["means3D"])
            ids = np.asarray(npz["semantic_ids"])
    except MapLoadError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise MapLoadError(f"{map_path}: not a readable .npz archive ({exc})") from exc
    if means.ndim != 2 or means.shape[1] != 3 or not np.issubdtype(means.dtype, np.number):
        raise MapLoadError(f"{map_path}: means3D must be a numeric [N, 3] array, got {means.shape} {means.dtype}")
    ids = ids.reshape(-1) if ids.ndim == 2 and 1 in ids.shape else ids
    if ids.ndim != 1 or not np.issubdtype(ids.dtype, np.integer):
        raise MapLoadError(f"{map_path}: semantic_ids must be an integer [N] array, got {ids.shape} {ids.dtype}")
    if len(ids) != len(means):
        raise MapLoadError(f"{map_path}: means3D has {len(means)} rows but semantic_ids has {len(ids)}")
    classes = load_classes(semantic_path)
    return SemanticMap(means.astype(np.float64, copy=False), ids.astype(np.int64, copy=False), classes)


def load_classes(semantic_path: str) -> dict[int, str]:
    """Read the ``{"segmentation": [{"id", "class"}]}`` table into ``{id: lower-cased name}``."""
    try:
        with open(semantic_path, encoding="utf-8") as fh:
            doc = json.load(fh)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise MapLoadError(f"{semantic_path}: not valid JSON ({exc})") from exc
    entries = doc.get("segmentation") if isinstance(doc, dict) else None
    if not isinstance(entries, list):
        raise MapLoadError(f'{semantic_path}: expected {{"segmentation": [{{"id": ..., "class": ...}}]}}')
    classes: dict[int, str] = {}
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict) or "id" not in entry or "class" not in entry:
            raise MapLoadError(f"{semantic_path}: segmentation[{i}] needs 'id' and 'class'")
        sid, name = entry["id"], entry["class"]
        if isinstance(sid, bool) or not isinstance(sid, int) or not isinstance(name, str) or not name.strip():
            raise MapLoadError(f"{semantic_path}: segmentation[{i}] has a bad id/class ({sid!r}, {name!r})")
        if sid in classes:
            raise MapLoadError(f"{semantic_path}: duplicate id {sid} ({classes[sid]!r} and {name!r})")
        classes[sid] = name.strip().lower()
    return classes


def compute_centroids(semantic_map: SemanticMap) -> dict[str, np.ndarray]:
    """Mean position of each class's points, in one O(N) pass (``np.bincount``).

    Classes of the table without points are left out. Several ids with one class name are
    merged. Returns ``{name: [3] float64}``.
    """
    ids = semantic_map.semantic_ids
    if len(ids) == 0:
        return {}
    offset = int(ids.min())
    idx = ids - offset  # [N] >= 0
    size = int(idx.max()) + 1
    counts = np.bincount(idx, minlength=size).astype(np.float64)  # [K]
    sums = np.stack(
        [np.bincount(idx, weights=semantic_map.means[:, k], minlength=size) for k in range(3)], axis=1
    )  # [K, 3]
    by_name_sum: dict[str, np.ndarray] = {}
    by_name_count: dict[str, float] = {}
    for sid, name in semantic_map.classes.items():
        j = sid - offset
        if 0 <= j < size and counts[j] > 0:
            by_name_sum[name] = by_name_sum.get(name, 0.0) + sums[j]
            by_name_count[name] = by_name_count.get(name, 0.0) + counts[j]
    return {name: by_name_sum[name] / by_name_count[name] for name in by_name_sum}


class ObjectDatabase:
    """Object name → centre, queried case-insensitively."""

    def __init__(self, centroids: dict[str, np.ndarray]) -> None:
        self._centroids = {name.lower(): np.asarray(c, dtype=np.float64) for name, c in centroids.items()}

    @classmethod
    def from_files(cls, map_path: str, semantic_path: str) -> ObjectDatabase:
        return cls(compute_centroids(load_semantic_map(map_path, semantic_path)))

    def names(self) -> list[str]:
        return sorted(self._centroids)

    def query(self, name: str) -> QueryResult:
        key = " ".join(str(name).split()).lower()
        if not key:
            return QueryResult(False, (0.0, 0.0, 0.0), "empty object name")
        centre = self._centroids.get(key)
        if centre is None:
            shown = key if len(key) <= 64 else key[:61] + "..."
            return QueryResult(False, (0.0, 0.0, 0.0), f"unknown object {shown!r}; known: {', '.join(self.names())}")
        x, y, z = (float(v) for v in centre)
        return QueryResult(True, (x, y, z), f"{key} at ({x:.3f}, {y:.3f}, {z:.3f})")

    def to_json(self) -> str:
        """``{"chair": [x, y, z], ...}`` with finite floats rounded to mm."""
        items = sorted(self._centroids.items())
        return json.dumps({n: [round(float(v), 4) if math.isfinite(v) else None for v in c] for n, c in items})
