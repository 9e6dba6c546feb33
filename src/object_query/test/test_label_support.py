"""The object database's label-support rule (``DatabaseConfig.min_label_views``) on small synthetic maps."""

from __future__ import annotations

import json

import numpy as np
import pytest

from object_query.semantic_map import (
    DatabaseConfig,
    ObjectDatabase,
    SemanticMap,
    label_views_threshold,
    load_semantic_map,
)


def _blob(centre, n, rng):
    return np.asarray(centre, np.float32) + rng.normal(0, 0.02, (n, 3)).astype(np.float32)


def _map():
    """Two cups (one named in 12 views, one in 2), an apple named in 1 view, a wall seen in 40: vote columns 1, 2, 3."""
    rng = np.random.default_rng(0)
    parts = [(_blob((0, 0, 1), 60, rng), 1, 12), (_blob((2, 0, 1), 40, rng), 1, 2), (_blob((0, 2, 1), 50, rng), 2, 1),
             (_blob((4, 4, 1), 80, rng), 3, 40)]
    means = np.concatenate([p[0] for p in parts])
    ids = np.concatenate([np.full(len(p[0]), p[1], np.uint8) for p in parts])
    vote_ids = np.array([1, 2, 3], np.int64)
    votes = np.zeros((len(means), 3), np.float32)
    start = 0
    for pts, sid, views in parts:
        col = int(np.flatnonzero(vote_ids == sid)[0])
        votes[start:start + len(pts), col] = rng.integers(0, views + 1, len(pts))
        votes[start, col] = views  # the best-seen point of the blob
        start += len(pts)
    return means, ids, votes, vote_ids, {1: "cup", 2: "apple", 3: "wall"}


def test_instances_named_in_few_views_are_dropped():
    means, ids, votes, vote_ids, classes = _map()
    db = ObjectDatabase.from_map(SemanticMap(means, ids, classes, votes=votes, vote_ids=vote_ids))
    cups = db.instances("cup").instances
    assert len(cups) == 1 and np.allclose(cups[0].centre, (0, 0, 1), atol=0.02)  # the 2-view cup is gone
    assert not db.query("apple").found  # a class left without supported instances is dropped
    assert db.query("wall").found
    assert db.stats.unsupported == 90
    assert any("fewer than 5 views" in w and "apple" in w for w in db.warnings)


def test_rule_off_and_maps_without_votes_keep_every_instance():
    means, ids, votes, vote_ids, classes = _map()
    off = ObjectDatabase.from_map(SemanticMap(means, ids, classes, votes=votes, vote_ids=vote_ids),
                                  DatabaseConfig(min_label_views=0))
    plain = ObjectDatabase.from_map(SemanticMap(means, ids, classes))
    for db in (off, plain):
        assert len(db.instances("cup").instances) == 2 and db.query("apple").found
    low = ObjectDatabase.from_map(SemanticMap(means, ids, classes, votes=votes, vote_ids=vote_ids),
                                  DatabaseConfig(min_label_views=2))
    assert len(low.instances("cup").instances) == 2 and not low.query("apple").found
    with pytest.raises(ValueError, match="min_label_views"):
        DatabaseConfig(min_label_views=-1)


def test_votes_are_read_from_the_map_file_and_bad_ones_ignored(tmp_path):
    means, ids, votes, vote_ids, classes = _map()
    sem = tmp_path / "semantic.json"
    sem.write_text(json.dumps({"segmentation": [{"id": k, "class": v} for k, v in classes.items()]}))
    good, bad = tmp_path / "good.npz", tmp_path / "bad.npz"
    np.savez(good, means3D=means, semantic_ids=ids, semantic_votes=votes, semantic_feature_ids=vote_ids)
    np.savez(bad, means3D=means, semantic_ids=ids, semantic_votes=votes[:, :2], semantic_feature_ids=vote_ids)
    assert len(ObjectDatabase.from_files(str(good), str(sem)).instances("cup").instances) == 1
    smap = load_semantic_map(str(bad), str(sem))
    assert smap.votes is None and any("ignoring semantic_votes" in w for w in smap.warnings)
    assert len(ObjectDatabase.from_map(smap).instances("cup").instances) == 2


def test_a_short_map_needs_fewer_views():
    """A map whose best-seen Gaussian has 16 votes (16 frames) asks for 16 / 8 = 2 views; 7 votes: 1 view."""
    means, ids, votes, vote_ids, classes = _map()
    assert label_views_threshold(votes, 5) == 5 and label_views_threshold(votes, 0) == 0
    short = np.minimum(votes, 16)
    assert label_views_threshold(short, 5) == 2
    db = ObjectDatabase.from_map(SemanticMap(means, ids, classes, votes=short, vote_ids=vote_ids))
    assert len(db.instances("cup").instances) == 2 and not db.query("apple").found
    tiny = np.minimum(votes, 7)
    db = ObjectDatabase.from_map(SemanticMap(means, ids, classes, votes=tiny, vote_ids=vote_ids))
    assert label_views_threshold(tiny, 5) == 1 and db.query("apple").found


def test_a_class_of_scattered_points_is_judged_too():
    """A class with no component of min_instance_points (15 points) is dropped when named in 1 view, kept in 9."""
    means, ids, votes, vote_ids, classes = _map()
    rng = np.random.default_rng(1)
    far = rng.uniform(-3, -2, (15, 3)).astype(np.float32)  # 15 points 0.1 m voxels apart or more: no component
    far[:, 0] = -2 - 0.3 * np.arange(15)
    means = np.vstack([means, far])
    ids = np.r_[ids, np.full(15, 4, np.uint8)]
    votes = np.hstack([votes, np.zeros((len(votes), 1), np.float32)])
    votes = np.vstack([votes, np.zeros((15, 4), np.float32)])
    votes[-15:, 3] = 1
    vote_ids = np.r_[vote_ids, 4]
    classes = {**classes, 4: "bottle"}
    db = ObjectDatabase.from_map(SemanticMap(means, ids, classes, votes=votes, vote_ids=vote_ids))
    assert not db.query("bottle").found and db.stats.unsupported == 105
    votes[-1, 3] = 9
    db = ObjectDatabase.from_map(SemanticMap(means, ids, classes, votes=votes, vote_ids=vote_ids))
    assert db.query("bottle").found
