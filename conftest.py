"""Repository-wide pytest setup: the ROS test fixtures (real processes, unique domains), slow tests first, and no
installed models.

Tests see no installed COCO detector (``HOME_ROBOT_MODELS`` points at an empty place), so ``labels: auto`` means the
same on every machine; a test that wants the real detector reads ``HOME_ROBOT_MODELS_REAL`` (the models folder the
user's setup filled) and skips, saying why, when nothing is installed there.
"""

import os
import tempfile

import pytest

pytest_plugins = ["home_robot_bringup.testing"]


def pytest_configure(config: pytest.Config) -> None:
    if "HOME_ROBOT_MODELS_REAL" not in os.environ:
        cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        os.environ["HOME_ROBOT_MODELS_REAL"] = os.environ.get("HOME_ROBOT_MODELS") or os.path.join(
            cache, "home-robot", "models")
    os.environ["HOME_ROBOT_MODELS"] = os.path.join(tempfile.gettempdir(), "home-robot-tests-no-models")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests marked ``slow`` (more than ~20 s each) start first, in their collection order, the rest after them.

    With ``pytest -n 2`` the workers take tests in this order as they free up, so a long test never starts last and
    runs alone while the other worker idles (with ``--dist loadgroup`` xdist puts test groups first, then this order).
    The sort is stable: tests of one module keep their order, and a module's tests stay together within each part.
    """
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
