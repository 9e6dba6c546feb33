"""Planners: the seam between "what was said" and "what the executor runs" (no ROS).

The executor only ever sees a :class:`~decision_maker.command_types.Plan` (validated primitives).
A planner turns text plus world context into one. Two exist here:

* :class:`RegistryPlanner` — the deterministic scenario library (phrase lookup), plus direct
  primitive syntax for operators and tests (``"goto:kitchen; grasp:cup"``).
* anything registered with :func:`register_planner` — e.g. the LLM planner (its own issue):
  it implements :class:`Planner` and validates its output with
  :func:`~decision_maker.command_types.parse_plan`.

The decision maker picks one by its ``planner`` parameter via :func:`make_planner`.
Planners are called from the execution thread, one command at a time; a slow planner delays
only the queue, never ``/cancel_command``.
"""

from __future__ import annotations

import importlib
import re
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

from decision_maker.command_types import NamedLocation, Plan, Pose2D, parse_plan
from decision_maker.errors import ConfigError, InvalidPrimitive, NoMatchingScenario, PlanningError, Reply
from decision_maker.memory.world import Clarification, answer_clarification, fetch_plan
from decision_maker.scenario_library import (
    SCENARIO_REGISTRY,
    ScenarioFn,
    World,
    match_scenario,
    normalize_utterance,
)
from object_query.memory import Belief

_PRIMITIVE_START = re.compile(r"^\s*(goto|grasp|place)\s*:", re.IGNORECASE)


@dataclass(frozen=True)
class PlanningContext:
    """What a planner may know about the world when planning.

    Attributes:
        known_objects: object names in the object database (``/object_list``), lower case.
        locations: the named locations (name → :class:`NamedLocation`).
        object_positions: last known object centres from ``/object_list`` (map frame, metres).
        should_stop: True once the command was cancelled; a slow planner should poll it and raise
            PlanningError("cancelled") early (the engine reports the command cancelled either way).
        held_object: what the robot holds after its own last grasp/place (None = nothing known).
        memory: the object memory's beliefs (``/object_memory``): where each instance is now.
        robot_pose: where the robot is (its last reached goal); None = unknown.
        aliases: other names of known objects → the class ("mug" → "cup"; from the synonyms file).
    """

    known_objects: frozenset[str] = frozenset()
    locations: Mapping[str, NamedLocation] = field(default_factory=dict)
    object_positions: Mapping[str, tuple[float, float, float]] = field(default_factory=dict)
    should_stop: Callable[[], bool] = lambda: False
    held_object: str | None = None
    memory: tuple[Belief, ...] = ()
    robot_pose: Pose2D | None = None
    aliases: Mapping[str, str] = field(default_factory=dict)

    def world(self) -> World:
        """The scenario library's view of this context."""
        return World(self.memory, self.locations, self.robot_pose, self.held_object, self.aliases)


@runtime_checkable
class Planner(Protocol):
    """Text → validated plan. Implementations must be thread-safe for one caller at a time."""

    name: str

    def plan(self, text: str, context: PlanningContext) -> Plan:
        """Plan a command.

        Args:
            text: the sanitised command text (non-empty, at most MAX_TEXT_CHARS characters).
            context: world knowledge at planning time.

        Returns:
            A plan of validated primitives.

        Raises:
            PlanningError: (or a subclass: NoMatchingScenario, MissingSlot, InvalidPrimitive) with
                a message for a person; nothing is executed.
        """
        ...


#: Words that accept a "did you mean ...?" suggestion / decline a pending question.
_YES = frozenset({"yes", "yeah", "yep", "sure", "ok", "okay", "correct", "right", "exactly"})
_NO = frozenset({"no", "nope", "neither", "none", "never", "mind", "forget", "it", "not", "that", "thanks"})


class RegistryPlanner:
    """The seed's deterministic planner: scenario phrase lookup, or literal primitives.

    Beyond the phrases, it keeps one pending question for the next utterance (worker thread only):
    after "which cup: the one at the kitchen counter or the one on the table?", "the one on the
    table" fetches that cup; after "did you mean 'give me the bottle'?", "yes" runs it. Any other
    utterance drops the question. A question expires after ``pending_s`` seconds.

    Args:
        registry: phrase → scenario function (default: the scenario library's registry).
        allow_primitives: accept literal primitive commands (``goto:1,2,0; grasp:cup``, separated
            by ``;`` or ``,`` between primitives).
        pending_s: how long a clarification / suggestion waits for its answer (s, > 0).
        clock: monotonic clock (injectable for tests).
    """

    name = "registry"

    def __init__(self, registry: dict[str, ScenarioFn] | None = None, allow_primitives: bool = True,
                 pending_s: float = 120.0, clock: Callable[[], float] = time.monotonic) -> None:
        if not pending_s > 0:
            raise ConfigError(f"pending_s must be > 0, got {pending_s!r}")
        self._registry = SCENARIO_REGISTRY if registry is None else registry
        self._allow_primitives = allow_primitives
        self._pending_s = pending_s
        self._clock = clock
        self._pending: tuple[float, object] | None = None  # (deadline, Clarification | suggested text)

    def plan(self, text: str, context: PlanningContext) -> Plan:
        pending, self._pending = self._pending, None
        if pending is not None and self._clock() <= pending[0]:
            answered = self._answer_pending(pending[1], text, context)
            if answered is not None:
                return answered
        try:
            return self._plan(text, context)
        except Reply as reply:
            if reply.pending is not None:
                self._pending = (self._clock() + self._pending_s, reply.pending)
            raise

    def _answer_pending(self, pending: object, text: str, context: PlanningContext) -> Plan | None:
        words = normalize_utterance(text)
        if words and set(words) <= _NO and set(words) & {"no", "nope", "neither", "none", "never"}:
            raise Reply("Okay, I won't do anything.")
        if isinstance(pending, str):  # a "did you mean" suggestion
            if words and set(words) <= _YES | {"please", "do", "it", "that"} and set(words) & _YES:
                return self._plan(pending, context)
            return None
        if isinstance(pending, Clarification):
            chosen = answer_clarification(pending, words)
            if chosen is None:
                return None
            items = fetch_plan(chosen, pending.destination, context.locations, context.robot_pose)
            return self._parse(items, context, f"{pending.request} ({chosen.id})",
                               {"item": chosen.name, "note": f"the {chosen.name} {dict(pending.options)[chosen]}"})
        return None

    def _plan(self, text: str, context: PlanningContext) -> Plan:
        if self._allow_primitives and _PRIMITIVE_START.match(text):
            return parse_plan(split_primitives(text), context.locations, scenario="primitives")
        match = match_scenario(text, context.known_objects, context.locations.keys(), self._registry,
                               world=context.world())
        items = match.function(match.utterance)
        slots: dict[str, str] = {}
        for item in items:
            if item.startswith("grasp:"):
                slots["item"] = item.partition(":")[2]
        item = slots.get("item")
        if match.said != match.phrase and item and item not in context.known_objects:
            # another wording ("hand me", or a fuzzy match) plus an object nobody knows: too weak to act
            # on (a planner tier behind this one, e.g. the LLM, may understand it)
            known = ", ".join(sorted(context.known_objects)) or "none"
            raise NoMatchingScenario(f"I don't know how to do that: {item!r} is no object I know (known: {known})")
        notes = list(match.utterance.notes)
        if match.score < 1.0:
            notes.insert(0, f"I read {match.said!r} as {match.phrase!r}")
        if notes:
            slots["note"] = "; ".join(notes)
        return self._parse(items, context, match.phrase, slots)

    @staticmethod
    def _parse(items: list[str], context: PlanningContext, scenario: str, slots: dict[str, str]) -> Plan:
        try:
            return parse_plan(items, context.locations, scenario=scenario, slots=slots)
        except InvalidPrimitive as exc:
            raise PlanningError(f"scenario {scenario!r}: {exc}") from exc


def split_primitives(text: str) -> list[str]:
    """``"goto:1,2,0; grasp:cup, place:user"`` → ``["goto:1,2,0", "grasp:cup", "place:user"]``.

    ``;`` and newlines always separate; a comma separates only when a primitive verb follows it
    (``goto:x,y,theta`` keeps its commas).
    """
    parts = re.split(r"[;\n]|,(?=\s*(?:goto|grasp|place)\s*:)", text, flags=re.IGNORECASE)
    return [p.strip() for p in parts if p.strip()]


PlannerFactory = Callable[..., Planner]
_PLANNERS: dict[str, PlannerFactory] = {"registry": RegistryPlanner}


def register_planner(name: str, factory: PlannerFactory) -> None:
    """Make a planner selectable by the decision maker's ``planner`` parameter."""
    _PLANNERS[name] = factory


def make_planner(name: str, **options: Any) -> Planner:
    """The planner registered as ``name``, built with ``options``.

    A name not registered yet is looked up as module ``decision_maker.planning.<name>_planner`` (then
    ``decision_maker.<name>_planner``), which registers itself on import (e.g. ``planning/llm_planner.py`` ending in
    ``register_planner("llm", LlmPlanner)``).

    Raises:
        ConfigError: unknown planner name, or its factory rejected the options.
    """
    if name not in _PLANNERS and re.fullmatch(r"[a-z][a-z0-9_]*", name):
        for module in (f"decision_maker.planning.{name}_planner", f"decision_maker.{name}_planner"):
            try:
                importlib.import_module(module)
                break
            except ModuleNotFoundError:
                pass
    if name not in _PLANNERS:
        raise ConfigError(f"unknown planner {name!r}; known: {', '.join(sorted(_PLANNERS))}")
    try:
        return _PLANNERS[name](**options)
    except TypeError as exc:
        raise ConfigError(f"planner {name!r}: bad options {sorted(options)}: {exc}") from exc
