"""Spoken stop benchmark: end of speech of "stop"/"cancel" → the running nav goal CANCELED.

A spoken "stop" must cancel directly, never queued behind the task; measured from the
end of speech to the goal canceled. Runs, as real processes on a leased ROS domain (loopback), the
simulated robot (``sim_robot`` node set: mock_nav_server slowed down so a goal lasts, mock_grasp_server,
object_query_server, decision_maker) and a real ``audio_command_node`` reading raw PCM from stdin
(VAD segmentation, offline Whisper), written by this script in real time in 20 ms blocks — silence
all along, as a microphone would deliver it. Per trial:

1. publishes "go to the kitchen" / "go home" (alternately) on ``/manual_command`` and waits until the
   nav server reports a new goal active (``navigate_to_pose/_action/status``);
2. after a short pause, puts espeak-ng speech of "stop" or "cancel" (voices and speeds vary) into the
   audio stream, and times from the moment the block holding the last speech sample was written
   (end of speech) to: the recognised text leaving the audio node ("command out"), and the goal's
   status CANCELED.

"Command out": the audio node hands the text to the brain through the ``submit_command`` service
(``CommandClient``; ``/manual_command`` only as its fallback), so the text is not seen on
``/manual_command``; its moment is the arrival here of the node's result line on
``audio_command/status``, published right after the submit (or of the text on ``/manual_command``,
whichever comes first).

Prints median / p90 / max of end of speech → CANCELED, end of speech → command out and command
out → CANCELED, the trials that did not cancel, and the load average (the machine is shared:
timings are noisy).

Usage: ``source scripts/env.sh && python bench/voice_stop_latency.py [--trials 8]`` (≈ 1-2 min;
needs espeak-ng, sox).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import threading
import time

import numpy as np

from decision_maker.speech import testaudio as ta
from decision_maker.speech.text import words
from home_robot_bringup.domain import DomainLease
from home_robot_bringup.launcher import apply_overrides
from home_robot_bringup.nodeset import find_executable, load_nodeset
from home_robot_bringup.process import Supervisor, node_environment

SIM_NODES = ("mock_nav_server", "mock_grasp_server", "object_query_server", "decision_maker")
GOTO = ("go to the kitchen", "go home")
STOPS = ("stop", "cancel")
BLOCK = 320  # samples written per block (20 ms at 16 kHz)
RATE = 16000


class AudioFeed:
    """Writes PCM into the audio node's stdin in real time: silence, or queued speech when there is some."""

    def __init__(self, stdin) -> None:  # noqa: ANN001 - a binary pipe
        self.stdin = stdin
        self.lock = threading.Lock()  # guards pending, end_time
        self.pending = np.zeros(0, dtype="<i2")
        self.end_time: float | None = None  # when the block with the last queued speech sample was written
        self.stop_event = threading.Event()
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self.thread.start()

    def say(self, audio: np.ndarray) -> None:
        pcm = (np.clip(audio, -1, 1) * 32767).astype("<i2")
        with self.lock:
            self.pending = pcm
            self.end_time = None

    def spoken_end(self) -> float | None:
        with self.lock:
            return self.end_time

    def _run(self) -> None:
        silence = np.zeros(BLOCK, dtype="<i2")
        t0 = time.monotonic()
        n = 0
        try:
            while not self.stop_event.is_set():
                n += 1
                delay = t0 + n * BLOCK / RATE - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                with self.lock:
                    if self.pending.size:
                        block, self.pending = self.pending[:BLOCK], self.pending[BLOCK:]
                        last = self.pending.size == 0
                        if block.size < BLOCK:
                            block = np.concatenate([block, silence[:BLOCK - block.size]])
                    else:
                        block, last = silence, False
                self.stdin.write(block.tobytes())
                self.stdin.flush()
                if last:
                    now = time.monotonic()
                    with self.lock:
                        self.end_time = now
        except (BrokenPipeError, ValueError, OSError) as exc:
            self.error = exc

    def close(self) -> None:
        self.stop_event.set()
        self.thread.join(2.0)
        try:
            self.stdin.close()
        except OSError:
            pass


def pct(xs: list[float], q: float) -> float:
    return float(np.percentile(xs, q)) if xs else float("nan")


def row(name: str, xs: list[float]) -> str:
    if not xs:
        return f"{name:34} {0:>3d}        -        -        -"
    return (f"{name:34} {len(xs):3d} {statistics.median(xs) * 1000:8.0f} {pct(xs, 90) * 1000:8.0f} "
            f"{max(xs) * 1000:8.0f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=8)
    ap.add_argument("--speed", type=float, default=0.1, help="mock nav speed, m/s (slow: a goal lasts)")
    ap.add_argument("--pause", type=float, default=0.5,
                    help="seconds between goal active and speech (x3 on 'go to the kitchen' trials)")
    ap.add_argument("--timeout", type=float, default=8.0, help="seconds after end of speech to wait for CANCELED")
    ap.add_argument("-v", "--verbose", action="store_true", help="print each trial")
    args = ap.parse_args(argv)
    if ta.missing_tools():
        print(f"needs {ta.missing_tools()} (apt-get install espeak-ng sox)", file=sys.stderr)
        return 2

    import rclpy
    from action_msgs.msg import GoalStatus, GoalStatusArray
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import String

    from decision_maker.topics import COMMAND_QOS

    status_qos = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                            reliability=ReliabilityPolicy.RELIABLE)
    speech = [(STOPS[i % 2], ta.speak(STOPS[i % 2], *ta.VOICES[i % len(ta.VOICES)])) for i in range(args.trials)]
    load_before = os.getloadavg()[0]

    results: list[dict] = []
    with DomainLease() as lease:
        env = node_environment(lease.domain_id)
        specs = [s for s in load_nodeset("sim_robot") if s.name in SIM_NODES]
        specs = apply_overrides(specs, [f"mock_nav_server.speed={args.speed}", "decision_maker.batch_timeout_s=3600.0"])
        sup = Supervisor(specs, env, echo=None)
        audio = None
        feed = None
        ctx = None
        node = ex = None
        log: list[bytes] = []
        try:
            sup.start()
            exe = find_executable("decision_maker", "audio_command_node")
            audio = subprocess.Popen([exe, "--ros-args", "-p", "source:=stdin", "-p", "segmentation:=vad",
                                      "-p", "wait_for_subscriber_s:=30.0"],
                                     env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
            threading.Thread(target=lambda: log.extend(audio.stdout), daemon=True).start()
            sup.wait_ready(90.0)

            ctx = Context()
            rclpy.init(context=ctx, domain_id=lease.domain_id)
            node = rclpy.create_node("voice_stop_bench", context=ctx)
            cond = threading.Condition()  # guards goals, heard
            goals: dict[bytes, tuple[int, float]] = {}  # goal id -> (status, first time seen)
            heard: list[tuple[float, str]] = []

            def on_goal_status(msg: GoalStatusArray) -> None:
                now = time.monotonic()
                with cond:
                    for st in msg.status_list:
                        key = bytes(st.goal_info.goal_id.uuid)
                        old = goals.get(key)
                        if old is None or old[0] != st.status:
                            goals[key] = (st.status, now)
                    cond.notify_all()

            def on_cmd(msg: String) -> None:
                now = time.monotonic()
                with cond:
                    heard.append((now, msg.data))
                    cond.notify_all()

            cmd = node.create_publisher(String, "manual_command", COMMAND_QOS)
            node.create_subscription(GoalStatusArray, "navigate_to_pose/_action/status", on_goal_status, status_qos)
            node.create_subscription(String, "manual_command", on_cmd, 50)

            def on_status(msg: String) -> None:  # the node's result line, published right after it submits
                now = time.monotonic()
                d = json.loads(msg.data)
                if d.get("event") == "utterance" and d.get("command"):
                    with cond:
                        heard.append((now, d["command"]))
                        cond.notify_all()

            # the node streams once /manual_command and its status topic both have a subscriber
            node.create_subscription(String, "audio_command/status", on_status, 50)
            ex = SingleThreadedExecutor(context=ctx)
            ex.add_node(node)
            threading.Thread(target=ex.spin, daemon=True).start()

            deadline = time.monotonic() + 90
            while not any(b"ready:" in line for line in list(log)):
                if audio.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError("audio_command_node did not start:\n" + b"".join(log).decode(errors="replace"))
                time.sleep(0.05)
            while (cmd.get_subscription_count() < 2 or node.count_publishers("manual_command") < 2) \
                    and time.monotonic() < deadline:
                time.sleep(0.05)
            feed = AudioFeed(audio.stdin)
            feed.start()
            time.sleep(2.0)  # the node's VAD settles on silence

            def active(known: set[bytes]) -> bytes | None:
                for key, (st, _) in goals.items():
                    if key not in known and st in (GoalStatus.STATUS_ACCEPTED, GoalStatus.STATUS_EXECUTING):
                        return key
                return None

            known: set[bytes] = set()
            for i in range(args.trials):
                text, stop_audio = speech[i]
                voice, speed = ta.VOICES[i % len(ta.VOICES)]
                r = {"trial": i, "goto": GOTO[i % 2], "said": text, "voice": f"{voice}/{speed}"}
                results.append(r)
                with cond:
                    known |= set(goals)
                cmd.publish(String(data=GOTO[i % 2]))
                with cond:
                    ok = cond.wait_for(lambda k=known: active(k) is not None, 15.0)
                    goal = active(known)
                if not ok:
                    r["error"] = "no active nav goal"
                    continue
                known.add(goal)
                # the robot drives for a moment: longer outbound, so that the way home outlasts the stop
                time.sleep(args.pause * (3 if i % 2 == 0 else 1))
                with cond:
                    n_heard = len(heard)
                feed.say(stop_audio)
                deadline = time.monotonic() + stop_audio.size / RATE + 2.0
                while feed.spoken_end() is None and time.monotonic() < deadline:
                    time.sleep(0.005)
                t_end = feed.spoken_end()
                if t_end is None:
                    raise RuntimeError(f"audio feed stalled ({feed.error}); audio_command_node:\n"
                                       + b"".join(log[-30:]).decode(errors="replace"))
                with cond:
                    cond.wait_for(lambda g=goal: goals[g][0] in (GoalStatus.STATUS_CANCELED, GoalStatus.STATUS_ABORTED,
                                                               GoalStatus.STATUS_SUCCEEDED), args.timeout)
                    st, t_goal = goals[goal]
                    cond.wait_for(lambda n=n_heard: any(words(h) in (["stop"], ["cancel"]) for _, h in heard[n:]), 0.5)
                    got = sorted((t, h) for t, h in heard[n_heard:] if words(h) in (["stop"], ["cancel"]))
                    r["heard"] = [h for _, h in heard[n_heard:]]
                if got:
                    r["speech_to_text"] = got[0][0] - t_end
                if st == GoalStatus.STATUS_CANCELED:
                    r["speech_to_canceled"] = t_goal - t_end
                    if got:
                        r["text_to_canceled"] = t_goal - got[0][0]
                elif not got:
                    r["error"] = f"not recognised as a stop, so not sent (goal status {st} after {args.timeout:g} s)"
                else:
                    r["error"] = f"stop sent, but goal status {st} after {args.timeout:g} s"
                if args.verbose:
                    print("  " + ", ".join(f"{k}={v:.3f}" if isinstance(v, float) else f"{k}={v}"
                                           for k, v in r.items()), flush=True)
                time.sleep(0.5)
        finally:
            if feed is not None:
                feed.close()
            if audio is not None:
                if audio.poll() is None:
                    audio.terminate()
                    try:
                        audio.wait(5)
                    except subprocess.TimeoutExpired:
                        audio.kill()
                        audio.wait(5)
            if ex is not None:
                ex.shutdown(timeout_sec=1.0)
            if node is not None:
                node.destroy_node()
            if ctx is not None:
                ctx.try_shutdown()
            sup.stop()

    def col(key: str) -> list[float]:
        return [r[key] for r in results if key in r]

    failed = [r for r in results if "speech_to_canceled" not in r]
    print(f"spoken stop benchmark: {len(results)} trials (sim_robot processes + audio_command_node on stdin, VAD, "
          f"espeak-ng 'stop'/'cancel', {len(ta.VOICES)} voices; loopback domain {lease.domain_id})")
    print(f"{'ms':34} {'n':>3} {'median':>8} {'p90':>8} {'max':>8}")
    print(row("end of speech -> goal CANCELED", col("speech_to_canceled")))
    print(row("end of speech -> command out", col("speech_to_text")))
    print(row("command out -> goal CANCELED", col("text_to_canceled")))
    print(f"trials that did not cancel: {len(failed)}/{len(results)}"
          + "".join(f"\n  trial {r['trial']} ({r['said']!r}, {r['voice']}): {r.get('error')}; heard {r.get('heard')}"
                    for r in failed))
    print(f"load average: {load_before:.2f} before, {os.getloadavg()[0]:.2f} after, on {os.cpu_count()} cores "
          "(shared machine: timings are noisy)")
    return 0 if results and not failed else 1


if __name__ == "__main__":
    raise SystemExit(main())
