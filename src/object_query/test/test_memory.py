"""The living object memory's core, without ROS: map merges, action evidence, persistence."""

from __future__ import annotations

import json
import math
import os
import re

import pytest

from object_query.errors import ObjectMemoryError
from object_query.memory import (
    Belief,
    MapObservation,
    MemoryConfig,
    ObjectMemory,
    load_memory,
    memory_from_json,
)


class Clock:
    def __init__(self, t: float = 1000.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


MAP = [MapObservation("bottle", (5.2, 0.3, 1.0)), MapObservation("cup", (4.6, 0.35, 0.95)),
       MapObservation("cup", (2.8, 2.6, 0.8)), MapObservation("trash", (2.3, 2.5, 0.8))]


def fresh(clock: Clock | None = None) -> ObjectMemory:
    mem = ObjectMemory(clock=clock or Clock())
    mem.merge_map(MAP, observed_at=900.0)
    return mem


def by_pos(mem: ObjectMemory, name: str, x: float) -> Belief:
    return min(mem.candidates(name), key=lambda b: abs(b.position[0] - x))


def test_first_map_creates_beliefs_with_ids_confidence_source() -> None:
    mem = fresh()
    snap = mem.snapshot()
    assert [b.id for b in snap] == ["bottle#1", "cup#1", "cup#2", "trash#1"]
    assert all(b.source == "map" and b.confidence == 1.0 and b.last_seen == 900.0 and b.state == "seen"
               for b in snap)


def test_reload_keeps_ids_moves_moved_and_marks_vanished_unseen() -> None:
    mem = fresh()
    cup_table = by_pos(mem, "cup", 2.8).id
    cup_counter = by_pos(mem, "cup", 4.6).id
    report = mem.merge_map([MapObservation("bottle", (5.25, 0.3, 1.0)),      # shifted 5 cm: same
                            MapObservation("cup", (4.6, 0.35, 0.95)),        # same
                            MapObservation("cup", (1.3, 3.9, 0.75)),         # the table cup moved to the sofa
                            MapObservation("chair", (2.5, 1.7, 0.4))],       # new
                           observed_at=950.0)
    assert set(report.kept) == {"bottle#1", cup_counter}
    assert report.moved == (cup_table,)
    assert report.added == ("chair#1",)
    assert report.unseen == ("trash#1",)
    assert mem.get(cup_table).position == (1.3, 3.9, 0.75)
    trash = mem.get("trash#1")
    assert trash.state == "unseen" and trash.confidence == pytest.approx(0.5) and trash.position == (2.3, 2.5, 0.8)
    assert mem.get("bottle#1").last_seen == 950.0


def test_grasp_then_place_follows_the_object_and_wins_over_an_older_map() -> None:
    clock = Clock(1000.0)
    mem = fresh(clock)
    held = mem.grasped("cup", near=(2.2, 2.5))  # robot at the table: the table cup
    assert held.state == "held" and held.source == "action" and held.place == "gripper"
    assert held.position == (2.8, 2.6, 0.8)  # the table cup, not the counter one
    assert mem.best("cup").id == held.id  # held objects answer first
    clock.t = 1010.0
    placed = mem.placed("cup", (1.3, 3.95, 0.75), "user")
    assert placed.id == held.id and placed.place == "user" and placed.state == "placed"
    # the old map (observed before the place) still shows the cup on the table: the action is newer
    report = mem.merge_map(MAP, observed_at=900.0)
    assert held.id in report.newer_than_map
    assert mem.get(held.id).position == (1.3, 3.95, 0.75)
    assert len(mem.candidates("cup")) == 2  # no duplicate created for the stale map blob
    # a newer map shows the cup at the user: confirmed by the map
    mem.merge_map([*MAP[:2], MapObservation("cup", (1.32, 3.93, 0.75)), MAP[3]], observed_at=1020.0)
    assert mem.get(held.id).source == "map" and mem.get(held.id).state == "seen"


def test_failed_grasp_lowers_confidence_and_best_prefers_a_trusted_one() -> None:
    mem = fresh()
    counter = by_pos(mem, "cup", 4.6)
    after = mem.grasp_failed("cup", near=(4.9, 1.1), reason="no cup within reach")
    assert after.id == counter.id
    assert after.confidence == pytest.approx(0.3) and "found nothing" in after.note and after.state == "unseen"
    assert mem.best("cup").id != counter.id
    assert mem.grasp_failed("sofa", near=(0, 0)) is None


def test_revision_increases_with_every_change() -> None:
    mem = fresh()
    r = mem.revision
    mem.grasped("bottle", near=(4.9, 1.1))
    assert mem.revision == r + 1


def test_set_position_by_user_and_bad_input() -> None:
    mem = fresh()
    b = mem.set_position("trash#1", (5.6, 4.5, 0.5), source="user", place="bin")
    assert b.source == "user" and b.place == "bin"
    with pytest.raises(ObjectMemoryError):
        mem.set_position("trash#1", (float("nan"), 0, 0))
    with pytest.raises(ObjectMemoryError):
        mem.set_position("trash#1", (0, 0, 0), source="rumour")


def test_save_is_atomic_and_roundtrips(tmp_path) -> None:
    mem = fresh()
    mem.grasped("bottle", near=(4.9, 1.1))
    path = str(tmp_path / "maps" / "home.memory.json")
    mem.save(path)
    assert not [f for f in os.listdir(tmp_path / "maps") if f.endswith(".tmp")]
    back, message = load_memory(path)
    assert back.snapshot() == mem.snapshot()
    assert "4 belief(s)" in message


@pytest.mark.parametrize("content", ["{not json", json.dumps({"version": 99, "beliefs": []}),
                                     json.dumps({"version": 1, "beliefs": [{"id": "x"}]}),
                                     json.dumps({"version": 1, "beliefs": [
                                         {"id": "cup#1", "name": "cup", "position": [0, 0, "nan"],
                                          "confidence": 1, "last_seen": 0, "source": "map"}]}),
                                     "\udcff"])
def test_corrupt_file_is_reported_and_set_aside(tmp_path, content) -> None:
    path = tmp_path / "m.json"
    path.write_bytes(content.encode("utf-8", "surrogateescape"))
    mem, message = load_memory(str(path), clock=Clock(1234.0))
    assert mem.snapshot() == ()
    assert "corrupt" in message and "set aside" in message
    assert not path.exists() and (tmp_path / "m.json.corrupt-1234").exists()


def test_missing_file_starts_empty(tmp_path) -> None:
    mem, message = load_memory(str(tmp_path / "none.json"))
    assert mem.snapshot() == () and "starting empty" in message


def test_duplicate_ids_rejected() -> None:
    b = Belief("cup#1", "cup", (0.0, 0.0, 0.0), 1.0, 0.0, "map")
    with pytest.raises(ObjectMemoryError):
        memory_from_json(json.dumps({"version": 1, "beliefs": [b.__dict__, b.__dict__]}))


def test_config_validation() -> None:
    with pytest.raises(ValueError):
        MemoryConfig(match_radius=-1)
    with pytest.raises(ValueError):
        MemoryConfig(trust_threshold=2)


def test_vanished_objects_are_forgotten_after_a_few_reloads_and_bad_centres_ignored() -> None:
    mem = fresh()
    without_trash = [o for o in MAP if o.name != "trash"] + [MapObservation("cup", (float("nan"), 0.0, 0.0))]
    confidences = []
    for t in range(5):
        report = mem.merge_map(without_trash, observed_at=901.0 + t)
        b = mem.get("trash#1")
        confidences.append(None if b is None else b.confidence)
        assert not report.added  # the NaN cup is ignored
    assert confidences == [0.5, 0.25, 0.125, 0.0625, None]
    assert report.forgotten == ("trash#1",)


def _blob_db(classes: dict[int, str], centres: dict[int, tuple[float, float, float]]):
    import numpy as np

    from object_query.semantic_map import ObjectDatabase, SemanticMap
    rng = np.random.default_rng(0)
    means = np.concatenate([rng.normal(centres[k], 0.02, (200, 3)) for k in centres]).astype(np.float32)
    ids = np.concatenate([np.full(200, k) for k in centres])
    return ObjectDatabase.from_map(SemanticMap(means, ids, classes))


def test_object_query_does_not_send_the_robot_to_a_class_the_new_map_no_longer_has() -> None:
    from object_query.answers import answer_query
    old = _blob_db({1: "placeholder", 2: "chair"}, {1: (1.0, 1.0, 0.5), 2: (3.0, 1.0, 0.5)})
    new = _blob_db({2: "chair"}, {2: (3.0, 1.0, 0.5)})
    mem = ObjectMemory(clock=Clock())
    mem.merge_map((MapObservation(i.name, i.centre) for i in old.all_instances()), observed_at=900.0)
    assert answer_query(mem, old, "placeholder").found
    mem.merge_map((MapObservation(i.name, i.centre) for i in new.all_instances()), observed_at=950.0)
    gone = answer_query(mem, new, "placeholder")
    assert not gone.found and "no longer shows it" in gone.message and "last seen at (0.99" in gone.message
    assert answer_query(mem, new, "chair").found
    # what the robot itself did still counts when the map lacks the class: the held object is found
    mem.grasped("placeholder", (1.0, 1.0, 0.0))
    assert answer_query(mem, new, "placeholder").found


def test_object_list_gives_each_name_its_object_query_position() -> None:
    """``/object_list`` agrees with ``/object_query``: while the map alone places the cups the largest one (the map's
    ``query_position``), not the cup the memory happened to see first; after a grasp the held cup."""
    import numpy as np

    from object_query.answers import answer_query, object_list
    from object_query.semantic_map import ObjectDatabase, SemanticMap

    def db_of(blobs: list[tuple[int, tuple[float, float, float], int]]) -> ObjectDatabase:
        rng = np.random.default_rng(0)
        means = np.concatenate([rng.normal(c, 0.02, (n, 3)) for _, c, n in blobs]).astype(np.float32)
        ids = np.concatenate([np.full(n, k) for k, _, n in blobs])
        return ObjectDatabase.from_map(SemanticMap(means, ids, {1: "cup", 2: "chair"}))

    small, large, chair = (4.6, 0.35, 0.95), (2.8, 2.6, 0.8), (1.0, 1.0, 0.5)
    first = db_of([(1, small, 60), (2, chair, 100)])  # only the small cup seen yet: it becomes cup#1
    later = db_of([(1, small, 60), (1, large, 300), (2, chair, 100)])
    mem = ObjectMemory(clock=Clock())
    for db, at in ((first, 900.0), (later, 950.0)):
        mem.merge_map((MapObservation(i.name, i.centre) for i in db.all_instances()), observed_at=at)
    assert mem.best("cup").id == "cup#1" and math.dist(mem.best("cup").position, small) < 0.05
    listed = object_list(mem, later)
    assert set(listed) == {"cup", "chair"}
    assert math.dist(listed["cup"], large) < 0.05, listed  # the map's largest cup, as /object_query says
    assert listed["cup"] == [round(v, 4) for v in answer_query(mem, later, "cup").position]
    assert math.dist(listed["chair"], chair) < 0.05
    mem.grasped("cup", small)  # the robot picked up the small cup: now the memory answers
    assert object_list(mem, later)["cup"] == [round(v, 4) for v in mem.get("cup#1").position]


@pytest.mark.parametrize("args, words", [
    (("teleported", "cup", None), "unknown event 'teleported'"),
    (("set", "x" * 2000, (1.0, 2.0, 3.0)), "name too long (2000 characters, at most 1024)"),
    (("set", "x " * 300, (1.0, 2.0, 3.0)), "name too long (599 characters after normalisation, at most 256)"),
    (("placed", "cup", (1.0, 2.0, 3.0), "y" * 5000), "place too long (5000 characters"),
    (("set", "cup", (1001.0, 0.0, 0.0)), "within 1000 m of the map's origin, got (1001, 0, 0)"),
    (("set", "cup", (math.nan, 0.0, 0.0)), "position must be finite"),
    (("grasp_failed", "cup", None, "", "z" * 1001), "detail too long (1001 characters, at most 1000)"),
])
def test_a_report_the_memory_cannot_take_is_refused_with_the_reason(args, words):
    from object_query.memory import check_report

    with pytest.raises(ObjectMemoryError, match=re.escape(words)):
        check_report(*args)
    check_report("placed", "cup", (1000.0, -1000.0, 0.0), "user", "z" * 1000)  # the limits themselves are fine
