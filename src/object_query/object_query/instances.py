"""Splitting each class's points into spatial instances, in O(N) over points (no ROS, numpy only).

Pipeline (``split_instances``):

1. Every valid point gets a voxel key ``(label, ix, iy, iz)`` packed into one int64.
2. :func:`dedupe_keys` gives each distinct key a compact voxel id in one hashing pass (expected
   O(N): multiplicative hashing into a table, colliding keys retried with a new salt).
3. Voxels of one label that touch (26-neighbourhood) are joined by :func:`connected_components`
   (vectorised union-find: hook roots to the smaller root, then pointer jumping). This runs on
   the M occupied voxels (M << N), neighbours found by ``searchsorted`` in the sorted voxel keys.
4. Per-voxel point counts/sums are gathered with ``np.bincount``; components smaller than
   ``min_points`` points are noise (floaters), the rest are instances.

:func:`dedupe_keys_reference` (``np.unique``) is the slow reference the tests compare against.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# 26-neighbourhood, one of each +/- pair: (dx, dy, dz) > (0, 0, 0) lexicographically.
_HALF_NEIGHBOURHOOD = [
    (dx, dy, dz)
    for dx in (-1, 0, 1)
    for dy in (-1, 0, 1)
    for dz in (-1, 0, 1)
    if (dx, dy, dz) > (0, 0, 0)
]
#: log2 of the largest hash table (2**22 slots of int64 = 32 MiB): cache-friendly; more distinct
#: keys than slots only cost extra rounds.
MAX_TABLE_BITS = 22
_HASH_MULTIPLIERS = np.array(
    [0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F, 0x165667B19E3779F9, 0xD6E8FEB86659FD93,
     0xFF51AFD7ED558CCD, 0xC4CEB9FE1A85EC53, 0x94D049BB133111EB, 0xBF58476D1CE4E5B9],
    dtype=np.uint64,
)


@dataclass(frozen=True)
class VoxelSplit:
    """Result of :func:`split_instances`.

    Attributes:
        point_instance: [N] int64, instance id of each point, -1 for invalid or noise points.
        instance_label: [I] int64, label (compact class index) of each instance.
        instance_count: [I] int64, number of points of each instance.
        instance_sum: [I, 3] float64, sum of the point coordinates of each instance.
        instance_min: [I, 3] float64, bounding-box minimum of each instance.
        instance_max: [I, 3] float64, bounding-box maximum of each instance.
        noise_points: points that were valid but fell in components below ``min_points``.
    """

    point_instance: np.ndarray
    instance_label: np.ndarray
    instance_count: np.ndarray
    instance_sum: np.ndarray
    instance_min: np.ndarray
    instance_max: np.ndarray
    noise_points: int


def _hash(keys: np.ndarray, salt: int, bits: int) -> np.ndarray:
    """Multiplicative hash of int64 keys into [0, 2**bits)."""
    mult = _HASH_MULTIPLIERS[salt % len(_HASH_MULTIPLIERS)]
    mixed = keys.view(np.uint64) ^ np.uint64((salt * 0x2545F4914F6CDD1D) & 0xFFFFFFFFFFFFFFFF)
    return ((mixed * mult) >> np.uint64(64 - bits)).astype(np.intp)


def dedupe_keys(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Compact ids for distinct keys, in expected O(N) (hashing, no sort).

    Args:
        keys: [N] int64 keys.

    Returns:
        ``(inverse, first)``: inverse [N] int64 with ``inverse[i]`` the id of ``keys[i]`` (ids are
        0..M-1 in no particular order), and first [M] int64, the index of one point per id
        (``keys[first[inverse]] == keys``).
    """
    keys = np.ascontiguousarray(keys, dtype=np.int64)  # [N]
    n = len(keys)
    inverse = np.empty(n, dtype=np.int64)
    if n == 0:
        return inverse, np.empty(0, dtype=np.int64)
    bits = int(min(max(np.ceil(np.log2(n)), 10), MAX_TABLE_BITS))
    table = np.full(1 << bits, -1, dtype=np.int64)  # slot -> point index, then -> compact id
    active = None  # None = all points (saves a copy in the first round)
    firsts: list[np.ndarray] = []
    next_id = 0
    salt = 0
    while True:
        k = keys if active is None else keys[active]
        idx = np.arange(n, dtype=np.int64) if active is None else active
        slot = _hash(k, salt, bits)
        table[slot] = idx  # last writer of each slot becomes its representative
        rep = table[slot]
        settled = keys[rep] == k
        is_rep = rep == idx
        rep_slots = slot[is_rep]
        reps = idx[is_rep]
        table[rep_slots] = np.arange(next_id, next_id + len(reps), dtype=np.int64)
        inverse[idx[settled]] = table[slot[settled]]
        table[rep_slots] = -1
        firsts.append(reps)
        next_id += len(reps)
        active = idx[~settled]
        salt += 1
        if len(active) == 0:
            break
        if len(active) < (1 << (bits - 2)) and bits > 10:
            bits -= 1  # fewer keys left: a smaller table is as good and cheaper to reset
    return inverse, np.concatenate(firsts)


def dedupe_keys_reference(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Same contract as :func:`dedupe_keys` via ``np.unique`` (sorting; the test reference)."""
    uniq, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    return inverse.reshape(-1).astype(np.int64), first.astype(np.int64)


def connected_components(n_nodes: int, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Connected components of an undirected graph (vectorised union-find).

    Args:
        n_nodes: number of nodes.
        src: [E] int64 edge ends.
        dst: [E] int64 edge ends.

    Returns:
        [n_nodes] int64: for each node the smallest node index of its component.
    """
    parent = np.arange(n_nodes, dtype=np.int64)  # [n_nodes]
    src = np.asarray(src, dtype=np.int64)
    dst = np.asarray(dst, dtype=np.int64)
    while True:
        while True:  # pointer jumping until every node points at a root
            grand = parent[parent]
            if np.array_equal(grand, parent):
                break
            parent = grand
        ps, pd = parent[src], parent[dst]
        open_edges = ps != pd
        if not open_edges.any():
            return parent
        src, dst, ps, pd = src[open_edges], dst[open_edges], ps[open_edges], pd[open_edges]
        # hook the larger root under the smaller one; parents only ever decrease: no cycles
        parent[np.maximum(ps, pd)] = np.minimum(ps, pd)


def voxel_keys(
    means: np.ndarray, labels: np.ndarray, voxel_size: float, n_labels: int
) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Pack ``(label, ix, iy, iz)`` of each point into one int64 key.

    Cell coordinates are shifted by +1 and the strides padded by 2 so that a neighbour offset
    of -1/+1 never wraps into another row.

    Args:
        means: [N, 3] finite coordinates.
        labels: [N] int64 labels in [0, n_labels).
        voxel_size: edge of a voxel, metres (> 0).
        n_labels: number of labels.

    Returns:
        ``(keys, strides)``: keys [N] int64 and the key strides of (x, y, z).

    Raises:
        ValueError: the extent of the map over ``voxel_size`` does not fit an int64 key.
    """
    if len(means) == 0:
        return np.empty(0, dtype=np.int64), (1, 1, 1)
    cells = []
    extents = []
    for axis in range(3):
        col = means[:, axis]
        lo = float(col.min())
        c = np.floor((col - lo) * (1.0 / voxel_size)).astype(np.int64)  # [N] >= 0
        c += 1
        cells.append(c)
        extents.append(int(c.max()) + 2)
    sx, sy, sz = extents[1] * extents[2], extents[2], 1
    if n_labels * extents[0] * sx >= 2**62:
        raise ValueError(f"map extent {extents} voxels x {n_labels} labels is too large for voxel_size={voxel_size}")
    keys = labels.astype(np.int64) * (extents[0] * sx)
    keys += cells[0] * sx
    keys += cells[1] * sy
    keys += cells[2]
    return keys, (sx, sy, sz)


def split_instances(
    means: np.ndarray,
    labels: np.ndarray,
    valid: np.ndarray | None,
    n_labels: int,
    voxel_size: float,
    min_points: int,
) -> VoxelSplit:
    """Split each label's points into spatially connected instances.

    Args:
        means: [N, 3] point coordinates (float32 or float64).
        labels: [N] int64 labels in [0, n_labels) (the caller maps class ids to labels).
        valid: [N] bool, points to use (finite, opaque enough), or None for all.
        n_labels: number of labels.
        voxel_size: voxel edge in metres; points of one label in touching voxels are one instance.
        min_points: components with fewer points are noise.

    Returns:
        The instances, with their ids in a deterministic order (label, then point count
        descending, then centroid x, y, z).
    """
    n = len(means)
    if valid is not None and not valid.any() or n == 0:
        empty3 = np.empty((0, 3))
        return VoxelSplit(np.full(n, -1, dtype=np.int64), np.empty(0, np.int64), np.empty(0, np.int64),
                          empty3, empty3, empty3, 0)
    if valid is None or bool(valid.all()):
        sel = None
        m, lab = means, labels
    else:
        sel = np.flatnonzero(valid)  # [Nv]
        m, lab = means[sel], labels[sel]
    keys, strides = voxel_keys(m, lab, voxel_size, n_labels)
    vox, _first = dedupe_keys(keys)  # vox [Nv] in [0, M)
    n_vox = len(_first)
    vkeys = keys[_first]  # [M]

    # neighbours: sorted voxel keys, key + offset preserves order -> fast searchsorted
    order = np.argsort(vkeys, kind="stable")
    skeys = vkeys[order]
    src_l, dst_l = [], []
    for dx, dy, dz in _HALF_NEIGHBOURHOOD:
        off = dx * strides[0] + dy * strides[1] + dz * strides[2]
        pos = np.searchsorted(skeys, skeys + off)
        pos_c = np.minimum(pos, n_vox - 1)
        hit = skeys[pos_c] == skeys + off
        src_l.append(np.flatnonzero(hit))
        dst_l.append(pos_c[hit])
    src = np.concatenate(src_l) if src_l else np.empty(0, np.int64)
    dst = np.concatenate(dst_l) if dst_l else np.empty(0, np.int64)
    comp_sorted = connected_components(n_vox, src, dst)  # in sorted-voxel index space
    vox_comp = np.empty(n_vox, dtype=np.int64)
    vox_comp[order] = order[comp_sorted]  # component = a representative voxel id

    # per-voxel aggregates (one pass over points each)
    vox_count = np.bincount(vox, minlength=n_vox)  # [M]
    comp_count = np.bincount(vox_comp, weights=vox_count, minlength=n_vox)  # [M] (by rep voxel)
    keep = comp_count >= max(min_points, 1)
    kept_comps = np.flatnonzero(keep)
    vox_label = lab[_first]  # [M]

    sums = np.empty((n_vox, 3))
    for axis in range(3):
        sums[:, axis] = np.bincount(vox, weights=m[:, axis], minlength=n_vox)
    comp_sum = np.stack([np.bincount(vox_comp, weights=sums[:, a], minlength=n_vox) for a in range(3)], 1)

    # deterministic instance order
    c_label = vox_label[kept_comps]
    c_count = comp_count[kept_comps].astype(np.int64)
    c_sum = comp_sum[kept_comps]
    c_mean = c_sum / np.maximum(c_count, 1)[:, None]
    rank = np.lexsort((c_mean[:, 2], c_mean[:, 1], c_mean[:, 0], -c_count, c_label))
    kept_comps, c_label, c_count, c_sum = kept_comps[rank], c_label[rank], c_count[rank], c_sum[rank]
    comp_to_inst = np.full(n_vox, -1, dtype=np.int64)
    comp_to_inst[kept_comps] = np.arange(len(kept_comps))
    vox_inst = comp_to_inst[vox_comp]  # [M]
    pinst = vox_inst[vox]  # [Nv]

    # exact bounding boxes: only points in voxels on an instance's boundary layer can be extreme
    n_inst = len(kept_comps)
    inst_min = np.full((n_inst, 3), np.inf)
    inst_max = np.full((n_inst, 3), -np.inf)
    if n_inst:
        # cell index along x, y, z (x keeps the label term, a constant within an instance)
        vkeys_cells = [vkeys // strides[0], (vkeys // strides[1]) % (strides[0] // strides[1]), vkeys % strides[1]]
        vmask = vox_inst >= 0
        boundary = np.zeros(n_vox, dtype=bool)
        for a in range(3):
            cell = vkeys_cells[a]
            lo = np.full(n_inst, np.iinfo(np.int64).max)
            hi = np.full(n_inst, np.iinfo(np.int64).min)
            np.minimum.at(lo, vox_inst[vmask], cell[vmask])
            np.maximum.at(hi, vox_inst[vmask], cell[vmask])
            vi = np.where(vmask, vox_inst, 0)
            boundary |= vmask & ((cell == lo[vi]) | (cell == hi[vi]))
        bpts = np.flatnonzero(boundary[vox])
        bi = pinst[bpts]
        for a in range(3):
            col = m[bpts, a]
            np.minimum.at(inst_min[:, a], bi, col)
            np.maximum.at(inst_max[:, a], bi, col)

    if sel is None:
        point_instance = pinst
    else:
        point_instance = np.full(n, -1, dtype=np.int64)
        point_instance[sel] = pinst
    noise = int(len(pinst) - c_count.sum())
    return VoxelSplit(point_instance, c_label, c_count, c_sum, inst_min, inst_max, noise)
