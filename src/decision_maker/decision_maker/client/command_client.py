"""Sending commands to the decision maker with an acknowledgement (for input nodes: text, voice, ...).

The brain serves ``submit_command`` (``decision_maker_interfaces/srv/SubmitCommand``): each call
answers with the command id (the ``id`` of its ``/task_status`` updates) or the reason it was
rejected, so a sender knows that every command arrived. ``/manual_command`` (the seed's topic)
stays; :class:`CommandClient` uses it, with a warning, when the service is not there (an older or
absent brain): then nothing is acknowledged.

Usage from a node (the node is spun elsewhere, e.g. by a MultiThreadedExecutor)::

    commands = CommandClient(node)                      # or CommandClient(node, publisher=own_pub)
    commands.submit_async("give me the cup", on_ack)    # never blocks: callbacks, audio threads
    ack = commands.submit("go home", timeout_s=5.0)     # blocks up to timeout_s: main/worker threads

Threads: ``submit_async`` may be called from any thread, ``on_ack`` runs in an executor thread or,
for the topic fallback and timeouts, in the caller's thread / the helper's timer. A call whose
answer does not come within ``answer_timeout_s`` is reported as not acknowledged (never silently).

Lost answers: DDS can drop a service's answer while the brain has not yet matched this client's
response reader (a discovery race of ROS 2 services, worst while many nodes start). Each command
carries a unique ``key``; while no answer has come, the same call is sent again after ``retry_s``,
then after twice, four times... as long (within ``answer_timeout_s``). The brain answers every
repeat with its first answer without running the command again
(``decision_maker.execution.repeated_calls``). The first answer to arrive is the one reported.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field

from decision_maker_interfaces.srv import SubmitCommand
from rclpy.callback_groups import CallbackGroup
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.task import Future
from std_msgs.msg import String

from decision_maker.topics import COMMAND_QOS, MANUAL_COMMAND, SERVICE_QOS, SUBMIT_COMMAND


@dataclass(frozen=True)
class Ack:
    """What became of one command sent.

    Attributes:
        text: the command as given to the client.
        via: ``"service"`` (acknowledged by the brain) or ``"topic"`` (published, not acknowledged).
        accepted: the brain took it (queued, or a stop / an answer it acted on); False = rejected or
            no answer. Always True for ``via == "topic"`` (nobody can tell).
        id: the command id of its ``/task_status`` updates (0 = unknown: topic, or no answer).
        state: first state from the brain (``queued``, ``rejected``, ...), ``"sent"`` for the topic,
            ``"no_answer"`` when the service did not answer in time.
        message: the brain's detail (reason of a rejection), or what happened.
    """

    text: str
    via: str
    accepted: bool
    id: int = 0
    state: str = ""
    message: str = ""


@dataclass
class _Call:
    """One command in flight: its key, the calls sent for it, when to send again and to give up."""

    text: str
    key: str
    on_ack: Callable[[Ack], None] | None
    deadline: float
    next_send: float
    wait_s: float  # before the next send; doubles with each send
    futures: list[Future] = field(default_factory=list)


class CommandClient:
    """The acknowledged way in for commands, with the topic as fallback.

    Args:
        node: the sending node (spun elsewhere).
        service: name of the brain's SubmitCommand service.
        publisher: an existing ``/manual_command`` publisher to reuse (else one is created).
        callback_group: group of the service client (default: the node's default group).
        answer_timeout_s: longest wait for the brain's answer to one command (> 0).
        log: where the one-time fallback warning goes (default: the node's logger).
        retry_s: while unanswered, the same call (same key) is sent again after this long, then after
            twice as long each time (> 0).
    """

    def __init__(self, node: Node, service: str = SUBMIT_COMMAND, publisher: Publisher | None = None,
                 callback_group: CallbackGroup | None = None, answer_timeout_s: float = 5.0,
                 log: Callable[[str], None] | None = None, retry_s: float = 1.0) -> None:
        if not answer_timeout_s > 0:
            raise ValueError(f"answer_timeout_s must be > 0, got {answer_timeout_s}")
        if not retry_s > 0:
            raise ValueError(f"retry_s must be > 0, got {retry_s}")
        self._node = node
        self._client = node.create_client(SubmitCommand, service, qos_profile=SERVICE_QOS,
                                          callback_group=callback_group)
        self._pub = publisher if publisher is not None else node.create_publisher(String, MANUAL_COMMAND,
                                                                                   COMMAND_QOS)
        self._answer_timeout_s = answer_timeout_s
        self._retry_s = retry_s
        self._warn = log or (lambda text: node.get_logger().warn(text))
        self._lock = threading.Lock()  # guards _pending, _warned, resends
        self._pending: dict[str, _Call] = {}  # by key
        self._warned = False
        self.resends = 0  # calls sent again because no answer had come
        self._timer = node.create_timer(min(0.25, retry_s / 2), self._tick, callback_group=callback_group)

    @property
    def service_name(self) -> str:
        return self._client.srv_name

    def service_ready(self) -> bool:
        """True when the brain's service is matched (it answers)."""
        return self._client.service_is_ready()

    def wait_for_service(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` for the service (not from a callback). Returns whether it is there."""
        deadline = time.monotonic() + max(0.0, timeout_s)
        while not self.service_ready():
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.02)
        return True

    def submit_async(self, text: str, on_ack: Callable[[Ack], None] | None = None) -> None:
        """Send ``text``; ``on_ack`` gets the :class:`Ack` later (at once for the topic). Never blocks.

        Text that no ROS string can carry (a lone surrogate) is answered at once: not accepted, with the reason.
        """
        try:
            text.encode("utf-8")
        except UnicodeEncodeError:
            if on_ack is not None:
                on_ack(Ack(text, "service", False, state="rejected",
                           message="the command is not valid Unicode text (a lone surrogate)"))
            return
        if not self.service_ready():
            self._publish(text, on_ack)
            return
        now = time.monotonic()
        call = _Call(text, uuid.uuid4().hex, on_ack, now + self._answer_timeout_s, now + self._retry_s,
                     2 * self._retry_s)
        with self._lock:
            self._pending[call.key] = call
        self._send(call)

    def submit(self, text: str, timeout_s: float | None = None) -> Ack:
        """Send ``text`` and wait for the answer, at most ``timeout_s`` (default ``answer_timeout_s``).

        Must not be called from a callback of the node's executor (it waits for one).
        """
        box: list[Ack] = []
        done = threading.Event()

        def keep(ack: Ack) -> None:
            box.append(ack)
            done.set()

        self.submit_async(text, keep)
        if not done.wait(self._answer_timeout_s if timeout_s is None else timeout_s) or not box:
            return Ack(text, "service", False, state="no_answer",
                       message=f"the decision maker did not answer within {timeout_s or self._answer_timeout_s:g} s")
        return box[0]

    def pending(self) -> int:
        """Commands sent and not answered yet."""
        with self._lock:
            return len(self._pending)

    # --- internals ---------------------------------------------------------------------------------

    def _publish(self, text: str, on_ack: Callable[[Ack], None] | None) -> None:
        with self._lock:
            warn, self._warned = not self._warned, True
        if warn:
            self._warn(f"the decision maker's {self._client.srv_name} service is not available: sending on "
                       f"/{MANUAL_COMMAND} without acknowledgement")
        self._pub.publish(String(data=text))
        if on_ack is not None:
            on_ack(Ack(text, "topic", True, state="sent", message=f"published on /{MANUAL_COMMAND}"))

    def _send(self, call: _Call) -> None:
        future = self._client.call_async(SubmitCommand.Request(text=call.text, key=call.key))
        with self._lock:
            call.futures.append(future)
        future.add_done_callback(lambda f, key=call.key: self._answered(key, f))

    def _answered(self, key: str, future: Future) -> None:
        with self._lock:
            call = self._pending.pop(key, None)
            others = [f for f in call.futures if f is not future] if call is not None else []
        if call is None:  # answered by an earlier send, or expired already (reported then)
            return
        for other in others:  # the repeats' answers are no longer awaited
            self._client.remove_pending_request(other)
        try:
            resp = future.result()
        except Exception as exc:  # the call failed (context shut down, ...): say so, never drop it silently
            ack = Ack(call.text, "service", False, state="no_answer", message=f"call failed: {exc!r}")
        else:
            ack = Ack(call.text, "service", bool(resp.accepted), int(resp.id), str(resp.state), str(resp.message))
        if call.on_ack is not None:
            call.on_ack(ack)

    def _tick(self) -> None:
        now = time.monotonic()
        with self._lock:
            late = [c for c in self._pending.values() if c.deadline <= now]
            for c in late:
                del self._pending[c.key]
            again = [c for c in self._pending.values() if c.next_send <= now]
            for c in again:  # backing off: a busy brain is not flooded with repeats
                c.next_send, c.wait_s = now + c.wait_s, 2 * c.wait_s
            self.resends += len(again)
        for call in again:  # the same key: the brain answers a repeat without running it again
            self._send(call)
        for call in late:
            for future in call.futures:
                self._client.remove_pending_request(future)
            if call.on_ack is not None:
                call.on_ack(Ack(call.text, "service", False, state="no_answer",
                                message=f"the decision maker did not answer within {self._answer_timeout_s:g} s"))
