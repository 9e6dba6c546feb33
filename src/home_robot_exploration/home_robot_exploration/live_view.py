"""A live 3-D view of exploration in a web browser, with ``viser`` (no ROS here).

Shows the Gaussian map (``params.npz``: splats straight from the SLAM map), the occupancy grid as
an image on the floor (unknown grey, free white, occupied black) with its frontier cells in
orange, the robot's pose and path, and object labels. The ROS node ``live_view_node`` feeds it.
viser serves the page and streams the scene over a websocket; it needs no GPU (the browser draws).
"""

from __future__ import annotations

import math
import threading

import numpy as np

from home_robot_exploration.errors import ConfigError
from home_robot_exploration.frontiers import frontier_mask
from home_robot_exploration.occupancy import FREE, OCCUPIED, UNKNOWN


def splats_from_params(path: str, max_splats: int = 60000) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gaussians of a SplaTAM / SGS-SLAM ``params.npz`` for :meth:`viser.SceneApi.add_gaussian_splats`.

    Args:
        path: the map file (``means3D``, ``rgb_colors``, ``log_scales`` [N, 1] or [N, 3],
            ``unnorm_rotations`` [N, 4] wxyz, ``logit_opacities`` [N, 1]).
        max_splats: at most this many (an even subsample), so the browser stays fluent.

    Returns:
        centers [N, 3], covariances [N, 3, 3], rgbs [N, 3] in [0, 1], opacities [N, 1] in [0, 1].

    Raises:
        ConfigError: unreadable file or missing keys.
    """
    try:
        with np.load(path) as d:
            means = np.asarray(d["means3D"], np.float32)  # [N, 3]
            rgb = np.clip(np.asarray(d["rgb_colors"], np.float32), 0, 1)  # [N, 3]
            log_s = np.asarray(d["log_scales"], np.float32)  # [N, 1] or [N, 3]
            q = np.asarray(d["unnorm_rotations"], np.float32)  # [N, 4] wxyz
            logit = np.asarray(d["logit_opacities"], np.float32).reshape(-1, 1)  # [N, 1]
    except (OSError, KeyError, ValueError) as exc:
        raise ConfigError(f"cannot read the Gaussian map {path!r}: {exc}") from exc
    if len(means) > max_splats:
        keep = np.linspace(0, len(means) - 1, max_splats).astype(np.int64)
        means, rgb, log_s, q, logit = means[keep], rgb[keep], log_s[keep], q[keep], logit[keep]
    s = np.exp(np.broadcast_to(log_s, (len(means), 3)))  # [N, 3]
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    w, x, y, z = q.T
    rot = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], 1)  # [N, 3, 3]
    cov = rot @ (s[:, :, None] ** 2 * np.transpose(rot, (0, 2, 1)))  # [N, 3, 3] = R S^2 R^T
    return means, cov.astype(np.float32), rgb, 1.0 / (1.0 + np.exp(-logit))


def grid_image(states: np.ndarray) -> np.ndarray:
    """[ny, nx] occupancy states -> [ny, nx, 3] uint8, row 0 = the grid's top (largest y), frontiers orange."""
    img = np.full(states.shape + (3,), 128, dtype=np.uint8)
    img[states == FREE] = 245
    img[states == OCCUPIED] = 20
    img[frontier_mask(states)] = (255, 140, 0)
    img[(states != UNKNOWN) & (states != FREE) & (states != OCCUPIED)] = 128
    return img[::-1].copy()


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
        self.server.on_client_connect(self._place_camera)
        self.server.scene.add_grid("/floor_grid", width=12.0, height=12.0, position=(3.0, 2.5, -0.01))

    @staticmethod
    def _place_camera(client) -> None:
        """A new browser looks at the home from above its south side."""
        client.camera.look_at = (3.0, 2.5, 0.0)
        client.camera.position = (3.0, -4.0, 7.0)

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
