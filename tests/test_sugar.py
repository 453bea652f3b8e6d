"""SuGaR (docs/methods/sugar.md): level-set sampling on analytic Gaussian fields, the Poisson
extractor, the density/sdf/normal regularisers, the schedule and hard prune, and a quick end-to-end run."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from gsbench.config.run_config import MeshConfig
from gsbench.data.loader import load_scene
from gsbench.data.synthetic.make import make_scene
from gsbench.errors import ConfigError, NumericalError
from gsbench.losses.terms import Batch, active_terms
from gsbench.mesh import MeshError
from gsbench.mesh.levelset import DensityField, auto_poisson_depth, level_crossings, levelset_mesh
from gsbench.methods import sugar_terms
from gsbench.raster.payload import quat_to_rotmat
from gsbench.raster.types import RasterGaussians, RasterSettings, RenderOutput
from gsbench.registry import METHODS
from gsbench.runs.runner import resolve_run, run
from gsbench.training.gaussians import Gaussians
from gsbench.training.trainer import Trainer, scaled_losses, scaled_strategy
from tests.raster_scenes import look_at_camera, make_camera

LEVEL = 0.3


def one_gaussian(mean, quat, scales, opacity, dtype=torch.float64) -> RasterGaussians:
    return RasterGaussians(means=torch.tensor([mean], dtype=dtype), quats=torch.tensor([quat], dtype=dtype),
                           scales=torch.tensor([scales], dtype=dtype), opacities=torch.tensor([opacity], dtype=dtype),
                           sh=torch.zeros(1, 1, 3, dtype=dtype))


# ---- level-set sampling on an analytic field ------------------------------------------------------


def test_level_crossings_lie_on_the_analytic_ellipsoid_with_its_normals():
    """One rotated anisotropic Gaussian: {d = level} is the ellipsoid (x−μ)ᵀΣ⁻¹(x−μ) = 2 ln(o/level)."""
    opacity = 0.9
    g = one_gaussian([0.2, -0.1, 0.4], [0.9, 0.2, -0.3, 0.1], [0.2, 0.1, 0.15], opacity)
    field = DensityField.of(g)
    mu = g.means
    R = quat_to_rotmat(torch.nn.functional.normalize(g.quats, dim=-1))[0]
    inv_cov = R @ torch.diag(g.scales[0] ** -2) @ R.T
    m_level = math.sqrt(2 * math.log(opacity / LEVEL))
    gen = torch.Generator().manual_seed(0)
    n = 1000
    cameras = mu + 3 * torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1)
    unit = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1)
    surface = mu + m_level * (unit * g.scales[0]) @ R.T  # points of the ellipsoid
    rays = torch.nn.functional.normalize(surface - cameras, dim=-1)
    outward = torch.nn.functional.normalize((surface - mu) @ inv_cov, dim=-1)
    facing = (outward * rays).sum(-1) < 0  # the ray enters the ellipsoid at `surface`
    sigma = ((rays @ R) * g.scales[0]).norm(dim=-1)  # σ_view along each ray
    jitter = (torch.rand(n, generator=gen, dtype=torch.float64) - 0.5) * sigma  # the hit is ±σ/2 off the surface
    hits, rays, surface, outward, sigma = (x[facing] for x in (surface + jitter[:, None] * rays, rays, surface,
                                                               outward, sigma))
    points, normals, kept = level_crossings(field, hits, rays, LEVEL)

    assert kept.float().mean() > 0.9 and len(points) == int(kept.sum())
    offset = points - mu
    m = ((offset @ inv_cov) * offset).sum(-1).sqrt()
    assert torch.allclose(m, torch.full_like(m, m_level), rtol=0.01)  # on the level set (linear interpolation)
    exact_normals = torch.nn.functional.normalize(offset @ inv_cov, dim=-1)  # −∇d/‖∇d‖ of one Gaussian
    assert torch.allclose(normals, exact_normals, atol=1e-10)
    head_on = (-(outward[kept] * rays[kept]).sum(-1)) > 0.5  # away from grazing, the crossing is the entry point
    error = (points - surface[kept]).norm(dim=-1) / sigma[kept]
    assert head_on.sum() > 200 and float(error[head_on].max()) < 0.03
    assert torch.allclose(normals[head_on], outward[kept][head_on], atol=0.03)


def test_rays_that_miss_start_inside_or_stay_below_are_dropped():
    """SuGaR keeps a ray only if its first sample is below the level and a later one above it."""
    g = one_gaussian([0.0, 0.0, 2.0], [1.0, 0.0, 0.0, 0.0], [0.1, 0.1, 0.1], 0.9)
    z = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand(2, 3)
    hits = torch.tensor([[0.5, 0.0, 2.0], [0.0, 0.0, 2.0]], dtype=torch.float64)  # a miss; the centre
    points, _, kept = level_crossings(DensityField.of(g), hits, z, LEVEL)
    assert kept.tolist() == [False, True]
    assert float(points[0, 2]) == pytest.approx(2.0 - 0.1 * math.sqrt(2 * math.log(0.9 / LEVEL)), abs=2e-3)
    # a small Gaussian inside a large one owns the hit point: its ±3σ window lies wholly above the level
    nested = one_gaussian([0.0, 0.0, 2.0], [1.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0], 0.9)
    small = one_gaussian([0.0, 0.0, 2.0], [1.0, 0.0, 0.0, 0.0], [0.01, 0.01, 0.01], 0.95)
    both = RasterGaussians(**{k: torch.cat([getattr(nested, k), getattr(small, k)]) for k in
                              ("means", "quats", "scales", "opacities", "sh")})
    assert not level_crossings(DensityField.of(both), hits[1:], z[1:], LEVEL)[2].any()
    faint = one_gaussian([0.0, 0.0, 2.0], [1.0, 0.0, 0.0, 0.0], [0.1, 0.1, 0.1], 0.2)  # never reaches the level
    assert not level_crossings(DensityField.of(faint), hits, z, LEVEL)[2].any()


@pytest.mark.parametrize("scale", [1.0, 1000.0])
def test_levelset_mesh_of_one_gaussian_is_its_level_sphere(scale):
    """Rendered from 10 views, one isotropic Gaussian meshes to the sphere of radius s·sqrt(2 ln(o/level)),
    in any unit (the scene scaled by 1000 gives the same mesh scaled by 1000)."""
    s, opacity = 0.3 * scale, 0.95
    g = one_gaussian([0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [s, s, s], opacity, dtype=torch.float32)
    dirs = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1], [1, 1, 1], [-1, -1, 1],
                     [1, -1, -1], [-1, 1, -1]], float)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    cameras = [look_at_camera(3 * scale * d, [0, 0, 0], width=40, height=40, fov_x_deg=40, up=(0.3, -1, 0.2))
               for d in dirs]
    mesh = levelset_mesh(g, cameras, RasterSettings(scene_radius=scale), MeshConfig(extractor="poisson", level=LEVEL),
                         kernel="ewa", depth_output="median_depth", centre=np.zeros(3), extent=3.3 * scale)
    radius = np.linalg.norm(mesh.vertices, axis=1)
    assert len(mesh.faces) > 500
    assert np.allclose(radius, s * math.sqrt(2 * math.log(opacity / LEVEL)), rtol=0.015)


def test_levelset_mesh_errors_name_the_problem():
    camera = look_at_camera([0.0, 0.0, -3.0], [0, 0, 0], width=24, height=24)
    cfg = MeshConfig(extractor="poisson", level=LEVEL)
    kwargs = dict(kernel="ewa", depth_output="median_depth", centre=np.zeros(3), extent=3.3)
    faint = one_gaussian([0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.3, 0.3, 0.3], 0.4, dtype=torch.float32)
    with pytest.raises(MeshError, match="no Gaussian to mesh"):
        levelset_mesh(faint, [camera], RasterSettings(), cfg, **kwargs)
    solid = one_gaussian([0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.3, 0.3, 0.3], 0.9, dtype=torch.float32)
    away = look_at_camera([0.0, 0.0, -3.0], [0, 0, -6], width=24, height=24)
    with pytest.raises(MeshError, match="empty mesh from 0 level-set points"):
        levelset_mesh(solid, [away], RasterSettings(), cfg, **kwargs)
    with pytest.raises(ConfigError, match="mesh.level must be in"):
        levelset_mesh(solid, [camera], RasterSettings(), MeshConfig(extractor="poisson", level=1.0), **kwargs)


def test_auto_poisson_depth_follows_the_pixel_footprint():
    box = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.2]])
    assert auto_poisson_depth(box, np.full(2, 1 / 100)) == 7  # ceil(log2(110))
    assert auto_poisson_depth(box * 1000, np.full(2, 10.0)) == 7  # unit-free
    assert auto_poisson_depth(box, np.full(2, 1e-4)) == 10  # capped at SuGaR's depth


# ---- the regularisers -----------------------------------------------------------------------------


def gaussians(means, log_scales, quats=None, opacities=None) -> Gaussians:
    n = len(means)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1) if quats is None else torch.as_tensor(quats)
    opacities = torch.full((n,), 0.8) if opacities is None else torch.as_tensor(opacities, dtype=torch.float32)
    return Gaussians(means=torch.as_tensor(means, dtype=torch.float32),
                     log_scales=torch.as_tensor(log_scales, dtype=torch.float32), quats=quats.float(),
                     opacity_logits=torch.logit(opacities), sh_dc=torch.zeros(n, 1, 3), sh_rest=torch.zeros(n, 0, 3),
                     max_sh_degree=0)


def field_at(g: Gaussians, points, source, knn) -> sugar_terms.SampleField:
    frames = sugar_terms.GaussianFrames.of(g)
    return sugar_terms.SampleField.at(frames, torch.tensor(points), torch.tensor(source), torch.tensor(knn))


@torch.no_grad()
def test_density_and_sdf_losses_by_hand():
    """Scales (1, 1, 0.1), normal z, o = 0.8; sample one smallest-scale std above the centre: m² = 1."""
    g = gaussians([[0.0, 0.0, 2.0]], [[0.0, 0.0, math.log(0.1)]])
    field = field_at(g, [[0.0, 0.0, 2.1]], [0], [[0]])
    d = 0.8 * math.exp(-0.5)
    assert float(field.contributions.sum()) == pytest.approx(d, rel=1e-6)
    assert float(field.beta()) == pytest.approx(0.1, rel=1e-6)
    assert float(sugar_terms.density_loss(field)) == pytest.approx(abs(d - math.exp(-0.5)), rel=1e-5)
    camera = make_camera(8, 8)  # at the origin looking down +z; D = 2 everywhere, so |f̂| = |2 − 2.1|
    depth = torch.full((8, 8), 2.0)
    sdf = 0.1 * math.sqrt(-2 * math.log(d))  # κ = 1/K = 1 with one neighbour
    loss = sugar_terms.sdf_loss(field, depth, camera, extent=1.0, near=0.2)
    assert float(loss) == pytest.approx(abs(sdf - 0.1) / 0.1, rel=1e-5)
    assert sugar_terms.sdf_loss(field, depth, camera, extent=1.0, near=2.5) is None  # behind the near plane


@torch.no_grad()
def test_normal_loss_by_hand():
    """x on g0's plane: g0 gets weight 0, so Σ ŵ_j n_j = n_1 and the loss is ‖n_0 − n_1‖² = 2 − 2 cos θ."""
    theta = 0.3
    tilt = [math.cos(theta / 2), 0.0, math.sin(theta / 2), 0.0]  # rotation by θ about y: normal (sin θ, 0, cos θ)
    g = gaussians([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]], [[0.0, 0.0, math.log(0.05)]] * 2,
                  quats=[[1.0, 0.0, 0.0, 0.0], tilt])
    field = field_at(g, [[0.05, 0.0, 0.0]], [0], [[0, 1]])
    assert float(sugar_terms.normal_loss(field, kappa=1.0)) == pytest.approx(2 - 2 * math.cos(theta), rel=1e-4)
    turned = [-tilt[2], 0.0, tilt[0], 0.0]  # by π + θ: normal −(sin θ, 0, cos θ), flipped back by the loss
    flipped = gaussians([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]], [[0.0, 0.0, math.log(0.05)]] * 2,
                        quats=[[1.0, 0.0, 0.0, 0.0], turned])
    flipped_field = field_at(flipped, [[0.05, 0.0, 0.0]], [0], [[0, 1]])
    assert float(sugar_terms.normal_loss(flipped_field, kappa=1.0)) == pytest.approx(2 - 2 * math.cos(theta), rel=1e-4)


def synthetic_render(n: int, height: int = 12, width: int = 16) -> RenderOutput:
    """Every Gaussian visible, a depth/alpha map that requires grad (the sdf mode reads them)."""
    return RenderOutput(visible=torch.ones(n, dtype=torch.bool),
                        depth=torch.full((height, width), 2.0, requires_grad=True),
                        alpha=torch.full((height, width), 0.9, requires_grad=True), width=width, height=height)


@pytest.mark.parametrize("mode", sugar_terms.MODES)
def test_terms_are_finite_for_degenerate_scales_and_coincident_neighbours(mode):
    torch.manual_seed(0)
    means = torch.tensor([[0.0, 0.0, 2.0]]).repeat(20, 1)  # coincident centres
    log_scales = torch.log(torch.tensor([[1e-12, 1e-12, 1e-12]] * 10 + [[0.1, 1e-12, 0.05]] * 10))
    g = gaussians(means, log_scales, quats=torch.randn(20, 4), opacities=torch.rand(20) * 0.98 + 0.01)
    out = synthetic_render(20)
    batch = Batch(torch.zeros(12, 16, 3), None, make_camera(16, 12), 0)
    terms = active_terms({"sugar_sdf": {"weight": 0.2}, "sugar_normal": {"weight": 0.2}}, 0,
                         {"sugar_sdf": {"mode": mode, "num_samples": 500, "near": 0.2},
                          "sugar_normal": {"mode": mode, "num_samples": 500}})
    assert terms[0].spec.requires == ({"depth", "alpha"} if mode == "sdf" else set())
    state = {"gaussians": g, "knn": sugar_terms.knn_indices(g.means)}
    values = [t.spec(out, batch, state) for t in terms]
    assert all(torch.isfinite(v) for v in values)
    assert state["sugar_samples"][2].points.shape == (500, 3)  # drawn once, shared by both terms
    sum(values).backward()
    grads = [p.grad for p in g.params.values()] + [out.depth.grad, out.alpha.grad]
    assert all(grad is None or torch.isfinite(grad).all() for grad in grads)
    assert g.params["means"].grad is not None


def test_terms_regularise_surfels_and_need_no_method_knn():
    """Two scales (a surfel) act as a zero third scale; without state['knn'] the kNN is computed."""
    torch.manual_seed(1)
    g = gaussians(torch.randn(30, 3) * 0.2 + torch.tensor([0.0, 0.0, 2.0]), torch.full((30, 2), -3.0),
                  quats=torch.randn(30, 4))
    value = sugar_terms.normal_term(synthetic_render(30), None, {"gaussians": g}, num_samples=200)
    value.backward()
    assert torch.isfinite(value) and torch.isfinite(g.params["quats"].grad).all()
    with pytest.raises(ConfigError, match="method.regularizer"):
        sugar_terms.sdf_term(synthetic_render(30), None, {"gaussians": g}, mode="depth")


# ---- method: schedule, hard prune, mesh hook --------------------------------------------------------

TINY = ["data.downscale=1", "method.random_init_points=300", "train.checkpoint_every=0"]


def setup_sugar(scene_dir, *overrides):
    cfg = resolve_run("sugar", str(scene_dir), preset="quick", overrides=[*TINY, *overrides])
    scene = load_scene(cfg.scene, downscale=cfg.data.downscale)
    m = METHODS.get("sugar")()
    m.setup(scene, cfg)
    return m, scene, cfg


def test_defaults_and_schedule_keep_sugars_proportions():
    cls = METHODS.get("sugar")
    info, p = cls.info(), cls.Config()
    assert (info.kernel, info.primitive) == ("ewa", "3d")
    assert (p.warmup_until, p.hard_prune_at, p.hard_prune_opacity, p.knn_k, p.knn_every) == (14000, 18000, 0.5, 16, 1000)
    warm_up = (p.refine_start, p.reset_every, p.position_lr_max_steps, p.sh_interval)
    assert p.regularizer == "density" and warm_up == (1000, 6000, 60000, 2000)  # 3DGS's, doubled
    cfg = resolve_run("sugar", "synthetic/spot", preset="paper")
    assert set(cfg.losses) == {"l1", "dssim", "opacity_entropy", "sugar_sdf", "sugar_normal"} and cfg.mesh.depth == "median"
    assert (cfg.mesh.extractor, cfg.mesh.level, cfg.mesh.poisson_density_quantile) == ("poisson", 0.3, 0.1)
    sugar = scaled_losses(cfg.losses, 15000 / 30000)  # SuGaR's own 15 000-step run
    assert sugar["opacity_entropy"] == {"weight": 0.1, "start": 7000, "end": 9000}
    assert sugar["sugar_sdf"] == {"weight": 0.2, "start": 9000, "end": -1} and sugar["sugar_normal"]["weight"] == 0.2


def test_strategy_densifies_during_the_warm_up_only(tiny_spot):
    m, _, _ = setup_sugar(tiny_spot)
    strategy = scaled_strategy(m.strategy(), 15000)
    schedule = (strategy.refine_start, strategy.refine_stop, strategy.refine_every, strategy.reset_every)
    assert schedule == (500, 7000, 100, 3000)  # SuGaR's 3DGS warm-up, stopped at 7000
    with pytest.raises(ConfigError, match="warmup_until <= method.hard_prune_at"):
        setup_sugar(tiny_spot, "method.warmup_until=20000")
    with pytest.raises(ConfigError, match="regularizer"):
        setup_sugar(tiny_spot, "method.regularizer=sdff")


def adam_step(m) -> None:
    m.optimizer.zero_grad()
    g = m.gaussians
    (g.means.square().sum() + g.scales.sum() + g.opacities.sum() + g.params["sh_dc"].square().sum()
     + g.params["sh_rest"].square().sum() + g.quats.sum()).backward()
    m.optimizer.step()


def test_hard_prune_keeps_optimizer_state_consistent(tiny_spot):
    m, _, cfg = setup_sugar(tiny_spot, "train.iterations=300")  # warm-up ends at 140, prune at 180
    scale = 300 / 30000
    m.update_schedules(139, scale)
    adam_step(m)
    assert len(m.optimizer.state) == 6
    m.update_schedules(140, scale)
    assert len(m.optimizer.state) == 0 and m.sh_degree == cfg.raster.sh_degree  # fresh Adam, full SH
    adam_step(m)
    logits = m.gaussians.params["opacity_logits"].data
    logits[:] = -2.0
    logits[::3] = 2.0  # a third above 0.5
    old = {name: m.optimizer.state[p]["exp_avg"].clone() for name, p in m.gaussians.params.items()}
    m.update_schedules(179, scale)
    assert len(m.gaussians) == 300 and m.knn is None
    m.update_schedules(180, scale)
    keep = torch.arange(300) % 3 == 0
    assert len(m.gaussians) == 100
    for group in m.optimizer.param_groups:
        param = m.gaussians.params[group["name"]]
        assert group["params"][0] is param
        assert torch.equal(m.optimizer.state[param]["exp_avg"], old[group["name"]][keep])
        assert m.optimizer.state[param]["exp_avg_sq"].shape == param.shape
    assert m.knn.shape == (100, 16) and torch.equal(m.knn[:, 0], torch.arange(100))
    adam_step(m)  # the pruned state steps
    state = m.state_dict()
    m.knn = None
    m.load_state_dict(state)
    assert m.knn.shape == (100, 16)
    m.gaussians.params["opacity_logits"].data[:] = -5.0
    with pytest.raises(NumericalError, match="hard prune"):
        m.hard_prune(180)


def test_term_params_and_the_tsdf_fallback(tiny_spot, tmp_path):
    m, scene, cfg = setup_sugar(tiny_spot, "method.regularizer=sdf", "method.num_samples=1234")
    params = m.term_params()
    assert params["sugar_sdf"] == {"mode": "sdf", "num_samples": 1234, "extent": m.extent,
                                   "near": pytest.approx(0.2 * scene.radius)}
    assert params["sugar_normal"] == {"mode": "sdf", "num_samples": 1234}
    tsdf, _, tsdf_cfg = setup_sugar(tiny_spot, "mesh.extractor=tsdf", "mesh.voxel_size=0.02", "mesh.sdf_trunc=0.08")
    tsdf.gaussians.params["opacity_logits"].data[:] = 4.0
    assert tsdf.extract_mesh(scene, tsdf_cfg, tmp_path / "tsdf.ply")["faces"] > 0
    with pytest.raises(ConfigError, match="supports mesh.extractor 'poisson' or 'tsdf', got 'tets'"):
        m.extract_mesh(scene, resolve_run("sugar", str(tiny_spot), preset="quick", overrides=["mesh.extractor=tets"]),
                       tmp_path / "x.ply")


def test_grazing_views_of_a_thin_sheet_train_without_nan_and_mesh(tmp_path_factory, restore_threads):
    """synthetic/thin-plate (as tests/test_methods_quick.py; the same scene folder), with the start opacity
    and no warm-up reset of `QUICK` below so that Gaussians survive the hard prune. Kilometre and
    millimetre units: `test_levelset_mesh_of_one_gaussian_is_its_level_sphere` (scenes load normalised)."""
    scene_dir = make_scene("synthetic/thin-plate", out=tmp_path_factory.getbasetemp() / "thin-plate-64x48",
                           res=(64, 48))
    m, scene, cfg = setup_sugar(scene_dir, "train.iterations=60", "method.random_init_points=1000",
                                "method.init_opacity=0.5", "method.reset_every=60000",
                                "method.num_samples=2000", "threads=1")
    run_dir = tmp_path_factory.mktemp("sugar-thin-plate")
    result = Trainer(m, scene, cfg, run_dir).fit()
    assert result.steps == 60 and result.num_gaussians > 0
    assert all(torch.isfinite(p).all() for p in m.gaussians.params.values())
    size = m.extract_mesh(scene, cfg, run_dir / "mesh.ply")
    mesh = trimesh.load(run_dir / "mesh.ply", process=False)
    assert size["faces"] == len(mesh.faces) > 0 and np.isfinite(mesh.vertices).all()


# ---- quick end-to-end run --------------------------------------------------------------------------

# 120 steps (warm-up to 56, entropy to 72, regularisers after) at 64x48 with 1000 Gaussians starting at
# opacity 0.5, so that some survive the hard prune in so short a run; no opacity reset in the warm-up.
QUICK = ["data.downscale=1", "method.random_init_points=1000", "method.init_opacity=0.5", "method.num_samples=2000",
         "method.reset_every=60000", "train.iterations=120", "train.checkpoint_every=0", "train.log_every=10",
         "eval.evaluators=[dtu_chamfer]", "threads=1"]


def test_quick_run_trains_meshes_evaluates_and_records(tiny_spot, tmp_path, restore_threads):
    cfg = resolve_run("sugar", str(tiny_spot), preset="quick", overrides=QUICK)
    cfg.out = str(tmp_path / "runs")
    record = run(cfg, echo=lambda *a: None)
    assert record.status == "ok" and record.method == "sugar" and 0 < record.num_gaussians < 1000
    assert all(math.isfinite(record.metrics[k]) for k in ("chamfer", "accuracy", "completeness"))
    assert record.mesh["faces"] > 0
    schedule = record.losses["schedule"]
    assert schedule["opacity_entropy"] == {"weight": 0.1, "start": 56, "end": 72}
    assert schedule["sugar_sdf"] == {"weight": 0.2, "start": 72, "end": -1}
    assert record.losses["params"]["sugar_sdf"]["num_samples"] == 2000
