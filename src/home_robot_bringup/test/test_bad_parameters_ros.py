"""Every node started with a parameter it cannot work with says which, in one line, and exits 2: not a traceback,
not a node that runs with the value (a 0-s timer spinning a core, a lockout that never ends, a stop that never
comes)."""

from __future__ import annotations

import pytest

from home_robot_bringup.background import CapturedProcess
from home_robot_bringup.nodeset import find_executable
from home_robot_bringup.process import node_environment

pytestmark = pytest.mark.ros

CASES = [
    ("decision_maker", "decision_maker_node", "max_queue:=abc", "expecting type 'INTEGER'"),
    ("decision_maker", "decision_maker_node", "frame_offset:=[.nan,0.0,0.0]", "three finite numbers"),
    ("decision_maker", "mock_nav_server", "rate_hz:=1e-300", "rate_hz must be a number from 0.01 to 1000"),
    ("decision_maker", "mock_nav_server", "stop_grace_s:=.nan", "stop_grace_s must be a number from 0 to 3600"),
    ("decision_maker", "mock_nav_server", "pose_topic:=bad//t", "Invalid topic name: topic name must not contain"),
    ("decision_maker", "mock_nav_server", "action_name:=bad//name", "Invalid topic name"),
    ("decision_maker", "decision_maker_node", "nav_action:=9lives", "must not start with a number"),
    ("decision_maker", "mock_grasp_server", "world_rate_hz:=1e-300", "world_rate_hz must be a number"),
    ("decision_maker", "mock_grasp_server", "reach:=.inf", "reach must be a number"),
    ("home_robot_exploration", "explorer_node", "tick_hz:=1e-300", "tick_hz must be a number"),
    ("home_robot_exploration", "sim_camera_node", "seed:=-1", "seed must be >= 0, got -1"),
    ("home_robot_exploration", "live_view_node", "map_check_s:=1e300", "map_check_s must be a number"),
    ("home_robot_web", "web_ui_node", "lockout_s:=.inf", "lockout_s finite and > 0"),
    ("home_robot_web", "web_ui_node", "port:=abc", "expecting type 'INTEGER'"),
    ("object_query", "object_query_server", "map_path:=/nonexistent/params.npz", "map file not found"),
    ("decision_maker", "audio_command_node", "model:=/nonexistent/whisper", "/nonexistent/whisper"),
    ("semantic_gs_slam_ros", "run_gs_slam_client", "start:=abc", "expecting type 'INTEGER'"),
]


@pytest.mark.parametrize("package, executable, param, words", CASES, ids=[f"{c[1]}-{c[2]}" for c in CASES])
def test_a_node_started_with_a_parameter_it_cannot_use_exits_2_and_says_why(ros_domain, package, executable, param,
                                                                            words):
    proc = CapturedProcess([find_executable(package, executable), "--ros-args", "-p", param],
                           node_environment(ros_domain))
    assert proc.wait(60) == 2, proc.text()
    assert "cannot start: " in proc.text() and words in proc.text() and "Traceback" not in proc.text(), proc.text()


@pytest.mark.parametrize("package, executable, node, param", [
    ("decision_maker", "mock_nav_server", "mock_nav_server", "speed"),
    ("home_robot_exploration", "live_view_node", "live_view", "map_check_s"),
])
def test_a_parameter_read_at_start_cannot_be_changed_later_without_a_word(ros_domain, ros_node, package, executable,
                                                                         node, param):
    """``ros2 param set`` on a parameter the node reads only at start is refused with the reason (it would be
    ignored); rclpy's own ``use_sim_time`` is still rclpy's to set."""
    import threading

    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    proc = CapturedProcess([find_executable(package, executable)], node_environment(ros_domain))
    try:
        client = ros_node.create_client(SetParameters, f"/{node}/set_parameters")
        assert client.wait_for_service(timeout_sec=60.0), proc.text()

        def set_param(name, value):
            req = SetParameters.Request(parameters=[Parameter(name=name, value=value)])
            done = threading.Event()
            future = client.call_async(req)
            future.add_done_callback(lambda _f: done.set())
            assert done.wait(20.0), proc.text()
            return future.result().results[0]

        refused = set_param(param, ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=2.0))
        assert not refused.successful
        assert refused.reason == f"{node} reads {param} at start only; restart the node with the new value"
        assert set_param("use_sim_time", ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=False)).successful
        assert proc.proc.poll() is None, proc.text()
    finally:
        proc.proc.terminate()
        proc.wait(10)


def test_the_slam_server_refuses_a_change_it_would_ignore_or_could_not_run_with(ros_domain, ros_node):
    """``run_gs_slam_server`` reads most parameters at each goal, so a ``ros2 param set`` between runs reaches the
    next run; a value that run could not use is refused now with the reason its goal would abort with, and a
    parameter read at start only (the live view's port, the device) is refused with that reason."""
    import threading

    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import GetParameters, SetParameters

    proc = CapturedProcess([find_executable("semantic_gs_slam_ros", "run_gs_slam_server")],
                           node_environment(ros_domain))
    try:
        setter = ros_node.create_client(SetParameters, "/run_gs_slam_server/set_parameters")
        getter = ros_node.create_client(GetParameters, "/run_gs_slam_server/get_parameters")
        assert setter.wait_for_service(timeout_sec=60.0) and getter.wait_for_service(timeout_sec=60.0), proc.text()

        def call(client, req):
            done = threading.Event()
            future = client.call_async(req)
            future.add_done_callback(lambda _f: done.set())
            assert done.wait(20.0), proc.text()
            return future.result()

        def set_param(name, value):
            return call(setter, SetParameters.Request(parameters=[Parameter(name=name, value=value)])).results[0]

        def integer(v):
            return ParameterValue(type=ParameterType.PARAMETER_INTEGER, integer_value=v)

        def double(v):
            return ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=v)

        refused = set_param("live_view_port", integer(8765))
        assert not refused.successful
        assert refused.reason == ("run_gs_slam_server reads live_view_port at start only; restart the node with "
                                  "the new value")
        for name, value, words in [("image_qos_depth", integer(0), "image_qos_depth must be >= 1, got 0"),
                                   ("done_wait", double(float("nan")), "done_wait must be a finite number"),
                                   ("lag_low", integer(400), "lag_low and lag_high must satisfy"),
                                   ("width", integer(-5), "width and height must be >= 0")]:
            refused = set_param(name, value)
            assert not refused.successful and words in refused.reason, (name, refused.reason)
        assert set_param("done_wait", double(3.0)).successful
        got = call(getter, GetParameters.Request(names=["done_wait", "image_qos_depth", "lag_low", "width"])).values
        assert [got[0].double_value, got[1].integer_value, got[2].integer_value, got[3].integer_value] == \
            [3.0, 50, 150, 1200]
        assert proc.proc.poll() is None, proc.text()
    finally:
        proc.proc.terminate()
        proc.wait(10)
