"""Background helpers shared by the demo, the test fixtures and the benchmarks (no node code).

* :class:`BackgroundNode` — an rclpy context + node on a given domain, spun by an executor in its
  own thread, closed in the one safe order (shut the executor down, join its thread, then destroy:
  a spin thread still alive at interpreter exit aborts the process).
* :class:`CapturedProcess` — a command-line program started with its output collected by a thread.
"""

from __future__ import annotations

import subprocess
import threading
from collections.abc import Sequence


class BackgroundNode:
    """An rclpy context and node on ``domain_id``, spun in a background thread.

    Args:
        domain_id: ROS_DOMAIN_ID of the context (the process environment is not consulted).
        name: node name.
        threads: executor threads (1 = SingleThreadedExecutor).
    """

    def __init__(self, domain_id: int, name: str, threads: int = 2) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor

        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = (SingleThreadedExecutor(context=self.context) if threads <= 1
                         else MultiThreadedExecutor(num_threads=threads, context=self.context))
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name=f"{name}-executor", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        try:
            self.executor.spin()
        except ExternalShutdownException:
            pass

    def close(self) -> None:
        self.executor.shutdown(timeout_sec=2.0)
        self._thread.join(3.0)  # before destroying: a live spin thread at exit aborts the process
        self.node.destroy_node()
        self.context.try_shutdown()


class CapturedProcess:
    """A program run with stdout+stderr collected line by line (``text()``) by a reader thread."""

    def __init__(self, args: Sequence[str], env: dict[str, str]) -> None:
        self.proc = subprocess.Popen(list(args), env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=lambda: self.lines.extend(iter(self.proc.stdout.readline, "")),
                                        daemon=True)
        self._reader.start()

    def text(self) -> str:
        return "".join(self.lines)

    def wait(self, timeout: float) -> int:
        """Exit code; the program is killed if it has not ended within ``timeout`` s (then raises)."""
        try:
            return self.proc.wait(timeout)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
            self._reader.join(5)
