"""RGB-D (+ semantic) dataset readers.

Layouts:

* ``replica`` — Replica as NICE-SLAM ships it: ``results/frame%06d.jpg``, ``results/depth%06d.png``
  (16-bit, metres x 6553.5), ``traj.txt`` (one 4x4 camera-to-world matrix per line), 1200x680,
  fx = fy = 600, cx = 599.5, cy = 339.5. Optional (our synthetic home adds them):
  ``semantic/semantic%06d.png`` ids, ``cam.json`` intrinsics, ``semantic.json`` classes.
* ``sgs`` — the Semantic-NeRF Replica renders SGS-SLAM uses: ``rgb/rgb_%d.png``,
  ``depth/depth_%d.png`` (16-bit, depth_scale default 1000), ``semantic_class/semantic_class_%d.png``,
  ``traj_w_c.txt`` (4x4 camera-to-world per line).
* ``tum`` — TUM RGB-D: ``rgb.txt``, ``depth.txt``, ``groundtruth.txt`` (t tx ty tz qx qy qz qw),
  depth scale 5000, rgb/depth/pose associated within 0.08 s.
"""

from __future__ import annotations

import glob
import json
import os
import re
from dataclasses import dataclass

import numpy as np

from semantic_gs_slam.config import Intrinsics
from semantic_gs_slam.errors import DatasetError

REPLICA_INTRINSICS = Intrinsics(1200, 680, 600.0, 600.0, 599.5, 339.5)
TUM_INTRINSICS = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)  # TUM "ROS default"


@dataclass
class Frame:
    """One RGB-D frame."""

    index: int
    timestamp: float
    rgb: np.ndarray  # [H, W, 3] float32 in [0, 1]
    depth: np.ndarray  # [H, W] float32 metres, 0 = missing
    semantics: np.ndarray | None  # [H, W] int64 class ids, or None
    gt_c2w: np.ndarray | None  # [4, 4] float64 or None


class Dataset:
    """A random-access sequence of :class:`Frame` (use ``len`` and indexing)."""

    def __init__(self, intrinsics: Intrinsics, rgb_paths: list[str], depth_paths: list[str],
                 sem_paths: list[str] | None, poses: list[np.ndarray] | None, timestamps: list[float],
                 depth_scale: float, classes: dict[int, str] | None = None) -> None:
        n = len(rgb_paths)
        if n == 0:
            raise DatasetError("dataset has no frames")
        if len(depth_paths) != n:
            raise DatasetError(f"{n} colour images but {len(depth_paths)} depth images")
        if sem_paths is not None and len(sem_paths) != n:
            raise DatasetError(f"{n} colour images but {len(sem_paths)} semantic images")
        if poses is not None and len(poses) < n:
            raise DatasetError(f"{n} frames but only {len(poses)} poses in the trajectory file")
        self.intrinsics = intrinsics
        self.rgb_paths, self.depth_paths, self.sem_paths = rgb_paths, depth_paths, sem_paths
        self.poses, self.timestamps, self.depth_scale = poses, timestamps, depth_scale
        self.classes = classes or {}

    def __len__(self) -> int:
        return len(self.rgb_paths)

    def __getitem__(self, i: int) -> Frame:
        if not -len(self) <= i < len(self):
            raise IndexError(i)
        i = i % len(self)
        rgb = _read_image(self.rgb_paths[i])
        if rgb.ndim != 3 or rgb.shape[2] < 3:
            raise DatasetError(f"{self.rgb_paths[i]}: expected a colour image, got shape {rgb.shape}")
        rgb = rgb[..., :3].astype(np.float32) / 255.0
        depth = _read_image(self.depth_paths[i])
        if depth.ndim != 2:
            raise DatasetError(f"{self.depth_paths[i]}: expected a single-channel depth image, got {depth.shape}")
        depth = depth.astype(np.float32) / self.depth_scale
        if depth.shape != rgb.shape[:2]:
            raise DatasetError(f"frame {i}: colour {rgb.shape[:2]} and depth {depth.shape} sizes differ")
        sem = None
        if self.sem_paths is not None:
            sem = _read_image(self.sem_paths[i])
            if sem.ndim == 3:
                sem = sem[..., 0]
            if sem.shape != depth.shape:
                raise DatasetError(f"frame {i}: semantic {sem.shape} and depth {depth.shape} sizes differ")
            sem = sem.astype(np.int64)
        k = self.intrinsics
        if rgb.shape[:2] != (k.height, k.width):
            raise DatasetError(f"frame {i}: image {rgb.shape[1]}x{rgb.shape[0]} does not match the intrinsics "
                               f"{k.width}x{k.height}")
        pose = None if self.poses is None else self.poses[i]
        return Frame(i, self.timestamps[i], rgb, depth, sem, pose)


def _read_image(path: str) -> np.ndarray:
    from PIL import Image

    if not os.path.isfile(path):
        raise DatasetError(f"missing image file: {path}")
    try:
        with Image.open(path) as im:
            return np.array(im)
    except OSError as exc:
        raise DatasetError(f"{path}: unreadable image ({exc})") from exc


def _read_c2w_lines(path: str) -> list[np.ndarray]:
    if not os.path.isfile(path):
        raise DatasetError(f"missing trajectory file: {path}")
    poses = []
    with open(path) as fh:
        for ln, line in enumerate(fh, 1):
            if not line.strip():
                continue
            try:
                vals = np.array([float(x) for x in line.split()])
            except ValueError as exc:
                raise DatasetError(f"{path}:{ln}: not numbers ({exc})") from exc
            if vals.size != 16:
                raise DatasetError(f"{path}:{ln}: expected 16 numbers (a 4x4 matrix), got {vals.size}")
            m = vals.reshape(4, 4)
            if not np.all(np.isfinite(m)):
                raise DatasetError(f"{path}:{ln}: non-finite pose")
            poses.append(m)
    return poses


def _numbered(folder: str, pattern: str) -> list[str]:
    rx = re.compile(pattern)
    files = []
    for p in glob.glob(os.path.join(folder, "*")):
        m = rx.fullmatch(os.path.basename(p))
        if m:
            files.append((int(m.group(1)), p))
    return [p for _, p in sorted(files)]


def _read_classes(root: str) -> dict[int, str]:
    p = os.path.join(root, "semantic.json")
    if not os.path.isfile(p):
        return {}
    try:
        with open(p) as fh:
            return {int(e["id"]): str(e["class"]) for e in json.load(fh)["segmentation"]}
    except (ValueError, KeyError, TypeError) as exc:
        raise DatasetError(f"{p}: not in the {{'segmentation': [{{'id', 'class'}}]}} schema ({exc})") from exc


def _read_cam(root: str, default: Intrinsics) -> tuple[Intrinsics, float | None]:
    p = os.path.join(root, "cam.json")
    if not os.path.isfile(p):
        return default, None
    with open(p) as fh:
        c = json.load(fh)
    try:
        k = Intrinsics(int(c["width"]), int(c["height"]), float(c["fx"]), float(c["fy"]), float(c["cx"]), float(c["cy"]))
    except KeyError as exc:
        raise DatasetError(f"{p}: missing key {exc}") from exc
    return k, c.get("depth_scale")


def load_replica(root: str, intrinsics: Intrinsics | None = None, depth_scale: float = 6553.5) -> Dataset:
    """Replica in the NICE-SLAM layout (see module docstring).

    Raises:
        DatasetError: missing folder/files, counts that do not match.
    """
    res = os.path.join(root, "results")
    if not os.path.isdir(res):
        raise DatasetError(f"not a Replica (NICE-SLAM) folder: {res} is missing")
    rgb = _numbered(res, r"frame(\d+)\.(?:jpg|png)")
    depth = _numbered(res, r"depth(\d+)\.png")
    sem_dir = os.path.join(root, "semantic")
    sem = _numbered(sem_dir, r"semantic(\d+)\.png") if os.path.isdir(sem_dir) else None
    poses = _read_c2w_lines(os.path.join(root, "traj.txt"))
    k, ds = _read_cam(root, REPLICA_INTRINSICS)
    return Dataset(intrinsics or k, rgb, depth, sem or None, poses, [float(i) for i in range(len(rgb))],
                   ds or depth_scale, _read_classes(root))


def load_sgs(root: str, intrinsics: Intrinsics | None = None, depth_scale: float = 1000.0) -> Dataset:
    """Replica as SGS-SLAM / Semantic-NeRF lay it out (see module docstring)."""
    for sub in ("rgb", "depth"):
        if not os.path.isdir(os.path.join(root, sub)):
            raise DatasetError(f"not an SGS-SLAM Replica folder: {os.path.join(root, sub)} is missing")
    rgb = _numbered(os.path.join(root, "rgb"), r"rgb_(\d+)\.(?:png|jpg)")
    depth = _numbered(os.path.join(root, "depth"), r"depth_(\d+)\.png")
    sd = os.path.join(root, "semantic_class")
    sem = _numbered(sd, r"semantic_class_(\d+)\.png") if os.path.isdir(sd) else None
    poses = _read_c2w_lines(os.path.join(root, "traj_w_c.txt"))
    k, ds = _read_cam(root, REPLICA_INTRINSICS)
    return Dataset(intrinsics or k, rgb, depth, sem or None, poses, [float(i) for i in range(len(rgb))],
                   ds or depth_scale, _read_classes(root))


def _read_tum_list(path: str) -> list[tuple[float, list[str]]]:
    if not os.path.isfile(path):
        raise DatasetError(f"missing TUM list file: {path}")
    out = []
    with open(path) as fh:
        for ln, line in enumerate(fh, 1):
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            parts = line.split()
            try:
                out.append((float(parts[0]), parts[1:]))
            except ValueError as exc:
                raise DatasetError(f"{path}:{ln}: bad timestamp ({exc})") from exc
    return out


def _quat_pose(v: list[str]) -> np.ndarray:
    from semantic_gs_slam.geometry import quat_to_rotmat
    import torch

    tx, ty, tz, qx, qy, qz, qw = (float(x) for x in v[:7])
    m = np.eye(4)
    m[:3, :3] = quat_to_rotmat(torch.tensor([qw, qx, qy, qz], dtype=torch.float64)).numpy()
    m[:3, 3] = (tx, ty, tz)
    return m


def associate(a: list[float], b: list[float], max_dt: float) -> list[tuple[int, int]]:
    """Greedy nearest-timestamp association (each element used once), pairs sorted by ``a`` index."""
    bs = np.asarray(b)
    used: set[int] = set()
    pairs = []
    for i, t in enumerate(a):
        if len(bs) == 0:
            break
        j = int(np.argmin(np.abs(bs - t)))
        if abs(bs[j] - t) <= max_dt and j not in used:
            used.add(j)
            pairs.append((i, j))
    return pairs


def load_tum(root: str, intrinsics: Intrinsics | None = None, depth_scale: float = 5000.0,
             max_dt: float = 0.08) -> Dataset:
    """TUM RGB-D (``rgb.txt``, ``depth.txt``, ``groundtruth.txt``), associated within ``max_dt`` seconds."""
    rgb = _read_tum_list(os.path.join(root, "rgb.txt"))
    depth = _read_tum_list(os.path.join(root, "depth.txt"))
    gt_path = os.path.join(root, "groundtruth.txt")
    gt = _read_tum_list(gt_path) if os.path.isfile(gt_path) else None
    pairs = associate([t for t, _ in rgb], [t for t, _ in depth], max_dt)
    rgb_p, depth_p, poses, times = [], [], [], []
    for i, j in pairs:
        pose = None
        if gt is not None:
            k = int(np.argmin(np.abs(np.array([t for t, _ in gt]) - rgb[i][0])))
            if abs(gt[k][0] - rgb[i][0]) > max_dt:
                continue
            pose = _quat_pose(gt[k][1])
        rgb_p.append(os.path.join(root, rgb[i][1][0]))
        depth_p.append(os.path.join(root, depth[j][1][0]))
        poses.append(pose)
        times.append(rgb[i][0])
    if not rgb_p:
        raise DatasetError(f"{root}: no colour/depth{'/pose' if gt else ''} triples within {max_dt} s")
    return Dataset(intrinsics or TUM_INTRINSICS, rgb_p, depth_p, None, poses if gt is not None else None, times,
                   depth_scale)


def load_dataset(root: str, layout: str = "auto", intrinsics: Intrinsics | None = None) -> Dataset:
    """Open a dataset folder; ``layout`` is ``auto``, ``replica``, ``sgs`` or ``tum``."""
    if not os.path.isdir(root):
        raise DatasetError(f"dataset folder not found: {root}")
    if layout == "auto":
        if os.path.isdir(os.path.join(root, "results")):
            layout = "replica"
        elif os.path.isdir(os.path.join(root, "rgb")) and os.path.isfile(os.path.join(root, "traj_w_c.txt")):
            layout = "sgs"
        elif os.path.isfile(os.path.join(root, "rgb.txt")):
            layout = "tum"
        else:
            raise DatasetError(f"{root}: cannot tell the layout (no results/, rgb/+traj_w_c.txt or rgb.txt)")
    loaders = {"replica": load_replica, "sgs": load_sgs, "tum": load_tum}
    if layout not in loaders:
        raise DatasetError(f"unknown layout {layout!r}; use one of {sorted(loaders)} or 'auto'")
    return loaders[layout](root, intrinsics)
