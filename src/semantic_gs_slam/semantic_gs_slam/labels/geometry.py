"""Class-agnostic objects from geometry alone (no model, no network): the labelling stage that works
offline out of the box on any RGB-D camera.

Per frame (numpy only):

1. back-project the depth, estimate normals on a box-smoothed depth;
2. find the supporting planes by RANSAC (up to ``max_planes``, each with >= ``min_plane_fraction`` of
   the valid pixels, inliers by distance and normal agreement) and name them with the gravity
   direction: horizontal with the camera >= ``floor_min_height`` above it: ``floor``; horizontal below
   the camera but higher: ``table`` (a support surface: table or counter top); horizontal above the
   camera: ``ceiling``; vertical: ``wall``;
3. split what is left at depth discontinuities and group it into connected components (a vectorised
   union-find over 4-neighbour edges), dropping specks and huge regions (background structure);
4. track the components across frames: each becomes voxels (``voxel`` metres) in world coordinates
   with the camera pose, and takes the id of the earlier instance whose voxels it overlaps most
   (>= ``min_overlap`` of its own), else a new id. Ids therefore stay stable while the camera moves
   and when an object comes back into view.

Output ids: plane classes 1-4 (:data:`PLANE_CLASSES`), object instances from
:data:`FIRST_INSTANCE_ID` up, all named ``object``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from semantic_gs_slam.config import Intrinsics
from semantic_gs_slam.errors import ConfigError, FrameError

PLANE_CLASSES: dict[int, str] = {1: "floor", 2: "wall", 3: "table", 4: "ceiling"}
FLOOR, WALL, TABLE, CEILING = 1, 2, 3, 4
FIRST_INSTANCE_ID = 128
OBJECT_CLASS = "object"


@dataclass
class GeometryLabelConfig:
    """Settings of :class:`GeometryLabeller` (distances in metres)."""

    max_planes: int = 4  # planes removed per frame
    min_plane_fraction: float = 0.08  # a plane must hold this share of the valid pixels ...
    min_support_fraction: float = 0.02  # ... a horizontal support surface below the camera (table top) only this
    max_rejected: int = 6  # plane hypotheses rejected as too small before the search stops
    plane_dist: float = 0.012  # inlier distance at 1 m; grows with depth^2 (Kinect-like noise)
    plane_normal_cos: float = 0.85  # inlier normals within ~32 degrees of the plane's
    ransac_iters: int = 200
    horizontal_cos: float = 0.9  # |n . up| above this: horizontal plane
    vertical_cos: float = 0.3  # |n . up| below this: vertical plane (wall)
    floor_min_height: float = 1.0  # a horizontal plane is the floor when the camera is at least this high above
    floor_tolerance: float = 0.15  # it and it lies within this of the lowest such plane seen so far (else: table)
    depth_jump: float = 0.03  # neighbours further apart than this x depth are not connected
    min_segment_fraction: float = 0.002  # smaller components (share of the image) are dropped
    max_segment_fraction: float = 0.35  # larger ones are structure, not objects
    max_extent: float = 2.5  # metres; components larger than this in 3-D are structure
    voxel: float = 0.04  # world voxel for tracking instances across frames
    min_overlap: float = 0.2  # share of a component's voxels an earlier instance must own to give its id
    smooth: int = 5  # box filter (pixels) on the depth for normals
    concave_cut: float = 0.3  # pixels on concave creases (normal turn > ~17 deg, see concave_pixels) split
    # objects from the wall / each other (0: off)
    concave_step: int = 2  # pixels between the compared normals
    seed: int = 0
    up: tuple[float, float, float] | None = None  # world up; None: minus the first camera's y axis, refined
    # by the normals of near-horizontal planes in the first ``up_frames`` frames that show one
    up_frames: int = 10
    up_snap_cos: float = 0.8  # planes within ~37 degrees of the current up estimate refine it

    def check(self) -> None:
        """Raise :class:`ConfigError` on values that cannot work."""
        if self.max_planes < 0 or self.ransac_iters < 1 or self.voxel <= 0:
            raise ConfigError("labels: max_planes >= 0, ransac_iters >= 1 and voxel > 0 are required")
        if not 0 < self.min_plane_fraction < 1 or not 0 <= self.min_segment_fraction < self.max_segment_fraction:
            raise ConfigError("labels: fractions must satisfy 0 < min_plane_fraction < 1 and "
                              "0 <= min_segment_fraction < max_segment_fraction")


@dataclass
class Plane:
    """A plane found in one frame, camera coordinates: n . p + d = 0, ``n`` unit."""

    normal: np.ndarray  # [3]
    d: float
    cls: int  # one of PLANE_CLASSES or 0 (slanted: not named)
    pixels: int


@dataclass
class FrameLabels:
    """Labelling of one frame."""

    ids: np.ndarray  # [H, W] int64: plane classes, instance ids (>= FIRST_INSTANCE_ID), 0 = none
    planes: list[Plane] = field(default_factory=list)
    new_instances: list[int] = field(default_factory=list)


def _dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(a * b).sum(-1)`` of [..., 3] arrays, in the same order (numpy adds a 3-long last axis left to right), without
    the strided reduction: the same bits, several times faster."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross(a, b)`` of [..., 3] arrays, the same bits, without its axis juggling."""
    return np.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                     a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                     a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], -1)


def _nonzero3(a: np.ndarray) -> np.ndarray:
    """``np.abs(a).sum(-1) > 0`` of a finite [..., 3] array: any component non-zero."""
    return (a[..., 0] != 0) | (a[..., 1] != 0) | (a[..., 2] != 0)


def box_filter_valid(depth: np.ndarray, size: int) -> np.ndarray:
    """Mean of the valid (> 0) depths in a ``size`` x ``size`` window; 0 where the pixel itself is invalid."""
    if size <= 1:
        return depth.copy()
    valid = (depth > 0).astype(np.float64)
    r = size // 2

    def box(a: np.ndarray) -> np.ndarray:
        c = np.pad(a, r).cumsum(0).cumsum(1)
        c = np.pad(c, ((1, 0), (1, 0)))
        h, w = a.shape
        return c[size:size + h, size:size + w] - c[:h, size:size + w] - c[size:size + h, :w] + c[:h, :w]

    s, n = box(depth * valid), box(valid)
    return np.where(depth > 0, s / np.maximum(n, 1), 0.0)


def backproject(depth: np.ndarray, k: Intrinsics) -> np.ndarray:
    """Camera-frame points [H, W, 3] of a depth image [H, W] (metres)."""
    h, w = depth.shape
    u = np.arange(w, dtype=np.float64)[None, :]
    v = np.arange(h, dtype=np.float64)[:, None]
    z = depth.astype(np.float64)
    return np.stack([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z], -1)


def normals_from_points(pts: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Unit normals [H, W, 3] facing the camera from central differences; 0 where undefined."""
    dx = np.zeros_like(pts)
    dy = np.zeros_like(pts)
    dx[:, 1:-1] = pts[:, 2:] - pts[:, :-2]
    dy[1:-1] = pts[2:] - pts[:-2]
    n = _cross3(dx, dy)
    ok = valid.copy()
    ok[:, 1:-1] &= valid[:, 2:] & valid[:, :-2]
    ok[1:-1] &= valid[2:] & valid[:-2]
    ok[[0, -1], :] = False
    ok[:, [0, -1]] = False
    norm = np.sqrt(_dot3(n, n))  # = np.linalg.norm(n, axis=-1), bit for bit
    ok &= norm > 1e-12
    n = np.where(ok[..., None], n / np.maximum(norm, 1e-12)[..., None], 0.0)
    flip = _dot3(n, pts) > 0  # face the camera
    n *= np.where(flip, -1.0, 1.0)[..., None]
    return n


def connected_components(mask: np.ndarray, join_h: np.ndarray, join_v: np.ndarray) -> tuple[np.ndarray, int]:
    """Label 4-connected components of ``mask`` whose neighbours are joined.

    Vectorised union-find: hook every edge's larger root onto the smaller, then pointer jumping,
    until no edge joins two roots.

    Args:
        mask: [H, W] bool, pixels to label.
        join_h: [H, W-1] bool, pixel (y, x) joins (y, x+1) (only where both are in ``mask``).
        join_v: [H-1, W] bool, pixel (y, x) joins (y+1, x).

    Returns:
        (labels [H, W] int64 with 1..n per component and 0 outside ``mask``, n).
    """
    h, w = mask.shape
    idx = np.arange(h * w).reshape(h, w)
    jh = join_h & mask[:, :-1] & mask[:, 1:]
    jv = join_v & mask[:-1, :] & mask[1:, :]
    a = np.concatenate([idx[:, :-1][jh], idx[:-1, :][jv]])
    b = np.concatenate([idx[:, 1:][jh], idx[1:, :][jv]])
    parent = np.arange(h * w)
    while a.size:
        pa, pb = parent[a], parent[b]
        diff = pa != pb
        if not diff.any():
            break
        lo, hi = np.minimum(pa[diff], pb[diff]), np.maximum(pa[diff], pb[diff])
        np.minimum.at(parent, hi, lo)
        while True:
            pp = parent[parent]
            if np.array_equal(pp, parent):
                break
            parent = pp
    roots = parent.reshape(h, w)
    out = np.zeros((h, w), np.int64)
    if mask.any():
        uniq, inv = np.unique(roots[mask], return_inverse=True)
        out[mask] = inv.reshape(-1) + 1
        return out, len(uniq)
    return out, 0


def concave_pixels(pts: np.ndarray, normals: np.ndarray, step: int, threshold: float) -> np.ndarray:
    """Pixels on a concave crease (where an object meets the wall or another object) [H, W] bool.

    Along x and y, ``c = (n(+s) - n(-s)) . (p(+s) - p(-s)) / |p(+s) - p(-s)|`` is positive across a
    convex edge (a box's own corner) and negative across a concave one; pixels with ``c < -threshold``
    are creases.
    """
    h, w = normals.shape[:2]
    out = np.zeros((h, w), bool)
    ok = _nonzero3(normals)
    s = step
    for axis in (0, 1):
        sl_a = (slice(2 * s, None), slice(None)) if axis == 0 else (slice(None), slice(2 * s, None))
        sl_b = (slice(None, -2 * s), slice(None)) if axis == 0 else (slice(None), slice(None, -2 * s))
        centre = (slice(s, -s), slice(None)) if axis == 0 else (slice(None), slice(s, -s))
        dp = pts[sl_a] - pts[sl_b]
        dn = normals[sl_a] - normals[sl_b]
        c = _dot3(dn, dp) / np.maximum(np.sqrt(_dot3(dp, dp)), 1e-9)
        out[centre] |= (c < -threshold) & ok[sl_a] & ok[sl_b]
    return out


def best_plane_hypothesis(p_h: np.ndarray, n_h: np.ndarray, p: np.ndarray, n: np.ndarray, tol: np.ndarray,
                          normal_cos: float) -> tuple[np.ndarray, float] | None:
    """RANSAC scoring, all hypotheses at once: each point ``p_h[k]`` with its normal ``n_h[k]`` ([K, 3]) is a
    plane; its score is how many of the sample points ``p`` ([S, 3], normals ``n``) lie within ``tol`` ([S])
    of it with a normal within ``normal_cos`` of its own. Returns the plane (unit normal [3], offset) of the
    first best-scoring hypothesis, as a sequential search that keeps strictly better ones would, or None
    when no hypothesis has a single inlier.
    """
    d_h = -(n_h * p_h).sum(-1)  # [K]
    dist = np.abs(p @ n_h.T + d_h)  # [S, K]
    scores = ((dist < tol[:, None]) & (n @ n_h.T > normal_cos)).sum(0)  # [K]
    k = int(np.argmax(scores))  # argmax returns the first of equal maxima
    if scores[k] <= 0:
        return None
    return n_h[k], float(d_h[k])


def _voxel_keys(world: np.ndarray, voxel: float) -> np.ndarray:
    """Unique int64 keys of the voxels holding the points [N, 3] (21 bits per axis, +-42 km at 2 cm)."""
    q = np.floor(world / voxel).astype(np.int64) + (1 << 20)
    return np.unique((q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2])


class GeometryLabeller:
    """Per-frame instance and plane labels from depth, with instance ids tracked across frames."""

    def __init__(self, intrinsics: Intrinsics, config: GeometryLabelConfig | None = None) -> None:
        self.k = intrinsics
        self.cfg = config or GeometryLabelConfig()
        self.cfg.check()
        self._rng = np.random.default_rng(self.cfg.seed)
        self._owner: dict[int, int] = {}  # world voxel key -> instance id
        self.next_id = FIRST_INSTANCE_ID  # id of the next new instance
        self._up: np.ndarray | None = None if self.cfg.up is None else np.asarray(self.cfg.up, np.float64)
        self.classes: dict[int, str] = dict(PLANE_CLASSES)
        self._up_sum = np.zeros(3)  # pixel-weighted sum of horizontal plane normals (world) seen so far
        self._up_frames = 0  # frames that refined the up estimate
        self._plane_masks: list[np.ndarray] = []  # inlier masks of the current frame's planes
        self._floor_level: float | None = None  # world height (along up) of the lowest floor candidate so far
        self._cam_height = 0.0  # the current camera's world height along up

    def label(self, rgb: np.ndarray, depth: np.ndarray, c2w: np.ndarray) -> FrameLabels:
        """Label one frame.

        Args:
            rgb: [H, W, 3] (unused by this stage; the ONNX stage reads it).
            depth: [H, W] metres, 0 = missing.
            c2w: [4, 4] camera-to-world pose (tracked or predicted) used to keep ids across frames.

        Returns:
            :class:`FrameLabels`; ``self.classes`` gains the new instance ids.

        Raises:
            FrameError: a depth image of the wrong shape.
        """
        k, cfg = self.k, self.cfg
        depth = np.asarray(depth, np.float64)
        if depth.shape != (k.height, k.width):
            raise FrameError(f"labels: depth must be [{k.height}, {k.width}], got {list(depth.shape)}")
        c2w = np.asarray(c2w, np.float64)
        if self._up is None:
            self._up = -c2w[:3, 1] / np.linalg.norm(c2w[:3, 1])
        up_c = c2w[:3, :3].T @ self._up  # gravity "up" in camera coordinates
        self._cam_height = float(c2w[:3, 3] @ self._up)
        valid = np.isfinite(depth) & (depth > 0)
        ids = np.zeros(depth.shape, np.int64)
        if valid.sum() < 50:
            return FrameLabels(ids)
        pts = backproject(depth, k)
        smooth_pts = backproject(box_filter_valid(depth, cfg.smooth), k)  # [H, W, 3], for normals and creases
        normals = normals_from_points(smooth_pts, valid)
        planes, plane_mask = self._planes(pts, normals, valid, up_c, ids)
        if self.cfg.up is None and self._up_frames < self.cfg.up_frames:
            self._refine_up(planes, c2w)
            up_c = c2w[:3, :3].T @ self._up
            self._cam_height = float(c2w[:3, 3] @ self._up)
            self._floor_level = None  # levels measured along the old up are void
            ids[:] = 0
            for pl, m in zip(planes, self._plane_masks, strict=True):
                pl.cls = self._plane_class(pl.normal, pl.d, up_c)
                if pl.cls:
                    ids[m] = pl.cls
        rest = valid & ~plane_mask
        if cfg.concave_cut > 0:
            rest &= ~concave_pixels(smooth_pts, normals, cfg.concave_step,
                                    cfg.concave_cut)
        z = depth
        jump = cfg.depth_jump * np.maximum(z, 1e-6)
        join_h = np.abs(z[:, 1:] - z[:, :-1]) < np.minimum(jump[:, 1:], jump[:, :-1])
        join_v = np.abs(z[1:, :] - z[:-1, :]) < np.minimum(jump[1:, :], jump[:-1, :])
        comp, n = connected_components(rest, join_h, join_v)
        new: list[int] = []
        if n:
            counts = np.bincount(comp.reshape(-1), minlength=n + 1)
            npx = depth.size
            keep = (counts >= cfg.min_segment_fraction * npx) & (counts <= cfg.max_segment_fraction * npx)
            keep[0] = False
            world = pts @ c2w[:3, :3].T + c2w[:3, 3]
            for c in np.flatnonzero(keep):
                m = comp == c
                wp = world[m]
                lo, hi = np.percentile(wp, [2, 98], 0)
                if np.any(hi - lo > cfg.max_extent):
                    continue
                iid = self._associate(_voxel_keys(wp, cfg.voxel))
                if iid not in self.classes:
                    self.classes[iid] = OBJECT_CLASS
                    new.append(iid)
                ids[m] = iid
        return FrameLabels(ids, planes, new)

    def _associate(self, keys: np.ndarray) -> int:
        owners = np.array([self._owner.get(int(q), 0) for q in keys], np.int64)
        hit = owners[owners > 0]
        iid = 0
        if hit.size:
            vals, cnt = np.unique(hit, return_counts=True)
            best = int(np.argmax(cnt))
            if cnt[best] >= self.cfg.min_overlap * len(keys):
                iid = int(vals[best])
        if iid == 0:
            iid = self.next_id
            self.next_id += 1
        for q in keys:
            self._owner.setdefault(int(q), iid)
        return iid

    def _planes(self, pts: np.ndarray, normals: np.ndarray, valid: np.ndarray, up_c: np.ndarray,
                ids: np.ndarray) -> tuple[list[Plane], np.ndarray]:
        cfg = self.cfg
        free = valid & _nonzero3(normals)
        taken = np.zeros(valid.shape, bool)
        n_valid = int(valid.sum())
        z = pts[..., 2]
        tol = cfg.plane_dist * np.maximum(z, 0.3) ** 2
        planes: list[Plane] = []
        self._plane_masks: list[np.ndarray] = []
        tried = np.zeros(valid.shape, bool)  # inliers of hypotheses rejected as too small
        for _ in range(cfg.max_planes + cfg.max_rejected):
            if len(planes) >= cfg.max_planes:
                break
            cand = np.flatnonzero((free & ~taken & ~tried).reshape(-1))
            if cand.size == 0:
                break
            if cand.size < cfg.min_support_fraction * n_valid:
                break
            p_all = pts.reshape(-1, 3)
            n_all = normals.reshape(-1, 3)
            sub = cand if cand.size <= 2000 else self._rng.choice(cand, 2000, replace=False)
            hyp = self._rng.choice(cand, min(cfg.ransac_iters, cand.size), replace=False)
            best = best_plane_hypothesis(p_all[hyp], n_all[hyp], p_all[sub], n_all[sub], tol.reshape(-1)[sub],
                                         cfg.plane_normal_cos)
            if best is None:
                break
            n0, d0 = best
            dist0 = np.abs(_dot3(pts, n0) + d0)  # [H, W]
            inl = (dist0 < tol) & (_dot3(normals, n0) > cfg.plane_normal_cos) & free & ~taken
            if inl.sum() < 10:
                tried |= inl
                continue
            # least-squares refit on the inliers, then the final inlier set
            q = pts[inl]
            c = q.mean(0)
            _, _, vt = np.linalg.svd(q - c, full_matrices=False)
            n1 = vt[2] if vt[2] @ n0 > 0 else -vt[2]
            d1 = -float(n1 @ c)
            inl = (np.abs(_dot3(pts, n1) + d1) < tol) & (_dot3(normals, n1) > cfg.plane_normal_cos) & valid & ~taken
            cls = self._plane_class(n1, d1, up_c)
            horizontal_below = float(n1 @ up_c) > cfg.up_snap_cos and d1 > 0  # the up estimate may still be off
            need = cfg.min_support_fraction if horizontal_below else cfg.min_plane_fraction
            if inl.sum() < need * n_valid:
                tried |= inl | (dist0 < tol) & free
                continue
            planes.append(Plane(n1, d1, cls, int(inl.sum())))
            self._plane_masks.append(inl)
            taken |= inl
            if cls:
                ids[inl] = cls
        return planes, taken

    def _refine_up(self, planes: list[Plane], c2w: np.ndarray) -> None:
        """Pull the up estimate toward the normals of near-horizontal planes (the first ``up_frames`` frames
        that have one): the first camera is rarely exactly level."""
        acc = np.zeros(3)
        for pl in planes:
            nw = c2w[:3, :3] @ pl.normal
            cos = float(nw @ self._up)
            if abs(cos) > self.cfg.up_snap_cos:
                acc += np.sign(cos) * nw * pl.pixels
        if np.linalg.norm(acc) > 0:
            self._up_sum = self._up_sum + acc
            self._up = self._up_sum / np.linalg.norm(self._up_sum)
            self._up_frames += 1

    def _plane_class(self, n: np.ndarray, d: float, up_c: np.ndarray) -> int:
        cos = float(n @ up_c)
        if abs(cos) < self.cfg.vertical_cos:
            return WALL
        if abs(cos) < self.cfg.horizontal_cos:
            return 0
        # signed height of the camera (the origin) above the plane along up: the plane point nearest the
        # origin is -d n, so the camera is at (d n) . up above it
        height = d * cos
        if height <= 0:
            return CEILING
        if height < self.cfg.floor_min_height:
            return TABLE
        level = self._cam_height - height  # the plane's height along up in world coordinates
        if self._floor_level is None or level < self._floor_level:
            self._floor_level = level
        return FLOOR if level < self._floor_level + self.cfg.floor_tolerance else TABLE
