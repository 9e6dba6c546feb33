"""The TF.js graph reader and its ONNX conversion: every supported op is converted on its own and run with
onnxruntime on random inputs against the NumPy reference; the references are checked against hand-computed values;
unsupported ops are refused by name."""

from __future__ import annotations

import base64
import json

import numpy as np
import pytest

from semantic_gs_slam.models import tfjs_graph as tg
from semantic_gs_slam.models.errors import ModelFormatError, UnsupportedOpError

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

_DT = {np.float32: ("DT_FLOAT", "float32"), np.int32: ("DT_INT32", "int32"), np.int64: ("DT_INT64", "int32")}


def _s(text: str) -> dict:
    return {"s": base64.b64encode(text.encode()).decode()}


def _ints(v: list[int]) -> dict:
    return {"list": {"i": [str(x) for x in v]}}


def write_model(folder, nodes: list[dict], consts: dict[str, np.ndarray], inputs: dict[str, list[int]],
                outputs: list[str], quantize: dict[str, str] | None = None) -> str:
    """A TF.js graph model in ``folder``: ``nodes`` (op nodes), constants (Const nodes + weights), float inputs."""
    quantize = quantize or {}
    topo = [{"name": n, "op": "Placeholder", "attr": {"dtype": {"type": "DT_FLOAT"},
                                                      "shape": {"shape": {"dim": [{"size": str(s)} for s in sh]}}}}
            for n, sh in inputs.items()]
    blob, specs = b"", []
    for name, v in consts.items():
        v = np.asarray(v)
        tf_dt, man_dt = _DT[v.dtype.type]
        topo.append({"name": name, "op": "Const", "attr": {"dtype": {"type": tf_dt}, "value": {"tensor": {
            "dtype": tf_dt, "tensorShape": {"dim": [{"size": str(s)} for s in v.shape]}}}}})
        spec = {"name": name, "shape": list(v.shape), "dtype": man_dt}
        q = quantize.get(name)
        if q == "float16":
            blob += v.astype(np.float16).tobytes()
            spec["quantization"] = {"dtype": "float16", "original_dtype": "float32"}
        elif q == "uint8":
            lo, hi = float(v.min()), float(v.max())
            scale = (hi - lo) / 255 or 1.0
            blob += np.round((v - lo) / scale).astype(np.uint8).tobytes()
            spec["quantization"] = {"dtype": "uint8", "scale": scale, "min": lo}
        else:
            blob += v.astype(np.int32 if man_dt == "int32" else np.float32).tobytes()
        specs.append(spec)
    doc = {"format": "graph-model", "modelTopology": {"node": topo + nodes},
           "weightsManifest": [{"paths": ["w.bin"], "weights": specs}],
           "signature": {"outputs": {o: {"name": o} for o in outputs}}}
    (folder / "w.bin").write_bytes(blob)
    path = folder / "model.json"
    path.write_text(json.dumps(doc))
    return str(path)


def _run_both(path: str, feeds: dict[str, np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    g = tg.read_graph(path)
    ref = tg.run_numpy(g, feeds)
    sess = ort.InferenceSession(tg.to_onnx(g).SerializeToString(), providers=["CPUExecutionProvider"])
    got = sess.run([tg.output_name(o) for o in g.outputs], feeds)
    return [ref[o] for o in g.outputs], got


rng = np.random.default_rng(0)
X = rng.normal(size=(1, 9, 11, 4)).astype(np.float32)  # NHWC
W = rng.normal(size=(3, 3, 4, 5)).astype(np.float32)  # HWIO


def _op(name: str, op: str, inputs: list[str], **attr) -> dict:
    return {"name": name, "op": op, "input": inputs, "attr": {"T": {"type": "DT_FLOAT"}, **attr}}


CASES = {  # name -> (op nodes, constants, outputs)
    "Identity": ([_op("y", "Identity", ["x"])], {}, ["y:0"]),
    "Add": ([_op("y", "Add", ["x", "b"])], {"b": rng.normal(size=(4,)).astype(np.float32)}, ["y:0"]),
    "AddV2": ([_op("y", "AddV2", ["x", "x"])], {}, ["y:0"]),
    "BiasAdd": ([_op("y", "BiasAdd", ["x", "b"])], {"b": rng.normal(size=(4,)).astype(np.float32)}, ["y:0"]),
    "Sub": ([_op("y", "Sub", ["x", "b"])], {"b": rng.normal(size=(11, 1)).astype(np.float32)}, ["y:0"]),
    "Mul": ([_op("y", "Mul", ["x", "b"])], {"b": rng.normal(size=(4,)).astype(np.float32)}, ["y:0"]),
    "RealDiv": ([_op("y", "RealDiv", ["x", "b"])], {"b": rng.uniform(1, 2, size=(4,)).astype(np.float32)}, ["y:0"]),
    "Maximum": ([_op("y", "Maximum", ["x", "b"])], {"b": np.zeros(4, np.float32)}, ["y:0"]),
    "Minimum": ([_op("y", "Minimum", ["x", "b"])], {"b": np.zeros(4, np.float32)}, ["y:0"]),
    "Relu": ([_op("y", "Relu", ["x"])], {}, ["y:0"]),
    "Relu6": ([_op("y", "Relu6", ["s"]), _op("s", "Mul", ["x", "k"])], {"k": np.float32([5.0])}, ["y:0"]),
    "LeakyRelu": ([_op("y", "LeakyRelu", ["x"], alpha={"f": 0.1})], {}, ["y:0"]),
    "Sigmoid": ([_op("y", "Sigmoid", ["x"])], {}, ["y:0"]),
    "Tanh": ([_op("y", "Tanh", ["x"])], {}, ["y:0"]),
    "Softmax": ([_op("y", "Softmax", ["x"])], {}, ["y:0"]),
    "Transpose": ([_op("y", "Transpose", ["x", "p"])], {"p": np.int32([0, 3, 1, 2])}, ["y:0"]),
    "Reshape": ([_op("y", "Reshape", ["x", "s"])], {"s": np.int64([1, -1, 4])}, ["y:0"]),
    "Pad": ([_op("y", "Pad", ["x", "p"])], {"p": np.int32([[0, 0], [1, 2], [0, 1], [0, 0]])}, ["y:0"]),
    "PadV2": ([_op("y", "PadV2", ["x", "p", "c"])],
              {"p": np.int32([[0, 0], [1, 1], [2, 0], [0, 0]]), "c": np.float32(-3.5)}, ["y:0"]),
    "ConcatV2": ([_op("y", "ConcatV2", ["x", "x2", "a"], N={"i": "2"}), _op("x2", "Sigmoid", ["x"])],
                 {"a": np.int32(3)}, ["y:0"]),
    "SplitV": ([_op("y", "SplitV", ["x", "s", "a"], num_split={"i": "3"})],
               {"s": np.int32([1, -1, 2]), "a": np.int32(-1)}, ["y:0", "y:1", "y:2"]),
    "Split": ([_op("y", "Split", ["a", "x"], num_split={"i": "2"})], {"a": np.int32(3)}, ["y:0", "y:1"]),
    "Conv2D": ([_op("y", "Conv2D", ["x", "w"], strides=_ints([1, 2, 2, 1]), padding=_s("SAME"),
                    dilations=_ints([1, 1, 1, 1]), data_format=_s("NHWC"))], {"w": W}, ["y:0"]),
    "MaxPool": ([_op("y", "MaxPool", ["x"], ksize=_ints([1, 3, 3, 1]), strides=_ints([1, 2, 2, 1]),
                     padding=_s("SAME"), data_format=_s("NHWC"))], {}, ["y:0"]),
    "ResizeBilinear": ([_op("y", "ResizeBilinear", ["x", "s"], align_corners={"b": False},
                            half_pixel_centers={"b": True})], {"s": np.int32([18, 7])}, ["y:0"]),
    "SparseToDense": ([_op("d", "SparseToDense", ["i", "sh", "v", "z"]), _op("y", "Reshape", ["x", "d"])],
                      {"i": np.int64([[0], [2]]), "sh": np.int64([3]), "v": np.int64([-1, 4]), "z": np.int64(1)},
                      ["y:0"]),
    "Cast": ([{"name": "c", "op": "Cast", "input": ["s"], "attr": {"DstT": {"type": "DT_INT64"}}},
              _op("y", "Reshape", ["x", "c"])], {"s": np.int32([1, 99, 4])}, ["y:0"]),
}


def test_every_supported_op_has_a_case():
    assert set(CASES) == tg.SUPPORTED_OPS - {"Const", "Placeholder"}


@pytest.mark.parametrize("op", sorted(CASES))
def test_op_matches_the_numpy_reference(tmp_path, op):
    nodes, consts, outputs = CASES[op]
    path = write_model(tmp_path, nodes, consts, {"x": list(X.shape)}, outputs)
    ref, got = _run_both(path, {"x": X})
    assert len(ref) == len(got) == len(outputs)
    for r, g in zip(ref, got, strict=True):
        assert r.shape == g.shape
        np.testing.assert_allclose(g, r, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("variant", ["valid_stride1", "explicit", "dilated", "nchw"])
def test_conv2d_variants(tmp_path, variant):
    attrs = {"strides": _ints([1, 1, 1, 1]), "padding": _s("VALID"), "dilations": _ints([1, 1, 1, 1])}
    x = X
    if variant == "explicit":
        attrs.update(padding=_s("EXPLICIT"), explicit_paddings=_ints([0, 0, 2, 0, 1, 3, 0, 0]),
                     strides=_ints([1, 2, 1, 1]))
    elif variant == "dilated":
        attrs.update(padding=_s("SAME"), dilations=_ints([1, 2, 2, 1]))
    elif variant == "nchw":
        attrs.update(data_format=_s("NCHW"), strides=_ints([1, 1, 2, 2]), padding=_s("SAME"))
        x = np.ascontiguousarray(X.transpose(0, 3, 1, 2))
    path = write_model(tmp_path, [_op("y", "Conv2D", ["x", "w"], **attrs)], {"w": W}, {"x": list(x.shape)}, ["y:0"])
    (r,), (g,) = _run_both(path, {"x": x})
    np.testing.assert_allclose(g, r, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("align,half", [(True, False), (False, False)])
def test_resize_bilinear_modes(tmp_path, align, half):
    node = _op("y", "ResizeBilinear", ["x", "s"], align_corners={"b": align}, half_pixel_centers={"b": half})
    path = write_model(tmp_path, [node], {"s": np.int32([4, 23])}, {"x": list(X.shape)}, ["y:0"])
    (r,), (g,) = _run_both(path, {"x": X})
    np.testing.assert_allclose(g, r, rtol=1e-4, atol=1e-5)


def test_numpy_references_match_hand_computed_values():
    """The references themselves: a 1x1 conv is a matrix product, SAME pads like TensorFlow (extra at the end),
    bilinear sampling follows TensorFlow's three coordinate rules, max pooling never picks the padding."""
    n = tg.TfjsNode("c", "Conv2D", [], {"strides": _ints([1, 1, 1, 1]), "padding": _s("VALID")})
    w1 = W[1:2, 1:2]
    np.testing.assert_allclose(tg.np_conv2d(n, X, w1)[0], X @ w1[0, 0], rtol=1e-5)
    assert tg._pads_same(9, 3, 2, 1) == (1, 1) and tg._pads_same(10, 3, 2, 1) == (0, 1)
    row = np.arange(4, dtype=np.float32).reshape(1, 1, 4, 1)  # values 0 1 2 3 along x

    def resize(align: bool, half: bool, out: int) -> list[float]:
        nd = tg.TfjsNode("r", "ResizeBilinear", [], {"align_corners": {"b": align}, "half_pixel_centers": {"b": half}})
        return tg.np_resize_bilinear(nd, row, np.int32([1, out]))[0].reshape(-1).tolist()

    assert resize(True, False, 7) == pytest.approx([0, 0.5, 1, 1.5, 2, 2.5, 3])
    assert resize(False, False, 8) == pytest.approx([0, 0.5, 1, 1.5, 2, 2.5, 3, 3])
    assert resize(False, True, 8) == pytest.approx([0, 0.25, 0.75, 1.25, 1.75, 2.25, 2.75, 3])
    p = tg.TfjsNode("p", "MaxPool", [], {"ksize": _ints([1, 2, 2, 1]), "strides": _ints([1, 2, 2, 1]),
                                         "padding": _s("SAME")})
    neg = -np.arange(1, 10, dtype=np.float32).reshape(1, 3, 3, 1)
    assert tg.np_maxpool(p, neg)[0].reshape(-1).tolist() == [-1, -3, -7, -9]


def test_quantised_weights_are_dequantised(tmp_path):
    b = np.linspace(-2, 3, 4, dtype=np.float32)
    nodes = [_op("y", "Add", ["x", "b"]), _op("z", "Add", ["x", "c"])]
    path = write_model(tmp_path, nodes, {"b": b, "c": b}, {"x": list(X.shape)}, ["y:0", "z:0"],
                       quantize={"b": "float16", "c": "uint8"})
    g = tg.read_graph(path)
    np.testing.assert_allclose(g.weights["b"], b, atol=1e-3)
    np.testing.assert_allclose(g.weights["c"], b, atol=5 / 255)
    ref, got = _run_both(path, {"x": X})
    np.testing.assert_allclose(got[0], ref[0], rtol=1e-5)


def test_unsupported_ops_are_refused_by_name(tmp_path):
    nodes = [_op("a", "Erf", ["x"]), _op("b", "NonMaxSuppressionV5", ["a"]), _op("y", "Add", ["b", "x"])]
    path = write_model(tmp_path, nodes, {}, {"x": list(X.shape)}, ["y:0"])
    g = tg.read_graph(path)
    assert tg.unsupported_ops(g) == ["Erf", "NonMaxSuppressionV5"]
    with pytest.raises(UnsupportedOpError, match="Erf, NonMaxSuppressionV5") as exc:
        tg.to_onnx(g)
    assert exc.value.ops == ["Erf", "NonMaxSuppressionV5"]


def test_constant_only_op_on_a_live_tensor_is_refused(tmp_path):
    nodes = [{"name": "y", "op": "Cast", "input": ["x"], "attr": {"DstT": {"type": "DT_INT32"}}}]
    path = write_model(tmp_path, nodes, {}, {"x": list(X.shape)}, ["y:0"])
    with pytest.raises(UnsupportedOpError, match="Cast"):
        tg.to_onnx(tg.read_graph(path))


def test_malformed_models_get_clear_errors(tmp_path):
    path = write_model(tmp_path, [_op("y", "Add", ["x", "b"])], {"b": np.ones(4, np.float32)},
                       {"x": list(X.shape)}, ["y:0"])
    (tmp_path / "w.bin").write_bytes(b"\0" * 8)  # shorter than the manifest says
    with pytest.raises(ModelFormatError, match="end before"):
        tg.read_graph(path)
    (tmp_path / "bad.json").write_text('{"format": "layers-model", "modelTopology": {}, "weightsManifest": []}')
    with pytest.raises(ModelFormatError, match="only graph models"):
        tg.read_graph(str(tmp_path / "bad.json"))
    with pytest.raises(ModelFormatError, match="not a readable"):
        tg.read_graph(str(tmp_path / "missing.json"))
    path = write_model(tmp_path, [_op("y", "Add", ["x", "nowhere"])], {}, {"x": list(X.shape)}, ["y:0"])
    with pytest.raises(ModelFormatError, match="unknown node 'nowhere'"):
        tg.to_onnx(tg.read_graph(path))


def test_cli_converts_and_refuses(tmp_path, capsys):
    path = write_model(tmp_path, [_op("y", "Sigmoid", ["x"])], {}, {"x": list(X.shape)}, ["y:0"])
    assert tg.main([path, str(tmp_path / "m.onnx")]) == 0
    assert "Sigmoid 1" in capsys.readouterr().out
    path = write_model(tmp_path, [_op("y", "Erf", ["x"])], {}, {"x": list(X.shape)}, ["y:0"])
    assert tg.main([path, str(tmp_path / "m2.onnx")]) == 2
    assert "unsupported TF.js op(s) Erf" in capsys.readouterr().err
