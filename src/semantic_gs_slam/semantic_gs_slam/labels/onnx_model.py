"""Names from a pretrained model: an ONNX instance segmenter or detector with COCO classes, run with
onnxruntime (CUDA provider when present, else CPU), loaded from a local file the user gives.

Accepted signatures:

**NanoDet's raw head** (the COCO detector :mod:`semantic_gs_slam.models.fetch` installs): one float input
``[1, 3, S, S]`` and pairs of outputs per stride, class scores ``[1, N, 80]`` (sigmoid applied, COCO's 80 classes in
their contiguous order) and box distributions ``[1, N, 4 (reg_max + 1)]``; decoded by :mod:`.nanodet` (letterbox in
and out, GFL distances, class-wise NMS at IoU ``nms_iou``). Recognised by the output shapes.

**torchvision** (the Mask R-CNN / Faster R-CNN export and its batched variant):

* input: one float32 (0-1) or uint8 RGB image, ``[3, H, W]`` or ``[1, 3, H, W]``; a fixed H, W in the
  model is honoured by resizing the frame (boxes and masks are scaled back);
* outputs, found by name (``box``, ``label``/``class``, ``score``, ``mask`` in the name) or else in this
  order: ``boxes [N, 4]`` (x1, y1, x2, y2 pixels), ``labels [N]`` (COCO category ids 1-90, or 0-79
  indices with ``label_space="coco80"``), ``scores [N]``, optional ``masks [N, 1, H, W]`` (probabilities);
  a leading batch dimension of 1 is dropped.

Without masks, a detection names the geometry instance (:mod:`semantic_gs_slam.labels.geometry`) that
fills most of its box. Semantic ids of COCO classes are ``COCO_BASE + category id``.
"""

from __future__ import annotations

import os

import numpy as np

from semantic_gs_slam.errors import ConfigError, FrameError

COCO_BASE = 10  # semantic id = COCO_BASE + COCO category id (11..100; plane classes 1-4, instances >= 128)
COCO_NAMES: dict[int, str] = {
    1: "person", 2: "bicycle", 3: "car", 4: "motorcycle", 5: "airplane", 6: "bus", 7: "train", 8: "truck",
    9: "boat", 10: "traffic light", 11: "fire hydrant", 13: "stop sign", 14: "parking meter", 15: "bench",
    16: "bird", 17: "cat", 18: "dog", 19: "horse", 20: "sheep", 21: "cow", 22: "elephant", 23: "bear",
    24: "zebra", 25: "giraffe", 27: "backpack", 28: "umbrella", 31: "handbag", 32: "tie", 33: "suitcase",
    34: "frisbee", 35: "skis", 36: "snowboard", 37: "sports ball", 38: "kite", 39: "baseball bat",
    40: "baseball glove", 41: "skateboard", 42: "surfboard", 43: "tennis racket", 44: "bottle",
    46: "wine glass", 47: "cup", 48: "fork", 49: "knife", 50: "spoon", 51: "bowl", 52: "banana", 53: "apple",
    54: "sandwich", 55: "orange", 56: "broccoli", 57: "carrot", 58: "hot dog", 59: "pizza", 60: "donut",
    61: "cake", 62: "chair", 63: "couch", 64: "potted plant", 65: "bed", 67: "dining table", 70: "toilet",
    72: "tv", 73: "laptop", 74: "mouse", 75: "remote", 76: "keyboard", 77: "cell phone", 78: "microwave",
    79: "oven", 80: "toaster", 81: "sink", 82: "refrigerator", 84: "book", 85: "clock", 86: "vase",
    87: "scissors", 88: "teddy bear", 89: "hair drier", 90: "toothbrush"}
COCO80_TO_91 = sorted(COCO_NAMES)  # contiguous 0-79 index -> category id


def coco_classes() -> dict[int, str]:
    """Semantic id -> class name of every COCO class."""
    return {COCO_BASE + c: n for c, n in COCO_NAMES.items()}


def _providers() -> list[str]:
    import onnxruntime as ort

    have = ort.get_available_providers()
    return [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in have]


class OnnxSegmenter:
    """An ONNX COCO instance segmenter/detector applied to one RGB frame at a time."""

    def __init__(self, path: str, score_threshold: float = 0.5, label_space: str = "coco91",
                 mask_threshold: float = 0.5, threads: int = 0, nms_iou: float = 0.6) -> None:
        """Load the model.

        Args:
            path: the .onnx file.
            score_threshold: detections below this score are dropped.
            label_space: class numbering of a torchvision model (a NanoDet head is always COCO's 80 classes).
            mask_threshold: mask probability that counts as inside.
            threads: onnxruntime's intra-op threads (0: its default, one per core).
            nms_iou: class-wise NMS threshold of the NanoDet decoder.

        Raises:
            ConfigError: missing file, onnxruntime not installed, a signature this class cannot read.
        """
        if not path or not os.path.isfile(path):
            raise ConfigError(f"labels: ONNX model file not found: {path!r}")
        if label_space not in ("coco91", "coco80"):
            raise ConfigError(f"labels: label_space must be 'coco91' or 'coco80', got {label_space!r}")
        try:
            import onnxruntime as ort
        except ImportError as exc:
            raise ConfigError("labels: the onnx mode needs onnxruntime (pip install onnxruntime)") from exc
        opts = ort.SessionOptions()
        opts.log_severity_level = 3  # no warnings about folded initializers on stderr
        if threads > 0:
            opts.intra_op_num_threads = threads
        try:
            self.session = ort.InferenceSession(path, opts, providers=_providers())
        except Exception as exc:  # onnxruntime raises its own exception types for bad files
            raise ConfigError(f"labels: cannot load ONNX model {path}: {exc}") from exc
        self.score_threshold, self.label_space, self.mask_threshold = score_threshold, label_space, mask_threshold
        inputs = self.session.get_inputs()
        if len(inputs) != 1:
            raise ConfigError(f"labels: expected a model with one image input, {path} has {len(inputs)}")
        self.input = inputs[0]
        shape = list(self.input.shape)
        if len(shape) not in (3, 4) or (len(shape) == 4 and shape[0] not in (1, "batch", None) and
                                        not isinstance(shape[0], str)):
            raise ConfigError(f"labels: input {self.input.name} must be [3, H, W] or [1, 3, H, W], got {shape}")
        self.batched = len(shape) == 4
        hw = shape[-2:]
        self.fixed_hw = tuple(hw) if all(isinstance(x, int) for x in hw) else None
        self.uint8 = "uint8" in self.input.type
        self.nms_iou = nms_iou
        self.provider = self.session.get_providers()[0]
        from semantic_gs_slam.labels.nanodet import is_nanodet_signature

        heads = [(o.name, list(o.shape)) for o in self.session.get_outputs()]
        self.kind = "nanodet" if (is_nanodet_signature(heads) and len(shape) == 4 and self.fixed_hw is not None
                                  and self.fixed_hw[0] == self.fixed_hw[1]
                                  and any(s[2] == 80 for _, s in heads)) else "torchvision"
        if self.kind == "nanodet":
            return
        outs = [o.name for o in self.session.get_outputs()]
        if len(outs) < 3:
            raise ConfigError(f"labels: expected boxes, labels, scores (and masks) outputs, got {outs}")
        self.out_index = self._match_outputs(outs)

    @staticmethod
    def _match_outputs(names: list[str]) -> dict[str, int]:
        keys = {"boxes": ("box",), "labels": ("label", "class"), "scores": ("score", "conf"), "masks": ("mask",)}
        found = {}
        for k, subs in keys.items():
            hit = [i for i, n in enumerate(names) if any(s in n.lower() for s in subs)]
            if hit:
                found[k] = hit[0]
        if not all(k in found for k in ("boxes", "labels", "scores")):
            found = {"boxes": 0, "labels": 1, "scores": 2}
            if len(names) > 3:
                found["masks"] = 3
        return found

    def __call__(self, rgb: np.ndarray) -> list[tuple[int, float, np.ndarray | None, np.ndarray]]:
        """Detections in one frame.

        Args:
            rgb: [H, W, 3] float in [0, 1] or uint8.

        Returns:
            list of (semantic id, score, mask [H, W] bool or None, box [4] x1 y1 x2 y2 pixels) above the
            score threshold, best first; classes outside COCO are skipped.

        Raises:
            FrameError: a frame that is not [H, W, 3]; the model failing on it.
        """
        from PIL import Image

        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3:
            raise FrameError(f"labels: rgb must be [H, W, 3], got {list(rgb.shape)}")
        h, w = rgb.shape[:2]
        if self.kind == "nanodet":
            return self._nanodet(rgb)
        img = rgb.astype(np.float32) / 255.0 if rgb.dtype == np.uint8 else rgb.astype(np.float32)
        if self.fixed_hw is not None and self.fixed_hw != (h, w):
            fh, fw = self.fixed_hw
            img = np.stack([np.asarray(Image.fromarray(img[..., c], mode="F")
                                       .resize((fw, fh), Image.Resampling.BILINEAR)) for c in range(3)], -1)
        x = img.transpose(2, 0, 1)
        x = (x * 255 + 0.5).clip(0, 255).astype(np.uint8) if self.uint8 else np.ascontiguousarray(x, np.float32)
        if self.batched:
            x = x[None]
        try:
            outs = self.session.run(None, {self.input.name: x})
        except Exception as exc:  # onnxruntime's own error types
            raise FrameError(f"labels: the ONNX model failed on a {w}x{h} frame: {exc}") from exc
        oi = self.out_index

        def get(name: str, rank: int) -> np.ndarray | None:
            if name not in oi:
                return None
            a = np.asarray(outs[oi[name]])
            return a[0] if a.ndim == rank + 1 and a.shape[0] == 1 else a

        boxes, labels, scores = get("boxes", 2), get("labels", 1), get("scores", 1)
        masks = get("masks", 4)
        if boxes is None or labels is None or scores is None or boxes.ndim != 2 or boxes.shape[-1] != 4:
            raise FrameError("labels: the ONNX model did not return boxes [N, 4], labels [N], scores [N]")
        sy, sx = (h / img.shape[0], w / img.shape[1])
        res = []
        for j in np.argsort(-scores):
            if scores[j] < self.score_threshold:
                break
            lab = int(labels[j])
            cat = COCO80_TO_91[lab] if self.label_space == "coco80" and 0 <= lab < 80 else lab
            if cat not in COCO_NAMES:
                continue
            box = boxes[j].astype(np.float64) * np.array([sx, sy, sx, sy])
            mask = None
            if masks is not None:
                m = masks[j].reshape(masks.shape[-2:]).astype(np.float32)
                if m.shape != (h, w):
                    m = np.asarray(Image.fromarray(m, mode="F").resize((w, h), Image.Resampling.BILINEAR))
                mask = m > self.mask_threshold
            res.append((COCO_BASE + cat, float(scores[j]), mask, box))
        return res

    def _nanodet(self, rgb: np.ndarray) -> list[tuple[int, float, np.ndarray | None, np.ndarray]]:
        from semantic_gs_slam.labels import nanodet

        h, w = rgb.shape[:2]
        size = self.fixed_hw[0]
        x, scale, ox, oy = nanodet.letterbox(rgb, size)
        try:
            outs = self.session.run(None, {self.input.name: x})
            levels = nanodet.pair_levels(outs, 80)
            boxes, scores, labels = nanodet.decode(levels, size, self.score_threshold, self.nms_iou)
        except Exception as exc:  # onnxruntime's own error types; a head that does not decode
            raise FrameError(f"labels: the NanoDet model failed on a {w}x{h} frame: {exc}") from exc
        boxes = nanodet.unletterbox(boxes, scale, ox, oy, w, h)
        return [(COCO_BASE + COCO80_TO_91[int(c)], float(sc), None, b)
                for b, sc, c in zip(boxes, scores, labels, strict=True)]
