"""The streaming server's ``device`` parameter reaches the engine (pure Python, no ROS graph)."""

from __future__ import annotations

import types

import pytest
import torch

from semantic_gs_slam_ros.engine import CPU_SWITCH_INTERVAL, load_slam_config, make_engine, switch_interval_for
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


def test_profile_sits_under_the_yaml_and_a_bad_one_is_named(tmp_path):
    y = tmp_path / "slam.yaml"
    y.write_text("mapping: {keyframe_every: 5}\n")
    cfg, _ = load_slam_config(str(y), CAM, {"device": "cpu"}, profile="realtime")
    assert cfg.threaded and cfg.tracking.frontend == "keyframe" and cfg.mapping.defer_keyframes
    assert cfg.mapping.keyframe_every == 5  # the YAML wins over the profile, field by field
    cfg, _ = load_slam_config(str(y), CAM)
    assert not cfg.threaded and cfg.tracking.frontend == "render" and cfg.mapping.keyframe_every == 5
    with pytest.raises(StreamingError, match="unknown profile 'fastest'"):
        load_slam_config("", CAM, profile="fastest")
    y.write_text("[1, 2]\n")
    with pytest.raises(StreamingError, match="mapping of SlamConfig fields"):
        load_slam_config(str(y), CAM)


def test_make_engine_explains_a_missing_gpu():
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    session_cfg = types.SimpleNamespace(width=120, height=68)
    with pytest.raises(StreamingError, match="no CUDA device"):
        make_engine("", lambda: CAM, session_cfg, overrides={"device": "cuda"})
    eng = make_engine("", lambda: CAM, session_cfg, overrides={"device": "auto"})
    assert eng.slam.device == torch.device("cpu")


def test_prepare_renderer_loads_gsplat_before_the_server_is_ready(monkeypatch):
    """On CUDA with gsplat installed the server loads (builds) gsplat's CUDA code before "ready:", and says how
    it went; on the CPU it does nothing. torch's CUDA check and gsplat's extension module are stand-ins here:
    only what the server does with their answers is under test (the real build runs in ``make bench-gpu``)."""
    if torch.cuda.is_available():
        pytest.skip("this test describes a machine without CUDA")
    pytest.importorskip("gsplat")
    import sys

    import semantic_gs_slam.render.gsplat_backend as rgm
    from semantic_gs_slam_ros.engine import prepare_renderer

    lines: list[str] = []
    prepare_renderer("auto", lines.append)  # no CUDA here: nothing to load
    prepare_renderer("cpu", lines.append)
    assert lines == []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    for ext, said in ((None, "did not build or load (gsplat found no CUDA toolkit (nvcc))"), (object(), "loaded in")):
        monkeypatch.setattr(rgm, "_EXTENSION", {})
        mod = types.ModuleType("gsplat.cuda._backend")
        mod._C = ext
        monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", mod)
        lines.clear()
        prepare_renderer("cuda", lines.append)
        assert lines[0].startswith("loading gsplat's CUDA code") and said in lines[1], lines


def test_the_lock_hand_over_is_short_on_the_cpu_and_left_to_python_on_cuda():
    """``gil_switch_interval`` auto: 0.5 ms where the engine runs on the CPU, Python's own (0) on CUDA, where a
    shorter one made the realtime engine far slower, and where the device cannot be had (the goal says why)."""
    assert switch_interval_for("cpu") == CPU_SWITCH_INTERVAL == 0.0005
    assert switch_interval_for("auto") == (0.0 if torch.cuda.is_available() else CPU_SWITCH_INTERVAL)
    assert switch_interval_for("cuda") == 0.0 and switch_interval_for("cuda:7") == 0.0
    assert switch_interval_for("gpu") == 0.0
