"""Synthetic large semantic maps for the object-query benchmarks (importable helper, not a bench)."""

from __future__ import annotations

import numpy as np


def make_big_map(n_points: int = 10_000_000, n_classes: int = 100, seed: int = 0, floater_fraction: float = 0.01,
                 shuffle: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[int, str], int]:
    """A SplaTAM-like map: box-surface objects of ``n_classes`` classes (1-3 instances each) in a 40 m x 40 m
    x 3 m building, plus near-transparent floaters with random labels.

    Returns:
        ``(means [N, 3] float32, semantic_ids [N] uint8, logit_opacities [N] float32, classes, n_instances)``.
    """
    rng = np.random.default_rng(seed)
    n_inst_per_class = 1 + np.arange(n_classes) % 3
    n_inst = int(n_inst_per_class.sum())
    slots = rng.permutation(20 * 20)[:n_inst]  # a 20 x 20 grid of 2 m cells, one object per cell
    lo = np.stack([slots % 20 * 2.0 + 0.3, slots // 20 * 2.0 + 0.3, np.zeros(n_inst)], 1)
    size = rng.uniform(0.2, 1.4, (n_inst, 3))
    area = 2 * (size[:, 0] * size[:, 1] + size[:, 1] * size[:, 2] + size[:, 0] * size[:, 2])
    n_surface = n_points - int(n_points * floater_fraction)
    per = np.floor(area / area.sum() * n_surface).astype(np.int64)
    per[: n_surface - per.sum()] += 1
    inst = np.repeat(np.arange(n_inst), per)  # [Ns]
    # a random point on a random face of its box: pick the face axis, the side, two free coordinates
    axis = rng.integers(0, 3, len(inst))
    u = rng.random((len(inst), 3), dtype=np.float32)
    side = rng.integers(0, 2, len(inst)).astype(np.float32)
    u[np.arange(len(inst)), axis] = side
    pts = lo[inst].astype(np.float32) + u * size[inst].astype(np.float32)
    pts += rng.normal(0, 0.003, pts.shape).astype(np.float32)
    cls_of_inst = np.repeat(np.arange(n_classes), n_inst_per_class) + 1  # ids 1..n_classes
    ids = cls_of_inst[inst]
    n_float = n_points - len(pts)
    f_pts = (rng.random((n_float, 3)) * [40, 40, 3]).astype(np.float32)
    f_ids = rng.integers(1, n_classes + 1, n_float)
    means = np.concatenate([pts, f_pts])
    sem = np.concatenate([ids, f_ids]).astype(np.uint8)
    opac = np.concatenate([rng.normal(4, 0.5, len(pts)), rng.normal(-5, 1, n_float)]).astype(np.float32)
    if shuffle:
        perm = rng.permutation(n_points)
        means, sem, opac = means[perm], sem[perm], opac[perm]
    classes = {i: f"object {i:03d}" for i in range(1, n_classes + 1)}
    return means, sem, opac, classes, n_inst


def make_blob_map(n_points: int = 10_000_000, n_classes: int = 100, seed: int = 1, label_dtype: str = "int32"
                  ) -> tuple[np.ndarray, np.ndarray, dict[int, str]]:
    """Dense Gaussian blobs: each class 1-3 blobs (sigma 0.05-0.3 m) in a 30 m x 30 m x 2 m space, points in
    random order, no opacities — a map unlike :func:`make_big_map` (no surfaces, no floaters).

    Returns:
        ``(means [N, 3] float32, semantic_ids [N] label_dtype, classes)``.
    """
    rng = np.random.default_rng(seed)
    n_blob_per_class = 1 + rng.integers(0, 3, n_classes)
    n_blobs = int(n_blob_per_class.sum())
    centres = rng.uniform([0, 0, 0.2], [30, 30, 1.8], (n_blobs, 3))
    sigma = rng.uniform(0.05, 0.3, n_blobs)
    per = rng.multinomial(n_points, np.full(n_blobs, 1.0 / n_blobs))
    blob = np.repeat(np.arange(n_blobs), per)  # [N]
    means = (centres[blob] + rng.standard_normal((n_points, 3)) * sigma[blob, None]).astype(np.float32)
    ids = (np.repeat(np.arange(n_classes), n_blob_per_class) + 1)[blob]
    perm = rng.permutation(n_points)
    classes = {i: f"object {i:03d}" for i in range(1, n_classes + 1)}
    return means[perm], ids[perm].astype(label_dtype), classes
