"""Per-pixel labels for the SLAM stream when the camera gives none: a plug-in stage between the
dataset / camera and :meth:`semantic_gs_slam.slam.SLAM.add_frame`.

Modes (``LabelConfig.mode``):

* ``dataset`` — the dataset's own label images (ground truth, e.g. our synthetic home);
* ``geometry`` — class-agnostic objects and named planes from depth alone (:mod:`.geometry`), offline,
  no model;
* ``onnx`` — ``geometry`` plus COCO names from a local ONNX segmenter/detector (:mod:`.onnx_model`): the file
  ``onnx_model``, or when that is empty the installed COCO detector (NanoDet-g,
  :func:`semantic_gs_slam.models.fetch.detector_path`);
* ``none`` — no labels (the map has no classes);
* ``auto`` — ``dataset`` when the dataset has label images; else ``onnx`` when ``onnx_model`` is given or the COCO
  detector is installed (``python -m semantic_gs_slam.models.fetch``); else ``geometry``, with one warning line
  (logging) that says how to add the detector.

Names given by people (``"this is my mug"``) are written into a saved map's ``semantic.json`` by
:func:`semantic_gs_slam.labels.names.name_instance`.
"""

from __future__ import annotations

import logging
import numbers
from dataclasses import dataclass, field

import numpy as np

from semantic_gs_slam.config import Intrinsics
from semantic_gs_slam.errors import ConfigError
from semantic_gs_slam.labels.geometry import (
    FIRST_INSTANCE_ID,
    OBJECT_CLASS,
    PLANE_CLASSES,
    TABLE,
    GeometryLabelConfig,
    GeometryLabeller,
)

LABEL_MODES = ("auto", "dataset", "geometry", "onnx", "none")
SUPPORT_IDS = frozenset({10 + 67})  # COCO "dining table" (semantic id COCO_BASE + 67): names the table plane in its box
_log = logging.getLogger(__name__)
OBJECT_ID = 5  # the map id of geometry instances with map_ids "class"


@dataclass
class LabelConfig:
    """Which labels the SLAM stream gets (see the module docstring)."""

    mode: str = "auto"
    onnx_model: str = ""  # path of the ONNX model (modes "onnx" and "auto"); "": the installed COCO detector
    # (semantic_gs_slam.models.fetch.detector_path(): $HOME_ROBOT_MODELS or ~/.cache/home-robot/models,
    # nanodet-g/nanodet-g.onnx)
    onnx_score: float = 0.5  # detections below this score are ignored (the installed NanoDet: detector_score)
    detector_score: float = 0.4  # score threshold when the model is the installed NanoDet-g (measured on the
    # kitchen, docs/detector.md)
    onnx_threads: int = 0  # onnxruntime intra-op threads (0: one per core)
    detector_min_views: int = 1  # > 1: the installed NanoDet-g names a tracked geometry instance only once it was
    # detected as one class in this many labelled frames (the class detected most often; then also in frames that miss
    # it); 1: each detection names the instance in its own frame, and the map's votes decide. Kitchen, docs/detector.md:
    # 2 made the 'tv' answer right but lost the printed mug and grew false instances; a model given by path: always 1
    box_min_fill: float = 0.25  # a detection box names the geometry instance it holds only when that instance fills at
    # least this share of the box's pixels with depth: an object fills much of its own box, while the box of a larger
    # object (a table, its top a plane) also holds other things under or behind it. Kitchen frames 0-249
    # (docs/detector.md): the named instances filled 0.30-0.76 of their boxes, the table's underside in a 'dining
    # table' box 0.04-0.10, a chair and the table's leg in a frame-wide 'bench' box 0.09-0.16; 0: off
    onnx_label_space: str = "coco91"  # "coco91" (category ids 1-90, torchvision) or "coco80" (indices 0-79)
    map_ids: str = "class"  # "class": every geometry instance goes to the map as class OBJECT_ID ("object",
    # one class column; the object-query server splits instances in space); "instance": each tracked instance
    # its own id and class column (names from people can then address it; rendering cost grows with the count)
    geometry: GeometryLabelConfig = field(default_factory=GeometryLabelConfig)
    every: int = 1  # modes geometry and onnx: label only every k-th engine frame and the frames the engine expects
    # to be keyframes (SLAM.keyframe_expected); the others get no labels, so they cast no label votes and seed
    # unlabelled Gaussians. Instances are then tracked across the gaps (map_ids "instance": larger motion between
    # labelled frames can split one). Measured on the 250 kitchen frames, 2 cores (docs/figures.md, "SLAM on the
    # real kitchen"): 1 -> 2.23 FPS with 87.6 % of the Gaussians labelled, 4 -> 2.77 FPS and 81.8 %

    def check(self) -> None:
        """Raise :class:`ConfigError` on an unknown mode, a missing model path or ``every`` < 1."""
        if self.mode not in LABEL_MODES:
            raise ConfigError(f"labels.mode must be one of {LABEL_MODES}, got {self.mode!r}")
        if isinstance(self.every, bool) or not isinstance(self.every, numbers.Integral) or self.every < 1:
            raise ConfigError(f"labels.every must be an integer >= 1, got {self.every!r}")
        if isinstance(self.detector_min_views, bool) or not isinstance(self.detector_min_views, numbers.Integral) \
                or self.detector_min_views < 1:
            raise ConfigError(f"labels.detector_min_views must be an integer >= 1, got {self.detector_min_views!r}")
        if not 0 <= self.onnx_score <= 1 or not 0 <= self.detector_score <= 1:
            raise ConfigError("labels.onnx_score and labels.detector_score must lie in [0, 1]")
        if not 0 <= self.box_min_fill <= 1:
            raise ConfigError(f"labels.box_min_fill must lie in [0, 1], got {self.box_min_fill!r}")
        if self.map_ids not in ("class", "instance"):
            raise ConfigError(f"labels.map_ids must be 'class' or 'instance', got {self.map_ids!r}")
        self.geometry.check()


def predict_pose(poses: list[np.ndarray], first: np.ndarray | None = None) -> np.ndarray:
    """Constant-velocity guess of the next camera-to-world pose from the poses so far ([4, 4]).

    ``first`` (or the identity) when there is none yet.
    """
    if not poses:
        return np.eye(4) if first is None else np.asarray(first, np.float64)
    if len(poses) == 1:
        return poses[-1]
    return poses[-1] @ (np.linalg.inv(poses[-2]) @ poses[-1])


def box_instance(geo: np.ndarray, box: tuple[int, int, int, int]) -> tuple[int, int] | None:
    """The geometry instance that fills most of ``box`` (x1, y1, x2, y2 pixels) in ``geo`` [H, W] (ids), with its
    pixel count in the box; None when the box holds no instance or that instance lies mostly (40 % or more) outside
    the box (not the detected object)."""
    x1, y1, x2, y2 = box
    inside = geo[y1:y2, x1:x2]
    cand = inside[inside >= FIRST_INSTANCE_ID]
    if cand.size == 0:
        return None
    vals, cnt = np.unique(cand, return_counts=True)
    j = int(np.argmax(cnt))
    if cnt[j] < 0.6 * int((geo == vals[j]).sum()):
        return None
    return int(vals[j]), int(cnt[j])


class LabelStage:
    """Turns each RGB-D frame into per-pixel ids according to a :class:`LabelConfig`."""

    def __init__(self, config: LabelConfig, intrinsics: Intrinsics, dataset_has_labels: bool = False) -> None:
        """Resolve the mode and load what it needs.

        Raises:
            ConfigError: bad config; ``dataset`` mode without dataset labels; an unloadable ONNX model.
        """
        from semantic_gs_slam.models.fetch import HOW_TO_ADD, detector_path, installed_detector

        config.check()
        self.cfg = config
        mode = config.mode
        model = config.onnx_model or (installed_detector() if mode in ("auto", "onnx") else None)
        if mode == "auto":
            mode = "dataset" if dataset_has_labels else ("onnx" if model else "geometry")
            if mode == "geometry":
                _log.warning("labels: no COCO detector installed (%s), objects get no names (labels: geometry); "
                             "add it with: %s", detector_path(), HOW_TO_ADD)
        if mode == "onnx" and not model:
            raise ConfigError(f"labels.mode 'onnx' needs labels.onnx_model (a local .onnx file) or the installed COCO "
                              f"detector ({detector_path()}: not there; add it with: {HOW_TO_ADD})")
        if mode == "dataset" and not dataset_has_labels:
            raise ConfigError("labels.mode 'dataset' but the dataset has no label images (use auto or geometry)")
        self.mode = mode
        self.geometry = GeometryLabeller(intrinsics, config.geometry) if mode in ("geometry", "onnx") else None
        self.model = None
        self.min_views = 1  # detections of an instance needed before it is named (installed detector: config's)
        self._inst_votes: dict[int, dict[int, int]] = {}  # geometry instance -> {semantic id: frames detected as it}
        self.model_path = model if mode == "onnx" else None  # the ONNX file used
        self._coco: dict[int, str] = {}
        if mode == "onnx":
            from semantic_gs_slam.labels.onnx_model import OnnxSegmenter, coco_classes

            self.model = OnnxSegmenter(model, config.onnx_score, config.onnx_label_space, threads=config.onnx_threads)
            if self.model.kind == "nanodet" and not config.onnx_model:
                self.model.score_threshold = config.detector_score
                self.min_views = config.detector_min_views
            self._coco = coco_classes()
        self.classes: dict[int, str] = {}  # ids this stage produced -> names
        self._calls = 0  # frames seen (the frame index when the caller gives none)
        if self.geometry is not None:
            self.classes.update(PLANE_CLASSES)
            self.classes[OBJECT_ID] = OBJECT_CLASS

    @property
    def stateful(self) -> bool:
        """Whether this stage keeps state across frames (instances tracked by the geometry layer: modes geometry and
        onnx), so a frame the engine would refuse must be refused before it reaches the stage
        (:meth:`semantic_gs_slam.slam.SLAM.check_frame`)."""
        return self.geometry is not None

    def reserve_ids(self, used: dict[int, str]) -> None:
        """New instance ids start above every id in ``used`` (a resumed map's classes)."""
        if self.geometry is not None and used:
            self.geometry.next_id = max(self.geometry.next_id, max(used) + 1)

    def __call__(self, rgb: np.ndarray, depth: np.ndarray, dataset_labels: np.ndarray | None,
                 c2w: np.ndarray, index: int | None = None, keyframe: bool = False) -> np.ndarray | None:
        """Labels of one frame.

        Args:
            rgb: [H, W, 3] float in [0, 1] or uint8.
            depth: [H, W] metres, 0 = missing.
            dataset_labels: [H, W] ids from the dataset, or None.
            c2w: [4, 4] pose of this frame (tracked, or :func:`predict_pose`), for stable instance ids.
            index: the engine's index of this frame (``len(SLAM.poses)`` before it is added), which
                ``LabelConfig.every`` counts; None: the frames this stage has seen.
            keyframe: the engine expects this frame to be a keyframe (:meth:`SLAM.keyframe_expected`): it is
                labelled whatever ``every`` says.

        Returns:
            [H, W] int64 ids (0 = unlabelled), or None in mode ``none`` and on the frames that ``every`` skips
            (modes geometry and onnx). New ids are added to :attr:`classes`.
        """
        n = self._calls if index is None else index
        labelled = self.stateful and (n % self.cfg.every == 0 or keyframe)
        # the model first: when it refuses the frame (FrameError) nothing of this stage has changed yet
        detections = self.model(rgb) if labelled and self.model is not None else []
        self._calls += 1
        if self.mode == "none":
            return None
        if self.mode == "dataset":
            return None if dataset_labels is None else np.asarray(dataset_labels, np.int64)
        if not labelled:
            return None
        assert self.geometry is not None  # modes geometry and onnx
        ids = self.geometry.label(rgb, depth, c2w).ids
        if self.model is not None:
            ids = self._apply_model(detections, ids, depth)
        if self.cfg.map_ids == "class":
            ids = np.where(ids >= FIRST_INSTANCE_ID, OBJECT_ID, ids)
        for i in np.unique(ids):
            if i > 0 and int(i) not in self.classes:
                self.classes[int(i)] = self.geometry.classes.get(int(i)) or self._coco.get(int(i), f"class_{i}")
        return ids

    def _apply_model(self, detections: list, geo: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
        """COCO names over the geometry labels: a mask's pixels take its class; without masks a detection
        names the geometry instance that fills most of its box, when that instance lies mostly inside the box and
        fills at least ``box_min_fill`` of the box's pixels with depth (``depth`` [H, W]; None: all of the box's
        pixels); and a detected support (``dining table``, :data:`SUPPORT_IDS`) also names the geometry's ``table``
        plane pixels in its box (its top is a plane, not an instance). ``detections``: the model's output for the
        frame (``OnnxSegmenter.__call__``: (id, score, mask or None, box), best first)."""
        out = geo.copy()
        h, w = geo.shape
        seen: dict[int, int] = {}  # instance -> class it was named in this frame
        for sem_id, _score, mask, box in reversed(detections):  # best last: it wins overlaps
            if mask is None:
                x1, y1, x2, y2 = np.clip(np.round(box), 0, [w, h, w, h]).astype(int)
                if sem_id in SUPPORT_IDS:
                    top = out[y1:y2, x1:x2]
                    top[geo[y1:y2, x1:x2] == TABLE] = sem_id
                found = box_instance(geo, (x1, y1, x2, y2))
                if found is None:  # no instance, or the largest lies mostly outside the box: not this object
                    continue
                inst, cnt = found
                measured = (y2 - y1) * (x2 - x1) if depth is None else int(np.count_nonzero(depth[y1:y2, x1:x2] > 0))
                if cnt < self.cfg.box_min_fill * measured:  # a small part of the box: something under or behind
                    continue  # the detected object (a table's leg in its box), not the object
                if self.min_views > 1:  # voted over the labelled frames: see _confirmed_names
                    seen[inst] = sem_id
                    continue
                mask = geo == inst
            out[mask] = sem_id
        if self.min_views > 1:
            self._confirmed_names(seen, geo, out)
        return out

    def _confirmed_names(self, seen: dict[int, int], geo: np.ndarray, out: np.ndarray) -> None:
        """Name the tracked geometry instances by their detections over the labelled frames so far: an instance takes
        the class it was detected as most often once that count reaches :attr:`min_views` (one-off false detections
        name nothing), and keeps it in the frames where the detector misses it (a small cup seen from afar)."""
        for inst, sem_id in seen.items():
            votes = self._inst_votes.setdefault(inst, {})
            votes[sem_id] = votes.get(sem_id, 0) + 1
        for inst in np.unique(geo[geo >= FIRST_INSTANCE_ID]):
            votes = self._inst_votes.get(int(inst))
            if not votes:
                continue
            sem_id, n = max(votes.items(), key=lambda kv: (kv[1], -kv[0]))
            if n >= self.min_views:
                out[geo == inst] = sem_id
