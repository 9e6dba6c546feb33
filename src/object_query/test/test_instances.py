"""Unit tests of instance splitting (no ROS): hashing, union-find, voxel keys, the sample map."""

from __future__ import annotations

import os

import numpy as np
import pytest

from object_query.instances import (
    connected_components,
    dedupe_keys,
    dedupe_keys_reference,
    split_instances,
    voxel_keys,
)
from object_query.semantic_map import ObjectDatabase

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", ".."))


@pytest.mark.parametrize("n, distinct", [(0, 1), (1, 1), (1000, 3), (50_000, 40_000), (200_000, 7)])
def test_dedupe_agrees_with_np_unique(n, distinct):
    rng = np.random.default_rng(n)
    keys = rng.integers(0, distinct, n) * 1_000_003 - 17  # negative keys too
    inv, first = dedupe_keys(keys)
    ref_inv, ref_first = dedupe_keys_reference(keys)
    assert len(first) == len(ref_first)
    np.testing.assert_array_equal(keys[first][inv], keys)  # each point maps to a slot with its key
    # the partition is the same as np.unique's
    pairs = np.unique(np.stack([inv, ref_inv[: len(inv)]], 1), axis=0) if n else np.empty((0, 2))
    assert len(pairs) == len(first)


def test_dedupe_survives_many_collisions():
    # more distinct keys than the largest table has slots at this size forces several rounds
    keys = np.arange(300_000, dtype=np.int64) * (1 << 40)
    inv, first = dedupe_keys(keys)
    assert len(first) == len(keys) and np.array_equal(keys[first][inv], keys)


def _components_bfs(n, src, dst):
    adj = [[] for _ in range(n)]
    for a, b in zip(src.tolist(), dst.tolist(), strict=True):
        adj[a].append(b)
        adj[b].append(a)
    label = [-1] * n
    for s in range(n):
        if label[s] >= 0:
            continue
        stack, label[s] = [s], s
        while stack:
            u = stack.pop()
            for v in adj[u]:
                if label[v] < 0:
                    label[v] = s
                    stack.append(v)
    return np.array(label)


@pytest.mark.parametrize("seed", range(5))
def test_union_find_agrees_with_bfs(seed):
    rng = np.random.default_rng(seed)
    n = 3000
    e = int(rng.integers(500, 4000))
    src, dst = rng.integers(0, n, e), rng.integers(0, n, e)
    np.testing.assert_array_equal(connected_components(n, src, dst), _components_bfs(n, src, dst))


def test_union_find_long_chain():
    n = 20_000
    perm = np.random.default_rng(0).permutation(n)
    comp = connected_components(n, perm[:-1], perm[1:])  # one path through all nodes in random order
    assert (comp == 0).all()


def test_voxel_keys_do_not_wrap_between_rows():
    # points at the +x edge of a row and the -x edge of the next row must not be neighbours
    means = np.array([[0.0, 0.0, 0.0], [0.95, 0.0, 0.0], [0.0, 0.1, 0.0]])
    vk = voxel_keys(means, np.zeros(3, np.int64), 0.1, 1)
    for stride in vk.strides:
        assert vk.keys[1] + stride != vk.keys[2]
    split = split_instances(means, np.zeros(3, np.int64), None, 1, 0.1, 1)
    assert len(split.instance_count) == 2  # (0,0,0)+(0,0.1,0) touch; (0.95,0,0) is alone


def test_classes_never_merge_and_gaps_split():
    rng = np.random.default_rng(1)
    a = rng.random((500, 3)) * 0.3
    b = a + [0.05, 0, 0]  # overlaps a, other class
    c = a + [1.0, 0, 0]  # same class as a, 0.7 m gap
    means = np.concatenate([a, b, c])
    labels = np.array([0] * 500 + [1] * 500 + [0] * 500)
    split = split_instances(means, labels, None, 2, 0.1, 10)
    got = sorted(zip(split.instance_label.tolist(), split.instance_count.tolist(), strict=True))
    assert got == [(0, 500), (0, 500), (1, 500)]
    np.testing.assert_array_equal(split.point_instance[:500], np.full(500, split.point_instance[0]))
    assert split.point_instance[0] != split.point_instance[1000]


def test_bounding_boxes_are_exact_for_many_instances():
    rng = np.random.default_rng(2)
    centres = rng.random((40, 3)) * 40
    pts = np.concatenate([c + rng.normal(0, 0.2, (300, 3)) for c in centres])
    labels = np.repeat(np.arange(40) % 3, 300)
    split = split_instances(pts, labels, None, 3, 0.25, 5)
    for i in range(len(split.instance_count)):
        mine = pts[split.point_instance == i]
        np.testing.assert_array_equal(split.instance_min[i], mine.min(0))
        np.testing.assert_array_equal(split.instance_max[i], mine.max(0))
        np.testing.assert_allclose(split.instance_sum[i], mine.sum(0))


def test_sample_map_has_three_chairs_and_two_cups():
    """The bundled map (built by our SLAM from the synthetic home) holds the home's objects where they are."""
    data = os.path.join(REPO, "data")
    db = ObjectDatabase.from_files(os.path.join(data, "params.npz"), os.path.join(data, "semantic.json"))

    def near(found, truth, tol):  # one found instance within tol of every true position
        xy = np.array([c.centre[:2] for c in found])
        return len(found) == len(truth) and all(np.hypot(*(xy - t).T).min() < tol for t in np.array(truth))

    # true positions (x, y) from the synthetic home's layout
    assert near(db.instances("cup").instances, [(2.8, 2.6), (4.6, 0.35)], 0.06)
    assert near(db.instances("chair").instances, [(2.5, 1.6), (2.5, 3.4), (3.7, 2.5)], 0.12)
    assert near(db.instances("bottle").instances, [(5.2, 0.3)], 0.06)
    assert near(db.instances("bin").instances, [(5.6, 4.5)], 0.12)
    for name in db.names():
        if name not in ("chair", "cup"):
            assert len(db.instances(name).instances) == 1, name
    assert db.stats.used > 0.99 * db.stats.points
