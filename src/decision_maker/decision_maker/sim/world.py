"""A small kinematic world for the simulated robot (no ROS): a base that drives, a gripper, objects.

* :class:`BaseSim` — the robot base: turns toward the goal and drives in a straight line at
  ``speed`` (m/s), turning at ``turn_rate`` (rad/s), then turns to the goal heading. No obstacles.
* :class:`ObjectWorld` — object instances (id, class, position), what the gripper holds, and the
  rules: grasp succeeds only when an object of that class is within ``reach`` (horizontal
  distance from the robot) and the gripper is empty; place needs a held object and the target
  within reach, and puts the object there. A held object rides with the robot.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass

from decision_maker.command_types import Point3, Pose2D, normalize_name
from decision_maker.errors import ConfigError, SimError

#: The sample home's true world (map frame, metres): what ``mock_grasp_server`` holds by default.
SAMPLE_OBJECTS = ('{"bottle": [5.2, 0.3, 1.02], "cup_1": [4.6, 0.35, 0.95], "cup_2": [2.8, 2.6, 0.8], '
                  '"trash": [2.28, 2.48, 0.8]}')
#: Longest object / location name a simulated server takes (longer: rejected, not stored or logged whole).
MAX_NAME_CHARS = 64


def check_coordinates(what: str, values: tuple[float, ...], bound: float) -> None:
    """Every value finite and within ``[-bound, bound]`` (metres, or a unit quaternion's parts).

    Raises:
        SimError: the reason, e.g. ``goal x = 1.7e+308 is outside the workspace (|x| <= 100 m)``.
    """
    for axis, v in zip("xyzw", values, strict=False):
        if not math.isfinite(v):
            raise SimError(f"{what} {axis} = {v} is not a finite number")
        if abs(v) > bound:
            raise SimError(f"{what} {axis} = {v:.6g} is outside the workspace (|{axis}| <= {bound:g} m)")


def check_quaternion(what: str, x: float, y: float, z: float, w: float) -> None:
    """A usable orientation: finite parts and a norm near 1 (0.9 .. 1.1; an all-zero one is refused).

    Raises:
        SimError: the reason.
    """
    if not all(math.isfinite(v) for v in (x, y, z, w)):
        raise SimError(f"{what} orientation is not finite")
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if not 0.9 <= norm <= 1.1:
        raise SimError(f"{what} orientation is not a unit quaternion (norm {norm:.3g})")


def check_name(what: str, name: str) -> None:
    """A non-empty name of at most :data:`MAX_NAME_CHARS` characters.

    Raises:
        SimError: the reason (the name is cut in the message).
    """
    if not name.strip():
        raise SimError(f"{what} is empty")
    if len(name) > MAX_NAME_CHARS:
        raise SimError(f"{what} is {len(name)} characters long (at most {MAX_NAME_CHARS}): {name[:20]!r}...")


def _wrap(a: float) -> float:
    return math.remainder(a, 2 * math.pi)


@dataclass
class BaseSim:
    """The base's pose and one goal; :meth:`step` advances it by ``dt`` seconds."""

    pose: Pose2D
    speed: float = 1.0  # m/s
    turn_rate: float = 2.0  # rad/s
    goal: Pose2D | None = None
    position_tolerance: float = 0.01  # m
    heading_tolerance: float = 0.01  # rad

    def __post_init__(self) -> None:
        if not self.speed > 0 or not self.turn_rate > 0:
            raise ConfigError(f"speed and turn_rate must be > 0, got {self.speed}, {self.turn_rate}")

    def distance_remaining(self) -> float:
        return 0.0 if self.goal is None else self.pose.distance_to(self.goal)

    def arrived(self) -> bool:
        g = self.goal
        return g is not None and self.distance_remaining() <= self.position_tolerance and \
            abs(_wrap(g.theta - self.pose.theta)) <= self.heading_tolerance

    def stop(self) -> None:
        self.goal = None

    def step(self, dt: float) -> None:
        """Move toward the goal for ``dt`` s (turn to face it, drive, turn to the goal heading)."""
        g = self.goal
        if g is None or dt <= 0:
            return
        p = self.pose
        dist = p.distance_to(g)
        if dist > self.position_tolerance:
            bearing = math.atan2(g.y - p.y, g.x - p.x)
            err = _wrap(bearing - p.theta)
            turn = max(-self.turn_rate * dt, min(self.turn_rate * dt, err))
            theta = _wrap(p.theta + turn)
            # drive while turning when roughly facing the goal (< 60 degrees off)
            if abs(err) < math.pi / 3:
                d = min(dist, self.speed * dt)
                x, y = p.x + d * math.cos(bearing), p.y + d * math.sin(bearing)
            else:
                x, y = p.x, p.y
            if math.hypot(g.x - x, g.y - y) <= self.position_tolerance:
                x, y = g.x, g.y
            self.pose = Pose2D(x, y, theta)
            return
        err = _wrap(g.theta - p.theta)
        turn = max(-self.turn_rate * dt, min(self.turn_rate * dt, err))
        self.pose = Pose2D(g.x, g.y, _wrap(p.theta + turn))


@dataclass
class SimObject:
    id: str
    cls: str
    position: Point3


class ObjectWorld:
    """Objects, the gripper, and the grasp/place rules.

    Args:
        objects: instances; ids must be unique.
        reach: how far (horizontal, metres, from the robot's centre) the arm reaches.
    """

    def __init__(self, objects: list[SimObject], reach: float = 1.1) -> None:
        ids = [o.id for o in objects]
        if len(set(ids)) != len(ids):
            raise ConfigError(f"object ids must be unique: {ids}")
        if not reach > 0:
            raise ConfigError(f"reach must be > 0, got {reach}")
        self.objects = {o.id: o for o in objects}
        self.reach = reach
        self.held: str | None = None

    @classmethod
    def from_mapping(cls, doc: Mapping[str, object], reach: float = 1.1) -> ObjectWorld:
        """``{"cup_1": {"class": "cup", "position": [x, y, z]}, "bottle": [x, y, z], ...}`` → world.

        An entry that is just ``[x, y, z]`` is an instance whose class is its id without a
        trailing ``_<n>``. ``None`` positions (unknown) are skipped.

        Raises:
            ConfigError: malformed entry.
        """
        objs = []
        for oid, body in doc.items():
            if isinstance(body, dict):
                cls_name, pos = body.get("class", oid), body.get("position")
            else:
                cls_name, pos = str(oid).rsplit("_", 1)[0] if str(oid).rsplit("_", 1)[-1].isdigit() else oid, body
            if pos is None or (isinstance(pos, list | tuple) and any(v is None for v in pos)):
                continue
            try:
                x, y, z = (float(v) for v in pos)  # type: ignore[union-attr]
            except (TypeError, ValueError, OverflowError) as exc:  # OverflowError: an integer too large for a float
                raise ConfigError(f"object {str(oid)[:40]!r}: position must be [x, y, z], got {pos!r}"[:200]) from exc
            if not all(math.isfinite(v) for v in (x, y, z)):
                raise ConfigError(f"object {str(oid)[:40]!r}: position must be finite, got {pos!r}")
            if len(str(oid)) > MAX_NAME_CHARS or len(str(cls_name)) > MAX_NAME_CHARS:
                raise ConfigError(f"object {str(oid)[:20]!r}...: name longer than {MAX_NAME_CHARS} characters")
            objs.append(SimObject(normalize_name(str(oid)), normalize_name(str(cls_name)), Point3(x, y, z)))
        return cls(objs, reach)

    def carry(self, robot: Pose2D, height: float = 0.9) -> None:
        """Keep the held object in the gripper (0.3 m ahead of the robot)."""
        if self.held is not None:
            o = self.objects[self.held]
            o.position = Point3(robot.x + 0.3 * math.cos(robot.theta), robot.y + 0.3 * math.sin(robot.theta), height)

    def check_grasp(self, robot: Pose2D, cls_name: str) -> SimObject:
        """The instance a grasp of ``cls_name`` would take (nearest to the robot).

        Raises:
            SimError: gripper full, no such object, or out of reach (message says which).
        """
        if self.held is not None:
            raise SimError(f"gripper is not empty (holding {self.held})")
        name = normalize_name(cls_name)
        cands = [o for o in self.objects.values() if name in (o.cls, o.id)]
        if not cands:
            raise SimError(f"there is no {name} in the world")
        best = min(cands, key=lambda o: robot.distance_to(o.position))
        d = robot.distance_to(best.position)
        if d > self.reach:
            raise SimError(f"the nearest {name} is {d:.2f} m away (reach {self.reach:.2f} m)")
        return best

    def grasp(self, robot: Pose2D, cls_name: str) -> SimObject:
        obj = self.check_grasp(robot, cls_name)
        self.held = obj.id
        self.carry(robot)
        return obj

    def check_place(self, robot: Pose2D, target: Point3) -> SimObject:
        """The held object, if ``target`` is within reach.

        Raises:
            SimError: nothing held, or target out of reach.
        """
        if self.held is None:
            raise SimError("the gripper is empty: nothing to place")
        d = robot.distance_to(target)
        if d > self.reach:
            raise SimError(f"place target is {d:.2f} m away (reach {self.reach:.2f} m)")
        return self.objects[self.held]

    def place(self, robot: Pose2D, target: Point3) -> SimObject:
        obj = self.check_place(robot, target)
        obj.position = target
        self.held = None
        return obj

    def move(self, oid: str, position: Point3) -> SimObject:
        """Move object ``oid`` by hand (not the robot's doing).

        Raises:
            SimError: unknown id, the object is in the gripper, or a non-finite position.
        """
        key = normalize_name(oid)
        if key not in self.objects:
            raise SimError(f"no object {key!r}; objects: {', '.join(sorted(self.objects))}")
        if self.held == key:
            raise SimError(f"{key} is in the gripper")
        if not all(math.isfinite(v) for v in (position.x, position.y, position.z)):
            raise SimError("position must be finite")
        self.objects[key].position = position
        return self.objects[key]

    def snapshot(self, robot: Pose2D | None) -> dict:
        """JSON-ready state: robot pose, held object id, every object's class and position."""
        return {
            "robot": None if robot is None else {"x": round(robot.x, 4), "y": round(robot.y, 4),
                                                 "theta": round(robot.theta, 4)},
            "held": self.held,
            "objects": {o.id: {"class": o.cls, "position": [round(o.position.x, 4), round(o.position.y, 4),
                                                            round(o.position.z, 4)]}
                        for o in sorted(self.objects.values(), key=lambda o: o.id)},
        }

    def to_json(self, robot: Pose2D | None) -> str:
        return json.dumps(self.snapshot(robot))
