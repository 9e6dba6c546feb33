"""Supervised node processes: what ``ros2 launch`` does, for machines without launch_ros.

Each node runs as its own process (own session, killed if the supervisor dies), its output is
read line by line by a reader thread, prefixed with the node's name (coloured on a terminal)
and kept in a bounded buffer for tests. Readiness = a regex seen on the node's output.
Stop = SIGINT, then SIGTERM, then SIGKILL, each after a grace period (a MultiThreadedExecutor
node sometimes ignores the first SIGINT).
"""

from __future__ import annotations

import collections
import ctypes
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterable, Sequence
from typing import TextIO

from home_robot_bringup.errors import NodeNotReady
from home_robot_bringup.nodeset import NodeSpec, find_executable

_COLOURS = ("36", "33", "35", "32", "34", "91", "96", "93", "95", "92")
_PR_SET_PDEATHSIG = 1


try:  # loaded once here: the child may only call it (no dlopen between fork and exec)
    _LIBC: ctypes.CDLL | None = ctypes.CDLL("libc.so.6", use_errno=True)
except OSError:  # pragma: no cover - non-glibc systems
    _LIBC = None


def _die_with_parent() -> None:  # runs in the child between fork and exec: keep it trivial
    if _LIBC is not None:
        _LIBC.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


def dds_profile_file() -> str | None:
    """The installed Fast DDS profile (config/dds/fastdds_liveliness.xml: a 2 s participant lease, so
    a killed node leaves the graph within 2 s), or None when it is not installed."""
    try:
        from ament_index_python.packages import get_package_share_directory

        path = os.path.join(get_package_share_directory("home_robot_bringup"), "config", "dds",
                            "fastdds_liveliness.xml")
    except (ImportError, LookupError, ValueError):
        return None
    return path if os.path.isfile(path) else None


def node_environment(domain_id: int | None = None, base: dict[str, str] | None = None) -> dict[str, str]:
    """Environment for node processes: loopback-only discovery, unbuffered, plain ROS logs, and the
    project's Fast DDS profile (unless the caller set a profile of their own)."""
    env = dict(os.environ if base is None else base)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    profile = dds_profile_file()
    if profile and not env.get("FASTRTPS_DEFAULT_PROFILES_FILE") and not env.get("FASTDDS_DEFAULT_PROFILES_FILE"):
        env["FASTRTPS_DEFAULT_PROFILES_FILE"] = env["FASTDDS_DEFAULT_PROFILES_FILE"] = profile
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(domain_id)
    env["PYTHONUNBUFFERED"] = "1"
    env["RCUTILS_COLORIZED_OUTPUT"] = "0"
    env.setdefault("RCUTILS_LOGGING_BUFFERED_STREAM", "0")
    return env


class ManagedProcess:
    """One node process, its output reader and its readiness flag."""

    def __init__(self, spec: NodeSpec, env: dict[str, str], echo: TextIO | None, colour: str | None,
                 max_lines: int = 5000) -> None:
        self.spec = spec
        self._env = env
        self._echo = echo
        self._prefix = f"\033[{colour}m[{spec.name}]\033[0m " if colour else f"[{spec.name}] "
        self._ready_re = re.compile(spec.ready) if spec.ready else None
        self.ready = threading.Event()
        self._lines: collections.deque[str] = collections.deque(maxlen=max_lines)
        self._lines_lock = threading.Lock()  # guards _lines
        self._echo_lock: threading.Lock | None = None
        self.popen: subprocess.Popen[bytes] | None = None
        self._reader: threading.Thread | None = None

    @property
    def name(self) -> str:
        return self.spec.name

    def start(self, echo_lock: threading.Lock) -> None:
        exe = find_executable(self.spec.package, self.spec.executable, self._env.get("AMENT_PREFIX_PATH"))
        self._echo_lock = echo_lock
        self.popen = subprocess.Popen(
            [exe, *self.spec.ros_args()],
            env=self._env,
            stdin=None if self.spec.stdin else subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            start_new_session=not self.spec.stdin,
            preexec_fn=_die_with_parent,
        )
        if self._ready_re is None:
            self.ready.set()
        self._reader = threading.Thread(target=self._read, name=f"reader-{self.name}", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.popen is not None and self.popen.stdout is not None
        for raw in iter(self.popen.stdout.readline, b""):
            line = raw.decode("utf-8", "replace").rstrip("\n")
            with self._lines_lock:
                self._lines.append(line)
            if self._ready_re is not None and not self.ready.is_set() and self._ready_re.search(line):
                self.ready.set()
            if self._echo is not None and self._echo_lock is not None:
                with self._echo_lock:
                    self._echo.write(self._prefix + line + "\n")
                    self._echo.flush()

    def output(self) -> str:
        with self._lines_lock:
            return "\n".join(self._lines)

    def returncode(self) -> int | None:
        return None if self.popen is None else self.popen.poll()

    def send(self, sig: int) -> None:
        if self.popen is not None and self.popen.poll() is None:
            try:
                self.popen.send_signal(sig)
            except ProcessLookupError:
                pass

    def join_reader(self, timeout: float) -> None:
        if self._reader is not None:
            self._reader.join(timeout)


class Supervisor:
    """Starts a node set, waits for readiness, watches for deaths, stops everything cleanly.

    Args:
        specs: the nodes, in start order.
        env: environment of the node processes (see :func:`node_environment`).
        echo: stream that receives the prefixed output lines (None = keep them silently).
        colour: colour the prefixes (default: when ``echo`` is a terminal).
    """

    def __init__(self, specs: Sequence[NodeSpec], env: dict[str, str], echo: TextIO | None = sys.stdout,
                 colour: bool | None = None) -> None:
        if colour is None:
            colour = echo is not None and hasattr(echo, "isatty") and echo.isatty() and "NO_COLOR" not in os.environ
        self.processes = [
            ManagedProcess(s, env, echo, _COLOURS[i % len(_COLOURS)] if colour else None)
            for i, s in enumerate(specs)
        ]
        self._echo_lock = threading.Lock()  # serialises writes of the reader threads to echo
        self._stopped = threading.Event()

    def __enter__(self) -> Supervisor:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> None:
        try:
            for p in self.processes:
                p.start(self._echo_lock)
        except BaseException:
            self.stop()
            raise

    def get(self, name: str) -> ManagedProcess:
        for p in self.processes:
            if p.name == name:
                return p
        raise KeyError(name)

    def wait_ready(self, timeout: float, names: Iterable[str] | None = None) -> None:
        """Block until every (named) node reported ready.

        Raises:
            NodeNotReady: a node died first, or ``timeout`` seconds passed; the message carries
                the tail of its output.
        """
        wanted = [self.get(n) for n in names] if names is not None else self.processes
        deadline = time.monotonic() + timeout
        for p in wanted:
            while not p.ready.wait(0.05):
                code = p.returncode()
                if code is not None:
                    p.join_reader(1.0)
                    raise NodeNotReady(f"{p.name} exited with code {code} while starting:\n{_tail(p.output())}")
                if time.monotonic() > deadline:
                    raise NodeNotReady(f"{p.name} not ready after {timeout:.0f} s:\n{_tail(p.output())}")

    def first_exit(self) -> ManagedProcess | None:
        for p in self.processes:
            if p.returncode() is not None:
                return p
        return None

    def wait(self, poll: float = 0.1) -> int:
        """Block until one node exits or :meth:`request_stop`; then stop all. Returns an exit code."""
        dead: ManagedProcess | None = None
        while not self._stopped.wait(poll):
            dead = self.first_exit()
            if dead is not None:
                break
        self.stop()
        if dead is None:
            return 0
        code = dead.returncode() or 0
        return code if code > 0 else (0 if code == 0 else 128 - code)

    def request_stop(self) -> None:
        self._stopped.set()

    def stop(self, grace: float = 5.0) -> None:
        """SIGINT → SIGTERM → SIGKILL, waiting up to ``grace`` s after each (0.5 s before KILL)."""
        self._stopped.set()
        for sig, wait_s in ((signal.SIGINT, grace), (signal.SIGTERM, grace / 2), (signal.SIGKILL, 0.5)):
            alive = [p for p in self.processes if p.returncode() is None]
            if not alive:
                break
            for p in alive:
                p.send(sig)
            deadline = time.monotonic() + wait_s
            while time.monotonic() < deadline and any(p.returncode() is None for p in alive):
                time.sleep(0.02)
        for p in self.processes:
            if p.popen is not None:
                try:
                    p.popen.wait(timeout=1.0)
                except subprocess.TimeoutExpired:
                    pass
            p.join_reader(1.0)
            if p.popen is not None and p.popen.stdout is not None:
                p.popen.stdout.close()

    def output(self) -> str:
        """Every node's captured output, one block per node (for failure reports)."""
        return "\n".join(f"----- {p.name} (exit {p.returncode()}) -----\n{p.output()}" for p in self.processes)


def _tail(text: str, n: int = 40) -> str:
    lines = text.splitlines()
    return "\n".join(lines[-n:]) if lines else "(no output)"
