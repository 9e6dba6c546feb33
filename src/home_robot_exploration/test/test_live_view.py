"""The live view: scene helpers (no ROS), and the node's page in a real headless Chromium."""

from __future__ import annotations

import shutil
import urllib.request

import numpy as np
import pytest

from home_robot_bringup.nodeset import NodeSpec
from home_robot_bringup.testing import wait_for
from home_robot_exploration.errors import ConfigError
from home_robot_exploration.live_view import (
    browser_screenshot,
    coloured_pixels,
    grid_image,
    scene_drawn,
    splats_from_params,
)
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
    with pytest.raises(ConfigError, match="cannot read the Gaussian map"):
        splats_from_params(str(tmp_path / "bad.npz"))
    np.savez(tmp_path / "short.npz", means3D=np.zeros((3, 3)), rgb_colors=np.zeros((2, 3)), log_scales=np.zeros((3, 1)),
             unnorm_rotations=np.zeros((3, 4)), logit_opacities=np.zeros((3, 1)))
    with pytest.raises(ConfigError, match="cannot show the Gaussian map .*3 means, 2 colours"):
        splats_from_params(str(tmp_path / "short.npz"))


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
    # 10000 of the map's 41128 splats: software WebGL draws them in a quarter of the time (16 s for the whole
    # test unloaded, 27 s with all; at load 6 on 2 cores 138 s, where all of them took over 150 s)
    sup = launch_nodes(nodes=[NodeSpec("live_view", "home_robot_exploration", "live_view_node",
                                       parameters={"port": 8765, "max_splats": 10000}, ready="ready:")])
    proc = sup.get("live_view")
    line = next(ln for ln in proc.output().splitlines() if "ready: live view at" in ln)
    url = line.split("ready: live view at ")[1].split(" ")[0]
    assert "Gaussians" in line and " 0 Gaussians" not in line, line
    with urllib.request.urlopen(url, timeout=30) as resp:  # the page itself
        assert resp.status == 200 and b"<html" in resp.read().lower()
    shot = tmp_path / "view.png"
    # a real headless Chromium loads the page, connects to the scene's websocket and draws the splats
    # (software WebGL); the screenshot is retaken until the map's colours are there and stable
    browser_screenshot(url, str(shot), ready=scene_drawn(min_pixels=2000), timeout_s=240)
    assert wait_for(lambda: "browser clients: 1" in proc.output(), 60.0), proc.output()[-2000:]
    assert coloured_pixels(str(shot)) >= 2000  # the furniture of the map, seen from the home view


def test_coloured_pixels_count_the_scene_not_the_page(tmp_path):
    from PIL import Image

    blank = np.full((800, 1280, 3), 255, np.uint8)
    blank[400:420, 100:900] = 128  # grey grid lines: not coloured
    blank[20:180, 960:1260] = (40, 120, 230)  # a blue button in the control panel: outside the scene
    Image.fromarray(blank).save(tmp_path / "blank.png")
    assert coloured_pixels(str(tmp_path / "blank.png")) == 0
    sofa = blank.copy()
    sofa[300:350, 300:400] = (60, 80, 200)  # a blue sofa in the scene
    Image.fromarray(sofa).save(tmp_path / "sofa.png")
    assert coloured_pixels(str(tmp_path / "sofa.png")) == 50 * 100
    ready = scene_drawn(min_pixels=1000)
    assert not ready(str(tmp_path / "blank.png")) and not ready(str(tmp_path / "sofa.png"))  # not yet stable
    assert ready(str(tmp_path / "sofa.png"))
