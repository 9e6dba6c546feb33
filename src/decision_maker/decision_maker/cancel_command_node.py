"""Safety input: every Enter → ``/cancel_command`` at once (the brain clears its queue, the robot stops).

Usage::

    ros_run decision_maker cancel_command_node          # press Enter to stop the robot; Ctrl-D ends
    ros_run decision_maker cancel_command_node --once   # send one cancel now and exit (scripts)

Text typed before Enter is sent as the reason. End of input (Ctrl-D, a closed pipe, /dev/null)
ends the node cleanly after delivering what was sent.
"""

from __future__ import annotations

import argparse
import sys

import rclpy
from rclpy.duration import Duration
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args
from std_msgs.msg import String

from decision_maker.client.console import stdin_lines, wait_for_listeners
from decision_maker.topics import CANCEL_QOS


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv if argv is None else argv
    ap = argparse.ArgumentParser(prog="cancel_command_node", description="Enter = stop the robot.")
    ap.add_argument("--once", action="store_true", help="send one cancel and exit")
    ap.add_argument("--brain", default="decision_maker",
                    help="node name of the decision maker: the first cancel waits until it is connected")
    ap.add_argument("--discovery-timeout", type=float, default=5.0,
                    help="seconds to wait for a listener before sending (a first cancel must not be lost)")
    opts = ap.parse_args(remove_ros_args(argv)[1:])
    # Python's own SIGINT handling: Ctrl-C must interrupt the blocking stdin read (KeyboardInterrupt)
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("cancel_command_node")
    pub = node.create_publisher(String, "cancel_command", CANCEL_QOS)

    settled = False

    def send(reason: str) -> None:
        nonlocal settled
        if not settled:  # first send: wait for listeners, and for discovery to settle (brain, nav, arm...)
            wait_for_listeners(pub, opts.discovery_timeout, node=node, required_node=opts.brain)
            settled = True
        pub.publish(String(data=f"operator: {reason}"))
        print(f"cancel sent ({reason}) to {pub.get_subscription_count()} listener(s)", flush=True)

    code = 0
    try:
        if opts.once:
            send("cancel_command_node --once")
        else:
            if sys.stdin.isatty():
                print("Press Enter to STOP the robot (Ctrl-D to quit).", flush=True)
            for line in stdin_lines():
                send(line.strip() or "Enter")
        pub.wait_for_all_acked(Duration(seconds=2.0))
    except KeyboardInterrupt:
        code = 130
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    raise SystemExit(main())
