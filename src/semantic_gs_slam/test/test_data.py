"""Synthetic generator and dataset readers (Replica / SGS-SLAM / TUM layouts), including bad input."""

from __future__ import annotations

import os

import numpy as np
import pytest
from PIL import Image

from semantic_gs_slam.errors import DatasetError
from semantic_gs_slam.io.datasets import associate, load_colmap_poses, load_dataset, load_replica, load_sgs, load_tum
from semantic_gs_slam.synthetic.scenes import HomeRenderer, default_intrinsics, trajectory

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", ".."))


def test_generator_writes_replica_layout_and_reader_round_trips(tiny_home):
    for f in ("traj.txt", "cam.json", "semantic.json", "results/frame000000.jpg", "results/depth000009.png",
              "semantic/semantic000009.png"):
        assert os.path.isfile(tiny_home / f), f
    d16 = np.array(Image.open(tiny_home / "results" / "depth000000.png"))
    assert d16.dtype == np.uint16
    ds = load_dataset(str(tiny_home))
    assert len(ds) == 10 and ds.intrinsics.width == 120 and ds.classes[5] == "chair"
    f = ds[3]
    k = default_intrinsics(120, 68)
    rgb, depth, sem = HomeRenderer(0).render(trajectory(10, 20.0)[3], k)
    assert np.abs(f.depth - depth).max() <= 1.0 / 6553.5  # 16-bit quantisation only
    assert (f.semantics == sem).all()
    assert np.abs(f.rgb - rgb).mean() < 0.03  # JPEG
    np.testing.assert_allclose(f.gt_c2w, trajectory(10, 20.0)[3], atol=1e-9)
    labels = set(np.unique(np.concatenate([ds[i].semantics.ravel() for i in range(0, 10, 3)])))
    assert {1, 2, 4, 5}.issubset(labels)  # floor, wall, table, chair in view


def _png(path, arr):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    Image.fromarray(arr).save(path)


def _pose_line(t):
    m = np.eye(4)
    m[0, 3] = t
    return " ".join(str(x) for x in m.ravel())


def test_sgs_layout(tmp_path):
    for i in range(3):
        _png(str(tmp_path / "rgb" / f"rgb_{i}.png"), np.full((6, 8, 3), 40 * i, np.uint8))
        _png(str(tmp_path / "depth" / f"depth_{i}.png"), np.full((6, 8), 1500, np.uint16))
        _png(str(tmp_path / "semantic_class" / f"semantic_class_{i}.png"), np.full((6, 8), 3, np.uint8))
    (tmp_path / "traj_w_c.txt").write_text("\n".join(_pose_line(0.1 * i) for i in range(3)) + "\n")
    (tmp_path / "cam.json").write_text('{"width": 8, "height": 6, "fx": 4, "fy": 4, "cx": 3.5, "cy": 2.5}')
    ds = load_sgs(str(tmp_path))
    assert len(ds) == 3
    f = ds[2]
    assert f.depth[0, 0] == pytest.approx(1.5) and f.semantics[0, 0] == 3 and f.gt_c2w[0, 3] == pytest.approx(0.2)
    assert load_dataset(str(tmp_path)).sem_paths is not None  # auto-detected


def test_tum_layout_and_association(tmp_path):
    (tmp_path / "rgb").mkdir()
    (tmp_path / "depth").mkdir()
    rgb_t = [1.00, 1.033, 1.066, 1.50]
    depth_t = [1.01, 1.04, 1.07, 1.30]
    for t in rgb_t:
        _png(str(tmp_path / "rgb" / f"{t:.3f}.png"), np.zeros((4, 6, 3), np.uint8))
    for t in depth_t:
        _png(str(tmp_path / "depth" / f"{t:.3f}.png"), np.full((4, 6), 5000, np.uint16))
    (tmp_path / "rgb.txt").write_text("# rgb\n" + "".join(f"{t:.3f} rgb/{t:.3f}.png\n" for t in rgb_t))
    (tmp_path / "depth.txt").write_text("# depth\n" + "".join(f"{t:.3f} depth/{t:.3f}.png\n" for t in depth_t))
    gt_lines = "".join(f"{t:.3f} {t} 0 0 0 0 0 1\n" for t in (1.0, 1.05, 1.49))
    (tmp_path / "groundtruth.txt").write_text("# gt\n" + gt_lines)
    from semantic_gs_slam.config import Intrinsics

    ds = load_tum(str(tmp_path), Intrinsics(6, 4, 5.0, 5.0, 2.5, 1.5))
    # 1.50 has no depth within 0.02 s (1.30 is 0.2 s away): 3 frames, and the one left out is named
    assert len(ds) == 3
    assert ds.left_out == "frames left out: 1 without a depth image within 0.02 s (first: rgb.txt line 5)"
    f = ds[0]
    assert f.depth[0, 0] == pytest.approx(1.0) and f.gt_c2w[0, 3] == pytest.approx(1.0)
    assert ds[1].gt_c2w[0, 3] == pytest.approx(1.033)  # between the samples at 1.0 and 1.05
    (tmp_path / "groundtruth.txt").write_text("# gt\n" + "".join(f"{t:.3f} {t} 0 0 0 0 0 1\n" for t in (1.0, 1.01)))
    ds = load_tum(str(tmp_path), Intrinsics(6, 4, 5.0, 5.0, 2.5, 1.5))  # 1.033 and 1.066: past the last pose
    assert len(ds) == 1 and ds.left_out == ("frames left out: 1 without a depth image within 0.02 s (first: rgb.txt "
                                            "line 5); 2 without a reference pose at its time (first: rgb.txt line 3)")
    (tmp_path / "groundtruth.txt").write_text("# gt\n5.0 5 0 0 0 0 0 1\n")  # no pose near any frame
    with pytest.raises(DatasetError, match=r"no colour/depth/pose triples within 0.02 s .*: frames left out: 1 "
                                           r"without a depth image within 0.02 s \(first: rgb.txt line 5\); 3 without"):
        load_tum(str(tmp_path), Intrinsics(6, 4, 5.0, 5.0, 2.5, 1.5))
    assert associate([0.0, 1.0], [0.05, 2.0], 0.08) == [(0, 0)]
    assert associate([0.0, 1.0], [0.05, 2.0], 0.02) == []


def test_reference_pose_interpolation():
    from semantic_gs_slam.io.datasets import interpolate_pose

    def pose(yaw_deg: float, x: float) -> np.ndarray:
        c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
        m = np.eye(4)
        m[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
        m[0, 3] = x
        return m

    times = np.array([0.0, 0.01, 0.02, 0.5])
    poses = [pose(0, 0.0), pose(10, 0.1), pose(20, 0.2), pose(90, 1.0)]
    mid = interpolate_pose(times, poses, 0.005)
    np.testing.assert_allclose(mid, pose(5, 0.05), atol=1e-9)  # halfway: 5 degrees, 5 cm
    np.testing.assert_allclose(interpolate_pose(times, poses, 0.01), poses[1], atol=1e-12)
    assert interpolate_pose(times, poses, 0.3) is None  # samples 0.48 s apart and none within 0.02 s
    np.testing.assert_allclose(interpolate_pose(times, poses, 0.51), poses[3])  # past the last: the nearest
    assert interpolate_pose(times, poses, 0.6) is None and interpolate_pose(times, poses, -0.1) is None


def test_bad_input_gives_clear_errors(tmp_path, tiny_home):
    with pytest.raises(DatasetError, match="not found"):
        load_dataset(str(tmp_path / "nope"))
    with pytest.raises(DatasetError, match="cannot tell the layout"):
        load_dataset(str(tmp_path))
    # missing trajectory
    (tmp_path / "results").mkdir()
    with pytest.raises(DatasetError, match="traj.txt"):
        load_replica(str(tmp_path))
    # bad trajectory line
    (tmp_path / "traj.txt").write_text("1 2 3\n")
    _png(str(tmp_path / "results" / "frame000000.jpg"), np.zeros((6, 8, 3), np.uint8))
    _png(str(tmp_path / "results" / "depth000000.png"), np.zeros((5, 8), np.uint16))
    with pytest.raises(DatasetError, match="expected 16 numbers"):
        load_replica(str(tmp_path))
    (tmp_path / "traj.txt").write_text(_pose_line(0) + "\n")
    (tmp_path / "cam.json").write_text('{"width": 8, "height": 6, "fx": 4, "fy": 4, "cx": 3.5, "cy": 2.5}')
    ds = load_replica(str(tmp_path))
    with pytest.raises(DatasetError, match="sizes differ"):
        ds[0]
    # a colour image without its depth image: left out, and named
    _png(str(tmp_path / "results" / "frame000001.jpg"), np.zeros((6, 8, 3), np.uint8))
    ds = load_replica(str(tmp_path))
    assert len(ds) == 1 and ds.left_out == "frames left out: 1 without a depth image (first: frame 1)"


def test_replica_files_pair_by_their_numbers_never_by_position(tmp_path):
    """Frame 2's colour and depth missing: frames 0, 1, 3 keep their own depth and trajectory line (by position, 3's
    colour went with 2's pose); a number with colour and no depth is named."""
    (tmp_path / "results").mkdir()
    for i in (0, 1, 3):
        _png(str(tmp_path / "results" / f"frame{i:06d}.jpg"), np.full((6, 8, 3), 10 * i, np.uint8))
        _png(str(tmp_path / "results" / f"depth{i:06d}.png"), np.full((6, 8), 1000 + i, np.uint16))
    (tmp_path / "traj.txt").write_text("\n".join(_pose_line(t) for t in range(4)) + "\n")
    ds = load_replica(str(tmp_path))
    assert [os.path.basename(p) for p in ds.depth_paths] == ["depth000000.png", "depth000001.png", "depth000003.png"]
    assert [p[0, 3] for p in ds.poses] == [0.0, 1.0, 3.0] and list(ds.timestamps) == [0.0, 1.0, 3.0]
    _png(str(tmp_path / "results" / "frame3.jpg"), np.zeros((6, 8, 3), np.uint8))  # frame 3 again
    with pytest.raises(DatasetError, match="frame 3 is given twice"):
        load_replica(str(tmp_path))
    assert ds.left_out == ""
    os.remove(tmp_path / "results" / "frame3.jpg")
    os.remove(tmp_path / "results" / "depth000003.png")  # frame 3 has colour only: left out, the others keep theirs
    ds = load_replica(str(tmp_path))
    assert list(ds.timestamps) == [0.0, 1.0] and [p[0, 3] for p in ds.poses] == [0.0, 1.0]
    assert ds.left_out == "frames left out: 1 without a depth image (first: frame 3)"
    _png(str(tmp_path / "results" / "depth000003.png"), np.full((6, 8), 1003, np.uint16))
    (tmp_path / "traj.txt").write_text("\n".join(_pose_line(t) for t in range(3)) + "\n")  # no line for frame 3
    ds = load_replica(str(tmp_path))
    assert list(ds.timestamps) == [0.0, 1.0]
    assert ds.left_out == ("frames left out: 1 without a line in traj.txt (3 lines; line n is frame n, from 0) "
                           "(first: frame 3)")
    (tmp_path / "semantic").mkdir()  # a label image for frame 0 only: 1 and 3 lack theirs (and 3 its line too)
    _png(str(tmp_path / "semantic" / "semantic000000.png"), np.zeros((6, 8), np.uint8))
    ds = load_replica(str(tmp_path))
    assert len(ds) == 1 and ds.left_out == "frames left out: 2 without a label image (first: frame 1)"  # each once
    (tmp_path / "traj.txt").write_text("")
    with pytest.raises(DatasetError, match="no frame has colour, depth, labels and a trajectory line: frames left "
                                           "out: 2 without a label image"):
        load_replica(str(tmp_path))


@pytest.mark.parametrize("line, words", [
    ("2 0 0 0 0 2 0 0 0 0 2 0 0 0 0 1", "not orthonormal"),
    ("0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0", "last row is 0 0 0 0"),
    ("-1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1", "reflection"),
    ("nan 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1", "non-finite pose"),
])
def test_a_trajectory_line_that_is_no_camera_pose_is_named(tmp_path, line, words):
    (tmp_path / "results").mkdir()
    _png(str(tmp_path / "results" / "frame000000.jpg"), np.zeros((6, 8, 3), np.uint8))
    _png(str(tmp_path / "results" / "depth000000.png"), np.zeros((6, 8), np.uint16))
    (tmp_path / "traj.txt").write_text(line + "\n")
    with pytest.raises(DatasetError, match=f"traj.txt:1: .*{words}"):
        load_replica(str(tmp_path))


@pytest.mark.parametrize("file, line, words", [
    ("rgb.txt", "1.0", "rgb.txt:3: expected 2 fields (timestamp filename), got 1"),
    ("rgb.txt", "nan rgb/x.png", "rgb.txt:3: bad timestamp 'nan'"),
    ("groundtruth.txt", "1.0 0 0 0 0 0", "groundtruth.txt:3: expected 8 fields"),
    ("groundtruth.txt", "1.0 x 0 0 0 0 0 1", "groundtruth.txt:3: a pose is 7 numbers"),
    ("groundtruth.txt", "1.0 nan 0 0 0 0 0 1", "groundtruth.txt:3: the pose has NaN or inf"),
    ("groundtruth.txt", "1.0 0 0 0 0 0 0 0", "groundtruth.txt:3: the quaternion has zero length"),
])
def test_a_tum_list_line_that_cannot_be_read_is_named(tmp_path, file, line, words):
    for name in ("rgb.txt", "depth.txt", "groundtruth.txt"):
        first = "0.0 0 0 0 0 0 0 1" if name == "groundtruth.txt" else f"0.0 {name[:-4]}/0.png"
        (tmp_path / name).write_text(f"# {name}\n{first}\n" + (line + "\n" if name == file else ""))
    with pytest.raises(DatasetError, match=words.replace("(", r"\(").replace(")", r"\)")):
        load_tum(str(tmp_path))


def test_supersampled_colour_keeps_centre_ray_depth_and_labels():
    ren, k = HomeRenderer(), default_intrinsics(40, 24)
    c2w = trajectory(3)[1]
    rgb1, d1, s1 = ren.render(c2w, k)
    rgb3, d3, s3 = ren.render(c2w, k, supersample=3)
    np.testing.assert_array_equal(d3, d1)  # the middle of the 3 x 3 rays is the pixel-centre ray
    np.testing.assert_array_equal(s3, s1)
    assert rgb3.shape == rgb1.shape and 0 < np.abs(rgb3 - rgb1).mean() < 0.1  # averaged, not another view
    # averaging over the pixel removes texture energy above the pixel frequency: smoother images
    assert np.abs(np.diff(rgb3, axis=1)).mean() < np.abs(np.diff(rgb1, axis=1)).mean()
    with pytest.raises(ValueError, match="odd"):
        ren.render(c2w, k, supersample=2)


def test_colmap_pose_lines_are_world_to_camera(tmp_path):
    """COLMAP's convention by hand: a camera at (1, 2, 3) turned 90 degrees about z; the file holds its
    world-to-camera quaternion (w x y z) and translation."""
    from semantic_gs_slam.geometry import fixed_offset

    c2w = np.eye(4)
    c2w[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # +90 deg about z
    c2w[:3, 3] = [1, 2, 3]
    w2c = np.linalg.inv(c2w)
    h = np.sqrt(0.5)  # w2c turns -90 deg about z: q = (cos 45, 0, 0, -sin 45)
    t = w2c[:3, 3]
    path = tmp_path / "poses.txt"
    path.write_text(f"# NAME QW QX QY QZ TX TY TZ FOCAL\n\nseq-01/frame-000000.color.png {h} 0 0 {-h} "
                    f"{t[0]} {t[1]} {t[2]} 525.0\n")
    got = load_colmap_poses(str(path))
    np.testing.assert_allclose(got["seq-01/frame-000000.color.png"], c2w, atol=1e-12)
    for bad, why in [("a 1 0 0 0 1 2", "7 fields"), ("a 1 0 0 0 1 2 x", "x"), ("a 2 0 0 0 1 2 3", "unit quaternion")]:
        path.write_text("# header\n" + bad + "\n")
        with pytest.raises(DatasetError, match=f"poses.txt:2: bad pose line.*{why}"):
            load_colmap_poses(str(path))
    with pytest.raises(DatasetError, match="missing pose file"):
        load_colmap_poses(str(tmp_path / "nope.txt"))
    # the fixed offset between two cameras of one rig comes back from their poses
    x = np.eye(4)
    x[:3, :3] = c2w[:3, :3].T
    x[:3, 3] = [0.025, 0.0, -0.002]
    a = [c2w, w2c, np.eye(4)]
    np.testing.assert_allclose(fixed_offset(a, [p @ x for p in a]), x, atol=1e-12)


def test_degraded_frames_noisier_depth_and_blurred_colour(tiny_home):
    from semantic_gs_slam.io.degrade import DegradedDataset, kinect_axial_noise, noisy_depth

    depth = np.full((200, 300), 3.0, np.float32)
    depth[:10] = 0.0
    out = noisy_depth(depth, 2.0, seed=7)
    assert (out[:10] == 0).all() and out.dtype == np.float32  # missing stays missing
    assert np.std(out[10:] - 3.0) == pytest.approx(2 * kinect_axial_noise(np.array(3.0)), rel=0.05)  # 2 x 1.4 cm
    np.testing.assert_array_equal(out, noisy_depth(depth, 2.0, seed=7))  # repeatable per frame
    ds = load_dataset(str(tiny_home))
    deg = DegradedDataset(ds, depth_noise=1.0, blur=1)
    assert len(deg) == len(ds) and deg.intrinsics == ds.intrinsics and deg.poses is ds.poses
    f = deg[4]
    np.testing.assert_allclose(f.rgb, np.mean([ds[3].rgb, ds[4].rgb, ds[5].rgb], axis=0), atol=1e-6)
    assert f.depth.shape == ds[4].depth.shape and not np.array_equal(f.depth, ds[4].depth)
    np.testing.assert_allclose(deg[0].rgb, np.mean([ds[0].rgb, ds[1].rgb], axis=0), atol=1e-6)  # the first frame
    assert "Kinect" in deg.describe() and "3 frames" in deg.describe()
    for bad in ({"depth_noise": -1.0}, {"depth_noise": float("nan")}, {"blur": -1}, {"gain": 1.0}, {"gain": -0.1},
                {"gain": 0.2, "gain_period": 0.0}):
        with pytest.raises(ValueError):
            DegradedDataset(ds, **bad)
    swing = DegradedDataset(ds, gain=0.5, gain_period=8.0)  # frame 2: a quarter swing, 1.5 times as bright
    np.testing.assert_allclose(swing[2].rgb, np.clip(ds[2].rgb * 1.5, 0, 1), atol=1e-6)
    np.testing.assert_allclose(swing[6].rgb, ds[6].rgb * 0.5, atol=1e-6)
    np.testing.assert_array_equal(swing[0].rgb, ds[0].rgb)
    np.testing.assert_array_equal(swing[2].depth, ds[2].depth)  # the depth is left alone
    assert "±50 % every 8 frames" in swing.describe()
    holes = DegradedDataset(ds, holes=0.3)  # 30 % of the depth pixels dropped, repeatably, colour untouched
    had = ds[3].depth > 0
    dropped = had & (holes[3].depth == 0)
    assert dropped.sum() / had.sum() == pytest.approx(0.3, abs=0.03)
    np.testing.assert_array_equal(holes[3].depth[~dropped], ds[3].depth[~dropped])
    np.testing.assert_array_equal(holes[3].depth, holes[3].depth)  # seeded by the frame
    np.testing.assert_array_equal(holes[3].rgb, ds[3].rgb)
    assert "30 % of the depth pixels dropped" in holes.describe()
    for bad in (1.0, -0.1):
        with pytest.raises(ValueError, match="holes"):
            DegradedDataset(ds, holes=bad)
    lag = DegradedDataset(ds, colour_lag=2)  # frame i shows recorded frame i + 2's colour, its own depth
    np.testing.assert_array_equal(lag[1].rgb, ds[3].rgb)
    np.testing.assert_array_equal(lag[1].depth, ds[1].depth)
    np.testing.assert_array_equal(lag[len(ds) - 1].rgb, ds[len(ds) - 1].rgb)  # clamped at the end
    lag_blur = DegradedDataset(ds, colour_lag=-1, blur=1)  # the lag applies to the blurred frames as well
    np.testing.assert_allclose(lag_blur[4].rgb, np.mean([ds[2].rgb, ds[3].rgb, ds[4].rgb], axis=0), atol=1e-6)
    assert "colour from +2 recorded frames" in lag.describe()
    with pytest.raises(ValueError, match="colour_lag"):
        DegradedDataset(ds, colour_lag=0.5)


def test_drop_frames_leaves_out_frames_unevenly_and_repeatably_keeping_the_first():
    from semantic_gs_slam.io.degrade import drop_frames

    kept = drop_frames(range(250, 500), 0.5)
    assert kept[0] == 250 and kept == drop_frames(list(range(250, 500)), 0.5) and set(kept) <= set(range(250, 500))
    assert 100 <= len(kept) <= 150  # about half
    assert len(set(np.diff(kept).tolist())) >= 4  # uneven steps: what a time-scaled guess is for
    assert drop_frames(range(10), 0.0) == list(range(10))
    for bad in (1.0, -0.1):
        with pytest.raises(ValueError, match="dropped"):
            drop_frames(range(10), bad)


def test_a_colour_calibration_is_written_whole_or_not_at_all(tmp_path):
    """The loaders read the file on their own: it is renamed into place, and a folder that is not there is an
    OSError that leaves nothing behind."""
    from semantic_gs_slam.io.colour_registration import ColourCalib, load, save

    calib = ColourCalib(530.0, 531.0, 320.5, 240.5, 0.025)
    save(calib, str(tmp_path / "colour-calibration.json"), note="test")
    assert load(str(tmp_path / "colour-calibration.json")) == calib and os.listdir(tmp_path) == [
        "colour-calibration.json"]
    with pytest.raises(OSError):
        save(calib, str(tmp_path / "missing" / "c.json"))
    with pytest.raises(OSError):
        save(calib, str(tmp_path))  # a folder
    assert sorted(os.listdir(tmp_path)) == ["colour-calibration.json"]


def test_a_working_size_is_two_whole_numbers_up_to_8k():
    from semantic_gs_slam.io.datasets import parse_size

    assert parse_size("320x240") == (320, 240) and parse_size(" 8192 X 8192 ") == (8192, 8192)
    for bad in ("abc", "0x240", "99999999x99999999", "8193x100", "-5x5", "320x"):
        with pytest.raises(DatasetError, match="each 1 .. 8192"):
            parse_size(bad)
