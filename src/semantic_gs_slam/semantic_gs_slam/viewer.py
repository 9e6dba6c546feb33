"""A Gaussian map in a web browser, with ``viser`` (no ROS here; no GPU: the browser draws).

:func:`splats_from_arrays` turns a SplaTAM / SGS-SLAM map (``params.npz`` arrays, ours included) into
what :meth:`viser.SceneApi.add_gaussian_splats` takes; :class:`MapViewer` serves the map and the
camera's path, e.g. from the streaming SLAM server while it maps (``run_gs_slam_server``'s
``live_view_port``). viser is imported only when a viewer is made (``requirements/viewer.in``).
"""

from __future__ import annotations

import threading

import numpy as np

from semantic_gs_slam.errors import ConfigError

#: The arrays of a map that :func:`splats_from_arrays` reads
SPLAT_KEYS = ("means3D", "rgb_colors", "log_scales", "unnorm_rotations", "logit_opacities")


def splats_from_arrays(a: dict[str, np.ndarray], max_splats: int = 60000
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gaussians of a map for the browser.

    Args:
        a: ``means3D`` [N, 3], ``rgb_colors`` [N, 3], ``log_scales`` [N, 1] or [N, 3],
            ``unnorm_rotations`` [N, 4] (w, x, y, z), ``logit_opacities`` [N, 1].
        max_splats: at most this many (an even subsample), so the browser stays fluent.

    Returns:
        centers [M, 3], covariances [M, 3, 3] (R S² Rᵀ), rgbs [M, 3] in [0, 1], opacities [M, 1] in [0, 1].

    Raises:
        ConfigError: missing keys or rows that do not match.
    """
    try:
        means = np.asarray(a["means3D"], np.float32).reshape(-1, 3)
        rgb = np.clip(np.asarray(a["rgb_colors"], np.float32), 0, 1).reshape(-1, 3)
        log_s = np.asarray(a["log_scales"], np.float32)
        q = np.asarray(a["unnorm_rotations"], np.float32).reshape(-1, 4)
        logit = np.asarray(a["logit_opacities"], np.float32).reshape(-1, 1)
    except (KeyError, ValueError) as exc:
        raise ConfigError(f"not a Gaussian map: {exc}") from exc
    n = len(means)
    log_s = log_s.reshape(n, -1) if n else log_s.reshape(0, 1)
    if not (len(rgb) == len(q) == len(logit) == len(log_s) == n) or log_s.shape[1] not in (1, 3):
        raise ConfigError(f"map arrays disagree: {n} means, {len(rgb)} colours, {len(q)} rotations, "
                          f"{len(logit)} opacities, scales {list(log_s.shape)}")
    if n > max_splats:
        keep = np.linspace(0, n - 1, max_splats).astype(np.int64)
        means, rgb, log_s, q, logit = means[keep], rgb[keep], log_s[keep], q[keep], logit[keep]
    s = np.exp(np.broadcast_to(log_s, (len(means), 3)))  # [M, 3]
    q = q / np.maximum(np.linalg.norm(q, axis=1, keepdims=True), 1e-12)
    w, x, y, z = q.T
    rot = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], 1)  # [M, 3, 3]
    cov = rot @ (s[:, :, None] ** 2 * np.transpose(rot, (0, 2, 1)))
    return means, cov.astype(np.float32), rgb, 1.0 / (1.0 + np.exp(-logit))


class MapViewer:
    """The map and the camera's path in a viser scene (``+z`` up). Thread-safe (one lock)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8081, max_splats: int = 60000) -> None:
        import viser

        if not 0 < port < 65536:
            raise ConfigError(f"live view port must be in 1..65535, got {port}")
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.url = f"http://{host}:{self.server.get_port()}"
        self.max_splats = max_splats
        self._lock = threading.Lock()  # guards the scene and _path
        self._path: list[np.ndarray] = []
        self.splats = 0
        self.server.scene.set_up_direction("+z")

    def clients(self) -> int:
        return len(self.server.get_clients())

    def show_map(self, arrays: dict[str, np.ndarray]) -> int:
        """Show (replace) the map; returns the number of splats drawn. Raises ConfigError on a bad map."""
        centers, covs, rgbs, opac = splats_from_arrays(arrays, self.max_splats)
        with self._lock:
            self.server.scene.add_gaussian_splats("/map/gaussians", centers=centers, covariances=covs, rgbs=rgbs,
                                                  opacities=opac)
            self.splats = len(centers)
        return self.splats

    def show_camera(self, c2w: np.ndarray) -> None:
        """The camera (OpenCV axes, [4, 4] camera-to-world) as axes, and its path so far."""
        m = np.asarray(c2w, np.float64)
        from semantic_gs_slam.geometry import rotmat_to_quat

        with self._lock:
            self.server.scene.add_frame("/camera", axes_length=0.25, axes_radius=0.015,
                                        wxyz=tuple(float(v) for v in rotmat_to_quat(m[:3, :3])),
                                        position=tuple(float(v) for v in m[:3, 3]))
            if not self._path or np.linalg.norm(self._path[-1] - m[:3, 3]) > 0.02:
                self._path.append(m[:3, 3].astype(np.float32))
            if len(self._path) >= 2:
                p = np.stack(self._path)
                self.server.scene.add_line_segments("/camera_path", np.stack([p[:-1], p[1:]], 1),
                                                    colors=(230, 60, 30), thickness=0.02)

    def close(self) -> None:
        self.server.stop()
