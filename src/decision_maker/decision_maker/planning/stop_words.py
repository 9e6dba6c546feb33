"""Spoken or typed stops: which words stop the robot at once (no ROS, no speech stack).

Used by the execution engine (a stop is never queued) and by the voice filter (a stop is kept at a
lower confidence than other commands: a missed stop is worse than a spurious one).
"""

from __future__ import annotations

import re

#: Words that, said alone (in any number, with "please", "robot", "now", "it"/"that"/"everything"),
#: stop the robot at once instead of being queued ("stop", "stop it", "cancel that", "abort!").
STOP_VERBS = frozenset({"stop", "cancel", "abort", "halt", "freeze"})
STOP_FILLERS = frozenset({"it", "that", "this", "now", "please", "robot", "everything", "all", "the", "task",
                           "emergency", "right", "immediately", "hey", "ok", "okay"})


def is_stop_command(text: str) -> bool:
    """True when ``text`` (sanitised) asks to stop and nothing else: "stop", "Stop it!", "cancel that".

    "stop at the kitchen" or "don't stop" are not stops (other words); those go to the planner.
    """
    words = re.findall(r"[a-z']+", text.lower())
    return bool(words) and len(words) <= 6 and any(w in STOP_VERBS for w in words) and \
        all(w in STOP_VERBS or w in STOP_FILLERS for w in words)
