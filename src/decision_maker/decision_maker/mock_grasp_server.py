"""Simulated arm and the objects of the world: ``grasp`` and ``place`` action servers.

The robot's pose comes from ``robot_pose`` (the simulated nav). A grasp succeeds only when an
object of the asked class is within ``reach`` of the robot and the gripper is empty (the nearest
instance is taken; the goal's target point, from the object database, is only reported against);
a place needs a held object and a target within reach, and puts the object there. A held object
rides with the robot. Each action takes ``grasp_duration_s`` / ``place_duration_s`` with feedback
stages; cancel is honoured at once and leaves the world unchanged.

Moving an object by hand (as a person would; tests of the object memory): service
``sim/move_object`` (decision_maker_interfaces/MoveObject: id, position → success, message).

World state for observers: ``sim/world_state`` (std_msgs/String JSON, transient local)::

    {"robot": {"x", "y", "theta"}, "held": "bottle" | null,
     "objects": {"bottle": {"class": "bottle", "position": [x, y, z]}, "cup_1": ...}}

Parameters:
    reach (m, 1.1), grasp_duration_s (1.0), place_duration_s (1.0), rate_hz (20),
    objects (JSON of instances, see sim.yaml), objects_source ("params" | "object_list": take the
    object database's centres of the ``graspable`` classes), graspable (list of classes),
    frame_id ("map"), pose_topic ("robot_pose"), world_topic ("sim/world_state"),
    world_rate_hz (2), stop_grace_s (0.5), fault ("none" | "fail" | "hang", for both actions),
    workspace_bound_m (100.0).

Everything that comes in is validated: goals (finite target inside ``workspace_bound_m``, the
right frame, names of at most 64 characters) are rejected with the reason; a ``robot_pose`` that
is not finite, in another frame or outside the bound is ignored with a warning (the last good pose
stays); a malformed ``/object_list`` is ignored. The defaults are the params file's values
(config/params/sim.yaml, a test compares them): the sample home's objects, so a plain
``ros2 run decision_maker mock_grasp_server`` serves the seed's scenarios.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass

from decision_maker_interfaces.action import Grasp, Place
from decision_maker_interfaces.srv import MoveObject
from geometry_msgs.msg import PoseStamped
from rclpy.action.server import ServerGoalHandle
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from decision_maker.command_types import Point3, Pose2D
from decision_maker.errors import ConfigError, SimError
from decision_maker.mock_nav_server import FAULTS, POSE_QOS, yaw_of
from decision_maker.sim.actions import SimGoals, run_sim_node
from decision_maker.sim.world import SAMPLE_OBJECTS, ObjectWorld, check_coordinates, check_name, check_quaternion
from decision_maker.topics import HARDWARE_STOP
from home_robot_ros.startup import number_in, read_once

WORLD_QOS = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
GRASP_STAGES = ((0.4, "approach"), (0.7, "close_gripper"), (1.01, "lift"))
PLACE_STAGES = ((0.4, "approach"), (0.7, "open_gripper"), (1.01, "retreat"))


#: Parameters and their defaults (= config/params/sim.yaml).
DEFAULTS: dict[str, object] = {
    "reach": 1.1, "grasp_duration_s": 1.0, "place_duration_s": 1.0, "rate_hz": 20.0, "objects": SAMPLE_OBJECTS,
    "objects_source": "params", "graspable": ["bottle", "cup", "trash"], "frame_id": "map",
    "pose_topic": "robot_pose", "world_topic": "sim/world_state", "world_rate_hz": 2.0, "stop_grace_s": 0.5,
    "fault": "none", "workspace_bound_m": 100.0,
}


@dataclass
class _Job:
    goals: SimGoals
    gh: ServerGoalHandle
    kind: str  # "grasp" | "place"
    started: float
    duration: float
    stop_deadline: float | None = None


class MockGraspServer(Node):
    def __init__(self) -> None:
        super().__init__("mock_grasp_server")
        v = read_once(self, DEFAULTS)
        if v["fault"] not in FAULTS:
            raise ConfigError(f"fault must be one of {FAULTS}, got {v['fault']!r}")
        if v["objects_source"] not in ("params", "object_list"):
            raise ConfigError(f"objects_source must be 'params' or 'object_list', got {v['objects_source']!r}")
        for k in ("rate_hz", "world_rate_hz"):
            number_in(k, v[k], 0.01, 1000.0)
        for k in ("grasp_duration_s", "place_duration_s"):
            number_in(k, v[k], 1e-3, 3600.0)
        number_in("stop_grace_s", v["stop_grace_s"], 0.0, 3600.0)
        number_in("reach", v["reach"], 1e-3, 100.0)
        try:
            objects = json.loads(v["objects"] or "{}")
        except json.JSONDecodeError as exc:
            raise ConfigError(f"objects: not JSON ({exc})") from exc
        if not isinstance(objects, dict):
            raise ConfigError("objects must be a JSON object {id: [x, y, z] | {class, position}}")
        self._bound = float(v["workspace_bound_m"])
        if not self._bound > 0 or not math.isfinite(self._bound):
            raise ConfigError(f"workspace_bound_m must be a finite number > 0, got {v['workspace_bound_m']}")
        self._reach = float(v["reach"])
        from_list = v["objects_source"] == "object_list"
        self._world = ObjectWorld.from_mapping({} if from_list else objects, self._reach)
        self._graspable = {str(c).lower() for c in v["graspable"]}
        self._frame = str(v["frame_id"])
        self._fault = str(v["fault"])
        self._grace = float(v["stop_grace_s"])
        self._durations = {"grasp": float(v["grasp_duration_s"]), "place": float(v["place_duration_s"])}
        self._robot: Pose2D | None = None
        self._job: _Job | None = None
        self._world_pub = self.create_publisher(String, str(v["world_topic"]), WORLD_QOS)
        self._grasp_goals = SimGoals(self, Grasp, "grasp", self._check_goal, self._start_grasp, self._cancelled)
        self._place_goals = SimGoals(self, Place, "place", self._check_goal, self._start_place, self._cancelled)
        self.create_subscription(PoseStamped, str(v["pose_topic"]), self._on_pose, POSE_QOS)
        self.create_subscription(String, "cancel_command", self._on_stop, 10)
        self.create_subscription(String, HARDWARE_STOP, self._on_stop, 10)  # the brain's own stop
        if v["objects_source"] == "object_list":
            self.create_subscription(String, "object_list", self._on_object_list, WORLD_QOS)
        self.create_service(MoveObject, "sim/move_object", self._on_move_object)
        self.create_timer(1.0 / float(v["rate_hz"]), self._tick)
        self.create_timer(1.0 / float(v["world_rate_hz"]), self._publish_world)
        self._publish_world()
        self.get_logger().info(
            f"ready: simulated arm, reach {self._reach:g} m, objects: "
            f"{', '.join(sorted(self._world.objects)) or '(waiting for /object_list)'}, fault {self._fault}"
        )

    # --- inputs -----------------------------------------------------------------------------------

    def _on_pose(self, msg: PoseStamped) -> None:
        p = msg.pose
        try:
            check_coordinates("robot_pose", (p.position.x, p.position.y, p.position.z), self._bound)
            check_quaternion("robot_pose", p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w)
            if msg.header.frame_id and msg.header.frame_id != self._frame:
                raise SimError(f"robot_pose frame {msg.header.frame_id[:40]!r} is not {self._frame!r}")
        except SimError as exc:
            self.get_logger().warn(f"ignoring a robot_pose: {exc}", throttle_duration_sec=1.0)
            return
        self._robot = Pose2D(p.position.x, p.position.y, yaw_of(p.orientation))
        if self._world.held is not None:
            self._world.carry(self._robot)

    def _on_object_list(self, msg: String) -> None:
        if self._world.objects:
            return  # the world is initialised once; later lists are the database's belief, not the world
        try:
            if len(msg.data) > 1_000_000:
                raise ConfigError(f"{len(msg.data)} characters (at most 1000000)")
            doc = json.loads(msg.data)
            chosen = {k: v for k, v in doc.items() if str(k).lower() in self._graspable}
            world = ObjectWorld.from_mapping(chosen, self._reach)
            for o in world.objects.values():
                check_coordinates(f"object {o.id}", (o.position.x, o.position.y, o.position.z), self._bound)
        except (json.JSONDecodeError, AttributeError, ConfigError, SimError, RecursionError) as exc:
            self.get_logger().warn(f"ignoring a malformed /object_list: {str(exc)[:200]}")
            return
        self._world = world
        self.get_logger().info(f"world objects from /object_list: {', '.join(sorted(self._world.objects))}")
        self._publish_world()

    def _on_stop(self, msg: String) -> None:
        job = self._job
        if job is not None and job.stop_deadline is None:
            job.stop_deadline = time.monotonic() + self._grace
        self.get_logger().warn(f"/cancel_command: arm stops ({msg.data[:80]!r})")

    def _on_move_object(self, request: MoveObject.Request, response: MoveObject.Response) -> MoveObject.Response:
        """A person moves an object by hand (the robot is not told)."""
        p = request.position
        try:
            check_name("object id", request.id)
            check_coordinates("position", (p.x, p.y, p.z), self._bound)
            obj = self._world.move(request.id, Point3(p.x, p.y, p.z))
        except SimError as exc:
            response.success, response.message = False, str(exc)
            return response
        response.success, response.message = True, f"moved {obj.id} to ({p.x:.2f}, {p.y:.2f}, {p.z:.2f})"
        self.get_logger().info(f"by hand: {response.message}")
        self._publish_world()
        return response

    # --- goals ------------------------------------------------------------------------------------

    def _check_goal(self, goal) -> str | None:
        if self._job is not None:
            return f"arm busy ({self._job.kind})"
        try:
            if hasattr(goal, "target"):  # Grasp
                header, p = goal.target.header, goal.target.point
                check_name("object name", goal.object_name)
            else:  # Place
                header, p = goal.target_pose.header, goal.target_pose.pose.position
                q = goal.target_pose.pose.orientation
                check_name("location name", goal.location_name)
                check_quaternion("target", q.x, q.y, q.z, q.w)
            check_coordinates("target", (p.x, p.y, p.z), self._bound)
        except SimError as exc:
            return str(exc)
        if header.frame_id and header.frame_id != self._frame:
            return f"target frame {header.frame_id[:40]!r} is not {self._frame!r}"
        return None

    def _start_grasp(self, gh: ServerGoalHandle) -> None:
        self._start(self._grasp_goals, gh, "grasp")

    def _start_place(self, gh: ServerGoalHandle) -> None:
        self._start(self._place_goals, gh, "place")

    def _start(self, goals: SimGoals, gh: ServerGoalHandle, kind: str) -> None:
        try:
            self._check(kind, gh.request)
        except SimError as exc:
            self.get_logger().info(f"{kind} refused: {exc}")
            goals.finish(gh, "abort", goals.result(success=False, message=str(exc)))
            return
        self._job = _Job(goals, gh, kind, time.monotonic(), self._durations[kind])

    def _check(self, kind: str, req) -> None:
        if self._robot is None:
            raise SimError("robot pose unknown (no robot_pose yet)")
        if kind == "grasp":
            self._world.check_grasp(self._robot, req.object_name)
        else:
            p = req.target_pose.pose.position
            self._world.check_place(self._robot, Point3(p.x, p.y, p.z))

    def _cancelled(self, gh: ServerGoalHandle) -> None:
        if self._job is not None and self._job.gh is gh:
            self.get_logger().info(f"{self._job.kind} cancelled")
            self._job = None

    # --- simulation -------------------------------------------------------------------------------

    def _tick(self) -> None:
        job = self._job
        if job is None:
            return
        now = time.monotonic()
        goals, gh = job.goals, job.gh
        if job.stop_deadline is not None and now >= job.stop_deadline:
            self._end(goals.result(success=False, message="stopped by /cancel_command"), "abort")
            return
        if self._fault == "hang":
            return
        progress = min(1.0, (now - job.started) / job.duration)
        if self._fault == "fail" and progress >= 0.5:
            self._end(goals.result(success=False, message=f"simulated {job.kind} failure"), "abort")
            return
        if progress < 1.0:
            fb = goals.feedback()
            fb.progress = float(progress)
            stages = GRASP_STAGES if job.kind == "grasp" else PLACE_STAGES
            fb.stage = next(name for limit, name in stages if progress < limit)
            gh.publish_feedback(fb)
            return
        try:
            if job.kind == "grasp":
                t = gh.request.target.point
                before = self._world.check_grasp(self._robot, gh.request.object_name).position
                off = math.hypot(t.x - before.x, t.y - before.y)
                obj = self._world.grasp(self._robot, gh.request.object_name)
                message = f"grasped {obj.id} (target point {off:.2f} m from it)"
            else:
                p = gh.request.target_pose.pose.position
                obj = self._world.place(self._robot, Point3(p.x, p.y, p.z))
                message = f"placed {obj.id} at ({p.x:.2f}, {p.y:.2f}, {p.z:.2f}) ({gh.request.location_name})"
        except SimError as exc:
            self._end(goals.result(success=False, message=str(exc)), "abort")
            return
        self.get_logger().info(message)
        self._end(goals.result(success=True, message=message), "succeed")

    def _end(self, result, kind: str) -> None:
        job, self._job = self._job, None
        job.goals.finish(job.gh, kind, result)
        self._publish_world()

    def _publish_world(self) -> None:
        self._world_pub.publish(String(data=self._world.to_json(self._robot)))


def main(args: list[str] | None = None) -> int:
    return run_sim_node(MockGraspServer, "mock_grasp_server", args)


if __name__ == "__main__":
    raise SystemExit(main())
