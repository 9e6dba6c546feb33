"""Repository-wide pytest setup: the ROS test fixtures (real processes, unique domains); slow tests first."""

import pytest

pytest_plugins = ["home_robot_bringup.testing"]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests marked ``slow`` (more than ~20 s each) start first, in their collection order, the rest after them.

    With ``pytest -n 2`` the workers take tests in this order as they free up, so a long test never starts last and
    runs alone while the other worker idles (with ``--dist loadgroup`` xdist puts test groups first, then this order).
    The sort is stable: tests of one module keep their order, and a module's tests stay together within each part.
    """
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
