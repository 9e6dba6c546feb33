"""``run_gs_slam_client``: sends the ``run_gs_slam`` goal and streams a recorded RGB-D sequence.

Any layout the SLAM core reads (Replica / NICE-SLAM, SGS-SLAM with semantics, TUM RGB-D, 7-Scenes)::

    ros_run semantic_gs_slam_ros run_gs_slam_client --ros-args -p dataset:=/data/home_seq -p rate:=10
    ros_run semantic_gs_slam_ros run_gs_slam_client --ros-args -p dataset:=/data/7scenes/seq-01 \
        -p size:=320x240 -p stride:=2 -p start:=0 -p max_frames:=120

``size`` (``WIDTHxHEIGHT``, "" = the files' size) resizes every frame and scales the camera_info.
``preload`` reads (decodes, resizes, registers) every frame before the goal is sent, so that ``rate`` is kept
where reading a frame takes longer than its period (7-Scenes' colour registration: about 0.6 s a frame on 2 busy
cores); memory: about 7 bytes a pixel a frame (500 frames at 320x240: 270 MB as float32 colour and depth).
``colour_calib`` (``auto``, ``none`` or a file) re-samples colour into the depth camera's pixels where
the recording did not register them (7-Scenes; see ``semantic_gs_slam.io.colour_registration``).

It publishes ``rgb`` (rgb8), ``depth`` (32FC1, metres), ``semantic`` (16UC1 ids, when the
dataset has them) and ``camera_info`` with the dataset's timestamps, starting on
``/slam_start_signal``; a frame goes out only while the server is subscribed (the server
unsubscribes when its backlog is too long), so a recording is never dropped. Then it publishes
``/data_transfer_done`` and waits for the result. Ctrl-C cancels the run (the server still
saves the map). Exit code: 0 success, 1 run failed, 2 bad input / no server, 130 cancelled.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
import time

import numpy as np
import rclpy
from action_msgs.msg import GoalStatus
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from semantic_gs_slam_interfaces.action import RunSlam
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String

from home_robot_ros.actions import ActionClient
from home_robot_ros.startup import build_node
from semantic_gs_slam_ros.images import array_to_image_fields

IMAGE_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
#: goal states after which the server has the result
_ENDED = (GoalStatus.STATUS_SUCCEEDED, GoalStatus.STATUS_CANCELED, GoalStatus.STATUS_ABORTED)
#: s to wait for the result of a goal the server reports ended before asking for it again
RESULT_RETRY_S = 5.0
LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)


def image_msg(array: np.ndarray, encoding: str, stamp: float, frame_id: str) -> Image:
    msg = Image(**array_to_image_fields(array, encoding))
    msg.header.stamp.sec = int(stamp)
    msg.header.stamp.nanosec = int(round((stamp - int(stamp)) * 1e9)) % 1_000_000_000
    msg.header.frame_id = frame_id
    return msg


class SlamClient(Node):
    def __init__(self) -> None:
        super().__init__("run_gs_slam_client")
        p = self.declare_parameter
        p("dataset", "")
        p("layout", "auto")
        p("colour_calib", "auto")  # colour registered to depth: auto | none | a calibration file
        p("max_frames", 0)
        p("stride", 1)  # send every k-th frame
        p("start", 0)  # first dataset frame to send
        p("size", "")  # working size WIDTHxHEIGHT ("" = the dataset's own)
        p("rate", 10.0)  # frames per second (0 = as fast as the server takes them)
        p("preload", False)  # read every frame before the goal is sent (keeps `rate` when reading is slower)
        p("output_dir", "")
        p("map_dir", "")
        p("resume", False)
        p("server_timeout", 30.0)
        p("pause_timeout", 600.0)  # longest wait for the server to take images again
        p("frame_id", "camera")
        self._pubs = {s: self.create_publisher(Image, s, IMAGE_QOS) for s in ("rgb", "depth", "semantic")}
        self._info_pub = self.create_publisher(CameraInfo, "camera_info", IMAGE_QOS)
        self._done_pub = self.create_publisher(String, "data_transfer_done", LATCHED)
        self._goal_id: str | None = None
        self._start: dict | None = None  # the start signal of our goal
        self._last_start: dict | None = None  # last start signal seen (any goal); guarded by _fb_lock
        self._started = threading.Event()
        self.create_subscription(String, "slam_start_signal", self._on_start, LATCHED)
        self._action = ActionClient(self, RunSlam, "run_gs_slam")
        self._fb_lock = threading.Lock()  # guards _feedback, _last_start
        self._feedback: RunSlam.Feedback | None = None
        self._t_first = time.monotonic()
        self._last_print = 0.0

    def _on_start(self, msg: String) -> None:
        try:
            doc = json.loads(msg.data)
        except (ValueError, RecursionError):
            return
        done = doc.get("frames_done", 0) if isinstance(doc, dict) else None
        if isinstance(done, int) and not isinstance(done, bool) and done >= 0:
            with self._fb_lock:
                self._last_start = doc  # kept: it may arrive before we know our goal id
            self._check_started()

    def _check_started(self) -> None:
        with self._fb_lock:
            doc = self._last_start
        if doc is not None and self._goal_id is not None and doc.get("goal") == self._goal_id:
            self._start = doc
            self._started.set()

    def _on_feedback(self, msg) -> None:
        with self._fb_lock:
            self._feedback = msg.feedback

    def run(self) -> int:
        from semantic_gs_slam.errors import MAX_BAD_IN_A_ROW, SlamError
        from semantic_gs_slam.io.datasets import frame_indices, load_dataset, parse_size

        g = lambda name: self.get_parameter(name).value  # noqa: E731
        log = self.get_logger()
        if not g("dataset"):
            log.error("parameter 'dataset' is required (a Replica, SGS-SLAM, TUM RGB-D or 7-Scenes folder)")
            return 2
        try:
            size = parse_size(g("size")) if g("size") else None
            data = load_dataset(g("dataset"), g("layout"), size=size, colour_calib=g("colour_calib"))
            indices = frame_indices(len(data), g("start"), max(1, g("stride")), g("max_frames"))
            log.info(data.camera_line())  # the CameraInfo published: cam.json, a TUM preset from the name, ...
            if data.left_out:
                log.warning(f"{g('dataset')}: {data.left_out}")
        except (SlamError, OSError) as exc:
            log.error(f"cannot read dataset {g('dataset')!r}: {exc}")
            return 2
        # preload: every frame read before the goal is sent; dataset index -> Frame, or what reading it raised
        loaded: dict[int, object] = {}
        if g("preload"):
            t_load = time.monotonic()
            for i in indices:
                try:
                    loaded[i] = data[i]
                except (SlamError, OSError) as exc:
                    loaded[i] = exc
            log.info(f"preloaded {len(indices)} frames in {time.monotonic() - t_load:.1f} s")
        if not self._action.wait_for_server(timeout_sec=g("server_timeout")):
            log.error(f"no run_gs_slam action server after {g('server_timeout'):.0f} s (is run_gs_slam_server up?)")
            return 2
        # relative folders mean this process's working folder, not the server's: sent absolute
        goal = RunSlam.Goal(output_dir=_absolute(g("output_dir")), map_dir=_absolute(g("map_dir")),
                            dataset_name=g("dataset"), max_frames=0, resume=g("resume"),
                            semantic_classes=json.dumps({str(k): v for k, v in data.classes.items()}))
        k = data.intrinsics
        self._publish_info(k, 0.0)  # the server needs the camera before the first frame
        sent = self._action.send_goal_async(goal, feedback_callback=self._on_feedback)
        handle = _wait(sent, g("server_timeout"))
        if handle is None:
            log.error(f"no answer to the run_gs_slam goal within {g('server_timeout'):.0f} s (server busy or gone?)")
            return 2
        if not handle.accepted:
            log.error("goal rejected (is another run in progress?)")
            return 2
        self._goal_id = bytes(handle.goal_id.uuid).hex()
        result_future = handle.get_result_async()
        self._t_first = time.monotonic()
        deadline = time.monotonic() + g("server_timeout")
        while not self._started.wait(0.1):
            self._check_started()
            self._publish_info(k, 0.0)  # until the run starts: the server needs the camera first
            if result_future.done():
                log.error(f"run failed before it started: {result_future.result().result.message}")
                return 1
            if time.monotonic() > deadline:
                log.error("no /slam_start_signal from the server")
                handle.cancel_goal_async()
                return 2
        skip = int(self._start.get("frames_done", 0)) if g("resume") else 0
        if skip:
            log.info(f"the server resumes after {skip} frames: skipping them")
            indices = indices[skip:]
        if not indices:
            indices = [len(data) - 1]  # nothing left: send the last frame again so the run can finish
        streams = ["rgb", "depth"] + (["semantic"] if data.sem_paths is not None else [])
        t0_wall, t0_data = time.time(), data.timestamps[indices[0]]
        period = 1.0 / g("rate") if g("rate") > 0 else 0.0
        next_t = time.monotonic()
        n = 0
        skipped: list[int] = []
        bad_in_a_row = 0
        try:
            for i in indices:
                if not self._wait_subscribed(streams, g("pause_timeout"), result_future) or result_future.done():
                    # the run ended on the server (frames it could not use, its engine failed, a cancel): its
                    # result says why; else the image topics stayed unsubscribed for pause_timeout
                    log.error(f"the server ended the run after {n} frames were sent" if result_future.done()
                              else "the server stopped taking images")
                    break
                try:
                    frame = loaded.pop(i) if i in loaded else data[i]
                    if isinstance(frame, Exception):
                        raise frame
                except (SlamError, OSError) as exc:  # a corrupt or missing file: skip the frame, lose nothing
                    skipped.append(i)
                    bad_in_a_row += 1
                    log.warning(f"frame {i} skipped: {exc}")
                    if bad_in_a_row >= MAX_BAD_IN_A_ROW:
                        log.error(f"{bad_in_a_row} frames in a row could not be read: stopping; the server maps "
                                  f"the {n} frames sent")
                        break
                    continue
                bad_in_a_row = 0
                n += 1
                stamp = t0_wall + (frame.timestamp - t0_data)
                rgb = np.clip(frame.rgb * 255.0 + 0.5, 0, 255).astype(np.uint8)
                self._publish_info(k, stamp)
                self._pubs["depth"].publish(image_msg(frame.depth.astype(np.float32), "32FC1", stamp, g("frame_id")))
                if frame.semantics is not None and "semantic" in streams:
                    ids = frame.semantics.astype(np.uint16)
                    self._pubs["semantic"].publish(image_msg(ids, "16UC1", stamp, g("frame_id")))
                self._pubs["rgb"].publish(image_msg(rgb, "rgb8", stamp, g("frame_id")))
                self._print_progress(n, len(indices))
                next_t += period
                time.sleep(max(0.0, next_t - time.monotonic()))
            self._done_pub.publish(String(data=json.dumps({"goal": self._goal_id, "frames_sent": n})))
            if skipped:
                shown = ", ".join(map(str, skipped[:10])) + (" ..." if len(skipped) > 10 else "")
                log.warning(f"skipped {len(skipped)} of {len(indices)} frames that could not be read: {shown}")
            log.info(f"sent {n} frames; waiting for the map")
            ended, gone = None, None  # since when the server reports the goal ended / its action server is gone
            while not result_future.done():
                time.sleep(0.5)
                self._print_progress(n, len(indices))
                now = time.monotonic()
                ended = (ended or now) if handle.status in _ENDED else None
                if ended is not None and now - ended > RESULT_RETRY_S:
                    # the goal has ended on the server but its result has not come: a service request or reply
                    # can be lost while DDS is still matching the two ends, so the result is asked for again (the
                    # server keeps it)
                    log.warning(f"the run ended on the server but its result did not arrive within "
                                f"{RESULT_RETRY_S:g} s: asking again")
                    result_future, ended = handle.get_result_async(), now
                gone = None if self._action.server_is_ready() else (gone or now)
                if gone is not None and now - gone > g("server_timeout"):
                    log.error(f"the run_gs_slam server has been gone for {g('server_timeout'):.0f} s: no map")
                    return 1
        except KeyboardInterrupt:
            log.warning("cancelling the run (the server still saves the map)")
            _wait(handle.cancel_goal_async(), 10.0)
            _wait(result_future, 120.0)
            return 130
        res = result_future.result().result
        (log.info if res.success else log.error)(
            f"{'map ready' if res.success else 'run failed'}: {res.message}; map {res.map_path or '-'}")
        return 0 if res.success else 1

    def _publish_info(self, k, stamp: float) -> None:
        info = CameraInfo()
        info.header.stamp.sec = int(stamp)
        info.header.stamp.nanosec = int(round((stamp - int(stamp)) * 1e9)) % 1_000_000_000
        info.header.frame_id = self.get_parameter("frame_id").value
        info.width, info.height = k.width, k.height
        info.k = [k.fx, 0.0, k.cx, 0.0, k.fy, k.cy, 0.0, 0.0, 1.0]
        info.distortion_model = "plumb_bob"
        info.d = [0.0] * 5
        self._info_pub.publish(info)

    def _wait_subscribed(self, streams: list[str], timeout: float, result_future=None) -> bool:
        """Until the server subscribes to every image topic (it unsubscribes while its backlog is long); False
        after ``timeout`` s, or as soon as ``result_future`` (the goal's result) is done."""
        deadline = time.monotonic() + timeout
        while any(self._pubs[s].get_subscription_count() == 0 for s in streams):
            if time.monotonic() > deadline or (result_future is not None and result_future.done()):
                return False
            time.sleep(0.02)
        return True

    def _print_progress(self, sent: int, total: int) -> None:
        """A progress line: rewritten in place on a terminal (at most 5 Hz), else every 5 s."""
        now = time.monotonic()
        tty = sys.stderr.isatty()
        if now - self._last_print < (0.2 if tty else 5.0) and sent != total:
            return
        self._last_print = now
        with self._fb_lock:
            fb = self._feedback
        done = fb.frames_processed if fb else 0
        lag = fb.lag if fb else 0
        paused = "" if (fb is None or fb.subscribed) else " (server paused intake)"
        rate = done / max(time.monotonic() - self._t_first, 1e-6)
        eta = (total - done) / rate if rate > 0 else float("nan")
        line = f"sent {sent}/{total}  processed {done}  lag {lag}  ETA {eta:5.0f} s{paused}"
        print(f"\r{line}   " if tty else line, end="" if tty else "\n", file=sys.stderr, flush=True)


def _wait(future, timeout: float):
    deadline = time.monotonic() + timeout
    while not future.done() and time.monotonic() < deadline:
        time.sleep(0.01)
    return future.result() if future.done() else None


def _absolute(folder: str) -> str:
    """``folder`` made absolute against this process's working folder ("" stays "": the server's default)."""
    return os.path.abspath(folder) if folder else ""


def main(args: list[str] | None = None) -> int:
    # Ctrl-C must reach run() as KeyboardInterrupt (to cancel the goal and wait for the saved
    # map) while the executor keeps running: rclpy's own handler would shut the context down.
    # Installed explicitly: a process started with SIGINT ignored (a script's background job, some
    # supervisors) keeps ignoring it otherwise, and the run could not be cancelled.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    node = build_node(SlamClient, "run_gs_slam_client")
    if node is None:
        return 2
    executor = MultiThreadedExecutor(num_threads=2)
    executor.add_node(node)
    spinner = threading.Thread(target=_spin, args=(executor,), daemon=True)
    spinner.start()
    try:
        return node.run()
    except KeyboardInterrupt:
        return 130
    finally:
        executor.shutdown(timeout_sec=2.0)
        spinner.join(3.0)  # a spin thread still alive at exit aborts the process (std::terminate)
        node.destroy_node()
        rclpy.try_shutdown()


def _spin(executor) -> None:
    try:
        executor.spin()
    except ExternalShutdownException:
        pass


if __name__ == "__main__":
    raise SystemExit(main())
