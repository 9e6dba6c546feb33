"""Unit tests of the pure map logic (no ROS): loading, bad input, centroids, instances, queries."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from object_query.errors import MapLoadError
from object_query.names import Synonyms
from object_query.semantic_map import (
    DatabaseConfig,
    ObjectDatabase,
    SemanticMap,
    compute_centroids,
    compute_centroids_masked,
    load_semantic_map,
)


def write_map(tmp_path, arrays: dict | None = None, classes=None, *, raw_json: str | None = None, name="params"):
    """Write ``<name>.npz`` + ``<name>.json`` into tmp_path; returns both paths."""
    npz, js = tmp_path / f"{name}.npz", tmp_path / f"{name}.json"
    if arrays is not None:
        np.savez(npz, **arrays)
    if raw_json is not None:
        js.write_text(raw_json, encoding="utf-8")
    else:
        classes = classes if classes is not None else [(1, "chair"), (2, "cup")]
        js.write_text(json.dumps({"segmentation": [{"id": i, "class": c} for i, c in classes]}), encoding="utf-8")
    return str(npz), str(js)


def blob(rng, centre, n, spread=0.03):
    return np.asarray(centre, float) + rng.normal(0, spread, (n, 3))


def two_chairs_one_cup(rng, dtype=np.float32):
    means = np.concatenate([blob(rng, (0, 0, 0.5), 400), blob(rng, (2, 0, 0.5), 300), blob(rng, (1, 1, 0.8), 200)])
    ids = np.array([1] * 700 + [2] * 200, dtype=np.uint8)
    return means.astype(dtype), ids


# --- loading and bad input ------------------------------------------------------------------------

def test_missing_files_name_the_parameter_and_path(tmp_path):
    npz, js = write_map(tmp_path, None)
    with pytest.raises(MapLoadError, match=r"map_path=.*params\.npz"):
        load_semantic_map(npz, js)
    rng = np.random.default_rng(0)
    m, i = two_chairs_one_cup(rng)
    npz, _ = write_map(tmp_path, {"means3D": m, "semantic_ids": i})
    with pytest.raises(MapLoadError, match=r"semantic_path=.*nope\.json"):
        load_semantic_map(npz, str(tmp_path / "nope.json"))


def test_wrong_keys_are_listed(tmp_path):
    npz, js = write_map(tmp_path, {"xyz": np.zeros((3, 3)), "semantic_ids": np.zeros(3, np.uint8)})
    with pytest.raises(MapLoadError, match=r"missing key\(s\) \['means3D'\].*xyz"):
        load_semantic_map(npz, js)


@pytest.mark.parametrize(
    "means, ids, pattern",
    [
        (np.zeros((4, 2)), np.zeros(4, np.uint8), r"means3D must be a real \[N, 3\]"),
        (np.zeros((4, 3, 1)), np.zeros(4, np.uint8), r"means3D must be a real \[N, 3\]"),
        (np.array([["a", "b", "c"]]), np.zeros(1, np.uint8), r"means3D must be a real"),
        (np.zeros((4, 3)), np.zeros(4, np.float32), r"semantic_ids must be an integer \[N\]"),
        (np.zeros((4, 3)), np.zeros((4, 2), np.int64), r"semantic_ids must be an integer \[N\]"),
        (np.zeros((4, 3)), np.zeros(5, np.int64), r"length mismatch: means3D has 4 rows, semantic_ids 5"),
    ],
)
def test_shape_dtype_and_length_mismatches(tmp_path, means, ids, pattern):
    npz, js = write_map(tmp_path, {"means3D": means, "semantic_ids": ids})
    with pytest.raises(MapLoadError, match=pattern):
        load_semantic_map(npz, js)


def test_not_an_npz_and_pickled_arrays_are_errors(tmp_path):
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"this is not a zip archive")
    _, js = write_map(tmp_path, None)
    with pytest.raises(MapLoadError, match="not a readable .npz"):
        load_semantic_map(str(bad), js)
    obj = np.empty(3, dtype=object)
    npz, js = write_map(tmp_path, {"means3D": np.zeros((3, 3)), "semantic_ids": obj}, name="pickled")
    with pytest.raises(MapLoadError, match="not a readable .npz"):
        load_semantic_map(npz, js)


@pytest.mark.parametrize(
    "text, pattern",
    [
        ('{"segmentation": [', "not valid JSON"),
        ("[1, 2]", "expected"),
        ('{"segmentation": [{"id": 1}]}', r"segmentation\[0\] needs 'id' and 'class'"),
        ('{"segmentation": [{"id": "1", "class": "chair"}]}', r"segmentation\[0\] has a bad id/class"),
        ('{"segmentation": [{"id": 1, "class": "  "}]}', r"segmentation\[0\] has a bad id/class"),
        ('{"segmentation": [{"id": 1, "class": "a"}, {"id": 1, "class": "b"}]}', "duplicate id 1 with two classes"),
        ("[" * 200_000, "not valid JSON"),  # nested deeper than the parser recurses
    ],
)
def test_malformed_semantic_json(tmp_path, text, pattern):
    npz, js = write_map(tmp_path, {"means3D": np.zeros((1, 3)), "semantic_ids": np.ones(1, np.uint8)}, raw_json=text)
    with pytest.raises(MapLoadError, match=pattern):
        load_semantic_map(npz, js)


def test_undecodable_json_is_an_error(tmp_path):
    npz, js = write_map(tmp_path, {"means3D": np.zeros((1, 3)), "semantic_ids": np.ones(1, np.uint8)})
    with open(js, "wb") as fh:
        fh.write(b"\xff\xfe\x00garbage")
    with pytest.raises(MapLoadError, match="not valid JSON"):
        load_semantic_map(npz, js)


def test_duplicate_id_with_same_class_is_a_warning(tmp_path):
    rng = np.random.default_rng(1)
    m, i = two_chairs_one_cup(rng)
    npz, js = write_map(tmp_path, {"means3D": m, "semantic_ids": i}, classes=[(1, "chair"), (1, "Chair"), (2, "cup")])
    db = ObjectDatabase.from_files(npz, js)
    assert db.names() == ["chair", "cup"]
    assert any("id 1 ('chair') is listed twice" in w for w in db.warnings)


def test_ids_missing_from_json_and_classes_missing_from_map_are_reported_not_fatal(tmp_path):
    rng = np.random.default_rng(2)
    m, i = two_chairs_one_cup(rng)
    i[:50] = 7  # 50 points of an id the table does not know
    npz, js = write_map(tmp_path, {"means3D": m, "semantic_ids": i}, classes=[(1, "chair"), (2, "cup"), (3, "sofa")])
    db = ObjectDatabase.from_files(npz, js)
    assert db.names() == ["chair", "cup"]
    text = "\n".join(db.warnings)
    assert "ignored 50 point(s)" in text and "id 7 (50 pts)" in text
    assert "without (usable) points in the map: sofa" in text
    assert db.stats.unlabelled == 50


def test_full_sgs_slam_key_set_is_accepted(tmp_path):
    rng = np.random.default_rng(3)
    m, i = two_chairs_one_cup(rng)
    n = len(m)
    arrays = {
        "means3D": m, "semantic_ids": i[:, None], "rgb_colors": rng.random((n, 3), dtype=np.float32),
        "unnorm_rotations": np.tile(np.float32([1, 0, 0, 0]), (n, 1)), "logit_opacities": np.full((n, 1), 3.0),
        "log_scales": np.full((n, 1), -4.0), "semantic_colors": rng.random((n, 3)),
        "cam_unnorm_rots": np.zeros((1, 4, 5)),
        "cam_trans": np.zeros((1, 3, 5)), "timestep": np.zeros(n), "intrinsics": np.eye(3), "w2c": np.eye(4),
    }
    npz, js = write_map(tmp_path, arrays)
    smap = load_semantic_map(npz, js)
    assert smap.semantic_ids.shape == (n,) and smap.logit_opacities.shape == (n,)
    db = ObjectDatabase.from_map(smap)
    assert db.names() == ["chair", "cup"] and len(db.instances("chair").instances) == 2


def test_bad_opacity_shape_is_ignored_with_a_warning(tmp_path):
    rng = np.random.default_rng(4)
    m, i = two_chairs_one_cup(rng)
    npz, js = write_map(tmp_path, {"means3D": m, "semantic_ids": i, "logit_opacities": np.zeros((3, 2))})
    smap = load_semantic_map(npz, js)
    assert smap.logit_opacities is None and "ignoring logit_opacities" in smap.warnings[0]


def test_non_finite_points_are_skipped_and_counted(tmp_path):
    rng = np.random.default_rng(5)
    m, i = two_chairs_one_cup(rng)
    m[:3] = np.nan
    m[3, 1] = np.inf
    npz, js = write_map(tmp_path, {"means3D": m, "semantic_ids": i})
    db = ObjectDatabase.from_files(npz, js)
    assert db.stats.non_finite == 4 and any("4 point(s) with NaN/inf" in w for w in db.warnings)
    r = db.query("cup")
    assert r.found and all(math.isfinite(v) for v in r.position)
    assert "NaN" not in db.to_json() and "Infinity" not in db.to_json()


def test_empty_map_gives_an_empty_database(tmp_path):
    npz, js = write_map(tmp_path, {"means3D": np.zeros((0, 3), np.float32), "semantic_ids": np.zeros(0, np.uint8)})
    db = ObjectDatabase.from_files(npz, js)
    assert db.names() == [] and db.to_json() == "{}"
    r = db.query("chair")
    assert not r.found and "map is empty" in r.message


def test_negative_and_huge_ids(tmp_path):
    rng = np.random.default_rng(6)
    m, _ = two_chairs_one_cup(rng)
    ids = np.array([-5] * 700 + [10**12] * 200, dtype=np.int64)
    smap = SemanticMap(m, ids, {-5: "chair", 10**12: "cup"})
    db = ObjectDatabase.from_map(smap)
    assert db.names() == ["chair", "cup"]
    assert np.allclose(db.query("cup").position, (1, 1, 0.8), atol=0.02)


# --- centroids ------------------------------------------------------------------------------------

def test_bincount_centroids_match_the_seed_method():
    rng = np.random.default_rng(7)
    n = 20000
    ids = rng.integers(0, 12, n).astype(np.uint8)
    means = rng.normal(0, 3, (n, 3)).astype(np.float32)
    classes = {i: f"class {i % 9}" for i in range(1, 11)}  # ids 9 and 10 share names with 0.. merged
    smap = SemanticMap(means, ids, classes)
    fast, slow = compute_centroids(smap), compute_centroids_masked(smap)
    assert fast.keys() == slow.keys() and len(fast) == 9
    for name in fast:
        np.testing.assert_allclose(fast[name], slow[name], rtol=1e-9, atol=1e-9)


# --- instances, robust centres ------------------------------------------------------------------

def test_two_chairs_are_two_instances_with_boxes_and_counts():
    rng = np.random.default_rng(8)
    m, i = two_chairs_one_cup(rng, np.float64)
    db = ObjectDatabase.from_map(SemanticMap(m, i, {1: "chair", 2: "cup"}))
    res = db.instances("chair")
    assert [x.point_count for x in res.instances] == [400, 300] and res.distances == (-1.0, -1.0)
    big, small = res.instances
    assert big.label == "chair#1" and np.allclose(big.centre, m[:400].mean(0))
    assert np.allclose(big.bbox_min, m[:400].min(0)) and np.allclose(big.bbox_max, m[:400].max(0))
    assert np.allclose(small.bbox_min, m[400:700].min(0)) and np.allclose(small.bbox_max, m[400:700].max(0))
    near = db.instances("CHAIR", reference=(2.1, 0, 0))
    assert near.instances[0].index == 2 and near.distances[0] < near.distances[1]
    assert math.isclose(near.distances[0], float(np.linalg.norm(np.asarray(small.centre) - (2.1, 0, 0))))
    q = db.query("chair")
    assert q.found and np.allclose(q.position, big.centre) and "2 instances of chair" in q.message
    for bad in ((math.nan, 0, 0), (1e308, 0, 0), (0, math.inf, 0)):  # said, not ignored
        res = db.instances("chair", reference=bad)
        assert not res.found and "reference must be three finite numbers within 1000 m" in res.message


def test_query_position_class_is_the_centre_of_all_instances():
    rng = np.random.default_rng(9)
    m, i = two_chairs_one_cup(rng, np.float64)
    db = ObjectDatabase.from_map(SemanticMap(m, i, {1: "chair", 2: "cup"}), DatabaseConfig(query_position="class"))
    assert np.allclose(db.query("chair").position, m[:700].mean(0))


def test_transparent_floaters_are_ignored_and_isolated_ones_are_noise():
    rng = np.random.default_rng(10)
    m, i = two_chairs_one_cup(rng, np.float64)
    floaters = rng.random((30, 3)) * 10 + 20  # far away, scattered
    means = np.concatenate([m, floaters])
    ids = np.concatenate([i, np.full(30, 2, np.uint8)])
    opac = np.concatenate([np.full(len(m), 4.0), np.full(30, -6.0)])
    with_opacity = ObjectDatabase.from_map(SemanticMap(means, ids, {1: "chair", 2: "cup"}, opac))
    assert with_opacity.stats.transparent == 30 and with_opacity.stats.noise == 0
    no_opacity = ObjectDatabase.from_map(SemanticMap(means, ids, {1: "chair", 2: "cup"}))
    assert no_opacity.stats.noise == 30 and len(no_opacity.instances("cup").instances) == 1
    for db in (with_opacity, no_opacity):
        assert np.allclose(db.query("cup").position, m[700:].mean(0))
    seed_like = compute_centroids(SemanticMap(means, ids, {1: "chair", 2: "cup"}))
    assert np.linalg.norm(seed_like["cup"] - m[700:].mean(0)) > 1.0  # what the seed would have answered


def test_robust_centres_resist_outliers_in_an_instance():
    rng = np.random.default_rng(11)
    core = blob(rng, (1, 1, 1), 500, 0.02)
    tail = np.linspace((1.05, 1, 1), (1.6, 1, 1), 40)  # a dense streak attached to the object
    means = np.concatenate([core, tail])
    smap = SemanticMap(means, np.ones(len(means), np.uint8), {1: "vase"})
    mean = ObjectDatabase.from_map(smap, DatabaseConfig(voxel_size=0.05)).query("vase").position
    median = ObjectDatabase.from_map(smap, DatabaseConfig(voxel_size=0.05, centre_method="median")).query("vase")
    trimmed = ObjectDatabase.from_map(smap, DatabaseConfig(voxel_size=0.05, centre_method="trimmed_mean",
                                                           trim_fraction=0.1)).query("vase")
    assert mean[0] > 1.02
    assert abs(median.position[0] - 1.0) < 0.01 and abs(trimmed.position[0] - 1.0) < 0.01
    assert np.allclose(median.position, np.median(means, axis=0))


def test_class_with_only_scattered_points_still_answers():
    rng = np.random.default_rng(12)
    means = rng.random((10, 3)) * 5
    db = ObjectDatabase.from_map(SemanticMap(means, np.ones(10, np.uint8), {1: "key"}))
    r = db.query("key")
    assert r.found and np.min(np.linalg.norm(means - np.array(r.position), axis=1)) < 1e-6  # one of its points
    assert any("only 10 scattered point(s)" in w for w in db.warnings)


def test_small_objects_far_apart_are_not_answered_by_the_space_between_them():
    """Two cups seen from afar: 12 and 8 points, each below min_instance_points (20). The answer is the larger
    cup, not the middle of the room between them (measured on the exploring robot's map: 1.3 m off)."""
    rng = np.random.default_rng(3)
    big = np.array([4.6, 0.35, 0.95]) + rng.normal(0, 0.01, (12, 3))
    small = np.array([2.8, 2.6, 0.8]) + rng.normal(0, 0.01, (8, 3))
    db = ObjectDatabase.from_map(SemanticMap(np.vstack([big, small]), np.ones(20, np.uint8), {1: "cup"}))
    r = db.query("cup")
    assert np.allclose(r.position, big.mean(0), atol=1e-6), r
    inst = db.instances("cup").instances
    assert [i.point_count for i in inst] == [12, 8]
    assert np.allclose(inst[1].centre, small.mean(0), atol=1e-6)
    assert any("only 20 scattered point(s)" in w and "2 small component(s)" in w for w in db.warnings)


@pytest.mark.parametrize("bad", [dict(voxel_size=0), dict(voxel_size=float("nan")), dict(min_instance_points=0),
                                 dict(min_opacity=1.0), dict(centre_method="mode"), dict(trim_fraction=0.5),
                                 dict(query_position="smallest")])
def test_config_is_validated(bad):
    with pytest.raises(ValueError):
        DatabaseConfig(**bad)


# --- names --------------------------------------------------------------------------------------

@pytest.fixture
def sample_db():
    rng = np.random.default_rng(13)
    m, i = two_chairs_one_cup(rng)
    syn = Synonyms((("sofa", "couch"), ("cup", "mug"), ("bin", "trash can")))
    return ObjectDatabase.from_map(SemanticMap(m, i, {1: "chair", 2: "mug"}), synonyms=syn)


@pytest.mark.parametrize("spoken, expected", [("Chair", "chair"), ("  CHAIR  ", "chair"), ("cup", "mug"),
                                              ("MUG", "mug"), ("chairs", "chair"), ("cups", "mug"),
                                              ("ｃｈａｉｒ", "chair"), ("the red chair", "chair"),
                                              ("coffee mugs", "mug"), ("big blue coffee cup", "mug")])
def test_names_people_use_resolve(sample_db, spoken, expected):
    r = sample_db.query(spoken)
    assert r.found, r.message
    assert r.message.startswith(f"{expected} at")


def test_unknown_names_get_suggestions(sample_db):
    r = sample_db.query("chiar")
    assert not r.found and "did you mean: chair?" in r.message and "'chiar'" in r.message
    r = sample_db.query("unicorn")
    assert not r.found and "did you mean" not in r.message and "known: chair, mug" in r.message


@pytest.mark.parametrize("name, pattern", [("", "empty object name"), ("   \t\n", "empty object name"),
                                           ("x" * 100_000, "too long (100000 characters")])
def test_empty_and_huge_names(sample_db, name, pattern):
    r = sample_db.query(name)
    assert not r.found and pattern in r.message and len(r.message) < 400
    assert not sample_db.instances(name).found


def test_unicode_names_and_classes(tmp_path):
    rng = np.random.default_rng(14)
    m, i = two_chairs_one_cup(rng)
    npz, js = write_map(tmp_path, {"means3D": m, "semantic_ids": i}, classes=[(1, "Stuhl"), (2, "Tasse ☕")])
    db = ObjectDatabase.from_files(npz, js)
    assert db.query("stuhl").found and db.query("TASSE ☕").found
    r = db.query("椅子\x00\u200b")
    assert not r.found and "椅子" in r.message
    assert json.loads(db.to_json()).keys() == {"stuhl", "tasse ☕"}


@pytest.mark.parametrize("id_values, dtype", [([-3, 0, 7], np.int64), ([5, 10**12, 2**40 + 1], np.int64),
                                             ([65535, 1, 300], np.uint16), ([-128, 127, 0], np.int8)])
def test_bincount_centroids_with_negative_huge_and_wide_ids(id_values, dtype):
    rng = np.random.default_rng(15)
    ids = rng.choice(np.array(id_values, dtype=dtype), 3000)
    means = rng.normal(0, 2, (3000, 3))
    smap = SemanticMap(means, ids, {id_values[0]: "a", id_values[1]: "b", id_values[2]: "a"})
    valid = rng.random(3000) > 0.2
    fast = compute_centroids(smap, valid)
    for name, members in (("a", [id_values[0], id_values[2]]), ("b", [id_values[1]])):
        sel = np.isin(ids, members) & valid
        np.testing.assert_allclose(fast[name], means[sel].mean(0))
    assert compute_centroids(smap).keys() == compute_centroids_masked(smap).keys()


def test_far_away_points():
    rng = np.random.default_rng(16)
    m, i = two_chairs_one_cup(rng, np.float64)
    means = np.concatenate([m, [[1e15, -1e15, 3e14]]])
    ids = np.concatenate([i, [2]]).astype(np.uint8)
    # a transparent far-away floater is clamped away and changes nothing
    opac = np.concatenate([np.full(len(m), 4.0), [-9.0]])
    db = ObjectDatabase.from_map(SemanticMap(means, ids, {1: "chair", 2: "cup"}, opac))
    assert len(db.instances("chair").instances) == 2 and np.allclose(db.query("cup").position, m[700:].mean(0))
    # an opaque one makes the grid impossible: a clear error, not a crash
    with pytest.raises(MapLoadError, match="raise voxel_size or remove far-away points"):
        ObjectDatabase.from_map(SemanticMap(means, ids, {1: "chair", 2: "cup"}))


def test_query_one_instance_by_label(sample_db):
    all_chairs = sample_db.instances("chair").instances
    r = sample_db.query("Chair #2")
    assert r.found and np.allclose(r.position, all_chairs[1].centre) and r.message.startswith("chair#2 at")
    assert sample_db.query("mug#1").found  # labels work with synonyms too
    r = sample_db.query("chair#3")
    assert not r.found and "there are 2 instance(s) of chair (chair#1..chair#2)" in r.message
    assert not sample_db.query("chair#0").found
    assert not sample_db.query("unicorn#1").found and "unknown object" in sample_db.query("unicorn#1").message


def test_int8_ids_spanning_the_whole_range():
    rng = np.random.default_rng(17)
    m, _ = two_chairs_one_cup(rng, np.float64)
    ids = np.array([-128] * 700 + [127] * 200, dtype=np.int8)
    db = ObjectDatabase.from_map(SemanticMap(m, ids, {-128: "chair", 127: "cup"}))
    assert db.names() == ["chair", "cup"] and len(db.instances("chair").instances) == 2
    assert np.allclose(db.query("cup").position, m[700:].mean(0))


def test_ids_beyond_a_signed_64_bit_integer_and_a_corrupt_archive_are_map_errors(tmp_path):
    """Once an OverflowError (ids >= 2^63) and a zlib error (a damaged compressed member): the server's reload thread
    died with them and answered no reload again."""
    npz, js = write_map(tmp_path, {"means3D": np.zeros((2, 3)), "semantic_ids": np.array([1, 2**63], np.uint64)})
    with pytest.raises(MapLoadError, match="ids must fit a signed 64-bit integer"):
        load_semantic_map(npz, js)
    means = np.random.default_rng(0).normal(size=(2000, 3))
    np.savez_compressed(npz, means3D=means, semantic_ids=np.ones(2000, np.int32))
    data = bytearray(open(npz, "rb").read())
    middle = len(data) // 2
    data[middle:middle + 64] = bytes(64)  # damage the deflate stream, not the zip directory
    open(npz, "wb").write(bytes(data))
    with pytest.raises(MapLoadError, match="not a readable .npz"):
        load_semantic_map(npz, js)
