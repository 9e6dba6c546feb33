"""The map-to-browser conversion of the live view (viser's splat format), without a browser."""

from __future__ import annotations

import numpy as np
import pytest

from semantic_gs_slam.errors import ConfigError
from semantic_gs_slam.viewer import splats_from_arrays


def one_map(n: int = 1) -> dict[str, np.ndarray]:
    a = np.radians(30.0)
    return {"means3D": np.tile([[1.0, 2.0, 3.0]], (n, 1)), "rgb_colors": np.tile([[0.2, 1.5, -0.1]], (n, 1)),
            "log_scales": np.tile(np.log([[0.1, 0.2, 0.3]]), (n, 1)),
            "unnorm_rotations": np.tile([[2 * np.cos(a / 2), 0.0, 0.0, 2 * np.sin(a / 2)]], (n, 1)),  # 30 deg about z
            "logit_opacities": np.zeros((n, 1))}


def test_covariance_is_r_s2_rt_and_colours_opacities_are_in_range() -> None:
    centers, covs, rgbs, opac = splats_from_arrays(one_map())
    a = np.radians(30.0)
    r = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    np.testing.assert_allclose(covs[0], r @ np.diag([0.01, 0.04, 0.09]) @ r.T, atol=1e-6)
    np.testing.assert_allclose(centers[0], [1, 2, 3])
    np.testing.assert_allclose(rgbs[0], [0.2, 1.0, 0.0])
    np.testing.assert_allclose(opac, [[0.5]])
    iso = one_map()
    iso["log_scales"] = np.log([[0.1]])  # isotropic [N, 1] scales
    np.testing.assert_allclose(np.linalg.eigvalsh(splats_from_arrays(iso)[1][0]), [0.01] * 3, atol=1e-6)


def test_big_maps_are_subsampled_and_bad_maps_refused() -> None:
    centers, covs, rgbs, opac = splats_from_arrays(one_map(1000), max_splats=100)
    assert len(centers) == len(covs) == len(rgbs) == len(opac) == 100
    bad = one_map(3)
    del bad["rgb_colors"]
    with pytest.raises(ConfigError, match="not a Gaussian map"):
        splats_from_arrays(bad)
    bad = one_map(3)
    bad["logit_opacities"] = np.zeros((2, 1))
    with pytest.raises(ConfigError, match="disagree"):
        splats_from_arrays(bad)
