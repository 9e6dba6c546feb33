"""The live view: scene helpers (no ROS), and the node's page in a real headless Chromium."""

from __future__ import annotations

import shutil
import subprocess
import urllib.request

import numpy as np
import pytest

from home_robot_bringup.nodeset import NodeSpec
from home_robot_bringup.testing import wait_for
from home_robot_exploration.errors import ConfigError
from home_robot_exploration.live_view import grid_image, splats_from_params
from home_robot_exploration.occupancy import FREE, OCCUPIED, UNKNOWN


def test_splats_from_the_bundled_map(tmp_path):
    from pathlib import Path

    path = Path(__file__).resolve().parents[3] / "data" / "params.npz"
    centers, cov, rgbs, opac = splats_from_params(str(path), max_splats=1000)
    assert centers.shape == (1000, 3) and cov.shape == (1000, 3, 3) and rgbs.shape == (1000, 3)
    assert opac.shape == (1000, 1) and ((opac >= 0) & (opac <= 1)).all()
    assert np.allclose(cov, np.transpose(cov, (0, 2, 1)), atol=1e-9)  # symmetric
    assert (np.linalg.eigvalsh(cov.astype(np.float64)) > -1e-12).all()  # positive semi-definite
    (tmp_path / "bad.npz").write_bytes(b"not a map")
    with pytest.raises(ConfigError):
        splats_from_params(str(tmp_path / "bad.npz"))


def test_grid_image_colours_and_orientation():
    st = np.full((4, 5), UNKNOWN, dtype=np.int8)
    st[0, :] = OCCUPIED  # bottom row (smallest y)
    st[1:3, 1:4] = FREE
    img = grid_image(st)
    assert img.shape == (4, 5, 3) and img.dtype == np.uint8
    assert (img[-1] == 20).all()  # the bottom row of the grid is the image's last row
    assert tuple(img[2, 1]) == (255, 140, 0)  # a free cell next to unknown: frontier
    assert tuple(img[0, 0]) == (128, 128, 128)  # unknown


@pytest.mark.ros
@pytest.mark.skipif(shutil.which("chromium") is None, reason="needs chromium (apt-get install chromium)")
def test_page_loads_in_headless_chromium_with_the_map(launch_nodes, tmp_path):
    sup = launch_nodes(nodes=[NodeSpec("live_view", "home_robot_exploration", "live_view_node",
                                       parameters={"port": 8765}, ready="ready:")])
    proc = sup.get("live_view")
    line = next(ln for ln in proc.output().splitlines() if "ready: live view at" in ln)
    url = line.split("ready: live view at ")[1].split(" ")[0]
    assert "Gaussians" in line and " 0 Gaussians" not in line, line
    with urllib.request.urlopen(url, timeout=30) as resp:  # the page itself
        assert resp.status == 200 and b"<html" in resp.read().lower()
    shot = tmp_path / "view.png"
    cmd = ["chromium", "--headless=new", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader",
           "--use-angle=swiftshader", "--window-size=1280,800", "--virtual-time-budget=15000",
           f"--screenshot={shot}", url]
    subprocess.run(cmd, capture_output=True, timeout=180, stdin=subprocess.DEVNULL)
    # the browser connected to the scene's websocket and received the map
    assert wait_for(lambda: "browser clients: 1" in proc.output(), 60.0), proc.output()[-2000:]
    from PIL import Image

    img = np.asarray(Image.open(shot).convert("RGB"), dtype=np.float32)
    assert img.shape[0] > 100 and img.std() > 5.0  # not a blank page
