"""The living object memory: where each object is *now*, and why we think so (no ROS).

The semantic map says where things were when the camera last saw them; the robot's own actions
say where it put them since. :class:`ObjectMemory` keeps one :class:`Belief` per object instance
and updates it from three sources:

* ``map``: a (re)loaded semantic map (:meth:`ObjectMemory.merge_map`). Map instances are matched
  to beliefs of the same class, nearest first: within ``match_radius`` they are the same object
  (it may have shifted a little), farther away but still unmatched on both sides they are the
  same object that *moved* (same id, new position). New instances get new ids; beliefs the map no
  longer shows are marked ``unseen`` and lose confidence (and are forgotten after a few such
  reloads). A belief set by an action *after* the map
  was observed (``observed_at``) is newer than the map and is kept as it is.
* ``action``: the robot's own grasps and places (:meth:`ObjectMemory.grasped`,
  :meth:`ObjectMemory.placed`, :meth:`ObjectMemory.grasp_failed` — negative evidence: the object
  was not where we thought, its confidence drops).
* ``user``: someone says or sets where an object is (:meth:`ObjectMemory.set_position`).

Persistence: :meth:`ObjectMemory.save` writes JSON atomically (temporary file, fsync, rename);
:func:`load_memory` reads it back and sets a corrupt file aside (renamed ``*.corrupt-<time>``)
with a warning instead of failing.

Thread safety: every public method takes the memory's lock; beliefs are immutable.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, replace

from object_query.errors import ObjectMemoryError
from object_query.names import MAX_COORD_M, MAX_NAME_LENGTH, normalise_name, raw_name_error

#: Where a belief came from.
SOURCES = ("map", "action", "user")
#: What we know of the object's state.
STATES = ("seen", "unseen", "held", "placed")
#: Version of the file format written by :meth:`ObjectMemory.save`.
FILE_VERSION = 1


#: What a report to the memory says happened (``/object_memory/report``'s ``event``)
EVENTS = ("grasped", "grasp_failed", "placed", "set")
#: Longest ``detail`` of a report (characters): a failure's reason, kept as the belief's note
MAX_DETAIL_CHARS = 1000


def check_report(event: str, name: str, position: tuple[float, float, float] | None, place: str = "",
                 detail: str = "") -> None:
    """Refuse a report the memory cannot take, before anything is looked up or changed.

    Raises:
        ObjectMemoryError: an unknown event; a name or place over :data:`~object_query.names.MAX_RAW_NAME_LENGTH`
            characters as sent or :data:`~object_query.names.MAX_NAME_LENGTH` once normalised; a position not
            finite or farther than :data:`~object_query.names.MAX_COORD_M` from the map's origin; a ``detail`` over
            :data:`MAX_DETAIL_CHARS` characters.
    """
    if event not in EVENTS:
        raise ObjectMemoryError(f"unknown event {event[:40]!r}; known: {', '.join(EVENTS)}")
    for text, what in ((name, "name"), (place, "place")):
        refused = raw_name_error(text, what)
        if refused:
            raise ObjectMemoryError(refused)
        if len(normalise_name(text)) > MAX_NAME_LENGTH:
            raise ObjectMemoryError(f"{what} too long ({len(normalise_name(text))} characters after normalisation, "
                                    f"at most {MAX_NAME_LENGTH})")
    if position is not None and not all(math.isfinite(v) and abs(v) <= MAX_COORD_M for v in position):
        raise ObjectMemoryError(f"position must be finite and within {MAX_COORD_M:g} m of the map's origin, got "
                                f"({', '.join(f'{v:g}' for v in position)})")
    if len(detail) > MAX_DETAIL_CHARS:
        raise ObjectMemoryError(f"detail too long ({len(detail)} characters, at most {MAX_DETAIL_CHARS})")

@dataclass(frozen=True)
class Belief:
    """What the robot believes about one object instance.

    Attributes:
        id: stable id, ``<class>#<n>`` (kept across map reloads and restarts).
        name: class name, e.g. ``"cup"``.
        position: map frame, metres.
        confidence: 0..1; 1 = just seen or just handled, lower after a failed grasp or when the map
            no longer shows it.
        last_seen: wall-clock time (s since the epoch) of the last evidence that it is there.
        source: ``map`` | ``action`` | ``user``: what set the current position.
        state: ``seen`` (in the map), ``unseen`` (the map no longer shows it), ``held`` (in the
            gripper), ``placed`` (put down by the robot, not yet confirmed by the map).
        place: named place it was put at or is held by (``user``, ``bin``, ``gripper``), or "".
        note: last thing worth telling a person ("a grasp found nothing there").
    """

    id: str
    name: str
    position: tuple[float, float, float]
    confidence: float
    last_seen: float
    source: str
    state: str = "seen"
    place: str = ""
    note: str = ""

    def distance_xy(self, point: tuple[float, float] | tuple[float, float, float]) -> float:
        """Horizontal distance (m) from ``point``."""
        return math.hypot(self.position[0] - point[0], self.position[1] - point[1])


@dataclass(frozen=True)
class MapObservation:
    """One instance of the loaded map (anything with a class name and a centre)."""

    name: str
    centre: tuple[float, float, float]


@dataclass(frozen=True)
class MergeReport:
    """What :meth:`ObjectMemory.merge_map` changed (ids per category)."""

    kept: tuple[str, ...] = ()
    moved: tuple[str, ...] = ()
    added: tuple[str, ...] = ()
    unseen: tuple[str, ...] = ()
    newer_than_map: tuple[str, ...] = ()
    forgotten: tuple[str, ...] = ()

    def summary(self) -> str:
        parts = [f"{len(v)} {k.replace('_', ' ')}" + (f" ({', '.join(v)})" if v and k != "kept" else "")
                 for k, v in asdict(self).items() if v]
        return "memory: " + (", ".join(parts) if parts else "no instances")


@dataclass(frozen=True)
class MemoryConfig:
    """How the memory weighs evidence.

    Attributes:
        match_radius: m; a map instance this close to a belief of its class is the same object.
        move_radius: m; farther than ``match_radius`` but within this, an unmatched pair of the same
            class is one object that moved (0 = never match moved objects).
        unseen_factor: confidence multiplier for a belief the reloaded map no longer shows.
        failed_grasp_factor: confidence multiplier after a grasp found nothing there.
        trust_threshold: beliefs below this confidence are not trusted blindly by planners.
        forget_below: a belief the reloaded map does not show is forgotten once its confidence
            falls below this (after a few reloads without it).
    """

    match_radius: float = 0.5
    move_radius: float = 20.0
    unseen_factor: float = 0.5
    failed_grasp_factor: float = 0.3
    trust_threshold: float = 0.5
    forget_below: float = 0.05

    def __post_init__(self) -> None:
        for name in ("match_radius", "move_radius"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
        for name in ("unseen_factor", "failed_grasp_factor", "trust_threshold", "forget_below"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and 0.0 <= v <= 1.0):
                raise ValueError(f"{name} must be in [0, 1], got {v!r}")


def _point(value: object, what: str) -> tuple[float, float, float]:
    if not isinstance(value, list | tuple) or len(value) != 3 or any(isinstance(v, bool) for v in value):
        raise ObjectMemoryError(f"{what}: expected [x, y, z], got {value!r:.80}")
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError) as exc:
        raise ObjectMemoryError(f"{what}: expected numbers, got {value!r:.80}") from exc
    if not all(math.isfinite(v) for v in out):
        raise ObjectMemoryError(f"{what}: coordinates must be finite, got {value!r:.80}")
    return out  # type: ignore[return-value]


def belief_from_dict(d: object) -> Belief:
    """A belief from its JSON form (as written by :meth:`ObjectMemory.to_json`).

    Raises:
        ObjectMemoryError: missing/invalid field (the message names it).
    """
    if not isinstance(d, dict):
        raise ObjectMemoryError(f"a belief must be an object, got {d!r:.80}")
    try:
        b = Belief(id=str(d["id"]), name=str(d["name"]), position=_point(d["position"], f"{d.get('id')}.position"),
                   confidence=float(d["confidence"]), last_seen=float(d["last_seen"]), source=str(d["source"]),
                   state=str(d.get("state", "seen")), place=str(d.get("place", "")), note=str(d.get("note", "")))
    except (KeyError, TypeError, ValueError) as exc:
        raise ObjectMemoryError(f"belief {str(d)[:80]}: {exc!r}") from exc
    if not b.id or not b.name:
        raise ObjectMemoryError(f"belief needs an id and a name: {str(d)[:80]}")
    if not 0.0 <= b.confidence <= 1.0 or not math.isfinite(b.last_seen):
        raise ObjectMemoryError(f"belief {b.id}: confidence must be in [0, 1] and last_seen finite")
    if b.source not in SOURCES or b.state not in STATES:
        raise ObjectMemoryError(f"belief {b.id}: source must be one of {SOURCES}, state one of {STATES}")
    return b


class ObjectMemory:
    """Beliefs about object instances, updated by the map, the robot's actions and people.

    Args:
        config: evidence weights.
        beliefs: initial beliefs (e.g. from a file); ids must be unique.
        clock: wall clock (s since the epoch); injectable for tests.
    """

    def __init__(self, config: MemoryConfig | None = None, beliefs: Iterable[Belief] = (),
                 clock: Callable[[], float] = time.time) -> None:
        self.config = config or MemoryConfig()
        self._clock = clock
        self._lock = threading.Lock()  # guards _beliefs, _revision
        self._beliefs: dict[str, Belief] = {}
        for b in beliefs:
            if b.id in self._beliefs:
                raise ObjectMemoryError(f"duplicate belief id {b.id!r}")
            self._beliefs[b.id] = b
        self._revision = 0

    # -- reading ----------------------------------------------------------------------------------

    @property
    def revision(self) -> int:
        """Increases by one with every change (readers keep the newest snapshot)."""
        with self._lock:
            return self._revision

    def snapshot(self) -> tuple[Belief, ...]:
        """Every belief, by class then id."""
        with self._lock:
            return tuple(sorted(self._beliefs.values(), key=_order))

    def get(self, belief_id: str) -> Belief | None:
        with self._lock:
            return self._beliefs.get(belief_id)

    def candidates(self, name: str, reference: tuple[float, ...] | None = None) -> list[Belief]:
        """Beliefs of class ``name``: held first, then by confidence, then nearest ``reference``."""
        with self._lock:
            group = [b for b in self._beliefs.values() if b.name == name]
        return rank(group, reference)

    def best(self, name: str, reference: tuple[float, ...] | None = None) -> Belief | None:
        """The belief a query for class ``name`` answers with (see :meth:`candidates`), or None."""
        group = self.candidates(name, reference)
        return group[0] if group else None

    # -- updates from the map ----------------------------------------------------------------------

    def merge_map(self, observations: Iterable[MapObservation], observed_at: float | None = None) -> MergeReport:
        """Match a (re)loaded map's instances to the beliefs (see the module docstring).

        Args:
            observations: the map's instances (class name + centre).
            observed_at: when the map was observed (e.g. the map file's mtime); beliefs set by an
                action or a person after this are newer than the map and kept. None = now.

        Returns:
            What changed.
        """
        now = self._clock()
        seen_at = now if observed_at is None else float(observed_at)
        obs = [MapObservation(o.name, tuple(float(v) for v in o.centre)) for o in observations  # type: ignore[misc]
               if len(o.centre) == 3 and all(math.isfinite(float(v)) for v in o.centre)]
        cfg = self.config
        kept, moved, added, unseen, newer, forgotten = [], [], [], [], [], []
        with self._lock:
            beliefs = dict(self._beliefs)
            for name in sorted({o.name for o in obs} | {b.name for b in beliefs.values()}):
                olist = [o for o in obs if o.name == name]
                blist = [b for b in beliefs.values() if b.name == name]
                pairs = sorted(
                    ((b.distance_xy(o.centre), bi, oi)
                     for bi, b in enumerate(blist) for oi, o in enumerate(olist)),
                    key=lambda t: (t[0], blist[t[1]].id, t[2]))
                used_b: set[int] = set()
                used_o: set[int] = set()
                for limit in (cfg.match_radius, cfg.move_radius):
                    for dist, bi, oi in pairs:
                        if bi in used_b or oi in used_o or dist > limit:
                            continue
                        used_b.add(bi)
                        used_o.add(oi)
                        b, o = blist[bi], olist[oi]
                        if b.source != "map" and b.last_seen > seen_at:
                            newer.append(b.id)  # our own action is newer than this map
                            continue
                        beliefs[b.id] = replace(b, position=o.centre, confidence=1.0, last_seen=seen_at,
                                                source="map", state="seen", place="", note="")
                        (kept if dist <= cfg.match_radius else moved).append(b.id)
                for bi, b in enumerate(blist):
                    if bi in used_b:
                        continue
                    if b.source != "map" and b.last_seen > seen_at:
                        newer.append(b.id)
                        continue
                    if b.state == "held":
                        continue  # the camera cannot see into the gripper
                    if b.confidence * cfg.unseen_factor < cfg.forget_below:
                        del beliefs[b.id]
                        forgotten.append(b.id)
                        continue
                    beliefs[b.id] = replace(b, confidence=b.confidence * cfg.unseen_factor, state="unseen",
                                            note="the map no longer shows it here")
                    unseen.append(b.id)
                for oi, o in enumerate(olist):
                    if oi in used_o:
                        continue
                    bid = _new_id(name, beliefs)
                    beliefs[bid] = Belief(bid, name, o.centre, 1.0, seen_at, "map")
                    added.append(bid)
            self._beliefs = beliefs
            self._revision += 1
        return MergeReport(tuple(kept), tuple(moved), tuple(added), tuple(unseen), tuple(newer), tuple(forgotten))

    # -- updates from the robot's actions -----------------------------------------------------------

    def grasped(self, name: str, near: tuple[float, ...] | None = None, holder: str = "gripper") -> Belief:
        """The robot picked up a ``name``: the belief nearest ``near`` (the robot) is now held.

        A grasp of an object the memory did not know creates a belief for it.
        """
        now = self._clock()
        with self._lock:
            group = [b for b in self._beliefs.values() if b.name == name and b.state != "held"]
            b = _nearest(group, near)
            if b is None:
                pos = tuple(float(v) for v in near) if near is not None and len(near) == 3 else (0.0, 0.0, 0.0)
                b = Belief(_new_id(name, self._beliefs), name, pos, 1.0, now, "action")  # type: ignore[arg-type]
            b = replace(b, confidence=1.0, last_seen=now, source="action", state="held", place=holder,
                        note="picked up by the robot")
            self._put(b)
            return b

    def grasp_failed(self, name: str, near: tuple[float, ...] | None = None, reason: str = "") -> Belief | None:
        """Negative evidence: a grasp of ``name`` near ``near`` found nothing. Lowers that belief's confidence.

        Returns:
            The updated belief, or None when the memory has no ``name``.
        """
        with self._lock:
            group = [b for b in self._beliefs.values() if b.name == name and b.state != "held"]
            b = _nearest(group, near)
            if b is None:
                return None
            why = f"a grasp found nothing there ({reason})" if reason else "a grasp found nothing there"
            b = replace(b, confidence=b.confidence * self.config.failed_grasp_factor, state="unseen", note=why)
            self._put(b)
            return b

    def placed(self, name: str, position: tuple[float, float, float], place: str = "") -> Belief:
        """The robot put down the ``name`` it held at ``position`` (named ``place`` if any)."""
        now = self._clock()
        pos = _point(position, "placed position")
        with self._lock:
            held = [b for b in self._beliefs.values() if b.state == "held"]
            b = next((h for h in held if h.name == name), held[0] if held and not name else None)
            if b is None:
                b = Belief(_new_id(name, self._beliefs), name, pos, 1.0, now, "action")
            b = replace(b, position=pos, confidence=1.0, last_seen=now, source="action", state="placed",
                        place=place, note=f"put down by the robot{' at the ' + place if place else ''}")
            self._put(b)
            return b

    def set_position(self, ref: str, position: tuple[float, float, float], source: str = "user",
                     place: str = "") -> Belief:
        """Someone says where an object is: ``ref`` is a belief id, or a class (its best belief)."""
        if source not in SOURCES:
            raise ObjectMemoryError(f"source must be one of {SOURCES}, got {source[:40]!r}")
        now = self._clock()
        pos = _point(position, "position")
        with self._lock:
            b = self._beliefs.get(ref) or _nearest([x for x in self._beliefs.values() if x.name == ref], pos)
            if b is None:
                b = Belief(_new_id(ref, self._beliefs), ref, pos, 1.0, now, source)
            b = replace(b, position=pos, confidence=1.0, last_seen=now, source=source, state="placed", place=place,
                        note=f"set by {source}")
            self._put(b)
            return b

    def _put(self, b: Belief) -> None:  # caller holds the lock
        self._beliefs[b.id] = b
        self._revision += 1

    # -- persistence --------------------------------------------------------------------------------

    def to_json(self) -> str:
        """The file form: ``{"version": 1, "saved_at": t, "beliefs": [...]}``."""
        doc = {"version": FILE_VERSION, "saved_at": self._clock(),
               "beliefs": [asdict(b) for b in self.snapshot()]}
        return json.dumps(doc, indent=1)

    def save(self, path: str) -> None:
        """Write the memory to ``path`` atomically (a reader sees the old or the new file, never half).

        Raises:
            OSError: the directory is not writable (the memory in RAM is unchanged).
        """
        data = self.to_json()
        directory = os.path.dirname(os.path.abspath(path))
        os.makedirs(directory, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".object_memory.", suffix=".tmp", dir=directory)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, path)
        except BaseException:
            try:
                os.unlink(tmp)
            except OSError:
                pass
            raise


def memory_from_json(text: str, config: MemoryConfig | None = None,
                     clock: Callable[[], float] = time.time) -> ObjectMemory:
    """Parse the file form.

    Raises:
        ObjectMemoryError: not a memory file (the message says what is wrong).
    """
    try:
        doc = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ObjectMemoryError(f"not JSON: {exc}") from exc
    if not isinstance(doc, dict) or doc.get("version") != FILE_VERSION or not isinstance(doc.get("beliefs"), list):
        raise ObjectMemoryError(f"not an object memory file (expected version {FILE_VERSION} and a 'beliefs' list)")
    return ObjectMemory(config, [belief_from_dict(d) for d in doc["beliefs"]], clock=clock)


def load_memory(path: str, config: MemoryConfig | None = None,
                clock: Callable[[], float] = time.time) -> tuple[ObjectMemory, str]:
    """The memory saved at ``path``; a missing file gives an empty memory.

    A corrupt file is renamed to ``<path>.corrupt-<unix time>`` (kept for inspection) and an empty
    memory is returned; never raises for a bad file.

    Returns:
        ``(memory, message)``: the message says what was loaded or what was set aside.
    """
    if not os.path.exists(path):
        return ObjectMemory(config, clock=clock), f"no memory file yet at {path}; starting empty"
    try:
        with open(path, encoding="utf-8") as fh:
            memory = memory_from_json(fh.read(), config, clock)
    except (OSError, UnicodeDecodeError, ObjectMemoryError) as exc:
        aside = f"{path}.corrupt-{int(clock())}"
        try:
            os.replace(path, aside)
            where = f"set aside as {aside}"
        except OSError as exc2:
            where = f"could not be set aside ({exc2})"
        return ObjectMemory(config, clock=clock), f"memory file {path} is corrupt ({exc}); {where}; starting empty"
    return memory, f"memory: {len(memory.snapshot())} belief(s) from {path}"


# -- helpers ------------------------------------------------------------------------------------------


def _order(b: Belief) -> tuple[str, int, str]:
    head, _, tail = b.id.rpartition("#")
    return (b.name, int(tail) if tail.isdigit() else 0, b.id)


def _new_id(name: str, beliefs: dict[str, Belief]) -> str:
    n = 1
    while f"{name}#{n}" in beliefs:
        n += 1
    return f"{name}#{n}"


def _nearest(group: list[Belief], near: tuple[float, ...] | None) -> Belief | None:
    if not group:
        return None
    if near is None:
        return rank(group, None)[0]
    return min(group, key=lambda b: (b.distance_xy(near), -b.confidence, b.id))


def rank(group: Iterable[Belief], reference: tuple[float, ...] | None = None) -> list[Belief]:
    """Beliefs in answer order: held first, then higher confidence, then nearer ``reference``, then id."""
    def key(b: Belief) -> tuple:
        dist = b.distance_xy(reference) if reference is not None else 0.0
        return (b.state != "held", -round(b.confidence, 3), dist, _order(b))

    return sorted(group, key=key)
