"""The streaming engine adapter's labelling stage (no ROS): label-less frames get geometry labels and
their names reach the engine's classes; bad settings are a StreamingError."""

from __future__ import annotations

import threading
import types

import numpy as np
import pytest
import torch

from semantic_gs_slam.config import MappingConfig, SlamConfig
from semantic_gs_slam.labels import OBJECT_ID
from semantic_gs_slam.slam import SLAM
from semantic_gs_slam.synthetic.scenes import HomeRenderer, default_intrinsics, trajectory
from semantic_gs_slam_ros.engine import EngineAdapter, make_engine, make_labels
from semantic_gs_slam_ros.errors import StreamingError


class _Recorder(SLAM):
    """The real engine class with its per-frame work replaced by a record of what it was given (the
    adapter's wiring is under test here; the engine has its own tests)."""

    def __init__(self, keyframe_every: int = 4) -> None:
        self.classes, self.poses, self.initial_c2w, self.given = {}, [], None, []
        self.cfg = SlamConfig(intrinsics=default_intrinsics(96, 54),
                              mapping=MappingConfig(keyframe_every=keyframe_every))
        self.keyframes = []  # no keyframe yet: only the index says which frame will be one
        self._last_kf_index, self._poses_lock, self._kf_due = -1, threading.RLock(), False  # what
        # keyframe_expected reads
        self.k, self.device = self.cfg.intrinsics, torch.device("cpu")  # what check_frame needs

    def add_frame(self, rgb, depth, semantics=None, timestamp=None, gt_c2w=None):
        self.given.append(semantics)
        self.poses.append(np.eye(4))
        return np.eye(4)


def test_adapter_labels_label_less_frames():
    k = default_intrinsics(96, 54)
    rgb, depth, _ = HomeRenderer(0).render(trajectory(4, 10.0)[0], k)
    slam = _Recorder()
    slam.classes = {200: "object"}  # a resumed map: new instance ids start above its ids
    stage = make_labels("auto", "", k, streamed_labels=False)
    adapter = EngineAdapter(slam, stage)
    assert stage.mode == "geometry" and stage.geometry.next_id == 201
    adapter.add_frame((rgb * 255).astype(np.uint8), depth, None, 0.0)
    sem = slam.given[-1]
    assert sem is not None and sem.shape == depth.shape and (sem == OBJECT_ID).any()
    assert slam.classes[OBJECT_ID] == "object" and slam.classes[1] == "floor"
    assert make_labels("auto", "", k, streamed_labels=True).mode == "dataset"


@pytest.mark.parametrize("mode, model, every, match", [("magic", "", 1, "labels"), ("onnx", "", 1, "labels"),
                                                      ("onnx", "/nonexistent.onnx", 1, "labels"),
                                                      ("geometry", "", 0, "labels.every must be")])
def test_make_labels_bad_settings(mode, model, every, match):
    with pytest.raises(StreamingError, match=match):
        make_labels(mode, model, default_intrinsics(32, 18), streamed_labels=False, every=every)


@pytest.mark.parametrize("every", [0, -2, 1.5, True])
def test_make_engine_refuses_a_bad_labels_every_in_any_mode(every):
    """Checked before the engine waits for camera_info, also with streamed (dataset) labels that never use it."""
    def no_camera():
        raise AssertionError("must fail before waiting for camera_info")

    cfg = types.SimpleNamespace(width=96, height=54, use_semantic=True)
    with pytest.raises(StreamingError, match="labels_every must be an integer >= 1"):
        make_engine("", no_camera, cfg, labels=("dataset", ""), labels_every=every)


def test_adapter_labels_every_kth_engine_frame():
    """labels_every 2: the adapter gives the stage the engine's frame index, so frames 0 and 2 are labelled, also
    when the engine already holds frames (a resumed run: frame 3 is not labelled, frame 4 is)."""
    k = default_intrinsics(96, 54)
    rgb, depth, _ = HomeRenderer(0).render(trajectory(4, 10.0)[0], k)
    rgb8 = (rgb * 255).astype(np.uint8)
    slam = _Recorder()
    adapter = EngineAdapter(slam, make_labels("geometry", "", k, streamed_labels=False, every=2))
    for t in range(3):
        adapter.add_frame(rgb8, depth, None, float(t))
    assert [g is not None for g in slam.given] == [True, False, True]
    resumed = _Recorder()
    resumed.poses = [np.eye(4)] * 3
    adapter = EngineAdapter(resumed, make_labels("geometry", "", k, streamed_labels=False, every=2))
    for t in range(2):
        adapter.add_frame(rgb8, depth, None, float(t))
    assert [g is not None for g in resumed.given] == [False, True]
    # frames the engine expects to be keyframes are labelled whatever labels_every says (here every 2nd frame)
    kf2 = _Recorder(keyframe_every=2)
    adapter = EngineAdapter(kf2, make_labels("geometry", "", k, streamed_labels=False, every=4))
    for t in range(5):
        adapter.add_frame(rgb8, depth, None, float(t))
    assert [g is not None for g in kf2.given] == [True, False, True, False, True]
