"""Where the robot should stand to reach an object, and how to name where a point is (no ROS).

Both planners (the scenario library and the LLM planner) use :func:`approach_pose`, so "give me
the cup" drives to the cup wherever it is now, not to a fixed room.

Rules of :func:`approach_pose`:

1. A named location whose stand pose is within ``reach`` (horizontal) of the object is a known
   good place to stand (clear of furniture): the nearest such location is used, as the location
   itself (``goto:kitchen`` keeps the seed's plan shape).
2. Otherwise the robot stands ``standoff`` metres from the object, facing it, on the side it comes
   from: candidate bearings around the object are tried, those facing the robot first, and the
   first that ``is_free`` accepts (a costmap check; default: every point is free) is used.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from decision_maker.command_types import NamedLocation, Point3, Pose2D

#: Horizontal distance (m) from the robot's centre the arm can reach (the simulated arm: 1.1 m),
#: less a safety margin.
DEFAULT_REACH = 0.9
#: How far from the object (m) a computed approach pose stands.
DEFAULT_STANDOFF = 0.6
#: Places where an object "is with" someone / "in" something rather than "at" it.
_PLACE_PHRASES = {"user": "with you", "gripper": "in my gripper", "bin": "in the bin", "table": "on the table",
                  "fridge": "in the fridge"}


@dataclass(frozen=True)
class Approach:
    """Where to stand for an object.

    Attributes:
        pose: the stand pose (map frame).
        location: the named location used, or None for a computed pose.
        distance: horizontal distance (m) from the pose to the object.
    """

    pose: Pose2D
    location: str | None
    distance: float

    def primitive(self) -> str:
        """``goto:<location>`` or ``goto:x,y,theta``."""
        if self.location:
            return f"goto:{self.location}"
        p = self.pose
        return f"goto:{p.x:.3f},{p.y:.3f},{p.theta:.4f}"


def approach_pose(target: tuple[float, float, float] | Point3, locations: Mapping[str, NamedLocation],
                  robot: Pose2D | None = None, reach: float = DEFAULT_REACH, standoff: float = DEFAULT_STANDOFF,
                  is_free: Callable[[float, float], bool] | None = None, exclude: tuple[str, ...] = ("user",)
                  ) -> Approach:
    """Where to stand to grasp an object at ``target`` (see the module docstring).

    Args:
        target: the object's position (map frame, metres).
        locations: named locations (their stand poses are known to be free).
        robot: where the robot is now (prefers the side facing it); None = no preference.
        reach: largest horizontal distance (m) from the stand pose to the object; > 0.
        standoff: distance (m) of a computed pose from the object; 0 < standoff <= reach.
        is_free: ``(x, y) -> bool``, False where the robot cannot stand (None = all free).
        exclude: named locations never used as stand poses (the user's place is for handing over).

    Returns:
        The approach.

    Raises:
        ValueError: bad reach/standoff or a non-finite target, or no free pose around the object.
    """
    tx, ty = (target.x, target.y) if isinstance(target, Point3) else (float(target[0]), float(target[1]))
    if not (math.isfinite(tx) and math.isfinite(ty)):
        raise ValueError(f"approach_pose: target must be finite, got ({tx}, {ty})")
    if not (reach > 0 and 0 < standoff <= reach):
        raise ValueError(f"approach_pose: need 0 < standoff <= reach, got standoff {standoff}, reach {reach}")
    near = sorted((math.hypot(loc.pose.x - tx, loc.pose.y - ty), name) for name, loc in locations.items()
                  if name not in exclude)
    for dist, name in near:
        if dist <= reach and (is_free is None or is_free(locations[name].pose.x, locations[name].pose.y)):
            return Approach(locations[name].pose, name, dist)
    first = math.atan2(robot.y - ty, robot.x - tx) if robot is not None else 0.0
    if robot is not None and math.hypot(robot.x - tx, robot.y - ty) < 1e-6:
        first = robot.theta + math.pi
    for k in range(16):  # 0, +22.5, -22.5, +45, ... degrees from the robot's side
        step = (k + 1) // 2 * (1 if k % 2 else -1)
        bearing = first + step * math.pi / 8
        x, y = tx + standoff * math.cos(bearing), ty + standoff * math.sin(bearing)
        if is_free is None or is_free(x, y):
            theta = math.remainder(bearing + math.pi, 2 * math.pi)  # face the object
            return Approach(Pose2D(round(x, 3), round(y, 3), round(theta, 4)), None, standoff)
    raise ValueError(f"approach_pose: no free place to stand within {standoff:.2f} m of ({tx:.2f}, {ty:.2f})")


def place_phrase(point: tuple[float, float, float], locations: Mapping[str, NamedLocation], place: str = "",
                 radius: float = 1.5) -> str:
    """Where ``point`` is, for a person: "with you", "on the table", "near the kitchen", or coordinates.

    Args:
        point: map frame, metres.
        locations: the named locations.
        place: a named place known for it (from the robot's own action), used first.
        radius: a location whose drop point or stand pose is within this (m) names the point.
    """
    if place:
        return _PLACE_PHRASES.get(place, f"at the {place}")
    best: tuple[float, str] | None = None
    for name, loc in locations.items():
        if name == "home":
            continue
        drop = loc.drop_point()
        d = min(math.hypot(drop.x - point[0], drop.y - point[1]), math.hypot(loc.pose.x - point[0],
                                                                             loc.pose.y - point[1]))
        if d <= radius and (best is None or d < best[0]):
            best = (d, name)
    if best is None:
        return f"at ({point[0]:.2f}, {point[1]:.2f})"
    name = best[1]
    if best[0] <= 0.3 and name in _PLACE_PHRASES:
        return _PLACE_PHRASES[name]
    return {"table": "on the table", "kitchen": "at the kitchen counter"}.get(name, f"near the {name}")
