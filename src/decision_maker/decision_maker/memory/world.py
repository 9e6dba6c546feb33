"""Planning from the object memory, and answering questions about it (no ROS).

The object memory (``object_query.memory``, served on ``/object_memory``) says where each object
instance is now. This module turns it into decisions for the planners:

* :func:`choose_instance` — which instance "give me the cup" means: the instances with the user
  are not fetched again (if that leaves nothing, the request is already fulfilled); beliefs below
  the trust threshold are used only when nothing better exists (and the plan says so); among the
  rest the one nearest to the robot wins, unless the second is within ``ambiguity_margin`` metres
  of it — then the person is asked which one (:class:`Clarification`).
* :func:`fetch_plan` — primitives to fetch an instance and put it somewhere (the approach pose of
  :mod:`decision_maker.planning.approach`, then ``grasp`` and ``place``).
* :func:`where_answer`, :func:`inventory_answer` — sentences for "where is X" / "what do you see".
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

from decision_maker.command_types import NamedLocation, Pose2D
from decision_maker.errors import Reply
from decision_maker.planning.approach import DEFAULT_REACH, approach_pose, place_phrase
from object_query.memory import Belief, rank

#: Confidence below which a belief is not trusted blindly (object_query.memory.MemoryConfig's default).
TRUST_THRESHOLD = 0.5
#: Two candidates whose distances from the robot differ by less than this (m) are ambiguous.
AMBIGUITY_MARGIN = 0.5
#: Classes that are furniture or structure: "what do you see" lists them apart from the objects.
FURNITURE = frozenset("floor wall ceiling door window counter table chair sofa couch fridge bin shelf cabinet bed "
                      "desk stairs".split())


def robot_or_home(robot: Pose2D | None, locations: Mapping[str, NamedLocation]) -> Pose2D | None:
    """The robot's pose, or the home location's when unknown (the robot starts there)."""
    if robot is not None:
        return robot
    home = locations.get("home")
    return home.pose if home is not None else None


@dataclass(frozen=True)
class Choice:
    """The instance a request is about, and what to tell the person about the choice."""

    belief: Belief
    note: str = ""


@dataclass(frozen=True)
class Clarification:
    """A pending "which one?" question: the candidates, each with a phrase naming its place."""

    request: str  # the original command text
    name: str  # class
    destination: str  # where the fetched object goes ("user", "bin", ...)
    options: tuple[tuple[Belief, str], ...]

    def question(self) -> str:
        phrases = [f"the one {where}" for _, where in self.options]
        listed = ", ".join(phrases[:-1]) + f" or {phrases[-1]}" if len(phrases) > 1 else phrases[0]
        return f"Which {self.name}: {listed}?"


def aliases_for(known: Iterable[str], groups: Iterable[Sequence[str]]) -> dict[str, str]:
    """Spoken name → known class, from synonym groups (``[[cup, mug], ...]``): ``{"mug": "cup"}``.

    A name that is itself known maps to nothing (it is its own class); a group maps to its first
    known member.
    """
    known_set = set(known)
    out: dict[str, str] = {}
    for group in groups:
        target = next((n for n in group if n in known_set), None)
        if target is None:
            continue
        for name in group:
            if name not in known_set:
                out.setdefault(name, target)
    return out


def clock_time(t: float) -> str:
    """``19:42`` (local time) for a wall-clock stamp."""
    return time.strftime("%H:%M", time.localtime(t))


def instances_of(memory: Sequence[Belief], name: str) -> list[Belief]:
    return [b for b in memory if b.name == name]


def choose_instance(memory: Sequence[Belief], name: str, robot: Pose2D | None, locations: Mapping[str, NamedLocation],
                    request: str = "", destination: str = "user", trust: float = TRUST_THRESHOLD,
                    margin: float = AMBIGUITY_MARGIN) -> Choice | None:
    """Which instance of ``name`` a fetch request means (see the module docstring).

    Returns:
        The choice, or None when the memory has no ``name`` at all (the caller falls back).

    Raises:
        Reply: ``answer`` when every instance already is at ``destination``; ``clarify`` with a
            :class:`Clarification` in ``reply.pending`` when two candidates are about equally near.
    """
    group = instances_of(memory, name)
    if not group:
        return None
    there = [b for b in group if b.place == destination and b.state != "held"]
    pool = [b for b in group if b not in there]
    if not pool:
        b = there[0]
        where = place_phrase(b.position, locations, b.place)
        raise Reply(f"The {name} is already {where}: I put it there at {clock_time(b.last_seen)}.")
    trusted = [b for b in pool if b.confidence >= trust]
    note = ""
    if not trusted:
        b = rank(pool)[0]
        why = b.note or "my information is old"
        note = (f"I'm not sure the {name} is still {place_phrase(b.position, locations, b.place)} "
                f"({why}; confidence {b.confidence:.1f}); I'll look there again")
        return Choice(b, note)
    robot = robot_or_home(robot, locations)
    if robot is None or len(trusted) == 1:
        return Choice(rank(trusted)[0])
    by_dist = sorted(trusted, key=lambda b: (b.distance_xy((robot.x, robot.y)), b.id))
    d0, d1 = (b.distance_xy((robot.x, robot.y)) for b in by_dist[:2])
    if d1 - d0 < margin:
        close = [b for b in by_dist if b.distance_xy((robot.x, robot.y)) - d0 < margin]
        options = tuple((b, place_phrase(b.position, locations, b.place)) for b in close)
        if len({w for _, w in options}) == len(options):  # distinguishable by place: ask
            clar = Clarification(request, name, destination, options)
            raise Reply(clar.question(), "clarify", pending=clar)
    return Choice(by_dist[0], f"the nearest {name} ({d0:.1f} m from me)" if len(by_dist) > 1 else "")


def answer_clarification(clar: Clarification, text_words: Sequence[str]) -> Belief | None:
    """The option an answer like "the one on the table" / "the first" / "the nearest" picks, or None."""
    words = set(text_words)
    ordinals = {"first": 0, "1": 0, "one": None, "second": 1, "2": 1, "third": 2, "3": 2, "last": -1}
    for b, where in clar.options:
        place_words = set(where.split()) - {"the", "at", "on", "in", "near", "with", "counter"}
        if place_words and place_words & words:
            return b
        if b.id in " ".join(text_words):
            return b
    for w in text_words:
        idx = ordinals.get(w)
        if idx is not None and -len(clar.options) <= idx < len(clar.options):
            return clar.options[idx][0]
    if words & {"nearest", "closest", "either", "any", "whichever"}:
        return clar.options[0][0]
    return None


def fetch_plan(belief: Belief, destination: str, locations: Mapping[str, NamedLocation], robot: Pose2D | None,
               reach: float = DEFAULT_REACH) -> list[str]:
    """``goto`` (approach pose next to the object), ``grasp:<class>``, ``place:<destination>``."""
    if belief.state == "held":
        return [f"place:{destination}"]
    approach = approach_pose(belief.position, locations, robot_or_home(robot, locations), reach=reach)
    return [approach.primitive(), f"grasp:{belief.name}", f"place:{destination}"]


def describe_belief(b: Belief, locations: Mapping[str, NamedLocation], trust: float = TRUST_THRESHOLD) -> str:
    """``the cup is on the table (2.80, 2.60, 0.80), seen 19:40`` and a doubt if it is not trusted."""
    where = place_phrase(b.position, locations, b.place)
    x, y, z = b.position
    if b.state == "held":
        how = f"picked up {clock_time(b.last_seen)}"
    elif b.source == "action":
        how = f"I put it there at {clock_time(b.last_seen)}"
    elif b.source == "user":
        how = f"I was told at {clock_time(b.last_seen)}"
    else:
        how = f"seen {clock_time(b.last_seen)}"
    text = f"{where} (at {x:.2f}, {y:.2f}, {z:.2f}; {how})"
    if b.confidence < trust:
        text += f", but I'm not sure it is still there ({b.note or 'not seen since'})"
    return text


def where_answer(memory: Sequence[Belief], name: str, locations: Mapping[str, NamedLocation],
                 trust: float = TRUST_THRESHOLD) -> str:
    """The answer to "where is <name>" from the memory."""
    group = rank(instances_of(memory, name))
    if not group:
        return f"I don't know where the {name} is: I have not seen one."
    if len(group) == 1:
        return f"The {name} is {describe_belief(group[0], locations, trust)}."
    parts = [f"one {describe_belief(b, locations, trust)}" for b in group]
    return f"I know {len(group)} {name}s: " + ", ".join(parts[:-1]) + f" and {parts[-1]}."


def inventory_answer(memory: Sequence[Belief], locations: Mapping[str, NamedLocation], limit: int = 12) -> str:
    """The answer to "what do you see": each class with where its instances are."""
    if not memory:
        return "I don't know of any objects yet."
    by_class: dict[str, list[Belief]] = {}
    for b in memory:
        by_class.setdefault(b.name, []).append(b)
    objects = sorted(n for n in by_class if n not in FURNITURE)
    parts = []
    for name in objects[:limit]:
        wheres = [place_phrase(b.position, locations, b.place) for b in rank(by_class[name])]
        count = f"{len(wheres)} {name}s" if len(wheres) > 1 else f"a {name}"
        parts.append(f"{count} ({', '.join(wheres)})")
    more = f", and {len(objects) - limit} more kinds" if len(objects) > limit else ""
    text = ("I see " + "; ".join(parts) + more + ".") if parts else "I see no objects, only furniture."
    furniture = sorted(n for n in by_class if n in FURNITURE)
    if furniture:
        text += " Furniture: " + ", ".join(furniture) + "."
    return text


def holding_answer(memory: Sequence[Belief], held: str | None) -> str:
    """The answer to "what are you holding"."""
    names = [b.name for b in memory if b.state == "held"] or ([held] if held else [])
    return f"I am holding the {names[0]}." if names else "I am not holding anything."


def is_finite_pose(p: Pose2D | None) -> bool:
    return p is not None and all(math.isfinite(v) for v in (p.x, p.y, p.theta))
