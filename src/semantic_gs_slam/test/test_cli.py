"""The command line: run with checkpoints, resume, evaluation table, and a clean error exit."""

from __future__ import annotations

import os

from semantic_gs_slam.run import main
from semantic_gs_slam.slam import SLAM


def test_run_checkpoint_resume_and_eval(tiny_home, tmp_path, capsys):
    out = str(tmp_path / "map")
    args = ["--dataset", str(tiny_home), "--out", out, "--threads", "1", "--mapping-iters", "3"]
    assert main(args + ["--frames", "4", "--checkpoint-every", "2"]) == 0
    assert os.path.isfile(os.path.join(out, "checkpoint", "checkpoint.json"))
    assert main(args + ["--frames", "6", "--resume", "--eval", "--refine-iters", "4", "--refine-poses"]) == 0
    cap = capsys.readouterr()
    assert "resumed from" in cap.err and "frame     5" in cap.err
    assert "refined the map and the keyframes poses over 2 keyframes for 4 iterations" in cap.err
    assert "| ATE RMSE (cm, aligned) |" in cap.out and "| semantic mIoU |" in cap.out
    for name in ("params.npz", "semantic.json", "map.ply"):
        assert os.path.getsize(os.path.join(out, name)) > 0


def test_run_reports_bad_dataset(tmp_path, capsys):
    assert main(["--dataset", str(tmp_path / "missing"), "--out", str(tmp_path / "o")]) == 2
    assert "error: dataset folder not found" in capsys.readouterr().err


def test_refine_poses_without_refinement_is_a_usage_error(tmp_path, capsys):
    import pytest

    with pytest.raises(SystemExit) as exc:
        main(["--dataset", str(tmp_path), "--out", str(tmp_path / "o"), "--refine-poses"])
    assert exc.value.code == 2
    assert "--refine-poses needs --refine-iters N" in capsys.readouterr().err


def test_demo_map_builder_writes_a_map_object_query_reads(tmp_path):
    from semantic_gs_slam.demo_map import build

    out = tmp_path / "map"
    res = build(str(out), frames=8, width=80, height=45, refine_iters=5, threads=1, quiet=True)
    assert {"ate_rmse_cm", "psnr", "miou", "gaussians"} <= set(res)
    assert (out / "params.npz").is_file() and (out / "semantic.json").is_file() and not (out / "map.ply").exists()
    gmap, classes, arr = SLAM.load_map(str(out))
    assert len(gmap) == res["gaussians"] and classes[7] == "bottle" and arr["cam_trans"].shape == (1, 3, 8)
