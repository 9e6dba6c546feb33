"""NanoDet's raw head (the legacy GFL head of NanoDet-g, RangiLyu/nanodet): pre-processing and decoding in NumPy.

The ONNX graph (:mod:`semantic_gs_slam.models.fetch` makes it) takes one image ``[1, 3, S, S]`` and gives, per
stride ``s`` (8, 16, 32), class scores ``[1, (S/s)^2, C]`` (sigmoid applied) and box distributions
``[1, (S/s)^2, 4 * (reg_max + 1)]``. This module:

* :func:`letterbox`: the frame scaled with its aspect kept into ``S`` x ``S`` (black border, centred), BGR,
  normalised with NanoDet-g's mean and std;
* :func:`decode`: anchor centre ``((i + 0.5) s, (j + 0.5) s)``; each side (left, top, right, bottom) is the
  expectation of the softmax over its ``reg_max + 1`` bins times ``s``; every (anchor, class) pair above the score
  threshold is a candidate; class-wise non-maximum suppression (:func:`nms`);
* :func:`unletterbox`: boxes back into the frame's pixels.
"""

from __future__ import annotations

import numpy as np

MEAN_BGR = np.array([103.53, 116.28, 123.675], np.float32)
STD_BGR = np.array([57.375, 57.12, 58.395], np.float32)


def letterbox(rgb: np.ndarray, size: int) -> tuple[np.ndarray, float, float, float]:
    """Network input of one frame.

    Args:
        rgb: [H, W, 3] uint8, or float in [0, 1].
        size: the network's square input side S.

    Returns:
        (x [1, 3, S, S] float32 BGR normalised, scale, x offset, y offset): frame pixel p is at ``p * scale +
        offset`` in the network input.
    """
    from PIL import Image

    img = np.asarray(rgb)
    if img.dtype != np.uint8:
        img = (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
    h, w = img.shape[:2]
    scale = min(size / w, size / h)
    nw, nh = max(1, round(w * scale)), max(1, round(h * scale))
    resized = np.asarray(Image.fromarray(img).resize((nw, nh), Image.Resampling.BILINEAR))
    ox, oy = (size - nw) // 2, (size - nh) // 2
    canvas = np.zeros((size, size, 3), np.uint8)
    canvas[oy:oy + nh, ox:ox + nw] = resized
    x = (canvas[..., ::-1].astype(np.float32) - MEAN_BGR) / STD_BGR  # RGB -> BGR
    return np.ascontiguousarray(x.transpose(2, 0, 1)[None]), nw / w, float(ox), float(oy)


def unletterbox(boxes: np.ndarray, scale: float, ox: float, oy: float, width: int, height: int) -> np.ndarray:
    """Boxes [N, 4] (x1, y1, x2, y2) of the network input -> the frame's pixels, clipped to it."""
    out = (np.asarray(boxes, np.float64) - [ox, oy, ox, oy]) / scale
    return np.clip(out, 0, [width, height, width, height])


def nms(boxes: np.ndarray, scores: np.ndarray, iou: float) -> np.ndarray:
    """Greedy non-maximum suppression: indices kept, best first.

    Args:
        boxes: [N, 4] x1, y1, x2, y2.
        scores: [N].
        iou: a box overlapping a kept one by more than this is dropped.
    """
    order = np.argsort(-scores, kind="stable")
    area = np.maximum(boxes[:, 2] - boxes[:, 0], 0) * np.maximum(boxes[:, 3] - boxes[:, 1], 0)
    keep = []
    while order.size:
        i = order[0]
        keep.append(i)
        rest = order[1:]
        xx1 = np.maximum(boxes[i, 0], boxes[rest, 0])
        yy1 = np.maximum(boxes[i, 1], boxes[rest, 1])
        xx2 = np.minimum(boxes[i, 2], boxes[rest, 2])
        yy2 = np.minimum(boxes[i, 3], boxes[rest, 3])
        inter = np.maximum(xx2 - xx1, 0) * np.maximum(yy2 - yy1, 0)
        union = area[i] + area[rest] - inter
        overlap = np.where(union > 0, inter / np.maximum(union, 1e-12), 0.0)
        order = rest[overlap <= iou]
    return np.asarray(keep, np.int64)


def decode(levels: list[tuple[np.ndarray, np.ndarray]], size: int, score_threshold: float,
           iou: float = 0.6, max_candidates: int = 1000, max_detections: int = 100
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Detections of NanoDet's raw head.

    Args:
        levels: per stride, (class scores [N, C] after sigmoid, box distributions [N, 4 * (reg_max + 1)]), where
            N = (S / stride)^2; the stride is found from N.
        size: the network's input side S.
        score_threshold: candidates below this score are dropped.
        iou: class-wise NMS threshold.
        max_candidates: the best candidates kept before NMS.
        max_detections: the most detections returned.

    Returns:
        (boxes [K, 4] x1 y1 x2 y2 in network-input pixels, scores [K], class indices [K]), best first.

    Raises:
        ValueError: inconsistent shapes (N not a square grid of S, a box width not a multiple of 4).
    """
    all_boxes, all_scores, all_cls = [], [], []
    for cls, reg in levels:
        n, c = cls.shape
        side = int(round(np.sqrt(n)))
        if side * side != n or size % side or reg.shape[0] != n or reg.shape[1] % 4:
            raise ValueError(f"nanodet: level of {n} anchors and box width {reg.shape[1]} does not fit a "
                             f"{size}x{size} input")
        stride = size // side
        ai, ci = np.nonzero(cls > score_threshold)
        if ai.size == 0:
            continue
        bins = reg.shape[1] // 4
        d = reg[ai].reshape(-1, 4, bins).astype(np.float64)
        d = np.exp(d - d.max(-1, keepdims=True))
        d /= d.sum(-1, keepdims=True)
        dist = (d @ np.arange(bins, dtype=np.float64)) * stride  # [K, 4] left, top, right, bottom
        cx = (ai % side + 0.5) * stride
        cy = (ai // side + 0.5) * stride
        all_boxes.append(np.stack([cx - dist[:, 0], cy - dist[:, 1], cx + dist[:, 2], cy + dist[:, 3]], -1))
        all_scores.append(cls[ai, ci].astype(np.float64))
        all_cls.append(ci)
    if not all_boxes:
        return np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64)
    boxes, scores, labels = np.concatenate(all_boxes), np.concatenate(all_scores), np.concatenate(all_cls)
    top = np.argsort(-scores, kind="stable")[:max_candidates]
    boxes, scores, labels = boxes[top], scores[top], labels[top]
    offset = labels[:, None] * (boxes.max() + size + 1.0)  # class-wise NMS in one pass: classes never overlap
    keep = nms(boxes + offset, scores, iou)[:max_detections]
    return boxes[keep], scores[keep], labels[keep].astype(np.int64)


def is_nanodet_signature(outputs: list[tuple[str, list]]) -> bool:
    """Whether ONNX outputs (name, shape) look like NanoDet's raw head: pairs of [1, N, C] scores and
    [1, N, 4k] distributions with the same N, at least one level."""
    shapes = [s for _, s in outputs]
    if not shapes or len(shapes) % 2 or any(len(s) != 3 or not all(isinstance(d, int) for d in s) for s in shapes):
        return False
    by_n: dict[int, list[int]] = {}
    for s in shapes:
        by_n.setdefault(s[1], []).append(s[2])
    return all(len(v) == 2 for v in by_n.values())


def pair_levels(outputs: list[np.ndarray], num_classes: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Group the head's outputs (any order, batch of 1) into (scores [N, C], distributions [N, 4k]) per level,
    finest first; the scores are the one of the pair with ``num_classes`` columns.

    Raises:
        ValueError: outputs that do not pair up.
    """
    by_n: dict[int, list[np.ndarray]] = {}
    for o in outputs:
        a = np.asarray(o)
        a = a[0] if a.ndim == 3 else a
        by_n.setdefault(a.shape[0], []).append(a)
    levels = []
    for n in sorted(by_n, reverse=True):
        pair = by_n[n]
        cls = [a for a in pair if a.shape[1] == num_classes]
        reg = [a for a in pair if a.shape[1] != num_classes]
        if len(pair) != 2 or len(cls) != 1 or len(reg) != 1:
            raise ValueError(f"nanodet: outputs with {n} anchors do not form a (scores, boxes) pair: "
                             f"{[a.shape for a in pair]}")
        levels.append((cls[0], reg[0]))
    return levels
