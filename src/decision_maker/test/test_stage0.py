"""Stage 0 in the brain: the exploration gate and the execution engine holding commands (no ROS)."""

from __future__ import annotations

import json
import os
import threading

import pytest

from decision_maker.command_types import Point3, load_locations
from decision_maker.errors import ConfigError
from decision_maker.execution.engine import EngineConfig, ExecutionEngine, TaskState
from decision_maker.execution.stage0 import ExplorationGate
from decision_maker.nl_planner import PlanningContext, RegistryPlanner

LOCS = load_locations(os.path.join(os.path.dirname(__file__), "..", "config", "locations.yaml"))
CTX = PlanningContext(frozenset({"bottle", "cup"}), LOCS)


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


class Robot:
    """A RobotPort that records navigations (everything succeeds at once)."""

    def __init__(self) -> None:
        self.calls: list[str] = []
        self.ran = threading.Event()

    def navigate(self, pose, timeout_s, abort) -> None:
        self.calls.append("nav")
        self.ran.set()

    def locate(self, name, timeout_s, abort) -> Point3:
        return Point3(1.0, 1.0, 1.0)

    def grasp(self, name, target, timeout_s, abort) -> None:
        self.calls.append("grasp")

    def place(self, location, target, timeout_s, abort) -> None:
        self.calls.append("place")

    def cancel_active(self) -> None:
        pass

    def emergency_stop(self, reason) -> None:
        pass


def progress(state: str, seen: float = 62.0, reason: str = "") -> str:
    return json.dumps({"state": state, "seen_percent": seen, "reason": reason})


def test_gate_holds_until_done_and_says_how_much_is_seen() -> None:
    gate = ExplorationGate("queue", 100.0, Clock())
    h = gate.hold()
    assert h is not None and h.reason == "still exploring" and not h.reject
    assert gate.on_progress(progress("travelling", 61.6)) is False
    h = gate.hold()
    assert h is not None and h.sentence == "Still exploring (62 % of the home seen)"
    assert gate.on_progress(progress("mapping", 96.0)) is False  # explored; SLAM finishing its map
    h = gate.hold()
    assert h is not None and h.sentence == "Still finishing the map (96 % of the home seen)"
    assert gate.on_progress(progress("done", 97.0, "no reachable frontier left")) is True
    assert gate.hold() is None and gate.done_reason == "no reachable frontier left"
    assert gate.on_progress(progress("done")) is False  # only the first done ends it


def test_gate_modes_deadline_and_bad_input() -> None:
    assert ExplorationGate("off").hold() is None
    h = ExplorationGate("reject").hold()
    assert h is not None and h.reject
    clock = Clock()
    gate = ExplorationGate("queue", 5.0, clock)
    assert gate.timed_out() is False
    clock.t = 5.0
    assert gate.hold() is None and gate.timed_out() is True and gate.timed_out() is False
    for bad in ("", "[]", "{\"seen_percent\": 3}", "not json", json.dumps({"state": "x", "seen_percent": "a lot"})):
        with pytest.raises(ValueError):
            ExplorationGate("queue").on_progress(bad)
    with pytest.raises(ConfigError):
        ExplorationGate("sometimes")
    with pytest.raises(ConfigError):
        ExplorationGate("queue", 0.0)


def run_engine(gate: ExplorationGate) -> tuple[ExecutionEngine, Robot, list, threading.Thread]:
    statuses: list = []
    robot = Robot()
    eng = ExecutionEngine(RegistryPlanner(), robot, EngineConfig(), statuses.append, lambda: CTX)
    eng.set_gate(gate.hold)
    worker = threading.Thread(target=eng.run, daemon=True)
    worker.start()
    return eng, robot, statuses, worker


def test_engine_queues_while_exploring_and_runs_after() -> None:
    gate = ExplorationGate("queue", 600.0)
    gate.on_progress(progress("looking", 62.0))
    eng, robot, statuses, worker = run_engine(gate)
    try:
        st = eng.submit("go to the kitchen")
        assert st.state is TaskState.QUEUED
        assert st.sentence == "Still exploring (62 % of the home seen); I will do it after."
        assert not robot.ran.wait(0.5) and eng.queue_length() == 1  # held
        gate.on_progress(progress("done"))
        eng.gate_changed()
        assert robot.ran.wait(30.0)
        assert robot.calls[:1] == ["nav"]
    finally:
        eng.stop()
        worker.join(10.0)


def test_engine_rejects_while_exploring_in_reject_mode_and_stop_clears_the_queue() -> None:
    gate = ExplorationGate("reject", 600.0)
    eng, robot, statuses, worker = run_engine(gate)
    try:
        st = eng.submit("go to the kitchen")
        assert st.state is TaskState.REJECTED and "still exploring" in st.message
        assert eng.queue_length() == 0 and robot.calls == []
    finally:
        eng.stop()
        worker.join(10.0)
    gate = ExplorationGate("queue", 600.0)
    eng, robot, statuses, worker = run_engine(gate)
    try:
        assert eng.submit("go to the kitchen").state is TaskState.QUEUED
        stop = eng.submit("stop")
        assert stop.state is TaskState.SUCCEEDED and eng.queue_length() == 0
        gate.on_progress(progress("done"))
        eng.gate_changed()
        assert not robot.ran.wait(0.5)  # the queued command was cancelled by the stop
    finally:
        eng.stop()
        worker.join(10.0)
