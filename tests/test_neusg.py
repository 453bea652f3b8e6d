"""NeuSG's implicit side (methods/neusg_field.py, methods/neusg.py): the Eikonal term on exact SDFs, NeuS
weights on an exact plane against their closed form, marching cubes of an exact sphere, the hard cases, and a
quick run to ok."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
import trimesh

from gsbench.cli import main
from gsbench.data.camera import GroundTruth, Normalisation, Scene
from gsbench.data.loader import load_scene
from gsbench.data.tnt import gt_bounding_sphere
from gsbench.errors import DataError
from gsbench.geometry.depth import world_rays
from gsbench.mesh import MeshError
from gsbench.methods.neusg import sdf_mesh
from gsbench.methods.neusg_field import (
    ImplicitScene,
    MultiGrid,
    SDFField,
    importance_samples,
    neus_alpha,
    sphere_chord,
    transmittance_weights,
)
from gsbench.registry import METHODS
from gsbench.runs.runner import resolve_run
from gsbench.training.trainer import Trainer
from tests.method_setup import interrupt_at


def _field(radius=1.0):
    return SDFField(radius, MultiGrid(3, 32, 128, 2, seed=0))


def test_eikonal_is_zero_for_an_exact_sphere_sdf_and_positive_otherwise():
    """At initialisation f = |x| − R/2 exactly (the MLP's output layer is zero): the numerical gradient has unit
    norm up to its O(ε²) error; a field scaled by 2 is no distance function."""
    field = _field()
    gen = torch.Generator().manual_seed(0)
    points = torch.nn.functional.normalize(torch.randn(2000, 3, generator=gen), dim=-1) * (0.4 + 0.5 * torch.rand(2000, 1, generator=gen))
    sdf, grad, _ = field.with_gradient(points)
    assert torch.allclose(sdf, points.norm(dim=-1) - 0.5, atol=1e-6)
    eikonal = ((grad.norm(dim=-1) - 1) ** 2).mean()
    assert eikonal < 1e-4  # the 4-tap difference's O(ε |∇²f|) error at ε = 2/128, |x| >= 0.4 (measured 5.5e-5)
    assert torch.allclose(torch.nn.functional.normalize(grad, dim=-1), torch.nn.functional.normalize(points, dim=-1),
                          atol=0.05)  # the same O(ε / |x|) error in direction
    with torch.no_grad():
        field.out.bias[0] = 0.0
        field.out.weight[0].normal_(0, 0.5, generator=torch.Generator().manual_seed(1))
    _, grad, _ = field.with_gradient(points)
    assert ((grad.norm(dim=-1) - 1) ** 2).mean() > 100 * eikonal


def test_neus_weights_of_a_plane_peak_at_the_plane():
    """A ray hitting the plane z = 0 head on (f = z along it: f(t) = z₀ − t): NeuS's α from Φ_s gives
    weights w_i = Φ_s(f_i) − Φ_s(f_{i+1}) (the transmittance telescopes), whose sum is ≈ 1 and whose
    maximum sits at the sample just in front of the plane; the depth Σ w t is the plane's within a sample."""
    s = 64.0
    t = torch.linspace(0.0, 2.0, 401)
    sdf = 1.0 - t  # the plane at t = 1
    weights, rest = transmittance_weights(neus_alpha(sdf[None], s))
    cdf = torch.sigmoid(s * sdf)
    expected = torch.cat([cdf[:-1] - cdf[1:], torch.zeros(1)])
    assert torch.allclose(weights[0], expected, atol=1e-5)
    assert abs(float(t[weights[0].argmax()]) - 1.0) <= float(t[1] - t[0])
    assert abs(float((weights[0] * t).sum()) - 1.0) < 0.01 and float(rest) < 1e-3


def test_marching_cubes_of_an_exact_sphere_sdf_is_at_the_grid_floor():
    mesh, n = sdf_mesh(lambda x: x.norm(dim=-1) - 0.513, 1.0, 0.02)  # no zero exactly on a grid vertex
    vertices = np.asarray(mesh.vertices)
    assert n == 101 and len(mesh.triangles) > 1000
    spacing = 2.0 / (n - 1)
    assert np.abs(np.linalg.norm(vertices, axis=1) - 0.513).max() < 0.05 * spacing  # linear interpolation's error
    closed = trimesh.Trimesh(vertices, np.asarray(mesh.triangles), process=True)
    assert closed.is_watertight and closed.euler_number == 2  # one closed sphere
    normals = np.asarray(mesh.compute_triangle_normals().triangle_normals)
    centres = vertices[np.asarray(mesh.triangles)].mean(1)
    assert np.mean(np.sum(normals * centres, axis=1) > 0) > 0.99  # facing out


def test_empty_level_set_and_non_finite_sdf_are_mesh_errors():
    with pytest.raises(MeshError, match="no zero level set"):
        sdf_mesh(lambda x: x.norm(dim=-1) + 0.1, 1.0, 0.05)
    with pytest.raises(MeshError, match="no zero level set"):
        sdf_mesh(lambda x: -torch.ones(len(x)), 1.0, 0.05)
    with pytest.raises(MeshError, match="not finite"):
        sdf_mesh(lambda x: torch.where(x[:, 0] > 0.5, torch.nan, x.norm(dim=-1) - 0.3), 1.0, 0.05)


def test_rays_that_miss_or_start_far_and_a_flat_sdf_stay_finite():
    """Rays missing the sphere see the background only; cameras a thousand radii away; points far outside;
    an SDF whose gradient is zero: every output and every gradient finite."""
    scene = ImplicitScene(1.0, 0, levels=2, min_res=8, max_res=16, background_levels=2, background_max_res=16)
    origins = torch.tensor([[0.0, -3.0, 0.0], [0.0, -3.0, 0.0], [0.0, -1000.0, 0.0], [5.0, 5.0, 5.0]])
    directions = torch.nn.functional.normalize(torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0],
                                                             [1.0, 0.0, 0.0]]), dim=-1)
    near, far, hit = sphere_chord(origins, directions, 1.0)
    assert hit.tolist() == [True, False, True, False] and float(near[1]) == float(far[1]) == 0.0
    out = scene.render_rays(origins, directions, 8, 4, 4, torch.Generator().manual_seed(0))
    assert out.opacity[1] == 0 and out.opacity[3] == 0 and torch.isfinite(out.colour).all()
    loss = out.colour.sum() + ((out.gradients.norm(dim=-1) - 1) ** 2).mean()
    loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in scene.parameters() if p.grad is not None)
    far_points = torch.tensor([[1e6, 0.0, 0.0], [0.0, -1e4, 3.0]])
    assert torch.isfinite(scene.sdf(far_points)[0]).all() and torch.isfinite(scene.background(far_points, directions[:2])[0]).all()
    flat = torch.zeros(3, requires_grad=True)
    normal = torch.nn.functional.normalize(flat[None] * 0, dim=-1)  # an SDF gradient of zero
    (normal.sum() + (normal.norm(dim=-1) - 1).pow(2).sum()).backward()
    assert torch.isfinite(flat.grad).all()


def test_importance_samples_follow_the_weights():
    t = torch.linspace(0, 1, 11)[None]
    weights = torch.zeros(1, 11)
    weights[0, 6] = 1.0  # all mass in [0.6, 0.7]
    samples = importance_samples(t, weights, 200, torch.Generator().manual_seed(0))
    assert ((samples >= 0.6) & (samples <= 0.7)).float().mean() > 0.95


def test_quick_run_to_ok(tiny_spot, tmp_path, restore_threads):
    assert main(["run", "--method", "neusg", "--scene", str(tiny_spot), "--preset", "quick", "--out", str(tmp_path),
                 "--set", "train.iterations=200", "--set", "mesh.voxel_size=0.02"]) == 0
    record = json.loads(next(tmp_path.rglob("record.json")).read_text())
    assert record["status"] == "ok" and math.isfinite(record["metrics"]["chamfer"])
    assert set(record["losses"]["schedule"]) >= {"neus_rgb", "eikonal", "sdf_points", "sdf_align", "flatten"}
    assert record["mesh"]["sdf_grid"] > 1 and record["mesh"]["sdf_region"] == {"centre": [0.0, 0.0, 0.0], "radius": 1.0}


def test_resume_is_bit_identical_for_the_field_too(tiny_spot, tmp_path, monkeypatch, restore_threads):
    """16 steps straight vs 8 + crash + resume + 8, the cross terms active from step 1: Gaussians, the SDF's
    grids and networks, and their Adam moments all equal."""
    overrides = ["data.downscale=1", "train.iterations=16", "train.checkpoint_every=8", "threads=1",
                 "losses.sdf_points.start=0", "losses.sdf_align.start=0", "method.rays=32"]

    def trainer(run_dir):
        cfg = resolve_run("neusg", str(tiny_spot), preset="quick", overrides=overrides)
        scene = load_scene(cfg.scene, downscale=cfg.data.downscale)
        method = METHODS.get("neusg")()
        method.setup(scene, cfg)
        return Trainer(method, scene, cfg, run_dir)

    straight = trainer(tmp_path / "a")
    straight.fit()
    interrupted = trainer(tmp_path / "b")
    interrupt_at(interrupted, 9, monkeypatch)
    with pytest.raises(KeyboardInterrupt):
        interrupted.fit()
    monkeypatch.undo()
    resumed = trainer(tmp_path / "b")
    assert resumed.fit().resumed_from == 8
    for name, param in straight.method.field.state_dict().items():
        assert torch.equal(param, resumed.method.field.state_dict()[name]), name
    for name, param in straight.method.gaussians.params.items():
        assert torch.equal(param, resumed.method.gaussians.params[name]), name


def test_world_rays_of_chosen_pixels_are_those_of_the_whole_image(tiny_spot):
    """NeuSG casts rays through its sampled pixels only; they are the whole image's rays at those indices."""
    camera = load_scene(tiny_spot, load_images=False).cameras[3]
    pixels = np.array([0, 7, camera.width - 1, camera.width, camera.width * camera.height - 1])
    assert np.array_equal(world_rays(camera, pixels), world_rays(camera)[pixels])


def test_a_field_moved_to_its_region_renders_as_the_same_field_with_the_rays_moved():
    """The region's centre is a pure translation: a field about c renders rays o + c exactly as the field
    about 0 renders o (same seed, same samples)."""
    centre = (0.3, -0.2, 0.5)
    at_origin = ImplicitScene(0.5, 0, levels=2, min_res=8, max_res=16, background_levels=2, background_max_res=16)
    moved = ImplicitScene(0.5, 0, centre=centre, levels=2, min_res=8, max_res=16, background_levels=2,
                          background_max_res=16)
    origins = torch.tensor([[0.0, -2.0, 0.1], [0.2, 0.1, -2.0]])
    directions = torch.nn.functional.normalize(torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.1, 1.0]]), dim=-1)
    a = at_origin.render_rays(origins, directions, 8, 4, 4, torch.Generator().manual_seed(1))
    b = moved.render_rays(origins + torch.tensor(centre), directions, 8, 4, 4, torch.Generator().manual_seed(1))
    assert torch.allclose(a.colour, b.colour, atol=1e-5) and torch.allclose(a.depth, b.depth, atol=1e-5)
    assert float(a.opacity.detach().min()) > 0


def test_the_tnt_region_is_the_ground_truths_bounding_sphere_in_the_training_frame(tmp_path):
    """gt_bounding_sphere maps the GT points by the inverse alignment and the normalisation: a box of GT
    points under a known similarity comes back as its box's centre and 1.01 x half its diagonal; a scene
    without TnT ground truth is an error that names method.sdf_region."""
    rng = np.random.default_rng(0)
    box = rng.uniform([-1.0, -2.0, -0.5], [1.0, 2.0, 0.5], (5000, 3))
    box[:800:100] = np.array([[x, y, z] for x in (-1, 1) for y in (-2, 2) for z in (-0.5, 0.5)])  # corners, read
    angle = 0.7
    rot = np.array([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1]])
    trans = np.eye(4)
    trans[:3, :3], trans[:3, 3] = 2.0 * rot, [5.0, -1.0, 3.0]  # COLMAP -> GT
    colmap_points = box + np.array([0.5, 0.5, 0.5])
    gt_points = colmap_points @ trans[:3, :3].T + trans[:3, 3]
    trimesh.PointCloud(gt_points).export(tmp_path / "toy.ply")
    np.savetxt(tmp_path / "toy_trans.txt", trans)
    norm = Normalisation(scale=4.0, center=np.array([0.5, 0.5, 1.5]))
    scene = Scene(name="toy", fmt="tnt", root=tmp_path, cameras=[], images=[], normalisation=norm,
                  gt=GroundTruth(kind="tnt", root=tmp_path, name="toy"))
    centre, radius = gt_bounding_sphere(scene)
    assert np.allclose(centre, (np.array([0.5, 0.5, 0.5]) - norm.center) / 4.0, atol=1e-6)
    assert math.isclose(radius, 1.01 * math.sqrt(1 + 4 + 0.25) / 4.0, rel_tol=1e-6)
    with pytest.raises(DataError, match="method.sdf_region=scene"):
        gt_bounding_sphere(Scene(name="toy", fmt="tnt", root=tmp_path, cameras=[], images=[], gt_missing="toy.ply not found"))
