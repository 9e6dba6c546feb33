"""The execution engine: a bounded FIFO of commands, one batch at a time, with a watchdog (no ROS).

Threads: input callbacks call :meth:`ExecutionEngine.submit` and :meth:`ExecutionEngine.cancel`
(they never block); one worker thread runs :meth:`ExecutionEngine.run`, which plans each command
and executes its primitives sequentially through a :class:`RobotPort` (the ROS shell implements it
with action clients; unit tests with a fake).

Watchdog, as the seed's diagram: the batch's start time is recorded; before every primitive,
``elapsed > batch_timeout_s`` → abort (``/hardware_stop`` is published through
:meth:`RobotPort.emergency_stop`) and report ``timed_out``. Beyond the seed: each primitive waits
at most ``min(its own timeout, time left in the batch)``, so a hung action cannot hold the batch past
its deadline; on any timeout the active goal is cancelled, ``/hardware_stop`` is published and the
batch reports ``timed_out``.

Every command gets an id and at least one status: ``queued`` or ``rejected`` at once, then
``running`` per step and one terminal state (succeeded | failed | cancelled | timed_out | rejected).
"""

from __future__ import annotations

import collections
import dataclasses
import enum
import itertools
import json
import math
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Protocol

from decision_maker.command_types import (
    MAX_TEXT_CHARS,
    GoTo,
    Grasp,
    NamedLocation,
    Place,
    Plan,
    Point3,
    Pose2D,
    Primitive,
    sanitize_text,
    shorten,
)
from decision_maker.errors import (
    ActionCancelled,
    ActionFailed,
    ActionTimeout,
    ConfigError,
    ExecutionError,
    PlanningError,
    Reply,
)
from decision_maker.execution.stage0 import Hold
from decision_maker.nl_planner import Planner, PlanningContext
from decision_maker.planning.stop_words import is_stop_command
from decision_maker.scenario_library import answer_question


class TaskState(str, enum.Enum):
    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELLED = "cancelled"
    TIMED_OUT = "timed_out"
    REJECTED = "rejected"

    @property
    def terminal(self) -> bool:
        return self not in (TaskState.QUEUED, TaskState.RUNNING)


#: the /task_status fields checked on parsing (stamp: any finite number), so a reader never holds, say, a list as an id
_STATUS_FIELD_TYPES: dict[str, type] = {"id": int, "step": int, "steps": int, "text": str, "primitive": str,
                                        "message": str, "sentence": str}


@dataclass(frozen=True)
class TaskStatus:
    """One ``/task_status`` update (JSON on the wire, see :meth:`to_json`).

    Attributes:
        id: command id (1, 2, ... per decision maker run).
        text: the command text as received (sanitised, cut to 200 characters).
        state: see :class:`TaskState`.
        step: current step (1-based; 0 = before the first primitive).
        steps: number of primitives in the plan (0 = not planned yet).
        primitive: the current primitive (``goto:kitchen``), or "".
        message: machine-oriented detail (reason of a failure, stage, ...).
        sentence: the same for a person.
        stamp: wall-clock time of the update (seconds since the epoch).
    """

    id: int
    text: str
    state: TaskState
    step: int = 0
    steps: int = 0
    primitive: str = ""
    message: str = ""
    sentence: str = ""
    stamp: float = 0.0

    def to_json(self) -> str:
        d = asdict(self)
        d["state"] = self.state.value
        return json.dumps(d, ensure_ascii=False)

    @classmethod
    def from_json(cls, data: str) -> TaskStatus:
        """Parse a ``/task_status`` message.

        Raises:
            ValueError: not a task status (not JSON, not an object, a field missing or of the wrong type).
        """
        try:
            d = json.loads(data)
            d["state"] = TaskState(d["state"])
            fields = {k: d[k] for k in cls.__dataclass_fields__ if k in d}
            for name, kind in _STATUS_FIELD_TYPES.items():
                v = fields.get(name)
                if v is not None and (not isinstance(v, kind) or (kind is int and isinstance(v, bool))):
                    raise TypeError(f"{name} must be {kind.__name__}, got {type(v).__name__}")
            if "stamp" in fields:
                stamp = fields["stamp"]
                if isinstance(stamp, bool) or not isinstance(stamp, int | float) or not math.isfinite(stamp):
                    raise TypeError(f"stamp must be a finite number, got {shorten(repr(stamp), 30)}")
                fields["stamp"] = float(stamp)
            return cls(**fields)
        except (TypeError, KeyError, ValueError, RecursionError, OverflowError) as exc:
            raise ValueError(f"not a task status ({shorten(str(exc), 60)}): {shorten(str(data), 60)!r}") from exc

    def line(self) -> str:
        """One readable terminal line."""
        step = f" {self.step}/{self.steps}" if self.steps else ""
        return f"[#{self.id} {self.state.value}{step}] {self.sentence or self.message}"


@dataclass(frozen=True)
class EngineConfig:
    """Limits of the engine. All times in seconds; every one must be > 0.

    Attributes:
        max_queue: commands waiting (not counting the running one); more are rejected.
        max_text_chars: longer commands are rejected.
        batch_timeout_s: watchdog limit of one command's batch (the seed's 150 s).
        nav_timeout_s: one navigation (``goto``, and the approach of ``place``).
        grasp_timeout_s: one Grasp action.
        place_timeout_s: one Place action.
        query_timeout_s: one object query (including waiting for the service).
        confirm_llm_plans: show LLM plans and run them only after "yes" on /manual_command.
        confirm_timeout_s: how long a plan waits for that answer before it is dropped.
    """

    max_queue: int = 10
    max_text_chars: int = MAX_TEXT_CHARS
    batch_timeout_s: float = 150.0
    nav_timeout_s: float = 60.0
    grasp_timeout_s: float = 30.0
    place_timeout_s: float = 30.0
    query_timeout_s: float = 5.0
    confirm_llm_plans: bool = False
    confirm_timeout_s: float = 30.0

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if name == "confirm_llm_plans":
                if not isinstance(value, bool):
                    raise ConfigError(f"{name} must be true or false, got {value!r}")
                continue
            if not isinstance(value, int | float) or isinstance(value, bool) or not value > 0:
                raise ConfigError(f"{name} must be a number > 0, got {value!r}")


class AbortToken:
    """Set once when the running batch must stop; wakes every waiter registered with it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()  # guards _wakers, reason
        self._event = threading.Event()
        self._wakers: list[threading.Event] = []
        self.reason = ""

    def abort(self, reason: str) -> None:
        with self._lock:
            if not self._event.is_set():
                self.reason = reason
                self._event.set()
            wakers = list(self._wakers)
        for w in wakers:
            w.set()

    def is_set(self) -> bool:
        return self._event.is_set()

    def add_waker(self, event: threading.Event) -> Callable[[], None]:
        """``event`` is set on abort (at once if already aborted); returns the un-register function."""
        with self._lock:
            self._wakers.append(event)
            if self._event.is_set():
                event.set()

        def remove() -> None:
            with self._lock:
                if event in self._wakers:
                    self._wakers.remove(event)

        return remove


class RobotPort(Protocol):
    """What the engine needs from the robot. Blocking calls run in the worker thread only.

    Each blocking call returns normally on success and raises an
    :class:`~decision_maker.errors.ExecutionError` otherwise: ``ActionTimeout`` after it cancelled
    the goal itself, ``ActionCancelled`` when ``abort`` was set, ``ActionFailed`` /
    ``ServerUnavailable`` / ``ObjectNotFound``. ``timeout_s`` > 0 bounds the whole call
    (server wait, goal acceptance and result).
    """

    def navigate(self, pose: Pose2D, timeout_s: float, abort: AbortToken) -> None: ...

    def locate(self, name: str, timeout_s: float, abort: AbortToken) -> Point3: ...

    def grasp(self, name: str, target: Point3, timeout_s: float, abort: AbortToken) -> None: ...

    def place(self, location: NamedLocation, target: Point3, timeout_s: float, abort: AbortToken) -> None: ...

    def cancel_active(self) -> None:
        """Cancel the goal(s) active now; never blocks; callable from any thread."""
        ...

    def emergency_stop(self, reason: str) -> None:
        """Tell the hardware layer to stop (the ROS shell publishes ``/hardware_stop``); never blocks."""
        ...


#: Bytes one code point may take in UTF-8: the raw byte bound is this times ``max_text_chars``.
MAX_UTF8_BYTES_PER_CHAR = 4
#: Answers to a confirmation question (normalised words).
YES_WORDS = frozenset({"yes", "y", "yeah", "yep", "ok", "okay", "confirm", "do it", "go ahead", "sure"})
NO_WORDS = frozenset({"no", "n", "nope", "don't", "dont", "stop", "cancel", "never mind", "abort"})


@dataclass(frozen=True)
class ActionOutcome:
    """What one of the robot's own actions did to an object (for the object memory).

    Attributes:
        event: ``grasped`` | ``grasp_failed`` | ``placed``.
        name: object class ("" when a place's object is unknown).
        robot: where the robot stood (its last reached goal), or None.
        position: where the object was put (``placed``), or None.
        place: the named location it was put at (``placed``), or "".
        detail: the failure's reason (``grasp_failed``).
    """

    event: str
    name: str
    robot: Pose2D | None = None
    position: Point3 | None = None
    place: str = ""
    detail: str = ""


@dataclass
class _Command:
    id: int
    text: str
    received: float  # engine clock at submit


def describe(prim: Primitive) -> str:
    """What a primitive does, for a person ("going to the kitchen")."""
    if isinstance(prim, GoTo):
        if prim.location:
            return f"going to the {prim.location}" if prim.location not in ("home",) else "going home"
        return f"going to ({prim.pose.x:.2f}, {prim.pose.y:.2f})"
    if isinstance(prim, Grasp):
        return f"picking up the {prim.object_name}"
    if prim.location.name == "user":
        return "bringing it to you"
    return f"putting it down at the {prim.location.name}"


class ExecutionEngine:
    """Queue + worker logic. Thread-safe: ``submit``/``cancel`` from callbacks, ``run`` in one thread.

    Args:
        planner: turns text into a plan (called in the worker thread).
        robot: the hardware port.
        config: limits.
        publish: receives every status update (called from the calling thread; must not block).
        context: returns the current planning context (object list, locations).
        clock: monotonic clock (seconds); injectable for tests.
        on_outcome: told what the robot's own grasps and places did to objects (the object memory:
            :class:`ActionOutcome`); called in the worker thread, may block briefly (with a deadline).
    """

    def __init__(self, planner: Planner, robot: RobotPort, config: EngineConfig,
                 publish: Callable[[TaskStatus], None], context: Callable[[], PlanningContext],
                 clock: Callable[[], float] = time.monotonic,
                 on_outcome: Callable[[ActionOutcome], None] | None = None) -> None:
        self._planner = planner
        self._robot = robot
        self.config = config
        self._publish_cb = publish
        self._context = context
        self._clock = clock
        self._ids = itertools.count(1)
        self._cond = threading.Condition()  # guards _queue, _current, _stopping
        self._queue: collections.deque[_Command] = collections.deque()
        self._current: tuple[_Command, AbortToken] | None = None
        self._stopping = False
        self._confirm: tuple[threading.Event, list[bool]] | None = None  # guarded by _cond: a plan awaiting yes/no
        self._held: str | None = None  # worker thread only: what the robot holds after our own grasp/place
        self._on_outcome = on_outcome
        self._pose: Pose2D | None = None  # worker thread only: the robot's last reached goal pose
        self._gate: Callable[[], Hold | None] = lambda: None  # Stage 0: why commands wait (set_gate)

    # --- input side (callbacks; never block) -------------------------------------------------

    def submit(self, raw_text: str) -> TaskStatus:
        """Queue a command; returns its first status (``queued`` or ``rejected``, also published).

        The raw text is bounded first (code points, then UTF-8 bytes) and only then normalised:
        NFKC can turn one code point into 18 (U+FDFA), so a 10 MB message must never reach it.
        A spoken/typed stop ("stop", "cancel", "stop it", "abort", ...) is not queued: it cancels
        at once like ``/cancel_command`` and gets one final status ``succeeded`` (what it stopped).
        """
        raw = str(raw_text)
        limit = self.config.max_text_chars
        size = len(raw) if len(raw) > limit else len(raw.encode("utf-8", "surrogatepass"))
        if len(raw) > limit or size > MAX_UTF8_BYTES_PER_CHAR * limit:
            shown = shorten(sanitize_text(raw[:240]), 200)
            unit = "code points" if len(raw) > limit else "UTF-8 bytes"
            bound = limit if len(raw) > limit else MAX_UTF8_BYTES_PER_CHAR * limit
            with self._cond:
                cid = next(self._ids)
                return self._emit(cid, shown, TaskState.REJECTED,
                                  message=f"command too long ({size} {unit} > {bound}, before normalisation)",
                                  sentence="That command is too long for me; please say it shorter.")
        text = sanitize_text(raw)
        shown = shorten(text, 200)
        if is_stop_command(text):
            with self._cond:
                cid = next(self._ids)
            n = self.cancel(f"spoken stop ({shorten(text, 40)!r})")
            return self._emit(cid, shown, TaskState.SUCCEEDED, message=f"stop: cancelled {n} command(s)",
                              sentence="Stopped." if n else "Nothing to stop.")
        answered = self._answer_now(text, shown)
        if answered is not None:
            return answered
        with self._cond:
            cid = next(self._ids)
            if not text:
                return self._emit(cid, shown, TaskState.REJECTED, message="empty command",
                                  sentence="I heard an empty command; nothing to do.")
            if len(text) > self.config.max_text_chars:
                return self._emit(cid, shown, TaskState.REJECTED,
                                  message=f"command too long ({len(text)} > {self.config.max_text_chars} characters)",
                                  sentence="That command is too long for me; please say it shorter.")
            if self._stopping:
                return self._emit(cid, shown, TaskState.REJECTED, message="decision maker is shutting down",
                                  sentence="I am shutting down and cannot take commands.")
            answer = " ".join(text.lower().strip(" .!?").split())
            if self._confirm is not None and answer in YES_WORDS | NO_WORDS:
                event, box = self._confirm
                box.append(answer in YES_WORDS)
                event.set()
                return self._emit(cid, shown, TaskState.SUCCEEDED, message=f"answer to the pending plan: {answer}",
                                  sentence="Understood.")
            if len(self._queue) >= self.config.max_queue:
                return self._emit(cid, shown, TaskState.REJECTED,
                                  message=f"queue full ({len(self._queue)} commands waiting)",
                                  sentence=f"I am busy with {len(self._queue)} waiting commands; "
                                           "please try again later.")
            hold = self._gate()
            if hold is not None and hold.reject:
                return self._emit(cid, shown, TaskState.REJECTED, message=f"{hold.reason}: not taking commands yet",
                                  sentence=f"{hold.sentence}; please ask me again when I am done.")
            ahead = len(self._queue) + (1 if self._current else 0)
            self._queue.append(_Command(cid, text, self._clock()))
            after = f" ({ahead} ahead of it)." if ahead else "."
            status = self._emit(cid, shown, TaskState.QUEUED, message=f"queued, {ahead} ahead",
                                sentence=f"Okay: {shorten(text, 60)!r}{after}" if hold is None else
                                f"{hold.sentence}; I will do it after.")
            self._cond.notify_all()
            return status

    def _answer_now(self, text: str, shown: str) -> TaskStatus | None:
        """A question ("where is the cup") asked while the robot is busy (or exploring): answered at once.

        Questions move nothing, so they never wait behind a running command. Only exact question
        intents are answered here (a pure look-up in the memory, no model, no waiting); anything
        else, or a question while idle, takes the normal queued path. Returns the final status, or
        None when ``text`` is not answered here.
        """
        with self._cond:
            busy = self._current is not None or bool(self._queue) or self._gate() is not None  # or exploring
        if not busy or not text:
            return None
        try:
            context = self._context()
            answer_question(text, context.world(), context.known_objects, context.locations)
        except Reply as reply:
            with self._cond:
                cid = next(self._ids)
            return self._emit(cid, shown, TaskState.SUCCEEDED, message=f"answer: {reply.sentence}",
                              sentence=reply.sentence)
        except Exception:  # a failing look-up must not lose the command: the queued path reports it
            return None
        return None

    def cancel(self, reason: str = "cancel requested") -> int:
        """Clear the queue and stop the running batch. Returns how many commands it cancelled."""
        with self._cond:
            current = self._current
        if current is not None:  # the robot first, the bookkeeping after
            current[1].abort(reason)
            self._robot.cancel_active()
        return self._drop_queue(reason) + (1 if current else 0)

    def _drop_queue(self, reason: str) -> int:
        """Cancel every waiting command (the running one is not touched). Returns how many."""
        with self._cond:
            dropped = list(self._queue)
            self._queue.clear()
        for cmd in dropped:
            self._emit(cmd.id, shorten(cmd.text, 200), TaskState.CANCELLED, message=f"{reason} (was queued)",
                       sentence="Cancelled before it started.")
        return len(dropped)

    def set_gate(self, gate: Callable[[], Hold | None]) -> None:
        """Stage 0: while ``gate()`` returns a :class:`~decision_maker.execution.stage0.Hold`, queued commands wait
        (or, for a rejecting hold, new ones are refused). Call :meth:`gate_changed` when it may have opened."""
        with self._cond:
            self._gate = gate
            self._cond.notify_all()

    def gate_changed(self) -> None:
        """Wake the worker: the gate may have opened (queued commands run now)."""
        with self._cond:
            self._cond.notify_all()

    def queue_length(self) -> int:
        with self._cond:
            return len(self._queue)

    def current(self) -> tuple[int, float] | None:
        """Id and receive time (engine clock) of the running command, if any."""
        with self._cond:
            return None if self._current is None else (self._current[0].id, self._current[0].received)

    def busy(self) -> bool:
        with self._cond:
            return self._current is not None

    def stop(self) -> None:
        """Make :meth:`run` return (after cancelling everything)."""
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        self.cancel("shutting down")

    # --- worker side ------------------------------------------------------------------------------

    def run(self) -> None:
        """The worker loop: one command at a time until :meth:`stop`."""
        while True:
            with self._cond:
                while (not self._queue or self._gate() is not None) and not self._stopping:
                    self._cond.wait(1.0 if self._queue else None)  # a held queue: the gate's deadline opens it
                if self._stopping:
                    return
                cmd = self._queue.popleft()
                token = AbortToken()
                self._current = (cmd, token)
            try:
                self.run_command(cmd.id, cmd.text, token)
            except Exception as exc:  # a bug in a port must not kill the worker: report and go on
                self._emit(cmd.id, shorten(cmd.text, 200), TaskState.FAILED, message=f"internal error: {exc!r}",
                           sentence="Sorry, something went wrong inside me; I stopped that command.")
            finally:
                with self._cond:
                    self._current = None

    def run_command(self, cid: int, text: str, token: AbortToken) -> TaskState:
        """Plan and execute one command (worker thread). Returns its terminal state."""
        shown = shorten(text, 200)
        self._emit(cid, shown, TaskState.RUNNING, message="planning", sentence="Thinking about it...")
        try:
            context = dataclasses.replace(self._context(), should_stop=token.is_set, held_object=self._held,
                                          robot_pose=self._pose)
            plan = self._planner.plan(text, context)
        except Reply as reply:  # a question, or nothing to do: answered in words, nothing moves
            if reply.kind == "answer":
                return self._final(cid, shown, TaskState.SUCCEEDED, 0, 0, "", f"answer: {reply.sentence}",
                                   reply.sentence)
            return self._final(cid, shown, TaskState.REJECTED, 0, 0, "", f"{reply.kind}: {reply.sentence}",
                               reply.sentence)
        except PlanningError as exc:
            if token.is_set():
                return self._final(cid, shown, TaskState.CANCELLED, 0, 0, "", token.reason, "Cancelled; I stopped.")
            return self._final(cid, shown, TaskState.REJECTED, 0, 0, "", str(exc), f"Sorry, I can't do that: {exc}")
        except Exception as exc:  # a planner bug must not kill the worker
            return self._final(cid, shown, TaskState.REJECTED, 0, 0, "", f"planner error: {exc!r}",
                               "Sorry, my planner failed on that command.")
        notes = "; ".join(f"{k}: {v}" for k, v in plan.slots.items() if k in ("message", "note"))
        if notes:
            self._emit(cid, shown, TaskState.RUNNING, 0, len(plan.primitives), "",
                       f"plan ({plan.scenario}): {plan}; {notes}", f"My plan: {plan}. {plan.slots.get('note', '')}")
        if plan.scenario == "llm" and self.config.confirm_llm_plans and not self._confirmed(cid, shown, plan, token):
            reason = token.reason if token.is_set() else "plan not confirmed"
            return self._final(cid, shown, TaskState.CANCELLED, 0, len(plan.primitives), "", reason,
                               "Okay, I won't do it." if not token.is_set() else "Cancelled; I stopped.")
        return self.execute_plan(cid, shown, plan, token)

    def _confirmed(self, cid: int, shown: str, plan: Plan, token: AbortToken) -> bool:
        """Ask for "yes"/"no" on /manual_command; False on no, timeout or cancel (worker thread)."""
        event, box = threading.Event(), []
        with self._cond:
            self._confirm = (event, box)
        remove = token.add_waker(event)
        self._emit(cid, shown, TaskState.RUNNING, 0, len(plan.primitives), "",
                   f"awaiting confirmation ({self.config.confirm_timeout_s:g} s): {plan}",
                   f"I would: {plan}. Shall I? Say yes or no.")
        try:
            event.wait(self.config.confirm_timeout_s)
        finally:
            remove()
            with self._cond:
                self._confirm = None
        return bool(box) and box[0] and not token.is_set()

    def execute_plan(self, cid: int, shown: str, plan: Plan, token: AbortToken) -> TaskState:
        cfg = self.config
        n = len(plan.primitives)
        start = self._clock()  # the seed's batch start time
        at_location: str | None = None
        for i, prim in enumerate(plan.primitives, 1):
            if token.is_set():
                return self._final(cid, shown, TaskState.CANCELLED, i, n, str(prim), token.reason,
                                   "Cancelled; I stopped.")
            elapsed = self._clock() - start
            if elapsed > cfg.batch_timeout_s:
                msg = f"batch watchdog: {elapsed:.1f} s elapsed > {cfg.batch_timeout_s:g} s before {prim}"
                self._robot.emergency_stop(msg)
                self._drop_queue(f"command #{cid} timed out")  # nothing runs blindly after a timeout
                return self._final(cid, shown, TaskState.TIMED_OUT, i, n, str(prim), msg,
                                   "That took too long, so I stopped.")
            self._emit(cid, shown, TaskState.RUNNING, i, n, str(prim), f"step {i}/{n}: {prim}",
                       f"Step {i} of {n}: {describe(prim)}.")
            try:
                at_location = self._run_primitive(prim, start, token, at_location)
            except ActionCancelled as exc:
                return self._final(cid, shown, TaskState.CANCELLED, i, n, str(prim),
                                   token.reason or str(exc), "Cancelled; I stopped.")
            except ActionTimeout as exc:
                msg = f"{prim}: {exc}"
                if self._clock() - start >= cfg.batch_timeout_s - 0.05:  # the batch deadline bounded the wait
                    msg = f"batch time limit {cfg.batch_timeout_s:g} s reached during {msg}"
                self._robot.cancel_active()
                self._robot.emergency_stop(msg)
                self._drop_queue(f"command #{cid} timed out")  # nothing runs blindly after a timeout
                return self._final(cid, shown, TaskState.TIMED_OUT, i, n, str(prim), msg,
                                   f"I stopped: {describe(prim)} took too long.")
            except ExecutionError as exc:
                return self._final(cid, shown, TaskState.FAILED, i, n, str(prim), f"{prim}: {exc}",
                                   f"Sorry, {describe(prim)} failed: {exc}")
        return self._final(cid, shown, TaskState.SUCCEEDED, n, n, "", f"done: {plan}", "Done.")

    def _budget(self, start: float, own: float, what: str) -> float:
        left = self.config.batch_timeout_s - (self._clock() - start)
        if left <= 0:
            raise ActionTimeout(f"batch time limit {self.config.batch_timeout_s:g} s reached before {what}")
        return min(own, left)

    def _run_primitive(self, prim: Primitive, start: float, token: AbortToken, at: str | None) -> str | None:
        cfg, robot = self.config, self._robot
        if isinstance(prim, GoTo):
            self._pose = None  # somewhere on the way
            robot.navigate(prim.pose, self._budget(start, cfg.nav_timeout_s, "navigation"), token)
            self._pose = prim.pose
            return prim.location
        if isinstance(prim, Grasp):
            target = robot.locate(prim.object_name, self._budget(start, cfg.query_timeout_s, "object query"), token)
            try:
                robot.grasp(prim.object_name, target, self._budget(start, cfg.grasp_timeout_s, "grasp"), token)
            except ActionFailed as exc:
                self._report(ActionOutcome("grasp_failed", prim.object_name, self._pose, detail=str(exc)))
                raise
            self._held = prim.object_name
            self._report(ActionOutcome("grasped", prim.object_name, self._pose))
            return at
        if isinstance(prim, Place):
            loc = prim.location
            if at != loc.name:  # the placement sequence: approach the location first
                self._pose = None
                robot.navigate(loc.pose, self._budget(start, cfg.nav_timeout_s, "approach"), token)
                self._pose = loc.pose
            if token.is_set():
                raise ActionCancelled(token.reason)
            robot.place(loc, loc.drop_point(), self._budget(start, cfg.place_timeout_s, "place"), token)
            held, self._held = self._held, None
            self._report(ActionOutcome("placed", held or "", self._pose, loc.drop_point(), loc.name))
            return loc.name
        raise ActionFailed(f"unsupported primitive {prim!r}")

    def _report(self, outcome: ActionOutcome) -> None:
        """Tell the object memory (never fails the command: a report that fails is only printed)."""
        if self._on_outcome is None:
            return
        try:
            self._on_outcome(outcome)
        except Exception as exc:  # the memory is advisory: the action itself succeeded/failed already
            print(f"decision_maker: object memory report failed: {exc!r}", flush=True)

    # --- status ---------------------------------------------------------------------------------

    def _final(self, cid: int, shown: str, state: TaskState, step: int, steps: int, prim: str, message: str,
               sentence: str) -> TaskState:
        self._emit(cid, shown, state, step, steps, prim, message, sentence)
        return state

    def _emit(self, cid: int, text: str, state: TaskState, step: int = 0, steps: int = 0, primitive: str = "",
              message: str = "", sentence: str = "") -> TaskStatus:
        status = TaskStatus(cid, text, state, step, steps, primitive, message, sentence, time.time())
        self._publish_cb(status)
        return status
