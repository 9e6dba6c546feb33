"""Pure tests: transcript normalisation, word edit distance, the wake-word gate, the vocabulary."""

import pytest

from decision_maker.speech.errors import ConfigError
from decision_maker.speech.text import WakeWordGate, edit_distance, normalise, word_edit_distance
from decision_maker.speech.vocabulary import Vocabulary, parse_object_list


@pytest.mark.parametrize(("raw", "expected"), [
    (" Give me the bottle.", "give me the bottle"),
    ("Go home!", "go home"),
    ("Clean   the\ttable, please...", "clean the table please"),
    ("Don't stop", "dont stop"),
    ("Go to table 3.", "go to table 3"),
    ("Move 2.5 meters", "move 2.5 meters"),
    ("Bring me item #42, now", "bring me item 42 now"),
    ("snake_case-word", "snake case word"),
    ("Café au lait", "café au lait"),
    ("...", ""),
    ("", ""),
])
def test_normalise(raw, expected):
    assert normalise(raw) == expected


def test_edit_distances():
    assert edit_distance("robot", "robots") == 1
    assert edit_distance("", "abc") == 3
    assert word_edit_distance("Give me the bottle.", "give me the model") == 1
    assert word_edit_distance("go home", "go home") == 0
    assert word_edit_distance("clean table", "please enable") == 2


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_wake_word_off_passes_everything():
    gate = WakeWordGate("")
    assert not gate.enabled
    assert gate.process("go home").command == "go home"
    assert gate.process("").reason == "empty"


def test_wake_word_is_required_and_stripped():
    gate = WakeWordGate("robot", clock=FakeClock())
    assert gate.process("robot go home").command == "go home"
    assert gate.process("hey robot bring me the cup").command == "bring me the cup"
    assert gate.process("robots stop").command == "stop"  # one edit tolerated
    d = gate.process("go home")
    assert d.command is None and d.reason == "no_wake_word"
    assert gate.process("rabbit go home").reason == "no_wake_word"  # two edits: not the wake word


def test_lone_wake_word_arms_the_gate_until_timeout():
    clock = FakeClock()
    gate = WakeWordGate("robot", timeout_s=5.0, clock=clock)
    assert gate.process("robot").reason == "wake_word_only"
    clock.t += 3.0
    assert gate.process("clean the table").command == "clean the table"
    assert gate.process("stop").reason == "no_wake_word"  # used up
    gate.process("robot")
    clock.t += 6.0
    assert gate.process("stop").reason == "no_wake_word"  # expired


def test_multi_word_wake_word():
    gate = WakeWordGate("hey robot", clock=FakeClock())
    assert gate.process("hey robot go home").command == "go home"
    assert gate.process("robot go home").reason == "no_wake_word"


def test_vocabulary_prompt_lists_phrases_objects_and_wake_word():
    v = Vocabulary(command_phrases=("give me the", "go home", "Go  home"), objects=("cup", "red_box"),
                   places=("kitchen",), wake_word="robot")
    assert v.command_phrases == ("give me the", "go home")  # duplicates (case/space) removed
    assert v.prompt() == "robot, give me the cup, go home, cup, red box, kitchen"
    assert v.prompt_words()[:4] == ["robot", "give", "me", "the"]
    assert "cup" in Vocabulary().with_objects(["cup"]).prompt()


def test_parse_object_list():
    assert parse_object_list('{"table": [1, 2, 0], "bottle": [5.2, 0.3, 1.0]}') == ("bottle", "table")
    with pytest.raises(ConfigError, match="not JSON"):
        parse_object_list("{nope")
    with pytest.raises(ConfigError, match="JSON object"):
        parse_object_list('["bottle"]')


def test_command_grammar_from_the_vocabulary():
    v = Vocabulary(objects=("cup", "coffee_mug"), places=("kitchen",), wake_word="robot")
    sentences = v.grammar_sentences()
    assert {"give me the cup", "give me the coffee mug", "bring me the kitchen", "go home", "stop"} <= sentences
    assert "give me the" not in sentences and "go home cup" not in sentences
    assert len(sentences) == 2 * 3 + 5  # 2 phrases x 3 names + 5 whole commands
    for text in ("Give me the cup.", "robot, give me the cup", "hey robot go home", "please stop", "stop please"):
        assert v.in_grammar(text), text
    for text in ("good clean the cup", "give me the teapot", "give me the", "what time is it", "", "robot"):
        assert not v.in_grammar(text), text
    assert not Vocabulary().in_grammar("give me the cup")  # no object names: no object commands
