"""The `launch` command on a real node set: readiness, Ctrl-C, a dying node, a node that cannot start."""

import os
import re
import signal

import pytest

from home_robot_bringup.background import CapturedProcess
from home_robot_bringup.nodeset import find_executable
from home_robot_bringup.process import node_environment
from home_robot_bringup.testing import wait_for

pytestmark = pytest.mark.ros


class LauncherRun(CapturedProcess):
    def __init__(self, domain: int, *args: str) -> None:
        exe = find_executable("home_robot_bringup", "launch")
        super().__init__([exe, *args, "--domain-id", str(domain), "--no-color"], node_environment(domain))

    def finish(self, timeout: float = 30) -> int:
        return self.wait(timeout)


def child_pid(run: LauncherRun, name: str) -> int:
    m = re.search(rf"started {name} \(pid (\d+)\)", run.text())
    assert m, run.text()
    return int(m.group(1))


def test_ctrl_c_stops_all_nodes_cleanly(ros_domain):
    run = LauncherRun(ros_domain, "object_query")
    assert wait_for(lambda: "all 1 nodes ready" in run.text(), 60), run.text()
    pid = child_pid(run, "object_query_server")
    assert "[object_query_server] [INFO]" in run.text()  # node output, prefixed with its name
    run.proc.send_signal(signal.SIGINT)
    assert run.finish() == 0, run.text()
    assert "all nodes stopped" in run.text()
    assert not os.path.exists(f"/proc/{pid}") or open(f"/proc/{pid}/stat").read().split()[2] == "Z"


def test_a_dying_node_stops_the_launcher(ros_domain):
    run = LauncherRun(ros_domain, "object_query")
    assert wait_for(lambda: "all 1 nodes ready" in run.text(), 60), run.text()
    os.kill(child_pid(run, "object_query_server"), signal.SIGKILL)
    assert run.finish() == 128 + signal.SIGKILL, run.text()
    assert "stopped because a node exited" in run.text()


def test_node_that_cannot_start_is_reported(ros_domain, tmp_path):
    run = LauncherRun(ros_domain, "object_query", "--set", f"object_query_server.map_path={tmp_path}/missing.npz")
    assert run.finish(60) == 1, run.text()
    assert "exited with code 2 while starting" in run.text() and "missing.npz" in run.text()


def test_unknown_node_set_and_list(ros_domain):
    run = LauncherRun(ros_domain, "no_such_set")
    assert run.finish() == 2 and "unknown node set 'no_such_set'" in run.text()
    run = LauncherRun(ros_domain, "--list")
    assert run.finish() == 0 and "object_query" in run.text()
