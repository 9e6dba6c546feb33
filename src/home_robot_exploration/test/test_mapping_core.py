"""Mapping while exploring, without ROS: the SLAM run's state machine and the simulated wheel odometry."""

from __future__ import annotations

import math

import pytest

from home_robot_exploration.errors import ConfigError
from home_robot_exploration.mapping import MappingConfig, MappingResult, MappingRun
from home_robot_exploration.simcam import OdometryConfig, WheelOdometry


def test_run_waits_for_acceptance_and_its_own_start_signal_then_finishes() -> None:
    run = MappingRun(MappingConfig(enabled=True, start_timeout_s=10.0, finish_timeout_s=20.0), now=0.0)
    assert run.state == "connecting" and not run.ready_to_explore()
    run.accepted("abc", now=1.0)
    assert run.state == "waiting_start" and not run.ready_to_explore()
    assert run.start_signal("an earlier run") is False and run.state == "waiting_start"
    assert run.start_signal("abc") is True and run.ready_to_explore()
    run.feedback(12, 3400)
    assert run.finish(now=30.0) is True and run.state == "finishing" and not run.settled()
    assert run.finish(now=31.0) is False  # only once
    run.ended(MappingResult(True, "/m/params.npz", 40, "40 frames processed"))
    assert run.state == "done" and run.settled()
    assert run.summary() == {"state": "done", "frames": 40, "gaussians": 3400, "map_path": "/m/params.npz",
                             "message": "40 frames processed"}


def test_deadlines_and_refusals_never_block_exploration_or_its_end() -> None:
    cfg = MappingConfig(enabled=True, start_timeout_s=10.0, finish_timeout_s=20.0)
    run = MappingRun(cfg, now=0.0)
    assert run.tick(9.0) is None
    assert "server not available" in (run.tick(10.5) or "")
    assert run.state == "failed" and run.ready_to_explore() and run.settled()
    run = MappingRun(cfg, now=0.0)
    run.accepted("g", now=1.0)
    assert "no start signal" in (run.tick(12.0) or "")
    run = MappingRun(cfg, now=0.0)
    run.rejected("refused")
    assert run.state == "failed" and run.reason == "refused" and run.ready_to_explore()
    run = MappingRun(cfg, now=0.0)
    run.accepted("g", now=0.0)
    run.start_signal("g")
    run.finish(now=5.0)
    assert run.tick(24.0) is None
    assert "did not finish the map within 20 s" in (run.tick(25.5) or "")
    assert run.settled()
    run.ended(MappingResult(True, "late", 3, "ok"))  # a late result is kept but does not undo the failure
    assert run.state == "failed" and run.result.map_path == "late"
    run = MappingRun(cfg, now=0.0)
    assert run.finish(now=1.0) is False and run.state == "failed"  # ended before the run started
    run = MappingRun(cfg, now=0.0)
    run.accepted("g", now=0.0)
    run.start_signal("g")
    run.ended(MappingResult(False, "", 0, "no camera_info received"))  # the server gave up by itself
    assert run.state == "failed" and "camera_info" in run.summary()["message"]


def test_mapping_off_is_settled_at_once_and_bad_deadlines_are_refused() -> None:
    run = MappingRun(MappingConfig(enabled=False), now=0.0)
    assert run.state == "off" and run.ready_to_explore() and run.settled() and run.finish(1.0) is False
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ConfigError, match="start_timeout_s"):
            MappingRun(MappingConfig(enabled=True, start_timeout_s=bad), now=0.0)


def drive(odo: WheelOdometry, steps: int, fwd: float, turn: float) -> tuple[tuple[float, float, float], tuple]:
    """Drive a square-ish path in small steps; returns (true pose, odometry pose)."""
    x, y, yaw = 1.0, 2.0, 0.3
    est = odo.update(x, y, yaw)
    for _ in range(steps):
        x, y, yaw = x + fwd * math.cos(yaw), y + fwd * math.sin(yaw), yaw + turn
        est = odo.update(x, y, yaw)
    return (x, y, yaw), est


def test_wheel_odometry_starts_exact_and_drifts_with_distance_and_turns() -> None:
    perfect = WheelOdometry(OdometryConfig(0.0, 0.0, 0.0))
    true, est = drive(perfect, 200, 0.02, 0.03)
    assert math.dist(true[:2], est[:2]) < 1e-9
    assert abs(math.remainder(true[2] - est[2], 2 * math.pi)) < 1e-9
    first = WheelOdometry(OdometryConfig(0.05, 0.05, 0.02, seed=3))
    assert first.update(1.0, 2.0, 0.3) == (1.0, 2.0, 0.3)  # the start is known
    short_true, short_est = drive(WheelOdometry(OdometryConfig(0.02, 0.02, 0.01)), 20, 0.02, 0.03)
    long_true, long_est = drive(WheelOdometry(OdometryConfig(0.02, 0.02, 0.01)), 400, 0.02, 0.03)
    short_err = math.dist(short_true[:2], short_est[:2])
    long_err = math.dist(long_true[:2], long_est[:2])
    assert 0.0 < short_err < long_err and long_err > 0.05  # 8 m and 12 rad travelled: centimetres off
    # a turn in place: only the angle drifts (2 % of 2 pi)
    odo = WheelOdometry(OdometryConfig(0.0, 0.02, 0.0))
    odo.update(0.0, 0.0, 0.0)
    for i in range(1, 37):
        est = odo.update(0.0, 0.0, math.radians(10 * i))
    assert est[:2] == (0.0, 0.0) and abs(abs(est[2]) - 0.02 * 2 * math.pi) < 1e-6
    with pytest.raises(ConfigError, match="noise"):
        WheelOdometry(OdometryConfig(noise=-0.1))
    with pytest.raises(ConfigError, match="trans_scale_error"):
        WheelOdometry(OdometryConfig(trans_scale_error=0.9))
