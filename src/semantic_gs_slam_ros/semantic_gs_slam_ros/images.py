"""Image conversions of the streaming server (pure numpy; no rclpy).

Works on anything with the fields of ``sensor_msgs/Image`` (height, width, encoding, step,
is_bigendian, data), so it is unit-tested without ROS.
"""

from __future__ import annotations

import sys
from array import array as byte_array
from typing import Any

import numpy as np

from semantic_gs_slam_ros.errors import ImageFormatError

#: encoding -> (numpy dtype, channels)
ENCODINGS: dict[str, tuple[np.dtype, int]] = {
    "rgb8": (np.dtype(np.uint8), 3),
    "bgr8": (np.dtype(np.uint8), 3),
    "rgba8": (np.dtype(np.uint8), 4),
    "bgra8": (np.dtype(np.uint8), 4),
    "mono8": (np.dtype(np.uint8), 1),
    "8UC1": (np.dtype(np.uint8), 1),
    "mono16": (np.dtype(np.uint16), 1),
    "16UC1": (np.dtype(np.uint16), 1),
    "32FC1": (np.dtype(np.float32), 1),
    "32SC1": (np.dtype(np.int32), 1),
}

UINT16_MAX = 65535


def image_to_array(msg: Any) -> np.ndarray:
    """``sensor_msgs/Image`` → array [H, W] or [H, W, C] (a copy; row padding removed).

    Raises:
        ImageFormatError: unknown encoding, or data too short for height × step.
    """
    enc = str(msg.encoding)
    if enc not in ENCODINGS:
        raise ImageFormatError(f"unsupported image encoding {enc!r}; supported: {', '.join(ENCODINGS)}")
    dtype, ch = ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * ch * dtype.itemsize
    if h <= 0 or w <= 0 or step < row:
        raise ImageFormatError(f"bad image geometry: {w}x{h}, step {step} < {row} bytes per row")
    data = bytes(msg.data) if not isinstance(msg.data, (bytes, bytearray, memoryview, np.ndarray)) else msg.data
    buf = np.frombuffer(data, dtype=np.uint8)
    if buf.size < h * step:
        raise ImageFormatError(f"image data has {buf.size} bytes, expected {h * step} ({w}x{h}, step {step})")
    rows = buf[: h * step].reshape(h, step)[:, :row]
    swapped = dtype.newbyteorder(">" if msg.is_bigendian else "<")
    arr = np.ascontiguousarray(rows).view(swapped).reshape((h, w, ch) if ch > 1 else (h, w))
    arr = arr.astype(dtype, copy=True)
    if enc.startswith("bgr"):
        arr = arr[..., [2, 1, 0] + ([3] if ch == 4 else [])]
    return arr


def array_to_image_fields(array: np.ndarray, encoding: str) -> dict[str, Any]:
    """Fields of a ``sensor_msgs/Image`` holding ``array`` (the client's streamer uses it). ``data`` is an
    ``array('B')``: a message takes one as it is, where it checks a ``bytes`` value element by element in Python
    (5 ms for a 320 x 240 colour image, 6.5 ms for its float depth: a third of a core at 30 Hz)."""
    if encoding not in ENCODINGS:
        raise ImageFormatError(f"unsupported image encoding {encoding!r}")
    dtype, ch = ENCODINGS[encoding]
    arr = np.ascontiguousarray(array, dtype=dtype)
    if (ch == 1 and arr.ndim != 2) or (ch > 1 and (arr.ndim != 3 or arr.shape[2] != ch)):
        raise ImageFormatError(f"{encoding} needs {'[H, W]' if ch == 1 else f'[H, W, {ch}]'}, got {arr.shape}")
    h, w = arr.shape[:2]
    return {"height": h, "width": w, "encoding": encoding, "is_bigendian": sys.byteorder == "big",
            "step": w * ch * dtype.itemsize, "data": byte_array("B", arr.tobytes())}


def rgb_of(array: np.ndarray) -> np.ndarray:
    """Colour image as uint8 [H, W, 3] (drops alpha, replicates mono)."""
    if array.ndim == 2:
        return np.repeat(array[:, :, None], 3, axis=2).astype(np.uint8)
    return np.ascontiguousarray(array[:, :, :3]).astype(np.uint8)


def depth_to_mm(depth: np.ndarray, scale: float = 1000.0) -> np.ndarray:
    """Depth in metres (float) → uint16 in units of ``1/scale`` m (mm by default).

    Invalid values (NaN, ±inf, ≤ 0, beyond the uint16 range) become 0 = "no depth". A uint16
    input is taken as already converted and returned as is.

    Args:
        depth: [H, W] float metres, or uint16.
        scale: units per metre of the output (1000 → millimetres).
    """
    if depth.dtype == np.uint16:
        return depth
    d = np.asarray(depth, dtype=np.float64) * scale
    bad = ~np.isfinite(d) | (d <= 0) | (d > UINT16_MAX)
    out = np.rint(np.where(bad, 0.0, d)).astype(np.uint16)
    return out


def resize_nearest(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour resize (for depth and semantic ids: never invents values)."""
    h, w = image.shape[:2]
    if (w, h) == (width, height):
        return image
    ys = np.minimum(((np.arange(height) + 0.5) * h / height).astype(np.int64), h - 1)
    xs = np.minimum(((np.arange(width) + 0.5) * w / width).astype(np.int64), w - 1)
    return image[ys][:, xs]


def resize_rgb(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Bilinear resize of a uint8 colour image [H, W, 3] (pixel-centre convention)."""
    h, w = image.shape[:2]
    if (w, h) == (width, height):
        return image
    fy = np.clip((np.arange(height) + 0.5) * h / height - 0.5, 0, h - 1)
    fx = np.clip((np.arange(width) + 0.5) * w / width - 0.5, 0, w - 1)
    y0, x0 = fy.astype(np.int64), fx.astype(np.int64)
    y1, x1 = np.minimum(y0 + 1, h - 1), np.minimum(x0 + 1, w - 1)
    wy, wx = (fy - y0)[:, None, None], (fx - x0)[None, :, None]
    img = image.astype(np.float32)
    top = img[y0][:, x0] * (1 - wx) + img[y0][:, x1] * wx
    bot = img[y1][:, x0] * (1 - wx) + img[y1][:, x1] * wx
    return np.clip(np.rint(top * (1 - wy) + bot * wy), 0, 255).astype(np.uint8)
