"""The labelling stage: geometry labels on the synthetic home (where truth exists), instance ids stable
across frames, the ONNX path on a toy model the test exports itself, names from people, and the CLI
on a 7-Scenes-layout sequence without labels."""

from __future__ import annotations

import json
import os
from collections import deque

import numpy as np
import pytest
from PIL import Image

from semantic_gs_slam.errors import ConfigError, FrameError, MapFormatError
from semantic_gs_slam.labels import OBJECT_ID, LabelConfig, LabelStage, predict_pose
from semantic_gs_slam.labels.geometry import (
    FIRST_INSTANCE_ID,
    FLOOR,
    TABLE,
    WALL,
    GeometryLabeller,
    best_plane_hypothesis,
    connected_components,
)
from semantic_gs_slam.labels.names import main as names_main
from semantic_gs_slam.labels.names import name_instance, read_names
from semantic_gs_slam.synthetic.scenes import CLASS_ID, HomeRenderer, default_intrinsics, trajectory


def _bfs_components(mask, join_h, join_v):
    """Reference: breadth-first flood fill."""
    h, w = mask.shape
    lab = np.zeros((h, w), int)
    n = 0
    for y in range(h):
        for x in range(w):
            if mask[y, x] and not lab[y, x]:
                n += 1
                lab[y, x] = n
                q = deque([(y, x)])
                while q:
                    a, b = q.popleft()
                    for c, d, ok in ((a, b + 1, b + 1 < w and join_h[a, b]), (a, b - 1, b > 0 and join_h[a, b - 1]),
                                     (a + 1, b, a + 1 < h and join_v[a, b]), (a - 1, b, a > 0 and join_v[a - 1, b])):
                        if ok and mask[c, d] and not lab[c, d]:
                            lab[c, d] = n
                            q.append((c, d))
    return lab, n


@pytest.mark.parametrize("seed", range(4))
def test_connected_components_match_a_flood_fill(seed):
    rng = np.random.default_rng(seed)
    mask = rng.random((23, 31)) < 0.7
    jh, jv = rng.random((23, 30)) < 0.8, rng.random((22, 31)) < 0.8
    got, n = connected_components(mask, jh, jv)
    ref, m = _bfs_components(mask, jh, jv)
    assert n == m
    # same partition: a one-to-one map between the two labellings
    pairs = set(zip(got[mask].tolist(), ref[mask].tolist(), strict=True))
    assert len(pairs) == n and (got[~mask] == 0).all()


def _sequential_ransac(p_h, n_h, p, n, tol, normal_cos):
    """Reference: one hypothesis at a time, keeping a strictly better score (the loop the search had before)."""
    best, best_score = None, 0
    for ph, nh in zip(p_h, n_h, strict=True):
        d = -float(nh @ ph)
        score = int(((np.abs(p @ nh + d) < tol) & (n @ nh > normal_cos)).sum())
        if score > best_score:
            best, best_score = (nh, d), score
    return best


@pytest.mark.parametrize("seed", range(6))
def test_plane_hypotheses_scored_at_once_match_one_at_a_time(seed):
    rng = np.random.default_rng(seed)
    # two noisy planes and clutter; hypotheses drawn from the points themselves, as the labeller draws them
    s = 600
    p = rng.normal(size=(s, 3))
    p[:250, 2] = 1.5 + 0.004 * rng.normal(size=250)
    p[250:400, 1] = -0.8 + 0.004 * rng.normal(size=150)
    n = rng.normal(size=(s, 3))
    n[:250] = [0, 0, 1]
    n[250:400] = [0, 1, 0]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    tol = 0.012 * np.maximum(np.abs(p[:, 2]), 0.3) ** 2
    hyp = rng.choice(s, 40, replace=False)
    got = best_plane_hypothesis(p[hyp], n[hyp], p, n, tol, 0.85)
    ref = _sequential_ransac(p[hyp], n[hyp], p, n, tol, 0.85)
    assert got is not None and ref is not None
    assert np.array_equal(got[0], ref[0]) and abs(got[1] - ref[1]) < 1e-12
    assert best_plane_hypothesis(p[hyp], n[hyp], p + 100.0, n, tol, 0.85) is None  # no inlier anywhere


def test_three_term_helpers_give_numpys_bits():
    """The labeller's per-pixel 3-vector arithmetic, written out, equals numpy's reductions bit for bit (so its
    labels did not change when it was sped up): dot products, norms, cross products, any-non-zero. (The plane
    distances were a matmul, which rounds in another order: within an ulp, same labels on 60 real frames.)"""
    from semantic_gs_slam.labels.geometry import _cross3, _dot3, _nonzero3, normals_from_points

    rng = np.random.default_rng(0)
    a = rng.normal(size=(37, 53, 3)) * 10.0 ** rng.integers(-6, 3, size=(37, 53, 1))
    b = rng.normal(size=(37, 53, 3))
    a[0, :5] = 0.0
    a[1, :5, 1] = 0.0
    v = rng.normal(size=3)
    assert np.array_equal(_dot3(a, b), (a * b).sum(-1))
    assert np.array_equal(_dot3(a, v), (a * v).sum(-1))
    np.testing.assert_allclose(_dot3(a, v), a @ v, rtol=1e-14, atol=1e-14 * float(np.abs(a).max()))
    assert np.array_equal(np.sqrt(_dot3(a, a)), np.linalg.norm(a, axis=-1))
    assert np.array_equal(_nonzero3(a), np.abs(a).sum(-1) > 0)
    assert np.array_equal(_cross3(a, b), np.cross(a, b))
    # normals_from_points as it was written with numpy's reductions (the flip by boolean indexing)
    pts = np.concatenate([rng.normal(size=(37, 53, 2)), 1.0 + rng.random((37, 53, 1))], -1)
    valid = rng.random((37, 53)) > 0.1
    dx, dy = np.zeros_like(pts), np.zeros_like(pts)
    dx[:, 1:-1] = pts[:, 2:] - pts[:, :-2]
    dy[1:-1] = pts[2:] - pts[:-2]
    n = np.cross(dx, dy)
    ok = valid.copy()
    ok[:, 1:-1] &= valid[:, 2:] & valid[:, :-2]
    ok[1:-1] &= valid[2:] & valid[:-2]
    ok[[0, -1], :] = False
    ok[:, [0, -1]] = False
    norm = np.linalg.norm(n, axis=-1)
    ok &= norm > 1e-12
    n = np.where(ok[..., None], n / np.maximum(norm, 1e-12)[..., None], 0.0)
    n[(n * pts).sum(-1) > 0] *= -1
    assert np.array_equal(normals_from_points(pts, valid), n)


@pytest.fixture(scope="module")
def home_frames():
    k = default_intrinsics(160, 90)
    traj = trajectory(10, 20.0)
    r = HomeRenderer(0)
    return k, [(traj[i], *r.render(traj[i], k)) for i in (0, 1, 4)]


def _share(pred, gt_mask, value):
    return float((pred[gt_mask] == value).mean())


def test_geometry_labels_on_the_synthetic_home(home_frames):
    k, frames = home_frames
    lab = GeometryLabeller(k)
    outs = [lab.label(rgb, depth, c2w) for c2w, rgb, depth, _ in frames]
    for (_, _, _, sem), out in zip(frames, outs, strict=True):
        ids = out.ids
        assert _share(ids, sem == CLASS_ID["floor"], FLOOR) > 0.7
        assert _share(ids, sem == CLASS_ID["wall"], WALL) > 0.5
        top = ids == TABLE
        assert top.sum() > 300 and np.isin(sem[top], [CLASS_ID["table"], CLASS_ID["sofa"], CLASS_ID["chair"]]).mean() \
            > 0.8  # support surfaces: the table top and seats, not the floor or walls
        chair = sem == CLASS_ID["chair"]
        inst = ids[chair][ids[chair] >= FIRST_INSTANCE_ID]
        vals, cnt = np.unique(inst, return_counts=True)
        best = vals[np.argmax(cnt)]
        iou = (chair & (ids == best)).sum() / (chair | (ids == best)).sum()
        assert iou > 0.3, iou  # the largest chair part is one instance (the chair's legs/back may split)
    # ids of the chair parts stay the same while the camera moves
    c0 = set(np.unique(outs[0].ids[frames[0][3] == CLASS_ID["chair"]]).tolist()) - {0, FLOOR, WALL, TABLE}
    c2 = set(np.unique(outs[2].ids[frames[2][3] == CLASS_ID["chair"]]).tolist()) - {0, FLOOR, WALL, TABLE}
    assert len(c0 & c2) >= 1
    assert all(lab.classes[i] == "object" for i in c0)


def test_geometry_labeller_rejects_bad_depth(home_frames):
    k, frames = home_frames
    lab = GeometryLabeller(k)
    with pytest.raises(FrameError, match="depth must be"):
        lab.label(frames[0][1], np.zeros((10, 10)), np.eye(4))
    out = lab.label(frames[0][1], np.zeros((k.height, k.width)), np.eye(4))  # no depth: nothing, no crash
    assert (out.ids == 0).all()


def test_label_stage_modes(home_frames):
    k, frames = home_frames
    c2w, rgb, depth, sem = frames[0]
    assert LabelStage(LabelConfig(), k, dataset_has_labels=True).mode == "dataset"
    st = LabelStage(LabelConfig(), k, dataset_has_labels=False)
    assert st.mode == "geometry"
    ids = st(rgb, depth, None, c2w)
    assert set(np.unique(ids).tolist()) <= {0, 1, 2, 3, 4, OBJECT_ID} and (ids == OBJECT_ID).any()
    assert st.classes[OBJECT_ID] == "object" and st.classes[FLOOR] == "floor"
    inst = LabelStage(LabelConfig(mode="geometry", map_ids="instance"), k)
    assert (inst(rgb, depth, None, c2w) >= FIRST_INSTANCE_ID).any()
    assert LabelStage(LabelConfig(mode="none"), k)(rgb, depth, sem, c2w) is None
    np.testing.assert_array_equal(LabelStage(LabelConfig(mode="dataset"), k, True)(rgb, depth, sem, c2w), sem)
    for bad in (LabelConfig(mode="magic"), LabelConfig(mode="onnx"), LabelConfig(map_ids="x")):
        with pytest.raises(ConfigError):
            LabelStage(bad, k)
    with pytest.raises(ConfigError, match="no label images"):
        LabelStage(LabelConfig(mode="dataset"), k, dataset_has_labels=False)
    with pytest.raises(ConfigError, match="not found"):
        LabelStage(LabelConfig(mode="onnx", onnx_model="/nonexistent.onnx"), k)


def test_label_stage_every_kth_frame(home_frames):
    """labels.every k: geometry labels on engine frames 0, k, 2k, ... (the index the caller gives, else the frames
    seen); the others get none. Dataset labels cost nothing and come on every frame."""
    k, frames = home_frames
    c2w, rgb, depth, sem = frames[0]
    st = LabelStage(LabelConfig(mode="geometry", every=2), k)
    got = [st(rgb, depth, None, c2w) for _ in range(4)]
    assert [g is not None for g in got] == [True, False, True, False]
    np.testing.assert_array_equal(got[0], LabelStage(LabelConfig(mode="geometry"), k)(rgb, depth, None, c2w))
    # the engine's frame index wins over the count (a resumed run keeps the same frames labelled)
    assert st(rgb, depth, None, c2w, index=7) is None and st(rgb, depth, None, c2w, index=8) is not None
    assert st(rgb, depth, None, c2w, index=7, keyframe=True) is not None  # an expected keyframe always is
    data = LabelStage(LabelConfig(mode="dataset", every=4), k, dataset_has_labels=True)
    assert all(data(rgb, depth, sem, c2w, index=i) is not None for i in range(3))
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ConfigError, match="labels.every"):
            LabelStage(LabelConfig(mode="geometry", every=bad), k)
    assert LabelStage(LabelConfig(mode="geometry", every=np.int64(3)), k).cfg.every == 3


def test_predict_pose_is_constant_velocity():
    a, b = np.eye(4), np.eye(4)
    b[0, 3] = 0.1
    assert predict_pose([a, b])[0, 3] == pytest.approx(0.2)
    assert predict_pose([], b)[0, 3] == pytest.approx(0.1) and (predict_pose([]) == np.eye(4)).all()


# ----------------------------------------------------------------------------- ONNX (layer 2)
def _export_toy(path, masks: bool = True, fixed: tuple[int, int] | None = None, batched: bool = False,
                labels=(44, 1)):
    """A toy 'segmenter' with the torchvision Mask R-CNN signature: detection 0 is every pixel whose red
    channel is > 0.5 (class ``labels[0]``, score 0.9), detection 1 the rest (score 0.2)."""
    torch = pytest.importorskip("torch")
    pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")

    class Toy(torch.nn.Module):
        def forward(self, image):
            img = image[0] if batched else image
            m = (img[0:1] > 0.5).float()  # [1, H, W]
            h, w = img.shape[1], img.shape[2]
            ys = torch.arange(h, dtype=torch.float32)[:, None] * m[0]
            xs = torch.arange(w, dtype=torch.float32)[None, :] * m[0]
            box = torch.stack([torch.zeros(()), torch.zeros(()), xs.max() + 1, ys.max() + 1])
            boxes = torch.stack([box, box])
            out = (boxes, torch.tensor(list(labels)), torch.tensor([0.9, 0.2]))
            return (*out, torch.stack([m, 1 - m])) if masks else out

    shape = (1, 3, *(fixed or (24, 32))) if batched else (3, *(fixed or (24, 32)))
    names = ["boxes", "labels", "scores"] + (["masks"] if masks else [])
    dyn = None if fixed else {"image": ({2: "h", 3: "w"} if batched else {1: "h", 2: "w"})}
    torch.onnx.export(Toy(), (torch.rand(*shape),), str(path), input_names=["image"], output_names=names,
                      dynamic_axes=dyn, dynamo=False)
    return str(path)


def _scene(k):
    """Floor-like depth with a box standing on it; the box is red (what the toy model 'detects')."""
    depth = np.full((k.height, k.width), 2.0)
    rgb = np.full((k.height, k.width, 3), 0.2)
    y0, y1, x0, x1 = k.height // 3, 2 * k.height // 3, k.width // 3, 2 * k.width // 3
    depth[y0:y1, x0:x1] = 1.5
    rgb[y0:y1, x0:x1, 0] = 0.9
    return rgb, depth, (slice(y0, y1), slice(x0, x1))


def test_onnx_segmenter_masks_name_pixels(tmp_path, home_frames):
    k = default_intrinsics(64, 48)
    path = _export_toy(tmp_path / "toy.onnx")
    st = LabelStage(LabelConfig(mode="onnx", onnx_model=path), k)
    assert st.model is not None and st.model.provider == "CPUExecutionProvider"
    rgb, depth, box = _scene(k)
    ids = st(rgb, depth, None, np.eye(4))
    assert (ids[box] == 54).mean() > 0.95  # COCO 44 = bottle -> semantic id 10 + 44
    assert st.classes[54] == "bottle"
    assert not (ids == 11).any()  # the 0.2-score detection is below the threshold


def test_onnx_detector_names_the_geometry_instance(tmp_path):
    k = default_intrinsics(64, 48)
    path = _export_toy(tmp_path / "det.onnx", masks=False, batched=True, labels=(46, 1))  # coco80 46 = "banana"
    st = LabelStage(LabelConfig(mode="onnx", onnx_model=path, onnx_label_space="coco80",
                                geometry=__import__("semantic_gs_slam.labels.geometry", fromlist=["x"])
                                .GeometryLabelConfig(max_planes=0)), k)
    rgb, depth, box = _scene(k)
    ids = st(rgb, depth, None, np.eye(4))
    assert (ids[box] == 10 + 52).mean() > 0.9 and st.classes[62] == "banana"


def test_onnx_model_failure_refuses_the_frame_before_the_stage_changes(tmp_path):
    """A model that fails on a frame (here: it reshapes to the size it was exported at, so onnxruntime raises on
    any other) refuses the frame with a FrameError before the geometry layer has seen it: no instance id is
    taken and the frame is not counted, so a run that skips the frame goes on as if it never came."""
    torch = pytest.importorskip("torch")
    pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")

    class Brittle(torch.nn.Module):
        def forward(self, image):
            m = (image.reshape(3, 24 * 32)[0:1] > 0.5).float().reshape(1, 1, 24, 32)  # only 24x32 fits
            return torch.tensor([[0.0, 0.0, 32.0, 24.0]]), torch.tensor([44]), torch.tensor([0.9]), m

    path = str(tmp_path / "brittle.onnx")
    torch.onnx.export(Brittle(), (torch.rand(3, 24, 32),), path, input_names=["image"],
                      output_names=["boxes", "labels", "scores", "masks"], dynamic_axes={"image": {1: "h", 2: "w"}},
                      dynamo=False)
    from semantic_gs_slam.labels.geometry import GeometryLabelConfig

    k = default_intrinsics(64, 48)
    geo = GeometryLabelConfig(max_planes=0)  # the box is an instance, not a plane
    st = LabelStage(LabelConfig(mode="onnx", onnx_model=path, geometry=geo), k)
    rgb, depth, box = _scene(k)
    before = (st._calls, st.geometry.next_id, dict(st.classes))
    with pytest.raises(FrameError, match="the ONNX model failed on a 64x48 frame"):
        st(rgb, depth, None, np.eye(4))
    assert (st._calls, st.geometry.next_id, dict(st.classes)) == before
    geometry_only = LabelStage(LabelConfig(mode="geometry", geometry=geo), k)  # what the geometry layer would do
    assert (geometry_only(rgb, depth, None, np.eye(4))[box] == OBJECT_ID).mean() > 0.9  # an instance, as "object"
    assert geometry_only.geometry.next_id > before[1]


def test_onnx_fixed_input_size_is_resized_back(tmp_path):
    k = default_intrinsics(64, 48)
    path = _export_toy(tmp_path / "fixed.onnx", fixed=(24, 32))
    from semantic_gs_slam.labels.onnx_model import OnnxSegmenter

    seg = OnnxSegmenter(path)
    assert seg.fixed_hw == (24, 32)
    rgb, _, box = _scene(k)
    (sem_id, score, mask, bx), = seg(rgb)
    assert sem_id == 54 and score == pytest.approx(0.9) and mask.shape == (48, 64)
    assert mask[box].mean() > 0.9 and mask.mean() < 0.2
    assert bx[2] == pytest.approx(2 * 64 // 3, abs=3)  # box scaled back to the frame
    with pytest.raises(FrameError):
        seg(np.zeros((4, 4)))


def test_onnx_bad_model_file(tmp_path):
    p = tmp_path / "junk.onnx"
    p.write_bytes(b"not a model")
    pytest.importorskip("onnxruntime")
    with pytest.raises(ConfigError, match="cannot load"):
        LabelStage(LabelConfig(mode="onnx", onnx_model=str(p)), default_intrinsics(64, 48))


# ----------------------------------------------------------------------------- names from people (layer 3)
def test_name_instance_round_trip(tmp_path, capsys):
    sj = tmp_path / "semantic.json"
    sj.write_text(json.dumps({"segmentation": [{"id": 1, "class": "floor"}, {"id": 130, "class": "object"}]}))
    assert name_instance(str(sj), 130, "  my   mug ") == "object"
    assert read_names(str(sj)) == {1: "floor", 130: "my mug"}
    with pytest.raises(MapFormatError, match="no id 7"):
        name_instance(str(sj), 7, "cup")
    with pytest.raises(ValueError):
        name_instance(str(sj), 130, "   ")
    assert names_main(["--map", str(tmp_path), "--list"]) == 0 and "130 my mug" in capsys.readouterr().out
    assert names_main(["--map", str(tmp_path / "nope"), "--id", "1", "--name", "x"]) == 2
    assert "no semantic.json" in capsys.readouterr().err


def _two_objects_map(folder) -> None:
    rng = np.random.default_rng(0)
    mug = rng.normal([0.4, 0.0, 1.6], 0.03, (60, 3))
    box = rng.normal([1.0, 0.0, 1.6], 0.05, (80, 3))
    floor = np.c_[rng.uniform(-1, 2, 200), np.full(200, 0.75), rng.uniform(1, 3, 200)]
    np.savez_compressed(folder / "params.npz", means3D=np.vstack([mug, box, floor]).astype(np.float32),
                        semantic_ids=np.r_[np.full(140, 5), np.full(200, 1)].astype(np.uint8))
    (folder / "semantic.json").write_text(json.dumps({"segmentation": [{"id": 1, "class": "floor"},
                                                                        {"id": 5, "class": "object"}]}))


def test_name_by_place_gives_one_object_its_own_id_and_the_object_database_finds_it(tmp_path, capsys):
    from semantic_gs_slam.labels.names import name_at

    _two_objects_map(tmp_path)
    new_id, n, was = name_at(str(tmp_path), (0.42, 0.01, 1.61), "  my  mug ")
    assert (new_id, n, was) == (6, 60, "object")  # all of the mug, none of the box 60 cm away, no floor
    assert read_names(str(tmp_path / "semantic.json")) == {1: "floor", 5: "object", 6: "my mug"}
    with np.load(tmp_path / "params.npz") as z:
        ids = z["semantic_ids"]
        assert ids.dtype == np.uint8 and list(np.bincount(ids)[[1, 5, 6]]) == [200, 80, 60]
    semantic_map = pytest.importorskip("object_query.semantic_map")
    db = semantic_map.ObjectDatabase.from_files(str(tmp_path / "params.npz"), str(tmp_path / "semantic.json"))
    found = db.query("my mug")
    assert found.found and np.allclose(found.position, (0.4, 0.0, 1.6), atol=0.03)
    # nothing to name: only floor near the point; a bad name; the CLI reports and exits 2
    with pytest.raises(MapFormatError, match="nothing but floor"):
        name_at(str(tmp_path), (0.0, 0.75, 2.0), "rug", radius=0.1)
    with pytest.raises(ValueError):
        name_at(str(tmp_path), (1.0, 0.0, 1.6), "")
    assert names_main(["--map", str(tmp_path), "--at", "1.0", "0.0", "1.6", "--radius", "0.2", "--name", "box"]) == 0
    assert "80 Gaussians of 'object'" in capsys.readouterr().out
    assert names_main(["--map", str(tmp_path), "--at", "5", "5", "5", "--name", "ghost"]) == 2
    assert "nothing but floor" in capsys.readouterr().err


def test_name_by_place_takes_unlabelled_gaussians_and_several_classes(tmp_path, capsys):
    """A TV screen gives the depth camera nothing: its Gaussians (seeded at the depth around it) have no class
    (id 0), its frame is an ``object``; both are named at once. Every id of a repeated name is taken."""
    from semantic_gs_slam.labels.names import name_at

    rng = np.random.default_rng(1)
    screen = np.c_[rng.uniform(-0.2, 0.2, 50), rng.uniform(-0.1, 0.1, 50), np.full(50, 3.0)]
    bezel = np.c_[rng.uniform(-0.25, 0.25, 20), np.full(20, -0.13), np.full(20, 3.0)]
    far = rng.normal([2.0, 0.0, 3.0], 0.05, (30, 3))  # unlabelled too, 2 m away
    wall = np.c_[rng.uniform(-1, 1, 100), rng.uniform(-1, 1, 100), np.full(100, 3.05)]
    np.savez_compressed(tmp_path / "params.npz", means3D=np.vstack([screen, bezel, far, wall]).astype(np.float32),
                        semantic_ids=np.r_[np.zeros(50), np.full(20, 5), np.zeros(30), np.full(100, 2)]
                        .astype(np.uint8)[:, None])  # [N, 1], as some writers save it
    (tmp_path / "semantic.json").write_text(json.dumps({"segmentation": [{"id": 2, "class": "wall"},
                                                                        {"id": 5, "class": "object"}]}))
    # the default never takes id 0: here the bezel alone
    assert name_at(str(tmp_path), (0.0, 0.0, 3.0), "frame", radius=0.3)[1:] == (20, "object")
    assert names_main(["--map", str(tmp_path), "--at", "0", "0", "3", "--radius", "0.3", "--of-class", "frame",
                       "--of-class", "unlabelled", "--name", "tv"]) == 0
    assert "70 Gaussians of 'frame, unlabelled'" in capsys.readouterr().out
    with np.load(tmp_path / "params.npz") as z:
        ids = z["semantic_ids"]
        assert ids.shape == (200, 1) and list(np.bincount(ids[:, 0], minlength=8)[[0, 2, 5, 6, 7]]) == \
            [30, 100, 0, 0, 70]  # the far unlabelled ones and the wall untouched
    assert read_names(str(tmp_path / "semantic.json"))[7] == "tv"
    # two ids of one name are one class to of_class
    name_at(str(tmp_path), (2.0, 0.0, 3.0), "tv", radius=0.3, of_class="unlabelled")
    new_id, n, was = name_at(str(tmp_path), (0.0, 0.0, 3.0), "television", radius=5.0, of_class=["tv"])
    assert (n, was) == (100, "tv")
    # a class the map does not have; an empty list; no such Gaussian near the point
    with pytest.raises(MapFormatError, match="no class 'sofa'.*'unlabelled'"):
        name_at(str(tmp_path), (0.0, 0.0, 3.0), "x", of_class=["object", "sofa"])
    with pytest.raises(ValueError, match="at least one"):
        name_at(str(tmp_path), (0.0, 0.0, 3.0), "x", of_class=[])
    with pytest.raises(MapFormatError, match="no Gaussian of class 'unlabelled'"):
        name_at(str(tmp_path), (0.0, 0.0, 3.0), "x", radius=0.3, of_class="unlabelled")
    assert names_main(["--map", str(tmp_path), "--at", "0", "0", "3", "--of-class", "sofa", "--name", "x"]) == 2
    assert "no class 'sofa'" in capsys.readouterr().err


# ----------------------------------------------------------------------------- CLI on a label-less real layout
@pytest.mark.slow
def test_cli_runs_a_7scenes_layout_with_geometry_labels(tiny_home, tmp_path, capsys):
    from semantic_gs_slam.io.datasets import load_dataset
    from semantic_gs_slam.run import main

    src = load_dataset(str(tiny_home))
    seq = _seven_scenes_copy(src, tmp_path / "seq-01", 3)
    k = src.intrinsics
    out = tmp_path / "map"
    rc = main(["--dataset", str(seq), "--out", str(out), "--size", f"{k.width // 2 * 2}x{k.height // 2 * 2}",
               "--frames", "3", "--mapping-iters", "2", "--quiet", "--eval",
               "--config", _write(tmp_path / "c.json", {"mapping": {"first_frame_iters": 3}})])
    assert rc == 0, capsys.readouterr().err
    names = read_names(str(out / "semantic.json"))
    assert names[OBJECT_ID] == "object" and names[FLOOR] == "floor"
    assert "ATE RMSE" in capsys.readouterr().out
    assert main(["--dataset", str(seq), "--out", str(out), "--labels", "dataset"]) == 2
    assert "no label images" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--dataset", str(seq), "--out", str(out), "--labels-every", "0"])
    assert "--labels-every must be >= 1" in capsys.readouterr().err


def _seven_scenes_copy(src, seq, frames: int, hole: tuple[int, slice, slice] | None = None):
    """The first ``frames`` frames of ``src`` written in the 7-Scenes layout (millimetre depth, no labels);
    ``hole``: (frame, rows, columns) of depth left at 0."""
    os.makedirs(seq)
    np.savetxt(seq / "camera-intrinsics.txt", src.intrinsics.as_matrix())
    for i in range(frames):
        f = src[i]
        depth = f.depth.copy()
        if hole is not None and hole[0] == i:
            depth[hole[1], hole[2]] = 0
        Image.fromarray((f.rgb * 255 + 0.5).astype(np.uint8)).save(seq / f"frame-{i:06d}.color.jpg")
        Image.fromarray((depth * 1000).round().astype(np.uint16)).save(seq / f"frame-{i:06d}.depth.png")
        np.savetxt(seq / f"frame-{i:06d}.pose.txt", f.gt_c2w)
    return seq


def test_name_by_pixel_of_a_frame_the_map_was_built_from(tiny_home, tmp_path, capsys):
    """``--frame N --pixel U V``: a pixel of the frame's colour image file, at the map's working size (half here),
    with the frame's depth and the map's own pose of that frame, matched by time stamp (every 2nd frame used)."""
    from semantic_gs_slam.io.colour_registration import SEVEN_SCENES_COLOUR, scaled
    from semantic_gs_slam.io.datasets import load_dataset
    from semantic_gs_slam.labels.names import point_at_pixel
    from semantic_gs_slam.run import main

    src = load_dataset(str(tiny_home))
    k = src.intrinsics  # 120 x 68
    seq = _seven_scenes_copy(src, tmp_path / "seq-01", 5, hole=(2, slice(0, 12), slice(0, 12)))
    out = tmp_path / "map"
    assert main(["--dataset", str(seq), "--out", str(out), "--size", f"{k.width // 2}x{k.height // 2}", "--stride", "2",
                 "--frames", "3", "--labels", "none", "--mapping-iters", "2", "--quiet",
                 "--config", _write(tmp_path / "c.json", {"mapping": {"first_frame_iters": 3}})]) == 0
    # colour registered to depth (colour_calib none): the colour file's pixel is the depth image's
    for frame, map_frame in ((0, 0), (2, 1), (4, 2)):
        u, v = 30.0, 60.0  # a smooth surface in these frames (depth within 6.5 cm over 7 x 7 pixels)
        truth = src[frame]
        z_true = float(truth.depth[int(v), int(u)])
        p, z, j = point_at_pixel(str(out), str(seq), frame, (u, v), window=1, colour_calib="none")
        assert j == map_frame and z == pytest.approx(z_true, abs=0.04)  # a neighbouring pixel's depth at half size
        ray = np.array([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z])  # the native pixel's ray, at that depth
        expect = truth.gt_c2w[:3, :3] @ ray + truth.gt_c2w[:3, 3]
        assert np.linalg.norm(p - expect) < (1e-4 if frame == 0 else 0.02)  # frame 0 is anchored on its pose
    # the 7-Scenes default: colour from the Kinect's colour camera, 2.35 cm beside the depth camera with another
    # focal length; the colour pixel that shows depth pixel (ud, vd) must give that depth pixel's point
    half = load_dataset(str(seq), size=(k.width // 2, k.height // 2))
    kw, d = half.intrinsics, half[0].depth
    cal = scaled(SEVEN_SCENES_COLOUR, k.width / 640, k.height / 480)
    ud, vd = 15, 29
    zd = float(d[vd, ud])
    x, y = (ud - kw.cx) / kw.fx * zd, (vd - kw.cy) / kw.fy * zd
    uc, vc = cal.fx * (x + cal.tx) / zd + cal.cx, cal.fy * (y + cal.ty) / zd + cal.cy
    assert abs(uc - (ud + 0.5) * 2 + 0.5) > 1.0  # the calibration moves it by more than a pixel here
    p, z, j = point_at_pixel(str(out), str(seq), 0, (uc, vc), window=1)
    c2w = src[0].gt_c2w
    assert z == pytest.approx(zd) and np.linalg.norm(p - (c2w[:3, :3] @ [x, y, zd] + c2w[:3, 3])) < 1e-4
    # refused with the reason: a skipped frame, a frame or pixel outside, no depth, a bad window
    with pytest.raises(ValueError, match="not one of the map's 3 frames"):
        point_at_pixel(str(out), str(seq), 1, (70, 40))
    with pytest.raises(ValueError, match="not in the dataset"):
        point_at_pixel(str(out), str(seq), 5, (70, 40))
    with pytest.raises(ValueError, match="outside frame 0's 120x68 colour image"):
        point_at_pixel(str(out), str(seq), 0, (120, 40))
    with pytest.raises(ValueError, match="no depth"):
        point_at_pixel(str(out), str(seq), 2, (4, 4), colour_calib="none")
    with pytest.raises(ValueError, match="odd"):
        point_at_pixel(str(out), str(seq), 0, (70, 40), window=4)
    # another sequence (poses 10 cm off, or another camera) than the one the map was built from
    other = _seven_scenes_copy(src, tmp_path / "seq-02", 3)
    pose = np.loadtxt(other / "frame-000002.pose.txt")
    pose[0, 3] += 0.1
    np.savetxt(other / "frame-000002.pose.txt", pose)
    with pytest.raises(ValueError, match="built from another sequence"):
        point_at_pixel(str(out), str(other), 2, (70, 40))
    np.savetxt(other / "camera-intrinsics.txt", [[k.fx * 1.1, 0, k.cx], [0, k.fy, k.cy], [0, 0, 1]])
    with pytest.raises(ValueError, match="is not this dataset's"):
        point_at_pixel(str(out), str(other), 0, (70, 40))
    # the CLI: the Gaussians there have no class (labels none), so they are named as 'unlabelled'
    assert names_main(["--map", str(out), "--dataset", str(seq), "--frame", "2", "--pixel", "70", "40", "--radius",
                       "0.3", "--of-class", "unlabelled", "--name", "thing"]) == 0
    said = capsys.readouterr().out
    assert "frame 2, pixel (70, 40)" in said and "its frame 1's pose" in said and "Gaussians of 'unlabelled'" in said
    assert "thing" in read_names(str(out / "semantic.json")).values()
    assert names_main(["--map", str(out), "--dataset", str(seq), "--frame", "3", "--pixel", "70", "40",
                       "--name", "x"]) == 2
    assert "pick a frame the run used" in capsys.readouterr().err
    for bad in (["--frame", "2", "--pixel", "70", "40", "--name", "x"],  # no --dataset
                ["--id", "3", "--at", "0", "0", "1", "--name", "x"]):  # an id and a place
        with pytest.raises(SystemExit) as exc:
            names_main(["--map", str(out), *bad])
        assert exc.value.code == 2
    assert "go together" in capsys.readouterr().err
    # a map without time stamps (an older file) cannot be matched to frames
    with np.load(out / "params.npz") as z:
        arrays = {n: z[n] for n in z.files if n != "timestamps"}
    np.savez_compressed(out / "params.npz", **arrays)
    with pytest.raises(MapFormatError, match="no time stamp"):
        point_at_pixel(str(out), str(seq), 0, (70, 40))


def _write(path, obj) -> str:
    path.write_text(json.dumps(obj))
    return str(path)
