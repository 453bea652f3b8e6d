"""The mesh normal-consistency term of SuGaR's refinement (methods/sugar_refine.py: `face_pairs`,
`mesh_normal_consistency`) against a dense reference that compares every pair of faces by brute force with
pytorch3d's formula, on meshes whose value is known by hand: a flat grid (0), a grid folded along a line, an edge
shared by three faces, faces wound either way and an edge's faces far apart in the face list; float64 gradients."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from gsbench.methods.sugar_refine import face_pairs, mesh_normal_consistency


def dense_reference(vertices: np.ndarray, faces: np.ndarray) -> float:
    """pytorch3d's mesh normal consistency, straight from its definition: for every two faces and every edge
    (v₀ < v₁) they share, with a and b their vertices off the edge, 1 − cos(n₀, n₁), n₀ = e × (a − v₀),
    n₁ = −e × (b − v₀), e = v₁ − v₀; the mean over all such pairs."""
    values = []
    for f0, f1 in itertools.combinations(range(len(faces)), 2):
        for v0, v1 in itertools.combinations(sorted(set(faces[f0].tolist())), 2):
            if {v0, v1} <= set(faces[f1].tolist()):
                a = next(v for v in faces[f0].tolist() if v not in (v0, v1))
                b = next(v for v in faces[f1].tolist() if v not in (v0, v1))
                e = vertices[v1] - vertices[v0]
                n0, n1 = np.cross(e, vertices[a] - vertices[v0]), -np.cross(e, vertices[b] - vertices[v0])
                values.append(1 - n0 @ n1 / (np.linalg.norm(n0) * np.linalg.norm(n1)))
    return float(np.mean(values))


def grid(columns: int, rows: int, fold_at: int | None = None, fold: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A columns x rows grid of unit squares in z = 0, each cut along its diagonal into two triangles wound
    counter-clockwise; with ``fold_at``, the part x > fold_at turned by ``fold`` radians about the line x = fold_at."""
    xs, ys = np.meshgrid(np.arange(columns + 1, dtype=float), np.arange(rows + 1, dtype=float), indexing="xy")
    vertices = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1)
    if fold_at is not None:
        beyond = vertices[:, 0] > fold_at
        d = vertices[beyond, 0] - fold_at
        vertices[beyond, 0], vertices[beyond, 2] = fold_at + d * math.cos(fold), d * math.sin(fold)
    at = lambda i, j: j * (columns + 1) + i  # noqa: E731
    faces = [f for i in range(columns) for j in range(rows)
             for f in ([at(i, j), at(i + 1, j), at(i + 1, j + 1)], [at(i, j), at(i + 1, j + 1), at(i, j + 1)])]
    return vertices, np.array(faces)


def book(pages: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """Triangles sharing the edge (0, 0, 0)-(0, 1, 0), one per page, the page at angle θ about the edge (from +x
    towards +z): a non-manifold edge with len(pages) faces."""
    vertices = [[0.0, 0.0, 0.0], [0.0, 1.0, 0.0]] + [[math.cos(t), 0.5, math.sin(t)] for t in pages]
    return np.array(vertices), np.array([[0, 1, 2 + k] for k in range(len(pages))])


def normal_consistency(vertices: np.ndarray, faces: np.ndarray) -> float:
    pairs, signs = face_pairs(faces)
    return float(mesh_normal_consistency(torch.from_numpy(vertices), torch.from_numpy(faces), pairs, signs))


def test_a_flat_grid_is_zero_and_a_fold_costs_its_crossing_pairs():
    """Flat: 0. A 4 x 2 grid folded along x = 2 by θ has 18 pairs (4 inner horizontal, 6 inner vertical edges and 8
    diagonals), of which the 2 edges on the fold give 1 − cos θ each: (1 − cos θ) / 9; θ = 90°: 1/9."""
    flat_vertices, flat_faces = grid(4, 2)
    assert normal_consistency(flat_vertices, flat_faces) == pytest.approx(0.0, abs=1e-12)
    assert dense_reference(flat_vertices, flat_faces) == pytest.approx(0.0, abs=1e-12)
    for theta in (math.pi / 2, 0.3, 2.5):
        vertices, faces = grid(4, 2, fold_at=2, fold=theta)
        assert len(face_pairs(faces)[0]) == 18
        expected = (1 - math.cos(theta)) / 9
        assert dense_reference(vertices, faces) == pytest.approx(expected, rel=1e-12)
        assert normal_consistency(vertices, faces) == pytest.approx(expected, rel=1e-12)


def test_an_edge_of_three_faces_compares_every_pair_of_them_wherever_they_stand():
    """Pages at 0°, 90° and 180° about one edge: pairs (0°, 180°) 0, (0°, 90°) 1 and (90°, 180°) 1, mean 2/3,
    whatever the order of the faces, with other faces between them in the face list (pairing consecutive faces
    of the edge sees two of the three pairs: 1/2 or 1)."""
    vertices, faces = book([0.0, math.pi / 2, math.pi])
    assert dense_reference(vertices, faces) == pytest.approx(2 / 3, rel=1e-12)
    for order in itertools.permutations(range(3)):
        assert normal_consistency(vertices, faces[list(order)]) == pytest.approx(2 / 3, rel=1e-12)
    far_vertices, far_faces = grid(3, 2)  # the book's faces spread through a grid's face list
    offset = len(far_vertices)
    spread = np.insert(far_faces, [0, 5, 12], faces + offset, axis=0)
    both = np.concatenate([far_vertices, vertices + [10.0, 0.0, 0.0]])
    pairs_of_grid = len(face_pairs(far_faces)[0])
    expected = 2.0 / (pairs_of_grid + 3)  # the flat grid's pairs add 0
    assert dense_reference(both, spread) == pytest.approx(expected, rel=1e-12)
    assert normal_consistency(both, spread) == pytest.approx(expected, rel=1e-12)


def test_the_winding_of_a_face_does_not_change_the_term():
    """pytorch3d's normals are taken from the shared edge, not from the faces' winding: a flat grid with some
    faces wound the other way is still 0, and a fold still costs its crossing pairs."""
    vertices, faces = grid(4, 2, fold_at=2, fold=math.pi / 2)
    flipped = faces.copy()
    flipped[::3] = flipped[::3, ::-1]
    assert normal_consistency(vertices, flipped) == pytest.approx(1 / 9, rel=1e-12)
    assert dense_reference(vertices, flipped) == pytest.approx(1 / 9, rel=1e-12)
    flat_vertices, flat_faces = grid(4, 2)
    flat_faces[1::2] = flat_faces[1::2, ::-1]
    assert normal_consistency(flat_vertices, flat_faces) == pytest.approx(0.0, abs=1e-12)


def test_random_meshes_match_the_dense_reference():
    """A perturbed grid, with a few faces rewound, a fin of three extra faces on one of its edges and the face list
    shuffled, equals the reference to float64 precision; a mesh without shared edges gives 0."""
    rng = np.random.default_rng(0)
    for trial in range(5):
        vertices, faces = grid(4, 3)
        vertices = vertices + 0.2 * rng.standard_normal(vertices.shape)
        rewound = rng.random(len(faces)) < 0.3
        faces[rewound] = faces[rewound, ::-1]
        v0, v1 = faces[trial][:2]
        fins = rng.standard_normal((3, 3)) + vertices[[v0, v1]].mean(0)
        faces = np.concatenate([faces, [[v0, v1, len(vertices) + k] for k in range(3)]])
        vertices = np.concatenate([vertices, fins])
        faces = faces[rng.permutation(len(faces))]
        assert normal_consistency(vertices, faces) == pytest.approx(dense_reference(vertices, faces), rel=1e-12, abs=1e-14)
    apart = np.array([[0, 1, 2], [3, 4, 5]])
    assert normal_consistency(np.eye(6, 3) + np.arange(18.0).reshape(6, 3) ** 1.5, apart) == 0.0


def test_gradients_match_finite_differences():
    """gradcheck of the term w.r.t. the vertices (float64) on a folded, partly rewound grid with a fin."""
    vertices, faces = grid(3, 2, fold_at=1, fold=0.7)
    faces[::2] = faces[::2, ::-1]
    faces = np.concatenate([faces, [[faces[2][0], faces[2][1], len(vertices)]]])
    vertices = np.concatenate([vertices, [[0.3, 0.4, 0.9]]]) + 0.05 * np.random.default_rng(1).standard_normal((len(vertices) + 1, 3))
    pairs, signs = face_pairs(faces)
    assert torch.autograd.gradcheck(lambda v: mesh_normal_consistency(v, torch.from_numpy(faces), pairs, signs),
                                    (torch.from_numpy(vertices).requires_grad_(),))
