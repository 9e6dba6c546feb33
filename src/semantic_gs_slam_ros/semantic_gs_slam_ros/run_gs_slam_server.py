"""``run_gs_slam_server``: streaming SLAM as a ROS 2 action server (thin shell over :mod:`.session`).

Action ``run_gs_slam`` (``semantic_gs_slam_interfaces/action/RunSlam``). On a goal the server
cleans its frame folders, subscribes the image topics, publishes ``/slam_start_signal``, feeds
the frames to the SLAM engine kept in memory, and when the client signalled
``/data_transfer_done`` and the backlog is empty, publishes the map where the object-query server
reads it and asks that server to reload. Cancel stops after the current frame and still saves.

Topics (relative names, remap as usual): ``rgb`` (sensor_msgs/Image), ``depth`` (32FC1 metres or
16UC1), ``semantic`` (optional, integer ids), ``camera_info`` (sensor_msgs/CameraInfo),
``odometry_topic`` (parameter, "" = none: geometry_msgs/PoseStamped, the camera-to-map pose from the
robot's odometry in OpenCV camera axes, stamped like the images: the engine's tracking prior and map
frame, see :meth:`semantic_gs_slam.slam.SLAM.add_frame`),
``slam_start_signal`` (std_msgs/String JSON ``{"goal": id, "frames_done": N}``, out; N > 0 after
a resume: the client skips the first N frames of its sequence), ``data_transfer_done``
(std_msgs/String JSON ``{"goal": id, "frames_sent": N}``, in). Both are latched (transient local);
the goal id tells runs apart.
"""

from __future__ import annotations

import json
import math
import os
import sys
import threading
import time

import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import SetParametersResult
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from semantic_gs_slam_interfaces.action import RunSlam
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String
from std_srvs.srv import Trigger

from home_robot_ros.poses import pose_to_matrix
from home_robot_ros.spinning import spin
from home_robot_ros.startup import build_node
from semantic_gs_slam_ros.cancels import CancelRouter
from semantic_gs_slam_ros.engine import camera_info_intrinsics, make_engine, prepare_renderer, switch_interval_for
from semantic_gs_slam_ros.errors import ImageFormatError, StreamingError
from semantic_gs_slam_ros.images import image_to_array
from semantic_gs_slam_ros.lag import LagAction
from semantic_gs_slam_ros.session import Progress, SessionConfig, StreamingSession, checkpoint_state

IMAGE_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
#: work_dir when the parameter is "" (its default)
DEFAULT_WORK_DIR = os.path.join(os.path.expanduser("~"), ".local", "share", "home_robot", "slam")
LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)


#: parameters the server reads once, at start (a change would be ignored, so ``ros2 param set`` refuses it): the
#: object-query reload client, the live view's address, Python's switch interval and the renderer prepared for
#: ``device`` (``slam_enabled`` false prepares none)
START_ONLY = frozenset({"reload_service", "live_view_port", "live_view_host", "gil_switch_interval", "device",
                        "slam_enabled"})


def stamp_seconds(msg: Image) -> float:
    return msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9


def goal_key(goal_handle) -> bytes:
    """A goal's id as bytes (the cancel router's key; ``.hex()`` is what the start and done signals carry)."""
    return bytes(goal_handle.goal_id.uuid)


class SlamServer(Node):
    def __init__(self) -> None:
        super().__init__("run_gs_slam_server")
        p = self.declare_parameter
        p("work_dir", "")  # "" = DEFAULT_WORK_DIR (the params file cannot spell the home directory)
        p("map_dir", "")
        p("start_map", "")  # folder of a saved map (params.npz) to continue, relocalised in its frame; "" = a new map
        p("width", 1200)
        p("height", 680)
        p("depth_scale", 1000.0)
        p("sync_tolerance", 0.02)
        p("sync_max_wait", 5.0)
        p("use_semantic", False)
        p("lag_high", 300)
        p("lag_low", 150)
        p("max_behind", 0)  # live camera: skip the oldest waiting frames beyond this many (0 = never skip)
        p("checkpoint_every", 20)
        p("export_every", 0)
        p("refine_iters", 0)  # Adam iterations over all keyframes after the last frame, before the map is written
        p("refine_poses", False)  # the refinement also optimises its views' poses (false: mapping.refine_poses decides)
        p("refine_seconds", 0.0)  # the refinement's time budget in s (0 = none; with refine_iters 0: this long)
        p("slam_config", "")  # YAML of the engine's SlamConfig ("" = defaults)
        p("profile", "")  # named engine settings under slam_config ("" = none; realtime: every frame of a real
        # camera at its rate on a CPU, docs/slam.md)
        p("device", "auto")  # torch device of the engine: auto (CUDA when present), cpu, cuda, cuda:N;
        # overrides slam_config's device (with CUDA and gsplat installed, renderer backend auto picks gsplat)
        p("slam_enabled", True)  # false = record frames only (no map), e.g. for offline runs
        p("reload_service", "/object_query_server/reload")  # std_srvs/Trigger of object_query_server
        p("done_wait", 10.0)  # s to wait for images still in flight after data_transfer_done
        p("image_qos_depth", 50)
        p("gil_switch_interval", -1.0)  # s; how long a thread waiting for Python's lock waits at most while another
        # runs Python (sys.setswitchinterval; Python's default 0.005). < 0: auto (engine.switch_interval_for: 0.0005
        # with the engine on the CPU, Python's own on CUDA); 0 = leave it as it is
        p("labels", "auto")  # auto | dataset | geometry | onnx | none (auto: the semantic stream if any, else the
        # installed COCO detector, else geometry)
        p("onnx_model", "")  # ONNX COCO segmenter/detector for labels:=onnx/auto ("" = the installed NanoDet-g)
        p("labels_every", 1)  # geometry / onnx labels on every k-th frame only (2 or 4: faster, fewer labelled)
        p("odometry_topic", "")  # PoseStamped camera-to-map odometry (OpenCV axes) as the tracking prior; "" = none
        p("live_view_port", 0)  # > 0: serve the map as it grows and the camera's path in a browser (viser)
        p("live_view_host", "127.0.0.1")  # loopback by default
        p("min_motion_m", 0.0)  # with odometry: skip frames that moved less than this and ...
        p("min_motion_deg", 0.0)  # ... turned less than this since the last mapped one (0 = take every frame)
        self._config(RunSlam.Goal())  # every run's settings, checked now: a bad value stops the node at start
        # a later ros2 param set: refused with the reason for what is read at start only, or for a value the next
        # run could not use (checked as at start); else taken by the next run
        self.add_on_set_parameters_callback(self._on_set_parameters)
        switch = float(self.get_parameter("gil_switch_interval").value)
        if switch > 1.0 or switch != switch:
            raise ValueError(f"gil_switch_interval must be at most 1 s (< 0: auto), got {switch}")
        if switch < 0:
            switch = switch_interval_for(str(self.get_parameter("device").value))
        if switch > 0:
            sys.setswitchinterval(switch)
        self.get_logger().info(f"threads hand Python's lock over every {sys.getswitchinterval() * 1000:g} ms at most")
        self._busy = threading.Lock()  # held while a goal runs (one goal at a time)
        self._session_lock = threading.Lock()  # guards _session, _subs, _intrinsics
        self._cancels = CancelRouter()  # a cancel reaches its own goal's session, also one that comes before it
        self._session: StreamingSession | None = None
        self._subs: list = []
        self._intrinsics: tuple[float, float, float, float, int, int] | None = None  # fx fy cx cy w h
        self._info_refused = ""  # why the latest camera_info was refused ("" when it was taken)
        self._info_note = ""  # the latest camera_info's note (lens distortion), logged when it changes
        self._images_group = ReentrantCallbackGroup()
        self._action_group = ReentrantCallbackGroup()
        self._timer_group = MutuallyExclusiveCallbackGroup()
        self._start_pub = self.create_publisher(String, "slam_start_signal", LATCHED)
        self.create_subscription(String, "data_transfer_done", self._on_done, LATCHED,
                                 callback_group=self._images_group)
        self.create_subscription(CameraInfo, "camera_info", self._on_camera_info, qos_profile_sensor_data,
                                 callback_group=self._images_group)
        self._goal_id: str | None = None  # hex uuid of the running goal
        self._done_expected: int | None = None  # frames the client announced as sent
        self._done_deadline = float("inf")
        name = self.get_parameter("reload_service").value
        self._reload = self.create_client(Trigger, name, callback_group=self._images_group) if name else None
        self._action = ActionServer(self, RunSlam, "run_gs_slam", execute_callback=self._execute,
                                    goal_callback=self._on_goal, cancel_callback=self._on_cancel,
                                    callback_group=self._action_group)
        self.create_timer(0.2, self._tick, callback_group=self._timer_group)
        self.viewer = None
        port = int(self.get_parameter("live_view_port").value)
        if port > 0:
            from semantic_gs_slam.viewer import MapViewer

            try:
                self.viewer = MapViewer(str(self.get_parameter("live_view_host").value), port)
            except ImportError as exc:  # ConfigError / OSError (a bad or taken port) are reported by main()
                raise ValueError(f"live_view_port needs viser (pip install -r requirements/viewer.in): {exc}") from exc
            self.get_logger().info(f"live view at {self.viewer.url} (the map as it is written, the camera's path)")
        if self.get_parameter("slam_enabled").value:
            prepare_renderer(str(self.get_parameter("device").value), self.get_logger().info)
        self.get_logger().info("ready: waiting for a run_gs_slam goal")

    # ------------------------------------------------------------------ images
    def _subscribe(self) -> None:
        self._unsubscribe()  # never two sets of subscriptions
        depth = self.get_parameter("image_qos_depth").value
        qos = QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
        streams = ["rgb", "depth"] + (["semantic"] if self.get_parameter("use_semantic").value else [])
        self._subs = [self.create_subscription(Image, s, self._image_cb(s), qos, callback_group=self._images_group)
                      for s in streams]
        odom = self.get_parameter("odometry_topic").value
        if odom:
            self._subs.append(self.create_subscription(PoseStamped, odom, self._on_odometry, qos,
                                                       callback_group=self._images_group))

    def _on_odometry(self, msg: PoseStamped) -> None:
        session = self._session
        if session is None:
            return
        try:
            session.on_odometry(stamp_seconds(msg), pose_to_matrix(msg).tolist())
        except (StreamingError, ValueError) as exc:
            self.get_logger().warning(f"odometry pose dropped: {exc}", throttle_duration_sec=2.0)

    def _unsubscribe(self) -> None:
        for sub in self._subs:
            self.destroy_subscription(sub)
        self._subs = []

    def _image_cb(self, stream: str):
        def cb(msg: Image) -> None:
            session = self._session
            if session is None:
                return
            try:
                session.on_image(stream, stamp_seconds(msg), image_to_array(msg))
            except (ImageFormatError, StreamingError, ValueError) as exc:
                self.get_logger().warning(f"{stream} image dropped: {exc}", throttle_duration_sec=2.0)
        return cb

    def _on_camera_info(self, msg: CameraInfo) -> None:
        """Keep the latest usable camera; a malformed one is refused with a (throttled) warning and keeps the
        previous; lens distortion is noted once per set of coefficients."""
        try:
            k, note = camera_info_intrinsics(msg.k, msg.d, msg.width, msg.height, msg.distortion_model)
        except StreamingError as exc:
            with self._session_lock:
                self._info_refused = str(exc)
            self.get_logger().warning(f"camera_info refused: {exc}", throttle_duration_sec=5.0)
            return
        with self._session_lock:
            self._intrinsics = k
            self._info_refused = ""
            noted, self._info_note = self._info_note, note
        if note and note != noted:
            self.get_logger().warning(note)

    def _on_done(self, msg: String) -> None:
        try:
            doc = json.loads(msg.data)
            if not isinstance(doc, dict) or doc.get("goal") != self._goal_id or self._goal_id is None:
                return  # another (earlier) run's signal, or not ours at all
            expected = doc["frames_sent"]
            if isinstance(expected, bool) or not isinstance(expected, int) or expected < 0:
                raise ValueError("frames_sent is not a whole number >= 0")
        except (ValueError, KeyError, TypeError, RecursionError):
            self.get_logger().warning(f"malformed data_transfer_done {msg.data[:80]!r} ignored; expected "
                                      '{"goal": id, "frames_sent": N}')
            return
        self._done_deadline = time.monotonic() + self.get_parameter("done_wait").value
        self._done_expected = expected

    def _tick(self) -> None:
        """Every 0.2 s: lag control, and completion once the announced images have arrived."""
        session = self._session
        if session is None:
            return
        action = session.lag_action()
        with self._session_lock:
            if self._session is not session:
                return  # the run ended meanwhile: its subscriptions are gone and must stay gone
            if action is LagAction.UNSUBSCRIBE and self._subs:
                self._unsubscribe()
                self.get_logger().warning("backlog too long: image topics unsubscribed")
            elif action is LagAction.RESUBSCRIBE and not self._subs:
                self._subscribe()
                self.get_logger().info("backlog drained: image topics subscribed again")
        expected = self._done_expected
        if expected is not None:
            # every image stream must have delivered the announced count: the topics are
            # independent, so the last depth images may still be on their way after the colour ones
            streams = session.matcher_streams()
            counts = session.progress().received
            received = min(counts.get(s, 0) for s in streams)
            if received >= expected or time.monotonic() > self._done_deadline:
                if received < expected:
                    got = ", ".join(f"{counts.get(s, 0)} {s}" for s in streams)
                    self.get_logger().warning(f"data_transfer_done: {expected} frames announced, {got} arrived")
                self._done_expected = None
                session.data_transfer_done()

    # ------------------------------------------------------------------ action
    def _on_goal(self, goal: RunSlam.Goal) -> GoalResponse:
        if self._busy.locked():
            self.get_logger().warning("goal rejected: a SLAM run is already in progress")
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _on_cancel(self, goal_handle) -> CancelResponse:
        self._cancels.request(goal_key(goal_handle))
        return CancelResponse.ACCEPT

    def _on_set_parameters(self, params: list) -> SetParametersResult:
        """``ros2 param set``: refused for a parameter read at start only (:data:`START_ONLY`) and for a value the
        next run could not use (the reason is the one a goal would abort with); else taken by the next run."""
        fixed = [p.name for p in params if p.name in START_ONLY]
        if fixed:
            return SetParametersResult(successful=False, reason=f"{self.get_name()} reads {', '.join(fixed)} at "
                                                                "start only; restart the node with the new value")
        try:
            self._config(RunSlam.Goal(), {p.name: p.value for p in params})
        except (StreamingError, ValueError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _config(self, goal: RunSlam.Goal, proposed: dict | None = None) -> SessionConfig:
        """The run's settings: the goal's folders over the parameters (``proposed`` values over the node's own: a
        change checked before it is taken).

        Raises:
            StreamingError: a bad value (the goal aborts with it; at start, the node refuses to run).
        """
        for name in ("output_dir", "map_dir"):
            folder = getattr(goal, name)
            if folder and not os.path.isabs(folder):
                raise StreamingError(f"the goal's {name} must be an absolute path (the server's working folder is "
                                     f"not the client's), got {folder[:200]!r}")
        proposed = proposed or {}
        g = lambda name: proposed[name] if name in proposed else self.get_parameter(name).value  # noqa: E731
        if g("image_qos_depth") < 1:
            raise StreamingError(f"image_qos_depth must be >= 1, got {g('image_qos_depth')}")
        done_wait = g("done_wait")
        if not (math.isfinite(done_wait) and done_wait >= 0):
            raise StreamingError(f"done_wait must be a finite number of seconds >= 0, got {done_wait}")
        return SessionConfig(
            work_dir=goal.output_dir or g("work_dir") or DEFAULT_WORK_DIR,
            map_dir=goal.map_dir or g("map_dir"),
            width=g("width"), height=g("height"), depth_scale=g("depth_scale"),
            sync_tolerance=g("sync_tolerance"), sync_max_wait=g("sync_max_wait"),
            use_semantic=g("use_semantic"), use_odometry=bool(g("odometry_topic")),
            min_motion_m=float(g("min_motion_m")), min_motion_deg=float(g("min_motion_deg")),
            lag_high=g("lag_high"), lag_low=g("lag_low"), max_behind=int(g("max_behind")),
            checkpoint_every=g("checkpoint_every"), export_every=g("export_every"),
            refine_iters=int(g("refine_iters")),
            refine_poses=bool(g("refine_poses")), refine_seconds=float(g("refine_seconds")),
            max_frames=goal.max_frames, clean_start=not goal.resume)

    def _execute(self, goal_handle) -> RunSlam.Result:
        result = RunSlam.Result()
        if not self._busy.acquire(blocking=False):
            self._cancels.finish(goal_key(goal_handle))  # its early cancel, if any, is not kept
            goal_handle.abort()
            result.message = "another run is in progress"
            return result
        try:
            return self._run(goal_handle, result)
        finally:
            with self._session_lock:
                self._unsubscribe()
                self._session = None
                self._goal_id = None
            self._cancels.finish(goal_key(goal_handle))
            self._busy.release()

    def _run(self, goal_handle, result: RunSlam.Result) -> RunSlam.Result:
        goal: RunSlam.Goal = goal_handle.request
        self._done_expected = None
        self._done_deadline = float("inf")
        try:
            cfg = self._config(goal)  # a bad parameter value is a StreamingError: the goal aborts with it
            resume_state = checkpoint_state(cfg.work_dir) if goal.resume else None
            cfg.frames_before = int(resume_state["processed"]) if resume_state else 0
            engine = None
            if self.get_parameter("slam_enabled").value:
                engine = make_engine(self.get_parameter("slam_config").value, self._wait_intrinsics, cfg,
                                     overrides={"device": str(self.get_parameter("device").value)},
                                     classes=parse_classes(goal.semantic_classes),
                                     resume_dir=os.path.join(cfg.work_dir, "checkpoint") if resume_state else None,
                                     start_map=str(self.get_parameter("start_map").value),
                                     labels=(self.get_parameter("labels").value,
                                             self.get_parameter("onnx_model").value),
                                     labels_every=self.get_parameter("labels_every").value,
                                     profile=str(self.get_parameter("profile").value))
            session = StreamingSession(cfg, engine, on_map=self._request_reload,
                                       log=lambda line: self.get_logger().info(line))
        except StreamingError as exc:
            goal_handle.abort()
            result.message = str(exc)
            self.get_logger().error(f"run_gs_slam: {exc}")
            return result
        with self._session_lock:
            self._session = session
            self._subscribe()
        # a cancel that came while the engine was being made had no session to reach: the router kept it
        if not self._cancels.start(goal_key(goal_handle), session) and goal_handle.is_cancel_requested:
            session.cancel()
        done_before = cfg.frames_before
        start_map = str(self.get_parameter("start_map").value)
        if resume_state:
            what = f"resuming after frame {done_before}"
        elif start_map and engine is not None:
            what = f"continuing the saved map {start_map}: mapping starts once a frame is relocalised in it"
        else:
            what = "fresh start"
        self._goal_id = goal_key(goal_handle).hex()
        self._start_pub.publish(String(data=json.dumps({"goal": self._goal_id, "frames_done": done_before,
                                                        "dataset": goal.dataset_name})))
        self.get_logger().info(f"run started ({what}); work_dir={cfg.work_dir}, map_dir={cfg.resolved_map_dir()}")

        def feedback(p: Progress) -> None:
            goal_handle.publish_feedback(to_feedback(p))
            if self.viewer is not None and p.pose is not None:
                self.viewer.show_camera(np.asarray(p.pose))

        out = session.run(on_progress=feedback)
        result.success, result.map_path, result.semantic_path = out.success, out.map_path, out.semantic_path
        result.frames_processed, result.message = out.frames_processed, out.message
        if goal_handle.is_cancel_requested:
            goal_handle.canceled()
        elif out.success:
            goal_handle.succeed()
        else:
            goal_handle.abort()
        self.get_logger().info(f"run finished: {out.message}")
        return result

    def _wait_intrinsics(self, timeout: float = 5.0) -> tuple[float, float, float, float, int, int] | None:
        """The latest usable camera, waiting up to ``timeout`` s for one; None when none came.

        Raises:
            StreamingError: none usable came, but a refused one did (the message says why it was refused).
        """
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._session_lock:
                if self._intrinsics is not None:
                    return self._intrinsics
            time.sleep(0.05)
        with self._session_lock:
            refused = self._info_refused
        if refused:
            raise StreamingError(f"no usable camera_info received; the last one was refused: {refused}")
        return None

    def _request_reload(self, map_path: str, semantic_path: str) -> None:
        """Show the map just written in the live view, and ask the object-query server to load it
        (SLAM thread; bounded wait)."""
        if self.viewer is not None:
            from semantic_gs_slam.errors import SlamError

            try:
                with np.load(map_path) as z:
                    n = self.viewer.show_map({k: z[k] for k in z.files})
                self.get_logger().info(f"live view: {n} Gaussians")
            except (OSError, ValueError, SlamError) as exc:
                self.get_logger().warning(f"live view not updated: {exc}")
        if self._reload is None:
            return
        if not self._reload.wait_for_service(timeout_sec=2.0):
            self.get_logger().info(f"map written; no {self._reload.srv_name} service to ask for a reload")
            return
        future = self._reload.call_async(Trigger.Request())
        done = threading.Event()
        future.add_done_callback(lambda _f: done.set())
        if not done.wait(10.0):
            self.get_logger().warning(f"{self._reload.srv_name} did not answer within 10 s")
            return
        res = future.result()
        (self.get_logger().info if res.success else self.get_logger().warning)(
            f"object-query reload: {res.message}")


def parse_classes(text: str) -> dict[int, str]:
    """Goal field ``semantic_classes``: JSON ``{"1": "chair", ...}`` ("" = none).

    Raises:
        StreamingError: not a JSON object of id → name.
    """
    if not text:
        return {}
    try:
        doc = json.loads(text)
        classes = {int(k): v for k, v in doc.items()}
    except (ValueError, AttributeError, TypeError, RecursionError) as exc:
        raise StreamingError(f"semantic_classes must be JSON {{\"id\": \"name\"}}: {str(exc)[:120]}") from exc
    for k, v in classes.items():
        if not 0 <= k < 2**31 or not isinstance(v, str) or len(v) > 256:
            raise StreamingError(f"semantic_classes: ids are whole numbers 0 .. 2^31 - 1 and names strings of at "
                                 f"most 256 characters, got {str(k)[:40]}: {str(v)[:40]!r}")
    return classes


def to_feedback(p: Progress) -> RunSlam.Feedback:
    fb = RunSlam.Feedback()
    fb.frames_received = p.received.get("rgb", 0)
    fb.frames_written = p.written
    fb.frames_processed = p.processed
    # unmatched; refused by the writer, by SLAM; skipped while SLAM was more than max_behind frames behind
    fb.frames_dropped = sum(p.dropped.values()) + p.refused + p.skipped + p.behind
    fb.lag = max(p.backlog, 0)
    fb.subscribed = p.subscribed
    fb.num_gaussians = p.gaussians
    if p.pose is not None:
        from semantic_gs_slam_ros.engine import pose_msg_fields

        (fb.current_pose.position.x, fb.current_pose.position.y, fb.current_pose.position.z,
         fb.current_pose.orientation.w, fb.current_pose.orientation.x, fb.current_pose.orientation.y,
         fb.current_pose.orientation.z) = pose_msg_fields(p.pose)
    return fb


def main(args: list[str] | None = None) -> int:
    rclpy.init(args=args)
    # the live view's port taken (OSError), a bad parameter value (ValueError)
    node = build_node(SlamServer, "run_gs_slam_server", (OSError, ValueError, StreamingError))
    if node is None:
        return 2
    executor = MultiThreadedExecutor(num_threads=4)
    executor.add_node(node)
    try:
        spin(executor, node.get_logger())  # a run's end destroys its image subscriptions while the executor spins
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        session = node._session
        if session is not None:
            session.cancel()
        executor.shutdown(timeout_sec=5.0)
        if node.viewer is not None:
            node.viewer.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
