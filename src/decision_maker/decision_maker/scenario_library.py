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

The intent grammar: people do not say the registry's phrases verbatim.

* :data:`PHRASE_SYNONYMS` — other wordings of a phrase ("go back home" → ``go home``, "fetch the
  bottle please" → ``give me``, "could you bring me the cup" → ``bring me``). Fillers ("could you",
  "please", "robot") need no rule: phrases match anywhere in the utterance and slot filling skips
  :data:`STOP_WORDS`.
* Question intents (:data:`QUESTION_REGISTRY`: "where is X", "where did you see my X", "what do you
  see", "what can you do", "what are you holding") are answered from the object memory with a
  :class:`~decision_maker.errors.Reply`; nothing moves.
* No phrase matches: the utterance is compared with every phrase word by word (:func:`fuzzy_match`).
  A score >= ``ACCEPT_SCORE`` is taken as that phrase (a mis-heard word: "giv me the bottle");
  ``SUGGEST_SCORE`` <= score < ``ACCEPT_SCORE`` only asks "did you mean ...?" (a "yes" next runs
  it); lower is "I don't know how to do that". Nothing below ``ACCEPT_SCORE`` ever moves the robot.

Scenarios that fetch an object plan from the object memory (:mod:`decision_maker.memory.world`):
"give me the trash" goes to where the trash is now, not to a fixed room.
"""

from __future__ import annotations

import difflib
import unicodedata
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field

from decision_maker.command_types import NamedLocation, Pose2D
from decision_maker.errors import MissingSlot, NoMatchingScenario, Reply
from decision_maker.memory.world import (
    choose_instance,
    fetch_plan,
    holding_answer,
    instances_of,
    inventory_answer,
    where_answer,
)
from object_query.memory import Belief

#: Words that never name an object or a place ("give me the cup please" → cup).
STOP_WORDS = frozenset(
    "a an the my your our some this that these those please to me us for of from in on at with and now "
    "quickly thanks thank you can could would will kindly go get robot hey hi okay ok just i d like want "
    "need".split()
)


def normalize_utterance(text: str) -> tuple[str, ...]:
    """Words of ``text``: NFKC, lower case, punctuation and symbols as separators."""
    text = unicodedata.normalize("NFKC", str(text)).lower()
    return tuple("".join(ch if ch.isalnum() else " " for ch in text).split())


@dataclass(frozen=True)
class World:
    """What a scenario may know beyond names: the object memory, places and the robot.

    Attributes:
        memory: the object memory's beliefs (``/object_memory``); empty = no memory.
        places: named locations (name → pose and drop point).
        robot: where the robot is (its last reached pose); None = unknown.
        held: what the robot holds after its own last grasp (None = nothing known).
        aliases: other names of known objects → the class ("mug" → "cup", from the synonyms).
    """

    memory: tuple[Belief, ...] = ()
    places: Mapping[str, NamedLocation] = field(default_factory=dict)
    robot: Pose2D | None = None
    held: str | None = None
    aliases: Mapping[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class Utterance:
    """A matched command, handed to the scenario function.

    Attributes:
        words: all words of the command (normalised).
        rest: the words after the matched phrase.
        known_objects: object names the robot knows (from ``/object_list``; may be empty).
        locations: names of the named locations.
        world: memory, places and robot pose (the default: nothing known).
        notes: a scenario may append sentences for the person (shown with the plan).
    """

    words: tuple[str, ...]
    rest: tuple[str, ...]
    known_objects: frozenset[str]
    locations: frozenset[str]
    world: World = field(default_factory=World)
    notes: list[str] = field(default_factory=list)

    def object_slot(self, slot: str = "item") -> str:
        """The object named after the phrase (longest known name; plural 's' forgiven).

        Falls back to the remaining non-filler words when no known object is named (the object
        query then says whether it exists).

        Raises:
            MissingSlot: nothing names an object.
        """
        names = self.known_objects | set(self.world.aliases)
        found = _longest_name(self.rest, names) or _longest_name(self.words, names)
        if found:
            return self.world.aliases.get(found, found)  # "mug" -> cup
        words = [w for w in self.rest if w not in STOP_WORDS]
        if not words:
            raise MissingSlot(f"which object? the {slot} is missing (e.g. 'give me the bottle')")
        said = " ".join(words)
        close = difflib.get_close_matches(said, sorted(self.known_objects), n=1, cutoff=0.8)
        return close[0] if close else said  # "botle" -> bottle

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
    """Fetch an object from where it is now and hand it to the user.

    Without a belief about the object in the memory: the seed's plan (from the kitchen).
    """
    name = u.object_slot("item")
    w = u.world
    if w.held == name or any(b.name == name and b.state == "held" for b in w.memory):
        return ["place:user"]
    if "user" not in w.places:
        return ["goto:kitchen", f"grasp:{name}", "place:user"]
    choice = choose_instance(w.memory, name, w.robot, w.places, " ".join(u.words), "user")
    if choice is None:
        return ["goto:kitchen", f"grasp:{name}", "place:user"]
    if choice.note:
        u.notes.append(choice.note)
    return fetch_plan(choice.belief, "user", w.places, w.robot)


def park_robot(u: Utterance) -> list[str]:
    """Drive to the home (parking) position."""
    return ["goto:home"]


def clean_table(u: Utterance) -> list[str]:
    """Take the trash from the table to the bin (the trash the memory places at the table)."""
    w = u.world
    trash = instances_of(w.memory, "trash")
    if not trash or "table" not in w.places or "bin" not in w.places:
        return ["goto:table", "grasp:trash", "place:bin"]
    table = w.places["table"].drop_point()
    on_table = [b for b in trash if b.place != "bin" and b.state != "held"
                and b.distance_xy((table.x, table.y)) <= 1.0]
    if not on_table:
        elsewhere = [b for b in trash if b.place != "bin"]
        if elsewhere:
            raise Reply("The table is already clean: there is no trash on it (" + where_answer(
                w.memory, "trash", w.places).rstrip(".") + ").")
        raise Reply("The table is already clean: the trash is in the bin.")
    choice = choose_instance(on_table, "trash", w.robot, w.places, " ".join(u.words), "bin", margin=0.0)
    assert choice is not None  # on_table is not empty
    if choice.note:
        u.notes.append(choice.note)
    return fetch_plan(choice.belief, "bin", w.places, w.robot)


def go_to(u: Utterance) -> list[str]:
    """Drive to a named location."""
    return [f"goto:{u.location_slot()}"]


# --- questions: answered from the memory, nothing moves ---------------------------------------


def where_is(u: Utterance) -> list[str]:
    """Where is an object now (from the memory)?"""
    raise Reply(where_answer(u.world.memory, u.object_slot("object"), u.world.places))


def what_do_you_see(u: Utterance) -> list[str]:
    """Every object the memory knows, with where it is."""
    raise Reply(inventory_answer(u.world.memory, u.world.places))


def what_can_you_do(u: Utterance) -> list[str]:
    """What the robot understands."""
    places = ", ".join(sorted(u.world.places)) or "the named places"
    raise Reply("I can bring you things ('give me the cup'), clean the table, go home, go to a place "
                f"({places}), and answer 'where is the bottle', 'what do you see' and 'what are you holding'. "
                "Say 'stop' to cancel what I am doing.")


def what_are_you_holding(u: Utterance) -> list[str]:
    """What the gripper holds."""
    raise Reply(holding_answer(u.world.memory, u.world.held))


SCENARIO_REGISTRY: dict[str, ScenarioFn] = {
    "give me": give_item,
    "bring me": give_item,
    "go home": park_robot,
    "clean table": clean_table,
    "clean the table": clean_table,
    "go to": go_to,
}

#: Question intents: phrase → function raising a :class:`~decision_maker.errors.Reply`.
QUESTION_REGISTRY: dict[str, ScenarioFn] = {
    "where is": where_is,
    "what do you see": what_do_you_see,
    "what can you do": what_can_you_do,
    "what are you holding": what_are_you_holding,
}

#: Other wordings of a phrase of :data:`SCENARIO_REGISTRY` / :data:`QUESTION_REGISTRY`.
PHRASE_SYNONYMS: dict[str, tuple[str, ...]] = {
    "give me": ("gimme", "fetch me", "fetch", "get me", "hand me", "pass me", "grab me", "can i have", "could i have",
                "may i have", "i want", "i need", "i would like"),
    "go home": ("go back home", "return home", "head home", "go home now", "back home", "go to home",
                "go back to base", "go to base", "go to your dock", "dock", "park"),
    "clean table": ("clear the table", "clean up the table", "tidy the table", "tidy up the table",
                    "clear table", "tidy table", "clean up the trash", "throw away the trash", "take out the trash"),
    "go to": ("drive to", "move to", "head to", "navigate to", "go back to", "come to"),
    "where is": ("where s", "where are", "where did you see", "where did you put", "where did you leave",
                 "where can i find", "where could i find", "do you know where", "have you seen", "where was"),
    "what do you see": ("what can you see", "what objects do you know", "what do you know about", "what is around",
                        "what s around", "what objects are there", "what is in the room", "list objects",
                        "list the objects", "what have you seen"),
    "what can you do": ("what do you do", "what are your commands", "what commands", "how do i use you",
                        "what do you understand", "what can you help with"),
    "what are you holding": ("what are you carrying", "what do you hold", "what do you have",
                             "what s in your hand", "what is in your hand", "what s in your gripper"),
}
#: Fuzzy scores (0..1): at least ACCEPT_SCORE is taken as the phrase; SUGGEST_SCORE..ACCEPT_SCORE
#: only asks "did you mean ...?"; lower is not understood.
ACCEPT_SCORE = 0.86
SUGGEST_SCORE = 0.6


def answer_question(text: str, world: World, known_objects: Iterable[str] = (),
                    locations: Iterable[str] = ()) -> None:
    """Answer ``text`` if it is a question intent ("where is the cup"); return None otherwise.

    For planners that do not use the registry (the LLM-only tier): questions are answered from the
    memory here, without a model.

    Raises:
        Reply: the answer (kind ``answer``).
    """
    try:
        match = match_scenario(text, known_objects, locations, registry={}, world=world)
    except (NoMatchingScenario, Reply):
        return None
    if match.score == 1.0:
        match.function(match.utterance)


@dataclass(frozen=True)
class ScenarioMatch:
    """A matched command.

    Attributes:
        phrase: the registry phrase (canonical, also when a synonym or a fuzzy match was said).
        function: its scenario function.
        utterance: the words and slots.
        said: the wording that matched (a synonym, or the fuzzy-matched words).
        score: 1.0 for an exact phrase or synonym, the fuzzy score otherwise.
    """

    phrase: str
    function: ScenarioFn
    utterance: Utterance
    said: str = ""
    score: float = 1.0


def _phrase_table(registry: Mapping[str, ScenarioFn], questions: bool) -> dict[str, str]:
    """Wording → canonical phrase, for the phrases of ``registry`` (+ questions) and their synonyms."""
    table = {p: p for p in registry}
    if questions:
        table.update({p: p for p in QUESTION_REGISTRY if p not in table})
    for canonical, alts in PHRASE_SYNONYMS.items():
        if canonical in table:
            for alt in alts:
                table.setdefault(alt, canonical)
    return table


def fuzzy_match(words: tuple[str, ...], wordings: Iterable[str]) -> tuple[float, str, int, int]:
    """The wording most similar to a window of ``words``, word by word.

    A window of as many words as the wording scores the mean of its words' character similarity
    (``difflib`` ratio) with the wording's words ("giv me" ~ "give me" = 0.93); a window whose
    first word scores below 0.75 or any word below 0.5 does not compare ("what is" ≁ "where is").

    Returns:
        ``(score, wording, start, end)``: score in [0, 1] (0 when nothing compares), the window.
    """
    best = (0.0, "", 0, 0)
    for wording in wordings:
        parts = normalize_utterance(wording)
        n = len(parts)
        for i in range(len(words) - n + 1):
            window = words[i : i + n]
            ratios = [difflib.SequenceMatcher(None, a, b).ratio() for a, b in zip(window, parts, strict=True)]
            if ratios[0] < 0.75 or min(ratios) < 0.5:  # the verb must be close, and no word far off
                continue
            score = sum(ratios) / n
            if score > best[0] + 1e-9:
                best = (score, wording, i, i + n)
    return best


def match_scenario(text: str, known_objects: Iterable[str] = (), locations: Iterable[str] = (),
                   registry: dict[str, ScenarioFn] | None = None, world: World | None = None,
                   questions: bool = True) -> ScenarioMatch:
    """Find the scenario a command asks for.

    Args:
        text: the command as said/typed.
        known_objects: object names (lower case) for slot filling.
        locations: named-location names for slot filling.
        registry: phrase → function (default :data:`SCENARIO_REGISTRY`).
        world: memory, places and robot pose for the scenario functions (default: nothing known).
        questions: also match :data:`QUESTION_REGISTRY` (and every synonym of :data:`PHRASE_SYNONYMS`).

    Returns:
        The longest wording (phrase or synonym) whose words occur contiguously in the command
        (earliest on a tie); if none, the best fuzzy match scoring at least ``ACCEPT_SCORE``.

    Raises:
        Reply: kind ``did_you_mean`` (``pending`` = the suggested command) when the best fuzzy
            match scores between ``SUGGEST_SCORE`` and ``ACCEPT_SCORE``: nothing is done.
        NoMatchingScenario: nothing matches; the message lists the phrases.
    """
    registry = SCENARIO_REGISTRY if registry is None else registry
    functions = {**(QUESTION_REGISTRY if questions else {}), **registry}
    table = _phrase_table(registry, questions)
    words = normalize_utterance(text)
    best: tuple[int, int, str, int] | None = None  # (-len, position, wording, end)
    for wording in table:
        parts = normalize_utterance(wording)
        n = len(parts)
        for i in range(len(words) - n + 1):
            if n and words[i : i + n] == parts:
                key = (-len(" ".join(parts)), i, wording, i + n)
                if best is None or key[:2] < best[:2]:
                    best = key
                break
    score = 1.0
    if best is not None:
        _, _, wording, end = best
        rest = words[end:]
    else:
        content = tuple(w for w in words if w not in ("please", "robot", "could", "would", "you", "can", "hey"))
        fuzzy_wordings = [w for w in table if " " in w or len(w) >= 6]  # "park" ~ "pack": too short to guess
        score, wording, start, end = fuzzy_match(content, fuzzy_wordings)
        rest = content[end:]
        if score < SUGGEST_SCORE:
            raise NoMatchingScenario(
                f"I don't know how to do that; try one of: {', '.join(sorted(set(table.values())))}")
        if score < ACCEPT_SCORE:
            suggestion = " ".join((*normalize_utterance(table[wording]), *rest))
            raise Reply(f"Did you mean {suggestion!r}? Say yes to do it.", "did_you_mean", pending=suggestion)
    phrase = table[wording]
    utt = Utterance(words, rest, frozenset(n.lower() for n in known_objects),
                    frozenset(n.lower() for n in locations), world or World())
    return ScenarioMatch(phrase, functions[phrase], utt, wording, score)
