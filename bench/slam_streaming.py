"""Benchmark of the streaming SLAM server (issue: SLAM streaming over ROS 2).

A. Per-frame overhead — everything but the SLAM optimisation itself — of our in-process server
   (engine kept in memory) vs the seed's subprocess-per-frame mode (a new Python process per frame
   that imports the engine, loads the checkpoint, reads the frame, saves the checkpoint), on the
   same frames in the same run. Target: ≥ 10× less overhead in-process.
B. Sustained input rate at 1200×680 over ROS 2: a publisher sends colour (rgb8) + depth (32FC1)
   at increasing rates to ``run_gs_slam_server`` in record-only mode; the highest rate with no
   frame lost is the rate the server accepts (intake: decode, match, JPEG/PNG writing).

    source scripts/env.sh && python bench/slam_streaming.py [--frames 10] [--rates 5 10 15 20 30]

Discovery stays on loopback (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) on a leased ROS_DOMAIN_ID.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

SETTLE_S = 0.5  # see run_gs_slam_client: let discovery finish matching both sides
FAST = "mapping: {first_frame_iters: 10, iters: 4, keyframe_every: 3}\ntracking: {icp_iters: 6}\n"


def part_a(frames: int, width: int, height: int, tmp: str) -> None:
    from semantic_gs_slam.io.datasets import load_dataset
    from semantic_gs_slam.synthetic.scenes import generate
    from semantic_gs_slam_ros.engine import EngineAdapter, load_slam_config
    from semantic_gs_slam_ros.session import SessionConfig, StreamingSession

    seq = os.path.join(tmp, "seq")
    generate(seq, frames=frames, width=width, height=height)
    data = load_dataset(seq)
    cfg_path = os.path.join(tmp, "fast.yaml")
    with open(cfg_path, "w") as fh:
        fh.write(FAST)
    k = data.intrinsics
    intr = (k.fx, k.fy, k.cx, k.cy, k.width, k.height)
    from semantic_gs_slam.slam import SLAM

    config, _ = load_slam_config(cfg_path, intr)
    engine = EngineAdapter(SLAM(config))
    add_times: list[float] = []
    inner = engine.add_frame

    def timed_add(*a, **kw):
        t0 = time.perf_counter()
        out = inner(*a, **kw)
        add_times.append(time.perf_counter() - t0)
        return out

    engine.add_frame = timed_add  # type: ignore[method-assign]
    work = os.path.join(tmp, "inproc")
    session = StreamingSession(SessionConfig(work_dir=work, width=width, height=height, checkpoint_every=1,
                                             use_semantic=False), engine)
    t0 = time.perf_counter()
    for i in range(len(data)):
        f = data[i]
        rgb = np.clip(f.rgb * 255 + 0.5, 0, 255).astype(np.uint8)
        session.on_image("depth", f.timestamp, f.depth)
        session.on_image("rgb", f.timestamp, rgb)
    session.data_transfer_done()
    res = session.run()
    total_in = time.perf_counter() - t0
    assert res.frames_processed == len(data), res.message
    over_in = (total_in - sum(add_times)) / len(data)

    walls, adds = [], []
    for i in range(len(data)):
        t0 = time.perf_counter()
        out = subprocess.run([sys.executable, "-m", "semantic_gs_slam_ros.per_frame", "--work", work, "--index",
                              str(i), "--config", cfg_path, "--intrinsics", *map(str, intr)],
                             capture_output=True, text=True, check=True)
        walls.append(time.perf_counter() - t0)
        adds.append(json.loads(out.stdout.strip().splitlines()[-1])["add_frame_s"])
    # the seed writes the frames to disk too: its overhead = ours (intake + writing, same code) + the
    # per-frame process (start, imports, checkpoint load and save)
    over_sub = over_in + statistics.mean(w - a for w, a in zip(walls, adds, strict=True))
    print(f"A. per-frame overhead, {len(data)} frames {width}x{height}, checkpoint every frame in both modes")
    print(f"   in-process (ours):        {over_in * 1000:8.1f} ms/frame   "
          f"(SLAM itself {statistics.mean(add_times) * 1000:.0f} ms/frame)")
    print(f"   subprocess per frame:     {over_sub * 1000:8.1f} ms/frame   "
          f"(SLAM itself {statistics.mean(adds) * 1000:.0f} ms/frame)")
    print(f"   ratio subprocess / ours:  {over_sub / over_in:8.1f}x   (target >= 10x)")


def part_b(rates: list[float], seconds: float, tmp: str) -> None:
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from semantic_gs_slam_interfaces.action import RunSlam
    from sensor_msgs.msg import CameraInfo, Image
    from std_msgs.msg import String

    from home_robot_bringup.background import BackgroundNode
    from home_robot_bringup.domain import DomainLease
    from home_robot_bringup.nodeset import NodeSpec
    from home_robot_bringup.process import Supervisor, node_environment
    from home_robot_ros.actions import ActionClient
    from semantic_gs_slam_ros.images import array_to_image_fields

    w, h = 1200, 680
    rng = np.random.default_rng(0)
    frames = [(np.ascontiguousarray(rng.integers(0, 255, (h, w, 3), dtype=np.uint8)),
               (1.0 + rng.random((h, w))).astype(np.float32)) for _ in range(4)]
    print(f"B. sustained intake at {w}x{h} (rgb8 + 32FC1 depth), record-only server, {seconds:g} s per rate")
    with DomainLease() as lease:
        spec = NodeSpec("run_gs_slam_server", "semantic_gs_slam_ros", "run_gs_slam_server", ready="ready:",
                        parameters={"work_dir": os.path.join(tmp, "rate"), "width": w, "height": h,
                                    "slam_enabled": False, "done_wait": 5.0, "image_qos_depth": 100})
        sup = Supervisor([spec], node_environment(lease.domain_id), echo=None)
        sup.start()
        sup.wait_ready(60)
        ros = BackgroundNode(lease.domain_id, "bench_streamer")
        node = ros.node
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE)
        pub_rgb = node.create_publisher(Image, "rgb", qos)
        pub_depth = node.create_publisher(Image, "depth", qos)
        pub_info = node.create_publisher(CameraInfo, "camera_info", qos)
        pub_done = node.create_publisher(String, "data_transfer_done", latched)
        action = ActionClient(node, RunSlam, "run_gs_slam")
        assert action.wait_for_server(timeout_sec=30)
        msgs = [(Image(**array_to_image_fields(c, "rgb8")), Image(**array_to_image_fields(d, "32FC1")))
                for c, d in frames]
        best = 0.0
        try:
            for rate in rates:
                info = CameraInfo(width=w, height=h, k=[600.0, 0, 599.5, 0, 600.0, 339.5, 0, 0, 1])
                pub_info.publish(info)
                handle = _wait(action.send_goal_async(RunSlam.Goal()), 30)
                goal = bytes(handle.goal_id.uuid).hex()
                result = handle.get_result_async()
                while pub_rgb.get_subscription_count() == 0 or pub_depth.get_subscription_count() == 0:
                    time.sleep(0.02)
                time.sleep(SETTLE_S)  # the server's side of the match may lag the publisher's
                n = int(rate * seconds)
                t_start = time.monotonic()
                base = time.time()
                for i in range(n):
                    rgb, depth = msgs[i % len(msgs)]
                    stamp = base + i / rate
                    for m in (rgb, depth):
                        m.header.stamp.sec, m.header.stamp.nanosec = int(stamp), int((stamp % 1) * 1e9)
                    pub_depth.publish(depth)
                    pub_rgb.publish(rgb)
                    time.sleep(max(0.0, t_start + (i + 1) / rate - time.monotonic()))
                sent_rate = n / (time.monotonic() - t_start)
                pub_done.publish(String(data=json.dumps({"goal": goal, "frames_sent": n})))
                res = _wait(result, 120).result
                lost = n - res.frames_processed
                ok = lost == 0
                best = rate if ok else best
                print(f"   {rate:5.1f} Hz offered ({sent_rate:5.1f} Hz achieved by the publisher): "
                      f"{res.frames_processed}/{n} frames written, {lost} lost")
                if not ok:
                    break
        finally:
            ros.close()
            sup.stop()
    print(f"   highest rate with no frame lost: {best:g} Hz (load average {os.getloadavg()[0]:.1f})")


def _wait(future, timeout: float):
    deadline = time.monotonic() + timeout
    while not future.done() and time.monotonic() < deadline:
        time.sleep(0.005)
    if not future.done():
        raise TimeoutError("no answer")
    return future.result()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--width", type=int, default=300)
    ap.add_argument("--height", type=int, default=170)
    ap.add_argument("--rates", type=float, nargs="+", default=[5, 10, 20, 30, 40])
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--skip-a", action="store_true")
    ap.add_argument("--skip-b", action="store_true")
    a = ap.parse_args()
    print(f"load average at start: {os.getloadavg()[0]:.1f} (2 cores; other jobs make the figures noisy)")
    with tempfile.TemporaryDirectory() as tmp:
        if not a.skip_a:
            part_a(a.frames, a.width, a.height, tmp)
        if not a.skip_b:
            part_b(a.rates, a.seconds, tmp)


if __name__ == "__main__":
    main()
