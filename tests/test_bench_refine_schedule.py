"""bench/refine_schedule.py end to end on a small synthetic sequence: one online state, one row per share."""

import os
import re
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.slow
def test_refine_schedule_prints_one_row_per_share_and_poses_setting(tmp_path):
    from semantic_gs_slam.synthetic.scenes import generate

    generate(str(tmp_path), frames=12, width=120, height=68, span_deg=20.0)
    out = subprocess.run([sys.executable, os.path.join(ROOT, "bench", "refine_schedule.py"), str(tmp_path),
                          "--frames", "12", "--size", "120x68", "--seconds", "1", "--shares", "0,0.5",
                          "--poses", "off,on", "--eval-every", "4", "--threads", "1"],
                         capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    rows = re.findall(r"^\| (0|0\.5) \| (off|on) \| (\d+) \| ([\d.]+) \| ([-+\d.]+) \| ([\d.]+|nan) \|",
                      out.stdout, re.M)
    assert [r[:2] for r in rows] == [("0", "off"), ("0", "on"), ("0.5", "off"), ("0.5", "on")], out.stdout
    assert all(int(r[2]) > 0 for r in rows) and rows[0][4] == "+0.00", out.stdout
    bad = subprocess.run([sys.executable, os.path.join(ROOT, "bench", "refine_schedule.py"), str(tmp_path),
                          "--shares", "0,1"], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert bad.returncode == 2 and "[0, 1)" in bad.stderr
    bad = subprocess.run([sys.executable, os.path.join(ROOT, "bench", "refine_schedule.py"), str(tmp_path),
                          "--poses", "yes"], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert bad.returncode == 2 and "--poses must be comma-separated off / on" in bad.stderr
