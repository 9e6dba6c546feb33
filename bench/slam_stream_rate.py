"""Streaming SLAM at a camera's rate: ``run_gs_slam_server`` fed a real RGB-D sequence by ``run_gs_slam_client``.

Starts the server (``profile`` realtime, 320x240, ``labels`` none by default) and the client replaying the
sequence at ``--rate`` Hz (having read every frame first: ``preload``) on a leased ROS_DOMAIN_ID (discovery on
loopback only), watches the run's action feedback and the camera_info sent with each frame, and prints: frames
sent (and the rate the client achieved), frames processed by SLAM, frames not processed by reason (unmatched
images, refused by the writer or by SLAM, skipped by ``max_behind``), the engine's own note (keyframes deferred
while mapping was busy, frames lost), the lag (frames waiting for SLAM and the seconds of camera time that
makes: the largest, in the last feedback before the last frame was sent, at the end), the processing rate, the
time from the last frame sent to the final map written, and the ATE of the processed frames against the sequence's
poses (the map's ``params.npz`` keeps every processed frame's pose and stamp).

    source scripts/env.sh && python bench/slam_stream_rate.py [SEQ] [--rate 30] [--frames 500] \\
        [--profile realtime] [--labels none] [--refine-seconds 0] [--max-behind 0] [--checkpoint-every 0] \\
        [--no-preload] [--set NODE.PARAM=VALUE ...]

Every wait has a deadline (``--timeout``, s, for the whole run after the client starts).
"""

from __future__ import annotations

import argparse
import os
import re
import tempfile
import threading
import time

import numpy as np

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"

KITCHEN = "/work/shared/data/7scenes-redkitchen-0-499"


class Watcher:
    """The run as seen from outside: the action's feedback (lag, processed) and the stamps and arrival times of the
    camera_info the client publishes with every frame (the camera's timeline; not the images, whose subscription
    count tells the client whether the server takes images)."""

    def __init__(self, node) -> None:
        from semantic_gs_slam_interfaces.action import RunSlam
        from sensor_msgs.msg import CameraInfo

        from semantic_gs_slam_ros.run_gs_slam_server import IMAGE_QOS

        self._lock = threading.Lock()  # guards every field below
        self.stamps: list[float] = []  # header stamps of the frames sent, in arrival order
        self.arrived: list[float] = []  # their arrival (wall clock, s)
        self.lag: list[tuple[float, int, int]] = []  # (wall clock, frames waiting, frames processed) per feedback
        self.received = 0  # colour images the server received (the last feedback's count)
        node.create_subscription(CameraInfo, "camera_info", self._on_info, IMAGE_QOS)
        node.create_subscription(RunSlam.Impl.FeedbackMessage, "run_gs_slam/_action/feedback", self._on_feedback,
                                 10)

    def _on_info(self, msg) -> None:
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        if stamp == 0.0:  # sent before the run starts (the camera for the engine), not a frame
            return
        with self._lock:
            self.stamps.append(stamp)
            self.arrived.append(time.time())

    def _on_feedback(self, msg) -> None:
        fb = msg.feedback
        with self._lock:
            self.lag.append((time.time(), int(fb.lag), int(fb.frames_processed)))
            self.received = max(self.received, int(fb.frames_received))

    def snapshot(self) -> tuple[list[float], list[float], list[tuple[float, int, int]]]:
        with self._lock:
            return list(self.stamps), list(self.arrived), list(self.lag)


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """(w, x, y, z) → [3, 3]."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def map_trajectory(params: str) -> tuple[np.ndarray, list[np.ndarray]]:
    """The stamps [T] and camera-to-world poses of the frames a saved map was made from."""
    with np.load(params) as z:
        rots, trans, stamps = z["cam_unnorm_rots"][0], z["cam_trans"][0], z["timestamps"]
    poses = []
    for i in range(rots.shape[1]):
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = quat_to_rot(rots[:, i].astype(np.float64)), trans[:, i]
        poses.append(np.linalg.inv(w2c))
    return np.asarray(stamps, dtype=np.float64), poses


def ate_of_processed(params: str, sent_stamps: list[float], dataset_indices: list[int], gt: list) -> tuple[float, int]:
    """ATE (cm, rigid alignment) of the map's frames against the sequence's poses, matched by stamp to the k-th
    frame sent (= dataset frame ``dataset_indices[k]``); and how many frames were compared."""
    from semantic_gs_slam.eval.metrics import ate_rmse

    if not gt:  # a sequence without poses
        return float("nan"), 0
    stamps, poses = map_trajectory(params)
    sent = np.asarray(sent_stamps)
    est, ref = [], []
    for t, pose in zip(stamps, poses, strict=True):
        k = int(np.argmin(np.abs(sent - t))) if len(sent) else -1
        if k < 0 or abs(sent[k] - t) > 0.005 or k >= len(dataset_indices) or gt[dataset_indices[k]] is None:
            continue
        est.append(pose)
        ref.append(gt[dataset_indices[k]])
    return (100 * ate_rmse(est, ref) if len(est) >= 3 else float("nan")), len(est)


def log_time(text: str, what: str) -> float | None:
    """Wall-clock time (s) of the last ROS log line that contains ``what`` (rcutils' ``[LEVEL] [time] [node]:``)."""
    found = [float(m) for m in re.findall(r"\[\w+\] \[(\d+\.\d+)\] \[[^\]]+\]: [^\n]*" + re.escape(what), text)]
    return found[-1] if found else None


def server_numbers(text: str) -> dict[str, str]:
    """The reasons and counts the server logs at the end of a run (session.py's final lines)."""
    out: dict[str, str] = {}
    patterns = {
        "unmatched": r"unmatched images dropped: ([^;]+); frames the writer refused: (\d+); frames skipped by SLAM: "
                     r"(\d+)",
        "behind": r"frames skipped while SLAM was more than max_behind=(\d+) frames behind: (\d+)",
        "engine": r"engine: (.+)$",
        "finished": r"run finished: (.+)$",
        "refined": r"map refined (.+)$",
    }
    for key, pat in patterns.items():
        found = re.findall(pat, text, flags=re.MULTILINE)
        if found:
            last = found[-1]
            out[key] = " / ".join(last) if isinstance(last, tuple) else last
    return out


def run(a: argparse.Namespace) -> int:
    from home_robot_bringup.background import BackgroundNode
    from home_robot_bringup.domain import DomainLease
    from home_robot_bringup.launcher import apply_overrides
    from home_robot_bringup.nodeset import NodeSpec
    from home_robot_bringup.process import Supervisor, node_environment
    from semantic_gs_slam.io.datasets import frame_indices, load_dataset

    data = load_dataset(a.dataset)
    indices = frame_indices(len(data), a.start, 1, a.frames)
    w, h = (int(v) for v in a.size.split("x"))
    tmp = tempfile.mkdtemp(prefix="stream_rate_")
    map_dir = os.path.join(tmp, "map")
    params_npz = os.path.join(map_dir, "params.npz")
    server = NodeSpec("run_gs_slam_server", "semantic_gs_slam_ros", "run_gs_slam_server", ready="ready:",
                      parameters={"work_dir": os.path.join(tmp, "work"), "map_dir": map_dir, "width": w, "height": h,
                                  "profile": a.profile, "labels": a.labels, "refine_seconds": a.refine_seconds,
                                  "max_behind": a.max_behind, "checkpoint_every": a.checkpoint_every,
                                  "reload_service": ""})
    client = NodeSpec("run_gs_slam_client", "semantic_gs_slam_ros", "run_gs_slam_client",
                      parameters={"dataset": a.dataset, "size": a.size, "rate": a.rate, "start": a.start,
                                  "max_frames": a.frames, "preload": not a.no_preload})
    server, client = apply_overrides([server, client], a.set)
    print(f"{a.dataset}: {len(indices)} frames from {indices[0]} at {a.rate:g} Hz, {a.size}; server profile "
          f"{a.profile or '-'}, labels {a.labels}, refine_seconds {a.refine_seconds:g}, max_behind {a.max_behind}, "
          f"checkpoint_every {a.checkpoint_every}"
          + (f", {' '.join(a.set)}" if a.set else ""))
    print(f"load average at the start: {' '.join(f'{v:.1f}' for v in os.getloadavg())} "
          f"({os.cpu_count()} CPUs; a shared machine makes wall-clock figures noisy)", flush=True)
    with DomainLease() as lease:
        env = node_environment(lease.domain_id)
        sup = Supervisor([server], env, echo=None)
        csup = Supervisor([client], env, echo=None)
        ros = None
        try:
            sup.start()
            sup.wait_ready(a.ready_timeout)
            ros = BackgroundNode(lease.domain_id, "bench_stream_rate")
            watch = Watcher(ros.node)
            time.sleep(1.0)  # discovery: the watcher's subscriptions matched before the first frame
            t_client = time.time()
            csup.start()
            proc = csup.get("run_gs_slam_client")
            deadline = time.monotonic() + a.timeout
            while proc.returncode() is None and time.monotonic() < deadline:
                time.sleep(0.2)
            if proc.returncode() is None:
                print(f"TIMEOUT: the run did not end within {a.timeout:.0f} s; stopping it")
            rc = proc.returncode()
            t_end = time.time()
        finally:
            csup.stop(grace=10.0)
            if ros is not None:
                ros.close()
            sup.stop(grace=10.0)
    client_out, server_out = proc.output(), sup.get("run_gs_slam_server").output()
    for name, text in (("client.log", client_out), ("server.log", server_out)):
        with open(os.path.join(tmp, name), "w", encoding="utf-8") as fh:
            fh.write(text)
    print(f"logs and map: {tmp}")
    stamps, arrived, lag = watch.snapshot()
    t_sent = log_time(client_out, "frames; waiting for the map")  # the client's own clock: when it sent the last
    nums = server_numbers(server_out)
    sent_m = re.findall(r"sent (\d+) frames; waiting for the map", client_out)
    sent = int(sent_m[-1]) if sent_m else len(stamps)
    processed_m = re.findall(r"(\d+) frames processed \(([\d.]+) frames/s\)", client_out + "\n" + server_out)
    processed = int(processed_m[-1][0]) if processed_m else (lag[-1][2] if lag else 0)
    preload = re.findall(r"preloaded \d+ frames in ([\d.]+) s", client_out)
    print(f"client exit code {rc} (0 = map ready); {t_end - t_client:.1f} s from the client's start to its end"
          + (f" (reading the frames before sending: {preload[-1]} s)" if preload else ""))
    if rc != 0:
        print("client output (tail):\n" + "\n".join(client_out.splitlines()[-15:]))
        print("server output (tail):\n" + "\n".join(server_out.splitlines()[-25:]))
    # the first frame's stamp is the client's wall clock when it began sending (run_gs_slam_client)
    span = t_sent - stamps[0] if stamps and t_sent is not None else float("nan")
    achieved = (sent - 1) / span if span > 0 else float("nan")
    print(f"frames sent: {sent} of {len(indices)} in {span:.1f} s ({achieved:.1f} Hz achieved of {a.rate:g} Hz asked; "
          f"{len(stamps)} seen by this benchmark)")
    print(f"frames processed by SLAM: {processed}")
    pauses = len(re.findall(r"backlog \d+ frames: unsubscribe image topics", server_out))
    unmatched = nums.get("unmatched", "0 / 0 / 0").split(" / ")
    behind = nums.get("behind", f"{a.max_behind} / 0").split(" / ")
    print(f"frames not processed: {sent - processed} - not received {max(sent - watch.received, 0)} (sent while "
          f"the server had unsubscribed, its backlog above lag_high: {pauses} pauses; or its subscriptions' queues, "
          f"image_qos_depth deep, overflowed while its executor was behind), unmatched images {unmatched[0]},"
          f" refused by the writer {unmatched[1]}, refused by SLAM {unmatched[2]}, skipped as SLAM was more than "
          f"max_behind={behind[0]} frames behind {behind[1]}")
    print(f"engine: {nums.get('engine', '(no note)')}")
    if lag:
        waiting = [n for _, n, _ in lag]
        rate = a.rate if a.rate > 0 else float("nan")
        last_sent = t_sent if t_sent is not None else (arrived[-1] if arrived else lag[-1][0])
        during = [n for t, n, _ in lag if t <= last_sent] or waiting
        print(f"lag (frames waiting for SLAM; / {rate:g} Hz = seconds behind the camera): max {max(waiting)} "
              f"({max(waiting) / rate:.1f} s), in the last feedback before the last frame was sent {during[-1]} "
              f"({during[-1] / rate:.1f} s), at the end {waiting[-1]}")
        t_proc = [t for t, _, p in lag if p >= processed]
        if stamps and t_proc:
            wall = t_proc[0] - stamps[0]
            print(f"processing rate: {processed / wall:.2f} frames/s over {wall:.1f} s (first frame on the wire to "
                  f"the last one processed); camera rate {a.rate:g} Hz")
    else:
        print("lag: no feedback seen")
    if os.path.exists(params_npz) and stamps:
        written = os.path.getmtime(params_npz)
        last_sent = t_sent if t_sent is not None else arrived[-1]
        print(f"last frame sent -> final map written: {written - last_sent:.1f} s"
              + (f" (map refined {nums['refined']})" if "refined" in nums else ""))
        ate, n = ate_of_processed(params_npz, stamps, indices, data.poses if data.poses is not None else [])
        print(f"ATE of the processed frames: {ate:.2f} cm over {n} frames (rigid alignment to the sequence's poses)")
    else:
        print("no map written")
    print(f"server's result: {nums.get('finished', '-')}")
    print(f"load average at the end: {' '.join(f'{v:.1f}' for v in os.getloadavg())}")
    return 0 if rc == 0 else 1


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset", nargs="?", default=KITCHEN, help="a recorded RGB-D sequence (any layout the "
                                                                 "client reads)")
    ap.add_argument("--rate", type=float, default=30.0, help="frames per second the client sends (the camera's rate)")
    ap.add_argument("--frames", type=int, default=500, help="frames to send (0 = all)")
    ap.add_argument("--start", type=int, default=0)
    ap.add_argument("--size", default="320x240", help="WIDTHxHEIGHT of the frames sent and mapped")
    ap.add_argument("--profile", default="realtime", help='the server\'s engine profile ("" = none)')
    ap.add_argument("--labels", default="none", help="the server's labels parameter (auto | geometry | onnx | none)")
    ap.add_argument("--refine-seconds", type=float, default=0.0, help="the server's refine_seconds")
    ap.add_argument("--max-behind", type=int, default=0, help="the server's max_behind (0 = never skip)")
    ap.add_argument("--checkpoint-every", type=int, default=0,
                    help="the server's checkpoint_every (0: none; the server's own default is 20)")
    ap.add_argument("--no-preload", action="store_true", help="the client reads each frame as it sends it (the "
                    "camera's rate is then also bounded by the reading: 7-Scenes' colour registration, 0.6 s a frame "
                    "on 2 busy cores)")
    ap.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                    help="any other parameter, e.g. run_gs_slam_server.checkpoint_every=0")
    ap.add_argument("--ready-timeout", type=float, default=120.0)
    ap.add_argument("--timeout", type=float, default=1200.0, help="s for the whole run once the client starts")
    a = ap.parse_args()
    return run(a)


if __name__ == "__main__":
    raise SystemExit(main())
