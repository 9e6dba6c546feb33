"""``demo``: the main job, end to end on the bundled data (``make demo``).

Brings up the whole simulated robot and its web page (node set ``demo``: the object database on the
bundled sample map, the simulated base and arm, the decision maker, ``web_ui_node`` on
http://127.0.0.1:8090/) on a freshly leased ROS_DOMAIN_ID with loopback-only discovery, then says
to it, as a person would:

    "give me the bottle", "go home", "clean table", "where is the bottle",
    "could you bring me the bottle"

prints every ``/task_status`` update as it arrives and finally the simulated world: the bottle is
with the user, the trash in the bin. The last two show the living object memory: the answer comes
from what the robot did, and the second request for the bottle — which a static map would send to
the kitchen counter, where it would fail — is answered "already with you" without moving. Exit
code 0 when all commands succeeded and the world is as expected.

Options::

    demo                         # the three commands above
    demo --command "give me the cup" --command "go home"   # your own commands
    demo --interactive           # type commands; 'stop' cancels, 'world' shows the world, Ctrl-D quits
    demo --verbose               # also show the nodes' own log lines
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import threading
import time

from home_robot_bringup.background import BackgroundNode
from home_robot_bringup.domain import DomainLease
from home_robot_bringup.errors import BringupError
from home_robot_bringup.launcher import apply_overrides
from home_robot_bringup.nodeset import load_nodeset
from home_robot_bringup.process import Supervisor, node_environment

DEFAULT_COMMANDS = ("give me the bottle", "go home", "clean table", "where is the bottle",
                    "could you bring me the bottle")


class Operator:
    """The demo's own ROS node: sends commands/cancels, receives statuses and the world state."""

    def __init__(self, domain_id: int, echo=sys.stdout) -> None:
        from std_msgs.msg import String

        from decision_maker.topics import CANCEL_QOS, COMMAND_QOS, OBJECT_LIST_QOS, STATUS_QOS

        self._String = String
        self._echo = echo
        self._t0 = time.monotonic()
        self._cond = threading.Condition()  # guards finals, world
        self.finals: dict[str, object] = {}
        self.world: dict | None = None
        self._ros = BackgroundNode(domain_id, "demo_operator", threads=1)
        node = self._ros.node
        self._cmd = node.create_publisher(String, "manual_command", COMMAND_QOS)
        self._cancel = node.create_publisher(String, "cancel_command", CANCEL_QOS)
        node.create_subscription(String, "task_status", self._on_status, STATUS_QOS)
        node.create_subscription(String, "sim/world_state", self._on_world, OBJECT_LIST_QOS)

    def _on_status(self, msg) -> None:
        from decision_maker.execution.engine import TaskStatus

        try:
            st = TaskStatus.from_json(msg.data)
        except ValueError:
            return
        self._echo.write(f"demo: {time.monotonic() - self._t0:6.1f} s  {st.line()}"
                         + (f"  ({st.message})" if st.state.terminal and st.state.value != "succeeded" else "")
                         + "\n")
        self._echo.flush()
        if st.state.terminal:
            with self._cond:
                self.finals[st.text] = st
                self._cond.notify_all()

    def _on_world(self, msg) -> None:
        try:
            world = json.loads(msg.data)
        except (ValueError, RecursionError):
            return  # not the simulated world's state: the last good one stays
        if not isinstance(world, dict):
            return
        with self._cond:
            self.world = world
            self._cond.notify_all()

    def wait_connected(self, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._cond:
                have_world = self.world is not None and self.world.get("robot") is not None
            if have_world and self._cmd.get_subscription_count() > 0 and self._cancel.get_subscription_count() > 0:
                return True
            time.sleep(0.05)
        return False

    def send(self, text: str) -> None:
        self._cmd.publish(self._String(data=text))

    def cancel(self) -> None:
        self._cancel.publish(self._String(data="demo operator"))

    def wait_finals(self, texts: list[str], timeout: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: all(t in self.finals for t in texts), timeout)

    def snapshot(self) -> dict | None:
        with self._cond:
            return None if self.world is None else json.loads(json.dumps(self.world))

    def close(self) -> None:
        self._ros.close()


def _free_web_port(overrides: list[str], port: int = 8090) -> list[str]:
    """The overrides, plus ``web_ui.port=0`` (any free port) when ``port`` is taken (another demo runs)."""
    import socket

    if any(o.startswith("web_ui.port=") for o in overrides):
        return overrides
    with socket.socket() as sock:
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            print(f"demo: port {port} is taken; the web page gets a free port", flush=True)
            return [*overrides, "web_ui.port=0"]
    return overrides


def _is_question(text: str) -> bool:
    return text.lower().lstrip().startswith(("where", "what", "which", "who", "how", "do you", "have you"))


def describe_world(world: dict, locations: dict) -> list[str]:
    """Readable lines: robot pose, gripper, each object and the named place it is at (if any)."""
    r = world.get("robot") or {}
    lines = [f"robot at ({r.get('x', float('nan')):.2f}, {r.get('y', float('nan')):.2f}) "
             f"heading {math.degrees(r.get('theta', 0.0)):.0f} deg, gripper: {world.get('held') or 'empty'}"]
    where_names = {"user": "with the user", "bin": "in the bin"}
    for oid, body in sorted(world.get("objects", {}).items()):
        pos = body["position"]
        at = ""
        for loc in locations.values():
            p = loc.drop_point()
            if math.dist(pos, (p.x, p.y, p.z)) < 0.15:
                at = where_names.get(loc.name, f"at the {loc.name}")
        if world.get("held") == oid:
            at = "in the gripper"
        lines.append(f"  {oid:8s} ({pos[0]:.2f}, {pos[1]:.2f}, {pos[2]:.2f})  {at}")
    return lines


def _interactive(op: Operator, locations: dict, timeout: float) -> int:
    print("demo: type a command (e.g. 'give me the cup', 'go to the table', 'goto:2,1,0'); "
          "'stop' cancels, 'world' shows the world, Ctrl-D quits.", flush=True)
    from decision_maker.command_types import sanitize_text, shorten

    sent: list[str] = []
    while True:
        try:
            line = input("> " if sys.stdin.isatty() else "")
        except EOFError:
            # end of input (a pipe): let what was sent finish, then show the world
            op.wait_finals(sent, timeout)
            time.sleep(0.6)  # the world state of the last step (published on change, and at 2 Hz)
            world = op.snapshot()
            print("demo: the world now:\n" + "\n".join(describe_world(world, locations)), flush=True)
            return 0
        cmd = line.strip()
        if not cmd:
            continue
        if cmd.lower() in ("stop", "cancel"):
            op.cancel()
        elif cmd.lower() == "world":
            world = op.snapshot()
            print("\n".join(describe_world(world, locations)) if world else "no world state yet", flush=True)
        elif cmd.lower() in ("quit", "exit"):
            return 0
        else:
            sent.append(shorten(sanitize_text(line), 200))
            op.send(line)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="demo", description=__doc__.split("\n")[0])
    ap.add_argument("--command", action="append", default=[], help="a command to give (repeatable)")
    ap.add_argument("--interactive", action="store_true", help="type commands yourself")
    ap.add_argument("--verbose", action="store_true", help="show the nodes' log lines too")
    ap.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                    help="override a parameter, e.g. mock_nav_server.speed=2.0")
    ap.add_argument("--ready-timeout", type=float, default=60.0)
    ap.add_argument("--timeout", type=float, default=120.0, help="seconds to wait for the commands to finish")
    opts = ap.parse_args(argv)

    from decision_maker.command_types import load_locations
    from decision_maker.decision_maker_node import default_locations_file

    locations = load_locations(default_locations_file())
    commands = opts.command or ([] if opts.interactive else list(DEFAULT_COMMANDS))
    with DomainLease() as lease:
        env = node_environment(lease.domain_id)
        print(f"demo: ROS_DOMAIN_ID={lease.domain_id}, discovery LOCALHOST; starting the simulated robot "
              "(object database, simulated base and arm, decision maker, web page)...", flush=True)
        t0 = time.monotonic()
        sup = None
        try:
            specs = apply_overrides(load_nodeset("demo"), _free_web_port(opts.set))
            sup = Supervisor(specs, env, echo=sys.stdout if opts.verbose else None)
            sup.start()
            sup.wait_ready(opts.ready_timeout)
        except BringupError as exc:
            print(f"demo: error: {exc}", file=sys.stderr)
            if sup is not None:
                sup.stop()
            return 1
        from decision_maker.command_types import sanitize_text, shorten

        # statuses carry the command as the decision maker sanitised it: match on that
        keys = [shorten(sanitize_text(t), 200) for t in commands]
        op = None
        try:
            op = Operator(lease.domain_id)
            if not op.wait_connected(30.0):
                print("demo: error: the decision maker did not connect", file=sys.stderr)
                for proc in sup.processes:
                    print(f"--- {proc.name}:\n{proc.output()[-2000:]}", file=sys.stderr)
                return 1
            print(f"demo: {len(specs)} nodes ready in {time.monotonic() - t0:.1f} s", flush=True)
            web = re.search(r"ready: web UI at (\S+)", sup.get("web_ui").output())
            if web:
                print(f"demo: open {web.group(1)} in a browser to watch and command the robot", flush=True)
            print("demo: the world now:\n" + "\n".join(describe_world(op.snapshot(), locations)), flush=True)
            sent: list[str] = []
            for text, key in zip(commands, keys, strict=True):
                if _is_question(text) and sent:
                    # a question is answered at once, even while the robot is busy: ask it once the
                    # earlier commands are done, as a person watching the robot would
                    op.wait_finals(sent, opts.timeout)
                print(f"demo: you say: {text!r}", flush=True)
                op.send(text)
                sent.append(key)
            ok = True
            if commands:
                if not op.wait_finals(keys, opts.timeout):
                    print(f"demo: not all commands finished within {opts.timeout:g} s", file=sys.stderr)
                    ok = False
                ok = ok and all(getattr(op.finals.get(t), "state", None) is not None
                                and op.finals[t].state.value == "succeeded" for t in keys)
                time.sleep(0.6)  # the world state of the last step (published on change, and at 2 Hz)
                world = op.snapshot()
                print("demo: the world now:\n" + "\n".join(describe_world(world, locations)), flush=True)
                if not opts.command:  # the default story: check its outcome
                    user, bin_ = locations["user"].drop_point(), locations["bin"].drop_point()
                    bottle = world["objects"]["bottle"]["position"]
                    trash = world["objects"]["trash"]["position"]
                    ok = ok and math.dist(bottle, (user.x, user.y, user.z)) < 0.15 \
                        and math.dist(trash, (bin_.x, bin_.y, bin_.z)) < 0.15
                    # the memory: the second request was answered, not driven to the kitchen
                    again = op.finals.get(keys[-1])
                    ok = ok and again is not None and "already with you" in again.sentence
                    where = op.finals.get(keys[-2])
                    ok = ok and where is not None and "with you" in where.sentence
            if opts.interactive:
                _interactive(op, locations, opts.timeout)
        finally:
            if op is not None:
                op.close()
            sup.stop()
        if commands:
            print("demo: " + ("OK - the bottle is with the user, the table is clean, and asked again the robot "
                              "knew the bottle was already with the user"
                              if ok and not opts.command else "OK" if ok else "FAILED"), flush=True)
        return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
