"""home_robot_ros.startup: numeric parameters checked with their name, action names checked as rclpy would."""

from __future__ import annotations

import math

import pytest
import rclpy
from rclpy.exceptions import NameValidationException

from home_robot_ros.startup import CONFIG_ERRORS, ParameterError, action_name, number_in


def test_a_number_in_its_range_is_taken():
    assert number_in("rate_hz", 20, 0.01, 1000.0) == 20.0
    assert number_in("rate_hz", 0.01, 0.01, 1000.0) == 0.01 and number_in("rate_hz", 1000, 0.01, 1000.0) == 1000.0


@pytest.mark.parametrize("value", [1e-300, 1e300, math.nan, math.inf, -1.0, True, "abc", None, 10**400])
def test_a_number_it_cannot_use_names_the_parameter(value):
    with pytest.raises(ParameterError, match=r"rate_hz must be a number from 0.01 to 1000, got "):
        number_in("rate_hz", value, 0.01, 1000.0)
    assert issubclass(ParameterError, CONFIG_ERRORS)


def test_an_action_name_rclpy_refuses_is_a_name_error():
    rclpy.init()
    try:
        node = rclpy.create_node("startup_test")
        assert action_name(node, "navigate_to_pose") == "navigate_to_pose"
        assert action_name(node, "/robot/grasp") == "/robot/grasp"
        for bad in ("bad//name", "9lives", "with space"):
            with pytest.raises(NameValidationException):
                action_name(node, bad)
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
