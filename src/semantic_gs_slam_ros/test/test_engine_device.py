"""The streaming server's ``device`` parameter reaches the engine (pure Python, no ROS graph)."""

from __future__ import annotations

import types

import pytest
import torch

from semantic_gs_slam_ros.engine import load_slam_config, make_engine
from semantic_gs_slam_ros.errors import StreamingError

CAM = (60.0, 60.0, 59.5, 33.5, 120, 68)


def test_device_override_wins_over_the_yaml(tmp_path):
    y = tmp_path / "slam.yaml"
    y.write_text("device: cpu\nmapping: {iters: 3}\n")
    cfg, _ = load_slam_config(str(y), CAM, {"device": "auto"})
    assert cfg.device == "auto" and cfg.mapping.iters == 3
    cfg, _ = load_slam_config(str(y), CAM)
    assert cfg.device == "cpu"
    with pytest.raises(StreamingError, match="device must be"):
        load_slam_config("", CAM, {"device": "gpu"})


def test_make_engine_explains_a_missing_gpu():
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    session_cfg = types.SimpleNamespace(width=120, height=68)
    with pytest.raises(StreamingError, match="no CUDA device"):
        make_engine("", lambda: CAM, session_cfg, overrides={"device": "cuda"})
    eng = make_engine("", lambda: CAM, session_cfg, overrides={"device": "auto"})
    assert eng.slam.device == torch.device("cpu")
