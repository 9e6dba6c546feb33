"""The command line: run with checkpoints, resume, evaluation table, and a clean error exit."""

from __future__ import annotations

import os

import pytest

from semantic_gs_slam.run import main
from semantic_gs_slam.slam import SLAM


def _fast(tmp_path) -> list[str]:
    """``--config`` with a short first-frame fit (60 iterations by default: most of a short run's time). These tests
    check what the command line does with frames, checkpoints and signals, not the map's quality."""
    path = tmp_path / "fast.json"
    path.write_text('{"mapping": {"first_frame_iters": 4}}')
    return ["--config", str(path)]


def test_run_checkpoint_resume_and_eval(tiny_home, tmp_path, capsys):
    out = str(tmp_path / "map")
    args = ["--dataset", str(tiny_home), "--out", out, "--threads", "1", "--mapping-iters", "3", *_fast(tmp_path)]
    assert main(args + ["--frames", "4", "--checkpoint-every", "2"]) == 0
    assert os.path.isfile(os.path.join(out, "checkpoint", "checkpoint.json"))
    assert main(args + ["--frames", "6", "--resume", "--eval", "--refine-iters", "4", "--refine-poses"]) == 0
    cap = capsys.readouterr()
    assert "resumed from" in cap.err and "frame     5" in cap.err
    assert "refined the map and its views' poses over 2 keyframes for 4 iterations" in cap.err
    assert "| ATE RMSE (cm, aligned) |" in cap.out and "| semantic mIoU |" in cap.out
    for name in ("params.npz", "semantic.json", "map.ply"):
        assert os.path.getsize(os.path.join(out, name)) > 0


def test_run_refines_for_a_time_budget(tiny_home, tmp_path, capsys):
    """``--refine-seconds S`` alone: as many refinement iterations as S seconds allow, then the map is saved."""
    import re

    out = str(tmp_path / "map")
    assert main(["--dataset", str(tiny_home), "--out", out, "--threads", "1", "--mapping-iters", "3", "--frames", "4",
                 "--refine-seconds", "1", "--quiet", *_fast(tmp_path)]) == 0
    m = re.search(r"refined the map over \d+ keyframes for (\d+) iterations in ([\d.]+) s", capsys.readouterr().err)
    assert m and int(m.group(1)) > 0, m
    assert os.path.getsize(os.path.join(out, "params.npz")) > 0


def test_run_reports_bad_dataset(tmp_path, capsys):
    assert main(["--dataset", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert "error: dataset folder not found" in capsys.readouterr().err


def test_an_output_that_is_no_writable_folder_is_refused_before_any_frame(tiny_home, tmp_path, capsys):
    """Checked first: a run mapped in full and then lost at the save on a file in the way is no run."""
    blocker = tmp_path / "a_file"
    blocker.write_text("in the way")
    assert main(["--dataset", str(tiny_home), "--out", str(blocker), "--frames", "4"]) == 2
    err = capsys.readouterr().err
    assert f"error: --out {blocker}: not a writable folder" in err and "frame" not in err.split("error:")[0]
    assert blocker.read_text() == "in the way"


def test_threads_and_refinement_iterations_out_of_range_are_usage_errors(tmp_path, capsys):
    for flag, value in (("--threads", "-1"), ("--refine-iters", "-5")):
        with pytest.raises(SystemExit) as info:
            main(["--dataset", str(tmp_path), "--out", str(tmp_path / "o"), flag, value])
        assert info.value.code == 2 and "--threads must be >= 0 (0: torch's own) and --refine-iters >= 0" in \
            capsys.readouterr().err


def test_run_reports_bad_config_overrides(tiny_home, tmp_path, capsys):
    args = ["--dataset", str(tiny_home), "--out", str(tmp_path / "o"), "--frames", "1", "--quiet"]
    assert main(args + ["--config", '{"mapping": {"iterz": 3}}']) == 2
    assert "error: unknown MappingConfig field(s): ['iterz']" in capsys.readouterr().err
    assert main(args + ["--config", str(tmp_path / "none.json")]) == 2
    assert "error: config overrides: cannot read" in capsys.readouterr().err
    assert not os.path.exists(tmp_path / "o" / "params.npz")


def test_refine_poses_without_refinement_is_a_usage_error(tmp_path, capsys):
    import pytest

    with pytest.raises(SystemExit) as exc:
        main(["--dataset", str(tmp_path), "--out", str(tmp_path / "o"), "--refine-poses"])
    assert exc.value.code == 2
    assert "--refine-poses needs --refine-iters N or --refine-seconds S" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--dataset", str(tmp_path), "--out", str(tmp_path / "o"), "--refine-seconds", "-1"])
    assert "--refine-seconds must be a finite number >= 0" in capsys.readouterr().err


def test_demo_map_builder_writes_a_map_object_query_reads(tmp_path):
    from semantic_gs_slam.synthetic.demo_map import build

    out = tmp_path / "map"
    res = build(str(out), frames=8, width=80, height=45, refine_iters=5, threads=1, quiet=True)
    assert {"ate_rmse_cm", "psnr", "miou", "gaussians"} <= set(res)
    assert (out / "params.npz").is_file() and (out / "semantic.json").is_file() and not (out / "map.ply").exists()
    gmap, classes, arr = SLAM.load_map(str(out))
    assert len(gmap) == res["gaussians"] and classes[7] == "bottle" and arr["cam_trans"].shape == (1, 3, 8)


def _replica_copy(src, dst):
    """A copy of a Replica-layout sequence whose files a test may break."""
    import shutil

    shutil.copytree(src, dst)
    return dst


def test_a_bad_frame_is_skipped_and_nothing_is_lost(tiny_home, tmp_path, capsys):
    """A corrupt image and a depth image with no valid depth are skipped with a warning, listed at the end; the
    map and the evaluation cover the frames that could be used (matched by time stamp, not by count)."""
    import glob

    seq = _replica_copy(tiny_home, tmp_path / "seq")
    rgb = sorted(glob.glob(str(seq / "results" / "frame*")))
    depth = sorted(glob.glob(str(seq / "results" / "depth*")))
    with open(rgb[2], "wb") as fh:
        fh.write(b"not an image")
    from PIL import Image

    Image.new("I;16", Image.open(depth[4]).size, 0).save(depth[4])  # no valid depth at all
    out = str(tmp_path / "map")
    rc = main(["--dataset", str(seq), "--out", out, "--threads", "1", "--mapping-iters", "2", "--frames", "6",
               "--quiet", "--eval", "--checkpoint-every", "2", *_fast(tmp_path)])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "warning: frame 2 skipped" in cap.err and "unreadable image" in cap.err
    assert "warning: frame 4 skipped" in cap.err and "depth pixels are valid" in cap.err
    assert "skipped 2 of 6 frames that could not be used (frame 2: " in cap.err
    assert "| ATE RMSE (cm, aligned) |" in cap.out and "| frames | 4 |" in cap.out
    gmap, classes, arr = SLAM.load_map(out)
    from semantic_gs_slam.io.datasets import load_dataset

    stamps = load_dataset(str(seq)).timestamps
    assert arr["cam_trans"].shape == (1, 3, 4) and list(arr["timestamps"]) == [stamps[i] for i in (0, 1, 3, 5)]
    # resumed from the checkpoint written after the skipped frames: it goes on after the last frame it has
    eng = SLAM.resume(os.path.join(out, "checkpoint"))
    n_ck = len(eng.poses)
    assert main(["--dataset", str(seq), "--out", out, "--threads", "1", "--mapping-iters", "2", "--frames", "8",
                 "--quiet", "--resume", "--eval"]) == 0
    cap = capsys.readouterr()
    assert f"resumed from {os.path.join(out, 'checkpoint')} at frame {n_ck}" in cap.err
    assert "| ATE RMSE (cm, aligned) |" in cap.out
    assert SLAM.load_map(out)[2]["cam_trans"].shape[2] == 6  # frames 0 1 3 5 6 7


def test_many_bad_frames_in_a_row_stop_the_run_and_keep_the_map(tiny_home, tmp_path, capsys):
    import glob

    from semantic_gs_slam import run

    seq = _replica_copy(tiny_home, tmp_path / "seq")
    for p in sorted(glob.glob(str(seq / "results" / "frame*")))[2:]:
        with open(p, "wb") as fh:
            fh.write(b"junk")
    out = str(tmp_path / "map")
    old = run.MAX_BAD_IN_A_ROW
    run.MAX_BAD_IN_A_ROW = 3
    try:
        assert main(["--dataset", str(seq), "--out", out, "--threads", "1", "--mapping-iters", "2", "--quiet",
                     *_fast(tmp_path)]) == 2
    finally:
        run.MAX_BAD_IN_A_ROW = old
    err = capsys.readouterr().err
    assert "error: 3 frames in a row could not be used (the last, frame 4:" in err
    assert "the map of the 2 frames mapped is saved" in err and "warning: frame 5" not in err
    assert "--checkpoint-every N would let --resume continue from there" in err
    assert SLAM.load_map(out)[2]["cam_trans"].shape == (1, 3, 2)
    # nothing usable at all: a clear error, no map
    for p in sorted(glob.glob(str(seq / "results" / "frame*")))[:2]:
        with open(p, "wb") as fh:
            fh.write(b"junk")
    assert main(["--dataset", str(seq), "--out", str(tmp_path / "none"), "--quiet"]) == 2
    assert "error: no frame could be used, nothing to save (frame 0: " in capsys.readouterr().err
    assert not os.path.exists(tmp_path / "none" / "params.npz")


_SIGINT_AT = """
import os, signal, sys
from semantic_gs_slam import run
from semantic_gs_slam.slam import SLAM
at = int(os.environ["SIGINT_AT_FRAMES"])
real = SLAM.add_frame
def add_frame(self, *a, **k):  # a real SIGINT to this process once it has mapped `at` frames
    out = real(self, *a, **k)
    if len(self.poses) == at:
        os.kill(os.getpid(), signal.SIGINT)
    return out
SLAM.add_frame = add_frame
sys.exit(run.main(sys.argv[1:]))
"""


def _run_with_sigint(at: int, args: list[str]):
    import subprocess
    import sys

    env = {**os.environ, "SIGINT_AT_FRAMES": str(at)}
    return subprocess.run([sys.executable, "-c", _SIGINT_AT, *args], capture_output=True, text=True, env=env,
                          timeout=600)


def test_ctrl_c_saves_the_map_so_far_and_resume_goes_on(tiny_home, tmp_path):
    """A real process gets a real SIGINT while it maps frame 1 (of 6): it finishes that frame, saves the two frames,
    writes a checkpoint and exits with 130; --resume maps the rest."""
    out = tmp_path / "map"
    args = ["--dataset", str(tiny_home), "--out", str(out), "--threads", "1", "--mapping-iters", "2", "--frames", "6",
            "--checkpoint-every", "4", *_fast(tmp_path)]
    res = _run_with_sigint(2, args)
    assert res.returncode == 130, res.stderr
    assert "interrupted: finishing this step, then saving the map so far" in res.stderr
    assert "error: stopped by Ctrl-C before frame 2; the map of the 2 frames mapped is saved" in res.stderr
    assert SLAM.load_map(str(out))[2]["cam_trans"].shape == (1, 3, 2)
    assert len(SLAM.resume(str(out / "checkpoint")).poses) == 2  # written on the stop, not only every 4 frames
    assert main(args + ["--resume", "--quiet"]) == 0
    assert SLAM.load_map(str(out))[2]["cam_trans"].shape == (1, 3, 6)


def test_ctrl_c_during_the_last_frame_skips_the_refinement_and_says_so(tiny_home, tmp_path):
    out = tmp_path / "map"
    res = _run_with_sigint(3, ["--dataset", str(tiny_home), "--out", str(out), "--threads", "1", "--mapping-iters",
                               "2", "--frames", "3", "--refine-iters", "50", "--eval", *_fast(tmp_path)])
    assert res.returncode == 130, res.stderr
    assert "error: stopped by Ctrl-C; the map of the 3 frames mapped is saved, without --eval" in res.stderr
    assert "refined the map" not in res.stderr and "ATE" not in res.stdout
    assert SLAM.load_map(str(out))[2]["cam_trans"].shape == (1, 3, 3)


def test_run_with_the_keyframe_front_end_and_the_mapping_thread(tiny_home, tmp_path, capsys):
    out = str(tmp_path / "map")
    assert main(["--dataset", str(tiny_home), "--out", out, "--threads", "1", "--mapping-iters", "3", "--frames", "6",
                 "--frontend", "keyframe", "--threaded", "--eval"]) == 0
    cap = capsys.readouterr()
    assert "mapping thread drained in" in cap.err and "lost [], recoveries [], dropped [" in cap.err
    assert "| ATE RMSE (cm, aligned) |" in cap.out
    assert len(SLAM.load_map(out)[0]) > 0


def test_start_map_continues_a_saved_map_and_bad_ones_are_clear_errors(tiny_home, tmp_path, capsys):
    first, second = str(tmp_path / "first"), str(tmp_path / "second")
    args = ["--dataset", str(tiny_home), "--threads", "1", "--mapping-iters", "3", "--quiet", *_fast(tmp_path)]
    assert main(args + ["--out", first, "--frames", "4"]) == 0
    assert main(args + ["--out", second, "--start", "3", "--start-map", first]) == 0
    assert "continuing the saved map" in capsys.readouterr().err
    saved, grown = SLAM.load_map(first), SLAM.load_map(second)
    assert len(grown[0]) > len(saved[0]) and grown[2]["cam_trans"].shape == (1, 3, 7)  # frames 3-9, mapped on
    # the new file keeps the views it started from and its own keyframes: a later restart relocalises in either
    assert len(grown[2]["view_c2w"]) > len(saved[2]["view_c2w"])
    assert main(args + ["--out", second, "--start-map", str(tmp_path / "nowhere")]) == 2
    assert "error: no saved map at" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main(args + ["--out", second, "--start-map", first, "--resume"])
    assert exc.value.code == 2
    assert "--start-map and --resume exclude each other" in capsys.readouterr().err
