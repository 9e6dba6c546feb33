"""The CPU-runnable parts of the GPU benchmark (``bench/slam_gpu.py``, ``bench/gpu.sh``)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", ".."))
BENCH = os.path.join(ROOT, "bench")


def test_table_printer_runs_on_cpu_at_a_tiny_size(tmp_path):
    sys.path.insert(0, BENCH)
    try:
        import slam_gpu
    finally:
        sys.path.remove(BENCH)
    from semantic_gs_slam.config import MappingConfig

    data = slam_gpu.make_sequence(str(tmp_path), 64, 36, 4, supersample=1, workers=1)
    row = slam_gpu.run_size(data, "cpu", "torch", 1, count_syncs=True,
                            mapping=MappingConfig(first_frame_iters=20, iters=3))
    table = slam_gpu.format_table([row], slam_gpu.device_name("cpu"))
    print(table)
    assert row.size == "64x36" and row.frames == 4 and row.fps > 0 and row.gaussians > 0
    assert row.syncs_per_frame > 0 and row.ate_cm == row.ate_cm  # counted, and ground truth was there
    lines = table.splitlines()
    assert lines[0].startswith("CPU") and lines[2].count("|") == lines[4].count("|") == 12
    assert "| - |" in lines[4]  # no GPU memory figure on the CPU


def test_gpu_script_is_valid_bash_and_refuses_a_cpu_torch_clearly():
    import torch

    script = os.path.join(BENCH, "gpu.sh")
    assert subprocess.run(["bash", "-n", script]).returncode == 0
    if torch.cuda.is_available():
        pytest.skip("a CUDA machine: the script would run for real (make bench-gpu)")
    r = subprocess.run(["bash", script], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHON": sys.executable})
    assert r.returncode == 2 and "needs a CUDA machine" in r.stderr


def test_gpu_script_refuses_a_real_data_path_that_is_not_a_folder(tmp_path):
    """``REAL_DATA`` is checked first, before any GPU work, so a typo does not cost a device run."""
    script = os.path.join(BENCH, "gpu.sh")
    r = subprocess.run(["bash", script], capture_output=True, text=True, timeout=60,
                       env={**os.environ, "PYTHON": sys.executable, "REAL_DATA": str(tmp_path / "nope")})
    assert r.returncode == 2 and "REAL_DATA=" in r.stderr and "is not a folder" in r.stderr, r.stderr


def test_size_argument_errors_are_clear():
    sys.path.insert(0, BENCH)
    try:
        import slam_gpu
    finally:
        sys.path.remove(BENCH)
    assert slam_gpu.parse_size("1200x680") == (1200, 680)
    with pytest.raises(Exception, match="WIDTHxHEIGHT"):
        slam_gpu.parse_size("1200")


def test_frame_profiler_prints_stages_and_operators_on_cpu(tmp_path, capsys):
    """``bench/profile_frame.py`` at a tiny size: every stage of a frame gets a figure for keyframes and other
    frames, the profiler window prints its operator table, and config overrides reach the engine."""
    sys.path.insert(0, BENCH)
    try:
        import profile_frame
    finally:
        sys.path.remove(BENCH)
    rc = profile_frame.main(["--device", "cpu", "--size", "64x36", "--frames", "6", "--threads", "1", "--workers", "1",
                             "--data", str(tmp_path), "--profile-from", "2", "--profile-frames", "2", "--top", "40",
                             "--set", "mapping.iters=2", "--set", "mapping.keyframe_every=2"])
    out = capsys.readouterr().out
    assert rc == 0
    assert "torch.profiler over 2 frames" in out and "aten::" in out
    import semantic_gs_slam.io.exposure as exposure
    import semantic_gs_slam.mapping.steps as steps_mod
    import semantic_gs_slam.slam as slam_mod
    import semantic_gs_slam.tracking.tracker as tracking

    assert slam_mod.icp is tracking.icp and steps_mod.fit_exposure is exposure.fit  # the functions are put back
    rows = {line.split("|")[1].strip(): line for line in out.splitlines() if line.startswith("| ")}
    for stage in ("upload", "track", "icp", "densify", "keyframe.optimise", "frame (total)"):
        assert stage in rows, (stage, out)
    kf_ms, other_ms = (float(v) for v in rows["keyframe.optimise"].split("|")[2:4])
    assert kf_ms > 0 and other_ms == 0  # mapping runs on keyframes only
    assert "keyframes (2)" in out  # frames 2 and 4 of 1..5 with keyframe_every=2
    for bad in ("mapping.no_such_field=1", "nosection.iters=1", "mapping.iters=many"):  # SlamConfig.with_overrides
        with pytest.raises(SystemExit) as exc:
            profile_frame.main(["--device", "cpu", "--size", "64x36", "--frames", "6", "--workers", "1",
                                "--data", str(tmp_path), "--set", bad])
        assert exc.value.code == 2


def test_streaming_report_counts_frames_and_times_the_object_query_reload(tmp_path):
    """The streaming figures at a tiny size on the CPU: every frame processed, the map written, and the written
    map loaded by object_query (the reload the server triggers) with the home's classes in it."""
    sys.path.insert(0, BENCH)
    try:
        import slam_gpu
    finally:
        sys.path.remove(BENCH)
    data = slam_gpu.make_sequence(str(tmp_path), 64, 36, 4, supersample=1, workers=1)
    line = slam_gpu.streaming(data, "cpu", "torch", 1, rate=30.0)
    print(line)
    assert "processed 4, skipped 0" in line and "; ok." in line
    reload = line.splitlines()[-1]
    assert reload.startswith("object_query reload of that map") and " s, " in reload
    assert int(reload.split(" s, ")[1].split()[0]) > 0  # classes found in the written map
