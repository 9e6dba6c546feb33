"""Action-server plumbing shared by the simulated servers: goals driven by a timer, never blocking.

A goal is accepted and then advanced by the node's simulation timer (``tick``); nothing waits
inside a callback. When the simulation decides the outcome, :meth:`SimGoals.finish` hands the goal
to rclpy's execute step, whose callback only sets the terminal state and returns the result.
A cancel request is accepted at once; a guard condition finishes the goal in the very next
executor iteration (as CANCELED), so cancel latency is one executor round trip, not a tick.

Meant for a SingleThreadedExecutor (``rclpy.spin``): all callbacks of the node run in one thread,
so the simulation state needs no locks.

``/cancel_command`` (the hardware stop): the simulation stops moving at once
(:meth:`SimGoals.on_stop` hook), and a goal that its client does not cancel within
``stop_grace_s`` is aborted.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.action.server import ServerGoalHandle
from rclpy.node import Node

from decision_maker.errors import ConfigError
from home_robot_ros.startup import action_name, spin_node


@dataclass
class _Outcome:
    kind: str  # "succeed" | "abort" | "cancel"
    result: Any


class SimGoals:
    """One action server whose goals the owner finishes from its simulation timer.

    Args:
        node: the owning node (spun by a single-threaded executor).
        action_type: e.g. ``NavigateToPose``.
        name: action name.
        on_goal: ``(goal_request) -> str | None`` — a reason to reject, or None to accept.
        on_accepted: ``(goal_handle) -> None`` — start simulating it.
        on_cancel: ``(goal_handle) -> None`` — the goal is being cancelled: stop simulating it.
        result_timeout_s: seconds a finished goal's result is kept for late ``get_result`` calls.
    """

    def __init__(self, node: Node, action_type: type, name: str, on_goal: Callable[[Any], str | None],
                 on_accepted: Callable[[ServerGoalHandle], None],
                 on_cancel: Callable[[ServerGoalHandle], None], result_timeout_s: int = 10) -> None:
        self._node = node
        self._action_type = action_type
        self._on_goal = on_goal
        self._on_accepted = on_accepted
        self._on_cancel = on_cancel
        self._outcomes: dict[bytes, _Outcome] = {}
        self._cancelling: list[ServerGoalHandle] = []
        self.active: set[bytes] = set()  # ids of goals accepted and not yet finished
        self._wake = node.create_guard_condition(self._on_wake)
        self.server = ActionServer(
            node, action_type, action_name(node, name),
            execute_callback=self._finisher,
            goal_callback=self._goal_cb,
            handle_accepted_callback=self._accepted_cb,
            cancel_callback=self._cancel_cb,
            # finished goals leave the status array after this long (rclpy's default is 15 min: the
            # array, which every client parses on every change, would grow with each goal)
            result_timeout=result_timeout_s,
        )

    @staticmethod
    def key(gh: ServerGoalHandle) -> bytes:
        return bytes(gh.goal_id.uuid)

    def _goal_cb(self, request: Any) -> GoalResponse:
        reason = self._on_goal(request)
        if reason:
            self._node.get_logger().warn(f"goal rejected: {reason}")
            return GoalResponse.REJECT
        return GoalResponse.ACCEPT

    def _accepted_cb(self, gh: ServerGoalHandle) -> None:
        self.active.add(self.key(gh))
        self._on_accepted(gh)

    def _cancel_cb(self, gh: ServerGoalHandle) -> CancelResponse:
        if self.key(gh) not in self.active:
            return CancelResponse.REJECT
        self._on_cancel(gh)  # the simulation stops now; the goal ends in the next iteration
        self._cancelling.append(gh)
        self._wake.trigger()  # runs after this cancel request is processed (same thread)
        return CancelResponse.ACCEPT

    def _on_wake(self) -> None:
        pending, self._cancelling = self._cancelling, []
        for gh in pending:
            self.finish(gh, "cancel", self.result())

    def result(self, **fields: Any) -> Any:
        res = self._action_type.Result()
        for k, v in fields.items():
            setattr(res, k, v)
        return res

    def feedback(self) -> Any:
        return self._action_type.Feedback()

    def finish(self, gh: ServerGoalHandle, kind: str, result: Any) -> None:
        """End ``gh``: ``kind`` is ``succeed``, ``abort`` or ``cancel``; ``result`` its result message."""
        k = self.key(gh)
        if k not in self.active:
            return
        self.active.discard(k)
        self._outcomes[k] = _Outcome(kind, result)
        gh.execute()  # → _finisher in the next executor iteration

    def _finisher(self, gh: ServerGoalHandle) -> Any:
        outcome = self._outcomes.pop(self.key(gh), _Outcome("abort", self.result()))
        if gh.is_cancel_requested:
            gh.canceled()
        elif outcome.kind == "succeed":
            gh.succeed()
        else:
            gh.abort()
        return outcome.result


def run_sim_node(node_class: Callable[[], Node], name: str, args: list[str] | None = None) -> int:
    """``main()`` of a simulated server (:func:`home_robot_ros.startup.spin_node`; a ConfigError: exit 2)."""
    return spin_node(node_class, name, args, (ConfigError,))
