"""End to end: the simulated robot with the LLM planner configured (real processes over ROS 2).

The model is NOT under test: a scripted OpenAI-compatible endpoint on 127.0.0.1 (started by the
test) answers the decision maker's requests. Tested: the decision maker's planner parameters, the
request it sends (world context), validation before motion, and that valid LLM plans move the
simulated robot while refusals and an unreachable endpoint only produce a status.
"""

from __future__ import annotations

import json

import pytest

from decision_maker.execution.engine import TaskState

from .llm_testing import ScriptedEndpoint, completion
from .test_decision_maker_ros import FAST, USER_DROP, Robot, near, robot_specs

pytestmark = pytest.mark.ros

DRINK = {"decision": "plan", "message": "Bringing you the bottle.",
         "steps": [{"action": "goto", "target": "kitchen"}, {"action": "grasp", "target": "bottle"},
                   {"action": "place", "target": "user"}]}
KNIFE = {"decision": "plan", "message": "ok", "steps": [{"action": "grasp", "target": "knife"}]}
REFUSE = {"decision": "clarify", "steps": [], "message": "Which room do you mean?"}


def llm_robot(endpoint_url: str, **options):
    opts = {"tier": "registry_first", "base_url": endpoint_url, "model": "scripted", "timeout_s": 3.0,
            "retries": 0, **options}
    return [s.with_parameters(planner="llm", planner_options=json.dumps(opts)) if s.name == "decision_maker" else s
            for s in robot_specs()]


def test_llm_plans_move_the_robot_only_when_valid(launch_nodes, ros_node):
    ep = ScriptedEndpoint([(200, completion(DRINK)), (200, completion(KNIFE)), (200, completion(REFUSE))])
    try:
        launch_nodes(nodes=llm_robot(ep.url), set=FAST)
        robot = Robot(ros_node)
        robot.wait_connected()
        robot.send("go home")  # a registry phrase: never reaches the LLM
        assert robot.final("go home").state is TaskState.SUCCEEDED
        assert ep.requests == []

        robot.wait_knows("bottle")  # the LLM's plan is checked against the objects the brain knows
        robot.send("I'm thirsty, could you help?")
        done = robot.final("I'm thirsty, could you help?", 60.0)
        assert done.state is TaskState.SUCCEEDED, done
        assert near(robot.snapshot()["objects"]["bottle"]["position"], USER_DROP), robot.snapshot()
        request = ep.requests[0]["body"]
        system = request["messages"][0]["content"]
        assert "bottle" in system and "kitchen" in system  # the object list and locations went along
        assert json.loads(request["messages"][1]["content"]) == {"request": "I'm thirsty, could you help?"}

        before = robot.snapshot()
        robot.send("hand me something sharp")  # the model proposes an unknown object
        bad = robot.final("hand me something sharp")
        assert bad.state is TaskState.REJECTED and "I don't know where knife is" in bad.message
        robot.send("tidy up over there")  # the model asks back
        asked = robot.final("tidy up over there")
        assert asked.state is TaskState.REJECTED and "Which room do you mean?" in asked.message
        after = robot.snapshot()
        assert after["robot"] == before["robot"] and after["objects"] == before["objects"]  # nothing moved
    finally:
        ep.close()


def test_unreachable_endpoint_is_reported_and_registry_still_works(launch_nodes, ros_node):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # nobody listens here
    launch_nodes(nodes=llm_robot(f"http://127.0.0.1:{port}/v1", tier="llm_only"), set=FAST)
    robot = Robot(ros_node)
    robot.wait_connected()
    robot.send("go home")  # LLM down → falls back to the registry, and says so
    st = robot.final("go home", 30.0)
    assert st.state is TaskState.SUCCEEDED
    assert any("LLM unavailable" in s.message for s in robot.of("go home")), robot.of("go home")
    robot.send("I'm thirsty")
    st = robot.final("I'm thirsty", 30.0)
    assert st.state is TaskState.REJECTED and "unavailable" in st.message
