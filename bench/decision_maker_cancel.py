"""Benchmark: how fast the decision maker stops the robot, and how fast it starts.

Runs the simulated nav server and the decision maker as real processes on a leased ROS domain
(loopback only), and from this process, per trial:

1. publishes a ``goto`` command on ``/manual_command`` and waits until the nav server reports the
   goal active (``navigate_to_pose/_action/status``);
2. publishes ``/cancel_command`` and times until that goal is CANCELED on the server's status
   topic, and until ``/task_status`` says ``cancelled``.

Prints median / p90 / p99 / max over the trials, and the decision maker's own measurement of
"command received → first goal sent" (its ``latency:`` log lines).

``--stop-via manual_command`` stops with a typed/spoken "stop" on ``/manual_command`` instead
(the brain cancels it directly, never queued); ``--stop-via both`` alternates the two in one run
and prints the ratio of the spoken stop's median to ``/cancel_command``'s (the baseline).

Usage: ``source scripts/env.sh && python bench/decision_maker_cancel.py [--trials 200] [--stop-via both]``
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import threading
import time

import rclpy
from action_msgs.msg import GoalStatus, GoalStatusArray
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from decision_maker.execution.engine import TaskState, TaskStatus
from decision_maker.topics import CANCEL_QOS, COMMAND_QOS
from home_robot_bringup.domain import DomainLease
from home_robot_bringup.launcher import apply_overrides
from home_robot_bringup.nodeset import load_nodeset
from home_robot_bringup.process import Supervisor, node_environment

STATUS_QOS = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)


ENDED = (GoalStatus.STATUS_CANCELED, GoalStatus.STATUS_ABORTED, GoalStatus.STATUS_SUCCEEDED)


def pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(round(q / 100.0 * (len(s) - 1))))]


def summary(name: str, ms: list[float]) -> str:
    return (f"{name}: n={len(ms)} median {statistics.median(ms):.2f} ms, p90 {pct(ms, 90):.2f} ms, "
            f"p99 {pct(ms, 99):.2f} ms, max {max(ms):.2f} ms")


class Bench:
    def __init__(self, domain_id: int) -> None:
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node("bench_cancel", context=self.context)
        self.cond = threading.Condition()  # guards goal_status, task_final
        self.goal_status: dict[bytes, tuple[int, float]] = {}  # goal id -> (status, first time seen)
        self.task_final: dict[int, tuple[TaskState, float]] = {}
        self.cmd = self.node.create_publisher(String, "manual_command", COMMAND_QOS)
        self.cancel = self.node.create_publisher(String, "cancel_command", CANCEL_QOS)
        self.node.create_subscription(GoalStatusArray, "navigate_to_pose/_action/status", self._on_goal_status,
                                      STATUS_QOS)
        self.node.create_subscription(String, "task_status", self._on_task, COMMAND_QOS)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self.executor.spin, daemon=True)
        self.thread.start()

    def _on_goal_status(self, msg: GoalStatusArray) -> None:
        now = time.monotonic()
        with self.cond:
            for st in msg.status_list:
                key = bytes(st.goal_info.goal_id.uuid)
                old = self.goal_status.get(key)
                if old is None or old[0] != st.status:
                    self.goal_status[key] = (st.status, now)
            self.cond.notify_all()

    def _on_task(self, msg: String) -> None:
        st = TaskStatus.from_json(msg.data)
        if st.state.terminal:
            with self.cond:
                self.task_final[st.id] = (st.state, time.monotonic())
                self.cond.notify_all()

    def start_far_goal(self, trial: int, known: set[bytes]) -> bytes:
        """Command a drive that no trial lasts long enough to finish; returns its goal id (added to ``known``)."""
        target = "goto:5.0,4.0,0" if trial % 2 == 0 else "goto:4.0,0.5,0"  # far: never reached in a trial
        self.cmd.publish(String(data=f"{target}; goto:1,1,0"))
        with self.cond:
            ok = self.cond.wait_for(lambda: self.active_goal(known) is not None, 10.0)
            goal = self.active_goal(known)
        if not ok or goal is None:
            raise SystemExit(f"trial {trial}: no active nav goal")
        known.add(goal)
        return goal

    def active_goal(self, known: set[bytes]) -> bytes | None:
        for key, (status, _) in self.goal_status.items():
            if key not in known and status in (GoalStatus.STATUS_ACCEPTED, GoalStatus.STATUS_EXECUTING):
                return key
        return None

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        self.node.destroy_node()
        self.context.try_shutdown()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--stop-via", choices=("cancel_command", "manual_command", "both"), default="cancel_command",
                    help="how the stop is sent: /cancel_command, the word 'stop' on /manual_command, or alternating")
    opts = ap.parse_args()
    with DomainLease() as lease:
        specs = [s for s in load_nodeset("sim_robot") if s.name in ("mock_nav_server", "decision_maker")]
        specs = apply_overrides(specs, ["mock_nav_server.speed=0.2", "decision_maker.batch_timeout_s=3600.0"])
        sup = Supervisor(specs, node_environment(lease.domain_id), echo=None)
        sup.start()
        bench = None
        try:
            sup.wait_ready(60.0)
            bench = Bench(lease.domain_id)
            deadline = time.monotonic() + 20
            while (bench.cmd.get_subscription_count() == 0 or bench.cancel.get_subscription_count() < 2) \
                    and time.monotonic() < deadline:
                time.sleep(0.05)
            time.sleep(0.5)
            to_cancelled: dict[str, list[float]] = {"cancel_command": [], "manual_command": []}
            to_task: dict[str, list[float]] = {"cancel_command": [], "manual_command": []}
            known: set[bytes] = set()
            cid = 0
            failures = 0
            for i in range(opts.trials):
                cid += 1
                goal = bench.start_far_goal(i, known)
                time.sleep(0.02)  # let the goal run for a moment
                via = opts.stop_via if opts.stop_via != "both" else ("cancel_command", "manual_command")[i % 2]
                t0 = time.monotonic()
                if via == "cancel_command":
                    bench.cancel.publish(String(data="bench"))
                else:
                    bench.cmd.publish(String(data="stop"))
                with bench.cond:
                    done = bench.cond.wait_for(
                        lambda g=goal, c=cid: bench.goal_status[g][0] in ENDED and c in bench.task_final, 10.0)
                    status, t_goal = bench.goal_status[goal]
                    state, t_task = bench.task_final.get(cid, (None, 0.0))
                if via == "manual_command":
                    cid += 1  # the spoken stop has an id of its own
                if not done or status != GoalStatus.STATUS_CANCELED or state is not TaskState.CANCELLED:
                    failures += 1
                    print(f"trial {i}: done={done} goal status={status} task state={state}")
                    continue
                to_cancelled[via].append((t_goal - t0) * 1000)
                to_task[via].append((t_task - t0) * 1000)
            sup_out = sup.get("decision_maker").output()
        finally:
            if bench is not None:
                bench.close()
            sup.stop()
    first_goal = [float(m) for m in re.findall(r"received -> first goal sent \(navigation\): ([0-9.]+) ms", sup_out)]
    print(f"decision maker cancel benchmark ({opts.trials} trials, mock nav server + decision_maker processes, "
          f"loopback; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs)")
    names = {"cancel_command": "/cancel_command", "manual_command": "'stop' on /manual_command"}
    for via in ("cancel_command", "manual_command"):
        if to_cancelled[via]:
            print(summary(f"{names[via]} published -> nav goal CANCELED (server status)", to_cancelled[via]))
            print(summary(f"{names[via]} published -> /task_status cancelled", to_task[via]))
    if to_cancelled["cancel_command"] and to_cancelled["manual_command"]:
        ratio = statistics.median(to_cancelled["manual_command"]) / statistics.median(to_cancelled["cancel_command"])
        print(f"spoken stop / /cancel_command, median to CANCELED: {ratio:.2f}x")
    if first_goal:
        print(summary("command received -> first goal sent (decision maker's clock)", first_goal))
    print(f"failed trials (goal not CANCELED / status not cancelled): {failures}")
    p99 = pct(to_cancelled["cancel_command"] or to_cancelled["manual_command"], 99)
    print(f"target p99 < 30 ms: {'met' if p99 < 30.0 else 'NOT met'} ({p99:.2f} ms)")
    return 0 if failures == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
