"""The SLAM server's cancel bookkeeping (semantic_gs_slam_ros.cancels), without ROS."""

from __future__ import annotations

import pytest

from semantic_gs_slam_ros.cancels import CancelRouter


class Session:
    def __init__(self) -> None:
        self.cancelled = 0

    def cancel(self) -> None:
        self.cancelled += 1


def test_a_cancel_before_the_session_exists_is_kept_for_that_goal():
    r = CancelRouter()
    assert r.request(b"a") is False and r.pending == 1  # the engine is still being made
    s = Session()
    assert r.start(b"a", s) is True and s.cancelled == 1 and r.pending == 0
    r.finish(b"a")
    s2 = Session()
    assert r.start(b"a", s2) is False and s2.cancelled == 0  # used once


def test_a_cancel_reaches_only_its_own_goals_session():
    r = CancelRouter()
    s = Session()
    assert r.start(b"a", s) is False
    assert r.request(b"b") is False and s.cancelled == 0  # another goal (accepted beside, refused at start)
    assert r.request(b"a") is True and s.cancelled == 1
    r.finish(b"b")  # b's run ended without starting: its early cancel goes, a keeps running
    assert r.pending == 0
    assert r.request(b"a") is True and s.cancelled == 2
    r.finish(b"a")
    assert r.request(b"a") is False and s.cancelled == 2  # over: kept as early, the session is not touched


def test_early_cancels_are_bounded():
    r = CancelRouter(remember=3)
    for g in (b"1", b"2", b"3", b"4", b"5"):
        r.request(g)
    assert r.pending == 3
    s_old, s_new = Session(), Session()
    assert r.start(b"1", s_old) is False and s_old.cancelled == 0  # forgotten (the oldest)
    assert r.start(b"5", s_new) is True and s_new.cancelled == 1
    with pytest.raises(ValueError):
        CancelRouter(remember=0)
