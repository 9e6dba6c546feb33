"""pytest plugin: real ROS 2 node processes per test, each test on its own ROS_DOMAIN_ID.

Registered by the repository's ``conftest.py``. Fixtures:

* ``ros_domain`` -- a leased, unique domain id (tests may run in parallel: pytest -n 2).
* ``launch_nodes`` -- ``launch_nodes(nodeset=..., nodes=[NodeSpec...], set=[...], ready_timeout=...)``
  starts nodes as processes on the test's domain, waits for readiness, and always stops them;
  if the test failed, their output is printed (pytest shows it under "Captured stdout teardown").
* ``ros_node`` -- an rclpy node in the test process on the test's domain, spun by a
  MultiThreadedExecutor in a background thread; wait on futures/events from the test.
* ``shared_domain``, ``launch_shared_nodes``, ``shared_ros_node`` -- the same for a whole test
  module: a node set started once that several tests use (one process start instead of one per
  test). Only for tests that leave the nodes as they found them (queries, or names of their own);
  mark them ``@pytest.mark.xdist_group(...)`` so that ``pytest -n 2 --dist loadgroup`` runs them on
  one worker. The nodes' output is printed at the end of the module if one of its tests failed.

Every environment created here sets ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator

import pytest

from home_robot_bringup.background import BackgroundNode
from home_robot_bringup.domain import DomainLease
from home_robot_bringup.launcher import apply_overrides
from home_robot_bringup.nodeset import NodeSpec, load_nodeset
from home_robot_bringup.process import Supervisor, node_environment

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo) -> Iterator[None]:
    report = yield
    setattr(item, f"rep_{report.when}", report)
    return report


def _failed(request: pytest.FixtureRequest) -> bool:
    return any(getattr(request.node, f"rep_{w}", None) is not None and getattr(request.node, f"rep_{w}").failed
               for w in ("setup", "call"))


@pytest.fixture
def ros_domain() -> Iterator[int]:
    with DomainLease() as lease:
        yield lease.domain_id


def _starter(domain: int, started: list[Supervisor]) -> Callable[..., Supervisor]:
    """The ``start(nodeset=..., nodes=[...], set=[...], ...)`` of a fixture: nodes on ``domain``, kept in ``started``.
    """

    def start(nodeset: str | None = None, nodes: list[NodeSpec] | None = None, set: list[str] | None = None,
              ready_timeout: float = 60.0, env: dict[str, str] | None = None) -> Supervisor:
        specs = list(load_nodeset(nodeset) if nodeset else []) + list(nodes or [])
        specs = apply_overrides(specs, set or [])
        node_env = node_environment(domain)
        node_env.update(env or {})
        sup = Supervisor(specs, node_env, echo=None)
        started.append(sup)
        sup.start()
        sup.wait_ready(ready_timeout)
        return sup

    return start


@pytest.fixture
def launch_nodes(ros_domain: int, request: pytest.FixtureRequest) -> Iterator[Callable[..., Supervisor]]:
    started: list[Supervisor] = []
    yield _starter(ros_domain, started)
    for sup in started:
        sup.stop()
    if _failed(request):
        for sup in started:
            print(sup.output())


@pytest.fixture(scope="module")
def shared_domain() -> Iterator[int]:
    with DomainLease() as lease:
        yield lease.domain_id


@pytest.fixture(scope="module")
def launch_shared_nodes(shared_domain: int, request: pytest.FixtureRequest) -> Iterator[Callable[..., Supervisor]]:
    started: list[Supervisor] = []
    failed_before = request.session.testsfailed
    yield _starter(shared_domain, started)
    for sup in started:
        sup.stop()
    if request.session.testsfailed > failed_before:
        for sup in started:
            print(sup.output())


@pytest.fixture(scope="module")
def shared_ros_node(shared_domain: int) -> Iterator[object]:
    """An rclpy node in the test process on ``shared_domain``, already being spun, for a whole module."""
    helper = BackgroundNode(shared_domain, "test_client")
    try:
        yield helper.node
    finally:
        helper.close()


@pytest.fixture
def ros_node(ros_domain: int) -> Iterator[object]:
    """The test's own rclpy node (``rclpy.node.Node``), already being spun."""
    helper = BackgroundNode(ros_domain, "test_client")
    try:
        yield helper.node
    finally:
        helper.close()


def wait_for(predicate: Callable[[], bool], timeout: float, interval: float = 0.02) -> bool:
    """Poll ``predicate`` until true or ``timeout`` seconds; returns its last value."""
    import time

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(interval)
    return bool(predicate())
