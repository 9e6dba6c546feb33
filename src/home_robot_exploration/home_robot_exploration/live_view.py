"""A live 3-D view of exploration in a web browser, with ``viser`` (no ROS here).

Shows the Gaussian map (``params.npz``: splats straight from the SLAM map), the occupancy grid as
an image on the floor (unknown grey, free white, occupied black) with its frontier cells in
orange, the robot's pose and path, and object labels. The ROS node ``live_view_node`` feeds it.
viser serves the page and streams the scene over a websocket; it needs no GPU (the browser draws).
"""

from __future__ import annotations

import math
import threading
import zipfile
import zlib
from collections.abc import Callable

import numpy as np

from home_robot_exploration.errors import ConfigError
from home_robot_exploration.frontiers import frontier_mask
from home_robot_exploration.occupancy import FREE, OCCUPIED, UNKNOWN
from semantic_gs_slam.errors import ConfigError as MapArraysError
from semantic_gs_slam.viewer import SPLAT_KEYS, splats_from_arrays


def splats_from_params(path: str, max_splats: int = 60000) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gaussians of a SplaTAM / SGS-SLAM ``params.npz`` for :meth:`viser.SceneApi.add_gaussian_splats`
    (:func:`semantic_gs_slam.viewer.splats_from_arrays` on the file's arrays).

    Args:
        path: the map file (``means3D``, ``rgb_colors``, ``log_scales`` [N, 1] or [N, 3],
            ``unnorm_rotations`` [N, 4] wxyz, ``logit_opacities`` [N, 1]).
        max_splats: at most this many (an even subsample), so the browser stays fluent.

    Returns:
        centers [M, 3], covariances [M, 3, 3], rgbs [M, 3] in [0, 1], opacities [M, 1] in [0, 1].

    Raises:
        ConfigError: unreadable file, missing keys or arrays that disagree.
    """
    try:
        with np.load(path, allow_pickle=False) as d:
            arrays = {k: d[k] for k in SPLAT_KEYS if k in d.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        raise ConfigError(f"cannot read the Gaussian map {path!r}: {exc}") from exc
    try:
        return splats_from_arrays(arrays, max_splats)
    except MapArraysError as exc:
        raise ConfigError(f"cannot show the Gaussian map {path!r}: {exc}") from exc


def grid_image(states: np.ndarray) -> np.ndarray:
    """[ny, nx] occupancy states -> [ny, nx, 3] uint8, row 0 = the grid's top (largest y), frontiers orange."""
    img = np.full(states.shape + (3,), 128, dtype=np.uint8)
    img[states == FREE] = 245
    img[states == OCCUPIED] = 20
    img[frontier_mask(states)] = (255, 140, 0)
    img[(states != UNKNOWN) & (states != FREE) & (states != OCCUPIED)] = 128
    return img[::-1].copy()


#: where a browser's camera starts (m, map frame) and what it looks at: the simulated home from above its south side
HOME_VIEW_POSITION = (3.0, -3.0, 7.5)
HOME_VIEW_LOOK_AT = (3.0, 2.2, 0.0)


def browser_screenshot(url: str, path: str, width: int = 1280, height: int = 800, settle_s: float = 6.0,
                       timeout_s: float = 120.0, ready: Callable[[str], bool] | None = None) -> None:
    """Load ``url`` in a headless Chromium (software WebGL: no GPU needed) and save a PNG screenshot.

    Driven over the DevTools protocol in real time (:mod:`home_robot_web.cdp`; not Chromium's ``--screenshot``,
    whose virtual time raced the scene's websocket): the page loads, then a screenshot is taken every ``settle_s``
    seconds until ``ready(path)`` says the scene is drawn (default: the first one after ``settle_s``), at most
    ``timeout_s`` seconds.

    Raises:
        ConfigError: no ``chromium`` on the PATH, it did not start or answer, or the scene was not ready in time
            (the last screenshot is still written).
    """
    import time

    from home_robot_web.cdp import BrowserError, Chromium

    deadline = time.monotonic() + timeout_s
    try:
        with Chromium(start_timeout_s=timeout_s, webgl=True) as browser:
            page = browser.page(width, height)
            page.navigate(url, timeout_s=max(1.0, deadline - time.monotonic()))
            while True:
                time.sleep(settle_s)
                page.screenshot(path, timeout_s=max(1.0, deadline - time.monotonic()))
                if ready is None or ready(path):
                    return
                if time.monotonic() + settle_s > deadline:
                    raise ConfigError(f"the scene was not drawn within {timeout_s:g} s (last screenshot: {path})")
    except BrowserError as exc:
        raise ConfigError(str(exc)) from exc


def coloured_pixels(png_path: str, min_chroma: int = 20) -> int:
    """Strongly coloured pixels (max - min channel >= ``min_chroma``) in the scene part of a 1280 x 800
    screenshot (below the notification, left of the control panel): the map's furniture (blue sofa,
    brown table and chairs). The background, the grey grid and the floor grid have none, so a scene
    without the splats drawn has few (the robot's axes, the path, frontier cells)."""
    from PIL import Image

    img = np.asarray(Image.open(png_path).convert("RGB"), dtype=np.int16)
    h, w = img.shape[:2]
    scene = img[int(h * 0.25):int(h * 0.93), int(w * 0.05):int(w * 0.72)]
    chroma = scene.max(-1) - scene.min(-1)
    return int((chroma >= min_chroma).sum())


def scene_drawn(min_pixels: int = 2000) -> Callable[[str], bool]:
    """A ``ready`` test for :func:`browser_screenshot`: at least ``min_pixels`` coloured pixels
    (:func:`coloured_pixels`; 0 on an empty scene, thousands with the home's map) and no more than
    5 % growth since the previous screenshot (the splats have finished fading in)."""
    last = [-1]

    def ready(path: str) -> bool:
        n = coloured_pixels(path)
        stable = last[0] >= 0 and n <= last[0] * 1.05
        last[0] = n
        return n >= min_pixels and stable

    return ready


class LiveView:
    """The viser scene. Thread-safe (one lock around scene updates)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080) -> None:
        import viser

        if not 0 < port < 65536:
            raise ConfigError(f"port must be in 1..65535, got {port}")
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.url = f"http://{host}:{self.server.get_port()}"
        self._lock = threading.Lock()  # guards the scene handles and _path
        self._path: list[tuple[float, float]] = []
        self._labels: dict[str, object] = {}
        self.splats = 0
        self.server.scene.set_up_direction("+z")
        # every browser starts looking at the home from above its south side (set before any client
        # connects, so a headless browser's first frame already has it: no race with a connect callback)
        cam = self.server.initial_camera
        cam.position, cam.look_at, cam.up = HOME_VIEW_POSITION, HOME_VIEW_LOOK_AT, (0.0, 0.0, 1.0)
        self.server.scene.add_grid("/floor_grid", width=12.0, height=12.0, position=(3.0, 2.5, -0.01))

    def clients(self) -> int:
        return len(self.server.get_clients())

    def show_gaussians(self, centers: np.ndarray, covariances: np.ndarray, rgbs: np.ndarray,
                       opacities: np.ndarray) -> None:
        with self._lock:
            self.server.scene.add_gaussian_splats("/map/gaussians", centers=centers, covariances=covariances,
                                                  rgbs=rgbs, opacities=opacities)
            self.splats = len(centers)

    def show_grid(self, states: np.ndarray, resolution: float, origin_x: float, origin_y: float) -> None:
        ny, nx = states.shape
        with self._lock:
            self.server.scene.add_image("/grid", grid_image(states), render_width=nx * resolution,
                                        render_height=ny * resolution, format="png",
                                        position=(origin_x + nx * resolution / 2, origin_y + ny * resolution / 2,
                                                  0.0))

    def show_robot(self, x: float, y: float, yaw: float) -> None:
        with self._lock:
            self.server.scene.add_frame("/robot", axes_length=0.4, axes_radius=0.03,
                                        wxyz=(math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)), position=(x, y, 0.05))
            if not self._path or math.hypot(self._path[-1][0] - x, self._path[-1][1] - y) > 0.05:
                self._path.append((x, y))
            if len(self._path) >= 2:
                p = np.array([(px, py, 0.03) for px, py in self._path], dtype=np.float32)
                segs = np.stack([p[:-1], p[1:]], 1)  # [S, 2, 3]
                self.server.scene.add_line_segments("/path", segs, colors=(30, 90, 230), thickness=0.03)

    def show_objects(self, objects: dict[str, list[float]]) -> None:
        with self._lock:
            for name, handle in list(self._labels.items()):
                if name not in objects:
                    handle.remove()  # type: ignore[attr-defined]
                    del self._labels[name]
            for name, pos in objects.items():
                self._labels[name] = self.server.scene.add_label(f"/objects/{name}", name,
                                                                 position=tuple(float(v) for v in pos))

    def close(self) -> None:
        self.server.stop()
