"""Start-up in two stages: class centroids at once, instances from a background thread (no ROS)."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from object_query.semantic_map import PROVISIONAL_NOTE, DatabaseConfig, ObjectDatabase, SemanticMap
from object_query.staged import StagedBuild

CLASSES = {1: "chair", 2: "cup", 7: "table"}


def dense_blobs(dtype, n_per_blob=3000, seed=0):
    """Two chairs, a cup and a table as dense blobs, some NaN and near-transparent points, an unknown id."""
    rng = np.random.default_rng(seed)
    centres = [((0, 0, 0.5), 1), ((3, 0, 0.5), 1), ((1, 2, 0.8), 2), ((5, 5, 0.7), 7)]
    means = np.concatenate([c + rng.normal(0, 0.05, (n_per_blob, 3)) for c, _ in centres]).astype(np.float32)
    ids = np.repeat([i for _, i in centres], n_per_blob).astype(dtype)
    opac = rng.normal(4.0, 0.5, len(ids)).astype(np.float32)
    opac[::50] = -8.0  # transparent: ignored by both stages
    means[::97] = np.nan  # non-finite: ignored by both stages
    ids[::101] = 9  # not in the table: ignored by both stages
    perm = rng.permutation(len(ids))
    return SemanticMap(means[perm], ids[perm], CLASSES, opac[perm])


@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.int32, np.int64, np.uint32])
def test_provisional_and_final_agree_on_class_centroids(dtype):
    smap = dense_blobs(dtype)
    final_box: list[ObjectDatabase] = []
    done = threading.Event()
    staged = StagedBuild(smap, DatabaseConfig(), None, lambda db: (final_box.append(db), done.set()),
                         lambda exc: pytest.fail(f"build failed: {exc}")).start()
    prov = staged.provisional
    assert prov.provisional and prov.names() == ["chair", "cup", "table"]
    assert done.wait(60.0) and staged.wait(60.0)
    final = final_box[0]
    assert not final.provisional and final is staged.final
    assert len(final.instances("chair").instances) == 2  # the full build split the two chairs
    for name in prov.names():
        np.testing.assert_allclose(prov.class_centroids[name], final.class_centroids[name], atol=1e-5)
        np.testing.assert_allclose(prov.query(name).position, final.class_centroids[name], atol=1e-5)
    # the reference: the mean of the valid points of each class, by hand
    finite = np.isfinite(smap.means).all(axis=1) & (smap.logit_opacities > -2.9)
    for sid, name in CLASSES.items():
        sel = finite & (smap.semantic_ids == sid)
        np.testing.assert_allclose(prov.class_centroids[name], smap.means[sel].astype(np.float64).mean(0), atol=1e-5)


def test_queries_are_answered_while_the_instances_are_built():
    """The build is held by a gate: the provisional database answers, says so, and the final one follows."""
    gate = threading.Event()
    finals: list[ObjectDatabase] = []
    staged = StagedBuild(dense_blobs(np.int32), DatabaseConfig(), None, finals.append,
                         lambda exc: pytest.fail(f"build failed: {exc}"), gate=gate).start()
    prov = staged.provisional
    r = prov.query("chair")
    assert r.found and PROVISIONAL_NOTE in r.message
    assert prov.instances("chairs").found and PROVISIONAL_NOTE in prov.instances("chairs").message
    assert not prov.query("unicorn").found
    assert not staged.done and not finals  # the build really was still waiting
    assert "provisional" in prov.summary()
    gate.set()
    assert staged.wait(60.0) and len(finals) == 1
    final = finals[0]
    assert PROVISIONAL_NOTE not in final.query("chair").message and final.query("chair").found
    # largest chair instance (default query_position) vs the class centre: the message says which
    assert "2 instances of chair" in final.query("chair").message


def test_a_failing_build_leaves_the_provisional_database():
    smap = dense_blobs(np.int32)
    far = SemanticMap(np.concatenate([smap.means, [[1e9, 0, 0]]]).astype(np.float64),
                      np.concatenate([smap.semantic_ids, [1]]).astype(np.int32), CLASSES, None)
    errors: list[Exception] = []
    staged = StagedBuild(far, DatabaseConfig(voxel_size=1e-4), None, lambda db: None, errors.append).start()
    assert staged.wait(60.0)
    assert staged.error is not None and "voxel" in str(staged.error).lower(), staged.error  # too many voxels
    assert errors == [staged.error] and staged.final is None and staged.provisional.query("chair").found


def test_chunked_bin_sums_equal_the_reference():
    from object_query.kernels import bin_sums_chunked, bin_sums_numpy

    rng = np.random.default_rng(3)
    ids = rng.integers(-3, 40, 100_003).astype(np.int32)  # some out of range on both sides
    means = rng.normal(0, 5, (len(ids), 3)).astype(np.float32)
    valid = rng.random(len(ids)) > 0.1
    lo, size = 2, 30
    counts, sums = bin_sums_chunked(ids, means, lo, size, lambda a, b: valid[a:b], chunk=4096)
    ref_counts, ref_sums = bin_sums_numpy(np.where(valid, ids.astype(np.intp) - lo, -1), means, size)
    np.testing.assert_array_equal(counts, ref_counts)
    np.testing.assert_allclose(sums, ref_sums, rtol=1e-12, atol=1e-9)
    with pytest.raises(ValueError, match="means"):
        bin_sums_chunked(ids, means[:, :2], lo, size)


def test_sparse_huge_ids_take_the_compact_path():
    smap = dense_blobs(np.int64)
    ids = smap.semantic_ids.copy()
    ids[ids == 7] = 10**12  # table id far from the others: no dense bin table
    classes = {1: "chair", 2: "cup", 10**12: "table"}
    big = SemanticMap(smap.means, ids, classes, smap.logit_opacities)
    prov = ObjectDatabase.provisional_from_map(big)
    final = ObjectDatabase.from_map(big)
    for name in ("chair", "cup", "table"):
        np.testing.assert_allclose(prov.class_centroids[name], final.class_centroids[name], atol=1e-5)
