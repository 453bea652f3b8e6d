"""NeuSG's implicit side (methods/neusg_field.py, methods/neusg.py): the Eikonal term on exact SDFs, NeuS
weights on an exact plane against their closed form, marching cubes of an exact sphere, the hard cases, and a
quick run to ok."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
import torch
import trimesh

from gsbench.cli import main
from gsbench.data.camera import Camera
from gsbench.data.loader import load_scene
from gsbench.data.synthetic.rigs import look_at
from gsbench.errors import ConfigError
from gsbench.geometry.depth import world_rays
from gsbench.mesh import MeshError
from gsbench.methods.neusg import bound_by_cameras, sdf_mesh, sdf_region
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


# the hash grid with a level added every 2 steps from step 10 (16 iterations: 3 000 of 30 000 scale to 1.6), so the
# active levels change after the resume at step 8
HASH_FIELD = ["method.encoding=hash", "method.grid_levels=6", "method.grid_max_res=256", "method.hash_table_log2=12",
              "method.grid_level_step=3000"]


@pytest.mark.parametrize("field", [[], HASH_FIELD], ids=["dense", "hash"])
def test_resume_is_bit_identical_for_the_field_too(tiny_spot, tmp_path, monkeypatch, restore_threads, field):
    """16 steps straight vs 8 + crash + resume + 8, the cross terms active from step 1: Gaussians, the SDF's
    grids and networks, and their Adam moments all equal (the hash grid's active levels too)."""
    overrides = ["data.downscale=1", "train.iterations=16", "train.checkpoint_every=8", "threads=1",
                 "losses.sdf_points.start=0", "losses.sdf_align.start=0", "method.rays=32", *field]

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
    if field:
        assert int(resumed.method.field.sdf.grid.active) == 6  # every level by step 16, 4 at the resume
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


def _looking_at(eyes: np.ndarray, targets: np.ndarray) -> list[Camera]:
    cameras = []
    for eye, target in zip(eyes, targets):
        R, t = look_at(eye, target)
        cameras.append(Camera(K=np.diag([50.0, 50.0, 1.0]), R=R, t=t, width=64, height=48))
    return cameras


def test_the_cameras_region_is_neuralangelos_bound_by_pose_and_the_same_in_any_frame():
    """Twelve cameras on a ring 1.5 above p, all looking at p: every pair of axes meets at p, and each camera paired
    with itself gives its own centre (1/12 of the weight), so the centre is 1.5/12 above p. Cameras looking near p:
    the centre is Neuralangelo's mean over all ordered pairs of the least-squares midpoint of the two optical axes
    (its loop, np.linalg.lstsq per pair), and a shifted, scaled frame moves the sphere with it."""
    p = np.array([0.3, -0.2, 0.1])
    angles = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    ring = p + np.stack([2 * np.cos(angles), 2 * np.sin(angles), np.full(12, 1.5)], axis=1)
    centre, radius = bound_by_cameras(_looking_at(ring, np.tile(p, (12, 1))))
    assert np.allclose(centre, p + [0, 0, 1.5 / 12], atol=1e-9) and radius == pytest.approx(math.hypot(2, 1.5 * 11 / 12))

    rng = np.random.default_rng(0)
    eyes, targets = ring + rng.normal(0, 0.3, ring.shape), p + rng.normal(0, 0.2, (12, 3))
    cameras = _looking_at(eyes, targets)
    axes, total = [cam.R[2] for cam in cameras], np.zeros(3)
    for i, j in itertools.product(range(12), repeat=2):
        t_i, t_j = np.linalg.lstsq(np.stack([axes[i], -axes[j]], axis=1), eyes[j] - eyes[i], rcond=None)[0]
        total += 0.5 * (eyes[i] + t_i * axes[i] + eyes[j] + t_j * axes[j])
    centre, radius = bound_by_cameras(cameras)
    assert np.allclose(centre, total / 144, atol=1e-9) and not np.allclose(centre, p, atol=1e-3)
    assert radius == pytest.approx(np.linalg.norm(eyes - centre, axis=1).mean())
    moved_centre, moved_radius = bound_by_cameras(_looking_at(3 * eyes + 1.0, 3 * targets + 1.0))
    assert np.allclose(moved_centre, 3 * centre + 1.0, atol=1e-9) and moved_radius == pytest.approx(3 * radius)


def test_the_sfm_region_is_three_standard_deviations_and_a_scene_without_points_names_the_fix(tiny_spot):
    """sdf_region dispatches on method.sdf_region: ``sfm_points`` is the points' mean and 3 x their largest per-axis
    standard deviation (Neuralangelo's bound_by_points); a scene without SfM points is a ConfigError naming the
    other regions; ``cameras`` is `bound_by_cameras` of the scene's cameras; an unknown region is refused."""
    scene = load_scene(tiny_spot, load_images=False)
    assert scene.points is None
    with pytest.raises(ConfigError, match="has no SfM points.*fix: method.sdf_region=cameras or scene"):
        sdf_region(scene, "sfm_points")
    scene.points = np.random.default_rng(1).normal([1.0, 2.0, 3.0], [0.1, 0.4, 0.2], (5000, 3))
    centre, radius = sdf_region(scene, "sfm_points")
    assert np.allclose(centre, scene.points.mean(axis=0)) and radius == pytest.approx(3 * scene.points[:, 1].std())
    assert np.array_equal(sdf_region(scene, "cameras")[0], bound_by_cameras(scene.cameras)[0])
    assert np.array_equal(sdf_region(scene, "scene")[0], np.zeros(3)) and sdf_region(scene, "scene")[1] == scene.radius
    with pytest.raises(ConfigError, match="method.sdf_region must be one of"):
        sdf_region(scene, "gt_bounds")


def test_neusg_bounds_tnt_scenes_by_their_cameras_and_dtu_scenes_by_their_sphere():
    """The region is the dataset's (configs/methods/neusg.tnt.yaml); the removed GT bound is refused before a run."""
    assert resolve_run("neusg", "synthetic/tnt-rig-spot", preset="cpu").method["sdf_region"] == "cameras"
    assert resolve_run("neusg", "synthetic/spot", preset="cpu").method["sdf_region"] == "scene"
    with pytest.raises(ConfigError, match="method.sdf_region must be one of .*got 'gt_bounds'"):
        METHODS.get("neusg").check_config(resolve_run("neusg", "synthetic/tnt-rig-spot", overrides=["method.sdf_region=gt_bounds"]))
