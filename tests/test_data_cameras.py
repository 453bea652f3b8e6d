"""Camera decomposition and pixel conventions of the DTU (IDR) cameras."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from gsbench.data.camera import Camera
from gsbench.data.dtu import PIXEL_SHIFT, decompose_projection, world_mat
from gsbench.data.similarity import similarity, transform_camera
from gsbench.errors import DataError


def _random_camera(rng):
    K = np.array([[rng.uniform(200, 3000), rng.uniform(-2, 2), rng.uniform(100, 900)],
                  [0.0, rng.uniform(200, 3000), rng.uniform(100, 700)], [0.0, 0.0, 1.0]])
    return K, Rotation.random(random_state=rng.integers(1 << 31)).as_matrix(), rng.normal(scale=500, size=3)


def test_rq_recovers_random_cameras():
    rng = np.random.default_rng(0)
    for _ in range(200):
        K, R, t = _random_camera(rng)
        P = rng.choice([-1.0, 1.0]) * rng.uniform(0.01, 100) * K @ np.hstack([R, t[:, None]])
        K2, R2, t2 = decompose_projection(P)
        assert np.allclose(K2, K, rtol=1e-6, atol=1e-6) and np.allclose(R2, R, atol=1e-6)
        assert np.allclose(t2, t, rtol=1e-6, atol=1e-6) and np.linalg.det(R2) == pytest.approx(1.0)


@pytest.mark.parametrize("bad", ["rank2", "nan", "shape"])
def test_rq_rejects_bad_projection(bad):
    P = np.hstack([np.eye(3), np.ones((3, 1))])
    if bad == "rank2":
        P[2, :3] = P[0, :3] + P[1, :3]
    elif bad == "nan":
        P[1, 1] = np.nan
    else:
        P = P[:2]
    with pytest.raises(DataError, match="cameras.npz world_mat_3"):
        decompose_projection(P, source="cameras.npz world_mat_3")


def test_world_mat_uses_integer_pixel_centres():
    """gsbench K (centres at i+0.5) -> world_mat (integer centres) -> decomposition + 0.5 = the same camera."""
    rng = np.random.default_rng(1)
    K, R, t = _random_camera(rng)
    K[0, 1] = 0.0
    cam = Camera(K=K, R=R, t=t, width=1600, height=1200)
    P = world_mat(cam)[:3]
    K_dtu, R2, t2 = decompose_projection(P)
    assert np.allclose(K_dtu[:2, 2], K[:2, 2] - 0.5)
    assert np.allclose(PIXEL_SHIFT @ K_dtu, K) and np.allclose(R2, R) and np.allclose(t2, t)


def test_transform_camera_keeps_projections():
    rng = np.random.default_rng(2)
    K, R, t = _random_camera(rng)
    cam = Camera(K=K, R=R, t=t, width=100, height=80)
    m = similarity(3.7, Rotation.random(random_state=3).as_matrix(), [1e6, -2e5, 40.0])
    moved = transform_camera(cam, m)
    x = rng.normal(size=(50, 3))
    uv, z = cam.project(x)
    uv2, z2 = moved.project(x @ m[:3, :3].T + m[:3, 3])
    assert np.allclose(uv, uv2, atol=1e-6) and np.allclose(z2, 3.7 * z)
