"""Unit tests of the pure core: primitives, scenario library, planner, engine, sim world (no ROS)."""

import math
import os
import threading
import time

import pytest

from decision_maker.command_types import (
    FrameTransform,
    GoTo,
    Grasp,
    Place,
    Point3,
    Pose2D,
    load_locations,
    locations_from_dict,
    parse_plan,
    parse_primitive,
    sanitize_text,
)
from decision_maker.errors import (
    ActionCancelled,
    ActionFailed,
    ActionTimeout,
    ConfigError,
    InvalidPrimitive,
    MissingSlot,
    NoMatchingScenario,
    ObjectNotFound,
    SimError,
)
from decision_maker.execution.engine import AbortToken, EngineConfig, ExecutionEngine, TaskState, TaskStatus
from decision_maker.nl_planner import (
    PlanningContext,
    RegistryPlanner,
    make_planner,
    register_planner,
    split_primitives,
)
from decision_maker.scenario_library import match_scenario
from decision_maker.sim.world import BaseSim, ObjectWorld

LOCS_FILE = os.path.join(os.path.dirname(__file__), "..", "config", "locations.yaml")
LOCS = load_locations(LOCS_FILE)
OBJECTS = frozenset({"bottle", "cup", "trash", "chair", "table", "bin", "sofa", "coffee mug"})
CTX = PlanningContext(OBJECTS, LOCS)


# --- primitives ------------------------------------------------------------------------------------


def wait_until(predicate, timeout_s: float, poll_s: float = 0.01) -> bool:
    """Poll ``predicate`` until it is true or ``timeout_s`` (monotonic) has passed."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        threading.Event().wait(poll_s)
    return bool(predicate())


def test_parse_primitives_valid():
    assert parse_primitive("goto:1.5, 2, 3.14159", LOCS) == GoTo(Pose2D(1.5, 2.0, math.remainder(3.14159, 2 * math.pi)))
    assert parse_primitive(" GOTO: Kitchen ", LOCS) == GoTo(LOCS["kitchen"].pose, "kitchen")
    assert parse_primitive("grasp:Bottle", LOCS) == Grasp("bottle")
    assert parse_primitive("place:user", LOCS) == Place(LOCS["user"])


@pytest.mark.parametrize("text, reason", [
    ("goto:1,2", "3 numbers"),
    ("goto:a,b,c", "numbers"),
    ("goto:nan,1,0", "finite"),
    ("goto:1e9,0,0", "away"),
    ("goto:attic", "unknown location 'attic'"),
    ("place:moon", "unknown location 'moon'"),
    ("grasp:", "missing argument"),
    ("grasp:<script>", "bad object name"),
    ("fly:kitchen", "unknown primitive"),
    ("kitchen", "not a primitive"),
])
def test_parse_primitive_rejects_with_reason(text, reason):
    with pytest.raises(InvalidPrimitive, match=reason):
        parse_primitive(text, LOCS)


def test_parse_plan_names_the_bad_step():
    with pytest.raises(InvalidPrimitive, match="step 2"):
        parse_plan(["goto:home", "goto:attic"], LOCS)


def test_locations_file_and_errors():
    assert {"home", "kitchen", "table", "user", "bin"} <= set(LOCS)
    assert LOCS["user"].drop_point() == Point3(1.3, 3.95, 0.75)
    with pytest.raises(ConfigError, match="pose"):
        locations_from_dict({"locations": {"x": {"place": [1, 2, 3]}}})
    with pytest.raises(ConfigError, match="3 numbers"):
        locations_from_dict({"locations": {"x": {"pose": [1, 2]}}})
    with pytest.raises(ConfigError, match="not found"):
        load_locations("/nonexistent/locations.yaml")


def test_sanitize_and_frame_transform():
    assert sanitize_text("  give\x00 me\n the\tbottle\u200b ") == "give me the bottle"
    t = FrameTransform("world", 1.0, 2.0, math.pi / 2)
    p = t.pose(Pose2D(1.0, 0.0, 0.0))
    assert p.x == pytest.approx(1.0) and p.y == pytest.approx(3.0) and p.theta == pytest.approx(math.pi / 2)
    assert t.point(Point3(0, 1, 0.5)) == pytest.approx(Point3(0.0, 2.0, 0.5))


# --- scenario library and planner ------------------------------------------------------------------


def test_matching_is_case_punctuation_insensitive_and_longest_wins():
    m = match_scenario("Please, GO HOME!!", OBJECTS, LOCS)
    assert m.phrase == "go home"
    m = match_scenario("go to the kitchen", OBJECTS, LOCS)
    assert m.phrase == "go to" and m.function(m.utterance) == ["goto:kitchen"]
    registry = {"give": lambda u: ["goto:home"], "give me": lambda u: ["goto:kitchen"]}
    assert match_scenario("give me it", (), (), registry).phrase == "give me"


def test_slot_filling_against_known_objects():
    plan = RegistryPlanner().plan("Give me the cup, please.", CTX)
    assert [str(p) for p in plan.primitives] == ["goto:kitchen", "grasp:cup", "place:user"]
    assert plan.slots == {"item": "cup"} and plan.scenario == "give me"
    assert str(RegistryPlanner().plan("bring me my coffee mug", CTX).primitives[1]) == "grasp:coffee mug"
    assert str(RegistryPlanner().plan("give me two cups", CTX).primitives[1]) == "grasp:cup"
    # unknown object: the words are kept, the object query will say it does not exist
    assert str(RegistryPlanner().plan("give me the unicorn please", CTX).primitives[1]) == "grasp:unicorn"
    with pytest.raises(MissingSlot):
        RegistryPlanner().plan("give me", CTX)


def test_unknown_phrase_and_bad_location():
    with pytest.raises(NoMatchingScenario, match="try one of"):
        RegistryPlanner().plan("dance for me", CTX)
    with pytest.raises(MissingSlot, match="attic"):
        RegistryPlanner().plan("go to the attic", CTX)


def test_literal_primitives_and_planner_registry():
    assert split_primitives("goto:1,2,0; grasp:cup, place:user") == ["goto:1,2,0", "grasp:cup", "place:user"]
    plan = make_planner("registry").plan("goto:1,2,0, grasp:cup, place:user", CTX)
    assert [type(p) for p in plan.primitives] == [GoTo, Grasp, Place]
    with pytest.raises(InvalidPrimitive):
        make_planner("registry").plan("goto:1,2", CTX)
    with pytest.raises(ConfigError):
        make_planner("nope")


# --- engine -----------------------------------------------------------------------------------------


class FakeRobot:
    """RobotPort that records calls; behaviour per call kind is scripted."""

    def __init__(self, clock=None):
        self.calls = []
        self.behaviour = {}
        self.stops = []
        self.cancels = 0
        self.clock = clock
        self.gate = None  # threading.Event: navigate blocks until set or aborted

    def _do(self, kind, timeout_s, abort):
        self.calls.append((kind, round(timeout_s, 3)))
        if self.gate is not None and kind == "nav":
            waker = threading.Event()
            remove = abort.add_waker(waker)
            waker.wait(5.0)
            remove()
            if abort.is_set():
                raise ActionCancelled(abort.reason)
        b = self.behaviour.get(kind)
        if callable(b):
            b()
        elif b is not None:
            raise b

    def navigate(self, pose, timeout_s, abort):
        self._do("nav", timeout_s, abort)

    def locate(self, name, timeout_s, abort):
        self._do("locate", timeout_s, abort)
        return Point3(1, 2, 3)

    def grasp(self, name, target, timeout_s, abort):
        self._do("grasp", timeout_s, abort)

    def place(self, location, target, timeout_s, abort):
        self._do("place", timeout_s, abort)

    def cancel_active(self):
        self.cancels += 1

    def emergency_stop(self, reason):
        self.stops.append(reason)


def make_engine(robot, clock=None, **cfg):
    statuses = []
    eng = ExecutionEngine(RegistryPlanner(), robot, EngineConfig(**cfg), statuses.append, lambda: CTX,
                          **({"clock": clock} if clock else {}))
    return eng, statuses


def final(statuses, cid):
    states = [s for s in statuses if s.id == cid and s.state.terminal]
    assert len(states) == 1, states
    return states[0]


def test_engine_happy_path_with_place_approach():
    robot = FakeRobot()
    eng, st = make_engine(robot)
    assert eng.submit("give me the bottle").state is TaskState.QUEUED
    assert eng.run_command(1, "give me the bottle", AbortToken()) is TaskState.SUCCEEDED
    # goto kitchen, locate+grasp, approach user, place
    assert [c[0] for c in robot.calls] == ["nav", "locate", "grasp", "nav", "place"]
    steps = [(s.step, s.steps, s.primitive) for s in st if s.state is TaskState.RUNNING and s.steps]
    assert steps == [(1, 3, "goto:kitchen"), (2, 3, "grasp:bottle"), (3, 3, "place:user")]
    assert all(s.sentence for s in st)


def test_engine_failure_and_unknown_object():
    robot = FakeRobot()
    robot.behaviour["locate"] = ObjectNotFound("unknown object 'unicorn'")
    eng, st = make_engine(robot)
    assert eng.run_command(1, "give me the unicorn", AbortToken()) is TaskState.FAILED
    assert "unicorn" in final(st, 1).message and final(st, 1).step == 2
    robot.behaviour = {"nav": ActionFailed("goal aborted")}
    assert eng.run_command(2, "go home", AbortToken()) is TaskState.FAILED
    assert not robot.stops


def test_engine_action_timeout_publishes_cancel_command():
    robot = FakeRobot()
    robot.behaviour["nav"] = ActionTimeout("no result within 0.5 s")
    eng, st = make_engine(robot, nav_timeout_s=0.5)
    assert eng.run_command(1, "go home", AbortToken()) is TaskState.TIMED_OUT
    assert robot.stops and "goto:home" in robot.stops[0] and robot.cancels >= 1
    assert robot.calls == [("nav", 0.5)]


def test_engine_batch_watchdog_before_every_primitive_and_bounded_waits():
    now = [0.0]
    robot = FakeRobot()
    robot.behaviour["nav"] = lambda: now.__setitem__(0, now[0] + 8.0)  # each nav takes 8 s
    eng, st = make_engine(robot, clock=lambda: now[0], batch_timeout_s=10.0, nav_timeout_s=60.0)
    assert eng.run_command(1, "clean table", AbortToken()) is TaskState.TIMED_OUT
    # first nav got the whole batch budget (10 s < 60 s), the grasp's query got what was left
    assert robot.calls[0] == ("nav", 10.0)
    assert robot.calls[1] == ("locate", 2.0)
    # after the approach of place:bin the batch was over: the Place was not sent, /cancel_command was
    assert robot.stops and "batch" in final(st, 1).message
    now[0] = 0.0
    robot.calls.clear()
    robot.stops.clear()
    robot.behaviour["nav"] = lambda: now.__setitem__(0, now[0] + 11.0)
    assert eng.run_command(2, "goto:home; goto:kitchen", AbortToken()) is TaskState.TIMED_OUT
    assert "watchdog" in final(st, 2).message and final(st, 2).step == 2 and robot.stops


def test_engine_rejections_queue_limit_and_cancel():
    robot = FakeRobot()
    eng, st = make_engine(robot, max_queue=2, max_text_chars=50)
    assert eng.submit("   ").state is TaskState.REJECTED
    assert eng.submit("x" * 51).state is TaskState.REJECTED
    assert eng.submit("go home").state is TaskState.QUEUED
    assert eng.submit("clean table").state is TaskState.QUEUED
    full = eng.submit("give me the cup")
    assert full.state is TaskState.REJECTED and "queue full" in full.message
    assert eng.cancel() == 2 and eng.queue_length() == 0
    assert [s.state for s in st if s.id in (3, 4)][-2:] == [TaskState.CANCELLED, TaskState.CANCELLED]
    assert eng.run_command(9, "dance", AbortToken()) is TaskState.REJECTED
    json_roundtrip = TaskStatus.from_json(st[-1].to_json())
    assert json_roundtrip == st[-1]
    with pytest.raises(ValueError):
        TaskStatus.from_json("{}")


@pytest.mark.parametrize("doc, words", [
    ('{"id": [1], "text": "hello", "state": "failed"}', "id must be int, got list"),
    ('{"id": 1, "text": "hello", "state": "failed", "step": true}', "step must be int, got bool"),
    ('{"id": 1, "text": {"a": 1}, "state": "failed"}', "text must be str, got dict"),
    ('{"id": 1, "text": "hello", "state": "failed", "stamp": "now"}', "stamp must be a finite number"),
    ('{"id": 1, "text": "hello", "state": "gone"}', "'gone' is not a valid TaskState"),
    ("[" * 100_000, "maximum recursion depth"),
    ("[1, 2]", "list indices must be integers"),
])
def test_a_task_status_of_the_wrong_shape_is_a_value_error(doc, words):
    """/task_status readers (nl_command_node, the demo, tests) hold ids as keys: a list there once raised
    TypeError in their callback and ended the reader; every wrong shape is a ValueError that says what."""
    with pytest.raises(ValueError, match="not a task status") as err:
        TaskStatus.from_json(doc)
    assert words in str(err.value)


def test_a_task_status_takes_a_whole_number_as_its_stamp():
    st = TaskStatus.from_json('{"id": 3, "text": "go home", "state": "queued", "stamp": 1700000000}')
    assert st.stamp == 1700000000.0 and isinstance(st.stamp, float) and st.state is TaskState.QUEUED


def test_engine_worker_cancel_while_navigating():
    robot = FakeRobot()
    robot.gate = threading.Event()
    eng, st = make_engine(robot)
    worker = threading.Thread(target=eng.run)
    worker.start()
    try:
        eng.submit("give me the bottle")
        eng.submit("go home")
        # generous deadlines (a busy CI machine may not run the worker thread for seconds)
        assert wait_until(lambda: robot.calls, 30.0), "the worker never started navigating"
        assert eng.busy()
        assert eng.cancel("operator") == 2
        assert wait_until(lambda: any(s.id == 1 and s.state.terminal for s in st), 30.0)
        assert final(st, 1).state is TaskState.CANCELLED and final(st, 2).state is TaskState.CANCELLED
        assert robot.cancels == 1 and [c[0] for c in robot.calls] == ["nav"]
    finally:
        eng.stop()
        worker.join(5)
    assert not worker.is_alive()


# --- sim world --------------------------------------------------------------------------------------


def test_base_sim_drives_to_goal_and_turns():
    base = BaseSim(Pose2D(0, 0, 0), speed=1.0, turn_rate=2.0)
    base.goal = Pose2D(3, 4, math.pi / 2)
    d0 = base.distance_remaining()
    base.step(0.5)
    assert base.distance_remaining() < d0
    for _ in range(200):
        base.step(0.05)
    assert base.arrived() and base.pose.x == 3 and base.pose.y == 4
    base.stop()
    assert not base.arrived() and base.distance_remaining() == 0.0
    with pytest.raises(ConfigError):
        BaseSim(Pose2D(0, 0), speed=0)


def test_object_world_reach_gripper_and_place():
    w = ObjectWorld.from_mapping({"bottle": [5.2, 0.3, 1.0], "cup_1": [4.6, 0.35, 0.95],
                                  "cup_2": {"class": "cup", "position": [2.8, 2.6, 0.8]}}, reach=1.1)
    assert w.objects["cup_1"].cls == "cup"
    far = Pose2D(0.5, 0.5)
    with pytest.raises(SimError, match="away"):
        w.grasp(far, "bottle")
    kitchen = LOCS["kitchen"].pose
    assert w.grasp(kitchen, "cup").id == "cup_1"  # the nearer cup
    with pytest.raises(SimError, match="not empty"):
        w.grasp(kitchen, "bottle")
    with pytest.raises(SimError, match="away"):
        w.place(kitchen, LOCS["user"].drop_point())
    user = LOCS["user"]
    w.carry(user.pose)
    assert w.snapshot(user.pose)["objects"]["cup_1"]["position"][1] > 3.5
    w.place(user.pose, user.drop_point())
    assert w.held is None and w.objects["cup_1"].position == user.drop_point()
    with pytest.raises(SimError, match="empty"):
        w.place(user.pose, user.drop_point())
    with pytest.raises(SimError, match="no unicorn"):
        w.grasp(user.pose, "unicorn")


def test_named_locations_reach_their_objects():
    """The locations file fits the sample map: each scenario's grasp/place is within 1.1 m."""
    reach = 1.1
    assert LOCS["kitchen"].pose.distance_to(Point3(5.2, 0.3, 1.0)) < reach
    assert LOCS["table"].pose.distance_to(Point3(2.28, 2.48, 0.8)) < reach
    for name in ("kitchen", "table", "user", "bin"):
        assert LOCS[name].pose.distance_to(LOCS[name].drop_point()) < reach


def test_planner_seam_custom_planner_and_cancel_while_planning():
    """A planner registered by name is used by the engine unchanged; a cancel during planning wins."""
    from decision_maker.command_types import parse_plan as pp
    from decision_maker.errors import PlanningError

    class ScriptedPlanner:
        name = "scripted"

        def __init__(self, steps=("goto:home",)):
            self.steps = list(steps)
            self.seen = []

        def plan(self, text, context):
            self.seen.append((text, context.known_objects))
            if text == "slow":
                started.set()
                assert release.wait(5.0)
                if context.should_stop():
                    raise PlanningError("cancelled")
            return pp(self.steps, context.locations, scenario=self.name)

    started, release = threading.Event(), threading.Event()
    register_planner("scripted", ScriptedPlanner)
    planner = make_planner("scripted", steps=["goto:kitchen", "grasp:cup"])
    with pytest.raises(ConfigError, match="bad options"):
        make_planner("scripted", nope=1)
    robot = FakeRobot()
    statuses = []
    eng = ExecutionEngine(planner, robot, EngineConfig(), statuses.append, lambda: CTX)
    assert eng.run_command(1, "anything at all", AbortToken()) is TaskState.SUCCEEDED
    assert [c[0] for c in robot.calls] == ["nav", "locate", "grasp"] and planner.seen[0][1] == OBJECTS
    token = AbortToken()
    result = []
    t = threading.Thread(target=lambda: result.append(eng.run_command(2, "slow", token)))
    t.start()
    assert started.wait(5.0)
    token.abort("operator")
    release.set()
    t.join(5.0)
    assert result == [TaskState.CANCELLED]


def test_worker_survives_a_port_bug_and_stdin_lines():
    import io

    from decision_maker.client.console import stdin_lines

    robot = FakeRobot()
    robot.behaviour["nav"] = RuntimeError("bug")
    eng, st = make_engine(robot)
    worker = threading.Thread(target=eng.run)
    worker.start()
    try:
        eng.submit("go home")
        eng.submit("clean table")
        assert wait_until(lambda: sum(s.state.terminal for s in st) >= 2, 30.0)
        assert final(st, 1).state is TaskState.FAILED and "internal error" in final(st, 1).message
        assert final(st, 2).state is TaskState.FAILED
    finally:
        eng.stop()
        worker.join(5)
    lines = stdin_lines(io.StringIO("give me the cup\n\ngo home"), poll_s=0.01)
    assert list(lines) == ["give me the cup", "", "go home"]


def test_raw_size_is_bounded_before_normalisation():
    """10 MB of U+FDFA (18 characters each after NFKC) is rejected on its raw length, unnormalised."""
    eng, st = make_engine(FakeRobot(), max_text_chars=500)
    huge = "\ufdfa" * 3_500_000  # ~10 MB of UTF-8
    status = eng.submit(huge)
    # the count in the reason is the raw one (3.5 M code points), not the normalised 63 M characters
    assert status.state is TaskState.REJECTED and "before normalisation" in status.message, status
    assert f"{len(huge)} code points" in status.message and len(status.text) <= 200
    # 500 code points of U+FDFA pass the raw bound but fail after NFKC (9 000 characters)
    after = eng.submit("\ufdfa" * 500)
    assert after.state is TaskState.REJECTED and "characters" in after.message
    assert [s.state for s in st].count(TaskState.REJECTED) == 2


def wait(predicate, timeout):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return predicate()


@pytest.mark.parametrize("text", ["stop", "Stop it!", "STOP STOP", "cancel", "cancel that", "abort", "please stop",
                                  "halt now", "robot, stop!"])
def test_stop_phrases(text):
    from decision_maker.planning.stop_words import is_stop_command

    assert is_stop_command(text)


@pytest.mark.parametrize("text", ["", "stop at the kitchen", "don't stop", "give me the bottle", "go home",
                                  "clean table", "stopwatch"])
def test_not_stop_phrases(text):
    from decision_maker.planning.stop_words import is_stop_command

    assert not is_stop_command(text)


def test_spoken_stop_cancels_at_once_never_queued():
    robot = FakeRobot()
    robot.gate = threading.Event()
    eng, st = make_engine(robot)
    worker = threading.Thread(target=eng.run, daemon=True)
    worker.start()
    try:
        first = eng.submit("go to the kitchen")
        queued = eng.submit("go home")
        assert wait(lambda: eng.busy(), 5.0)
        stop = eng.submit("Stop it!")
        assert stop.state is TaskState.SUCCEEDED and "cancelled 2 command(s)" in stop.message, stop
        assert robot.cancels >= 1 and eng.queue_length() == 0
        assert wait(lambda: any(s.id == first.id and s.state.terminal for s in st), 5.0)
        assert final(st, first.id).state is TaskState.CANCELLED and "spoken stop" in final(st, first.id).message
        assert final(st, queued.id).state is TaskState.CANCELLED
        idle = eng.submit("cancel")
        assert idle.state is TaskState.SUCCEEDED and "cancelled 0" in idle.message
    finally:
        eng.stop()
        worker.join(5.0)


def test_sim_validation_of_goals_and_objects():
    from decision_maker.errors import ConfigError, SimError
    from decision_maker.sim.world import ObjectWorld, check_coordinates, check_name, check_quaternion

    check_coordinates("goal", (1.0, 2.0, 0.0), 100.0)
    for bad in ((float("nan"), 0.0), (float("inf"), 0.0), (1.7e308, 0.0), (0.0, -101.0)):
        with pytest.raises(SimError, match="goal"):
            check_coordinates("goal", bad, 100.0)
    check_quaternion("goal", 0.0, 0.0, 0.0, 1.0)
    for q in ((0.0, 0.0, 0.0, 0.0), (float("nan"), 0.0, 0.0, 1.0), (0.0, 0.0, 5.0, 1.0)):
        with pytest.raises(SimError, match="orientation"):
            check_quaternion("goal", *q)
    check_name("object name", "bottle")
    for name in ("", "   ", "x" * 65):
        with pytest.raises(SimError):
            check_name("object name", name)
    with pytest.raises(ConfigError, match="finite"):
        ObjectWorld.from_mapping({"cup": [float("nan"), 0.0, 0.0]})
    with pytest.raises(ConfigError, match="64"):
        ObjectWorld.from_mapping({"x" * 100: [0.0, 0.0, 0.0]})


def test_server_watch_fails_only_after_the_server_stays_gone():
    from decision_maker.errors import ServerLost, ServerUnavailable
    from decision_maker.execution.ros_robot import LOST_AFTER_S, _Watch

    present = [True]
    watch = _Watch(lambda: present[0], "navigation server /navigate_to_pose")
    watch.check()
    present[0] = False
    watch.check()  # first miss: not yet
    present[0] = True
    watch.check()  # back: the miss is forgotten
    present[0] = False
    watch.check()
    time.sleep(LOST_AFTER_S + 0.05)
    with pytest.raises(ServerLost, match="navigation server /navigate_to_pose disappeared") as err:
        watch.check()
    assert isinstance(err.value, ServerUnavailable)
