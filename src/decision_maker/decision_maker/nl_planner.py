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
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

from decision_maker.command_types import NamedLocation, Plan, parse_plan
from decision_maker.errors import ConfigError, InvalidPrimitive, PlanningError
from decision_maker.scenario_library import SCENARIO_REGISTRY, ScenarioFn, match_scenario

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
    """

    known_objects: frozenset[str] = frozenset()
    locations: Mapping[str, NamedLocation] = field(default_factory=dict)
    object_positions: Mapping[str, tuple[float, float, float]] = field(default_factory=dict)
    should_stop: Callable[[], bool] = lambda: False
    held_object: str | None = None


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


class RegistryPlanner:
    """The seed's deterministic planner: scenario phrase lookup, or literal primitives.

    Args:
        registry: phrase → scenario function (default: the scenario library's registry).
        allow_primitives: accept literal primitive commands (``goto:1,2,0; grasp:cup``, separated
            by ``;`` or ``,`` between primitives).
    """

    name = "registry"

    def __init__(self, registry: dict[str, ScenarioFn] | None = None, allow_primitives: bool = True) -> None:
        self._registry = SCENARIO_REGISTRY if registry is None else registry
        self._allow_primitives = allow_primitives

    def plan(self, text: str, context: PlanningContext) -> Plan:
        if self._allow_primitives and _PRIMITIVE_START.match(text):
            return parse_plan(split_primitives(text), context.locations, scenario="primitives")
        match = match_scenario(text, context.known_objects, context.locations.keys(), self._registry)
        items = match.function(match.utterance)
        slots: dict[str, str] = {}
        for item in items:
            if item.startswith("grasp:"):
                slots["item"] = item.partition(":")[2]
        try:
            return parse_plan(items, context.locations, scenario=match.phrase, slots=slots)
        except InvalidPrimitive as exc:
            raise PlanningError(f"scenario {match.phrase!r}: {exc}") from exc


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

    A name not registered yet is looked up as module ``decision_maker.<name>_planner``, which
    registers itself on import (e.g. ``llm_planner.py`` ending in ``register_planner("llm", LlmPlanner)``).

    Raises:
        ConfigError: unknown planner name, or its factory rejected the options.
    """
    if name not in _PLANNERS and re.fullmatch(r"[a-z][a-z0-9_]*", name):
        try:
            importlib.import_module(f"decision_maker.{name}_planner")
        except ModuleNotFoundError:
            pass
    if name not in _PLANNERS:
        raise ConfigError(f"unknown planner {name!r}; known: {', '.join(sorted(_PLANNERS))}")
    try:
        return _PLANNERS[name](**options)
    except TypeError as exc:
        raise ConfigError(f"planner {name!r}: bad options {sorted(options)}: {exc}") from exc
