"""Answering a retried call once: the brain's memory of recent ``submit_command`` keys (no ROS).

A sender that gets no answer cannot tell a lost request from a lost answer: DDS can drop a service's
response while the server has not yet matched the caller's response reader (a discovery race of
ROS 2 services, worst while many nodes start at once). So senders tag each command with a key and
send the same call again until one answer arrives; the brain runs a key once and answers every repeat
with the first answer. Calls without a key run every time (the seed's behaviour).

Usage::

    answers = AnswerMemory()
    status, repeat = answers.answer(request.key, lambda: engine.submit(request.text), request.text)
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import Generic, TypeVar

from decision_maker.errors import BadKeyError

T = TypeVar("T")

#: Longest key accepted (a UUID's hex is 32 characters).
MAX_KEY_CHARS = 64


class AnswerMemory(Generic[T]):
    """The first answer of each of the last ``capacity`` keys (thread-safe).

    Args:
        capacity: keys remembered (> 0); the oldest is forgotten first. Above the commands a burst can
            have in flight (the service's request queue holds 2000).
    """

    def __init__(self, capacity: int = 4096) -> None:
        if capacity <= 0:
            raise ValueError(f"capacity must be > 0, got {capacity}")
        self._capacity = capacity
        self._lock = threading.Lock()  # guards _answers; held while a keyed call runs, so a repeat waits for it
        self._answers: OrderedDict[str, T] = OrderedDict()
        self._requests: dict[str, str] = {}  # key -> what it asked
        self.repeats = 0  # calls answered from memory

    def answer(self, key: str, run: Callable[[], T], request: str) -> tuple[T, bool]:
        """``run()``'s result for a new or empty ``key``; the remembered one for a repeat.

        Returns ``(answer, repeated)``. ``run`` must not block (it runs under the memory's lock when
        keyed). ``request`` is what was asked (the command's text): a repeat must ask the same.

        Raises:
            BadKeyError: a key longer than :data:`MAX_KEY_CHARS`, or a remembered key sent with another request
                (a sender that reuses keys would otherwise get the first command's answer and its command never
                run). ``run`` is not called.
        """
        if not key:
            return run(), False
        if len(key) > MAX_KEY_CHARS:
            raise BadKeyError(f"key of {len(key)} characters (at most {MAX_KEY_CHARS})")
        with self._lock:
            if key in self._answers:
                if self._requests[key] != request:
                    raise BadKeyError(f"key {key!r} was used for another command; a new command needs a new key")
                self._answers.move_to_end(key)
                self.repeats += 1
                return self._answers[key], True
            result = run()
            self._answers[key] = result
            self._requests[key] = request
            if len(self._answers) > self._capacity:
                old, _ = self._answers.popitem(last=False)
                del self._requests[old]
            return result, False

    def __len__(self) -> int:
        with self._lock:
            return len(self._answers)
