"""Mesh -> points and KD-tree helpers against brute-force references (DTUeval-python steps 1-3)."""

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from gsbench.evaluators import pointsets
from tests.eval_fixtures import grid_samples_loop


def test_barycentric_grid_matches_per_triangle_loop():
    rng = np.random.default_rng(0)
    m = trimesh.creation.icosphere(2, radius=3.0)
    v = m.vertices * rng.uniform(0.5, 1.5, (len(m.vertices), 1))  # irregular triangles, many (n1, n2) groups
    faces = np.vstack([m.faces, [[0, 0, 1]]])  # plus a zero-area face, which is dropped
    fast = pointsets.barycentric_grid_samples(v, faces, 0.2)
    slow = grid_samples_loop(v, faces, 0.2)
    assert fast.shape == slow.shape and len(fast) > 1000
    np.testing.assert_allclose(fast, slow, atol=1e-12)  # same points in the same (triangle) order


def _greedy_loop(points, radius, seed):
    pts = points[np.random.default_rng(seed).permutation(len(points))]
    keep = np.ones(len(pts), bool)
    for i, nb in enumerate(cKDTree(pts).query_ball_point(pts, radius)):
        if keep[i]:
            keep[nb] = False
            keep[i] = True
    return pts[keep]


@pytest.mark.parametrize("chunk", [100_000, 1_000, 333])
def test_greedy_downsample_equals_sequential_greedy(chunk):
    rng = np.random.default_rng(1)
    pts = rng.random((15_000, 3)) * [4.0, 4.0, 0.2]
    pts = np.vstack([pts, pts[:50], pts[:50] + 0.2])  # exact duplicates and neighbours at exactly r
    fast = pointsets.greedy_downsample(pts, 0.2, seed=3, chunk=chunk)
    np.testing.assert_array_equal(fast, _greedy_loop(pts, 0.2, 3))
    d, _ = cKDTree(fast).query(fast, k=2)
    assert d[:, 1].min() > 0.2


def test_nn_distances_chunked_and_bounded(monkeypatch):
    monkeypatch.setattr(pointsets, "QUERY_CHUNK", 7)
    ref = np.array([[0.0, 0, 0], [10.0, 0, 0]])
    q = np.array([[1.0, 0, 0], [0, 3.0, 0], [10, 0, 4.0]] * 5)
    d = pointsets.nn_distances(q, cKDTree(ref), upper=3.0)
    np.testing.assert_allclose(d, [1.0, np.inf, np.inf] * 5)  # >= upper -> inf (strict)


def test_queries_in_spatial_order_answer_each_point_as_a_plain_query(monkeypatch):
    """`spatial_order` only reorders the work: every query point gets its own answer back, in chunks too."""
    monkeypatch.setattr(pointsets, "QUERY_CHUNK", 97)
    rng = np.random.default_rng(3)
    ref = rng.normal(size=(2000, 3)) * [50.0, 20.0, 5.0]
    queries = rng.normal(size=(1000, 3)) * [60.0, 25.0, 6.0]
    tree = cKDTree(ref)
    order = pointsets.spatial_order(queries)
    assert np.array_equal(np.sort(order), np.arange(len(queries))) and not np.array_equal(order, np.arange(1000))
    plain_dist, plain_idx = tree.query(queries, k=1)
    dist, idx = pointsets.nn_indices(queries, tree)
    np.testing.assert_array_equal(dist, plain_dist)
    np.testing.assert_array_equal(idx, plain_idx)
    np.testing.assert_array_equal(pointsets.nn_distances(queries, tree, upper=4.0),
                                  tree.query(queries, k=1, distance_upper_bound=4.0)[0])
    first = queries[order[:20]]  # the first cell's points: all in the low corner
    assert np.all(first <= queries.min(0) + np.ptp(queries, axis=0).max() / 2)
    assert pointsets.spatial_order(np.zeros((0, 3))).shape == (0,)


def test_pca_normals_of_a_plane_and_sample_surface():
    rng = np.random.default_rng(0)
    plane = np.c_[rng.random((2000, 2)), np.zeros(2000)]
    n = pointsets.pca_normals(plane, plane[:100], k=20)
    np.testing.assert_allclose(np.abs(n[:, 2]), 1.0, atol=1e-9)
    m = trimesh.creation.box()
    p1, n1 = pointsets.sample_surface(m.vertices, m.faces, 500, seed=4)
    p2, _ = pointsets.sample_surface(m.vertices, m.faces, 500, seed=4)
    np.testing.assert_array_equal(p1, p2)
    assert np.allclose(np.abs(p1).max(axis=1), 0.5) and np.allclose(np.linalg.norm(n1, axis=1), 1)


def test_voxel_area_samples_are_one_centroid_per_voxel_whatever_the_chunking():
    import trimesh

    from gsbench.evaluators.pointsets import voxel_area_samples

    sphere = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    whole = voxel_area_samples(v, f, 0.05, seed=3, chunk=10**9)
    assert np.allclose(whole, voxel_area_samples(v, f, 0.05, seed=3, chunk=7), rtol=0, atol=1e-12)  # sums in another order
    cells = np.floor(whole / 0.05).astype(int)
    assert len(np.unique(cells, axis=0)) == len(whole)  # one point per occupied voxel, inside it
    assert np.abs(np.linalg.norm(whole, axis=1) - 1).max() < 0.05  # on the (faceted) surface
