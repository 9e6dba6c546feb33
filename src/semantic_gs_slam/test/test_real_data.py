"""Real-sensor dataset layouts: 7-Scenes and TUM RGB-D from real-format files the tests write, working-size
resizing with scaled intrinsics, frame ranges, and (when present) the shared 7-Scenes sequence."""

from __future__ import annotations

import os

import numpy as np
import pytest
from PIL import Image

from semantic_gs_slam.config import Intrinsics
from semantic_gs_slam.errors import DatasetError
from semantic_gs_slam.geometry import quat_to_rotmat
from semantic_gs_slam.io.datasets import (
    detect_layout,
    frame_indices,
    load_7scenes,
    load_dataset,
    load_tum,
    parse_size,
    resize_nearest,
)

SHARED_7SCENES = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", "..", "..", "shared", "data",
                                              "7scenes-redkitchen-0-499"))


def _pose(i: int) -> np.ndarray:
    m = np.eye(4)
    a = 0.05 * i
    m[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    m[:3, 3] = (0.1 * i, -0.02 * i, 0.3)
    return m


def write_7scenes(root, n: int = 3, w: int = 64, h: int = 48, k_file: bool = True, poses: bool = True):
    """A tiny 7-Scenes sequence in the real format: JPEG colour, 16-bit mm depth (0 and 65535 invalid)."""
    os.makedirs(root, exist_ok=True)
    rng = np.random.default_rng(0)
    depths = []
    for i in range(n):
        rgb = (rng.random((h, w, 3)) * 255).astype(np.uint8)
        Image.fromarray(rgb).save(os.path.join(root, f"frame-{i:06d}.color.jpg"), quality=95)
        d = (1000 + 100 * i + np.arange(w)[None, :] * 10 + np.zeros((h, 1))).astype(np.uint16)
        d[0, 0] = 0
        d[0, 1] = 65535
        depths.append(d)
        Image.fromarray(d).save(os.path.join(root, f"frame-{i:06d}.depth.png"))
        if poses:
            np.savetxt(os.path.join(root, f"frame-{i:06d}.pose.txt"), _pose(i))
    if k_file:
        np.savetxt(os.path.join(root, "camera-intrinsics.txt"), [[58.5, 0, 32], [0, 58.5, 24], [0, 0, 1]])
    return depths


def test_7scenes_layout_is_detected_and_read_in_metres(tmp_path):
    depths = write_7scenes(tmp_path / "seq-01")
    assert detect_layout(str(tmp_path / "seq-01")) == "7scenes"
    ds = load_dataset(str(tmp_path / "seq-01"))
    assert len(ds) == 3
    k = ds.intrinsics
    assert (k.width, k.height, k.fx, k.fy, k.cx, k.cy) == (64, 48, 58.5, 58.5, 32.0, 24.0)
    f = ds[2]
    assert f.rgb.shape == (48, 64, 3) and f.rgb.dtype == np.float32 and 0 <= f.rgb.min() and f.rgb.max() <= 1
    assert f.depth[0, 0] == 0 and f.depth[0, 1] == 0  # both invalid codes
    np.testing.assert_allclose(f.depth[5, 7], depths[2][5, 7] / 1000.0, rtol=1e-6)
    np.testing.assert_allclose(f.gt_c2w, _pose(2), atol=1e-12)
    assert f.timestamp == pytest.approx(2 / 30.0) and f.semantics is None


def test_7scenes_without_pose_files_or_k_file(tmp_path):
    write_7scenes(tmp_path, k_file=False, poses=False)
    ds = load_7scenes(str(tmp_path))
    assert ds.poses is None
    assert ds.intrinsics.fx == 585.0  # the Kinect default (and its 640x480 size: frames then do not match)
    with pytest.raises(DatasetError, match="does not match the intrinsics"):
        ds[0]


@pytest.mark.parametrize("missing, kept, note", [
    ("frame-000001.depth.png", [0, 2], "1 without a depth image (first: frame 1)"),
    ("frame-000002.pose.txt", [0, 1], "1 without a pose file (first: frame 2)"),
    ("frame-000000.color.jpg", [1, 2], "1 without a colour image (first: frame 0)")])
def test_7scenes_frame_missing_a_file_is_left_out_and_named(tmp_path, missing, kept, note):
    """An incomplete copy still runs: the frames that have every file keep their own files, pose and time; the
    frames left out are counted and the first is named."""
    write_7scenes(tmp_path, n=3)
    os.remove(tmp_path / missing)
    ds = load_dataset(str(tmp_path))
    assert ds.left_out == f"frames left out: {note}"
    assert [round(t * 30) for t in ds.timestamps] == kept
    assert [p[0, 3] for p in ds.poses] == [_pose(i)[0, 3] for i in kept]
    assert [os.path.basename(p) for p in ds.depth_paths] == [f"frame-{i:06d}.depth.png" for i in kept]
    assert load_dataset(str(tmp_path), size=(32, 24)).left_out == ds.left_out  # the working size keeps the note


def test_7scenes_with_no_complete_frame_is_refused(tmp_path):
    write_7scenes(tmp_path, n=2)
    for i in range(2):
        os.remove(tmp_path / f"frame-{i:06d}.depth.png")
    with pytest.raises(DatasetError, match=r"no colour frame has a depth image and a pose file: frames left out: "
                                           r"2 without a depth image \(first: frame 0\)"):
        load_dataset(str(tmp_path))


@pytest.mark.parametrize("breakage, message", [("badpose", "4x4"), ("badk", "3x3")])
def test_7scenes_bad_files_are_reported(tmp_path, breakage, message):
    write_7scenes(tmp_path)
    if breakage == "badpose":
        np.savetxt(tmp_path / "frame-000001.pose.txt", np.eye(3))
    else:
        (tmp_path / "camera-intrinsics.txt").write_text("585 0 320\n0 585 240\n")
    with pytest.raises(DatasetError, match=message):
        load_dataset(str(tmp_path))
    if breakage == "badk":  # the K file is not needed when the command line gives the camera
        assert load_dataset(str(tmp_path), intrinsics=(58.5, 58.5, 32.0, 24.0)).intrinsics.fx == 58.5


def test_7scenes_scene_folder_names_its_sequences(tmp_path):
    write_7scenes(tmp_path / "seq-01")
    os.makedirs(tmp_path / "seq-02")
    with pytest.raises(DatasetError, match="seq-01, seq-02"):
        load_7scenes(str(tmp_path))
    with pytest.raises(DatasetError, match="cannot tell the layout"):
        load_dataset(str(tmp_path))


def test_resized_dataset_scales_intrinsics_and_never_blends_depth(tmp_path):
    depths = write_7scenes(tmp_path)
    ds = load_dataset(str(tmp_path), size=(32, 24), colour_calib="none")  # colour as recorded: plumbing only
    k = ds.intrinsics
    assert (k.width, k.height) == (32, 24)
    assert (k.fx, k.fy, k.cx, k.cy) == (29.25, 29.25, 15.75, 11.75)
    assert ds.native_intrinsics.width == 64
    f = ds[1]
    assert f.rgb.shape == (24, 32, 3) and f.depth.shape == (24, 32)
    native = set((depths[1] / 1000.0).astype(np.float32).ravel().tolist()) | {0.0}
    assert set(f.depth.ravel().tolist()) <= native  # nearest: only measured values (or 0), no blends
    # a point projects to the same place (in units of the image) before and after
    full = load_dataset(str(tmp_path), colour_calib="none")
    x, z = 0.2, 1.5
    u0 = full.intrinsics.fx * x / z + full.intrinsics.cx
    u1 = k.fx * x / z + k.cx
    assert (u1 + 0.5) / 32 == pytest.approx((u0 + 0.5) / 64)
    # colour: area average of the 2x2 block
    np.testing.assert_allclose(f.rgb[3, 4], full[1].rgb[6:8, 8:10].mean((0, 1)), atol=1e-5)
    with pytest.raises(DatasetError):
        ds.resized(0, 10)


def test_resize_nearest_keeps_ids():
    ids = np.arange(12).reshape(3, 4)
    np.testing.assert_array_equal(resize_nearest(ids, 2, 3), ids[:, [1, 3]])  # the pixel under each new centre
    assert resize_nearest(ids, 8, 6).shape == (6, 8)


def test_frame_indices_and_size_parsing():
    assert frame_indices(10, start=2, stride=3) == [2, 5, 8]
    assert frame_indices(10, stride=2, frames=3) == [0, 2, 4]
    assert frame_indices(10, start=1, stop=4) == [1, 2, 3]
    for bad in ({"stride": 0}, {"start": 10}, {"start": -1}):
        with pytest.raises(DatasetError):
            frame_indices(10, **bad)
    assert parse_size("320x240") == (320, 240) and parse_size(" 64X48 ") == (64, 48)
    for bad in ("320", "0x10", "axb", "320x240x3"):
        with pytest.raises(DatasetError, match="WIDTHxHEIGHT"):
            parse_size(bad)


def write_tum(root, w: int = 64, h: int = 48):
    """A TUM RGB-D sequence in the real format: headers, float timestamps, 30 Hz images with a depth stream
    offset by a few ms, 100 Hz ground truth with quaternions, 5000-scaled 16-bit depth."""
    os.makedirs(root / "rgb")
    os.makedirs(root / "depth")
    t0 = 1305031102.175304
    rgb_lines = ["# color images", "# file: 'rgbd_dataset_freiburg1_xyz.bag'", "# timestamp filename"]
    depth_lines = ["# depth maps", "# file: 'rgbd_dataset_freiburg1_xyz.bag'", "# timestamp filename"]
    for i in range(4):
        tr, td = t0 + i / 30.0, t0 + i / 30.0 + 0.012
        Image.fromarray(np.full((h, w, 3), 40 * i, np.uint8)).save(root / "rgb" / f"{tr:.6f}.png")
        d = np.full((h, w), 5000 * (1 + 0.1 * i), np.float64).astype(np.uint16)
        d[:2] = 0
        Image.fromarray(d).save(root / "depth" / f"{td:.6f}.png")
        rgb_lines.append(f"{tr:.6f} rgb/{tr:.6f}.png")
        depth_lines.append(f"{td:.6f} depth/{td:.6f}.png")
    gt = ["# ground truth trajectory", "# file: 'rgbd_dataset_freiburg1_xyz.bag'", "# timestamp tx ty tz qx qy qz qw"]
    for j in range(-5, 20):
        t = t0 + j / 100.0
        gt.append(f"{t:.4f} {1.3 + 0.01 * j:.4f} 0.6 1.6 0.0 0.0 0.38268343 0.92387953")  # 45 deg about z
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")


def test_tum_real_format_sequence(tmp_path):
    write_tum(tmp_path)
    assert detect_layout(str(tmp_path)) == "tum"
    ds = load_tum(str(tmp_path), intrinsics=None)
    assert len(ds) == 4 and ds.intrinsics.fx == 525.0
    ds = load_dataset(str(tmp_path), intrinsics=ds.intrinsics.__class__(64, 48, 52.5, 52.5, 31.95, 23.95))
    f = ds[2]
    assert f.depth[0, 0] == 0 and f.depth[10, 10] == pytest.approx(1.2, abs=1e-4)  # 5000 per metre
    assert f.rgb[0, 0, 0] == pytest.approx(80 / 255)
    assert f.timestamp == pytest.approx(1305031102.175304 + 2 / 30.0)
    r = quat_to_rotmat(__import__("torch").tensor([0.92387953, 0.0, 0.0, 0.38268343], dtype=__import__("torch")
                                                  .float64)).numpy()
    np.testing.assert_allclose(f.gt_c2w[:3, :3], r, atol=1e-6)
    assert f.gt_c2w[0, 0] == pytest.approx(np.cos(np.pi / 4), abs=1e-6)
    assert f.gt_c2w[0, 3] == pytest.approx(1.3 + 0.01 * 100 * (2 / 30.0), abs=1e-4)  # interpolated at t0 + 2/30 s
    small = ds.resized(32, 24)
    assert small[2].depth.shape == (24, 32) and small.intrinsics.fx == pytest.approx(26.25)


@pytest.mark.skipif(not os.path.isdir(SHARED_7SCENES), reason="the shared 7-Scenes sequence is not here")
def test_shared_7scenes_sequence_reads_at_working_size():
    ds = load_dataset(SHARED_7SCENES, size=(320, 240))
    assert len(ds) == 500 and ds.intrinsics.fx == pytest.approx(292.5)
    f = ds[0]
    assert f.rgb.shape == (240, 320, 3)
    assert 0.8 < (f.depth > 0).mean() < 0.97 and 0.3 < np.median(f.depth[f.depth > 0]) < 4.0
    np.testing.assert_allclose(f.gt_c2w, np.loadtxt(os.path.join(SHARED_7SCENES, "frame-000000.pose.txt")))


def _colmap_line(name: str, c2w: np.ndarray) -> str:
    from semantic_gs_slam.geometry import rotmat_to_quat

    w2c = np.linalg.inv(c2w)
    q = rotmat_to_quat(w2c[:3, :3])  # w x y z
    return f"{name} {' '.join(f'{v:.12f}' for v in q)} {' '.join(f'{v:.12f}' for v in w2c[:3, 3])} 585.0\n"


def test_reference_agreement_bench_fits_the_camera_offset_and_removes_the_scale(tmp_path, capsys):
    """``bench/reference_agreement.py`` on a tiny 7-Scenes sequence: the second reference is the dataset's own
    trajectory seen from a camera 2.5 cm to the side, in another world frame at 1.05x the size. Fitted offset 2.5 cm;
    ATE with scale 0 (scale 1.05); rigid ATE not 0; a wrong sequence name is refused clearly."""
    import sys

    from semantic_gs_slam.geometry import se3_exp

    bench = os.path.join(os.path.dirname(__file__), "..", "..", "..", "bench")
    sys.path.insert(0, bench)
    try:
        import reference_agreement
    finally:
        sys.path.remove(bench)
    import torch

    root = tmp_path / "seq"
    write_7scenes(str(root), n=8)
    x = np.eye(4)
    x[0, 3] = 0.025
    world = se3_exp(torch.tensor([0.2, -0.1, 0.4, 1.0, -2.0, 0.5], dtype=torch.float64)).numpy()
    second, offset = "", ""
    for i in range(8):
        p = world @ _pose(i) @ x
        p[:3, 3] *= 1.05
        second += _colmap_line(f"seq-01/frame-{i:06d}.color.png", p)
        offset += _colmap_line(f"seq-01/frame-{i:06d}.color.png", _pose(i) @ x)
    (tmp_path / "second.txt").write_text(second)
    (tmp_path / "offset.txt").write_text(offset)
    args = [str(root), "--second", str(tmp_path / "second.txt"), "--offset-from", str(tmp_path / "offset.txt")]
    assert reference_agreement.main(args) == 0
    out = capsys.readouterr().out
    assert "8 frames" in out and "2.50 cm / 0.00 deg from the dataset's (fitted)" in out
    cells = [c.strip() for c in out.splitlines()[-1].split("|")[1:-1]]
    assert cells[0] == "dataset reference vs second reference"
    assert float(cells[1]) > 1.0 and cells[2] == "0.00 (1.050)"  # rigid ATE sees the scale, the similarity does not
    with pytest.raises(SystemExit):
        reference_agreement.main(args + ["--sequence", "seq-02"])
    assert "not in" in capsys.readouterr().err
    # a run's params.npz (here: the dataset's own poses, 5 cm off at one frame) adds its two rows
    from semantic_gs_slam.config import Intrinsics
    from semantic_gs_slam.mapping.gaussian_map import GaussianMap, save_params

    ours = [_pose(i) for i in range(8)]
    ours[3] = ours[3].copy()
    ours[3][:3, 3] += [0.0, 0.05, 0.0]
    save_params(str(tmp_path / "params.npz"), GaussianMap(), Intrinsics(64, 48, 58.5, 58.5, 32, 24),
                [np.linalg.inv(p) for p in ours], [None] * 8, [0])
    assert reference_agreement.main(args + ["--map", str(tmp_path / "params.npz")]) == 0
    rows = {r.split("|")[1].strip(): [c.strip() for c in r.split("|")[2:-1]]
            for r in capsys.readouterr().out.splitlines() if r.startswith("| ours")}
    assert set(rows) == {"ours vs dataset reference", "ours vs second reference"}
    assert 1.0 < float(rows["ours vs dataset reference"][0]) < 5.0  # one of 8 frames 5 cm off
    with pytest.raises(SystemExit):  # a run over other frames is refused
        reference_agreement.main(args + ["--map", str(tmp_path / "params.npz"), "--frames", "4"])
    assert "--start/--stride/--frames" in capsys.readouterr().err


def test_a_7scenes_sequence_rewritten_in_tums_layout_reads_back_the_same(tmp_path):
    """``bench/as_tum.py``: TUM's files (PNG, 5000 per metre, own time stamps, a missing depth image, poses on 2
    of 3 frames) read back as the same frames: colour, depth in metres, and poses, interpolated where absent."""
    import sys

    bench = os.path.join(os.path.dirname(__file__), "..", "..", "..", "bench")
    sys.path.insert(0, bench)
    try:
        import as_tum
    finally:
        sys.path.remove(bench)
    src, out = str(tmp_path / "seq"), str(tmp_path / "tum")
    write_7scenes(src, n=6)
    assert as_tum.main([src, out, "--drop-depth", "3"]) == 0
    assert detect_layout(out) == "tum"
    k = Intrinsics(64, 48, 58.5, 58.5, 32.0, 24.0)
    a, b = load_dataset(src, intrinsics=k, colour_calib="none"), load_dataset(out, intrinsics=k)  # colour as recorded
    assert len(b) == 5  # frame 3's colour has no depth within 0.02 s: left out
    for j, i in enumerate([0, 1, 2, 4, 5]):
        fa, fb = a[i], b[j]
        np.testing.assert_array_equal(fb.rgb, fa.rgb)
        np.testing.assert_allclose(fb.depth, fa.depth, atol=1e-6)  # 65535 ("none" in 7-Scenes) stays none
        assert fb.depth[0, 1] == 0
        np.testing.assert_allclose(fb.gt_c2w, fa.gt_c2w, atol=2e-3)  # frames 1 and 4 interpolated between poses
    assert as_tum.main([str(tmp_path / "nothing"), out]) == 2
