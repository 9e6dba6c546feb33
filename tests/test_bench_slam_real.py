"""bench/slam_real.py's lost / recovered summary from the engine's ``stats()``."""

import importlib.util
import os
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _bench():
    spec = importlib.util.spec_from_file_location("bench_slam_real", os.path.join(ROOT, "bench", "slam_real.py"))
    mod = importlib.util.module_from_spec(spec)
    sys.modules["bench_slam_real"] = mod
    spec.loader.exec_module(mod)
    return mod


def test_lost_summary_counts_maps_to_dataset_frames_and_says_na_without_the_keys():
    lost_summary = _bench().lost_summary
    idx = [0, 2, 4, 6, 8, 10]  # --stride 2: engine frame n is dataset frame 2n
    assert lost_summary({"frames": 6}, idx) == ("n/a", "")
    assert lost_summary({"lost_frames": [], "recoveries": []}, idx) == ("0 / 0", "")
    counts, detail = lost_summary({"lost_frames": [2, 3, 5], "recoveries": [[2, 4]]}, idx)
    assert counts == "3 / 1"
    assert detail == "lost at dataset frames 4, 6, 10; recovered (lost at -> recovered at): 4->8"
    assert lost_summary({"lost_frames": [5], "recoveries": []}, idx)[1] == "lost at dataset frames 10; none recovered"


def test_lost_summary_says_how_many_lost_frames_were_re_posed():
    lost_summary = _bench().lost_summary
    stats = {"lost_frames": [2, 3, 4], "recoveries": [[2, 5]], "rejoined_frames": 2}
    assert lost_summary(stats, list(range(6)))[0] == "3 / 1 (2 lost frames re-posed in the map)"


def test_frames_that_cannot_be_read_or_that_the_engine_refuses_are_left_out_for_both_trackers(tmp_path):
    """Real files: frame 1's depth is all zero (a covered lens), frame 2's colour file is missing; frames 0 and 3
    are kept, the others named with the reason."""
    import numpy as np
    from PIL import Image

    from semantic_gs_slam.config import Intrinsics, SlamConfig
    from semantic_gs_slam.io.datasets import Dataset

    k = Intrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)
    rgb_paths, depth_paths = [], []
    for i in range(4):
        rgb, depth = str(tmp_path / f"{i}.png"), str(tmp_path / f"{i}.depth.png")
        if i != 2:
            Image.fromarray(np.full((24, 32, 3), 100 + i, np.uint8)).save(rgb)
        Image.fromarray(np.full((24, 32), 0 if i == 1 else 1500, np.uint16)).save(depth)
        rgb_paths.append(rgb)
        depth_paths.append(depth)
    ds = Dataset(k, rgb_paths, depth_paths, None, [np.eye(4)] * 4, [0.0, 1.0, 2.0, 3.0], 1000.0)
    frames, refused = _bench().load_frames(ds, [0, 1, 2, 3], SlamConfig(intrinsics=k))
    assert sorted(frames) == [0, 3]
    assert [i for i, _ in refused] == [1, 2]
    assert "valid" in refused[0][1] and "2.png" in refused[1][1], refused
    assert np.allclose(frames[3].depth, 1.5)


@pytest.mark.parametrize("args, words", [
    (["/nonexistent-folder"], "error: dataset folder not found"),
    (["{data}", "--size", "abc"], "error: size must be WIDTHxHEIGHT"),
    (["{data}", "--stride", "0"], "error: need stride >= 1"),
])
def test_a_dataset_or_option_it_cannot_use_is_one_error_line_and_exit_2(tmp_path, monkeypatch, capsys, args,
                                                                         words):
    from semantic_gs_slam.synthetic.scenes import generate

    generate(str(tmp_path / "home"), frames=2, width=32, height=18)
    argv = [a.format(data=tmp_path / "home") for a in args]
    monkeypatch.setattr(sys, "argv", ["slam_real.py", *argv, "--no-open3d"])
    assert _bench().main() == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err, err


def test_lost_summary_names_the_spans_that_resumed_mapping_on_their_own_track():
    lost_summary = _bench().lost_summary
    stats = {"lost_frames": [2, 3, 4], "recoveries": [[2, 5]], "resumed": [[2, 5]]}
    assert lost_summary(stats, [0, 2, 4, 6, 8, 10])[0] == \
        "3 / 1 (1 resumed mapping on their own track (not relocalised then): 4->10)"
    stats["reanchored"] = [[2, 5, 103.4, 14.25]]
    assert lost_summary(stats, [0, 2, 4, 6, 8, 10])[0].endswith(
        "; 1 resumed track(s) later relocalised and moved into the map's frame: from 4 at 10 by 103 cm, 14.2 deg)")


def test_a_jump_takes_the_time_out_of_the_stream_a_gap_leaves_in():
    """--jump's frames after the jump come one usual step after the frame before it (a steady clock); the frames
    and their other fields are unchanged."""
    import numpy as np

    from semantic_gs_slam.io.datasets import Frame

    idx = [0, 1, 2, 50, 51]
    frames = {i: Frame(i, i / 30.0, np.zeros((2, 2, 3), np.float32), np.ones((2, 2), np.float32), None, None)
              for i in idx}
    out = _bench().steady_clock(frames, idx, [50])
    np.testing.assert_allclose([out[i].timestamp for i in idx], [0, 1 / 30, 2 / 30, 3 / 30, 4 / 30])
    assert out[50].index == 50 and out[50].depth is frames[50].depth
    assert [frames[i].timestamp for i in idx] == [i / 30.0 for i in idx]  # the caller's frames are not changed


def _baseline():
    spec = importlib.util.spec_from_file_location("open3d_baseline", os.path.join(ROOT, "bench", "open3d_baseline.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _frames():
    import numpy as np

    yy, xx = np.mgrid[0:48, 0:64]
    depth = np.stack([(1500 + 5 * xx + 3 * yy + 10 * n).astype(np.uint16) for n in range(3)])  # a slanted wall
    return depth, np.full((3, 48, 64, 3), 120, np.uint8), np.array([[50.0, 0, 31.5], [0, 50.0, 23.5], [0, 0, 1]])


def test_open3d_runs_in_a_child_process_whose_result_comes_back_or_whose_absence_is_one_line(capsys):
    """Real child processes: with open3d installed (requirements/bench-real.in) the child's poses come back; without
    it the child fails to import it and the parent says so in one line and returns None."""
    import numpy as np

    depth, rgb, k = _frames()
    res = _baseline().run_in_child(depth, rgb, k, np.eye(4), 0.02, 3.0, "cpu")
    if importlib.util.find_spec("open3d") is None:
        assert res is None
        assert "Open3D's tracker ended with exit code 1" in capsys.readouterr().err
    else:
        assert len(res["poses"]) == 3 and np.allclose(res["poses"][0], np.eye(4)) and res["fps"] > 0


def test_a_crash_of_the_open3d_child_is_reported_and_the_benchmark_goes_on(tmp_path, monkeypatch, capsys):
    """A child that ends with a segmentation fault (as Open3D 0.20 did on some kitchen stretches; here a real
    process killed by SIGSEGV in place of the interpreter) is named by its signal; the caller gets None."""
    import numpy as np

    crash = tmp_path / "crash.sh"
    crash.write_text("#!/bin/sh\nkill -SEGV $$\n")
    crash.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(crash))
    depth, rgb, k = _frames()
    assert _baseline().run_in_child(depth, rgb, k, np.eye(4), 0.02, 3.0, "cpu") is None
    err = capsys.readouterr().err
    assert "ended with a segmentation fault (signal 11)" in err and "no Open3D column" in err, err
