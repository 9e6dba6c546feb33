"""``demo_explore``: Stage 0 end to end in the simulated home (``make demo-explore``).

Brings up the whole simulated robot (node set ``sim_robot``, with the decision maker in
``exploration_mode=queue``) plus the camera on the base, the frontier explorer and the streaming
SLAM server (node set ``slam_sim_camera``), on a freshly leased ROS_DOMAIN_ID with loopback-only
discovery. The robot starts from an empty occupancy grid **and an empty object map**: the object
database waits for the map that SLAM builds from the camera's frames while the robot explores
(tracking guided by the base's simulated wheel odometry) and reloads it every 10 frames and at
the end. "give me the bottle" is said at once and is answered "Still exploring (...); I will do it
after." The demo prints the exploration's progress and the objects found as it goes, then the
command's steps on the self-built map, and ends with figures: the free area seen vs the home's true
free area, time, SLAM's and the odometry's trajectory error against the simulator's ground truth,
and each object's error (the self-built map's position vs the simulator's truth).

Options: ``--set NODE.PARAM=VALUE`` (e.g. ``sim_camera.width=150``), ``--timeout`` (s), ``--verbose``,
``--view`` (also serve the live 3-D view, viser, at the printed URL; ``--view-port``), ``--map-dir``
(keep the map there; default a temporary folder), ``--no-slam`` (the bundled map instead: no mapping).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import threading
import time

import numpy as np

from home_robot_bringup.background import BackgroundNode
from home_robot_bringup.domain import DomainLease
from home_robot_bringup.errors import BringupError
from home_robot_bringup.launcher import apply_overrides
from home_robot_bringup.nodeset import load_nodeset
from home_robot_bringup.process import Supervisor, node_environment

COMMAND = "give me the bottle"


class Watch:
    """Exploration progress, the final /map and /object_list, from the demo's own node."""

    def __init__(self, domain_id: int, echo=sys.stdout) -> None:
        from nav_msgs.msg import OccupancyGrid as GridMsg
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from std_msgs.msg import String

        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE)
        self._echo = echo
        self._t0 = time.monotonic()
        self._lock = threading.Lock()  # guards progress, grid, objects, _last_line
        self.progress: dict = {}
        self.grid = None
        self.objects: dict = {}
        self.objects_at_done: dict | None = None  # /object_list when exploration (and mapping) ended
        self.explored_s: float | None = None  # seconds from the start until exploration ended ...
        self.mapped_s: float | None = None  # ... and until the map was finished (state done)
        self._last_line = ("", -math.inf)
        self._ros = BackgroundNode(domain_id, "demo_explore_watch", threads=1)
        node = self._ros.node
        node.create_subscription(String, "exploration/progress", self._on_progress, latched)
        node.create_subscription(GridMsg, "map", self._on_map, latched)
        node.create_subscription(String, "object_list", self._on_objects, latched)
        from geometry_msgs.msg import PoseStamped

        self.truth: dict[int, np.ndarray] = {}  # stamp (ns) -> camera c2w, the simulator's ground truth
        self.odometry: dict[int, np.ndarray] = {}  # stamp (ns) -> camera c2w from the wheel odometry
        node.create_subscription(PoseStamped, "camera_pose", lambda m: self._on_pose(m, self.truth), 50)
        node.create_subscription(PoseStamped, "odom_camera_pose", lambda m: self._on_pose(m, self.odometry), 50)

    def _on_pose(self, msg, into: dict) -> None:
        from home_robot_ros.poses import pose_to_matrix

        try:
            c2w = np.asarray(pose_to_matrix(msg))
        except ValueError:
            return
        with self._lock:
            into[msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec] = c2w

    def _on_progress(self, msg) -> None:
        try:
            p = json.loads(msg.data)
        except (ValueError, RecursionError):
            return
        if not isinstance(p, dict):
            return
        now = time.monotonic()
        with self._lock:
            self.progress = p
            if p.get("state") in ("mapping", "done") and self.explored_s is None:
                self.explored_s = now - self._t0
            if p.get("state") == "done" and self.objects_at_done is None:
                self.objects_at_done = dict(self.objects)  # before the command moves anything
                self.mapped_s = now - self._t0
            state, last = self._last_line
            show = p.get("state") != state or now - last >= 5.0
            if show:
                self._last_line = (str(p.get("state")), now)
        if show:
            m = p.get("mapping") or {}
            slam = f", SLAM {m.get('state')}: {m.get('frames', 0)} frames mapped" if m.get("state") not in \
                (None, "off") else ""
            self._echo.write(f"demo: {now - self._t0:6.1f} s  exploring: {p.get('state')}{slam}, "
                             f"{p.get('explored_m2', 0):.1f} m2 free seen ({p.get('seen_percent', 0):.0f} %), "
                             f"{p.get('frontiers_left', 0)} frontiers left, {p.get('goals', 0)} goals, "
                             f"{p.get('frames', 0)} frames" + (f" - {p['reason']}" if p.get("reason") else "") + "\n")
            self._echo.flush()

    def _on_map(self, msg) -> None:
        with self._lock:
            self.grid = msg

    def _on_objects(self, msg) -> None:
        try:
            doc = json.loads(msg.data)
        except (ValueError, RecursionError):
            return
        if isinstance(doc, dict):
            with self._lock:
                new = sorted(set(doc) - set(self.objects))
                self.objects = doc
            if new:
                self._echo.write(f"demo: {time.monotonic() - self._t0:6.1f} s  objects in the map: "
                                 f"{', '.join(sorted(doc))} (new: {', '.join(new)})\n")
                self._echo.flush()

    def poses(self) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
        with self._lock:
            return dict(self.truth), dict(self.odometry)

    def snapshot(self) -> tuple[dict, object, dict]:
        """(progress, /map, the objects when exploration ended, or now if it has not)."""
        with self._lock:
            objects = self.objects if self.objects_at_done is None else self.objects_at_done
            return dict(self.progress), self.grid, dict(objects)

    def close(self) -> None:
        self._ros.close()


def coverage_of(msg) -> tuple[float, float, float]:
    """(seen free m2 inside the true free area, true free m2, coverage 0..1) of an OccupancyGrid message."""
    from home_robot_exploration.occupancy import GridConfig, OccupancyGrid
    from home_robot_exploration.simcam import true_free_mask

    res = msg.info.resolution
    grid = OccupancyGrid(GridConfig(resolution=res, origin_x=msg.info.origin.position.x,
                                    origin_y=msg.info.origin.position.y, width_m=msg.info.width * res,
                                    height_m=msg.info.height * res))
    states = np.array(msg.data, dtype=np.int8).reshape(msg.info.height, msg.info.width)
    truth = true_free_mask(grid)
    seen = float(((states == 0) & truth).sum()) * res * res
    total = float(truth.sum()) * res * res
    return seen, total, seen / max(total, 1e-9)


def object_errors(objects: dict) -> list[str]:
    """One line per object of the database (``{name: [x, y, z]}``): its nearest true object of the same
    class (the simulator's world) and the error (m)."""
    from decision_maker.sim.world import SAMPLE_OBJECTS

    truth = json.loads(SAMPLE_OBJECTS)

    def cls_of(name: str) -> str:
        return name.rsplit("_", 1)[0] if name.rsplit("_", 1)[-1].isdigit() else name

    lines = []
    for name, pos in sorted(objects.items()):
        same = [(oid, p) for oid, p in truth.items() if cls_of(oid) == cls_of(name)]
        if not same or not (isinstance(pos, list) and len(pos) == 3):
            continue
        oid, true = min(same, key=lambda kv: math.dist(kv[1], pos))
        lines.append(f"  {name:8s} ({pos[0]:.2f}, {pos[1]:.2f}, {pos[2]:.2f})  true {oid} "
                     f"({true[0]:.2f}, {true[1]:.2f}, {true[2]:.2f})  error {math.dist(pos, true) * 100:.1f} cm")
    return lines or ["  (no graspable object in the database)"]


def save_camera_poses(path: str, truth: dict[int, np.ndarray], odometry: dict[int, np.ndarray]) -> None:
    """The camera's true and odometry poses by stamp (``stamps_ns`` [N], ``truth`` / ``odometry``
    [N, 4, 4], NaN where missing): with the SLAM work folder's frames, enough to replay the run
    offline (``bench/slam_explore_replay.py``)."""
    stamps = sorted(truth)
    if not stamps:
        return
    nan = np.full((4, 4), np.nan)
    np.savez_compressed(path, stamps_ns=np.array(stamps, np.int64), truth=np.stack([truth[t] for t in stamps]),
                        odometry=np.stack([odometry.get(t, nan) for t in stamps]))


def trajectory_errors(map_path: str, truth: dict[int, np.ndarray], odometry: dict[int, np.ndarray]
                      ) -> list[str]:
    """SLAM's and the odometry's camera positions against the simulator's truth, on the frames SLAM
    mapped (matched by stamp): RMSE in the map frame (both start at the true pose, so no alignment)."""
    try:
        with np.load(map_path) as z:
            stamps, rots, trans = z["timestamps"], z["cam_unnorm_rots"][0].T, z["cam_trans"][0].T
    except (OSError, KeyError, ValueError) as exc:
        return [f"  trajectory: cannot read {map_path}: {exc}"]
    est_err, odo_err = [], []
    for t, q, tr in zip(stamps, rots, trans, strict=True):
        ns = int(round(t * 1e9))
        key = min(truth, key=lambda k: abs(k - ns), default=None)
        if key is None or abs(key - ns) > 5_000_000:
            continue
        w, x, y, z = q / np.linalg.norm(q)
        r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                      [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                      [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
        centre = -r.T @ tr  # w2c -> camera position
        est_err.append(np.linalg.norm(centre - truth[key][:3, 3]))
        if key in odometry:
            odo_err.append(np.linalg.norm(odometry[key][:3, 3] - truth[key][:3, 3]))
    if not est_err:
        return ["  trajectory: no SLAM frame matched the simulator's poses"]

    def rmse(e: list[float]) -> float:
        return float(np.sqrt(np.mean(np.square(e)))) * 100

    return [f"  trajectory ({len(est_err)} frames mapped): SLAM ATE {rmse(est_err):.1f} cm (max "
            f"{max(est_err) * 100:.1f} cm); the wheel odometry alone {rmse(odo_err):.1f} cm (max "
            f"{max(odo_err, default=0) * 100:.1f} cm), against the simulator's ground truth"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="demo_explore", description=__doc__.split("\n")[0])
    ap.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                    help="override a parameter, e.g. sim_camera.width=150")
    ap.add_argument("--verbose", action="store_true", help="show the nodes' log lines too")
    ap.add_argument("--view", action="store_true", help="also serve the live 3-D view (viser) in a browser")
    ap.add_argument("--view-port", type=int, default=8080, help="port of the live view (loopback)")
    ap.add_argument("--screenshot", default="", metavar="PNG",
                    help="at the end, save the live view as headless Chromium draws it (implies --view)")
    ap.add_argument("--ready-timeout", type=float, default=120.0)
    ap.add_argument("--timeout", type=float, default=540.0, help="seconds for exploration and the command")
    ap.add_argument("--map-dir", default="", help="where SLAM writes the map (default: a temporary folder)")
    ap.add_argument("--no-slam", action="store_true", help="no mapping: the object database serves the bundled map")
    opts = ap.parse_args(argv)
    opts.view = opts.view or bool(opts.screenshot)

    from decision_maker.command_types import load_locations
    from decision_maker.decision_maker_node import default_locations_file
    from home_robot_bringup.demo import Operator, describe_world

    locations = load_locations(default_locations_file())
    specs = load_nodeset("sim_robot") + [s for s in load_nodeset("explore") if s.name in ("sim_camera", "explorer")]
    if opts.view:
        from home_robot_bringup.nodeset import NodeSpec

        specs.append(NodeSpec("live_view", "home_robot_exploration", "live_view_node",
                              parameters={"port": opts.view_port}, ready="ready:"))
    overrides = ["decision_maker.exploration_mode=queue"]
    map_dir = ""
    if not opts.no_slam:
        import tempfile

        from semantic_gs_slam.synthetic.scenes import CLASSES

        map_dir = os.path.abspath(opts.map_dir) if opts.map_dir else tempfile.mkdtemp(prefix="explore_map_")
        for name in ("params.npz", "semantic.json"):  # from an empty map
            if os.path.exists(os.path.join(map_dir, name)):
                os.remove(os.path.join(map_dir, name))
        specs += load_nodeset("slam_sim_camera")
        if opts.view:  # the view shows the map SLAM is building (re-read each time it is written)
            overrides += [f"live_view.map_path={os.path.join(map_dir, 'params.npz')}", "live_view.map_check_s=2.0"]
        classes = json.dumps({str(i): name for i, name, _ in CLASSES if i > 0})
        # slower turns in 45 degree steps: consecutive frames overlap, so tracking has something to hold on to
        overrides += ["mock_nav_server.turn_rate=0.6", "explorer.look_steps=8",
                      f"run_gs_slam_server.work_dir={os.path.join(map_dir, 'work')}",
                      f"run_gs_slam_server.map_dir={map_dir}", "explorer.slam_action=run_gs_slam",
                      f"explorer.slam_map_dir={map_dir}",
                      f"object_query_server.map_path={os.path.join(map_dir, 'params.npz')}",
                      f"object_query_server.semantic_path={os.path.join(map_dir, 'semantic.json')}",
                      "object_query_server.wait_for_map=true"]
    specs = apply_overrides(specs, [*overrides, *opts.set])
    if map_dir:  # a JSON string: set directly (an override's value is read as YAML, i.e. a mapping)
        specs = [s.with_parameters(slam_classes=classes) if s.name == "explorer" else s for s in specs]
    with DomainLease() as lease:
        env = node_environment(lease.domain_id)
        print(f"demo: ROS_DOMAIN_ID={lease.domain_id}, discovery LOCALHOST; starting the simulated robot with its "
              "camera, the explorer" + (f" and SLAM (empty map, written to {map_dir})" if map_dir else
                                        " (empty grid; objects from the bundled map)") + "...", flush=True)
        t0 = time.monotonic()
        sup = Supervisor(specs, env, echo=sys.stdout if opts.verbose else None)
        try:
            sup.start()
            sup.wait_ready(opts.ready_timeout)
        except BringupError as exc:
            print(f"demo: error: {exc}", file=sys.stderr)
            sup.stop()
            return 1
        op = watch = None
        ok = False
        try:
            watch = Watch(lease.domain_id)
            op = Operator(lease.domain_id)
            if not op.wait_connected(30.0):
                print("demo: error: the decision maker did not connect", file=sys.stderr)
                return 1
            print(f"demo: {len(specs)} nodes ready in {time.monotonic() - t0:.1f} s", flush=True)
            url = ""
            if opts.view:
                ready = [ln for ln in sup.get("live_view").output().splitlines() if "ready: live view at" in ln]
                url = ready[-1].split("ready: live view at ")[1].split(" ")[0] if ready else "?"
                print(f"demo: watch it in a browser: {url}", flush=True)
            print(f"demo: you say: {COMMAND!r}", flush=True)
            t_cmd = time.monotonic()
            op.send(COMMAND)
            done = op.wait_finals([COMMAND], opts.timeout)
            time.sleep(0.6)  # the last world state
            progress, grid, objects = watch.snapshot()
            world = op.snapshot()
            print("demo: the world now:\n" + "\n".join(describe_world(world, locations)), flush=True)
            print("demo: figures", flush=True)
            if grid is not None:
                seen, total, cov = coverage_of(grid)
                took = (f"exploration ended at {watch.explored_s:.0f} s" if watch.explored_s is not None
                        else f"{progress.get('elapsed_s', 0):.0f} s")
                if map_dir and watch.mapped_s is not None:
                    took += f", map finished at {watch.mapped_s:.0f} s"
                print(f"  explored: {seen:.1f} m2 of the home's {total:.1f} m2 free area ({cov * 100:.1f} %), "
                      f"{took}, {progress.get('goals', 0)} goals, {progress.get('frames', 0)} camera frames; "
                      f"ended: {progress.get('reason', '?')}", flush=True)
            else:
                cov = 0.0
                print("  explored: no map received", flush=True)
            print(f"  command: {time.monotonic() - t_cmd:.0f} s from 'give me the bottle' to its end "
                  "(exploration included)", flush=True)
            if map_dir:
                m = progress.get("mapping") or {}
                print(f"  SLAM: {m.get('state')}, {m.get('frames', 0)} frames mapped, {m.get('gaussians', 0)} "
                      f"Gaussians, map {m.get('map_path') or '-'}" + (f" ({m['message']})" if m.get("message") else ""),
                      flush=True)
                truth, odometry = watch.poses()
                save_camera_poses(os.path.join(map_dir, "camera_poses.npz"), truth, odometry)
                if m.get("map_path"):
                    print("\n".join(trajectory_errors(m["map_path"], truth, odometry)), flush=True)
            source = "the map the robot built while exploring" if map_dir else "the bundled map"
            print(f"  objects when exploration ended ({source} vs the simulator's truth):", flush=True)
            print("\n".join(object_errors(objects)), flush=True)
            final = op.finals.get(COMMAND)
            user = locations["user"].drop_point()
            bottle = world["objects"]["bottle"]["position"] if world else [math.nan] * 3
            if opts.screenshot:
                from home_robot_exploration.errors import ConfigError
                from home_robot_exploration.live_view import browser_screenshot, scene_drawn

                try:
                    browser_screenshot(url, opts.screenshot, ready=scene_drawn())
                    print(f"demo: screenshot of the live view: {opts.screenshot}", flush=True)
                except ConfigError as exc:
                    print(f"demo: no screenshot: {exc}", flush=True)
            mapped = not map_dir or (progress.get("mapping") or {}).get("state") == "done"
            ok = bool(done and final is not None and final.state.value == "succeeded"
                      and math.dist(bottle, (user.x, user.y, user.z)) < 0.15 and cov >= 0.85 and mapped)
        finally:
            for closeable in (op, watch):
                if closeable is not None:
                    closeable.close()
            sup.stop()
        what = "explored and mapped, then the bottle is with the user (found in the self-built map)" if map_dir \
            else "explored, then the bottle is with the user"
        print("demo: " + (f"OK - {what}" if ok else "FAILED"), flush=True)
        return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
