"""The engine's handling of LLM plans (no ROS): confirmation step, held object in the context."""

from __future__ import annotations

import threading

from decision_maker.command_types import Plan, Point3, load_locations, parse_plan
from decision_maker.execution.engine import AbortToken, EngineConfig, ExecutionEngine, TaskState
from decision_maker.nl_planner import PlanningContext

from .test_llm_planner import LOCATIONS_FILE, OBJECTS

LOCATIONS = load_locations(LOCATIONS_FILE)
CTX = PlanningContext(frozenset(OBJECTS), LOCATIONS, OBJECTS)


class ScriptPlanner:
    """Returns a fixed plan marked as an LLM plan and records the contexts it was given."""

    name = "script"

    def __init__(self, items: list[str], scenario: str = "llm") -> None:
        self.plan_ = parse_plan(items, LOCATIONS, scenario=scenario)
        self.contexts: list[PlanningContext] = []

    def plan(self, text: str, context: PlanningContext) -> Plan:
        self.contexts.append(context)
        return Plan(self.plan_.primitives, self.plan_.scenario, {"message": "Bringing you the bottle."})


class Robot:
    def __init__(self) -> None:
        self.calls: list[str] = []

    def navigate(self, pose, timeout_s, abort):
        self.calls.append("nav")

    def locate(self, name, timeout_s, abort):
        self.calls.append("locate")
        return Point3(5.2, 0.3, 1.0)

    def grasp(self, name, target, timeout_s, abort):
        self.calls.append(f"grasp:{name}")

    def place(self, location, target, timeout_s, abort):
        self.calls.append(f"place:{location.name}")

    def cancel_active(self):
        pass

    def emergency_stop(self, reason):
        pass


def engine(planner, **cfg):
    statuses = []
    eng = ExecutionEngine(planner, Robot(), EngineConfig(**cfg), statuses.append, lambda: CTX)
    return eng, statuses


def run_in_thread(eng, text):
    box = []
    t = threading.Thread(target=lambda: box.append(eng.run_command(1, text, AbortToken())), daemon=True)
    t.start()
    return t, box


def wait_asking(statuses, timeout=5.0):
    import time

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if any("awaiting confirmation" in s.message for s in statuses):
            return True
        time.sleep(0.01)
    return False


def test_llm_plan_runs_after_yes():
    eng, st = engine(ScriptPlanner(["goto:kitchen", "grasp:bottle", "place:user"]), confirm_llm_plans=True)
    t, box = run_in_thread(eng, "I'm thirsty")
    assert wait_asking(st)
    assert eng._robot.calls == []  # nothing moves before the answer
    assert eng.submit("Yes!").state is TaskState.SUCCEEDED  # consumed as the answer, not queued
    t.join(5)
    assert box == [TaskState.SUCCEEDED] and eng.queue_length() == 0
    assert eng._robot.calls == ["nav", "locate", "grasp:bottle", "nav", "place:user"]
    assert any("My plan: goto:kitchen, grasp:bottle, place:user" in s.sentence for s in st)


def test_llm_plan_dropped_on_no_timeout_and_cancel():
    eng, st = engine(ScriptPlanner(["goto:kitchen"]), confirm_llm_plans=True, confirm_timeout_s=0.2)
    assert eng.run_command(1, "go somewhere nice", AbortToken()) is TaskState.CANCELLED  # no answer: timeout
    assert eng._robot.calls == []
    t, box = run_in_thread(eng, "go somewhere nice")
    assert wait_asking(st)
    eng.submit("no")
    t.join(5)
    assert box == [TaskState.CANCELLED] and eng._robot.calls == []
    eng2, st2 = engine(ScriptPlanner(["goto:kitchen"]), confirm_llm_plans=True, confirm_timeout_s=30)
    token = AbortToken()
    t = threading.Thread(target=lambda: box.append(eng2.run_command(1, "x", token)), daemon=True)
    t.start()
    assert wait_asking(st2)
    token.abort("operator")  # /cancel_command while waiting for the answer
    t.join(5)
    assert not t.is_alive() and box[-1] is TaskState.CANCELLED


def test_registry_plans_and_unconfirmed_mode_run_at_once():
    eng, _ = engine(ScriptPlanner(["goto:kitchen"], scenario="go to"), confirm_llm_plans=True)
    assert eng.run_command(1, "go to the kitchen", AbortToken()) is TaskState.SUCCEEDED
    eng, _ = engine(ScriptPlanner(["goto:kitchen"]))
    assert eng.run_command(1, "somewhere", AbortToken()) is TaskState.SUCCEEDED
    assert eng.submit("yes").state is TaskState.QUEUED  # no plan waits: "yes" is an ordinary command


def test_held_object_reaches_the_planner():
    planner = ScriptPlanner(["goto:kitchen", "grasp:bottle"])
    eng, _ = engine(planner)
    eng.run_command(1, "pick up the bottle", AbortToken())
    eng.run_command(2, "and now?", AbortToken())
    assert [c.held_object for c in planner.contexts] == [None, "bottle"]
