"""Repository-wide pytest setup: the ROS test fixtures (real processes, unique domains), and no installed models.

Tests see no installed COCO detector (``HOME_ROBOT_MODELS`` points at an empty place), so ``labels: auto`` means the
same on every machine; a test that wants the real detector reads ``HOME_ROBOT_MODELS_REAL`` (the models folder the
user's setup filled) and skips, saying why, when nothing is installed there.
"""

import os
import tempfile

pytest_plugins = ["home_robot_bringup.testing"]


def pytest_configure(config) -> None:
    if "HOME_ROBOT_MODELS_REAL" not in os.environ:
        cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        os.environ["HOME_ROBOT_MODELS_REAL"] = os.environ.get("HOME_ROBOT_MODELS") or os.path.join(
            cache, "home-robot", "models")
    os.environ["HOME_ROBOT_MODELS"] = os.path.join(tempfile.gettempdir(), "home-robot-tests-no-models")
