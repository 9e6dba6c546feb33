"""Where a dataset's camera comes from: --intrinsics / --depth-scale, --camera presets, cam.json (every layout), the
folder's name (TUM RGB-D fr1/fr2/fr3), the layout's own; their order, the working size, and bad input."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
from PIL import Image

from semantic_gs_slam.config import Intrinsics
from semantic_gs_slam.errors import DatasetError
from semantic_gs_slam.io.datasets import (
    CAMERA_PRESETS,
    TUM_INTRINSICS,
    camera_from_name,
    load_dataset,
    parse_intrinsics,
    scale_intrinsics,
)
from semantic_gs_slam.run import main


def _png(path, arr):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    Image.fromarray(arr).save(path)


def _tum(root, w=8, h=6, raw=5000):
    """Two TUM RGB-D frames of w x h (depth ``raw`` units), no ground truth."""
    for t in (1.0, 1.1):
        _png(os.path.join(root, "rgb", f"{t:.1f}.png"), np.zeros((h, w, 3), np.uint8))
        _png(os.path.join(root, "depth", f"{t:.1f}.png"), np.full((h, w), raw, np.uint16))
    with open(os.path.join(root, "rgb.txt"), "w") as fh:
        fh.write("".join(f"{t:.1f} rgb/{t:.1f}.png\n" for t in (1.0, 1.1)))
    with open(os.path.join(root, "depth.txt"), "w") as fh:
        fh.write("".join(f"{t:.1f} depth/{t:.1f}.png\n" for t in (1.0, 1.1)))
    return str(root)


def _seven_scenes(root, w=8, h=6):
    for i in range(2):
        _png(os.path.join(root, f"frame-{i:06d}.color.png"), np.zeros((h, w, 3), np.uint8))
        _png(os.path.join(root, f"frame-{i:06d}.depth.png"), np.full((h, w), 1000, np.uint16))
    return str(root)


def _cam(root, **kw):
    doc = {"width": 8, "height": 6, "fx": 7.0, "fy": 7.5, "cx": 3.5, "cy": 2.5, **kw}
    with open(os.path.join(root, "cam.json"), "w") as fh:
        json.dump(doc, fh)
    return Intrinsics(doc["width"], doc["height"], doc["fx"], doc["fy"], doc["cx"], doc["cy"])


def test_folder_name_selects_the_tum_preset_and_the_log_line_says_so(tmp_path):
    root = _tum(tmp_path / "rgbd_dataset_freiburg1_xyz", 640, 480, raw=10000)
    ds = load_dataset(root)
    assert ds.intrinsics == CAMERA_PRESETS["tum-fr1"].intrinsics and ds.depth_scale == 5000
    assert ds[0].depth[0, 0] == pytest.approx(2.0)
    line = ds.camera_line()
    assert "fx 517.30" in line and "rgbd_dataset_freiburg1_xyz" in line and "NOT undistorted" in line
    assert "\n" not in line
    assert camera_from_name(str(tmp_path / "rgbd_dataset_freiburg3_long_office_household")) == "tum-fr3"
    assert camera_from_name(str(tmp_path / "rgbd_dataset_freiburg2_desk" / "seq")) == "tum-fr2"
    assert camera_from_name(str(tmp_path / "freiburg12")) is None
    fr3 = load_dataset(_tum(tmp_path / "rgbd_dataset_freiburg3_walking", 640, 480))
    assert fr3.intrinsics == CAMERA_PRESETS["tum-fr3"].intrinsics and "undistorted" not in fr3.camera_line()


def test_camera_option_overrides_the_folder_name(tmp_path):
    root = _tum(tmp_path / "rgbd_dataset_freiburg1_xyz", 640, 480)
    ds = load_dataset(root, camera="tum-fr2")
    assert ds.intrinsics == CAMERA_PRESETS["tum-fr2"].intrinsics and "--camera" in ds.intrinsics_source
    plain = load_dataset(root, camera="none")
    assert plain.intrinsics == TUM_INTRINSICS and plain.intrinsics_source == "the layout's default"
    with pytest.raises(DatasetError, match="unknown camera 'tum-fr4'"):
        load_dataset(root, camera="tum-fr4")


@pytest.mark.parametrize("layout", ["tum", "7scenes"])
def test_cam_json_is_read_for_every_layout_and_beats_the_folder_name(tmp_path, layout):
    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    root = _tum(root) if layout == "tum" else _seven_scenes(root)
    k = _cam(root, depth_scale=2000)
    ds = load_dataset(root)
    assert ds.intrinsics == k and ds.depth_scale == 2000
    assert ds.intrinsics_source == ds.depth_scale_source == os.path.join(root, "cam.json")
    assert ds.distortion is None  # the preset's distortion went with its intrinsics
    # without depth_scale in cam.json, the next source gives it (here the folder-name preset: 5000)
    _cam(root)
    ds = load_dataset(root)
    assert ds.intrinsics == k and ds.depth_scale == 5000 and "folder name" in ds.depth_scale_source


def test_a_tum_layout_folder_with_calibration_txt_takes_its_camera_from_it(tmp_path):
    """ETH3D's RGB-D sequences: TUM's files plus ``calibration.txt`` (``fx fy cx cy``); the size is the images'.
    cam.json and the command line still outrank it; a file that is not one line of four numbers is named."""
    root = _tum(tmp_path / "table_3")
    (tmp_path / "table_3" / "calibration.txt").write_text("7.25 7.5 3.75 2.5\n")
    ds = load_dataset(root)
    assert ds.intrinsics == Intrinsics(8, 6, 7.25, 7.5, 3.75, 2.5) and ds.depth_scale == 5000
    assert ds.intrinsics_source == os.path.join(root, "calibration.txt")
    assert f"(from {os.path.join(root, 'calibration.txt')})" in ds.camera_line()
    assert load_dataset(root, intrinsics=(6.0, 6.5, 4.0, 3.0)).intrinsics.fx == 6.0
    k = _cam(root)
    assert load_dataset(root).intrinsics == k
    os.remove(os.path.join(root, "cam.json"))
    for text in ("7.25 7.5 3.75\n", "7.25 7.5 3.75 2.5\n1 2 3 4\n", "-7 7.5 3.75 2.5\n", "a b c d\n", ""):
        (tmp_path / "table_3" / "calibration.txt").write_text(text)
        with pytest.raises(DatasetError, match="calibration.txt: expected one line 'fx fy cx cy'"):
            load_dataset(root)
        # a file in another format does not stop a source that outranks it
        assert load_dataset(root, intrinsics=(6.0, 6.5, 4.0, 3.0)).intrinsics == Intrinsics(8, 6, 6.0, 6.5, 4.0, 3.0)
        assert load_dataset(root, camera="tum-fr3").intrinsics == CAMERA_PRESETS["tum-fr3"].intrinsics


def test_command_line_beats_everything_and_takes_the_size_from_the_images(tmp_path):
    root = _tum(tmp_path / "rgbd_dataset_freiburg1_xyz")
    _cam(root, depth_scale=2000)
    ds = load_dataset(root, intrinsics=(6.0, 6.5, 4.0, 3.0), depth_scale=1000.0, camera="tum-fr3")
    assert ds.intrinsics == Intrinsics(8, 6, 6.0, 6.5, 4.0, 3.0) and ds.depth_scale == 1000
    assert "--intrinsics" in ds.intrinsics_source and "--depth-scale" in ds.depth_scale_source
    assert ds[1].depth[0, 0] == pytest.approx(5.0)  # 5000 raw units at 1000 per metre
    named = load_dataset(root, camera="tum-fr3")  # --camera outranks cam.json
    assert named.intrinsics == CAMERA_PRESETS["tum-fr3"].intrinsics and named.depth_scale == 5000


@pytest.mark.parametrize("source", ["layout", "cam.json", "preset", "given"])
def test_intrinsics_are_scaled_to_the_working_size_whatever_their_source(tmp_path, source):
    root = _tum(tmp_path / ("rgbd_dataset_freiburg2_desk" if source == "preset" else "seq"), 16, 12)
    kw = {}
    if source == "cam.json":
        _cam(root, width=16, height=12)
    elif source == "given":
        kw["intrinsics"] = (14.0, 15.0, 7.5, 5.5)
    native = load_dataset(root, **kw).intrinsics
    w, h = native.width // 2, native.height // 2
    ds = load_dataset(root, size=(w, h), **kw)
    assert ds.native_intrinsics == native and ds.intrinsics == scale_intrinsics(native, w, h)
    assert ds.intrinsics.fx == pytest.approx(native.fx / 2)
    assert f"working size {w}x{h}" in ds.camera_line()
    if source == "given":  # the frames come out at the working size
        assert ds[0].depth.shape == (h, w)


@pytest.mark.parametrize("text, message", [
    ("{not json", "not a readable JSON"),
    ("[1, 2]", "expected a JSON object"),
    ('{"width": 8, "height": 6, "fx": 7, "fy": 7, "cx": 3.5}', "missing key.*'cy'"),
    ('{"width": 8, "height": 6, "fx": 7, "fy": 7, "cx": 3.5, "cy": 2.5, "depthscale": 1000}',
     "unknown key.*'depthscale'"),
    ('{"width": 8, "height": 6, "fx": "7", "fy": 7, "cx": 3.5, "cy": 2.5}', "'fx' must be a finite number"),
    ('{"width": 8, "height": 6, "fx": -7, "fy": 7, "cx": 3.5, "cy": 2.5}', "'fx' must be positive"),
    ('{"width": 8.5, "height": 6, "fx": 7, "fy": 7, "cx": 3.5, "cy": 2.5}', "'width' must be a positive whole"),
    ('{"width": 8, "height": 6, "fx": 7, "fy": 7, "cx": 3.5, "cy": 2.5, "depth_scale": 0}',
     "'depth_scale' must be positive"),
])
def test_a_malformed_cam_json_is_refused_with_the_reason(tmp_path, text, message):
    root = _tum(tmp_path)
    (tmp_path / "cam.json").write_text(text)
    with pytest.raises(DatasetError, match=message) as err:
        load_dataset(root)
    assert "cam.json" in str(err.value)


@pytest.mark.parametrize("text", ["517,516,318", "a,b,c,d", "0,516,318,255", "517,516,318,255,1", "", "nan,1,1,1"])
def test_a_bad_intrinsics_string_is_a_usage_error(tmp_path, capsys, text):
    with pytest.raises(DatasetError):
        parse_intrinsics(text)
    with pytest.raises(SystemExit) as exc:
        main(["--dataset", str(tmp_path), "--out", str(tmp_path / "out"), "--intrinsics", text])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--intrinsics" in err and ("fx,fy,cx,cy" in err or "focal lengths" in err)


@pytest.mark.parametrize("text", ["-1", "0", "mm"])
def test_a_bad_depth_scale_is_a_usage_error(tmp_path, capsys, text):
    with pytest.raises(SystemExit) as exc:
        main(["--dataset", str(tmp_path), "--out", str(tmp_path / "out"), "--depth-scale", text])
    assert exc.value.code == 2 and "depth units per metre" in capsys.readouterr().err


def test_parse_intrinsics_reads_four_numbers():
    assert parse_intrinsics(" 517.3, 516.5 ,318.6,255.3") == (517.3, 516.5, 318.6, 255.3)


def test_the_run_prints_the_camera_line_with_its_sources(tmp_path, capsys):
    root = _tum(tmp_path / "rgbd_dataset_freiburg1_xyz")
    _cam(root)
    # --first past the end: the run stops with exit 2 after opening the dataset (no SLAM work), the line printed
    code = main(["--dataset", root, "--out", str(tmp_path / "out"), "--first", "99", "--depth-scale", "1000",
                 "--size", "4x3"])
    err = capsys.readouterr().err
    assert code == 2 and "no frames selected" in err
    line = next(ln for ln in err.splitlines() if ln.startswith("camera: "))
    assert f"fx 7.00 fy 7.50 cx 3.50 cy 2.50 at 8x6 (from {os.path.join(root, 'cam.json')})" in line
    assert "depth scale 1000 per metre (from --depth-scale)" in line and "working size 4x3: fx 3.50" in line
    assert "left out" not in err
    with open(os.path.join(root, "rgb.txt"), "a") as fh:
        fh.write("1.5 rgb/1.0.png\n")  # no depth within 0.02 s of 1.5: the run names it
    assert main(["--dataset", root, "--out", str(tmp_path / "out"), "--first", "99"]) == 2
    assert f"{root}: frames left out: 1 without a depth image within 0.02 s (first: rgb.txt line 3)" in \
        capsys.readouterr().err
