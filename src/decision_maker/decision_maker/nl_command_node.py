"""Text input: each line typed (or piped) → ``/manual_command``; ``/task_status`` printed readably.

Usage::

    ros_run decision_maker nl_command_node                       # interactive: type, Enter; Ctrl-D ends
    printf 'give me the bottle\\ngo home\\n' | ros_run decision_maker nl_command_node   # scripting

Each command goes through the decision maker's ``submit_command`` service when it serves it
(acknowledged: the id, or the rejection reason at once), else on ``/manual_command`` with a
warning. The terminal stays live: statuses print while you type (the node is spun in its own thread; the
main thread only reads stdin). On end of input the node waits until every command it sent has a
final status (``--no-wait`` to skip, ``--timeout`` to bound it) and exits 0 when all succeeded,
1 otherwise; Ctrl-C exits at once (130).
"""

from __future__ import annotations

import argparse
import collections
import sys
import threading
import time

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args
from std_msgs.msg import String

from decision_maker.client.command_client import Ack, CommandClient
from decision_maker.client.console import stdin_lines, wait_for_listeners
from decision_maker.command_types import sanitize_text, shorten
from decision_maker.execution.engine import TaskState, TaskStatus
from decision_maker.topics import STATUS_QOS


class CommandSender:
    """Sends commands (acknowledged through ``submit_command`` when the brain serves it, else on
    ``/manual_command``) and tracks their statuses until each is final (thread-safe).

    A command the service answered is tracked by its id; one sent on the topic by its text.
    """

    def __init__(self, node, echo=sys.stdout, answer_timeout_s: float = 10.0) -> None:
        self._node = node
        self._echo = echo
        self.client = CommandClient(node, answer_timeout_s=answer_timeout_s,
                                    log=lambda text: print(f"warning: {text}", file=sys.stderr, flush=True))
        self._pub = self.client._pub
        node.create_subscription(String, "task_status", self._on_status, STATUS_QOS)
        self._cond = threading.Condition()  # guards _pending, _pending_ids, _final_ids, failures
        self._pending: collections.Counter[str] = collections.Counter()
        self._pending_ids: set[int] = set()
        self._final_ids: dict[int, TaskState] = {}  # final states seen on /task_status (any sender)
        self.failures = 0

    def wait_for_brain(self, timeout_s: float, brain: str = "") -> str:
        """Wait for the brain: its service ("service"), else its /manual_command subscription ("topic"),
        else "" (nobody); the whole wait is bounded by ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        if self.client.wait_for_service(timeout_s):
            return "service"
        left = max(0.5, deadline - time.monotonic())
        return "topic" if wait_for_listeners(self._pub, left, node=self._node, required_node=brain) > 0 else ""

    def send(self, line: str) -> Ack:
        """Send one command; returns the brain's answer (or the topic's "sent")."""
        if not self.client.service_ready():
            with self._cond:
                self._pending[shorten(sanitize_text(line), 200)] += 1
        ack = self.client.submit(line)
        with self._cond:
            if ack.via != "service":
                pass  # tracked by its text (above)
            elif ack.state == "no_answer":
                self.failures += 1
                print(f"nl_command_node: no answer for {shorten(line, 60)!r}: {ack.message}", file=sys.stderr,
                      flush=True)
            else:
                state = TaskState._value2member_map_.get(ack.state, TaskState.REJECTED)
                final = state if state.terminal else self._final_ids.get(ack.id)
                if final is None:
                    self._pending_ids.add(ack.id)
                elif final is not TaskState.SUCCEEDED:
                    self.failures += 1
        return ack

    def _on_status(self, msg: String) -> None:
        try:
            st = TaskStatus.from_json(msg.data)
        except ValueError:
            return
        self._echo.write(st.line() + "\n")
        self._echo.flush()
        if st.state.terminal:
            with self._cond:
                self._final_ids[st.id] = st.state
                if st.id in self._pending_ids:
                    self._pending_ids.discard(st.id)
                elif self._pending[st.text] > 0:
                    self._pending[st.text] -= 1
                else:
                    return
                if st.state is not TaskState.SUCCEEDED:
                    self.failures += 1
                self._cond.notify_all()

    def wait_all(self, timeout_s: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: not self._pending_ids and sum(self._pending.values()) == 0, timeout_s)

    def flush(self, timeout_s: float = 2.0) -> None:
        from rclpy.duration import Duration

        self._pub.wait_for_all_acked(Duration(seconds=timeout_s))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv if argv is None else argv
    ap = argparse.ArgumentParser(prog="nl_command_node", description="Type commands for the robot.")
    ap.add_argument("--no-wait", action="store_true", help="exit at end of input without waiting for results")
    ap.add_argument("--timeout", type=float, default=300.0, help="max seconds to wait for results after EOF")
    ap.add_argument("--brain", default="decision_maker",
                    help="node name of the decision maker: the first command waits until it is connected")
    ap.add_argument("--discovery-timeout", type=float, default=10.0,
                    help="seconds to wait for the decision maker to be connected before the first send")
    opts = ap.parse_args(remove_ros_args(argv)[1:])
    # Python's own SIGINT handling: Ctrl-C must interrupt the blocking stdin read (KeyboardInterrupt)
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("nl_command_node")
    sender = CommandSender(node)
    executor = SingleThreadedExecutor()
    executor.add_node(node)

    def spin() -> None:
        try:
            executor.spin()
        except ExternalShutdownException:
            pass

    spinner = threading.Thread(target=spin, name="ros-executor", daemon=True)
    spinner.start()
    interactive = sys.stdin.isatty()
    connected = False
    code = 0
    try:
        if interactive:
            print("Type a command (e.g. 'give me the bottle'), Enter to send; Ctrl-D to quit.", flush=True)
        for line in stdin_lines():
            if not line.strip():
                continue
            if not connected:
                connected = True
                way = sender.wait_for_brain(opts.discovery_timeout, opts.brain)
                if not way:
                    print("warning: nobody listens on /manual_command (decision maker running? same "
                          "ROS_DOMAIN_ID?); sending anyway", file=sys.stderr, flush=True)
            ack = sender.send(line)
            if ack.via == "service" and not ack.accepted:
                print(f"[#{ack.id} {ack.state}] {shorten(sanitize_text(line), 60)!r}: {ack.message}", flush=True)
        sender.flush()
        if not opts.no_wait and not sender.wait_all(opts.timeout):
            print(f"nl_command_node: gave up waiting for results after {opts.timeout:g} s", file=sys.stderr)
            code = 1
        elif sender.failures:
            code = 1
    except KeyboardInterrupt:
        code = 130
    finally:
        executor.shutdown(timeout_sec=1.0)
        spinner.join(2.0)
        node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    raise SystemExit(main())
