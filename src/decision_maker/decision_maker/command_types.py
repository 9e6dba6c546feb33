"""Data types of the brain: poses, named locations, validated primitives and plans (no ROS).

A plan is a tuple of validated primitives, never raw strings. The string forms are::

    goto:x,y,theta        metres, metres, radians (map frame)
    goto:<location>       a named location (locations file)
    grasp:<object>        an object the object database knows
    place:<location>      put the held object at a named location

:func:`parse_primitive` / :func:`parse_plan` turn strings into primitives and raise
:class:`~decision_maker.errors.InvalidPrimitive` with a reason a person can read.
"""

from __future__ import annotations

import math
import os
import re
import unicodedata
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import yaml

from decision_maker.errors import ConfigError, InvalidPrimitive

#: Longest command text accepted (characters after sanitising); longer ones are rejected.
MAX_TEXT_CHARS = 500
#: Object names: letters, digits, space, ``_`` and ``-``; at most this many characters.
MAX_NAME_CHARS = 64
#: |x|, |y| of a ``goto:x,y,theta`` larger than this (metres) is rejected as a typo.
MAX_COORD_M = 1000.0

_NAME_RE = re.compile(r"^[a-z0-9][a-z0-9 _\-]*$")


@dataclass(frozen=True)
class Pose2D:
    """A planar pose: position in metres, heading ``theta`` in radians (counter-clockwise from +x)."""

    x: float
    y: float
    theta: float = 0.0

    def distance_to(self, other: Pose2D | Point3) -> float:
        return math.hypot(other.x - self.x, other.y - self.y)


@dataclass(frozen=True)
class Point3:
    """A point in metres."""

    x: float
    y: float
    z: float


@dataclass(frozen=True)
class NamedLocation:
    """A place the robot knows by name.

    Attributes:
        name: lower-case name, e.g. ``"kitchen"``.
        pose: where the robot stands (and faces) at this location.
        place_point: where an object is put down here (``place:<name>``); None = the spot in front
            of the robot (0.4 m ahead, 0.8 m high).
    """

    name: str
    pose: Pose2D
    place_point: Point3 | None = None

    def drop_point(self) -> Point3:
        if self.place_point is not None:
            return self.place_point
        p = self.pose
        return Point3(p.x + 0.4 * math.cos(p.theta), p.y + 0.4 * math.sin(p.theta), 0.8)


@dataclass(frozen=True)
class GoTo:
    """Drive to ``pose``; ``location`` is set when the command named a location."""

    pose: Pose2D
    location: str | None = None

    def __str__(self) -> str:
        if self.location:
            return f"goto:{self.location}"
        return f"goto:{self.pose.x:g},{self.pose.y:g},{self.pose.theta:g}"


@dataclass(frozen=True)
class Grasp:
    """Look the object up in the object database, then pick it up."""

    object_name: str

    def __str__(self) -> str:
        return f"grasp:{self.object_name}"


@dataclass(frozen=True)
class Place:
    """Put the held object down at a named location (driving there first if needed)."""

    location: NamedLocation

    def __str__(self) -> str:
        return f"place:{self.location.name}"


Primitive = GoTo | Grasp | Place


@dataclass(frozen=True)
class Plan:
    """What a planner made of a command.

    Attributes:
        primitives: the validated steps, in order (at least one).
        scenario: which scenario / planner produced it (for status messages).
        slots: filled slots, e.g. ``{"item": "cup"}``.
    """

    primitives: tuple[Primitive, ...]
    scenario: str = ""
    slots: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.primitives:
            raise InvalidPrimitive("a plan needs at least one primitive")

    def __str__(self) -> str:
        return ", ".join(str(p) for p in self.primitives)


# --- text hygiene ------------------------------------------------------------------------------


def sanitize_text(text: str) -> str:
    """A command as received, made safe to log and match: NFKC, no control characters, one-line.

    The result is what status messages carry in their ``text`` field (input nodes use it to find
    the status of what they sent). Not truncated: the length check is the caller's.
    """
    text = unicodedata.normalize("NFKC", str(text))
    text = "".join(" " if unicodedata.category(ch)[0] == "C" else ch for ch in text)
    return " ".join(text.split())


def shorten(text: str, limit: int = 80) -> str:
    """``text`` cut to ``limit`` characters with an ellipsis (for messages)."""
    return text if len(text) <= limit else text[: limit - 1] + "…"


def normalize_name(name: str) -> str:
    """Lower-case, single-spaced name (object or location)."""
    return " ".join(sanitize_text(name).lower().split())


# --- locations ---------------------------------------------------------------------------------


def _floats(value: object, n: int, what: str) -> tuple[float, ...]:
    if not isinstance(value, list | tuple) or len(value) != n:
        raise ConfigError(f"{what}: expected a list of {n} numbers, got {value!r}")
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{what}: expected numbers, got {value!r}") from exc
    if not all(math.isfinite(v) for v in out):
        raise ConfigError(f"{what}: numbers must be finite, got {value!r}")
    return out


def locations_from_dict(doc: object, source: str = "locations") -> dict[str, NamedLocation]:
    """``{"locations": {name: {"pose": [x, y, theta], "place": [x, y, z]}}}`` → locations.

    Raises:
        ConfigError: malformed document (the message names the entry).
    """
    entries = doc.get("locations") if isinstance(doc, dict) else None
    if not isinstance(entries, dict) or not entries:
        raise ConfigError(f"{source}: expected a non-empty 'locations:' mapping")
    out: dict[str, NamedLocation] = {}
    for raw_name, body in entries.items():
        name = normalize_name(str(raw_name))
        if not _NAME_RE.match(name):
            raise ConfigError(f"{source}: bad location name {raw_name!r}")
        if not isinstance(body, dict) or "pose" not in body:
            raise ConfigError(f"{source}: location {name!r} needs 'pose: [x, y, theta]'")
        unknown = set(body) - {"pose", "place"}
        if unknown:
            raise ConfigError(f"{source}: location {name!r}: unknown key(s) {sorted(unknown)}")
        pose = Pose2D(*_floats(body["pose"], 3, f"{source}: {name}.pose"))
        place = Point3(*_floats(body["place"], 3, f"{source}: {name}.place")) if "place" in body else None
        out[name] = NamedLocation(name, pose, place)
    return out


def load_locations(path: str) -> dict[str, NamedLocation]:
    """Read a locations YAML file (schema: :func:`locations_from_dict`).

    Raises:
        ConfigError: missing or malformed file.
    """
    if not os.path.isfile(path):
        raise ConfigError(f"locations file not found: {path}")
    try:
        with open(path, encoding="utf-8") as fh:
            doc = yaml.safe_load(fh)
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"cannot read locations file {path}: {exc}") from exc
    return locations_from_dict(doc, path)


# --- primitives --------------------------------------------------------------------------------


def _location(name: str, locations: Mapping[str, NamedLocation], verb: str) -> NamedLocation:
    key = normalize_name(name)
    if key not in locations:
        raise InvalidPrimitive(
            f"{verb}: unknown location {shorten(key, 40)!r}; known: {', '.join(sorted(locations))}"
        )
    return locations[key]


def parse_primitive(text: str, locations: Mapping[str, NamedLocation]) -> Primitive:
    """One primitive string → a validated primitive.

    Args:
        text: e.g. ``"goto:1.5,2,0"``, ``"goto:kitchen"``, ``"grasp:cup"``, ``"place:user"``.
        locations: the named locations.

    Raises:
        InvalidPrimitive: with the reason (unknown verb, bad numbers, unknown location, bad name).
    """
    verb, sep, arg = str(text).strip().partition(":")
    verb, arg = verb.strip().lower(), arg.strip()
    if not sep:
        raise InvalidPrimitive(f"{shorten(str(text), 40)!r} is not a primitive (expected verb:argument)")
    if not arg:
        raise InvalidPrimitive(f"{verb}: missing argument")
    if verb == "goto":
        if "," in arg:
            parts = [p.strip() for p in arg.split(",")]
            if len(parts) != 3:
                raise InvalidPrimitive(f"goto: expected x,y,theta (3 numbers), got {len(parts)} values")
            try:
                x, y, theta = (float(p) for p in parts)
            except ValueError as exc:
                raise InvalidPrimitive(f"goto: x,y,theta must be numbers, got {shorten(arg, 40)!r}") from exc
            if not all(math.isfinite(v) for v in (x, y, theta)):
                raise InvalidPrimitive("goto: x,y,theta must be finite")
            if abs(x) > MAX_COORD_M or abs(y) > MAX_COORD_M:
                raise InvalidPrimitive(f"goto: ({x:g}, {y:g}) is more than {MAX_COORD_M:g} m away")
            return GoTo(Pose2D(x, y, math.remainder(theta, 2 * math.pi)))
        loc = _location(arg, locations, "goto")
        return GoTo(loc.pose, loc.name)
    if verb == "grasp":
        name = normalize_name(arg)
        if len(name) > MAX_NAME_CHARS or not _NAME_RE.match(name):
            raise InvalidPrimitive(f"grasp: bad object name {shorten(name, 40)!r}")
        return Grasp(name)
    if verb == "place":
        return Place(_location(arg, locations, "place"))
    raise InvalidPrimitive(f"unknown primitive {shorten(verb, 20)!r}; expected goto, grasp or place")


def parse_plan(items: Iterable[str], locations: Mapping[str, NamedLocation], scenario: str = "",
               slots: Mapping[str, str] | None = None) -> Plan:
    """Primitive strings → a :class:`Plan`; the first invalid one raises with its position."""
    prims = []
    for i, item in enumerate(items, 1):
        try:
            prims.append(parse_primitive(item, locations))
        except InvalidPrimitive as exc:
            raise InvalidPrimitive(f"step {i}: {exc}") from exc
    return Plan(tuple(prims), scenario, dict(slots or {}))


# --- frames ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FrameTransform:
    """Planar rigid transform from the map frame to the robot's command frame (Isaac Sim, ...).

    ``target = R(yaw) · map + (x, y)``; heading ``theta + yaw``; z unchanged. Identity by default.
    """

    frame_id: str = "map"
    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0

    def pose(self, p: Pose2D) -> Pose2D:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return Pose2D(c * p.x - s * p.y + self.x, s * p.x + c * p.y + self.y,
                      math.remainder(p.theta + self.yaw, 2 * math.pi))

    def point(self, p: Point3) -> Point3:
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return Point3(c * p.x - s * p.y + self.x, s * p.x + c * p.y + self.y, p.z)
