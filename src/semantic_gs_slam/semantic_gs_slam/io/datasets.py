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
  depth scale 5000, colour and depth paired within 0.02 s (TUM's ``associate.py``), the reference pose
  interpolated between motion-capture samples at the colour image's time. ETH3D's RGB-D sequences are in this
  layout, with their camera in ``calibration.txt`` (``fx fy cx cy``).
* ``7scenes`` — Microsoft 7-Scenes (one ``seq-XX`` folder): ``frame-XXXXXX.color.jpg``,
  ``frame-XXXXXX.depth.png`` (16-bit millimetres, 0 or 65535 = invalid), ``frame-XXXXXX.pose.txt``
  (4x4 camera-to-world), optional ``camera-intrinsics.txt`` (3x3 K; default fx = fy = 585,
  cx = 320, cy = 240), 30 Hz (time = frame number / 30 s). Colour and depth come from two unregistered
  cameras: expect the colour a few pixels off the depth.

The camera (intrinsics and depth scale) is resolved by :func:`load_dataset`, first source that has it:

1. the caller's (the command line's ``--intrinsics fx,fy,cx,cy`` and ``--depth-scale``);
2. a named preset (``--camera tum-fr1|tum-fr2|tum-fr3``, :data:`CAMERA_PRESETS`);
3. the folder's ``cam.json`` (any layout; schema in :func:`read_cam_json`);
4. the preset the folder's name implies (``rgbd_dataset_freiburg1_xyz`` -> ``tum-fr1``; :func:`camera_from_name`);
5. the layout's own file or default (7-Scenes' ``camera-intrinsics.txt``, a TUM-layout folder's ``calibration.txt``
   as ETH3D's RGB-D sequences have it, the defaults above).

TUM's fr1 and fr2 presets publish lens distortion; frames are not undistorted (the log line says so).

Any layout can be read at a working size (:meth:`Dataset.resized`: colour area-averaged, depth and
labels nearest-neighbour so no invalid zero is blended into a valid depth, intrinsics scaled).
"""

from __future__ import annotations

import copy
import glob
import json
import math
import os
import re
from dataclasses import dataclass

import numpy as np

from semantic_gs_slam.config import Intrinsics
from semantic_gs_slam.errors import DatasetError
from semantic_gs_slam.io.colour_registration import CALIB_FILE, SEVEN_SCENES_COLOUR, ColourCalib, register, scaled
from semantic_gs_slam.io.colour_registration import load as load_colour_calib

REPLICA_INTRINSICS = Intrinsics(1200, 680, 600.0, 600.0, 599.5, 339.5)
TUM_INTRINSICS = Intrinsics(640, 480, 525.0, 525.0, 319.5, 239.5)  # TUM "ROS default"
SEVEN_SCENES_INTRINSICS = Intrinsics(640, 480, 585.0, 585.0, 320.0, 240.0)  # the Kinect v1 depth camera
LAYOUTS = ("replica", "sgs", "tum", "7scenes")
CAM_FILE = "cam.json"
TUM_CALIB_FILE = "calibration.txt"  # a TUM-layout folder's own camera (ETH3D's RGB-D sequences)
CAM_KEYS = ("fx", "fy", "cx", "cy", "width", "height", "depth_scale")  # depth_scale is optional


@dataclass(frozen=True)
class CameraPreset:
    """A published camera: intrinsics of its 640x480 images, depth units per metre, lens distortion."""

    intrinsics: Intrinsics
    depth_scale: float
    distortion: tuple[float, ...]  # OpenCV k1 k2 p1 p2 k3; all zero: none published


# TUM RGB-D's published calibrations of its three Kinects (the colour camera; the depth images are registered to it)
CAMERA_PRESETS: dict[str, CameraPreset] = {
    "tum-fr1": CameraPreset(Intrinsics(640, 480, 517.3, 516.5, 318.6, 255.3), 5000.0,
                            (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "tum-fr2": CameraPreset(Intrinsics(640, 480, 520.9, 521.0, 325.1, 249.7), 5000.0,
                            (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "tum-fr3": CameraPreset(Intrinsics(640, 480, 535.4, 539.2, 320.1, 247.6), 5000.0, (0.0, 0.0, 0.0, 0.0, 0.0)),
}
CAMERAS = ("auto", "none", *CAMERA_PRESETS)  # --camera: auto = from the folder's name, none = never a preset


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
        self.native_intrinsics = intrinsics  # the files' camera; ``intrinsics`` is the working one
        self.invalid_depth_raw: int | None = None  # a raw depth value meaning "no depth" besides 0 (7-Scenes: 65535)
        # the colour camera relative to the depth camera (native size) when colour is not registered to depth;
        # frames are then re-sampled into the depth camera's pixels (:mod:`semantic_gs_slam.io.colour_registration`)
        self.colour_calib: ColourCalib | None = None
        self.intrinsics_source = "the layout's default"  # where the native intrinsics came from (for the log line)
        self.depth_scale_source = "the layout's default"
        self.distortion: tuple[float, ...] | None = None  # a preset's published lens distortion (not corrected)
        self.left_out = ""  # which of the folder's frames the loader left out and why ("" when none)
        # the layout's own camera file could not be read: raised by load_dataset only when no other source gives the
        # camera (a malformed file must not stop --intrinsics, --camera or cam.json from being used)
        self.camera_error: DatasetError | None = None

    def camera_line(self) -> str:
        """One log line: the effective camera, where each part came from, the working size's scaled intrinsics."""
        k, w = self.native_intrinsics, self.intrinsics
        line = (f"camera: fx {k.fx:.2f} fy {k.fy:.2f} cx {k.cx:.2f} cy {k.cy:.2f} at {k.width}x{k.height} "
                f"(from {self.intrinsics_source}), depth scale {self.depth_scale:g} per metre "
                f"(from {self.depth_scale_source})")
        if (w.width, w.height) != (k.width, k.height):
            line += (f"; working size {w.width}x{w.height}: fx {w.fx:.2f} fy {w.fy:.2f} cx {w.cx:.2f} "
                     f"cy {w.cy:.2f}")
        if self.distortion is not None and any(self.distortion):
            line += (f"; lens distortion k1 k2 p1 p2 k3 = {' '.join(f'{d:g}' for d in self.distortion)} "
                     "published, frames NOT undistorted")
        return line

    def resized(self, width: int, height: int) -> Dataset:
        """The same frames at a working size ``width`` x ``height`` (a shallow copy; the files are untouched).

        The intrinsics are scaled per axis (pixel-centre convention); colour is area-averaged, depth and
        labels are taken nearest-neighbour (a depth pixel is never blended with an invalid 0).

        Raises:
            DatasetError: a non-positive size.
        """
        if width <= 0 or height <= 0:
            raise DatasetError(f"working size must be positive, got {width}x{height}")
        out = copy.copy(self)
        out.intrinsics = scale_intrinsics(self.native_intrinsics, width, height)
        return out

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
        if self.invalid_depth_raw is not None:
            depth = np.where(depth == self.invalid_depth_raw, 0, depth)
        depth = depth.astype(np.float32) / self.depth_scale
        if depth.shape != rgb.shape[:2] and self.colour_calib is None:
            raise DatasetError(f"frame {i}: colour {rgb.shape[:2]} and depth {depth.shape} sizes differ")
        sem = None
        if self.sem_paths is not None:
            sem = _read_image(self.sem_paths[i])
            if sem.ndim == 3:
                sem = sem[..., 0]
            if sem.shape != depth.shape:
                raise DatasetError(f"frame {i}: semantic {sem.shape} and depth {depth.shape} sizes differ")
            sem = sem.astype(np.int64)
        k = self.native_intrinsics
        if depth.shape != (k.height, k.width):
            raise DatasetError(f"frame {i}: image {depth.shape[1]}x{depth.shape[0]} does not match the intrinsics "
                               f"{k.width}x{k.height}")
        w = self.intrinsics
        sx, sy = w.width / k.width, w.height / k.height
        native_rgb = rgb.shape[1], rgb.shape[0]
        if (w.width, w.height) != (k.width, k.height):
            cw, ch = round(rgb.shape[1] * sx), round(rgb.shape[0] * sy)
            rgb = rgb if (cw, ch) == (rgb.shape[1], rgb.shape[0]) else resize_area(rgb, cw, ch)
            depth = resize_nearest(depth, w.width, w.height)
            sem = None if sem is None else resize_nearest(sem, w.width, w.height)
        if self.colour_calib is not None:  # at the working size: the colour camera's pixels -> the depth camera's
            c = self.colour_calib  # for colour images of c.width x c.height (0: the files' size)
            rgb = register(rgb, depth, w.fx, w.fy, w.cx, w.cy, scaled(c, rgb.shape[1] / (c.width or native_rgb[0]),
                                                                     rgb.shape[0] / (c.height or native_rgb[1])))
        pose = None if self.poses is None else self.poses[i]
        return Frame(i, self.timestamps[i], rgb, depth, sem, pose)


def scale_intrinsics(k: Intrinsics, width: int, height: int) -> Intrinsics:
    """``k`` for the image resized to ``width`` x ``height`` (per-axis factors, pixel-centre convention)."""
    sx, sy = width / k.width, height / k.height
    return Intrinsics(width, height, k.fx * sx, k.fy * sy, (k.cx + 0.5) * sx - 0.5, (k.cy + 0.5) * sy - 0.5)


def resize_area(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize a float image [H, W, C] by box (area) filtering (PIL, per channel in float32)."""
    from PIL import Image

    chans = [np.asarray(Image.fromarray(np.ascontiguousarray(img[..., c], np.float32), mode="F")
                        .resize((width, height), Image.Resampling.BOX)) for c in range(img.shape[2])]
    return np.stack(chans, -1).astype(np.float32)


def resize_nearest(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour resize of a 2-D array [H, W] (depth, ids): the sample at each output pixel centre."""
    h, w = img.shape[:2]
    ys = np.minimum(((np.arange(height) + 0.5) * h / height).astype(np.int64), h - 1)
    xs = np.minimum(((np.arange(width) + 0.5) * w / width).astype(np.int64), w - 1)
    return img[ys[:, None], xs[None, :]]


def frame_indices(n: int, start: int = 0, stride: int = 1, frames: int = 0, stop: int = 0) -> list[int]:
    """Dataset indices: ``start``, ``start + stride``, ... below ``stop`` (0: the end), at most ``frames`` (0: all).

    Raises:
        DatasetError: negative values, ``stride < 1`` or a range that selects no frame.
    """
    if stride < 1 or start < 0 or frames < 0 or stop < 0:
        raise DatasetError(f"need stride >= 1 and start, frames, stop >= 0; got stride={stride} start={start} "
                           f"frames={frames} stop={stop}")
    idx = list(range(start, min(stop, n) if stop else n, stride))
    if frames:
        idx = idx[:frames]
    if not idx:
        raise DatasetError(f"no frames selected: the dataset has {n} frames, start={start} stop={stop}")
    return idx


#: Largest working width or height (pixels): 8K; a larger one is a typo that would exhaust memory resizing
MAX_SIZE = 8192


def parse_size(text: str) -> tuple[int, int]:
    """``"320x240"`` -> (320, 240).

    Raises:
        DatasetError: anything else.
    """
    m = re.fullmatch(r"\s*(\d{1,6})\s*[xX]\s*(\d{1,6})\s*", text)
    if not m or not 0 < int(m.group(1)) <= MAX_SIZE or not 0 < int(m.group(2)) <= MAX_SIZE:
        raise DatasetError(f"size must be WIDTHxHEIGHT, each 1 .. {MAX_SIZE}, e.g. 320x240; got {text[:40]!r}")
    return int(m.group(1)), int(m.group(2))


def _read_image(path: str) -> np.ndarray:
    from PIL import Image

    if not os.path.isfile(path):
        raise DatasetError(f"missing image file: {path}")
    try:
        with Image.open(path) as im:
            return np.array(im)
    except OSError as exc:
        raise DatasetError(f"{path}: unreadable image ({exc})") from exc


#: How far a pose file's rotation may be from orthonormal (largest |R^T R - I| entry): files written with 6-7 digits
#: are within 1e-5 (7-Scenes' KinectFusion poses 2.4e-4); a matrix farther off is not a camera pose
RIGID_TOLERANCE = 1e-2


def _rigid_error(m: np.ndarray) -> str:
    """Why a finite 4x4 matrix from a pose file is not a rigid camera-to-world transform ("" when it is)."""
    from semantic_gs_slam.geometry import rigid_error

    return rigid_error(m, RIGID_TOLERANCE)


def _finite(v: float) -> bool:
    """A JSON number as a finite float (an integer of 400 digits is not)."""
    try:
        return math.isfinite(float(v))
    except OverflowError:
        return False


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
            why = _rigid_error(m)
            if why:
                raise DatasetError(f"{path}:{ln}: not a camera pose: {why}")
            poses.append(m)
    return poses


def _numbered(folder: str, pattern: str) -> list[str]:
    return [p for _, p in _numbered_with_ids(folder, pattern)]


def _read_classes(root: str) -> dict[int, str]:
    p = os.path.join(root, "semantic.json")
    if not os.path.isfile(p):
        return {}
    try:
        with open(p) as fh:
            return {int(e["id"]): str(e["class"]) for e in json.load(fh)["segmentation"]}
    except (ValueError, KeyError, TypeError) as exc:
        raise DatasetError(f"{p}: not in the {{'segmentation': [{{'id', 'class'}}]}} schema ({exc})") from exc


def read_cam_json(path: str) -> tuple[Intrinsics, float | None]:
    """A ``cam.json``: one JSON object with ``fx``, ``fy``, ``cx``, ``cy`` (pixels), ``width``, ``height`` (the
    files' image size, pixels) and optionally ``depth_scale`` (depth image units per metre: 1000 for millimetres,
    5000 for TUM); no other keys (a misspelt key would otherwise be silently ignored).

    Returns:
        (intrinsics, depth_scale or None when the file does not say).

    Raises:
        DatasetError: unreadable JSON, a missing or unknown key, a value that is not a number, a non-positive size,
            focal length or depth scale (the file and the key are named).
    """
    try:
        with open(path) as fh:
            c = json.load(fh)
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{path}: not a readable JSON file ({exc})") from exc
    if not isinstance(c, dict):
        raise DatasetError(f"{path}: expected a JSON object with keys {', '.join(CAM_KEYS)}, got {type(c).__name__}")
    unknown = sorted(set(c) - set(CAM_KEYS))
    if unknown:
        raise DatasetError(f"{path}: unknown key(s) {', '.join(map(repr, unknown))}; the keys are "
                           f"{', '.join(CAM_KEYS)} (depth_scale optional)")
    missing = [key for key in CAM_KEYS[:6] if key not in c]
    if missing:
        raise DatasetError(f"{path}: missing key(s) {', '.join(map(repr, missing))}; need fx, fy, cx, cy, width, "
                           "height (and optionally depth_scale)")
    for key in c:
        v = c[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not _finite(v):
            raise DatasetError(f"{path}: {key!r} must be a finite number, got {str(v)[:40]}")
    for key in ("width", "height"):
        if c[key] != int(c[key]) or c[key] <= 0:
            raise DatasetError(f"{path}: {key!r} must be a positive whole number of pixels, got {c[key]!r}")
    for key in ("fx", "fy", "depth_scale"):
        if key in c and c[key] <= 0:
            raise DatasetError(f"{path}: {key!r} must be positive, got {c[key]!r}")
    k = Intrinsics(int(c["width"]), int(c["height"]), float(c["fx"]), float(c["fy"]), float(c["cx"]),
                   float(c["cy"]))
    return k, (float(c["depth_scale"]) if "depth_scale" in c else None)


def _read_cam(root: str, default: Intrinsics) -> tuple[Intrinsics, float | None]:
    p = os.path.join(root, CAM_FILE)
    return read_cam_json(p) if os.path.isfile(p) else (default, None)


def parse_intrinsics(text: str) -> tuple[float, float, float, float]:
    """``"517.3,516.5,318.6,255.3"`` -> (fx, fy, cx, cy), in pixels of the files' images.

    Raises:
        DatasetError: not four comma-separated finite numbers, or a non-positive focal length.
    """
    parts = [p.strip() for p in text.split(",")]
    try:
        vals = tuple(float(p) for p in parts)
    except ValueError:
        vals = ()
    if len(vals) != 4 or not all(np.isfinite(vals)):
        raise DatasetError(f"intrinsics must be four numbers fx,fy,cx,cy (pixels), e.g. 517.3,516.5,318.6,255.3; "
                           f"got {text!r}")
    if vals[0] <= 0 or vals[1] <= 0:
        raise DatasetError(f"focal lengths must be positive, got fx={vals[0]:g} fy={vals[1]:g}")
    return vals  # type: ignore[return-value]


def camera_from_name(root: str) -> str | None:
    """The preset a folder's name implies: TUM RGB-D's ``rgbd_dataset_freiburg1_xyz`` -> ``"tum-fr1"`` (its own
    name, else its parent's, so a ``seq`` subfolder works too); None when the name says nothing."""
    path = os.path.abspath(root)
    for name in (os.path.basename(path), os.path.basename(os.path.dirname(path))):
        m = re.search(r"freiburg([123])(?!\d)", name)
        if m:
            return f"tum-fr{m.group(1)}"
    return None


def load_replica(root: str, intrinsics: Intrinsics | None = None, depth_scale: float = 6553.5) -> Dataset:
    """Replica in the NICE-SLAM layout (see module docstring; files paired as :func:`_load_numbered` says).

    Raises:
        DatasetError: a missing folder or trajectory file, and as :func:`_load_numbered`.
    """
    res = os.path.join(root, "results")
    if not os.path.isdir(res):
        raise DatasetError(f"not a Replica (NICE-SLAM) folder: {res} is missing")
    sem_dir = os.path.join(root, "semantic")
    return _load_numbered(root, _numbered_with_ids(res, r"frame(\d+)\.(?:jpg|png)"),
                          _numbered_with_ids(res, r"depth(\d+)\.png"),
                          _numbered_with_ids(sem_dir, r"semantic(\d+)\.png") if os.path.isdir(sem_dir) else None,
                          os.path.join(root, "traj.txt"), intrinsics, depth_scale)


def load_sgs(root: str, intrinsics: Intrinsics | None = None, depth_scale: float = 1000.0) -> Dataset:
    """Replica as SGS-SLAM / Semantic-NeRF lay it out (see module docstring)."""
    for sub in ("rgb", "depth"):
        if not os.path.isdir(os.path.join(root, sub)):
            raise DatasetError(f"not an SGS-SLAM Replica folder: {os.path.join(root, sub)} is missing")
    sd = os.path.join(root, "semantic_class")
    return _load_numbered(root, _numbered_with_ids(os.path.join(root, "rgb"), r"rgb_(\d+)\.(?:png|jpg)"),
                          _numbered_with_ids(os.path.join(root, "depth"), r"depth_(\d+)\.png"),
                          _numbered_with_ids(sd, r"semantic_class_(\d+)\.png") if os.path.isdir(sd) else None,
                          os.path.join(root, "traj_w_c.txt"), intrinsics, depth_scale)


def _load_numbered(root: str, rgb: list[tuple[int, str]], depth: list[tuple[int, str]],
                   sem: list[tuple[int, str]] | None, traj: str, intrinsics: Intrinsics | None, depth_scale: float
                   ) -> Dataset:
    """A Replica-style folder's frames: colour, depth, labels and poses of the same frame numbers (the folder numbers
    its files from 0, and the trajectory file's line n is frame n), never paired by position in a listing; times are
    the frame numbers. A frame number with colour but no depth (or the other way round), without a label image while
    the folder has labels, or past the trajectory file's end is left out (``Dataset.left_out`` says so). The camera:
    ``intrinsics``, else the folder's ``cam.json``, else Replica's; its depth scale, else ``depth_scale``.

    Raises:
        DatasetError: a frame number given twice in one folder, no frame left, a bad ``cam.json``.
    """
    poses_all = _read_c2w_lines(traj)
    for listing in (rgb, depth, sem or []):
        seen: dict[int, str] = {}
        for i, path in listing:
            if i in seen:
                raise DatasetError(f"frame {i} is given twice: {seen[i]} and {path}")
            seen[i] = path
    c, d = dict(rgb), dict(depth)
    s = dict(sem) if sem else None
    # each frame left out is counted once, under the first thing it lacks
    lacks = {"depth image": sorted(set(c) - set(d)), "colour image": sorted(set(d) - set(c)),
             "label image": sorted(i for i in c if i in d and s is not None and i not in s),
             f"line in {os.path.basename(traj)} ({len(poses_all)} lines; line n is frame n, from 0)":
                 sorted(i for i in c if i in d and (s is None or i in s) and i >= len(poses_all))}
    ids = sorted(i for i in c if i in d and (s is None or i in s) and i < len(poses_all))
    note = _left_out_note(lacks)
    if not ids:
        raise DatasetError(f"{root}: no frame has colour, depth{', labels' if s else ''} and a trajectory line"
                           f"{': ' + note if note else ''}")
    k, scale = _read_cam(root, REPLICA_INTRINSICS)
    ds = Dataset(intrinsics or k, [c[i] for i in ids], [d[i] for i in ids], [s[i] for i in ids] if s else None,
                 [poses_all[i] for i in ids], [float(i) for i in ids], scale or depth_scale, _read_classes(root))
    cam = os.path.join(root, CAM_FILE)
    if intrinsics is None and os.path.isfile(cam):
        ds.intrinsics_source = cam
    if scale is not None:
        ds.depth_scale_source = cam
    ds.left_out = note
    return ds


def _left_out_note(lacks: dict[str, list[int]], first: str = "frame") -> str:
    """One line naming the frames a loader left out, by what each lacks (``{"depth image": [frame numbers]}``;
    ``first`` names what the numbers are); "" when none."""
    parts = [f"{len(v)} without a {what} (first: {first} {v[0]})" for what, v in lacks.items() if v]
    return f"frames left out: {'; '.join(parts)}" if parts else ""


def _read_tum_list(path: str, fields: int = 2, what: str = "timestamp filename"
                   ) -> list[tuple[float, list[str], int]]:
    """A TUM list file's lines: (timestamp, the other fields, line number); ``#`` comments and blank lines skipped.

    Raises:
        DatasetError: a line with fewer than ``fields`` fields, or a timestamp that is not a finite number (the file
            and the line are named).
    """
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
                t = float(parts[0])
            except ValueError as exc:
                raise DatasetError(f"{path}:{ln}: bad timestamp ({exc})") from exc
            if not math.isfinite(t):
                raise DatasetError(f"{path}:{ln}: bad timestamp {parts[0]!r} (not a finite number)")
            if len(parts) < fields:
                raise DatasetError(f"{path}:{ln}: expected {fields} fields ({what}), got {len(parts)}")
            out.append((t, parts[1:], ln))
    return out


def _quat_pose(v: list[str], where: str = "") -> np.ndarray:
    """``tx ty tz qx qy qz qw`` -> [4, 4] camera-to-world (the quaternion normalised).

    Raises:
        DatasetError: not numbers, not finite, or a quaternion of (almost) zero length (``where`` names the line).
    """
    import torch

    from semantic_gs_slam.geometry import quat_to_rotmat

    try:
        tx, ty, tz, qx, qy, qz, qw = (float(x) for x in v[:7])
    except ValueError as exc:
        raise DatasetError(f"{where}: a pose is 7 numbers tx ty tz qx qy qz qw ({exc})") from exc
    if not all(math.isfinite(x) for x in (tx, ty, tz, qx, qy, qz, qw)):
        raise DatasetError(f"{where}: the pose has NaN or inf")
    if math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw) < 1e-6:
        raise DatasetError(f"{where}: the quaternion has zero length")
    m = np.eye(4)
    m[:3, :3] = quat_to_rotmat(torch.tensor([qw, qx, qy, qz], dtype=torch.float64)).numpy()
    m[:3, 3] = (tx, ty, tz)
    return m


def load_colmap_poses(path: str) -> dict[str, np.ndarray]:
    """Camera poses in COLMAP's pose convention, one image per line: ``NAME QW QX QY QZ TX TY TZ [more]``, the
    quaternion and translation of the world-to-camera transform, the name first (the layout of the 7-Scenes /
    12-Scenes pseudo ground truth of Brachmann et al., ICCV 2021). COLMAP's own ``images.txt`` is not this layout (id
    first, name last, a line of points after each). ``#`` comments and blank lines are skipped.

    Returns:
        image name -> camera-to-world [4, 4].

    Raises:
        DatasetError: missing file, or a line that is not a name and seven numbers (its number is named).
    """
    if not os.path.isfile(path):
        raise DatasetError(f"missing pose file: {path}")
    out: dict[str, np.ndarray] = {}
    with open(path) as fh:
        for ln, line in enumerate(fh, 1):
            parts = line.split()
            if not parts or parts[0].startswith("#"):
                continue
            try:
                if len(parts) < 8:
                    raise ValueError(f"{len(parts)} fields, need NAME QW QX QY QZ TX TY TZ")
                qw, qx, qy, qz, tx, ty, tz = (float(x) for x in parts[1:8])
                w2c = _quat_pose(parts[5:8] + parts[2:5] + parts[1:2], f"{path}:{ln}")  # TUM's order: t, then x y z w
                if not np.isfinite(w2c).all() or abs(np.linalg.norm([qw, qx, qy, qz]) - 1) > 1e-3:
                    raise ValueError("not a unit quaternion")
            except ValueError as exc:
                raise DatasetError(f"{path}:{ln}: bad pose line ({exc})") from exc
            out[parts[0]] = np.linalg.inv(w2c)
    return out


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


#: Colour and depth further apart than this are not paired (TUM's own ``associate.py`` default).
TUM_MAX_DT = 0.02
#: Reference poses are interpolated between motion-capture samples at most this far apart.
TUM_GT_MAX_GAP = 0.1


def interpolate_pose(times: np.ndarray, poses: list[np.ndarray], t: float, max_gap: float = TUM_GT_MAX_GAP,
                     max_dt: float = TUM_MAX_DT) -> np.ndarray | None:
    """The pose at ``t`` from time-sorted samples: translation linear and rotation slerped between the two samples
    around ``t`` when they are at most ``max_gap`` apart, else the nearest sample within ``max_dt``, else None.

    Args:
        times: [N] sample times (s), ascending.
        poses: N [4, 4] camera-to-world samples.
    """
    j = int(np.searchsorted(times, t))
    if 0 < j < len(times) and times[j] - times[j - 1] <= max_gap:
        t0, t1 = times[j - 1], times[j]
        a = 0.0 if t1 == t0 else (t - t0) / (t1 - t0)
        out = np.eye(4)
        out[:3, 3] = (1 - a) * poses[j - 1][:3, 3] + a * poses[j][:3, 3]
        out[:3, :3] = _slerp(poses[j - 1][:3, :3], poses[j][:3, :3], a)
        return out
    near = [k for k in (j - 1, j) if 0 <= k < len(times)]
    k = min(near, key=lambda k: abs(times[k] - t)) if near else None
    return None if k is None or abs(times[k] - t) > max_dt else poses[k].copy()


def _slerp(r0: np.ndarray, r1: np.ndarray, a: float) -> np.ndarray:
    """The rotation a fraction ``a`` of the way from ``r0`` to ``r1`` (both [3, 3]): ``r0 @ exp(a log(r0^T r1))``.
    Near 180 degrees apart (never between motion-capture samples) the nearer of the two."""
    rel = r0.T @ r1
    angle = float(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1.0, 1.0)))
    w = np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
    if angle < 1e-9:
        return r0.copy()
    if np.linalg.norm(w) < 1e-6:
        return (r0 if a < 0.5 else r1).copy()
    x, y, z = w / np.linalg.norm(w)
    kx = np.array([[0, -z, y], [z, 0, -x], [-y, x, 0]])
    th = a * angle
    return r0 @ (np.eye(3) + np.sin(th) * kx + (1 - np.cos(th)) * kx @ kx)


def load_tum(root: str, intrinsics: Intrinsics | None = None, depth_scale: float = 5000.0,
             max_dt: float = TUM_MAX_DT) -> Dataset:
    """TUM RGB-D (``rgb.txt``, ``depth.txt``, ``groundtruth.txt``): colour and depth paired within ``max_dt``
    seconds, the reference pose interpolated at the colour image's time (:func:`interpolate_pose`); a frame
    without a reference pose there is left out."""
    rgb = sorted(_read_tum_list(os.path.join(root, "rgb.txt")), key=lambda e: e[0])  # in time order, as recorded
    depth = sorted(_read_tum_list(os.path.join(root, "depth.txt")), key=lambda e: e[0])
    gt_path = os.path.join(root, "groundtruth.txt")
    gt = sorted(_read_tum_list(gt_path, 8, "timestamp tx ty tz qx qy qz qw"), key=lambda e: e[0]) \
        if os.path.isfile(gt_path) else None
    if gt is not None and not gt:
        raise DatasetError(f"{gt_path}: no poses (a TUM groundtruth.txt lines up 'timestamp tx ty tz qx qy qz qw')")
    gt_t = np.array([t for t, _, _ in gt]) if gt else np.zeros(0)
    gt_poses = [_quat_pose(v, f"{gt_path}:{ln}") for _, v, ln in gt] if gt else []
    pairs = associate([t for t, _, _ in rgb], [t for t, _, _ in depth], max_dt)
    rgb_p, depth_p, poses, times = [], [], [], []
    paired = {i for i, _ in pairs}
    lacks: dict[str, list[int]] = {f"depth image within {max_dt} s": [ln for n, (_, _, ln) in enumerate(rgb)
                                                                    if n not in paired],
                                   "reference pose at its time": []}
    for i, j in pairs:
        pose = None
        if gt is not None:
            pose = interpolate_pose(gt_t, gt_poses, rgb[i][0], max_dt=max_dt)
            if pose is None:
                lacks["reference pose at its time"].append(rgb[i][2])
                continue
        rgb_p.append(os.path.join(root, rgb[i][1][0]))
        depth_p.append(os.path.join(root, depth[j][1][0]))
        poses.append(pose)
        times.append(rgb[i][0])
    if not rgb_p:
        span = f" (colour {rgb[0][0]:.3f}..{rgb[-1][0]:.3f} s, poses {gt_t[0]:.3f}..{gt_t[-1]:.3f} s)" \
            if gt and rgb else ""
        note = _left_out_note(lacks, first="rgb.txt line")
        raise DatasetError(f"{root}: no colour/depth{'/pose' if gt else ''} triples within {max_dt} s{span}"
                           f"{': ' + note if note else ''}")
    calib = os.path.join(root, TUM_CALIB_FILE)
    own, error = None, None
    if intrinsics is None and os.path.isfile(calib):
        try:
            own = _read_calibration_txt(calib, depth_p[0])
        except DatasetError as exc:
            error = exc
    ds = Dataset(intrinsics or own or TUM_INTRINSICS, rgb_p, depth_p, None, poses if gt is not None else None, times,
                 depth_scale)
    if own is not None:
        ds.intrinsics_source = calib
    ds.camera_error = error
    ds.left_out = _left_out_note(lacks, first="rgb.txt line")
    return ds


def _read_calibration_txt(path: str, image: str) -> Intrinsics:
    """A TUM-layout folder's own camera, ``calibration.txt`` (ETH3D's RGB-D sequences: one line ``fx fy cx cy`` of the
    undistorted images), at the size of ``image`` (the first depth image).

    Raises:
        DatasetError: not one line of four finite numbers with positive focal lengths (the file is named).
    """
    with open(path) as fh:
        lines = [ln.strip() for ln in fh if ln.strip() and not ln.lstrip().startswith("#")]
    try:
        vals = [float(v) for v in lines[0].split()] if len(lines) == 1 else []
    except ValueError:
        vals = []
    if len(vals) != 4 or not all(math.isfinite(v) for v in vals) or min(vals[:2]) <= 0:
        raise DatasetError(f"{path}: expected one line 'fx fy cx cy' (pixels, positive focal lengths), got "
                           f"{' / '.join(lines)[:120]!r}")
    h, w = _read_image(image).shape[:2]
    return Intrinsics(w, h, *vals)


def _read_k_txt(path: str, width: int, height: int) -> Intrinsics:
    """7-Scenes ``camera-intrinsics.txt``: a 3x3 K matrix (rows on lines) of ``width`` x ``height`` images."""
    try:
        vals = np.loadtxt(path, dtype=np.float64)
    except ValueError as exc:
        raise DatasetError(f"{path}: not a 3x3 matrix of numbers ({exc})") from exc
    if vals.shape != (3, 3):
        raise DatasetError(f"{path}: expected a 3x3 K matrix, got shape {vals.shape}")
    if not np.all(np.isfinite(vals)) or not (vals[0, 0] > 0 and vals[1, 1] > 0):
        raise DatasetError(f"{path}: K must be finite with positive focal lengths, got fx={vals[0, 0]:g} "
                           f"fy={vals[1, 1]:g}")
    return Intrinsics(width, height, float(vals[0, 0]), float(vals[1, 1]), float(vals[0, 2]), float(vals[1, 2]))


def _read_c2w_file(path: str) -> np.ndarray:
    try:
        m = np.loadtxt(path, dtype=np.float64)
    except ValueError as exc:
        raise DatasetError(f"{path}: not a 4x4 matrix of numbers ({exc})") from exc
    if m.shape != (4, 4):
        raise DatasetError(f"{path}: expected a 4x4 camera-to-world matrix, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise DatasetError(f"{path}: the camera-to-world matrix has NaN or inf")
    why = _rigid_error(m)
    if why:
        raise DatasetError(f"{path}: not a camera pose: {why}")
    return m


def load_7scenes(root: str, intrinsics: Intrinsics | None = None, depth_scale: float = 1000.0,
                 fps: float = 30.0) -> Dataset:
    """One 7-Scenes sequence folder (see module docstring); timestamps are ``frame number / fps``. A frame without
    its depth image, colour image or (when the folder has poses) pose file is left out (``Dataset.left_out``).

    Raises:
        DatasetError: no complete frame, a bad pose file. A bad K file is kept in ``Dataset.camera_error``
            (:func:`load_dataset` raises it when no other source gives the camera).
    """
    rgb = dict(_numbered_with_ids(root, r"frame-(\d+)\.color\.(?:jpg|png)"))
    depth = dict(_numbered_with_ids(root, r"frame-(\d+)\.depth\.png"))
    pose = dict(_numbered_with_ids(root, r"frame-(\d+)\.pose\.txt"))
    if not rgb:
        seqs = sorted(d for d in os.listdir(root) if d.startswith("seq-")) if os.path.isdir(root) else []
        hint = f" (it has {', '.join(seqs)}: give one of them)" if seqs else ""
        raise DatasetError(f"{root}: no frame-XXXXXX.color.jpg files{hint}")
    lacks = {"depth image": sorted(i for i in rgb if i not in depth),
             "colour image": sorted(i for i in depth if i not in rgb),
             "pose file": sorted(i for i in rgb if i in depth and pose and i not in pose)}
    ids = sorted(i for i in rgb if i in depth and (not pose or i in pose))
    left_out = _left_out_note(lacks)
    if not ids:
        raise DatasetError(f"{root}: no colour frame has a depth image{' and a pose file' if pose else ''}: "
                           f"{left_out}")
    poses = [_read_c2w_file(pose[i]) for i in ids] if pose else None
    kp = os.path.join(root, "camera-intrinsics.txt")
    source, error = "the layout's default", None
    if intrinsics is None and os.path.isfile(kp):
        h, w = _read_image(depth[ids[0]]).shape[:2]  # the K file does not say the image size
        try:
            intrinsics = _read_k_txt(kp, w, h)
            source = kp
        except DatasetError as exc:
            error = exc
    k = intrinsics or SEVEN_SCENES_INTRINSICS
    ds = Dataset(k, [rgb[i] for i in ids], [depth[i] for i in ids], None, poses, [i / fps for i in ids],
                 depth_scale)
    ds.intrinsics_source = source
    ds.camera_error = error
    ds.invalid_depth_raw = 65535
    ds.colour_calib = SEVEN_SCENES_COLOUR  # one Kinect v1 recorded the dataset; load_dataset may replace it
    ds.left_out = left_out
    return ds


def _numbered_with_ids(folder: str, pattern: str) -> list[tuple[int, str]]:
    rx = re.compile(pattern)
    out = []
    for p in glob.glob(os.path.join(folder, "*")):
        m = rx.fullmatch(os.path.basename(p))
        if m:
            out.append((int(m.group(1)), p))
    return sorted(out)


def detect_layout(root: str) -> str:
    """The layout of a dataset folder (one of :data:`LAYOUTS`), told by its files.

    Raises:
        DatasetError: no known layout.
    """
    if os.path.isdir(os.path.join(root, "results")):
        return "replica"
    if os.path.isdir(os.path.join(root, "rgb")) and os.path.isfile(os.path.join(root, "traj_w_c.txt")):
        return "sgs"
    if os.path.isfile(os.path.join(root, "rgb.txt")):
        return "tum"
    if glob.glob(os.path.join(root, "frame-*.color.*")):
        return "7scenes"
    raise DatasetError(f"{root}: cannot tell the layout (no results/, rgb/+traj_w_c.txt, rgb.txt or "
                       f"frame-XXXXXX.color.jpg)")


def load_dataset(root: str, layout: str = "auto", intrinsics: Intrinsics | tuple[float, float, float, float] | None
                 = None, size: tuple[int, int] | None = None, colour_calib: str = "auto",
                 depth_scale: float | None = None, camera: str = "auto") -> Dataset:
    """Open a dataset folder; ``layout`` is ``auto`` or one of :data:`LAYOUTS`.

    Args:
        root: the folder.
        layout: ``auto`` tells it from the files (:func:`detect_layout`).
        intrinsics: overrides every other source of the (native-size) camera: an :class:`Intrinsics`, or
            ``(fx, fy, cx, cy)`` of the files' images (their size is read from the first depth image).
        size: (width, height) working size; frames are resized and the intrinsics scaled (None: native).
        colour_calib: how colour meets depth. ``"auto"``: the folder's ``colour-calibration.json`` when
            present, else the layout's default (7-Scenes: ``colour_registration.SEVEN_SCENES_COLOUR``; the
            others are registered already); ``"none"``: colour taken as registered; else a calibration
            file's path (``python -m semantic_gs_slam.io.calibrate_colour`` writes one).
        depth_scale: depth image units per metre; overrides every other source.
        camera: ``"auto"`` (a preset when the folder's name implies one, :func:`camera_from_name`), ``"none"`` (no
            preset), or a :data:`CAMERA_PRESETS` name, which outranks ``cam.json``. The order of the sources is in
            the module docstring; :meth:`Dataset.camera_line` says which one gave each value.

    Raises:
        DatasetError: missing folder, unknown layout or camera, bad files (a malformed ``cam.json`` included), a bad
            calibration file, a non-positive depth scale.
    """
    if not os.path.isdir(root):
        raise DatasetError(f"dataset folder not found: {root}")
    if camera not in CAMERAS:
        raise DatasetError(f"unknown camera {camera!r}; use one of {', '.join(CAMERAS)}")
    if depth_scale is not None and not (np.isfinite(depth_scale) and depth_scale > 0):
        raise DatasetError(f"depth scale must be a positive number of depth units per metre, got {depth_scale!r}")
    ds = _load(root, layout, None)
    _resolve_camera(ds, root, intrinsics, depth_scale, camera)
    if colour_calib == "auto":
        own = os.path.join(root, CALIB_FILE)
        if os.path.isfile(own):
            ds.colour_calib = load_colour_calib(own)
    elif colour_calib == "none":
        ds.colour_calib = None
    else:
        ds.colour_calib = load_colour_calib(colour_calib)
    return ds.resized(*size) if size is not None else ds


def _resolve_camera(ds: Dataset, root: str, intrinsics, depth_scale: float | None, camera: str) -> None:
    """Apply the camera sources over the layout's own (lowest first, so the highest wins)."""
    named = camera if camera in CAMERA_PRESETS else None
    implied = camera_from_name(root) if camera == "auto" else None
    cam_path = os.path.join(root, CAM_FILE)
    cam = read_cam_json(cam_path) if os.path.isfile(cam_path) else None
    k, k_src = ds.native_intrinsics, ds.intrinsics_source
    scale, scale_src = ds.depth_scale, ds.depth_scale_source
    if implied is not None:
        p = CAMERA_PRESETS[implied]
        k, scale, ds.distortion = p.intrinsics, p.depth_scale, p.distortion
        k_src = scale_src = f"preset {implied}, implied by the folder name {os.path.basename(os.path.abspath(root))!r}"
    if cam is not None:
        k, k_src = cam[0], cam_path
        ds.distortion = None
        if cam[1] is not None:
            scale, scale_src = cam[1], cam_path
    if named is not None:
        p = CAMERA_PRESETS[named]
        k, scale, ds.distortion = p.intrinsics, p.depth_scale, p.distortion
        k_src = scale_src = f"--camera {named}"
    if intrinsics is not None:
        if not isinstance(intrinsics, Intrinsics):
            fx, fy, cx, cy = intrinsics
            h, w = _read_image(ds.depth_paths[0]).shape[:2]  # the images' size, for fx, fy, cx, cy of their pixels
            intrinsics = Intrinsics(w, h, float(fx), float(fy), float(cx), float(cy))
        k, k_src = intrinsics, "--intrinsics"
        ds.distortion = None
    if ds.camera_error is not None and implied is None and cam is None and named is None and intrinsics is None:
        raise ds.camera_error  # the layout's own file is the camera's only source, and it cannot be read
    if depth_scale is not None:
        scale, scale_src = float(depth_scale), "--depth-scale"
    ds.intrinsics = ds.native_intrinsics = k
    ds.intrinsics_source, ds.depth_scale, ds.depth_scale_source = k_src, scale, scale_src


def _load(root: str, layout: str, intrinsics: Intrinsics | None) -> Dataset:
    if layout == "auto":
        layout = detect_layout(root)
    loaders = {"replica": load_replica, "sgs": load_sgs, "tum": load_tum, "7scenes": load_7scenes}
    if layout not in loaders:
        raise DatasetError(f"unknown layout {layout!r}; use one of {sorted(loaders)} or 'auto'")
    return loaders[layout](root, intrinsics)
