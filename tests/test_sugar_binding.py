"""SuGaR's refinement (methods/sugar_binding.py, methods/sugar_refine.py): Gaussians stay in their triangle's plane and move with
its vertices exactly, the complex in-plane rotation equals the quaternion path, float64 gradients through the
binding, the hard meshes (zero-area faces, several components, empty), a quick run with refinement (its vertices
move from the mesh it starts from) and its decimated control (that mesh, not refined), and the budget's refusal."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from gsbench.cli import main
from gsbench.config.run_config import run_id
from gsbench.data.method_scene import scene_for_method
from gsbench.errors import ConfigError
from gsbench.geometry.rotations import quat_multiply, rotmat_to_quat
from gsbench.mesh import MeshError
from gsbench.mesh.cleanup import canonical_order
from gsbench.methods.sugar_binding import (
    BARYCENTRIC,
    barycentric,
    bound_frames,
    bound_gaussians,
    initial_log_scales,
    usable_faces,
)
from gsbench.methods.sugar_refine import bound_mesh
from gsbench.raster.reference_projection import quat_to_rotmat
from gsbench.registry import METHODS
from gsbench.runs.runner import load_run_scene, resolve_recorded, resolve_run
from gsbench.runs.sweep import expand, load_sweep
from gsbench.training.trainer import load_checkpoint
from sweep_files import sweep_file


def _two_components(dtype=torch.float64):
    """A tetrahedron and a separate quad (two components), random but fixed."""
    gen = torch.Generator().manual_seed(0)
    tet = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.1, 0.0], [0.2, 1.0, 0.1], [0.3, 0.2, 1.0]], dtype=dtype)
    quad = torch.tensor([[3.0, 0.0, 0.0], [4.0, 0.0, 0.2], [4.0, 1.0, 0.1], [3.0, 1.0, 0.0]], dtype=dtype)
    vertices = torch.cat([tet, quad]) + 0.01 * torch.randn(8, 3, generator=gen, dtype=dtype)
    faces = torch.tensor([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2], [4, 5, 6], [4, 6, 7]])
    return vertices, faces


@pytest.mark.parametrize("per_triangle", sorted(BARYCENTRIC))
def test_bound_gaussians_lie_in_their_triangle_and_follow_its_vertices(per_triangle):
    """Every centre is in its face's plane and inside it, its thin axis is the face normal; moving one vertex
    by δ moves the centres of its faces by b_k δ exactly and leaves the other faces' Gaussians where they were."""
    vertices, faces = _two_components()
    n = len(faces) * per_triangle
    gen = torch.Generator().manual_seed(1)
    log_scales, rotation = torch.randn(n, 2, generator=gen, dtype=torch.float64), torch.randn(n, 2, generator=gen, dtype=torch.float64)
    means, scales, quats = bound_gaussians(vertices, faces, per_triangle, log_scales, rotation, thickness=1e-6)
    v = vertices[faces].repeat_interleave(per_triangle, 0)
    normal = torch.nn.functional.normalize(torch.linalg.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), dim=-1)
    assert torch.allclose(((means - v[:, 0]) * normal).sum(-1), torch.zeros(n, dtype=torch.float64), atol=1e-14)
    coords, _ = barycentric(per_triangle)
    assert bool((coords > 0).all()) and torch.allclose(coords.sum(1), torch.ones(per_triangle, dtype=torch.float64))
    assert torch.allclose(quat_to_rotmat(quats)[..., 0], normal, atol=1e-12) and torch.all(scales[:, 0] == 1e-6)
    delta = torch.tensor([0.05, -0.02, 0.07], dtype=torch.float64)
    moved_vertices = vertices.clone()
    moved_vertices[1] += delta
    moved, _, _ = bound_gaussians(moved_vertices, faces, per_triangle, log_scales, rotation, thickness=1e-6)
    weight = torch.zeros(n, dtype=torch.float64)
    for f, face in enumerate(faces.tolist()):
        if 1 in face:
            weight[f * per_triangle:(f + 1) * per_triangle] = coords[:, face.index(1)]
    assert torch.allclose(moved - means, weight[:, None] * delta, atol=1e-14)
    assert torch.equal(moved[4 * per_triangle:], means[4 * per_triangle:])  # the other component did not move


def test_the_complex_rotation_equals_the_quaternion_path():
    """z = (cos θ, sin θ) turns the face's base frame [n, e₁, e₂] by θ about n: the same matrix as the base
    frame's quaternion times the quaternion (cos θ/2, sin θ/2 x̂) of a turn about the frame's first axis."""
    vertices, faces = _two_components()
    base = bound_frames(vertices, faces, torch.tensor([[1.0, 0.0]], dtype=torch.float64).expand(len(faces), 2), 1)
    q_base = rotmat_to_quat(base)
    for theta in (0.3, 1.7, -2.5, math.pi):
        z = torch.tensor([[math.cos(theta), math.sin(theta)]], dtype=torch.float64).expand(len(faces), 2)
        turn = torch.tensor([[math.cos(theta / 2), math.sin(theta / 2), 0.0, 0.0]], dtype=torch.float64).expand(len(faces), 4)
        assert torch.allclose(bound_frames(vertices, faces, z, 1), quat_to_rotmat(quat_multiply(q_base, turn)), atol=1e-12)


def test_gradients_through_the_binding_match_finite_differences():
    """gradcheck of means, scales and quaternions w.r.t. vertices, log-scales and the complex rotations."""
    vertices, faces = _two_components()
    gen = torch.Generator().manual_seed(2)
    log_scales = torch.randn(len(faces) * 3, 2, generator=gen, dtype=torch.float64).requires_grad_()
    rotation = torch.randn(len(faces) * 3, 2, generator=gen, dtype=torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(lambda v, s, r: bound_gaussians(v, faces, 3, s, r, thickness=1e-6),
                                    (vertices.requires_grad_(), log_scales, rotation))


def test_hard_meshes():
    """A zero-area face and a face on a NaN vertex are not usable; the rest are; an empty mesh, or one whose
    faces all lack a plane, is a MeshError; the initial scales follow SuGaR's r x shortest edge."""
    vertices, faces = _two_components()
    vertices = torch.cat([vertices, torch.tensor([[9.0, 9.0, 9.0], [9.5, 9.0, 9.0], [float("nan"), 0.0, 0.0]],
                                                 dtype=torch.float64)])
    faces = torch.cat([faces, torch.tensor([[8, 9, 9], [8, 9, 10]])])  # collapsed; on a NaN vertex
    assert usable_faces(vertices, faces).tolist() == [True] * 6 + [False, False]
    with pytest.raises(MeshError, match="empty"):
        usable_faces(vertices, faces[:0])
    with pytest.raises(MeshError, match="has a plane"):
        usable_faces(vertices, faces[6:])
    scales = torch.exp(initial_log_scales(vertices, faces[:1], 6))
    v = vertices[faces[0]]
    shortest = min(float((v[i] - v[(i + 1) % 3]).norm()) for i in range(3))
    assert scales.shape == (6, 2) and torch.allclose(scales, torch.full((6, 2), shortest / (4 + 2 * math.sqrt(3)), dtype=torch.float64))


QUICK_REFINEMENT = ["--preset", "quick", "--threads", "1", "--set", "train.iterations=300", "--set", "method.refine_triangles=5000",
                    "--set", "method.hard_prune_opacity=0.05"]


@pytest.fixture(scope="module")
def quick_runs(tiny_spot, tmp_path_factory):
    """The records of sugar on a small scene with refinement ``short`` and ``decimated`` (the same coarse training:
    300 steps, one thread; the short refinement's 2 000 of SuGaR's 15 000 steps scaled to 40)."""
    before = torch.get_num_threads()
    records = {}
    for refinement in ("short", "decimated"):
        out = tmp_path_factory.mktemp(f"sugar-{refinement}")
        assert main(["run", "--method", "sugar", "--scene", str(tiny_spot), "--out", str(out), *QUICK_REFINEMENT,
                     "--set", f"method.refinement={refinement}"]) == 0
        records[refinement] = json.loads(next(out.rglob("record.json")).read_text())
    torch.set_num_threads(before)
    return records


def starting_mesh(record: dict) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) the refinement of ``record``'s run starts from, rebuilt from its trained coarse model the way
    the runner builds the second stage (`SuGaR.refinement_mesh`, `bound_mesh`)."""
    cfg = resolve_recorded(record["config"])
    given = scene_for_method(load_run_scene(cfg), "sugar")
    coarse = METHODS.get("sugar")()
    coarse.setup(given, cfg)
    coarse.load_state_dict(load_checkpoint(Path(record["mesh"]["path"]).parent / "checkpoint-final.pt")["method"])
    vertices, faces = bound_mesh(coarse.refinement_mesh(given, cfg))
    return vertices.double().numpy(), faces.numpy()


def same_mesh(written: trimesh.Trimesh, vertices: np.ndarray, faces: np.ndarray) -> bool:
    """``written`` (a mesh file, in `canonical_order`) is exactly ``vertices`` and ``faces``."""
    expected = canonical_order(trimesh.Trimesh(vertices, faces, process=False))
    return np.array_equal(np.asarray(written.vertices), expected.vertices) and np.array_equal(written.faces, expected.faces)


def test_a_quick_run_with_refinement_moves_the_vertices_of_the_mesh_it_starts_from(quick_runs):
    """sugar with refinement short: status ok; the record states the coarse mesh's size, the Gaussians bound and the
    refine stage's time; the evaluated mesh is the starting mesh's faces on the refinement's final vertices, and
    those vertices moved: nearly every one, by at least 1e-5 of the cameras' extent at the median (a vertex learning
    rate of 0 leaves them where they started)."""
    record = quick_runs["short"]
    second = record["inputs"]["second_stage"]
    assert record["status"] == "ok" and math.isfinite(record["metrics"]["chamfer"]) and record["timings"]["refine"] > 0
    assert second["refinement"] == "short" and second["steps"] == 40 and second["bound_gaussians"] == second["coarse_mesh"]["faces"]
    assert 0 < second["coarse_mesh"]["faces"] <= 2 * 5000  # foreground and background, each at most 5000
    refined = trimesh.load(record["mesh"]["path"], process=False)
    state = torch.load(Path(record["mesh"]["path"]).parent / "refine" / "checkpoint-final.pt", weights_only=False)
    final = state["method"]["params"]["vertices"].double().numpy()
    start, faces = starting_mesh(record)
    assert same_mesh(refined, final, faces)
    moved = np.linalg.norm(final - start, axis=1)
    extent = float(np.ptp(start, axis=0).max())
    assert (moved > 0).mean() > 0.9 and np.median(moved) > 1e-5 * extent, (
        f"the refinement left the coarse mesh's vertices in place: {(moved > 0).mean():.0%} moved, median "
        f"{np.median(moved):.3g} (extent {extent:.3g})")


def test_the_decimated_control_evaluates_the_mesh_the_refinement_starts_from(quick_runs):
    """refinement decimated: no second stage; its evaluated mesh is, vertex for vertex and face for face, the mesh the
    refinement starts from (the same coarse training), so it has the refined mesh's vertex and face counts."""
    control, refined = quick_runs["decimated"], quick_runs["short"]
    assert control["status"] == "ok" and "second_stage" not in control["inputs"] and "refine" not in control["timings"]
    assert control["run_id"] not in (refined["run_id"], resolve_run("sugar", refined["scene"], preset="quick").run_id)
    mesh = trimesh.load(control["mesh"]["path"], process=False)
    assert same_mesh(mesh, *starting_mesh(refined))
    assert (control["mesh"]["vertices"], control["mesh"]["faces"]) == (refined["mesh"]["vertices"], refined["mesh"]["faces"])


def test_a_refinement_over_the_budget_is_refused_before_training():
    """refine_triangles x Gaussians per triangle above train.max_gaussians: a ConfigError naming both numbers and
    the largest allowed count, from the config check (nothing trained); an unknown refinement too."""
    cfg = resolve_run("sugar", "synthetic/spot", preset="cpu", overrides=["method.refinement=long", "method.refine_triangles=60000",
                                                                         "method.refine_gaussians_per_triangle=6"])
    with pytest.raises(ConfigError, match=r"2 x 60000 triangles x 6 = 720000 Gaussians.*max_gaussians = 100000.*<= 8333"):
        METHODS.get("sugar").check_config(cfg)
    with pytest.raises(ConfigError, match="none, decimated, short, medium or long"):
        METHODS.get("sugar").check_config(resolve_run("sugar", "synthetic/spot", preset="cpu",
                                                      overrides=["method.refinement=forever"]))


def test_the_refinement_fields_are_shown_and_leave_coarse_runs_ids_unchanged():
    """Off, the refinement's fields are in the resolved config but not in the run id
    (`gsbench.config.run_config.ADDED_AFTER_RECORDS`), so a coarse-only run keeps the run id its committed records
    have (docs/results/dtu_framed: sugar on dtu-bunny, seed 0), as does their config, which lacks the fields; on,
    they are in it."""
    off = resolve_run("sugar", "synthetic/dtu-bunny", preset="cpu", overrides=["eval.evaluators=[dtu_chamfer, normal_similarity, surface_offset]"])
    assert off.method["refinement"] == "none" and off.run_id == "5e97394a19c0"
    later = ("refinement", "refine_gaussians_per_triangle", "refine_triangles")
    recorded = {**off.to_dict(), "method": {k: v for k, v in off.method.items() if k not in later}}
    assert run_id(recorded) == off.run_id
    on = resolve_run("sugar", "synthetic/dtu-bunny", preset="cpu", overrides=["method.refinement=short"])
    assert on.method["refinement"] == "short" and on.run_id != off.run_id


@pytest.mark.parametrize("suite", ["dtu", "tnt"])
def test_the_claims_sweeps_share_the_boards_sugar_runs_and_add_the_decimated_control(suite):
    """sugar_claims_<suite>: the coarse and refined rows are the <suite>_rig board's sugar and sugar-refined runs (the
    same run ids, so a runs folder holds them once), the decimated row the coarse config with refinement decimated;
    three seeds on one or two of the suite's scenes."""
    board = {(r.label, r.config.scene, r.config.seed): r.run_id for r in expand(load_sweep(sweep_file(f"{suite}_rig")))}
    claims = expand(load_sweep(sweep_file(f"sugar_claims_{suite}")))
    scenes = {r.config.scene for r in claims}
    assert 1 <= len(scenes) <= 2 and {r.config.seed for r in claims} == {0, 1, 2} and len(claims) == 3 * 3 * len(scenes)
    for run in claims:
        key = (run.label, run.config.scene, run.config.seed)
        if run.label == "sugar-decimated":
            coarse = next(r for r in claims if (r.label, r.config.scene, r.config.seed) == ("sugar", *key[1:]))
            assert run.config.to_dict() == {**coarse.config.to_dict(), "method": {**coarse.config.method, "refinement": "decimated"}}
        else:
            assert run.run_id == board[key]
