"""The brain: ``/manual_command`` → plan → primitives on Nav2 / Grasp / Place; ``/cancel_command`` stops.

Topics:
    /manual_command (std_msgs/String, in): a command in words ("give me the bottle") or primitives.
    /cancel_command (std_msgs/String, in): stop now — clears the queue and cancels the active
        goal(s). Every message cancels, whatever its text (the brain never publishes here).
    /hardware_stop (std_msgs/String, out): the brain's own stop on any timeout, so the hardware
        layer stops too (the simulated servers obey it like /cancel_command).
    submit_command (decision_maker_interfaces/srv/SubmitCommand, service): the acknowledged way in:
        answers with the command id or the rejection reason (see decision_maker.client.command_client).
        A call repeated with the same ``key`` (its answer was lost) gets the first answer again and
        is not run twice (execution/repeated_calls.py).
        A spoken/typed "stop" / "cancel" / "stop it" / "abort" there or on /manual_command cancels at
        once, like /cancel_command.
    /object_list (std_msgs/String JSON, in, transient local): known objects, for slot filling.
    /task_status (std_msgs/String JSON, out, transient local): one update per state change (see
        execution.TaskStatus); the last 2000 are kept for a reader that asks (topics.STATUS_HISTORY_QOS),
        so an operator that joins late or is matched again after a stall misses none.
    /object_memory (object_query_interfaces/ObjectMemory, in, latched): where objects are now; plans
        and answers to questions come from it. Grasps and places are reported to the
        ``object_memory/report`` service (see memory/link.py).

Actions / services used: ``navigate_to_pose`` (nav2_msgs/NavigateToPose), ``grasp`` and ``place``
(decision_maker_interfaces), ``object_query`` (object_query_interfaces/ObjectQuery).

Threads: one MultiThreadedExecutor spins the node in its own thread; callback groups keep the
cancel input, the command input and the clients apart, so ``/cancel_command`` is served while
the execution thread blocks; the execution thread waits on futures/events with deadlines.

Parameters (read at start; see config/params/decision_maker.yaml for the defaults and units):
    planner, planner_options (JSON object: the planner's keyword arguments), locations_file,
    max_queue, max_text_chars, batch_timeout_s, nav_timeout_s,
    grasp_timeout_s, place_timeout_s, query_timeout_s, server_wait_s, cancel_wait_s,
    confirm_llm_plans, confirm_timeout_s (LLM plans wait for "yes"/"no" on /manual_command),
    frame_id, frame_offset ([x, y, yaw] of the map in the command frame: Isaac Sim and co.),
    nav_action, grasp_action, place_action, query_service,
    exploration_mode ("off" | "queue" | "reject", Stage 0: while ``exploration/progress`` says the robot
    explores, commands wait and run when it is done, or are refused; a stop also publishes
    ``exploration/cancel``), exploration_timeout_s (the hold ends by itself after this long).
"""

from __future__ import annotations

import json
import math
import os
import threading
import time

import rclpy
from decision_maker_interfaces.srv import SubmitCommand
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from std_msgs.msg import String

from decision_maker.command_types import FrameTransform, load_locations, sanitize_text
from decision_maker.errors import BadKeyError, ConfigError
from decision_maker.execution.engine import EngineConfig, ExecutionEngine, TaskState, TaskStatus
from decision_maker.execution.repeated_calls import AnswerMemory
from decision_maker.execution.ros_robot import RosRobot
from decision_maker.execution.stage0 import ExplorationGate
from decision_maker.memory.link import MemoryLink
from decision_maker.nl_planner import PlanningContext, make_planner
from decision_maker.planning.stop_words import is_stop_command
from decision_maker.topics import (
    CANCEL_QOS,
    COMMAND_QOS,
    HARDWARE_STOP,
    OBJECT_LIST_QOS,
    SERVICE_QOS,
    STATUS_PUBLISHER_QOS,
    SUBMIT_COMMAND,
)
from home_robot_ros.startup import build_node, read_once

#: Longest /object_list message parsed (characters); a longer one is ignored with a warning.
MAX_OBJECT_LIST_CHARS = 1_000_000


def default_locations_file() -> str:
    from ament_index_python.packages import get_package_share_directory

    return os.path.join(get_package_share_directory("decision_maker"), "config", "locations.yaml")


def _position(value: object) -> tuple[float, float, float]:
    """An /object_list position: exactly three finite numbers (ValueError otherwise)."""
    if not isinstance(value, list) or len(value) != 3 or any(isinstance(v, bool) for v in value):
        raise ValueError(f"bad position {value!r}")
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError, OverflowError) as exc:  # OverflowError: an integer too large for a float
        raise ValueError(f"bad position {value!r:.80}") from exc
    if not all(math.isfinite(v) for v in out):
        raise ValueError(f"bad position {value!r}")
    return out  # type: ignore[return-value]


class DecisionMakerNode(Node):
    """Wires topics, clients and parameters to the :class:`ExecutionEngine`."""

    def __init__(self) -> None:
        super().__init__("decision_maker")
        d = EngineConfig()
        p = {
            "planner": "registry", "planner_options": "{}", "locations_file": "",
            "max_queue": d.max_queue, "max_text_chars": d.max_text_chars,
            "batch_timeout_s": d.batch_timeout_s, "nav_timeout_s": d.nav_timeout_s,
            "grasp_timeout_s": d.grasp_timeout_s, "place_timeout_s": d.place_timeout_s,
            "query_timeout_s": d.query_timeout_s,
            "confirm_llm_plans": d.confirm_llm_plans, "confirm_timeout_s": d.confirm_timeout_s,
            "server_wait_s": 5.0, "cancel_wait_s": 2.0, "memory_report_timeout_s": 5.0,
            "frame_id": "map", "frame_offset": [0.0, 0.0, 0.0],
            "nav_action": "navigate_to_pose", "grasp_action": "grasp", "place_action": "place",
            "query_service": "object_query",
            "exploration_mode": "off", "exploration_timeout_s": 900.0,  # Stage 0 (decision_maker.execution.stage0)
        }
        v = read_once(self, p)

        # Raises ConfigError (reported by main) on bad values.
        config = EngineConfig(
            max_queue=int(v["max_queue"]), max_text_chars=int(v["max_text_chars"]),
            batch_timeout_s=float(v["batch_timeout_s"]), nav_timeout_s=float(v["nav_timeout_s"]),
            grasp_timeout_s=float(v["grasp_timeout_s"]), place_timeout_s=float(v["place_timeout_s"]),
            query_timeout_s=float(v["query_timeout_s"]),
            confirm_llm_plans=bool(v["confirm_llm_plans"]), confirm_timeout_s=float(v["confirm_timeout_s"]),
        )
        for name in ("server_wait_s", "cancel_wait_s", "memory_report_timeout_s"):
            if not float(v[name]) > 0:
                raise ConfigError(f"{name} must be > 0, got {v[name]}")
        offset = list(v["frame_offset"])
        if len(offset) != 3 or not all(math.isfinite(o) for o in offset):
            raise ConfigError(f"frame_offset must be [x, y, yaw], three finite numbers, got {offset}")
        frames = FrameTransform(str(v["frame_id"]), *(float(o) for o in offset))
        locations_file = v["locations_file"] or default_locations_file()
        self._locations = load_locations(locations_file)
        try:
            planner_options = json.loads(v["planner_options"] or "{}")
        except json.JSONDecodeError as exc:
            raise ConfigError(f"planner_options must be a JSON object: {exc}") from exc
        if not isinstance(planner_options, dict):
            raise ConfigError("planner_options must be a JSON object")
        self._planner = make_planner(str(v["planner"]), **planner_options)

        self._objects_lock = threading.Lock()  # guards _objects
        self._objects: dict[str, tuple[float, float, float]] = {}

        # Callback groups: cancel alone (never waits behind anything), command input, clients.
        self._cancel_group = MutuallyExclusiveCallbackGroup()
        self._input_group = MutuallyExclusiveCallbackGroup()
        self._client_group = ReentrantCallbackGroup()

        self._status_pub = self.create_publisher(String, "task_status", STATUS_PUBLISHER_QOS)
        cancel_pub = self.create_publisher(String, HARDWARE_STOP, CANCEL_QOS)
        self.robot = RosRobot(
            self, self._client_group, cancel_pub, frames,
            server_wait_s=float(v["server_wait_s"]), cancel_wait_s=float(v["cancel_wait_s"]),
            names={"nav": v["nav_action"], "grasp": v["grasp_action"], "place": v["place_action"],
                   "query": v["query_service"]},
            on_goal_sent=self._on_goal_sent,
        )
        self._last_timed_id = 0  # command whose first goal was already logged (execution thread only)
        # the object memory: /object_memory in, the robot's own grasps/places reported out
        self.memory = MemoryLink(self, self._input_group, self._client_group,
                                 timeout_s=float(v["memory_report_timeout_s"]))
        self.engine = ExecutionEngine(self._planner, self.robot, config, self._publish_status, self._planning_context,
                                      on_outcome=self.memory.report)
        self._setup_stage0(str(v["exploration_mode"]), float(v["exploration_timeout_s"]))
        self.create_subscription(String, "cancel_command", self._on_cancel, CANCEL_QOS,
                                 callback_group=self._cancel_group)
        self.create_subscription(String, "manual_command", self._on_command, COMMAND_QOS,
                                 callback_group=self._input_group)
        self._answers: AnswerMemory[TaskStatus] = AnswerMemory()  # keyed calls answered once (repeats of lost answers)
        self.create_service(SubmitCommand, SUBMIT_COMMAND, self._on_submit, qos_profile=SERVICE_QOS,
                            callback_group=self._input_group)
        self.create_subscription(String, "object_list", self._on_object_list, OBJECT_LIST_QOS,
                                 callback_group=self._input_group)
        self.get_logger().info(
            f"ready: decision maker (planner {self._planner.name}, {len(self._locations)} locations from "
            f"{locations_file}, queue {config.max_queue}, batch {config.batch_timeout_s:g} s, "
            f"nav {config.nav_timeout_s:g} s, frame {frames.frame_id})"
        )

    def _setup_stage0(self, mode: str, timeout_s: float) -> None:
        """Stage 0: hold (or refuse) commands while ``exploration/progress`` says the robot explores."""
        self._gate = ExplorationGate(mode, timeout_s)  # raises ConfigError
        self._exploration_cancel = self.create_publisher(String, "exploration/cancel", CANCEL_QOS)
        if mode == "off":
            return
        self.engine.set_gate(self._gate.hold)
        self.create_subscription(String, "exploration/progress", self._on_exploration_progress, OBJECT_LIST_QOS,
                                 callback_group=self._input_group)
        self.create_timer(1.0, self._check_exploration_deadline, callback_group=self._input_group)
        self.get_logger().info(f"stage 0: commands are {'queued' if mode == 'queue' else 'refused'} while exploring "
                               f"(at most {timeout_s:g} s)")

    def _on_exploration_progress(self, msg: String) -> None:
        try:
            ended = self._gate.on_progress(msg.data)
        except ValueError as exc:
            self.get_logger().warn(f"ignoring exploration progress: {exc}")
            return
        if ended:
            self.get_logger().info(f"stage 0 done ({self._gate.done_reason}): "
                                   f"{self.engine.queue_length()} queued command(s) run now")
            self.engine.gate_changed()

    def _check_exploration_deadline(self) -> None:
        if self._gate.timed_out():
            self.get_logger().warn(f"stage 0: {self._gate.done_reason}; taking commands now")
            self.engine.gate_changed()

    def _stop_exploration(self, text: str) -> None:
        """A stop (``/cancel_command`` or a spoken one) also ends exploration, as it cancels any goal."""
        if self._gate.mode != "off" and self._gate.hold() is not None:
            self._exploration_cancel.publish(String(data=text[:200]))

    def _on_goal_sent(self, what: str) -> None:
        current = self.engine.current()
        if current is not None and current[0] != self._last_timed_id:
            self._last_timed_id = current[0]
            dt_ms = (time.monotonic() - current[1]) * 1000.0
            self.get_logger().info(f"latency: command #{current[0]} received -> first goal sent ({what}): "
                                   f"{dt_ms:.2f} ms")

    def _planning_context(self) -> PlanningContext:
        with self._objects_lock:
            objects = dict(self._objects)
        memory = self.memory.snapshot()
        known = frozenset(objects) | {b.name for b in memory}
        return PlanningContext(known, self._locations, objects, memory=memory, aliases=self.memory.aliases(known))

    def _publish_status(self, status: TaskStatus) -> None:
        self.get_logger().info(status.line() + (f" — {status.message}" if status.state.terminal else ""))
        self._status_pub.publish(String(data=status.to_json()))

    def _on_command(self, msg: String) -> None:
        if is_stop_command(sanitize_text(msg.data[:200])):
            self._stop_exploration(msg.data)
        self.engine.submit(msg.data)

    def _on_submit(self, request: SubmitCommand.Request, response: SubmitCommand.Response) -> SubmitCommand.Response:
        def run() -> TaskStatus:
            if is_stop_command(sanitize_text(request.text[:200])):
                self._stop_exploration(request.text)
            return self.engine.submit(request.text)  # never blocks: bounded, then queued or rejected

        try:
            status, repeated = self._answers.answer(request.key, run, request.text)
        except BadKeyError as exc:
            response.accepted, response.state, response.message = False, TaskState.REJECTED.value, f"bad key: {exc}"
            return response
        if repeated:
            self.get_logger().info(f"submit_command: call repeated, answered #{status.id} again ({status.state.value})")
        response.accepted = status.state is not TaskState.REJECTED
        response.id = status.id
        response.state = status.state.value
        response.message = status.message
        return response

    def _on_cancel(self, msg: String) -> None:
        # Every message cancels, whoever sent it (the brain's own stop goes to /hardware_stop).
        reason = " ".join(msg.data[:400].split())[:200] or "operator"
        self._stop_exploration(reason)
        n = self.engine.cancel(f"/cancel_command ({reason})")
        self.get_logger().warn(f"/cancel_command ({reason}): cancelled {n} command(s)")

    def _on_object_list(self, msg: String) -> None:
        try:
            if len(msg.data) > MAX_OBJECT_LIST_CHARS:
                raise ValueError("object list too long")
            doc = json.loads(msg.data)
            objects = {str(k).lower(): _position(v) for k, v in doc.items()} if isinstance(doc, dict) else None
        except (json.JSONDecodeError, TypeError, ValueError, RecursionError):
            objects = None
        if objects is None:
            self.get_logger().warn("ignoring a malformed /object_list message")
            return
        with self._objects_lock:
            self._objects = objects
        self.get_logger().info(f"object list: {', '.join(sorted(objects))}")


def main(args: list[str] | None = None) -> int:
    rclpy.init(args=args)
    node = build_node(DecisionMakerNode, "decision_maker", (ConfigError,))
    if node is None:
        return 2
    executor = MultiThreadedExecutor(num_threads=4)
    executor.add_node(node)

    def spin() -> None:
        try:
            executor.spin()
        except ExternalShutdownException:
            pass
        except Exception:  # a wait interrupted by the shutdown (Ctrl-C) is not an error; anything else is
            if rclpy.ok():
                raise

    spinner = threading.Thread(target=spin, name="ros-executor", daemon=True)
    worker = threading.Thread(target=node.engine.run, name="execution", daemon=True)
    spinner.start()
    worker.start()
    try:
        while spinner.is_alive():
            spinner.join(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        node.engine.stop()
        worker.join(3.0)
        executor.shutdown(timeout_sec=2.0)
        spinner.join(2.0)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
