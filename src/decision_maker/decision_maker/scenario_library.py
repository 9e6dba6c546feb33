"""The scenario library: what a person says → a list of primitive strings (no ROS).

The registry pattern of the seed: a phrase maps to a small function that returns primitive
strings. Adding a scenario is one function plus one registry line::

    def water_plants(u: Utterance) -> list[str]:
        return ["goto:kitchen", "grasp:watering can", "place:window"]

    SCENARIO_REGISTRY["water the plants"] = water_plants

Matching (:func:`match_scenario`) is case- and punctuation-insensitive, phrases match whole
words, and the longest matching phrase wins ("go to the kitchen" → ``go to``, "go home" →
``go home``). Slots are filled from the words of the utterance against what the robot knows:
"give me the cup please" → ``item=cup`` when ``cup`` is in ``/object_list``.
"""

from __future__ import annotations

import unicodedata
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from decision_maker.errors import MissingSlot, NoMatchingScenario

#: Words that never name an object or a place ("give me the cup please" → cup).
STOP_WORDS = frozenset(
    "a an the my your our some this that these those please to me us for of from in on at with and now "
    "quickly thanks thank you can could would will kindly go get".split()
)


def normalize_utterance(text: str) -> tuple[str, ...]:
    """Words of ``text``: NFKC, lower case, punctuation and symbols as separators."""
    text = unicodedata.normalize("NFKC", str(text)).lower()
    return tuple("".join(ch if ch.isalnum() else " " for ch in text).split())


@dataclass(frozen=True)
class Utterance:
    """A matched command, handed to the scenario function.

    Attributes:
        words: all words of the command (normalised).
        rest: the words after the matched phrase.
        known_objects: object names the robot knows (from ``/object_list``; may be empty).
        locations: names of the named locations.
    """

    words: tuple[str, ...]
    rest: tuple[str, ...]
    known_objects: frozenset[str]
    locations: frozenset[str]

    def object_slot(self, slot: str = "item") -> str:
        """The object named after the phrase (longest known name; plural 's' forgiven).

        Falls back to the remaining non-filler words when no known object is named (the object
        query then says whether it exists).

        Raises:
            MissingSlot: nothing names an object.
        """
        found = _longest_name(self.rest, self.known_objects) or _longest_name(self.words, self.known_objects)
        if found:
            return found
        words = [w for w in self.rest if w not in STOP_WORDS]
        if not words:
            raise MissingSlot(f"which object? the {slot} is missing (e.g. 'give me the bottle')")
        return " ".join(words)

    def location_slot(self, slot: str = "location") -> str:
        """The named location after the phrase.

        Raises:
            MissingSlot: no known location is named.
        """
        found = _longest_name(self.rest, self.locations)
        if found:
            return found
        shown = " ".join(w for w in self.rest if w not in STOP_WORDS) or "nothing"
        raise MissingSlot(f"unknown {slot} {shown!r}; known: {', '.join(sorted(self.locations))}")


def _longest_name(words: tuple[str, ...], names: Iterable[str]) -> str | None:
    best: str | None = None
    for name in names:
        parts = tuple(name.split())
        if not parts:
            continue
        n = len(parts)
        for i in range(len(words) - n + 1):
            window = words[i : i + n]
            plural = window[:-1] + (window[-1][:-1],) if window[-1].endswith("s") else None
            if (window == parts or plural == parts) and (best is None or len(name) > len(best)):
                best = name
    return best


ScenarioFn = Callable[[Utterance], list[str]]


# --- scenarios: one small function each -------------------------------------------------------


def give_item(u: Utterance) -> list[str]:
    """Fetch an object from the kitchen and hand it to the user."""
    return ["goto:kitchen", f"grasp:{u.object_slot('item')}", "place:user"]


def park_robot(u: Utterance) -> list[str]:
    """Drive to the home (parking) position."""
    return ["goto:home"]


def clean_table(u: Utterance) -> list[str]:
    """Take the trash from the table to the bin."""
    return ["goto:table", "grasp:trash", "place:bin"]


def go_to(u: Utterance) -> list[str]:
    """Drive to a named location."""
    return [f"goto:{u.location_slot()}"]


SCENARIO_REGISTRY: dict[str, ScenarioFn] = {
    "give me": give_item,
    "bring me": give_item,
    "go home": park_robot,
    "clean table": clean_table,
    "clean the table": clean_table,
    "go to": go_to,
}


@dataclass(frozen=True)
class ScenarioMatch:
    phrase: str
    function: ScenarioFn
    utterance: Utterance


def match_scenario(text: str, known_objects: Iterable[str] = (), locations: Iterable[str] = (),
                   registry: dict[str, ScenarioFn] | None = None) -> ScenarioMatch:
    """Find the scenario a command asks for.

    Args:
        text: the command as said/typed.
        known_objects: object names (lower case) for slot filling.
        locations: named-location names for slot filling.
        registry: phrase → function (default :data:`SCENARIO_REGISTRY`).

    Returns:
        The longest phrase whose words occur contiguously in the command (earliest on a tie).

    Raises:
        NoMatchingScenario: no phrase matches; the message lists the phrases.
    """
    registry = SCENARIO_REGISTRY if registry is None else registry
    words = normalize_utterance(text)
    best: tuple[int, int, str, int] | None = None  # (-len, position, phrase, end)
    for phrase in registry:
        parts = normalize_utterance(phrase)
        n = len(parts)
        for i in range(len(words) - n + 1):
            if n and words[i : i + n] == parts:
                key = (-len(" ".join(parts)), i, phrase, i + n)
                if best is None or key[:2] < best[:2]:
                    best = key
                break
    if best is None:
        raise NoMatchingScenario(f"I don't know how to do that; try one of: {', '.join(sorted(registry))}")
    _, _, phrase, end = best
    utt = Utterance(words, words[end:], frozenset(n.lower() for n in known_objects),
                    frozenset(n.lower() for n in locations))
    return ScenarioMatch(phrase, registry[phrase], utt)
