"""An rclpy ``ActionClient`` whose replies can never overtake their requests.

rclpy's ``ActionClient.send_goal_async`` sends the request first and only then records its sequence
number. When another thread spins the node (our nodes send goals from a worker thread while a
``MultiThreadedExecutor`` spins), the server's reply can be taken and handled in that gap. rclpy then
logs "Ignoring unexpected goal response. There may be more than one action server …" and the
returned future never completes (ros2/rclpy#1123; the upstream fix, ros2/rclpy#1308, is not released
for Jazzy or Humble). The same gap exists for cancel and result requests. It was seen in CI: the SLAM
client waited 30 s for an answer the server had already sent, and reported the goal as rejected.

:class:`ActionClient` closes the gap with one lock: a request is sent and recorded under the lock, and
a reply is matched to its request under the same lock, so a reply taken early waits the few
microseconds until its request is recorded. Feedback and status messages are handled outside the
lock, so a slow feedback callback delays no one.

Use it exactly like ``rclpy.action.ActionClient``.
"""

from __future__ import annotations

import threading

from rclpy.action import ActionClient as _RclpyActionClient

__all__ = ["ActionClient"]

_REPLIES = ("goal", "cancel", "result")


class ActionClient(_RclpyActionClient):
    """``rclpy.action.ActionClient`` that is safe to use from any thread while another thread spins."""

    def __init__(self, *args, **kwargs) -> None:
        # re-entrant: a done callback run inline by a reply may send the next request on this thread
        self._requests_lock = threading.RLock()
        super().__init__(*args, **kwargs)

    def send_goal_async(self, goal, feedback_callback=None, goal_uuid=None):
        with self._requests_lock:
            return super().send_goal_async(goal, feedback_callback=feedback_callback, goal_uuid=goal_uuid)

    def _cancel_goal_async(self, goal_handle):
        with self._requests_lock:
            return super()._cancel_goal_async(goal_handle)

    def _get_result_async(self, goal_handle):
        with self._requests_lock:
            return super()._get_result_async(goal_handle)

    async def execute(self, taken_data):
        replies = {key: taken_data[key] for key in _REPLIES if key in taken_data}
        if replies:
            # rclpy's handling of replies never awaits, so the lock is held only while they are matched
            with self._requests_lock:
                await super().execute(replies)
        others = {key: value for key, value in taken_data.items() if key not in replies}
        if others:
            await super().execute(others)
