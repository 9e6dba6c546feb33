"""Planning from the object memory, the intent grammar and the approach pose (pure core, no ROS)."""

from __future__ import annotations

import dataclasses
import math
import os

import pytest

from decision_maker.command_types import GoTo, Grasp, Place, Pose2D, load_locations
from decision_maker.errors import ActionFailed, NoMatchingScenario, Reply
from decision_maker.execution.engine import ActionOutcome, EngineConfig, ExecutionEngine, TaskState
from decision_maker.memory.world import AMBIGUITY_MARGIN, Clarification
from decision_maker.nl_planner import PlanningContext, RegistryPlanner
from decision_maker.planning.approach import approach_pose, place_phrase
from decision_maker.scenario_library import match_scenario
from object_query.memory import MapObservation, ObjectMemory

LOCS = load_locations(os.path.join(os.path.dirname(__file__), "..", "config", "locations.yaml"))
HOME = LOCS["home"].pose
# the sample home's objects, as the memory holds them after the map is loaded
MAP = [MapObservation("bottle", (5.17, 0.32, 1.0)), MapObservation("cup", (2.79, 2.6, 0.8)),
       MapObservation("cup", (4.57, 0.37, 0.93)), MapObservation("trash", (2.28, 2.48, 0.8)),
       MapObservation("table", (2.5, 2.5, 0.4)), MapObservation("chair", (2.5, 1.7, 0.4))]


def memory() -> ObjectMemory:
    mem = ObjectMemory(clock=lambda: 1000.0)
    mem.merge_map(MAP, observed_at=900.0)
    return mem


def ctx(mem: ObjectMemory | None = None, robot: Pose2D | None = None, held: str | None = None) -> PlanningContext:
    m = mem or memory()
    names = frozenset(b.name for b in m.snapshot())
    return PlanningContext(names, LOCS, {}, memory=m.snapshot(), robot_pose=robot, held_object=held)


def steps(plan) -> list[str]:
    return [str(p) for p in plan.primitives]


# --- the approach pose ------------------------------------------------------------------------------


def test_approach_uses_a_named_location_within_reach():
    a = approach_pose((5.17, 0.32, 1.0), LOCS, HOME)
    assert a.location == "kitchen" and a.primitive() == "goto:kitchen" and a.distance <= 0.9


def test_approach_computes_a_pose_facing_the_object_on_the_robots_side():
    target = (2.79, 2.6, 0.8)  # the table cup: no named stand pose within reach
    a = approach_pose(target, LOCS, HOME)
    assert a.location is None
    assert math.hypot(a.pose.x - target[0], a.pose.y - target[1]) == pytest.approx(0.6, abs=1e-3)
    bearing_to_object = math.atan2(target[1] - a.pose.y, target[0] - a.pose.x)
    assert abs(math.remainder(a.pose.theta - bearing_to_object, 2 * math.pi)) < 1e-3
    assert a.pose.x < target[0] and a.pose.y < target[1]  # the side facing home (0.5, 0.5)


def test_approach_skips_occupied_points_and_rejects_bad_input():
    target = (2.79, 2.6, 0.8)
    a = approach_pose(target, LOCS, HOME, is_free=lambda x, y: x > 2.79)  # only east of the cup is free
    assert a.pose.x > 2.79
    with pytest.raises(ValueError, match="no free place"):
        approach_pose(target, LOCS, HOME, is_free=lambda x, y: False)
    with pytest.raises(ValueError):
        approach_pose((float("nan"), 0, 0), LOCS)
    with pytest.raises(ValueError):
        approach_pose(target, LOCS, standoff=2.0, reach=1.0)


def test_place_phrase():
    assert place_phrase((1.3, 3.95, 0.75), LOCS) == "with you"
    assert place_phrase((2.79, 2.6, 0.8), LOCS) == "on the table"
    assert place_phrase((4.57, 0.37, 0.93), LOCS) == "at the kitchen counter"
    assert place_phrase((0, 0, 0), LOCS, place="bin") == "in the bin"
    assert place_phrase((-9.0, -9.0, 0.0), LOCS) == "at (-9.00, -9.00)"


# --- intent grammar: the phrases people use ------------------------------------------------------


@pytest.mark.parametrize("text, expected", [
    ("go back home", ["goto:home"]),
    ("could you bring me the cup", None),  # a fetch of a cup (which one: see below)
    ("fetch the bottle please", ["goto:kitchen", "grasp:bottle", "place:user"]),
    ("Robot, give me the bottle!", ["goto:kitchen", "grasp:bottle", "place:user"]),
    ("can i have the bottle", ["goto:kitchen", "grasp:bottle", "place:user"]),
    ("clear the table", ["goto:table", "grasp:trash", "place:bin"]),
    ("please drive to the kitchen", ["goto:kitchen"]),
    ("giv me the bottle", ["goto:kitchen", "grasp:bottle", "place:user"]),  # a mis-heard word, accepted
])
def test_wordings_people_use(text, expected):
    plan = RegistryPlanner().plan(text, ctx())
    if expected is None:
        assert [type(p) for p in plan.primitives] == [GoTo, Grasp, Place] and plan.slots["item"] == "cup"
    else:
        assert steps(plan) == expected


def test_fuzzy_match_says_how_it_read_the_command():
    plan = RegistryPlanner().plan("giv me the bottle", ctx())
    assert "I read 'give me' as 'give me'" in plan.slots["note"]


@pytest.mark.parametrize("text, answer", [
    ("where is the bottle", "The bottle is at the kitchen counter (at 5.17, 0.32, 1.00"),
    ("where's the bottle?", "The bottle is at the kitchen counter"),
    ("where did you see my cup", "I know 2 cups: one on the table"),
    ("what do you see", "I see a bottle (at the kitchen counter); 2 cups"),
    ("what can you do", "I can bring you things"),
    ("what are you holding", "I am not holding anything."),
    ("where is the sofa", "I don't know where the sofa is"),
])
def test_questions_are_answered_without_a_plan(text, answer):
    with pytest.raises(Reply) as info:
        RegistryPlanner().plan(text, ctx())
    assert info.value.kind == "answer" and answer in info.value.sentence, info.value.sentence


def test_did_you_mean_moves_nothing_and_yes_runs_it():
    planner = RegistryPlanner()
    with pytest.raises(Reply) as info:
        planner.plan("give ne the botle", ctx())
    assert info.value.kind == "did_you_mean" and "Did you mean 'give me the botle'?" in info.value.sentence
    assert steps(planner.plan("yes", ctx())) == ["goto:kitchen", "grasp:bottle", "place:user"]  # botle -> bottle


def test_did_you_mean_is_dropped_by_another_command():
    planner = RegistryPlanner()
    with pytest.raises(Reply):
        planner.plan("give ne the botle", ctx())
    assert steps(planner.plan("go home", ctx())) == ["goto:home"]
    with pytest.raises(NoMatchingScenario):
        planner.plan("yes", ctx())  # nothing pending any more


@pytest.mark.parametrize("text", ["dance for me", "what is the time", "turn off the lights", "sing a song", "yes"])
def test_far_off_commands_are_not_understood(text):
    with pytest.raises(NoMatchingScenario, match="try one of"):
        RegistryPlanner().plan(text, ctx())


def test_match_reports_the_wording():
    m = match_scenario("go back home", locations=LOCS)
    assert (m.phrase, m.said, m.score) == ("go home", "go back home", 1.0)


# --- planning from the memory ------------------------------------------------------------------------


def test_give_me_the_trash_goes_to_the_table_not_the_kitchen():
    assert steps(RegistryPlanner().plan("give me the trash", ctx())) == ["goto:table", "grasp:trash", "place:user"]


def test_give_me_goes_to_where_the_object_is_now():
    mem = memory()
    mem.set_position("bottle#1", (2.6, 2.7, 0.8), source="user")  # someone put the bottle on the table
    plan = RegistryPlanner().plan("give me the bottle", ctx(mem))
    goto = plan.primitives[0]
    assert isinstance(goto, GoTo) and math.hypot(goto.pose.x - 2.6, goto.pose.y - 2.7) <= 0.9


def test_already_with_the_user_is_answered():
    mem = memory()
    mem.grasped("bottle", (4.9, 1.1, 0.0))
    mem.placed("bottle", (1.3, 3.95, 0.75), "user")
    with pytest.raises(Reply) as info:
        RegistryPlanner().plan("give me the bottle", ctx(mem))
    assert info.value.kind == "answer" and info.value.sentence.startswith("The bottle is already with you")


def test_held_object_is_handed_over_directly():
    mem = memory()
    mem.grasped("bottle", (4.9, 1.1, 0.0))
    assert steps(RegistryPlanner().plan("give me the bottle", ctx(mem))) == ["place:user"]


def test_failed_grasp_is_not_trusted_blindly():
    mem = memory()
    mem.grasp_failed("bottle", (4.9, 1.1, 0.0), "no bottle within reach")
    plan = RegistryPlanner().plan("give me the bottle", ctx(mem))  # the only bottle: look again, and say so
    assert "I'm not sure the bottle is still at the kitchen counter" in plan.slots["note"]
    mem.grasp_failed("cup", (4.9, 1.1, 0.0))  # the counter cup is gone: the table cup is chosen
    plan = RegistryPlanner().plan("give me the cup", ctx(mem, robot=LOCS["kitchen"].pose))
    assert math.hypot(plan.primitives[0].pose.x - 2.79, plan.primitives[0].pose.y - 2.6) <= 0.9


def test_nearest_cup_wins_when_not_ambiguous():
    plan = RegistryPlanner().plan("give me the cup", ctx(robot=LOCS["kitchen"].pose))
    assert steps(plan)[0] == "goto:kitchen"  # the counter cup is next to the robot


def test_two_equally_near_cups_ask_and_the_next_utterance_answers():
    # a robot about as far from both cups
    robot = Pose2D(3.7, 1.5, 0.0)
    mem = memory()
    d = [b.distance_xy((robot.x, robot.y)) for b in mem.candidates("cup")]
    assert abs(d[0] - d[1]) < AMBIGUITY_MARGIN
    planner = RegistryPlanner()
    with pytest.raises(Reply) as info:
        planner.plan("give me the cup", ctx(mem, robot))
    assert info.value.kind == "clarify" and isinstance(info.value.pending, Clarification)
    assert info.value.sentence == "Which cup: the one at the kitchen counter or the one on the table?"
    plan = planner.plan("the one on the table", ctx(mem, robot))
    goto = plan.primitives[0]
    assert math.hypot(goto.pose.x - 2.79, goto.pose.y - 2.6) <= 0.9 and steps(plan)[1:] == ["grasp:cup", "place:user"]


def test_clean_table_plans_from_memory_and_knows_when_it_is_clean():
    mem = memory()
    assert steps(RegistryPlanner().plan("clean table", ctx(mem))) == ["goto:table", "grasp:trash", "place:bin"]
    mem.grasped("trash", (1.5, 2.5, 0.0))
    mem.placed("trash", (5.6, 4.5, 0.5), "bin")
    with pytest.raises(Reply, match="already clean: the trash is in the bin"):
        RegistryPlanner().plan("clean the table", ctx(mem))


def test_without_memory_the_seed_plans_stand():
    plan = RegistryPlanner().plan("give me the cup", PlanningContext(frozenset({"cup"}), LOCS))
    assert steps(plan) == ["goto:kitchen", "grasp:cup", "place:user"]


# --- the engine: replies and outcomes ----------------------------------------------------------------


class Robot:
    def __init__(self, grasp_error: Exception | None = None) -> None:
        self.grasp_error = grasp_error
        self.calls: list[str] = []

    def navigate(self, pose, timeout_s, abort):
        self.calls.append("nav")

    def locate(self, name, timeout_s, abort):
        from decision_maker.command_types import Point3
        return Point3(0, 0, 0)

    def grasp(self, name, target, timeout_s, abort):
        self.calls.append("grasp")
        if self.grasp_error:
            raise self.grasp_error

    def place(self, location, target, timeout_s, abort):
        self.calls.append("place")

    def cancel_active(self):
        pass

    def emergency_stop(self, reason):
        pass


def run(text: str, robot: Robot, mem: ObjectMemory):
    statuses, outcomes = [], []
    eng = ExecutionEngine(RegistryPlanner(), robot, EngineConfig(), statuses.append, lambda: ctx(mem),
                          on_outcome=outcomes.append)
    from decision_maker.execution.engine import AbortToken
    state = eng.run_command(1, text, AbortToken())
    return state, statuses, outcomes


def test_engine_answers_questions_without_moving():
    robot = Robot()
    state, statuses, outcomes = run("where is the bottle", robot, memory())
    assert state == TaskState.SUCCEEDED and robot.calls == [] and outcomes == []
    assert statuses[-1].sentence.startswith("The bottle is at the kitchen counter")
    assert statuses[-1].message.startswith("answer: ")


def test_a_question_while_busy_is_answered_at_once_not_queued():
    statuses = []
    eng = ExecutionEngine(RegistryPlanner(), Robot(), EngineConfig(), statuses.append, lambda: ctx(memory()))
    eng._current = (99, 0.0)  # a command is running (no worker thread here: nothing would dequeue)
    first = eng.submit("where is the bottle")
    assert first.state == TaskState.SUCCEEDED and first.message.startswith("answer: ")
    assert first.sentence.startswith("The bottle is at the kitchen counter")
    assert eng.queue_length() == 0
    # a command (not a question) still queues behind the running one
    assert eng.submit("give me the bottle").state == TaskState.QUEUED
    assert eng.queue_length() == 1


def test_engine_reports_a_clarification_as_rejected():
    mem = memory()
    eng_ctx = dataclasses.replace(ctx(mem), robot_pose=Pose2D(3.7, 1.5, 0.0))
    statuses = []
    eng = ExecutionEngine(RegistryPlanner(), Robot(), EngineConfig(), statuses.append, lambda: eng_ctx)
    eng._pose = Pose2D(3.7, 1.5, 0.0)  # where the robot stopped last
    from decision_maker.execution.engine import AbortToken
    assert eng.run_command(1, "give me the cup", AbortToken()) == TaskState.REJECTED
    assert statuses[-1].message.startswith("clarify: Which cup")


def test_engine_reports_grasp_and_place_outcomes():
    state, _, outcomes = run("give me the bottle", Robot(), memory())
    assert state == TaskState.SUCCEEDED
    assert [o.event for o in outcomes] == ["grasped", "placed"]
    grasped, placed = outcomes
    assert grasped.name == "bottle" and grasped.robot == LOCS["kitchen"].pose
    assert placed.place == "user" and placed.position == LOCS["user"].drop_point() and placed.name == "bottle"


def test_engine_reports_a_failed_grasp_as_negative_evidence():
    state, _, outcomes = run("give me the bottle", Robot(ActionFailed("no bottle within reach")), memory())
    assert state == TaskState.FAILED
    assert outcomes == [ActionOutcome("grasp_failed", "bottle", LOCS["kitchen"].pose,
                                      detail="no bottle within reach")]


# --- the simulator: an object moved by hand -----------------------------------------------------------


def test_sim_world_move_by_hand():
    from decision_maker.command_types import Point3
    from decision_maker.errors import SimError
    from decision_maker.sim.world import ObjectWorld

    world = ObjectWorld.from_mapping({"cup_2": [2.8, 2.6, 0.8], "bottle": [5.2, 0.3, 1.02]})
    assert world.move("CUP_2", Point3(1.0, 4.5, 0.45)).position == Point3(1.0, 4.5, 0.45)
    with pytest.raises(SimError, match="no object"):
        world.move("unicorn", Point3(0, 0, 0))
    with pytest.raises(SimError, match="finite"):
        world.move("bottle", Point3(math.inf, 0, 0))
    world.grasp(Pose2D(4.9, 1.1, 0.0), "bottle")
    with pytest.raises(SimError, match="gripper"):
        world.move("bottle", Point3(0, 0, 0))


def test_synonyms_of_known_objects_fill_the_slot():
    from decision_maker.memory.world import aliases_for

    aliases = aliases_for({"cup", "bottle"}, [("cup", "mug"), ("sofa", "couch"), ("bottle", "flask", "cup")])
    assert aliases == {"mug": "cup", "flask": "bottle"}  # couch: no sofa known; cup is its own class
    context = dataclasses.replace(ctx(), aliases=aliases)
    with pytest.raises(Reply, match="I know 2 cups"):
        RegistryPlanner().plan("where is the mug", context)
    plan = RegistryPlanner().plan("could you bring me the mug", context)
    assert plan.slots["item"] == "cup" and steps(plan)[1:] == ["grasp:cup", "place:user"]


def test_the_llm_planner_gets_the_same_memory():
    import json

    from decision_maker.planning.llm_planner import build_messages

    mem = memory()
    mem.grasped("bottle", (4.9, 1.1, 0.0))
    mem.placed("bottle", (1.3, 3.95, 0.75), "user")
    system = build_messages("I'm thirsty", ctx(mem), None, 8)[0]["content"]
    world = json.loads(system.split("World: ", 1)[1])
    entries = {e["id"]: e for e in world["object_memory"]}
    assert entries["bottle#1"]["where"] == "with you" and entries["bottle#1"]["state"] == "placed"
    assert entries["trash#1"]["approach"] == {"action": "goto", "target": "table"}
    table_cup = next(e for e in entries.values() if e["object"] == "cup" and e["position"][0] < 3)
    assert table_cup["approach"]["target"] == "" and len(table_cup["approach"]["pose"]) == 3


def test_llm_only_tier_answers_questions_without_the_model():
    from decision_maker.planning.llm_planner import TieredPlanner

    class NoModel:
        name = "llm"

        def plan(self, text, context):
            raise AssertionError("the model must not be asked")

    planner = TieredPlanner(NoModel(), tier="llm_only")
    with pytest.raises(Reply, match="The bottle is at the kitchen counter"):
        planner.plan("where's the bottle", ctx())


def test_no_declines_a_pending_question():
    planner = RegistryPlanner()
    with pytest.raises(Reply):
        planner.plan("give ne the botle", ctx())
    with pytest.raises(Reply, match="Okay, I won't"):
        planner.plan("no", ctx())
    with pytest.raises(NoMatchingScenario):
        planner.plan("yes", ctx())  # declined: nothing pending


def test_the_bundled_synonyms_lead_spoken_words_to_the_detectors_classes():
    """A map named by the COCO detector knows "cup", "tv", "couch" ...: the words people say reach them."""
    from decision_maker.memory.world import aliases_for
    from object_query.names import load_synonyms

    path = os.path.join(os.path.dirname(__file__), "..", "..", "object_query", "config", "synonyms.yaml")
    groups = load_synonyms(path).groups
    coco = {"cup", "chair", "dining table", "tv", "couch", "refrigerator", "potted plant", "laptop", "bottle"}
    aliases = aliases_for(coco, groups)
    for said, cls in [("mug", "cup"), ("table", "dining table"), ("television", "tv"), ("sofa", "couch"),
                      ("fridge", "refrigerator"), ("plant", "potted plant"), ("flask", "bottle"),
                      ("computer", "laptop")]:
        assert aliases.get(said) == cls, (said, aliases.get(said))
    context = dataclasses.replace(ctx(), known_objects=frozenset(coco), memory=(), aliases=aliases)
    plan = RegistryPlanner().plan("could you bring me the mug", context)
    assert plan.slots["item"] == "cup" and steps(plan)[-2:] == ["grasp:cup", "place:user"]
