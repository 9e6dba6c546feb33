"""Loading a semantic Gaussian map and building the object database (no ROS).

Map files follow the SplaTAM / SGS-SLAM layout:

* ``params.npz``: ``means3D`` [N, 3] float and ``semantic_ids`` [N] (or [N, 1]) integer (SGS-SLAM
  saves uint8); optional ``logit_opacities`` [N] or [N, 1]; every other key (``rgb_colors``,
  ``unnorm_rotations``, ``log_scales``, ``semantic_colors``, ...) is ignored;
* ``semantic.json``: ``{"segmentation": [{"id": 1, "class": "chair"}, ...]}``.

:class:`ObjectDatabase` is immutable: a reload builds a new one and swaps the reference.
"""

from __future__ import annotations

import json
import math
import os
import re
import time
import zipfile
import zlib
from dataclasses import dataclass, field

import numpy as np

from object_query.errors import MapLoadError
from object_query.instances import _Ticker, split_instances
from object_query.kernels import bin_sums, bin_sums_chunked
from object_query.names import (
    MAX_COORD_M,
    MAX_NAME_LENGTH,
    Synonyms,
    closest_names,
    normalise_name,
    shorten,
    singular_forms,
)

#: Known-names list shown in "unknown object" messages is cut after this many names.
_MAX_LISTED_NAMES = 20
CENTRE_METHODS = ("mean", "median", "trimmed_mean")
#: ``chair#2`` / ``chair #2``: one instance of a class.
_INSTANCE_LABEL = re.compile(r"^(.+?)\s*#\s*(\d{1,6})$")
QUERY_POSITIONS = ("largest", "class")
#: Appended to every answer of a provisional database.
PROVISIONAL_NOTE = "provisional: the centre of all of the class's points; instances are still being built"


@dataclass(frozen=True)
class SemanticMap:
    """A loaded map: Gaussian centres with their semantic ids, and the id → class table."""

    means: np.ndarray  # [N, 3] float32 or float64, map frame, metres
    semantic_ids: np.ndarray  # [N] integer (dtype as saved, e.g. uint8)
    classes: dict[int, str]  # semantic id -> normalised class name
    logit_opacities: np.ndarray | None = None  # [N] float, None when the map has none
    warnings: tuple[str, ...] = ()  # non-fatal problems found while loading
    votes: np.ndarray | None = None  # [N, C] label votes over views (``semantic_votes``), None when the map has none
    vote_ids: np.ndarray | None = None  # [C] semantic id of each vote column (``semantic_feature_ids``)


@dataclass(frozen=True)
class QueryResult:
    """Answer to "where is <name>?" in the shape of the ObjectQuery service."""

    found: bool
    position: tuple[float, float, float]
    message: str


@dataclass(frozen=True)
class ObjectInstance:
    """One spatially connected object of a class."""

    name: str  # class name
    index: int  # 1-based, largest first within the class
    centre: tuple[float, float, float]
    bbox_min: tuple[float, float, float]
    bbox_max: tuple[float, float, float]
    point_count: int

    @property
    def label(self) -> str:
        """``chair#2``."""
        return f"{self.name}#{self.index}"


@dataclass(frozen=True)
class InstancesResult:
    """Answer to "which <name>s are there?": instances nearest first when a reference is given."""

    found: bool
    name: str  # the class the query resolved to ("" when not found)
    message: str
    instances: tuple[ObjectInstance, ...] = ()
    distances: tuple[float, ...] = ()  # to the reference, metres; -1.0 each without a reference


@dataclass(frozen=True)
class DatabaseConfig:
    """How a map becomes a database.

    Attributes:
        voxel_size: voxel edge (m) of instance splitting; points of one class in touching voxels
            (26-neighbourhood) form one instance. Objects closer than this merge.
        min_instance_points: connected components with fewer points are noise (floaters).
        min_opacity: Gaussians with ``sigmoid(logit_opacity)`` below this are ignored
            (0 keeps all); used only when the map has ``logit_opacities``.
        centre_method: ``mean``, ``median`` (per axis) or ``trimmed_mean`` (mean after dropping
            the ``trim_fraction`` of points farthest from the mean).
        trim_fraction: fraction dropped by ``trimmed_mean``, in [0, 0.5).
        query_position: what ``/object_query`` answers for a class with several instances:
            ``largest`` (the instance with most points) or ``class`` (the centre of all of the
            class's instance points, as the seed did).
        min_label_views: an instance is kept only when one of its points carried its class in at
            least this many views (the map's ``semantic_votes``: one vote per view that saw the
            Gaussian unoccluded and labelled it); instances below are dropped, and a class left
            without instances is dropped (a warning names them). On a short map the threshold is
            at most an eighth of the views of its best-seen Gaussian (``LABEL_VIEWS_SHARE``), and at
            least 1. One-off detector errors name a
            place in a view or two, real objects are named in most views that see them. 0 turns
            the rule off; maps without ``semantic_votes`` are not filtered.
    """

    voxel_size: float = 0.1
    min_instance_points: int = 20
    min_opacity: float = 0.05
    centre_method: str = "mean"
    trim_fraction: float = 0.1
    query_position: str = "largest"
    min_label_views: int = 5

    def __post_init__(self) -> None:
        if not (math.isfinite(self.voxel_size) and self.voxel_size > 0):
            raise ValueError(f"voxel_size must be > 0, got {self.voxel_size}")
        if self.min_instance_points < 1:
            raise ValueError(f"min_instance_points must be >= 1, got {self.min_instance_points}")
        if not 0.0 <= self.min_opacity < 1.0:
            raise ValueError(f"min_opacity must be in [0, 1), got {self.min_opacity}")
        if self.centre_method not in CENTRE_METHODS:
            raise ValueError(f"centre_method must be one of {CENTRE_METHODS}, got {self.centre_method!r}")
        if not 0.0 <= self.trim_fraction < 0.5:
            raise ValueError(f"trim_fraction must be in [0, 0.5), got {self.trim_fraction}")
        if isinstance(self.min_label_views, bool) or not isinstance(self.min_label_views, int) \
                or self.min_label_views < 0:
            raise ValueError(f"min_label_views must be an integer >= 0, got {self.min_label_views!r}")
        if self.query_position not in QUERY_POSITIONS:
            raise ValueError(f"query_position must be one of {QUERY_POSITIONS}, got {self.query_position!r}")


# ---------------------------------------------------------------------------------------------
# loading


def load_semantic_map(map_path: str, semantic_path: str) -> SemanticMap:
    """Load ``params.npz`` and ``semantic.json``, checking keys, shapes and dtypes.

    Args:
        map_path: path of the ``.npz`` archive.
        semantic_path: path of the ``.json`` class table.

    Returns:
        The map; ``means`` and ``semantic_ids`` keep their saved dtypes (no copies).

    Raises:
        MapLoadError: a file is missing or malformed; the message names the parameter or the
            file and the problem.
    """
    if not os.path.isfile(map_path):
        raise MapLoadError(f"map file not found: map_path={map_path!r}")
    if not os.path.isfile(semantic_path):
        raise MapLoadError(f"semantic file not found: semantic_path={semantic_path!r}")
    warnings: list[str] = []
    try:
        with np.load(map_path, allow_pickle=False) as npz:
            missing = [k for k in ("means3D", "semantic_ids") if k not in npz.files]
            if missing:
                raise MapLoadError(f"{map_path}: missing key(s) {missing}; found {sorted(npz.files)}")
            means = np.asarray(npz["means3D"])
            ids = np.asarray(npz["semantic_ids"])
            opac = np.asarray(npz["logit_opacities"]) if "logit_opacities" in npz.files else None
            votes = np.asarray(npz["semantic_votes"]) if "semantic_votes" in npz.files else None
            vote_ids = np.asarray(npz["semantic_feature_ids"]) if "semantic_feature_ids" in npz.files else None
    except MapLoadError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError, zlib.error) as exc:
        raise MapLoadError(f"{map_path}: not a readable .npz archive ({exc})") from exc
    if means.ndim != 2 or means.shape[1] != 3 or means.dtype.kind not in "fiu":
        raise MapLoadError(f"{map_path}: means3D must be a real [N, 3] array, got shape {means.shape} {means.dtype}")
    if ids.ndim == 2 and ids.shape[1] == 1:
        ids = ids[:, 0]
    if ids.ndim != 1 or ids.dtype.kind not in "iu":
        raise MapLoadError(f"{map_path}: semantic_ids must be an integer [N] array, got shape {ids.shape} {ids.dtype}")
    if len(ids) != len(means):
        raise MapLoadError(f"{map_path}: length mismatch: means3D has {len(means)} rows, semantic_ids {len(ids)}")
    if ids.dtype.kind == "u" and ids.dtype.itemsize == 8 and len(ids) and int(ids.max()) > np.iinfo(np.int64).max:
        raise MapLoadError(f"{map_path}: semantic_ids up to {int(ids.max())}; ids must fit a signed 64-bit integer "
                           f"(at most {np.iinfo(np.int64).max})")
    if opac is not None:
        if opac.ndim == 2 and opac.shape[1] == 1:
            opac = opac[:, 0]
        if opac.shape != (len(means),) or opac.dtype.kind not in "fiu":
            warnings.append(f"{map_path}: ignoring logit_opacities of shape {opac.shape} {opac.dtype} "
                            f"(expected [{len(means)}] or [{len(means)}, 1])")
            opac = None
    if votes is None:  # (a map without votes, e.g. with only semantic_feature_ids: nothing to judge)
        vote_ids = None
    elif (vote_ids is None or vote_ids.ndim != 1 or vote_ids.dtype.kind not in "iu"
            or votes.shape != (len(means), len(vote_ids)) or votes.dtype.kind not in "fiu"):
        warnings.append(f"{map_path}: ignoring semantic_votes of shape {votes.shape} with semantic_feature_ids of "
                        f"shape {getattr(vote_ids, 'shape', None)} (expected [N, C] and [C])")
        votes = vote_ids = None
    classes = load_classes(semantic_path, warnings)
    return SemanticMap(means, ids, classes, opac, tuple(warnings), votes, vote_ids)


def load_classes(semantic_path: str, warnings: list[str] | None = None) -> dict[int, str]:
    """Read the ``{"segmentation": [{"id", "class"}]}`` table into ``{id: normalised name}``.

    Several ids may share a class name (their points are one class). An id listed twice with
    the same name is a warning; with two different names it is an error.

    Args:
        semantic_path: path of the JSON file.
        warnings: non-fatal problems are appended here.

    Raises:
        MapLoadError: unreadable or malformed JSON, bad entries, conflicting duplicate ids.
    """
    try:
        with open(semantic_path, encoding="utf-8") as fh:
            doc = json.load(fh)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise MapLoadError(f"{semantic_path}: not valid JSON ({str(exc)[:200]})") from exc
    entries = doc.get("segmentation") if isinstance(doc, dict) else None
    if not isinstance(entries, list):
        raise MapLoadError(f'{semantic_path}: expected {{"segmentation": [{{"id": ..., "class": ...}}]}}')
    classes: dict[int, str] = {}
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict) or "id" not in entry or "class" not in entry:
            raise MapLoadError(f"{semantic_path}: segmentation[{i}] needs 'id' and 'class', got {entry!r:.80}")
        sid, raw = entry["id"], entry["class"]
        name = normalise_name(raw) if isinstance(raw, str) else ""
        if isinstance(sid, bool) or not isinstance(sid, int) or not name or len(name) > MAX_NAME_LENGTH:
            raise MapLoadError(f"{semantic_path}: segmentation[{i}] has a bad id/class ({sid!r}, {raw!r:.80})")
        if sid in classes:
            if classes[sid] != name:
                raise MapLoadError(f"{semantic_path}: duplicate id {sid} with two classes ({classes[sid]!r}, {name!r})")
            if warnings is not None:
                warnings.append(f"{semantic_path}: id {sid} ({name!r}) is listed twice")
            continue
        classes[sid] = name
    return classes


# ---------------------------------------------------------------------------------------------
# centroids


def class_labels(ids: np.ndarray, classes: dict[int, str]) -> tuple[np.ndarray, list[str]]:
    """Map semantic ids to compact labels of distinct class names, in O(N).

    Args:
        ids: [N] integer semantic ids.
        classes: id → class name.

    Returns:
        ``(labels, names)``: labels [N] int32 in [0, K], K = ``len(names)`` meaning "id not in
        the table"; names sorted.
    """
    names = sorted(set(classes.values()))
    k = len(names)
    label_of = {n: i for i, n in enumerate(names)}
    if len(ids) == 0:
        return np.empty(0, dtype=np.int32), names
    if ids.dtype.kind == "u" and ids.dtype.itemsize <= 2:
        lo, size = 0, 1 << (8 * ids.dtype.itemsize)
        rel = ids
    else:
        lo, hi = int(ids.min()), int(ids.max())
        size = hi - lo + 1
        rel = None
    if size <= 1 << 22:
        table = np.full(size, k, dtype=np.int32)  # int32 labels: half the memory traffic of int64
        for sid, name in classes.items():
            if 0 <= sid - lo < size:
                table[sid - lo] = label_of[name]
        return table[rel if rel is not None else ids.astype(np.intp) - lo], names  # (no int8 overflow)
    known = np.array(sorted(classes), dtype=np.int64)
    lab = np.array([label_of[classes[s]] for s in known.tolist()] + [k], dtype=np.int32)
    pos = np.searchsorted(known, ids)
    hit = (pos < len(known)) & (known[np.minimum(pos, len(known) - 1)] == ids)
    return np.where(hit, lab[np.minimum(pos, len(known))], k), names


def compute_centroids(semantic_map: SemanticMap, valid: np.ndarray | None = None,
                      fast: bool | None = None) -> dict[str, np.ndarray]:
    """Mean position of each class's points, in one O(N) pass (:func:`kernels.bin_sums`).

    Args:
        semantic_map: the map.
        valid: [N] bool, points to use; None uses all.
        fast: the compiled kernel (True), the numpy reference (False), or automatic (None).

    Returns:
        ``{name: [3] float64}`` for classes with at least one (valid) point; several ids with one
        class name are merged; ids absent from the table are ignored.
    """
    ids = semantic_map.semantic_ids
    if len(ids) == 0:
        return {}
    # bins = the ids themselves (offset by the smallest): no per-point label lookup, one cast
    lo = 0 if ids.dtype.kind == "u" else int(ids.min())
    size = int(ids.max()) - lo + 1
    if size > 1 << 22:  # sparse huge ids: go through compact labels instead
        labels, names = class_labels(ids, semantic_map.classes)
        bins, bin_names, size = labels, {j: [n] for j, n in enumerate(names)}, len(names) + 1
    else:
        bins = ids.astype(np.intp)  # [N]
        if lo:
            bins -= lo
        bin_names = {}
        for sid, name in semantic_map.classes.items():
            bin_names.setdefault(sid - lo, []).append(name)
    if valid is not None:
        bins = np.where(valid, bins, size)
    counts, sums = bin_sums(bins, semantic_map.means, size, fast)  # [B], [B, 3]
    total: dict[str, list] = {}
    for b, names_of_bin in bin_names.items():
        if 0 <= b < size and counts[b] > 0:
            for name in names_of_bin:
                acc = total.setdefault(name, [np.zeros(3), 0])
                acc[0] = acc[0] + sums[b]
                acc[1] += int(counts[b])
    return {name: acc[0] / acc[1] for name, acc in total.items()}


def compute_centroids_masked(semantic_map: SemanticMap) -> dict[str, np.ndarray]:
    """The seed's method: one boolean mask over all N points per class (O(N·K)).

    Kept as the test reference and the benchmark baseline of :func:`compute_centroids`.
    """
    out: dict[str, list[np.ndarray]] = {}
    for sid, name in semantic_map.classes.items():
        mask = semantic_map.semantic_ids == sid
        if mask.any():
            out.setdefault(name, []).append(semantic_map.means[mask].astype(np.float64))
    return {name: np.concatenate(parts).mean(axis=0) for name, parts in out.items()}


# ---------------------------------------------------------------------------------------------
# database


def _tuple3(v: np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


def _robust_centres(means: np.ndarray, point_instance: np.ndarray, counts: np.ndarray, config: DatabaseConfig
                    ) -> np.ndarray:
    """Median or trimmed-mean centre per instance ([I, 3]); sorts points by instance (O(N log N))."""
    sel = np.flatnonzero(point_instance >= 0)
    order = sel[np.argsort(point_instance[sel], kind="stable")]
    bounds = np.concatenate([[0], np.cumsum(counts)])
    out = np.empty((len(counts), 3))
    for i in range(len(counts)):
        pts = means[order[bounds[i]:bounds[i + 1]]].astype(np.float64)  # [n_i, 3]
        if config.centre_method == "median":
            out[i] = np.median(pts, axis=0)
        else:
            centre = pts.mean(axis=0)
            dist = np.linalg.norm(pts - centre, axis=1)
            keep = max(1, int(math.ceil(len(pts) * (1.0 - config.trim_fraction))))
            nearest = np.argpartition(dist, keep - 1)[:keep] if keep < len(pts) else slice(None)
            out[i] = pts[nearest].mean(axis=0)
    return out


#: A short map cannot give ``min_label_views`` views: the threshold is at most this share of the views of the map's
#: best-seen Gaussian (its total votes), and at least 1.
LABEL_VIEWS_SHARE = 1 / 8


def label_views_threshold(votes: np.ndarray, min_views: int) -> int:
    """The views an instance needs on a map with these ``votes`` [N, C]: ``min_views``, or fewer on a short map."""
    if min_views <= 0 or len(votes) == 0:
        return 0
    most = float(votes.sum(axis=1).max())
    return int(max(1, min(min_views, math.floor(most * LABEL_VIEWS_SHARE))))


def _own_votes(smap: SemanticMap, sel: np.ndarray) -> np.ndarray:
    """Votes of the points ``sel`` [M] for their own class [M] (inf where the id has no vote column: not judged)."""
    col_of = {int(s): j for j, s in enumerate(smap.vote_ids.tolist())}
    uniq, inv = np.unique(smap.semantic_ids[sel], return_inverse=True)  # few distinct ids
    cols = np.array([col_of.get(int(u), -1) for u in uniq.tolist()], np.int64)[inv.reshape(-1)]  # [M], -1: none
    own = np.full(len(sel), np.inf)
    has = cols >= 0
    own[has] = smap.votes[sel[has], cols[has]]
    return own


def _label_support(smap: SemanticMap, split, min_views: int) -> tuple[np.ndarray, int]:
    """([I] bool, threshold): instances with a point whose votes for its own class reach the threshold
    (:func:`label_views_threshold`; all True when the rule is off or the map has no votes; a class without a vote
    column is not judged)."""
    n_inst = len(split.instance_count)
    if min_views <= 0 or smap.votes is None or smap.vote_ids is None or n_inst == 0:
        return np.ones(n_inst, bool), 0
    min_views = label_views_threshold(smap.votes, min_views)
    pi = split.point_instance
    sel = np.flatnonzero(pi >= 0)  # the instances' points only
    own = _own_votes(smap, sel)
    best = np.full(n_inst, -np.inf)
    np.maximum.at(best, pi[sel], own)
    return best >= min_views, min_views


@dataclass(frozen=True)
class MapStats:
    """Counts of what a build used and skipped."""

    points: int = 0
    used: int = 0
    non_finite: int = 0
    transparent: int = 0
    unlabelled: int = 0
    noise: int = 0
    unsupported: int = 0  # points of instances dropped by ``min_label_views``
    build_s: float = 0.0


class ObjectDatabase:
    """Object name → instances and a query position; immutable, safe to share between threads.

    Build one with :meth:`from_files` / :meth:`from_map`; ``ObjectDatabase({"chair": (x, y, z)})``
    makes a database of one instance per name (handy in tests of other packages).
    """

    def __init__(
        self,
        centroids: dict[str, np.ndarray | tuple[float, float, float]],
        instances: dict[str, tuple[ObjectInstance, ...]] | None = None,
        synonyms: Synonyms | None = None,
        warnings: tuple[str, ...] = (),
        stats: MapStats | None = None,
        class_centroids: dict[str, tuple[float, float, float]] | None = None,
        provisional: bool = False,
    ) -> None:
        self._positions = {normalise_name(n): _tuple3(np.asarray(c, dtype=np.float64)) for n, c in centroids.items()}
        if instances is None:
            instances = {n: (ObjectInstance(n, 1, p, p, p, 0),) for n, p in self._positions.items()}
        #: the mean of each class's used points (all its instances together)
        self.class_centroids = dict(class_centroids) if class_centroids is not None else dict(self._positions)
        #: True for the quick database of class centroids served while the instances are built
        self.provisional = provisional
        self._instances = dict(instances)
        self._synonyms = synonyms or Synonyms()
        self.warnings = tuple(warnings)
        self.stats = stats or MapStats()
        self._names = sorted(self._positions)

    @classmethod
    def from_files(cls, map_path: str, semantic_path: str, config: DatabaseConfig | None = None,
                   synonyms: Synonyms | None = None) -> ObjectDatabase:
        """Load both files and build the database (see :meth:`from_map`).

        Raises:
            MapLoadError: a file is missing or malformed.
        """
        return cls.from_map(load_semantic_map(map_path, semantic_path), config, synonyms)

    @classmethod
    def provisional_from_map(cls, semantic_map: SemanticMap, config: DatabaseConfig | None = None,
                             synonyms: Synonyms | None = None) -> ObjectDatabase:
        """The quick database: one position per class, the mean of its points, in one fused pass.

        Served while :meth:`from_map` splits the instances (seconds on a 10 M map). The points
        used are those :meth:`from_map` uses before instance splitting (finite, opaque enough,
        id in the table), so a class's position here equals ``class_centroids`` of the full
        database up to the points that the split drops as noise (components smaller than
        ``min_instance_points``). Answers say that they are provisional.
        """
        t0 = time.perf_counter()
        config = config or DatabaseConfig()
        smap = semantic_map
        ids, means, opac = smap.semantic_ids, smap.means, smap.logit_opacities  # [N], [N, 3], [N] or None
        check_finite = means.dtype.kind == "f"
        logit_min = (math.log(config.min_opacity / (1.0 - config.min_opacity))
                     if opac is not None and config.min_opacity > 0 else None)

        def valid(start: int, stop: int) -> np.ndarray:  # [stop - start] bool
            ok = np.isfinite(means[start:stop]).all(axis=1) if check_finite else np.ones(stop - start, bool)
            if logit_min is not None:
                ok &= opac[start:stop] >= logit_min  # NaN opacity is transparent
            return ok

        use_valid = check_finite or logit_min is not None
        if len(ids) == 0:
            centroids: dict[str, np.ndarray] = {}
            used = 0
        else:
            small_unsigned = ids.dtype.kind == "u" and ids.dtype.itemsize <= 2
            lo = 0 if small_unsigned else int(ids.min())
            size = (1 << (8 * ids.dtype.itemsize)) if small_unsigned else int(ids.max()) - lo + 1
            if size > 1 << 22:  # sparse huge ids: the compact-label path
                step = 1 << 20
                mask = np.concatenate([valid(s, min(s + step, len(ids))) for s in range(0, len(ids), step)])
                finite_means = np.where(mask[:, None], means, 0).astype(means.dtype) if check_finite else means
                centroids = compute_centroids(SemanticMap(finite_means, ids, smap.classes, None), mask)
                used = int(np.count_nonzero(mask))
            else:
                counts, sums = bin_sums_chunked(ids, means, lo, size, valid if use_valid else None)
                total: dict[str, list] = {}
                for sid, name in smap.classes.items():
                    b = sid - lo
                    if 0 <= b < size and counts[b] > 0:
                        acc = total.setdefault(name, [np.zeros(3), 0])
                        acc[0] = acc[0] + sums[b]
                        acc[1] += int(counts[b])
                centroids = {name: acc[0] / acc[1] for name, acc in total.items()}
                used = sum(acc[1] for acc in total.values())
        stats = MapStats(points=len(ids), used=used, build_s=time.perf_counter() - t0)
        return cls(centroids, None, synonyms, smap.warnings, stats, provisional=True)

    @classmethod
    def from_map(cls, semantic_map: SemanticMap, config: DatabaseConfig | None = None,
                 synonyms: Synonyms | None = None, timings: dict[str, float] | None = None) -> ObjectDatabase:
        """Split every class into instances and compute their centres and boxes.

        Points are skipped when their coordinates are not finite (counted in a warning), when
        they are near-transparent (``config.min_opacity``), or when their id is not in the table
        (warning); classes of the table without points get a warning. ``timings``, when given,
        receives the seconds of each stage.
        """
        t0 = time.perf_counter()
        tick = _Ticker(timings)
        config = config or DatabaseConfig()
        warnings = list(semantic_map.warnings)
        means = semantic_map.means  # [N, 3]
        if means.dtype not in (np.float32, np.float64):
            means = means.astype(np.float64)
        n = len(means)
        labels, names = class_labels(semantic_map.semantic_ids, semantic_map.classes)  # [N]
        k = len(names)

        unlabelled = int(np.count_nonzero(labels == k))
        if unlabelled:
            ids = semantic_map.semantic_ids[labels == k]
            uniq, cnt = np.unique(ids, return_counts=True)
            listed = ", ".join(f"{int(u)} ({int(c)} pts)" for u, c in zip(uniq[:10], cnt[:10], strict=True))
            more = f" and {len(uniq) - 10} more" if len(uniq) > 10 else ""
            warnings.append(f"ignored {unlabelled} point(s) whose semantic id is not in the class table: "
                            f"id {listed}{more}")
        if means.dtype.kind != "f" or np.isfinite(means).all():  # one fast pass in the common case
            non_finite = 0
        else:
            finite = np.isfinite(means).all(axis=1)  # [N]
            non_finite = int(n - np.count_nonzero(finite))
            warnings.append(f"skipped {non_finite} point(s) with NaN/inf coordinates")
            means = np.where(finite[:, None], means, 0).astype(means.dtype)  # ignored below
            labels = np.where(finite, labels, k)
        transparent = 0
        if semantic_map.logit_opacities is not None and config.min_opacity > 0:
            logit_min = math.log(config.min_opacity / (1.0 - config.min_opacity))
            transparent_mask = ~(semantic_map.logit_opacities >= logit_min)  # NaN opacity is transparent
            transparent = int(np.count_nonzero(transparent_mask & (labels < k)))
            labels = np.where(transparent_mask, k, labels)
        tick("labels and validity")

        try:
            split = split_instances(means, labels, None, k, config.voxel_size, config.min_instance_points, timings)
        except ValueError as exc:  # e.g. far-away points: a map this database cannot grid
            raise MapLoadError(str(exc)) from exc
        counts = split.instance_count
        supported, min_views = _label_support(semantic_map, split, config.min_label_views)  # [I] bool
        unsupported = inst_unsupported = int(counts[~supported].sum())
        if config.centre_method == "mean" or len(counts) == 0:
            centres = split.instance_sum / np.maximum(counts, 1)[:, None]
        else:
            centres = _robust_centres(means, split.point_instance, counts, config)

        by_class: dict[str, list[ObjectInstance]] = {}
        class_sum: dict[str, np.ndarray] = {}
        dropped: dict[str, int] = {}
        for i in range(len(counts)):
            name = names[int(split.instance_label[i])]
            if not supported[i]:
                dropped[name] = dropped.get(name, 0) + 1
                continue
            group = by_class.setdefault(name, [])
            group.append(ObjectInstance(name, len(group) + 1, _tuple3(centres[i]), _tuple3(split.instance_min[i]),
                                        _tuple3(split.instance_max[i]), int(counts[i])))
            class_sum[name] = class_sum.get(name, 0.0) + split.instance_sum[i]

        # a class whose points are all in small components (a small object seen from afar: a cup at a low camera
        # resolution) still gets instances: its components, however small, largest first. Not all of its points as
        # one instance: two cups across the room would be answered by the empty space between them.
        valid_count = np.bincount(labels, minlength=k + 1)[:k]
        for j in np.flatnonzero(valid_count > 0):
            name = names[j]
            if name in by_class or name in dropped:
                continue
            if min_views and _own_votes(semantic_map, np.flatnonzero(labels == j)).max() < min_views:
                dropped[name] = dropped.get(name, 0) + 1  # scattered points, none named in enough views
                unsupported += int(valid_count[j])
                continue
            pts = means[labels == j].astype(np.float64)
            small = split_instances(pts, np.zeros(len(pts), np.int64), None, 1, config.voxel_size, 1)
            centres_j = small.instance_sum / np.maximum(small.instance_count, 1)[:, None]
            by_class[name] = [ObjectInstance(name, i + 1, _tuple3(centres_j[i]), _tuple3(small.instance_min[i]),
                                             _tuple3(small.instance_max[i]), int(small.instance_count[i]))
                              for i in range(len(small.instance_count))]
            class_sum[name] = pts.sum(axis=0)
            warnings.append(f"class {name!r} has only {len(pts)} scattered point(s) (no component of "
                            f"{config.min_instance_points}+ points); answering with its {len(small.instance_count)} "
                            f"small component(s), largest first ({int(small.instance_count[0])} points)")
        if dropped:
            gone = [nm for nm in dropped if nm not in by_class]
            warnings.append(f"dropped {sum(dropped.values())} instance(s) named in fewer than {min_views} "
                            f"views ({unsupported} points): " + ", ".join(f"{nm} x{c}" for nm, c in dropped.items())
                            + (f"; class(es) left without instances: {', '.join(gone)}" if gone else ""))
        empty = [nm for nm in names if nm not in by_class and nm not in dropped]
        if empty:
            warnings.append(f"class(es) in the table without (usable) points in the map: {', '.join(empty)}")

        positions: dict[str, tuple[float, float, float]] = {}
        class_centroids: dict[str, tuple[float, float, float]] = {}
        for name, group in by_class.items():
            total = sum(g.point_count for g in group)
            class_centroids[name] = _tuple3(class_sum[name] / max(total, 1))
            positions[name] = class_centroids[name] if config.query_position == "class" else group[0].centre
        if timings is not None:
            timings["centres and tables"] = time.perf_counter() - t0 - sum(timings.values())
        stats = MapStats(points=n, used=int(counts.sum()) - inst_unsupported, non_finite=non_finite,
                         transparent=transparent, unlabelled=unlabelled, noise=split.noise_points,
                         unsupported=unsupported, build_s=time.perf_counter() - t0)
        instances = {name: tuple(group) for name, group in by_class.items()}
        return cls(positions, instances, synonyms, tuple(warnings), stats, class_centroids)

    # -- queries ---------------------------------------------------------------------------------

    def names(self) -> list[str]:
        """Known class names, sorted."""
        return list(self._names)

    def instance_count(self) -> int:
        """Number of instances over all classes."""
        return sum(len(g) for g in self._instances.values())

    def all_instances(self) -> list[ObjectInstance]:
        """Every instance, by class name then index."""
        return [inst for name in self._names for inst in self._instances[name]]

    def resolve(self, name: str) -> tuple[str | None, str]:
        """Which class a spoken name means.

        Returns:
            ``(class_name, note)`` when known (note says how: synonym, plural), else
            ``(None, reason)`` with "did you mean" suggestions.
        """
        key = normalise_name(name)
        if not key:
            return None, "empty object name"
        if len(key) > MAX_NAME_LENGTH:
            return None, f"object name too long ({len(key)} characters, at most {MAX_NAME_LENGTH})"
        if key in self._positions:
            return key, ""
        found = self._resolve_exact(key)
        if found is not None:
            return found
        # "the red coffee mug": try the head noun phrase (the last two words, then the last word)
        words = key.split(" ")
        for tail in (" ".join(words[-2:]), words[-1]) if 1 < len(words) <= 8 else ():
            found = self._resolve_exact(tail)
            if found is not None:
                return found[0], f"{shorten(key)!r} read as {found[0]!r}"
        aliases = [s for s in self._synonyms.all_names() if self.resolve_known(s)]
        suggestions = closest_names(key, self._names + aliases)
        hint = f"; did you mean: {', '.join(suggestions)}?" if suggestions else ""
        known = ", ".join(self._names[:_MAX_LISTED_NAMES]) + (" ..." if len(self._names) > _MAX_LISTED_NAMES else "")
        return None, f"unknown object {shorten(key)!r}{hint} (known: {known or 'none, the map is empty'})"

    def _resolve_exact(self, key: str) -> tuple[str, str] | None:
        """``key`` (normalised) as a class, a plural of one, or a synonym of one; else None."""
        for candidate in [key, *singular_forms(key)]:
            if candidate in self._positions:
                return candidate, "" if candidate == key else f"{shorten(key)!r} read as {candidate!r}"
            for alt in self._synonyms.alternatives(candidate):
                if alt in self._positions:
                    return alt, f"{shorten(key)!r} is a synonym of {alt!r}"
        return None

    def resolve_known(self, alias: str) -> bool:
        """True when the synonym ``alias`` (normalised) leads to a class of this map."""
        return alias in self._positions or any(a in self._positions for a in self._synonyms.alternatives(alias))

    def query(self, name: str) -> QueryResult:
        """Where is ``name``? (the ``/object_query`` answer).

        ``name`` may address one instance by its label, ``chair#2`` (as listed by
        :meth:`instances`); otherwise the answer is the class's query position.
        """
        label = _INSTANCE_LABEL.match(normalise_name(name)[: MAX_NAME_LENGTH + 1])
        if label is not None:
            key, note = self.resolve(label.group(1))
            index = int(label.group(2))
            group = self._instances.get(key, ()) if key is not None else ()
            if key is not None and 1 <= index <= len(group):
                inst = group[index - 1]
                x, y, z = inst.centre
                msg = f"{inst.label} at ({x:.3f}, {y:.3f}, {z:.3f}); {inst.point_count} points"
                return QueryResult(True, (x, y, z), msg + (f" ({note})" if note else ""))
            if key is not None:
                return QueryResult(False, (0.0, 0.0, 0.0), f"no {key}#{index}: there are {len(group)} instance(s) "
                                                            f"of {key} ({key}#1..{key}#{len(group)})")
        key, note = self.resolve(name)
        if key is None:
            return QueryResult(False, (0.0, 0.0, 0.0), note)
        x, y, z = self._positions[key]
        msg = f"{key} at ({x:.3f}, {y:.3f}, {z:.3f})"
        group = self._instances.get(key, ())
        if len(group) > 1:
            what = (f"the largest ({group[0].label}, {group[0].point_count} points)"
                    if self._positions[key] == group[0].centre else "the centre of all of them")
            msg += f"; {len(group)} instances of {key}, this is {what}; see /object_instances"
        if note:
            msg += f" ({note})"
        if self.provisional:
            msg += f"; {PROVISIONAL_NOTE}"
        return QueryResult(True, (x, y, z), msg)

    def instances(self, name: str, reference: tuple[float, float, float] | None = None) -> InstancesResult:
        """All instances of ``name``; nearest to ``reference`` first when given, else largest first. A reference
        that is not three finite numbers within :data:`MAX_COORD_M` of the origin answers ``found: false`` with
        the reason."""
        if reference is not None and not all(math.isfinite(float(v)) and abs(float(v)) <= MAX_COORD_M
                                             for v in reference):
            got = ", ".join(f"{float(v):g}" for v in reference)
            return InstancesResult(False, "", f"reference must be three finite numbers within {MAX_COORD_M:g} m "
                                              f"of the map's origin, got ({got})")
        key, note = self.resolve(name)
        if key is None:
            return InstancesResult(False, "", note)
        group = self._instances.get(key, ())
        if reference is None:
            dists = [-1.0] * len(group)
            ordered = list(group)
            where = ""
        else:
            ref = np.asarray(reference, dtype=np.float64)
            dists_all = [float(np.linalg.norm(np.asarray(g.centre) - ref)) for g in group]
            order = sorted(range(len(group)), key=lambda i: (dists_all[i], i))
            ordered = [group[i] for i in order]
            dists = [dists_all[i] for i in order]
            where = f", nearest first from ({ref[0]:.2f}, {ref[1]:.2f}, {ref[2]:.2f})"
        msg = f"{len(group)} instance(s) of {key}{where}"
        if note:
            msg += f" ({note})"
        if self.provisional:
            msg += f"; {PROVISIONAL_NOTE}"
        return InstancesResult(True, key, msg, tuple(ordered), tuple(dists))

    def to_json(self) -> str:
        """``{"chair": [x, y, z], ...}``: each name's query position, rounded to 0.1 mm."""
        return json.dumps(
            {n: [round(v, 4) if math.isfinite(v) else None for v in self._positions[n]] for n in self._names}
        )

    def summary(self) -> str:
        """One line for logs: names with instance counts and what was skipped."""
        s = self.stats
        if self.provisional:
            return (f"{len(self._names)} objects (provisional class centroids, instances being built); "
                    f"{s.used}/{s.points} points used; built in {s.build_s:.3f} s")
        parts = [f"{n}x{len(self._instances.get(n, ()))}" if len(self._instances.get(n, ())) > 1 else n
                 for n in self._names]
        return (f"{len(self._names)} objects, {self.instance_count()} instances ({', '.join(parts)}); "
                f"{s.used}/{s.points} points used, skipped {s.transparent} transparent, {s.non_finite} non-finite, "
                f"{s.unlabelled} unlabelled, {s.noise} noise; built in {s.build_s:.2f} s")


@dataclass(frozen=True)
class FileSignature:
    """What identifies a version of the map files on disk (for change polling)."""

    entries: tuple[tuple[str, int, int], ...] = field(default_factory=tuple)  # (path, mtime_ns, size)

    @classmethod
    def of(cls, *paths: str) -> FileSignature:
        """Signature of ``paths``; a missing file has mtime and size -1."""
        out = []
        for p in paths:
            try:
                st = os.stat(p)
                out.append((p, st.st_mtime_ns, st.st_size))
            except OSError:
                out.append((p, -1, -1))
        return cls(tuple(out))
