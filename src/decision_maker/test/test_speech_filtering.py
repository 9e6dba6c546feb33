"""Pure tests of the hallucination filter."""

import pytest

from decision_maker.speech.errors import ConfigError
from decision_maker.speech.filtering import FilterConfig, judge, longest_common_run
from decision_maker.speech.vocabulary import Vocabulary

CFG = FilterConfig()
GOOD = {"no_speech_prob": 0.05, "avg_logprob": -0.3, "compression_ratio": 0.7}


def test_keeps_a_clean_command():
    v = judge(" Give me the bottle.", config=CFG, **GOOD)
    assert v.kept and v.text == "give me the bottle"


@pytest.mark.parametrize(("raw", "overrides", "reason"), [
    ("", {}, "empty"),
    (" ...", {}, "empty"),
    ("go home", {"no_speech_prob": 0.8}, "no_speech"),
    ("go home", {"avg_logprob": -1.4}, "low_logprob"),
    ("go go go go go go go go go go", {"compression_ratio": 3.1}, "repetitive"),
    ("a", {}, "too_short"),
    (" Thank you.", {}, "blocklisted"),
    (" you", {}, "blocklisted"),
    ("word " * 31, {}, "too_long"),
])
def test_drops_junk(raw, overrides, reason):
    v = judge(raw, config=CFG, **{**GOOD, **overrides})
    assert v.reason == reason


def test_prompt_echo_is_dropped_but_commands_from_the_prompt_are_not():
    vocab = Vocabulary(objects=("bottle", "cup", "chair"))
    words = vocab.prompt_words()
    echo = "give me the bottle, bring me the bottle, go home, clean table"
    assert judge(echo, config=CFG, prompt_words=words, **GOOD).reason == "prompt_echo"
    for command in ("give me the bottle", "bring me the cup", "clean the table", "stop"):
        assert judge(command, config=CFG, prompt_words=words, **GOOD).kept, command


def test_longest_common_run():
    assert longest_common_run("a b c d".split(), "x b c d y".split()) == 3
    assert longest_common_run([], ["a"]) == 0


def test_config_is_validated():
    with pytest.raises(ConfigError):
        FilterConfig(max_no_speech_prob=1.5)
    with pytest.raises(ConfigError):
        FilterConfig(min_avg_logprob=0.5)


@pytest.mark.parametrize("raw", ["cancel", "Cancel.", "stop it", "abort!"])
def test_a_stop_is_kept_at_a_lower_confidence_than_other_commands(raw):
    cfg = FilterConfig()  # min_avg_logprob -1.0, min_stop_avg_logprob -1.6
    assert judge(raw, 0.1, -1.3, 1.0, cfg).kept  # a missed stop is worse than a spurious one
    assert judge(raw, 0.1, -1.7, 1.0, cfg).reason == "low_logprob"  # but not at any confidence
    assert judge("give me the cup", 0.1, -1.3, 1.0, cfg).reason == "low_logprob"
    assert judge("stop at the kitchen", 0.1, -1.3, 1.0, cfg).reason == "low_logprob"  # not a stop
    with pytest.raises(ConfigError):
        FilterConfig(min_stop_avg_logprob=0.5)
