"""bench/slam_real.py's lost / recovered summary from the engine's ``stats()``."""

import importlib.util
import os
import sys

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
