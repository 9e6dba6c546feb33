"""Integration: the seed's usage section (§8) exactly as written — plain executables, no parameters.

Terminals of the seed: ``object_query_server``, ``decision_maker_node``, the simulated hardware
(``mock_nav_server``, ``mock_grasp_server``), ``nl_command_node`` and ``cancel_command_node``,
each started with no arguments at all (the code defaults only; no params file, no remapping) on
the test's leased ROS_DOMAIN_ID. "give me the bottle", "clean table" and "give me the cup" must
succeed at the default (real-time) speeds.
"""

from __future__ import annotations

import subprocess
import tempfile
import time
from pathlib import Path

import pytest

from home_robot_bringup.nodeset import find_executable
from home_robot_bringup.process import node_environment

pytestmark = [pytest.mark.ros, pytest.mark.slow]

SERVERS = [("object_query", "object_query_server"), ("decision_maker", "mock_nav_server"),
           ("decision_maker", "mock_grasp_server"), ("decision_maker", "decision_maker_node")]


def test_seed_terminals_with_defaults_only(ros_domain):
    env = node_environment(ros_domain)
    procs: list[tuple[str, subprocess.Popen, Path]] = []
    stop = None
    with tempfile.TemporaryDirectory() as tmp:
        try:
            for pkg, exe in SERVERS:  # one "terminal" each: the plain executable, nothing else
                log = Path(tmp) / f"{exe}.log"
                with log.open("wb") as out:
                    procs.append((exe, subprocess.Popen([find_executable(pkg, exe)], env=env, stdin=subprocess.DEVNULL,
                                                        stdout=out, stderr=subprocess.STDOUT), log))
            # the safety terminal: running, nothing typed into it (started beside the servers: it starts meanwhile)
            stop = subprocess.Popen([find_executable("decision_maker", "cancel_command_node")], env=env,
                                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            deadline = time.monotonic() + 120.0
            for exe, proc, log in procs:
                while "ready:" not in log.read_text(errors="replace"):
                    assert proc.poll() is None, f"{exe} exited ({proc.returncode}):\n{log.read_text()}"
                    assert time.monotonic() < deadline, f"{exe} not ready:\n{log.read_text()}"
                    time.sleep(0.1)
            typed = "give me the bottle\nclean table\ngive me the cup\n"
            result = subprocess.run([find_executable("decision_maker", "nl_command_node")], input=typed, env=env,
                                    capture_output=True, text=True, timeout=240)
            stop_out, _ = stop.communicate("", timeout=30)  # end of input: it exits cleanly, having sent nothing
            logs = "\n".join(f"--- {exe}\n{log.read_text(errors='replace')}" for exe, _, log in procs)
            assert result.returncode == 0, result.stdout + result.stderr + logs
            for n in (1, 2, 3):
                assert f"[#{n} succeeded 3/3]" in result.stdout, result.stdout + logs
            assert stop.returncode == 0 and "cancel sent" not in stop_out, stop_out
            for exe, proc, log in procs:
                assert proc.poll() is None, f"{exe} died:\n{log.read_text()}"
        finally:
            if stop is not None and stop.poll() is None:  # a check failed before its end of input
                stop.kill()
                stop.communicate(timeout=5)
            for _, proc, _ in procs:
                proc.terminate()
            for _, proc, _ in procs:
                try:
                    proc.wait(10)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(5)
