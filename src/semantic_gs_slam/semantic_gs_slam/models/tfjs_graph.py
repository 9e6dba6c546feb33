"""Reader of TensorFlow.js *graph models* and their conversion to ONNX, with NumPy and the ``onnx`` package only
(no TensorFlow).

A graph model is a ``model.json`` and one or more binary weight files beside it:

* ``modelTopology``: a TensorFlow GraphDef written as JSON: ``node[]``, each with ``name``, ``op``, ``input``
  (``"name"``, ``"name:1"`` for a node's second output, ``"^name"`` for a control dependency) and ``attr``;
* ``weightsManifest``: groups of ``paths`` (the weight files, read one after the other as one byte stream) and
  ``weights`` (``name``, ``shape``, ``dtype``, optional ``quantization``: ``float16``, or ``uint8``/``uint16``
  with ``scale`` and ``min``), in the order of the bytes; a ``Const`` node's value is the weight of its name;
* ``signature`` (optional): the graph's input and output tensors.

Conversion (:func:`to_onnx`): the nodes the outputs need are taken in dependency order; every node whose inputs
are all constant is evaluated in NumPy (constant folding: shape arithmetic such as ``SparseToDense`` disappears);
the others become ONNX nodes with TensorFlow's semantics kept: tensors stay in TensorFlow's layout (NHWC), and the
ops ONNX only has in NCHW (``Conv2D``, ``MaxPool``, ``ResizeBilinear``) are wrapped in a pair of ``Transpose``
(onnxruntime's optimiser removes the pairs that cancel). An op outside :data:`SUPPORTED_OPS` is refused by name
(:class:`~semantic_gs_slam.models.errors.UnsupportedOpError`).

Every op has a NumPy reference (:data:`NUMPY_OPS`, also used for folding and by :func:`run_numpy`); the tests check
each ONNX translation against it on random inputs.

Command line: ``python -m semantic_gs_slam.models.tfjs_graph MODEL.json OUT.onnx`` (prints the op counts).
"""

from __future__ import annotations

import argparse
import base64
import json
import math
import os
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from semantic_gs_slam.models.errors import ModelFormatError, UnsupportedOpError

OPSET = 17  # Resize with full 4-D sizes (onnxruntime refuses opset 18's ``axes`` form in some builds)

_DTYPES = {"DT_FLOAT": np.float32, "DT_INT32": np.int32, "DT_INT64": np.int64, "DT_BOOL": np.bool_,
           "DT_HALF": np.float16, "DT_UINT8": np.uint8, "DT_INT8": np.int8, "DT_DOUBLE": np.float64}
_MANIFEST_DTYPES = {"float32": np.float32, "int32": np.int32, "bool": np.bool_}


@dataclass
class TfjsNode:
    """One node of the graph (control dependencies dropped)."""

    name: str
    op: str
    inputs: list[str]
    attr: dict

    def a(self, key: str, default: object = None) -> object:
        """The attribute ``key`` as a Python value (bytes are decoded, lists flattened), or ``default``."""
        v = self.attr.get(key)
        if v is None:
            return default
        if "s" in v:
            return base64.b64decode(v["s"]).decode()
        if "i" in v:
            return int(v["i"])
        if "f" in v:
            return float(v["f"])
        if "b" in v:
            return bool(v["b"])
        if "type" in v:
            return v["type"]
        if "list" in v:
            lst = v["list"]
            if "i" in lst:
                return [int(x) for x in lst["i"]]
            if "f" in lst:
                return [float(x) for x in lst["f"]]
            if "s" in lst:
                return [base64.b64decode(x).decode() for x in lst["s"]]
            return []
        return v


@dataclass
class TfjsGraph:
    """A TF.js graph model read into memory.

    Attributes:
        nodes: name -> node.
        weights: name -> value of every weight in the manifest (dequantised to float32 where quantised).
        inputs: input tensor names (``Placeholder`` nodes) -> (dtype name, shape; -1 for an unknown size).
        outputs: output tensor names (``"Identity:0"``), from the signature, else the nodes nothing consumes.
        output_shapes: output tensor name -> shape from the signature (-1: unknown size), where it says.
        meta: the file's other top-level fields (``format``, ``generatedBy``, ``convertedBy``).
    """

    nodes: dict[str, TfjsNode]
    weights: dict[str, np.ndarray]
    inputs: dict[str, tuple[str, list[int]]]
    outputs: list[str]
    output_shapes: dict[str, list[int]] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)


def _natural(s: str) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", s)]


def _tensor_ref(ref: str) -> tuple[str, int]:
    """``"a/b:1"`` -> ("a/b", 1); ``"a/b"`` -> ("a/b", 0)."""
    m = re.fullmatch(r"(.+):(\d+)", ref)
    return (m.group(1), int(m.group(2))) if m else (ref, 0)


def read_weights(manifest: list, folder: str) -> dict[str, np.ndarray]:
    """Values of the weights of a ``weightsManifest`` whose files lie in ``folder``.

    Raises:
        ModelFormatError: a missing or short weight file, an unknown dtype or quantisation.
    """
    out: dict[str, np.ndarray] = {}
    for g, group in enumerate(manifest):
        try:
            blob = b"".join(open(os.path.join(folder, p), "rb").read() for p in group["paths"])
            specs = group["weights"]
        except (OSError, KeyError, TypeError) as exc:
            raise ModelFormatError(f"weightsManifest[{g}]: cannot read its weight files ({exc})") from exc
        pos = 0
        for w in specs:
            name, shape, dtype = w.get("name"), [int(s) for s in w.get("shape", [])], w.get("dtype")
            n = math.prod(shape)
            q = w.get("quantization")
            if q is not None:
                qd = q.get("dtype")
                if qd == "float16":
                    nbytes, raw = 2 * n, np.float16
                elif qd in ("uint8", "uint16"):
                    raw = np.uint8 if qd == "uint8" else np.uint16
                    nbytes = n * np.dtype(raw).itemsize
                else:
                    raise ModelFormatError(f"weight {name}: unknown quantization dtype {qd!r}")
            else:
                if dtype not in _MANIFEST_DTYPES:
                    raise ModelFormatError(f"weight {name}: unsupported dtype {dtype!r}")
                raw = _MANIFEST_DTYPES[dtype]
                nbytes = n * np.dtype(raw).itemsize
            if pos + nbytes > len(blob):
                raise ModelFormatError(f"weight {name}: the weight files end before it ({len(blob)} bytes, "
                                       f"need {pos + nbytes})")
            a = np.frombuffer(blob, raw, n, pos).reshape(shape)
            pos += nbytes
            if q is not None and q.get("dtype") in ("uint8", "uint16"):
                a = a.astype(np.float32) * np.float32(q["scale"]) + np.float32(q["min"])
            out[name] = a.astype(_MANIFEST_DTYPES.get(dtype, np.float32), copy=True)
        if pos != len(blob):
            raise ModelFormatError(f"weightsManifest[{g}]: {len(blob) - pos} bytes left over after its weights")
    return out


def _shape_of(sh: dict) -> list[int]:
    return [int(d.get("size", -1)) for d in sh.get("dim", [])]


def read_graph(model_json: str) -> TfjsGraph:
    """Read a TF.js graph model (``model.json`` and the weight files it names, in the same folder).

    Raises:
        ModelFormatError: a missing file, not a graph model, bad JSON, a node without a name or op.
    """
    try:
        with open(model_json, encoding="utf-8") as fh:
            doc = json.load(fh)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ModelFormatError(f"{model_json}: not a readable TF.js model.json ({exc})") from exc
    if not isinstance(doc, dict) or "modelTopology" not in doc or "weightsManifest" not in doc:
        raise ModelFormatError(f"{model_json}: not a TF.js model (no modelTopology / weightsManifest)")
    if doc.get("format", "graph-model") != "graph-model" or "node" not in doc["modelTopology"]:
        raise ModelFormatError(f"{model_json}: a TF.js {doc.get('format', 'layers')} model; only graph models "
                               "(a GraphDef with node[]) can be read")
    nodes: dict[str, TfjsNode] = {}
    for i, nd in enumerate(doc["modelTopology"]["node"]):
        if not isinstance(nd, dict) or "name" not in nd or "op" not in nd:
            raise ModelFormatError(f"{model_json}: node[{i}] has no name or op")
        ins = [s for s in nd.get("input", []) if not s.startswith("^")]
        nodes[nd["name"]] = TfjsNode(nd["name"], nd["op"], ins, nd.get("attr", {}))
    weights = read_weights(doc["weightsManifest"], os.path.dirname(os.path.abspath(model_json)))
    inputs = {}
    for nd in nodes.values():
        if nd.op == "Placeholder":
            sh = nd.attr.get("shape", {}).get("shape", {})
            inputs[nd.name] = (str(nd.a("dtype", "DT_FLOAT")), _shape_of(sh))
    sig = doc.get("signature") or {}
    outputs = sorted(sig.get("outputs", {}), key=_natural)
    out_shapes = {k: _shape_of(v.get("tensorShape", {})) for k, v in sig.get("outputs", {}).items()
                  if isinstance(v, dict) and "tensorShape" in v}
    if not outputs:
        used = {_tensor_ref(s)[0] for nd in nodes.values() for s in nd.inputs}
        outputs = sorted((n for n, nd in nodes.items() if n not in used and nd.op not in ("Const", "Placeholder")),
                         key=_natural)
    meta = {k: v for k, v in doc.items() if k not in ("modelTopology", "weightsManifest", "signature")}
    return TfjsGraph(nodes, weights, inputs, outputs, out_shapes, meta)


# --- NumPy references ---------------------------------------------------------------------------------------------

def _pads_same(size: int, k: int, s: int, d: int) -> tuple[int, int]:
    """TensorFlow's SAME padding of one axis (the extra pixel at the end)."""
    out = -(-size // s)
    total = max((out - 1) * s + (k - 1) * d + 1 - size, 0)
    return total // 2, total - total // 2


def _spatial(node: TfjsNode) -> tuple[bool, list[int], list[int]]:
    """(NCHW?, strides [sh, sw], dilations [dh, dw]) of a Conv2D / pool node."""
    nchw = node.a("data_format", "NHWC") == "NCHW"
    sl = slice(2, 4) if nchw else slice(1, 3)
    strides = (node.a("strides") or [1, 1, 1, 1])[sl]
    dil = (node.a("dilations") or [1, 1, 1, 1])[sl]
    return nchw, list(strides), list(dil)


def _explicit_hw(node: TfjsNode, nchw: bool) -> list[tuple[int, int]]:
    p = node.a("explicit_paddings") or []
    if len(p) != 8:
        raise ModelFormatError(f"{node.name}: EXPLICIT padding needs 8 explicit_paddings, got {p}")
    pairs = [(p[2 * i], p[2 * i + 1]) for i in range(4)]
    return pairs[2:4] if nchw else pairs[1:3]


def _window_pads(node: TfjsNode, hw: tuple[int, int], k: list[int], s: list[int], d: list[int],
                 nchw: bool) -> list[tuple[int, int]]:
    pad = node.a("padding", "VALID")
    if pad == "VALID":
        return [(0, 0), (0, 0)]
    if pad == "SAME":
        return [_pads_same(hw[i], k[i], s[i], d[i]) for i in range(2)]
    if pad == "EXPLICIT":
        return _explicit_hw(node, nchw)
    raise ModelFormatError(f"{node.name}: unknown padding {pad!r}")


def np_conv2d(node: TfjsNode, x: np.ndarray, w: np.ndarray) -> list[np.ndarray]:
    """Conv2D: x [N, H, W, C] (or NCHW), w [kh, kw, C, O]."""
    nchw, s, d = _spatial(node)
    if nchw:
        x = x.transpose(0, 2, 3, 1)
    kh, kw, c, o = w.shape
    if x.shape[3] != c:
        raise ModelFormatError(f"{node.name}: input has {x.shape[3]} channels, filter expects {c}")
    pads = _window_pads(node, x.shape[1:3], [kh, kw], s, d, nchw)
    xp = np.pad(x, [(0, 0), pads[0], pads[1], (0, 0)])
    oh = (xp.shape[1] - (kh - 1) * d[0] - 1) // s[0] + 1
    ow = (xp.shape[2] - (kw - 1) * d[1] - 1) // s[1] + 1
    y = np.zeros((x.shape[0], oh, ow, o), np.float64)
    for i in range(kh):
        for j in range(kw):
            patch = xp[:, i * d[0]:i * d[0] + s[0] * (oh - 1) + 1:s[0], j * d[1]:j * d[1] + s[1] * (ow - 1) + 1:s[1]]
            y += np.einsum("nhwc,co->nhwo", patch.astype(np.float64), w[i, j].astype(np.float64))
    y = y.astype(x.dtype)
    return [y.transpose(0, 3, 1, 2) if nchw else y]


def np_maxpool(node: TfjsNode, x: np.ndarray) -> list[np.ndarray]:
    """MaxPool: x [N, H, W, C] (or NCHW); padded places never win."""
    nchw, s, _ = _spatial(node)
    sl = slice(2, 4) if nchw else slice(1, 3)
    k = node.a("ksize")[sl]
    if nchw:
        x = x.transpose(0, 2, 3, 1)
    pads = _window_pads(node, x.shape[1:3], k, s, [1, 1], nchw)
    xp = np.pad(x, [(0, 0), pads[0], pads[1], (0, 0)], constant_values=-np.inf)
    oh = (xp.shape[1] - k[0]) // s[0] + 1
    ow = (xp.shape[2] - k[1]) // s[1] + 1
    y = np.full((x.shape[0], oh, ow, x.shape[3]), -np.inf, x.dtype)
    for i in range(k[0]):
        for j in range(k[1]):
            y = np.maximum(y, xp[:, i:i + s[0] * (oh - 1) + 1:s[0], j:j + s[1] * (ow - 1) + 1:s[1]])
    return [y.transpose(0, 3, 1, 2) if nchw else y]


def _resize_axis(n_in: int, n_out: int, align: bool, half: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """TensorFlow's bilinear sampling of one axis: (lower index, upper index, weight of upper) per output."""
    scale = (n_in - 1) / (n_out - 1) if align and n_out > 1 else n_in / n_out
    o = np.arange(n_out, dtype=np.float64)
    src = (o + 0.5) * scale - 0.5 if half else o * scale
    lo = np.floor(src)
    frac = src - lo
    lo_i = np.clip(lo, 0, n_in - 1).astype(np.int64)
    hi_i = np.clip(lo + 1, 0, n_in - 1).astype(np.int64)
    frac = np.where(src < 0, 0.0, frac)
    return lo_i, hi_i, frac


def np_resize_bilinear(node: TfjsNode, x: np.ndarray, size: np.ndarray) -> list[np.ndarray]:
    """ResizeBilinear: x [N, H, W, C] -> [N, size[0], size[1], C]."""
    align, half = bool(node.a("align_corners", False)), bool(node.a("half_pixel_centers", False))
    oh, ow = (int(v) for v in np.asarray(size).reshape(-1))
    y0, y1, fy = _resize_axis(x.shape[1], oh, align, half)
    x0, x1, fx = _resize_axis(x.shape[2], ow, align, half)
    xf = x.astype(np.float64)
    top = xf[:, y0] * (1 - fy)[None, :, None, None] + xf[:, y1] * fy[None, :, None, None]
    out = top[:, :, x0] * (1 - fx)[None, None, :, None] + top[:, :, x1] * fx[None, None, :, None]
    return [out.astype(x.dtype)]


def _axis(a: np.ndarray) -> int:
    return int(np.asarray(a).reshape(-1)[0])


def np_splitv(node: TfjsNode, x: np.ndarray, sizes: np.ndarray, axis: np.ndarray) -> list[np.ndarray]:
    """SplitV: pieces of the given sizes along ``axis`` (one size may be -1: the rest)."""
    ax = _axis(axis)
    sz = [int(v) for v in np.asarray(sizes).reshape(-1)]
    if sz.count(-1) > 1:
        raise ModelFormatError(f"{node.name}: SplitV with more than one -1 size {sz}")
    if -1 in sz:
        sz[sz.index(-1)] = x.shape[ax] - (sum(sz) + 1)
    return list(np.split(x, np.cumsum(sz)[:-1], axis=ax))


def np_split(node: TfjsNode, axis: np.ndarray, x: np.ndarray) -> list[np.ndarray]:
    """Split: ``num_split`` equal pieces along ``axis``."""
    return list(np.split(x, int(node.a("num_split")), axis=_axis(axis)))


def np_sparse_to_dense(node: TfjsNode, idx: np.ndarray, shape: np.ndarray, values: np.ndarray,
                       default: np.ndarray) -> list[np.ndarray]:
    """SparseToDense: ``default`` everywhere except at ``idx`` ([K] or [K, D]), which get ``values``."""
    shape = [int(v) for v in np.asarray(shape).reshape(-1)]
    out = np.full(shape, np.asarray(default).reshape(()), dtype=np.asarray(values).dtype)
    idx = np.asarray(idx).astype(np.int64)
    if idx.size:
        idx = idx.reshape(idx.shape[0], -1) if idx.ndim > 1 else idx[:, None]
        out[tuple(idx.T)] = values
    return [out]


def _pads_array(p: np.ndarray) -> np.ndarray:
    return np.asarray(p, np.int64).reshape(-1, 2)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return (1.0 / (1.0 + np.exp(-x.astype(np.float64)))).astype(x.dtype)


def _softmax(x: np.ndarray) -> np.ndarray:
    e = np.exp(x.astype(np.float64) - x.max(-1, keepdims=True))
    return (e / e.sum(-1, keepdims=True)).astype(x.dtype)


def _bias_add(n: TfjsNode, x: np.ndarray, b: np.ndarray) -> list[np.ndarray]:
    if n.a("data_format", "NHWC") == "NCHW":
        return [x + b.reshape((1, -1) + (1,) * (x.ndim - 2))]
    return [x + b]


#: op -> NumPy reference (node, *inputs) -> outputs
NUMPY_OPS: dict[str, Callable[..., list[np.ndarray]]] = {
    "Identity": lambda n, x: [x],
    "Add": lambda n, a, b: [a + b],
    "AddV2": lambda n, a, b: [a + b],
    "BiasAdd": _bias_add,
    "Sub": lambda n, a, b: [a - b],
    "Mul": lambda n, a, b: [a * b],
    "RealDiv": lambda n, a, b: [a / b],
    "Maximum": lambda n, a, b: [np.maximum(a, b)],
    "Minimum": lambda n, a, b: [np.minimum(a, b)],
    "Relu": lambda n, x: [np.maximum(x, 0)],
    "Relu6": lambda n, x: [np.clip(x, 0, 6)],
    "LeakyRelu": lambda n, x: [np.where(x >= 0, x, x * np.asarray(n.a("alpha", 0.2), x.dtype))],
    "Sigmoid": lambda n, x: [_sigmoid(x)],
    "Tanh": lambda n, x: [np.tanh(x)],
    "Softmax": lambda n, x: [_softmax(x)],
    "Transpose": lambda n, x, perm: [np.transpose(x, [int(p) for p in np.asarray(perm).reshape(-1)])],
    "Reshape": lambda n, x, shape: [x.reshape([int(s) for s in np.asarray(shape).reshape(-1)])],
    "Pad": lambda n, x, p: [np.pad(x, _pads_array(p))],
    "PadV2": lambda n, x, p, c: [np.pad(x, _pads_array(p), constant_values=np.asarray(c).reshape(()))],
    "ConcatV2": lambda n, *xs: [np.concatenate(xs[:-1], axis=_axis(xs[-1]))],
    "SplitV": np_splitv,
    "Split": np_split,
    "Conv2D": np_conv2d,
    "MaxPool": np_maxpool,
    "ResizeBilinear": np_resize_bilinear,
    "SparseToDense": np_sparse_to_dense,
    "Cast": lambda n, x: [x.astype(_DTYPES.get(str(n.a("DstT")), np.float32))],
}

#: ops that only occur on constant inputs (shape arithmetic); folded in NumPy, refused when an input is not constant
CONSTANT_ONLY = frozenset({"SparseToDense", "Cast"})
#: input positions that must be constant for the ONNX translation (perm, shape, paddings, axis, sizes)
_CONST_INPUTS: dict[str, tuple[int, ...]] = {
    "Transpose": (1,), "Reshape": (1,), "Pad": (1,), "PadV2": (1, 2), "SplitV": (1, 2), "Split": (0,),
    "ResizeBilinear": (1,), "Conv2D": (1,)}
#: every op :func:`to_onnx` accepts
SUPPORTED_OPS = frozenset(NUMPY_OPS) | {"Const", "Placeholder"}


# --- conversion ---------------------------------------------------------------------------------------------------

class _Builder:
    """ONNX nodes and initializers of the graph being written."""

    def __init__(self) -> None:
        from onnx import helper, numpy_helper

        self.h, self.nh = helper, numpy_helper
        self.nodes: list = []
        self.inits: list = []
        self._n = 0

    def const(self, value: np.ndarray, hint: str) -> str:
        self._n += 1
        name = f"{hint}__c{self._n}"
        self.inits.append(self.nh.from_array(np.ascontiguousarray(value), name))
        return name

    def node(self, op: str, inputs: list[str], outputs: list[str] | None = None, hint: str = "", **attrs) -> list[str]:
        self._n += 1
        outputs = outputs or [f"{hint or op}__t{self._n}"]
        self.nodes.append(self.h.make_node(op, inputs, outputs, name=f"{hint or op}__n{self._n}", **attrs))
        return outputs


def _onnx_window(b: _Builder, n: TfjsNode, x: str, out: str, op: str, w: np.ndarray | None) -> None:
    nchw, s, d = _spatial(n)
    inp = x if nchw else b.node("Transpose", [x], hint=n.name + "/to_nchw", perm=[0, 3, 1, 2])[0]
    attrs: dict = {"strides": s}
    pad = n.a("padding", "VALID")
    if pad == "SAME" and max(d) > 1:  # onnxruntime has no auto_pad with dilation: stride 1 pads (k - 1) d in all
        if max(s) > 1:
            raise ModelFormatError(f"{n.name}: SAME padding with both dilation {d} and stride {s} is not supported")
        k = [(w.shape[0] - 1) * d[0], (w.shape[1] - 1) * d[1]]
        attrs["pads"] = [k[0] // 2, k[1] // 2, k[0] - k[0] // 2, k[1] - k[1] // 2]
    elif pad == "SAME":
        attrs["auto_pad"] = "SAME_UPPER"  # TensorFlow's SAME: the extra pixel at the end
    elif pad == "EXPLICIT":
        (t, bo), (le, r) = _explicit_hw(n, nchw)
        attrs["pads"] = [t, le, bo, r]
    elif pad != "VALID":
        raise ModelFormatError(f"{n.name}: unknown padding {pad!r}")
    args = [inp]
    if op == "Conv":
        attrs["dilations"] = d
        args.append(b.const(np.transpose(w, (3, 2, 0, 1)).astype(np.float32), n.name + "/w"))  # HWIO -> OIHW
    else:
        sl = slice(2, 4) if nchw else slice(1, 3)
        attrs["kernel_shape"] = n.a("ksize")[sl]
    if nchw:
        b.node(op, args, [out], hint=n.name, **attrs)
    else:
        y = b.node(op, args, hint=n.name, **attrs)[0]
        b.node("Transpose", [y], [out], hint=n.name + "/to_nhwc", perm=[0, 2, 3, 1])


def _emit(b: _Builder, n: TfjsNode, ins: list[str], consts: list[np.ndarray | None], outs: list[str]) -> None:
    """Write the ONNX nodes of one TF node (inputs ``ins``: tensor names; ``consts``: their values where constant,
    already written as initializers)."""
    op, o = n.op, outs[0]
    simple = {"Identity": "Identity", "Add": "Add", "AddV2": "Add", "Sub": "Sub", "Mul": "Mul", "RealDiv": "Div",
              "Maximum": "Max", "Minimum": "Min", "Relu": "Relu", "Sigmoid": "Sigmoid", "Tanh": "Tanh"}
    if op in simple:
        b.node(simple[op], ins, [o], hint=n.name)
    elif op == "BiasAdd":
        bias = ins[1]
        if n.a("data_format", "NHWC") == "NCHW":
            bias = b.node("Unsqueeze", [bias, b.const(np.array([1, 2], np.int64), n.name + "/ax")], hint=n.name)[0]
        b.node("Add", [ins[0], bias], [o], hint=n.name)
    elif op == "Relu6":
        b.node("Clip", [ins[0], b.const(np.array(0, np.float32), n.name + "/lo"),
                        b.const(np.array(6, np.float32), n.name + "/hi")], [o], hint=n.name)
    elif op == "LeakyRelu":
        b.node("LeakyRelu", ins, [o], hint=n.name, alpha=float(n.a("alpha", 0.2)))
    elif op == "Softmax":
        b.node("Softmax", ins, [o], hint=n.name, axis=-1)
    elif op == "Transpose":
        b.node("Transpose", ins[:1], [o], hint=n.name, perm=[int(p) for p in consts[1].reshape(-1)])
    elif op == "Reshape":
        shape = consts[1].astype(np.int64).reshape(-1)
        b.node("Reshape", [ins[0], b.const(shape, n.name + "/shape")], [o], hint=n.name,
               allowzero=int(bool((shape == 0).any())))
    elif op in ("Pad", "PadV2"):
        p = _pads_array(consts[1])
        args = [ins[0], b.const(np.concatenate([p[:, 0], p[:, 1]]), n.name + "/pads")]
        if op == "PadV2":
            args.append(b.const(np.asarray(consts[2]).reshape(()).astype(np.float32), n.name + "/value"))
        b.node("Pad", args, [o], hint=n.name, mode="constant")
    elif op == "ConcatV2":
        if consts[-1] is None:
            raise ModelFormatError(f"{n.name}: ConcatV2 needs a constant axis")
        b.node("Concat", ins[:-1], [o], hint=n.name, axis=_axis(consts[-1]))
    elif op == "SplitV":
        ax = _axis(consts[2])
        sz = [int(v) for v in consts[1].reshape(-1)]
        if sz.count(-1) > 1:
            raise ModelFormatError(f"{n.name}: SplitV with more than one -1 size {sz}")
        k = sz.index(-1) if -1 in sz else len(sz)
        big = np.iinfo(np.int64).max
        for i, out in enumerate(outs):  # slices from the start before the -1 piece, from the end after it
            if i < k:
                start, end = sum(sz[:i]), sum(sz[:i + 1])
            elif i == k:
                start, end = sum(sz[:i]), (-sum(sz[i + 1:]) if i + 1 < len(sz) else big)
            else:
                start, end = -sum(sz[i:]), (-sum(sz[i + 1:]) if i + 1 < len(sz) else big)
            b.node("Slice", [ins[0], b.const(np.array([start], np.int64), n.name + "/s"),
                             b.const(np.array([end], np.int64), n.name + "/e"),
                             b.const(np.array([ax], np.int64), n.name + "/a")], [out], hint=n.name)
    elif op == "Split":
        b.node("Split", [ins[1]], outs, hint=n.name, axis=_axis(consts[0]))
    elif op == "Conv2D":
        _onnx_window(b, n, ins[0], o, "Conv", consts[1])
    elif op == "MaxPool":
        _onnx_window(b, n, ins[0], o, "MaxPool", None)
    elif op == "ResizeBilinear":
        align, half = bool(n.a("align_corners", False)), bool(n.a("half_pixel_centers", False))
        mode = "align_corners" if align else ("half_pixel" if half else "asymmetric")
        x = b.node("Transpose", [ins[0]], hint=n.name + "/to_nchw", perm=[0, 3, 1, 2])[0]
        nc = b.node("Slice", [b.node("Shape", [x], hint=n.name)[0], b.const(np.array([0], np.int64), n.name + "/s"),
                              b.const(np.array([2], np.int64), n.name + "/e")], hint=n.name)[0]
        sizes = b.node("Concat", [nc, b.const(consts[1].astype(np.int64).reshape(-1), n.name + "/hw")],
                       hint=n.name, axis=0)[0]
        y = b.node("Resize", [x, "", "", sizes], hint=n.name, mode="linear", coordinate_transformation_mode=mode)[0]
        b.node("Transpose", [y], [o], hint=n.name + "/to_nhwc", perm=[0, 2, 3, 1])
    else:
        raise UnsupportedOpError([op], n.name)


def _n_outputs(n: TfjsNode, consts: list[np.ndarray | None]) -> int:
    if n.op == "SplitV":
        return int(n.a("num_split", consts[1].size if consts[1] is not None else 1))
    if n.op == "Split":
        return int(n.a("num_split"))
    return 1


def _order(graph: TfjsGraph, targets: list[str]) -> list[str]:
    """Names of the nodes ``targets`` (tensor names) need, each after its inputs.

    Raises:
        ModelFormatError: an input naming no node; a cycle.
    """
    order: list[str] = []
    state: dict[str, int] = {}  # 1: being visited, 2: done
    for t in targets:
        stack = [(_tensor_ref(t)[0], False)]
        while stack:
            name, expanded = stack.pop()
            if name not in graph.nodes:
                raise ModelFormatError(f"the graph names a tensor of an unknown node {name!r}")
            if expanded:
                state[name] = 2
                order.append(name)
                continue
            if state.get(name) == 2:
                continue
            if state.get(name) == 1:
                raise ModelFormatError(f"the graph has a cycle through {name!r}")
            state[name] = 1
            stack.append((name, True))
            for ref in reversed(graph.nodes[name].inputs):
                dep = _tensor_ref(ref)[0]
                if state.get(dep) != 2:
                    if state.get(dep) == 1:
                        raise ModelFormatError(f"the graph has a cycle through {dep!r}")
                    stack.append((dep, False))
    return order


def _const_value(graph: TfjsGraph, n: TfjsNode) -> np.ndarray:
    t = n.attr.get("value", {}).get("tensor", {})
    dt = _DTYPES.get(t.get("dtype") or str(n.a("dtype", "DT_FLOAT")))
    if dt is None:
        raise ModelFormatError(f"{n.name}: constant of unsupported dtype {t.get('dtype')}")
    shape = _shape_of(t.get("tensorShape", {}))
    if n.name in graph.weights:
        v = graph.weights[n.name]
    elif math.prod(max(s, 0) for s in shape) == 0:
        v = np.zeros([max(s, 0) for s in shape])
    else:
        raise ModelFormatError(f"{n.name}: constant without a weight in the manifest")
    return np.asarray(v).astype(dt)  # int64 constants are stored as int32


def unsupported_ops(graph: TfjsGraph) -> list[str]:
    """Ops of the nodes the outputs need that :func:`to_onnx` does not support (sorted, each once)."""
    return sorted({graph.nodes[n].op for n in _order(graph, graph.outputs)} - SUPPORTED_OPS)


def _walk(graph: TfjsGraph, feeds: dict[str, np.ndarray] | None, b: _Builder | None) -> dict[str, np.ndarray | str]:
    """Evaluate (``feeds`` given: NumPy) or convert (``b`` given) the graph; returns tensor name -> value / name."""
    bad = unsupported_ops(graph)
    if bad:
        raise UnsupportedOpError(bad)
    vals: dict[str, np.ndarray] = {}  # constant (or, with feeds, every) tensor -> value
    names: dict[str, str] = {}  # tensor computed in ONNX -> ONNX name
    for name in _order(graph, graph.outputs):
        n = graph.nodes[name]
        if n.op == "Const":
            vals[name] = _const_value(graph, n)
            continue
        if n.op == "Placeholder":
            if feeds is not None:
                if name not in feeds:
                    raise ModelFormatError(f"no value fed for input {name!r}")
                vals[name] = np.asarray(feeds[name])
            else:
                names[name] = name
            continue
        refs = [r if ":" in r else r + ":0" for r in n.inputs]
        refs = [f"{_tensor_ref(r)[0]}" if _tensor_ref(r)[1] == 0 else r for r in refs]
        consts = [vals.get(r) for r in refs]
        if all(c is not None for c in consts):
            outs = NUMPY_OPS[n.op](n, *consts)
            for k, v in enumerate(outs):
                vals[name if k == 0 else f"{name}:{k}"] = np.asarray(v)
            continue
        if n.op in CONSTANT_ONLY:
            raise UnsupportedOpError([n.op], f"{name} (on a non-constant input)")
        need = _CONST_INPUTS.get(n.op, ())
        if n.op == "ConcatV2":
            need = (len(refs) - 1,)
        if any(consts[i] is None for i in need if i < len(consts)):
            raise ModelFormatError(f"{name}: {n.op} needs constant inputs at positions {list(need)}")
        assert b is not None  # with feeds every tensor is constant
        ins = []
        for i, (r, c) in enumerate(zip(refs, consts, strict=True)):
            if i in need:  # read as an attribute (perm, shape, axis, filter): no initializer of its own
                ins.append("")
                continue
            if c is not None and r not in names:
                names[r] = b.const(c.astype(np.float32) if c.dtype == np.float64 else c, r)
            ins.append(names[r])
        k = _n_outputs(n, consts)
        outs = [name if i == 0 else f"{name}:{i}" for i in range(k)]
        for t in outs:
            names[t] = t
        _emit(b, n, ins, consts, outs)
    return {**vals, **names}


def run_numpy(graph: TfjsGraph, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The graph's outputs computed with the NumPy references (slow; the reference the ONNX file is checked against).

    Args:
        feeds: input node name (``"input_1"``) -> value.

    Returns:
        output tensor name (as in :attr:`TfjsGraph.outputs`) -> value.
    """
    vals = _walk(graph, feeds, None)
    return {o: vals[_tensor_ref(o)[0] if _tensor_ref(o)[1] == 0 else o] for o in graph.outputs}


def output_name(tensor: str) -> str:
    """The ONNX output name of a TF tensor name: ``"Identity:0"`` -> ``"Identity"``, ``"a:1"`` stays."""
    base, k = _tensor_ref(tensor)
    return base if k == 0 else tensor


def to_onnx(graph: TfjsGraph, doc_string: str = "", metadata: dict[str, str] | None = None):
    """The graph as an ONNX model (``onnx.ModelProto``; opset :data:`OPSET`), constants folded.

    Inputs keep their node names (``input_1``), outputs their tensor names without ``:0``.

    Raises:
        UnsupportedOpError: ops outside :data:`SUPPORTED_OPS` (all named at once).
        ModelFormatError: a graph that cannot be converted (e.g. a non-constant shape).
    """
    import onnx
    from onnx import TensorProto, helper

    b = _Builder()
    names = _walk(graph, None, b)
    elem = {"DT_FLOAT": TensorProto.FLOAT, "DT_INT32": TensorProto.INT32, "DT_INT64": TensorProto.INT64}
    inputs = [helper.make_tensor_value_info(n, elem.get(dt, TensorProto.FLOAT), [s if s >= 0 else None for s in sh])
              for n, (dt, sh) in graph.inputs.items()]
    outputs = []
    for t in graph.outputs:
        src = names[_tensor_ref(t)[0] if _tensor_ref(t)[1] == 0 else t]
        out = output_name(t)
        if not isinstance(src, str):  # a constant output
            b.node("Identity", [b.const(np.asarray(src), out)], [out], hint=out)
        shape = graph.output_shapes.get(t)
        outputs.append(helper.make_tensor_value_info(out, TensorProto.FLOAT, None) if shape is None else
                       helper.make_tensor_value_info(out, TensorProto.FLOAT, [s if s >= 0 else None for s in shape]))
    g = helper.make_graph(b.nodes, "tfjs_graph", inputs, outputs, b.inits)
    model = helper.make_model(g, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="semantic_gs_slam.tfjs",
                              doc_string=doc_string)
    model.ir_version = 8
    for k, v in (metadata or {}).items():
        model.metadata_props.add(key=k, value=str(v))
    if all(t in graph.output_shapes for t in graph.outputs):
        onnx.checker.check_model(model)  # (the checker wants every output's shape)
    return model


def main(argv: list[str] | None = None) -> int:
    """Command line: convert a TF.js graph model to ONNX."""
    ap = argparse.ArgumentParser(description="Convert a TensorFlow.js graph model to ONNX (no TensorFlow needed).")
    ap.add_argument("model_json", help="the model.json (its weight files beside it)")
    ap.add_argument("out", help="the .onnx file to write")
    args = ap.parse_args(argv)
    try:
        g = read_graph(args.model_json)
        model = to_onnx(g, doc_string=f"converted from {os.path.basename(args.model_json)}")
    except ModelFormatError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    import onnx

    onnx.save(model, args.out)
    ops: dict[str, int] = {}
    for nd in model.graph.node:
        ops[nd.op_type] = ops.get(nd.op_type, 0) + 1
    print(f"{args.out}: {len(model.graph.node)} ONNX nodes ({', '.join(f'{k} {v}' for k, v in sorted(ops.items()))}); "
          f"inputs {list(g.inputs)}, outputs {[output_name(o) for o in g.outputs]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
