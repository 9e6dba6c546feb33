"""AnswerMemory (execution/repeated_calls.py): a keyed call runs once, however often it is repeated, even
concurrently."""

from __future__ import annotations

import threading
import time

import pytest

from decision_maker.errors import BadKeyError
from decision_maker.execution.repeated_calls import MAX_KEY_CHARS, AnswerMemory


def test_a_key_runs_once_and_repeats_get_the_first_answer():
    memory: AnswerMemory[int] = AnswerMemory()
    runs = []

    def run() -> int:
        runs.append(1)
        return len(runs)

    assert memory.answer("k1", run, "") == (1, False)
    assert memory.answer("k1", run, "") == (1, True)
    assert memory.answer("k2", run, "") == (2, False)
    assert memory.answer("", run, "") == (3, False) and memory.answer("", run, "") == (4, False)  # no key: every time
    assert len(runs) == 4 and memory.repeats == 1 and len(memory) == 2


def test_oldest_keys_are_forgotten_and_bad_keys_refused():
    memory: AnswerMemory[str] = AnswerMemory(capacity=2)
    for key in ("a", "b", "c"):
        memory.answer(key, lambda key=key: key, "")
    assert len(memory) == 2
    assert memory.answer("a", lambda: "again", "") == ("again", False)  # forgotten: runs again
    assert memory.answer("c", lambda: "x", "") == ("c", True)
    with pytest.raises(BadKeyError, match="at most 64"):
        memory.answer("k" * (MAX_KEY_CHARS + 1), lambda: pytest.fail("must not run"), "")
    with pytest.raises(ValueError):
        AnswerMemory(capacity=0)


def test_concurrent_repeats_wait_for_the_first_run():
    memory: AnswerMemory[int] = AnswerMemory()
    runs = []
    started = threading.Event()

    def slow() -> int:
        started.set()
        time.sleep(0.2)  # a repeat arrives while the first copy is still being run
        runs.append(1)
        return 7

    results = []
    first = threading.Thread(target=lambda: results.append(memory.answer("k", slow, "")))
    first.start()
    assert started.wait(10.0)
    results.append(memory.answer("k", lambda: pytest.fail("ran twice"), ""))
    first.join(10.0)
    assert sorted(results) == [(7, False), (7, True)] and runs == [1]


def test_a_key_sent_again_with_another_command_is_refused_not_answered_with_the_first():
    """A sender that reuses a key for a new command: refused with the reason (it was answered with the first
    command's id and its own command never ran)."""
    memory: AnswerMemory[str] = AnswerMemory()
    assert memory.answer("abc", lambda: "#6", "where is the bottle") == ("#6", False)
    assert memory.answer("abc", lambda: pytest.fail("must not run"), "where is the bottle") == ("#6", True)
    with pytest.raises(BadKeyError, match="'abc' was used for another command"):
        memory.answer("abc", lambda: pytest.fail("must not run"), "go to the kitchen")
    assert memory.repeats == 1
