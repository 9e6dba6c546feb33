"""``demo_explore``: Stage 0 end to end in the simulated home (``make demo-explore``).

Brings up the whole simulated robot (node set ``sim_robot``, with the decision maker in
``exploration_mode=queue``) plus the camera on the base and the frontier explorer, on a freshly
leased ROS_DOMAIN_ID with loopback-only discovery. The robot starts from an empty occupancy grid;
"give me the bottle" is said at once and is answered "Still exploring (...); I will do it after."
The demo prints the exploration's progress as it goes, then the command's steps, and ends with
figures: the free area seen vs the home's true free area, exploration time, goals and frames,
and each object's error (the object database's position vs the simulator's truth).

Not yet in the loop (see docs/exploration.md): the SLAM map is not rebuilt from the explorer's
frames, so the object positions come from the bundled map.

Options: ``--set NODE.PARAM=VALUE`` (e.g. ``sim_camera.width=150``), ``--timeout`` (s), ``--verbose``,
``--view`` (also serve the live 3-D view, viser, at the printed URL; ``--view-port``).
"""

from __future__ import annotations

import argparse
import json
import math
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
        self._last_line = ("", -math.inf)
        self._ros = BackgroundNode(domain_id, "demo_explore_watch", threads=1)
        node = self._ros.node
        node.create_subscription(String, "exploration/progress", self._on_progress, latched)
        node.create_subscription(GridMsg, "map", self._on_map, latched)
        node.create_subscription(String, "object_list", self._on_objects, latched)

    def _on_progress(self, msg) -> None:
        try:
            p = json.loads(msg.data)
        except json.JSONDecodeError:
            return
        now = time.monotonic()
        with self._lock:
            self.progress = p
            state, last = self._last_line
            show = p.get("state") != state or now - last >= 5.0
            if show:
                self._last_line = (str(p.get("state")), now)
        if show:
            self._echo.write(f"demo: {now - self._t0:6.1f} s  exploring: {p.get('state')}, "
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
        except json.JSONDecodeError:
            return
        if isinstance(doc, dict):
            with self._lock:
                self.objects = doc

    def snapshot(self) -> tuple[dict, object, dict]:
        with self._lock:
            return dict(self.progress), self.grid, dict(self.objects)

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
    from decision_maker.sim_world import SAMPLE_OBJECTS

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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="demo_explore", description=__doc__.split("\n")[0])
    ap.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                    help="override a parameter, e.g. sim_camera.width=150")
    ap.add_argument("--verbose", action="store_true", help="show the nodes' log lines too")
    ap.add_argument("--view", action="store_true", help="also serve the live 3-D view (viser) in a browser")
    ap.add_argument("--view-port", type=int, default=8080, help="port of the live view (loopback)")
    ap.add_argument("--ready-timeout", type=float, default=120.0)
    ap.add_argument("--timeout", type=float, default=540.0, help="seconds for exploration and the command")
    opts = ap.parse_args(argv)

    from decision_maker.command_types import load_locations
    from decision_maker.decision_maker_node import default_locations_file
    from home_robot_bringup.demo import Operator, describe_world

    locations = load_locations(default_locations_file())
    specs = load_nodeset("sim_robot") + [s for s in load_nodeset("explore") if s.name in ("sim_camera", "explorer")]
    if opts.view:
        from home_robot_bringup.nodeset import NodeSpec

        specs.append(NodeSpec("live_view", "home_robot_exploration", "live_view_node",
                              parameters={"port": opts.view_port}, ready="ready:"))
    specs = apply_overrides(specs, ["decision_maker.exploration_mode=queue", *opts.set])
    with DomainLease() as lease:
        env = node_environment(lease.domain_id)
        print(f"demo: ROS_DOMAIN_ID={lease.domain_id}, discovery LOCALHOST; starting the simulated robot with its "
              "camera and the explorer (empty map)...", flush=True)
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
                print(f"  explored: {seen:.1f} m2 of the home's {total:.1f} m2 free area ({cov * 100:.1f} %), "
                      f"{progress.get('elapsed_s', 0):.0f} s, {progress.get('goals', 0)} goals, "
                      f"{progress.get('frames', 0)} frames; ended: {progress.get('reason', '?')}", flush=True)
            else:
                cov = 0.0
                print("  explored: no map received", flush=True)
            print(f"  command: {time.monotonic() - t_cmd:.0f} s from 'give me the bottle' to its end "
                  "(exploration included)", flush=True)
            print("  objects (object database on the bundled map; the SLAM map is not rebuilt yet):", flush=True)
            print("\n".join(object_errors(objects)), flush=True)
            final = op.finals.get(COMMAND)
            user = locations["user"].drop_point()
            bottle = world["objects"]["bottle"]["position"] if world else [math.nan] * 3
            ok = bool(done and final is not None and final.state.value == "succeeded"
                      and math.dist(bottle, (user.x, user.y, user.z)) < 0.15 and cov >= 0.85)
        finally:
            for closeable in (op, watch):
                if closeable is not None:
                    closeable.close()
            sup.stop()
        print("demo: " + ("OK - explored, then the bottle is with the user" if ok else "FAILED"), flush=True)
        return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
