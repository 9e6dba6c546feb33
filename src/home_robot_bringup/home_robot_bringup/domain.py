"""Leases of unique ``ROS_DOMAIN_ID`` values, so concurrent tests/demos never hear each other.

A lease is an exclusive ``flock`` on ``<tmp>/home_robot_ros_domains/<id>.lock``; the OS drops it
when the holder exits, even after a crash, so ids are never leaked.
"""

from __future__ import annotations

import fcntl
import os
import random
import tempfile

# 0 is the ROS default that interactive users sit on; Fast DDS port formulas allow up to 232.
DOMAIN_RANGE = range(1, 101)


class DomainLease:
    """Holds one free domain id until :meth:`release` (or process exit)."""

    def __init__(self, lock_dir: str | None = None) -> None:
        lock_dir = lock_dir or os.path.join(tempfile.gettempdir(), "home_robot_ros_domains")
        os.makedirs(lock_dir, exist_ok=True)
        candidates = list(DOMAIN_RANGE)
        random.shuffle(candidates)
        for domain in candidates:
            fd = os.open(os.path.join(lock_dir, f"{domain}.lock"), os.O_RDWR | os.O_CREAT, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                continue
            self.domain_id, self._fd = domain, fd
            return
        raise RuntimeError(f"no free ROS_DOMAIN_ID in {DOMAIN_RANGE} (all leased)")

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing drops the flock
            self._fd = None

    def __enter__(self) -> DomainLease:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
