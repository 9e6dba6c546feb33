"""What ``/object_query`` and ``/object_list`` answer: the object memory's current belief over the map (no ROS).

One rule for both: while every belief of a class is just what the map shows (source ``map``, state ``seen``), the
map answers (its ``query_position``: the largest instance by default); once the robot or a person changed something
(held, placed, unseen after a failed grasp, set), the memory's best belief answers. ``/object_list`` is each
name's ``/object_query`` position, so the two never disagree.
"""

from __future__ import annotations

import json
import re

from object_query.memory import Belief, ObjectMemory
from object_query.names import normalise_name
from object_query.semantic_map import ObjectDatabase, QueryResult

_INSTANCE_ID = re.compile(r"^(.+?)\s*#\s*(\d{1,6})$")  # "cup#2", "cup #2"


def answer_query(memory: ObjectMemory, db: ObjectDatabase, name: str) -> QueryResult:
    """``/object_query``'s answer: the current belief, the seed's contract kept (see the module docstring).

    While every belief of the class is just what the map shows (source ``map``, state ``seen``),
    the map answers as before (its ``query_position``, its messages). Once the robot or a person
    changed something (held, placed, unseen after a failed grasp, set), the memory's best belief
    answers. ``name`` may be an instance id (``cup#2``: the memory's ids equal the map's labels
    until objects move).
    """
    label = _INSTANCE_ID.match(normalise_name(name)[:300])
    if label is not None:
        key, _ = db.resolve(label.group(1))
        belief = memory.get(f"{key or normalise_name(label.group(1))}#{int(label.group(2))}")
        if belief is None or _as_mapped(belief):
            return db.query(name)
        return _belief_answer(belief, f"{belief.id} at", memory)
    key, note = db.resolve(name)
    if key is None:
        key = normalise_name(name)
        group = memory.candidates(key)
        if not group:
            return QueryResult(False, (0.0, 0.0, 0.0), note)
        if all(b.source == "map" and b.state == "unseen" for b in group):
            # the map no longer has the class at all and nothing since says where it is: not found
            # (a stale position must not send the robot there), with where it was last seen
            b = group[0]
            x, y, z = b.position
            return QueryResult(False, (0.0, 0.0, 0.0),
                               f"{note}; {key} was last seen at ({x:.3f}, {y:.3f}, {z:.3f}) ({b.id}), "
                               "but the current map no longer shows it")
    group = memory.candidates(key)
    if not group or all(_as_mapped(b) for b in group):
        return db.query(name)
    return _belief_answer(group[0], f"{key} at", memory)


def _as_mapped(b: Belief) -> bool:
    return b.source == "map" and b.state == "seen"


def _belief_answer(belief: Belief, head: str, memory: ObjectMemory) -> QueryResult:
    x, y, z = belief.position
    at = f" at {belief.place}" if belief.place else ""
    where = {"held": "in the robot's gripper", "placed": f"put down by the robot{at}",
             "unseen": "not seen there lately", "seen": "seen in the map"}[belief.state]
    msg = f"{head} ({x:.3f}, {y:.3f}, {z:.3f}): {belief.id}, {where}; source {belief.source}, " \
          f"confidence {belief.confidence:.2f}"
    if belief.note:
        msg += f" ({belief.note})"
    n = len(memory.candidates(belief.name))
    if n > 1:
        msg += f"; {n} instances of {belief.name}, this is the current best belief; see /object_memory"
    return QueryResult(True, (x, y, z), msg)


def object_list(memory: ObjectMemory, db: ObjectDatabase) -> dict[str, list[float]]:
    """``/object_list``: every name of ``db`` with its :func:`answer_query` position (metres, 4 decimals).

    A name whose answer is not found (a class the map still lists but nothing places now) keeps the map's position.
    """
    doc = json.loads(db.to_json())
    for name in doc:
        answer = answer_query(memory, db, name)
        if answer.found:
            doc[name] = [round(float(v), 4) for v in answer.position]
    return doc
