"""Terminal helpers of the input nodes: stdin read in a thread, waiting for listeners (no node code)."""

from __future__ import annotations

import queue
import sys
import threading
import time
from collections.abc import Iterator
from typing import TextIO


def stdin_lines(stream: TextIO | None = None, poll_s: float = 0.2) -> Iterator[str]:
    """Lines of ``stream`` (default stdin, newline stripped) until end of input.

    The blocking read happens in a daemon thread; this generator waits on a queue in slices of
    ``poll_s``, so the calling (main) thread stays responsive to Ctrl-C (KeyboardInterrupt), which
    a ``readline`` blocked in the main thread of a multi-threaded process would not be.
    """
    stream = sys.stdin if stream is None else stream
    lines: queue.Queue[str | None] = queue.Queue()

    def read() -> None:
        try:
            for line in iter(stream.readline, ""):
                lines.put(line.rstrip("\n"))
        except (OSError, ValueError):  # closed / unreadable stdin = end of input
            pass
        lines.put(None)

    threading.Thread(target=read, name="stdin-reader", daemon=True).start()
    while True:
        try:
            line = lines.get(timeout=poll_s)
        except queue.Empty:
            continue
        if line is None:
            return
        yield line


def wait_for_listeners(pub, timeout_s: float, settle_s: float = 0.3, node=None, required_node: str = "") -> int:
    """Wait until ``pub`` is matched with its subscribers (or ``timeout_s``); returns how many.

    "Matched" means: at least one; when ``node`` is given, every subscription the ROS graph shows
    on the topic, including one of the node named ``required_node`` (e.g. the decision maker) if
    set; and the count unchanged for ``settle_s``. Used before the first publish of a short-lived
    node, so the message reaches the listeners discovery is still finding (brain, nav, arm...).
    """
    deadline = time.monotonic() + timeout_s
    count, since = pub.get_subscription_count(), time.monotonic()
    while time.monotonic() < deadline:
        now_count = pub.get_subscription_count()
        infos = node.get_subscriptions_info_by_topic(pub.topic_name) if node is not None else []
        required_seen = not required_node or node is None or any(i.node_name == required_node for i in infos)
        if now_count != count:
            count, since = now_count, time.monotonic()
        elif count > 0 and count >= len(infos) and required_seen and time.monotonic() - since >= settle_s:
            break
        time.sleep(0.02)
    return count
