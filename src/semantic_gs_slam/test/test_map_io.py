"""Map files: params.npz key set, semantic.json schema, .ply layout, loading SplaTAM-style files."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from semantic_gs_slam.config import Intrinsics
from semantic_gs_slam.errors import MapFormatError
from semantic_gs_slam.mapping.gaussian_map import (
    GaussianMap,
    export_ply,
    load_params,
    load_semantic_json,
    palette,
    save_params,
    save_semantic_json,
    trajectory_from_params,
)

KEYS = {"means3D", "rgb_colors", "unnorm_rotations", "logit_opacities", "log_scales", "semantic_colors",
        "semantic_ids", "cam_unnorm_rots", "cam_trans", "timestep", "intrinsics", "w2c", "org_width", "org_height",
        "gt_w2c_all_frames", "keyframe_time_indices"}


def small_map(n: int = 50) -> GaussianMap:
    m = GaussianMap()
    gen = torch.Generator().manual_seed(0)
    m.add(torch.rand(n, 3, generator=gen), torch.rand(n, 3, generator=gen), torch.randint(1, 12, (n,), generator=gen),
          torch.full((n,), 0.01), frame=0)
    return m


def test_params_npz_has_the_splatam_key_set_and_round_trips(tmp_path):
    m = small_map()
    m.normals = torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    k = Intrinsics(8, 6, 4.0, 4.0, 3.5, 2.5)
    w2c = [np.eye(4), np.eye(4)]
    w2c[1][0, 3] = 0.5
    save_params(str(tmp_path / "params.npz"), m, k, w2c, [None, np.eye(4)], [0])
    a = load_params(str(tmp_path / "params.npz"))
    assert KEYS.issubset(a)
    assert a["cam_unnorm_rots"].shape == (1, 4, 2) and a["cam_trans"].shape == (1, 3, 2)
    assert a["cam_trans"][0, 0, 1] == pytest.approx(0.5)
    assert a["log_scales"].shape == (50, 1) and a["semantic_ids"].shape == (50,)
    assert np.isnan(a["gt_w2c_all_frames"][0]).all() and a["gt_w2c_all_frames"][1][0, 0] == 1
    np.testing.assert_allclose(a["semantic_colors"], palette(a["semantic_ids"]), atol=1e-7)
    m2 = GaussianMap.from_arrays(a)
    for key, v in m.params.items():
        torch.testing.assert_close(m2.params[key], v.detach())
    assert (m2.semantic_ids == m.semantic_ids).all() and m2.class_slots == m.class_slots
    torch.testing.assert_close(m2.normals, m.normals)
    with pytest.raises(MapFormatError, match="normals"):
        GaussianMap.from_arrays(dict(a, normals=np.zeros((3, 3))))


def test_trajectory_comes_back_from_params(tmp_path):
    from semantic_gs_slam.geometry import pose_error, se3_exp

    c2w = [se3_exp(torch.tensor([0.1 * i, -0.3, 0.2 * i, 0.5, -1.0 * i, 0.25], dtype=torch.float64)).numpy()
           for i in range(4)]
    save_params(str(tmp_path / "params.npz"), small_map(), Intrinsics(8, 6, 4.0, 4.0, 3.5, 2.5),
                [np.linalg.inv(p) for p in c2w], [None] * 4, [0])
    back = trajectory_from_params(load_params(str(tmp_path / "params.npz")))
    assert len(back) == 4
    for a, b in zip(back, c2w, strict=True):
        cm, deg = pose_error(a, b)
        assert cm < 1e-6 and deg < 1e-4  # float32 storage
    with pytest.raises(MapFormatError, match="trajectory"):
        trajectory_from_params({"cam_trans": np.zeros((1, 3, 4))})


def test_object_query_reads_our_map(tmp_path):
    sm = pytest.importorskip("object_query.semantic_map")
    m = small_map()
    save_params(str(tmp_path / "params.npz"), m, Intrinsics(8, 6, 4.0, 4.0, 3.5, 2.5), [np.eye(4)], [None], [0])
    save_semantic_json(str(tmp_path / "semantic.json"), {5: "chair", 4: "table"})
    loaded = sm.load_semantic_map(str(tmp_path / "params.npz"), str(tmp_path / "semantic.json"))
    assert loaded.means.shape == (50, 3) and loaded.classes[5] == "chair"


def test_semantic_json_schema(tmp_path):
    p = tmp_path / "semantic.json"
    save_semantic_json(str(p), {2: "wall", 1: "floor"})
    assert json.loads(p.read_text()) == {"segmentation": [{"id": 1, "class": "floor"}, {"id": 2, "class": "wall"}]}
    assert load_semantic_json(str(p)) == {1: "floor", 2: "wall"}
    p.write_text('{"labels": []}')
    with pytest.raises(MapFormatError, match="schema"):
        load_semantic_json(str(p))


def test_load_splatam_style_params_without_semantics():
    a = {"means3D": np.zeros((3, 3)), "rgb_colors": np.ones((3, 3)), "log_scales": np.zeros((3, 3)),
         "logit_opacities": np.zeros((3, 1)), "unnorm_rotations": np.tile([1.0, 0, 0, 0], (3, 1))}
    m = GaussianMap.from_arrays(a)
    assert len(m) == 3 and m.params["log_scales"].shape == (3, 3) and (m.semantic_ids == 0).all()
    assert m.gaussians().semantic is None and (m.class_ids() == 0).all()
    with pytest.raises(MapFormatError, match="rows"):
        GaussianMap.from_arrays({"means3D": np.zeros((3, 3)), "rgb_colors": np.zeros((2, 3))})
    with pytest.raises(MapFormatError, match="means3D"):
        GaussianMap.from_arrays({"rgb_colors": np.zeros((2, 3))})


def test_bad_npz_is_a_map_format_error(tmp_path):
    p = tmp_path / "params.npz"
    p.write_bytes(b"not a zip")
    with pytest.raises(MapFormatError, match="not a readable"):
        load_params(str(p))
    with pytest.raises(MapFormatError, match="not found"):
        load_params(str(tmp_path / "missing.npz"))


def test_ply_standard_3dgs_layout(tmp_path):
    m = small_map(7)
    p = tmp_path / "map.ply"
    export_ply(str(p), m)
    raw = p.read_bytes()
    head, body = raw.split(b"end_header\n", 1)
    lines = head.decode().splitlines()
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 7"]
    props = [ln.split()[-1] for ln in lines if ln.startswith("property")]
    assert props[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert props[-8:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    data = np.frombuffer(body, "<f4").reshape(7, len(props))
    np.testing.assert_allclose(data[:, :3], m.params["means3D"].detach().numpy())
    np.testing.assert_allclose(data[:, 6:9] * 0.28209479177387814 + 0.5, m.params["rgb_colors"].detach().numpy(),
                               atol=1e-6)


def test_palette_is_distinct_for_home_classes():
    c = palette(np.arange(12))
    assert len({tuple(x) for x in c}) == 12 and (c[0] == 0).all()


def test_prune_removes_transparent_and_huge():
    m = small_map(10)
    with torch.no_grad():
        m.params["logit_opacities"][:3] = -10.0
        m.params["log_scales"][3] = 0.0  # 1 m
    assert m.prune(0.005, 0.3) == 4 and len(m) == 6 and len(m.semantic_ids) == 6


def test_class_features_are_one_hot_grow_with_new_classes_and_decide_ids():
    m = GaussianMap()
    m.add(torch.zeros(3, 3), torch.rand(3, 3), torch.tensor([5, 2, 0]), torch.full((3,), 0.01), frame=0)
    assert m.class_slots == [2, 5]
    f = m.params["semantic_features"].detach()
    assert f.tolist() == [[0, 1], [1, 0], [0, 0]]  # label 0 (unknown) has no class column set
    m.add(torch.zeros(1, 3), torch.rand(1, 3), torch.tensor([9]), torch.full((1,), 0.01), frame=1)
    assert m.class_slots == [2, 5, 9] and m.params["semantic_features"].shape == (4, 3)
    assert m.class_ids().tolist() == [5, 2, 0, 9]
    with torch.no_grad():  # optimisation moved the first Gaussian toward class 9
        m.params["semantic_features"][0] = torch.tensor([0.0, 0.3, 0.6])
    assert m.class_ids()[0] == 9
    # a blend of two classes is labelled with one of them (a 3-channel palette blend is not)
    blend = 0.5 * m.one_hot(torch.tensor([2])) + 0.5 * m.one_hot(torch.tensor([9])) + 0.01 * torch.tensor([0, 0, 1.0])
    assert m.labels_from_features(blend).tolist() == [9]
    assert m.labels_from_features(torch.zeros(1, 3)).tolist() == [0]


def test_sgs_slam_file_gets_one_hot_features_from_its_ids():
    n = 4
    a = {"means3D": np.zeros((n, 3)), "semantic_ids": np.array([3, 3, 7, 0]), "semantic_colors": palette([3, 3, 7, 0])}
    m = GaussianMap.from_arrays(a)
    assert m.class_slots == [3, 7] and m.class_ids().tolist() == [3, 3, 7, 0]
    bad = dict(a, semantic_features=np.zeros((n, 5)), semantic_feature_ids=np.array([3, 7]))
    with pytest.raises(MapFormatError, match="semantic_features"):
        GaussianMap.from_arrays(bad)


def test_label_votes_follow_the_majority_over_views_and_skip_occluded_gaussians():
    import torch

    from semantic_gs_slam.config import Intrinsics
    from semantic_gs_slam.mapping.gaussian_map import GaussianMap

    k = Intrinsics(8, 8, 8.0, 8.0, 3.5, 3.5)
    m = GaussianMap()
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0], [0.25, 0.0, 2.0]])  # the second one is behind
    m.add(means, torch.full((3, 3), 0.5), torch.tensor([5, 5, 7]), torch.full((3,), 0.01), frame=0)
    w2c = torch.eye(4)
    depth = torch.full((8, 8), 2.0)
    for label in (6, 6, 6, 0):  # three views say 6, one has no label (no vote)
        sem = torch.full((8, 8), label)
        m.vote(sem, depth, w2c, k)
    assert m.class_slots == [5, 7]  # 6 has no slot yet: its votes are not counted ...
    m.ensure_classes(torch.tensor([6]))
    for _ in range(3):
        m.vote(torch.full((8, 8), 6), depth, w2c, k)
    votes = dict(zip(m.class_slots, m.votes.T.tolist(), strict=True))
    assert votes[6] == [3.0, 0.0, 3.0]  # ... now they are; the occluded Gaussian (z = 3 m, depth 2 m) never votes
    assert votes[5] == [1.0, 1.0, 0.0] and votes[7] == [0.0, 0.0, 1.0]  # the seeding labels
    m.voted_features(min_votes=2.0)
    assert m.class_ids().tolist() == [6, 5, 6]  # the majority wins where there were >= 2 votes
    arrays = m.to_arrays()
    back = GaussianMap.from_arrays(arrays)
    assert torch.equal(back.votes, m.votes)
