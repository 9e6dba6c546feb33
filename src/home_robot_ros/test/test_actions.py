"""home_robot_ros.actions.ActionClient: replies that arrive before their request is recorded are kept.

A real action server and client (one rclpy node spun by a two-thread executor, as in our nodes); the
client's requests are sent from the test thread. To make the race certain rather than occasional,
the client's transport handle pauses 0.3 s after sending each request, before rclpy records it: the
server's reply is taken by the executor inside that pause. rclpy's own client loses that reply (its
future never completes); ours must not.
"""

from __future__ import annotations

import time

import pytest

from home_robot_bringup.testing import wait_for

pytestmark = pytest.mark.ros

PAUSE_S = 0.3


class _PausingHandle:
    """The client's rcl handle, pausing after each request is sent (everything else passed through)."""

    def __init__(self, handle) -> None:
        self._handle = handle

    def __getattr__(self, name):
        return getattr(self._handle, name)

    def __enter__(self):
        return self._handle.__enter__()

    def __exit__(self, *exc):
        return self._handle.__exit__(*exc)

    def _paused(self, send, request):
        sequence = send(request)
        time.sleep(PAUSE_S)
        return sequence

    def send_goal_request(self, request):
        return self._paused(self._handle.send_goal_request, request)

    def send_cancel_request(self, request):
        return self._paused(self._handle.send_cancel_request, request)

    def send_result_request(self, request):
        return self._paused(self._handle.send_result_request, request)


def _server(node, *, hold_s: float):
    from nav2_msgs.action import NavigateToPose
    from rclpy.action import ActionServer, CancelResponse
    from rclpy.callback_groups import ReentrantCallbackGroup

    def execute(goal_handle):
        deadline = time.monotonic() + hold_s
        while time.monotonic() < deadline and not goal_handle.is_cancel_requested:
            time.sleep(0.01)
        if goal_handle.is_cancel_requested:
            goal_handle.canceled()
        else:
            goal_handle.succeed()
        return NavigateToPose.Result()

    return ActionServer(node, NavigateToPose, "race_test", execute_callback=execute,
                        cancel_callback=lambda _request: CancelResponse.ACCEPT,
                        callback_group=ReentrantCallbackGroup())


def _client(node, cls):
    from nav2_msgs.action import NavigateToPose

    client = cls(node, NavigateToPose, "race_test")
    client._client_handle = _PausingHandle(client._client_handle)
    assert client.wait_for_server(timeout_sec=20)
    return client


def test_goal_and_result_replies_are_not_lost(ros_node):
    from action_msgs.msg import GoalStatus
    from nav2_msgs.action import NavigateToPose

    from home_robot_ros.actions import ActionClient

    _server(ros_node, hold_s=0.0)
    client = _client(ros_node, ActionClient)
    for _ in range(3):
        sent = client.send_goal_async(NavigateToPose.Goal())
        assert wait_for(sent.done, 10), "goal reply lost"
        handle = sent.result()
        assert handle.accepted
        result = handle.get_result_async()
        assert wait_for(result.done, 10), "result reply lost"
        assert result.result().status == GoalStatus.STATUS_SUCCEEDED


def test_cancel_reply_is_not_lost(ros_node):
    from action_msgs.msg import GoalStatus
    from nav2_msgs.action import NavigateToPose

    from home_robot_ros.actions import ActionClient

    _server(ros_node, hold_s=30.0)
    client = _client(ros_node, ActionClient)
    sent = client.send_goal_async(NavigateToPose.Goal())
    assert wait_for(sent.done, 10)
    handle = sent.result()
    result = handle.get_result_async()
    cancelled = handle.cancel_goal_async()
    assert wait_for(cancelled.done, 10), "cancel reply lost"
    assert len(cancelled.result().goals_canceling) == 1
    assert wait_for(result.done, 10)
    assert result.result().status == GoalStatus.STATUS_CANCELED


def test_the_pause_reproduces_the_rclpy_race(ros_node):
    """Guards the two tests above: with rclpy's own client the same pause loses the goal reply.

    If this fails, the installed rclpy no longer has the race (ros2/rclpy#1123 fixed):
    home_robot_ros.actions.ActionClient can then be retired in favour of rclpy's.
    """
    from nav2_msgs.action import NavigateToPose
    from rclpy.action import ActionClient

    _server(ros_node, hold_s=0.0)
    client = _client(ros_node, ActionClient)
    sent = client.send_goal_async(NavigateToPose.Goal())
    assert not wait_for(sent.done, 3.0)
