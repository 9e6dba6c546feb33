"""Typed errors of the decision maker (planning, execution, simulated hardware)."""


class DecisionMakerError(Exception):
    """Base class of the decision maker's errors."""


class ConfigError(DecisionMakerError):
    """A configuration file or parameter is malformed (locations file, objects, timeouts)."""


class BadKeyError(DecisionMakerError, ValueError):
    """A command's idempotency key is malformed (too long); the command is not run."""


class PlanningError(DecisionMakerError):
    """A command could not be turned into a plan; the message says why, for a person."""


class NoMatchingScenario(PlanningError):
    """No scenario phrase matches the command."""


class MissingSlot(PlanningError):
    """A scenario matched but a slot (e.g. which object) could not be filled."""


class InvalidPrimitive(PlanningError):
    """A primitive string is malformed or names something unknown (the message gives the reason)."""


class ExecutionError(DecisionMakerError):
    """A primitive did not complete; subclasses say how."""


class ActionFailed(ExecutionError):
    """The action server reported failure (aborted / unsuccessful result) or refused the goal."""


class ActionTimeout(ExecutionError):
    """An action (or the object query) did not finish within its deadline."""


class ActionCancelled(ExecutionError):
    """The primitive was cancelled (``/cancel_command`` or shutdown)."""


class ServerUnavailable(ExecutionError):
    """An action server or the object query service is not available before the deadline."""


class ServerLost(ServerUnavailable):
    """A server that was there left the ROS graph while a call waited on it (killed, crashed)."""


class ObjectNotFound(ExecutionError):
    """The object database does not know the object."""


class SimError(DecisionMakerError):
    """The simulated world refuses an operation (out of reach, gripper full, nothing held...)."""


class Reply(DecisionMakerError):
    """Not a failure: the command is answered in words and nothing moves.

    Raised by a planner for a question ("where is the bottle"), a request already fulfilled ("give
    me the bottle" while the user has it), a clarification question ("which cup: ...?") or a
    "did you mean ...?". The engine reports it on ``/task_status``: ``kind == "answer"`` as
    ``succeeded``, ``"clarify"`` and ``"did_you_mean"`` as ``rejected`` (nothing was done).

    Attributes:
        sentence: what to tell the person.
        kind: ``answer`` | ``clarify`` | ``did_you_mean``.
        pending: what the planner keeps to understand the next utterance (the clarification
            question's candidates, the suggested command), or None.
    """

    def __init__(self, sentence: str, kind: str = "answer", pending: object | None = None) -> None:
        super().__init__(sentence)
        self.sentence = sentence
        self.kind = kind
        self.pending = pending
