"""PGSR (docs/methods/pgsr.md): unbiased depth, plane homography, NCC, the loss terms, neighbours, the strategy,
exposure compensation, the declared configuration and a quick end-to-end run."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))

from method_setup import quick_run, setup_method, straight_and_resumed  # noqa: E402
from raster_scenes import concat, look_at_camera, make_camera, single_gaussian  # noqa: E402

from gsbench.config.files import reported_numbers  # noqa: E402
from gsbench.losses.terms import Batch, active_terms, required_outputs  # noqa: E402
from gsbench.methods import pgsr_terms as T  # noqa: E402
from gsbench.methods.multiview import MultiViewContext, neighbour_views  # noqa: E402
from gsbench.methods.pgsr import PGSR, PGSRStrategy  # noqa: E402
from gsbench.raster import RasterSettings, RenderOutput, rasterize, reference  # noqa: E402
from gsbench.registry import METHODS  # noqa: E402
from gsbench.runs.runner import resolve_run  # noqa: E402


def _plane_maps(camera, n_w, d_w, alpha=0.8, dtype=torch.float64):
    """Exact (plane_distance, normal) maps of the world plane n_w·X + d_w = 0 seen by ``camera``, scaled by
    ``alpha`` as the compositor's sums are, with the normal facing the camera."""
    R, t = np.asarray(camera.R), np.asarray(camera.t)
    n_c = R @ np.asarray(n_w, np.float64)
    d_c = float(d_w) - float(n_c @ t)
    if d_c < 0:
        n_c, d_c = -n_c, -d_c
    H, W = camera.height, camera.width
    normal = torch.tensor(alpha * n_c, dtype=dtype).expand(H, W, 3).clone()
    distance = torch.full((H, W), alpha * d_c, dtype=dtype)
    return distance, normal, n_c, d_c


# ---- geometry -----------------------------------------------------------------------------------------


def test_plane_homography_warps_a_plane_exactly():
    ref = look_at_camera((0.3, -0.2, -3.0), (0, 0, 0), 40, 30)
    nb = look_at_camera((1.0, 0.1, -2.8), (0.1, 0, 0), 36, 28)
    n_w, d_w = np.array([0.2, -0.1, -1.0]) / np.linalg.norm([0.2, -0.1, -1.0]), 0.4
    _, _, n_r, d_r = _plane_maps(ref, n_w, d_w)
    pix = T.pixel_centres(ref, torch.float64).reshape(-1, 2)
    rays = T.pixel_rays(ref, torch.float64).reshape(-1, 3)
    depth = d_r / -(rays @ torch.tensor(n_r))
    X_ref = depth[:, None] * rays
    R, t = T.relative_pose(ref, nb, torch.float64)
    X_nb = X_ref @ R.T + t
    K_nb = T.intrinsics(nb, torch.float64)
    expected = (X_nb @ K_nb.T)[:, :2] / X_nb[:, 2:]
    n = torch.tensor(n_r).expand(len(pix), 3)
    d = torch.full((len(pix),), d_r, dtype=torch.float64)
    ok = torch.ones(len(pix), dtype=torch.bool)
    H = T.plane_homography(n, d, ok, T.intrinsics(ref, torch.float64), K_nb, R, t)
    warped, w = T.apply_homography(H, pix)
    torch.testing.assert_close(warped, expected, rtol=0, atol=1e-9)
    torch.testing.assert_close(w * depth, X_nb[:, 2], rtol=1e-12, atol=1e-12)  # third coordinate = z_nb / depth
    # the same plane seen from the neighbour maps the points back: H_nr H_rn = identity on the plane
    n_nb = R @ torch.tensor(n_r)
    d_nb = d_r - float(n_nb @ t)
    R2, t2 = T.relative_pose(nb, ref, torch.float64)
    H_back = T.plane_homography(n_nb.expand(len(pix), 3), torch.full((len(pix),), d_nb, dtype=torch.float64), ok,
                                K_nb, T.intrinsics(ref, torch.float64), R2, t2)
    back, _ = T.apply_homography(H_back, warped)
    torch.testing.assert_close(back, pix, rtol=0, atol=1e-9)


def test_forward_backward_warp_of_an_exact_plane_has_zero_error():
    ref = look_at_camera((0.2, -0.3, -3.0), (0, 0, 0), 40, 30)
    nb = look_at_camera((0.8, -0.1, -2.9), (0, 0, 0), 40, 30)
    n_w = np.array([0.1, 0.3, -1.0]) / np.linalg.norm([0.1, 0.3, -1.0])
    D_r, N_r, *_ = _plane_maps(ref, n_w, 0.2, alpha=0.7)
    D_n, N_n, *_ = _plane_maps(nb, n_w, 0.2, alpha=0.4)  # other alpha: H depends on N/D only
    warp = T.warp_to_neighbour((D_r, N_r), ref, (D_n, N_n), nb, near=0.1, threshold=1.0)
    assert int(warp.valid.sum()) > 0.5 * D_r.numel()
    assert float(warp.error[warp.valid].max()) < 1e-6
    assert torch.equal(warp.mask, warp.valid) and torch.allclose(warp.weight[warp.mask], torch.ones(()).double())


def test_unbiased_depth_is_exact_for_coplanar_flat_gaussians():
    """Two flat Gaussians in one tilted plane: D/(−N·r̃) is the ray–plane depth, unlike the expected depth."""
    cam = make_camera(24, 18)
    angle = math.radians(35.0)
    quat = (math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0)  # rotation about x: the plane tilts in y
    normal = np.array([0.0, -math.sin(angle), math.cos(angle)])
    c1 = np.array([0.05, 0.0, 2.0])
    c2 = c1 + 0.25 * np.array([1.0, 0.0, 0.0]) + 0.2 * np.array([0.0, math.cos(angle), math.sin(angle)])
    g = concat(*(single_gaussian(tuple(c), quat=quat, scales=(0.25, 0.25, 1e-5), opacity=0.9) for c in (c1, c2)))
    for path in ("fast", "reference"):
        render = (rasterize if path == "fast" else reference.render)(
            g, cam, kernel="ewa", outputs=("plane_distance", "normal", "alpha", "depth"), settings=RasterSettings())
        depth, valid = T.unbiased_depth(render.plane_distance, render.normal, cam)
        rays = T.pixel_rays(cam, torch.float64)
        exact = float(normal @ c1) / (rays @ torch.tensor(normal))
        seen = valid & (render.alpha > 0.05)
        assert int(seen.sum()) > 40
        torch.testing.assert_close(depth[seen], exact[seen], rtol=1e-9, atol=1e-9)
        assert float((render.depth[seen] - exact[seen]).abs().max()) > 1e-2  # the expected depth is biased


def test_unbiased_depth_drops_grazing_and_empty_pixels_with_finite_gradients():
    cam = make_camera(8, 6)
    rays = T.pixel_rays(cam, torch.float64)
    normal = torch.zeros(6, 8, 3, dtype=torch.float64)
    normal[..., 2] = -0.5  # facing the camera
    normal[:2] = torch.linalg.cross(rays[:2], torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64).expand(2, 8, 3))
    normal[2, :2] = 0.0  # nothing rendered
    normal = normal.requires_grad_(True)
    distance = torch.full((6, 8), 0.3, dtype=torch.float64, requires_grad=True)
    depth, valid = T.unbiased_depth(distance, normal, cam)
    assert not bool(valid[:2].any()) and not bool(valid[2, :2].any()) and bool(valid[3:].all())
    assert bool((depth[~valid] == 0).all())
    depth.sum().backward()
    assert bool(torch.isfinite(normal.grad).all()) and bool(torch.isfinite(distance.grad).all())


def test_ncc_of_identical_patches_is_one():
    gen = torch.Generator().manual_seed(0)
    patch = torch.rand(5, 49, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(T.patch_ncc(patch, patch), torch.ones(5, dtype=torch.float64))
    torch.testing.assert_close(T.patch_ncc(patch, 2.5 * patch + 0.3), torch.ones(5, dtype=torch.float64))
    torch.testing.assert_close(T.patch_ncc(patch, 1.0 - patch), -torch.ones(5, dtype=torch.float64))
    assert float(T.ncc_cost(patch, patch).max()) < 1e-6
    flat = torch.full((3, 49), 0.5, dtype=torch.float64, requires_grad=True)
    other = torch.rand(3, 49, generator=gen, dtype=torch.float64, requires_grad=True)
    assert bool((T.patch_ncc(flat, other) == 0).all())
    cost = T.ncc_cost(flat, other)
    torch.testing.assert_close(cost, torch.ones(3, dtype=torch.float64))  # textureless: cost 1, left out (< 0.9)
    cost.sum().backward()
    assert bool(torch.isfinite(flat.grad).all()) and bool(torch.isfinite(other.grad).all())


def test_patch_offsets_are_7x7():
    off = T.patch_offsets(3)
    assert off.shape == (49, 2) and float(off.abs().max()) == 3 and bool((off.sum(0) == 0).all())


# ---- loss terms on synthetic maps ----------------------------------------------------------------------


def _term_inputs(grazing: bool, textureless: bool):
    ref = look_at_camera((0.2, -0.3, -3.0), (0, 0, 0), 32, 24)
    nb = look_at_camera((0.7, -0.1, -2.9), (0, 0, 0), 32, 24)
    n_w = np.array([0.1, 0.3, -1.0]) / np.linalg.norm([0.1, 0.3, -1.0])
    D_r, N_r, *_ = _plane_maps(ref, n_w, 0.2, alpha=0.7, dtype=torch.float32)
    D_n, N_n, *_ = _plane_maps(nb, n_w, 0.2, alpha=0.7, dtype=torch.float32)
    if grazing:  # the top rows see their plane edge-on
        rays = T.pixel_rays(ref, torch.float32)
        N_r[:8] = 0.7 * torch.nn.functional.normalize(torch.linalg.cross(rays[:8], torch.ones_like(rays[:8])), dim=-1)
    gen = torch.Generator().manual_seed(1)
    image = torch.full((24, 32, 3), 0.5) if textureless else torch.rand(24, 32, 3, generator=gen)
    leaves = [x.clone().requires_grad_(True) for x in (D_r, N_r, D_n, N_n)]
    render = RenderOutput(plane_distance=leaves[0], normal=leaves[1], alpha=torch.full((24, 32), 0.7), width=32,
                          height=24, rgb=image.clone().requires_grad_(True))
    warp = T.warp_to_neighbour((leaves[0], leaves[1]), ref, (leaves[2], leaves[3]), nb, near=0.1, threshold=1.0)
    gray_ref = T.gray(image)
    gray_nb = T.gray(torch.full((24, 32, 3), 0.5) if textureless else torch.rand(24, 32, 3, generator=gen))
    ctx = MultiViewContext(warp=warp, ncc_index=torch.nonzero(warp.mask).flatten(), ref_gray=gray_ref,
                           nb_gray=gray_nb, patch_half=3)
    state = {"pgsr_multiview": lambda r, b: ctx}
    return render, Batch(image, None, ref, 7000), state, leaves


@pytest.mark.parametrize("grazing,textureless", [(False, False), (True, False), (False, True), (True, True)])
def test_terms_have_finite_gradients_at_grazing_views_and_on_textureless_patches(grazing, textureless):
    render, batch, state, leaves = _term_inputs(grazing, textureless)
    total = 0.0
    for fn in (T.pgsr_normal_term, T.pgsr_geo_term, T.pgsr_ncc_term):
        value = fn(render, batch, state)
        assert bool(torch.isfinite(value)), fn.__name__
        total = total + value
    total.backward()
    for leaf in leaves:
        assert leaf.grad is None or bool(torch.isfinite(leaf.grad).all())
    if textureless:  # every patch is constant: no photometric pixel, no gradient through the NCC
        assert float(T.pgsr_ncc_term(render, batch, state).detach()) == 0.0


def test_geo_term_is_zero_on_a_consistent_plane():
    render, batch, state, _ = _term_inputs(False, False)
    assert float(T.pgsr_geo_term(render, batch, state).detach()) < 1e-4


def test_image_gradient_weight_matches_pgsr_definition():
    img = torch.zeros(6, 7, 3)
    img[:, 4:] = 1.0  # a vertical edge between columns 3 and 4
    w = T.image_gradient_weight(img)
    assert bool((w[0] == 0).all()) and bool((w[:, -1] == 0).all())  # border weight 0
    assert float(w[2, 3]) == 0.0 and float(w[2, 4]) == 0.0  # the strongest gradient gets weight 0
    assert float(w[2, 1]) == 1.0  # flat interior gets 1


def test_min_scale_term_averages_the_visible_gaussians():
    class G:
        scales = torch.tensor([[0.1, 0.2, 0.3], [0.5, 0.05, 0.6], [0.9, 0.9, 0.01]], requires_grad=True)

    render = RenderOutput(visible=torch.tensor([True, True, False]))
    value = T.min_scale_term(render, None, {"gaussians": G})
    assert float(value.detach()) == pytest.approx(0.075)
    render.visible = torch.zeros(3, dtype=torch.bool)
    assert float(T.min_scale_term(render, None, {"gaussians": G}).detach()) == 0.0


def test_l1_exposure_applies_the_affine_model_only_when_asked():
    gen = torch.Generator().manual_seed(2)
    gt = torch.rand(16, 16, 3, generator=gen)
    rgb = (0.8 * gt + 0.05).requires_grad_(True)
    render = RenderOutput(rgb=rgb)
    batch = Batch(gt, None, make_camera(16, 16), 10)
    plain = T.l1_exposure_term(render, batch, {})
    assert float(plain.detach()) == pytest.approx(float((rgb - gt).abs().mean().detach()))
    a, b = torch.tensor(math.log(1 / 0.8), requires_grad=True), torch.tensor(-0.05 / 0.8, requires_grad=True)
    corrected = T.l1_exposure_term(render, batch, {"exposure": lambda _: (a, b)})
    assert float(corrected.detach()) < 1e-6
    corrected.backward()
    assert a.grad is not None and b.grad is not None


# ---- method -------------------------------------------------------------------------------------------


def test_neighbours_follow_pgsr_selection():
    cams = [look_at_camera((3 * math.cos(math.radians(a)), 0.0, 3 * math.sin(math.radians(a))), (0, 0, 0))
            for a in range(0, 360, 10)]
    nb = neighbour_views(cams, range(len(cams)), 8, 30.0, 0.01, 1.5)
    assert set(nb[0][:2]) == {1, 35} and set(nb[0][2:]) == {2, 34}  # ±10° (0.52 apart), then ±20°; 30° is out
    assert sorted(nb[5]) == [3, 4, 6, 7]
    assert neighbour_views(cams, [0, 18], 8, 30.0, 0.01, 1.5) == {0: [], 18: []}


def test_declared_info_matches_the_configs_and_papers():
    pgsr = METHODS.get("pgsr")
    assert pgsr is PGSR and (pgsr.info().kernel, pgsr.info().primitive) == ("ewa", "3d")
    cfg = resolve_run("pgsr", "synthetic/spot", preset="paper")
    assert set(cfg.losses) == {"l1_exposure", "dssim", "min_scale", "pgsr_normal", "pgsr_geo", "pgsr_ncc"}
    assert cfg.mesh.depth == "unbiased"
    assert cfg.losses["pgsr_normal"] == {"weight": 0.015, "start": 7000, "end": -1}
    assert cfg.losses["pgsr_geo"] == {"weight": 0.03, "start": 7000, "end": -1}
    assert cfg.losses["pgsr_ncc"] == {"weight": 0.15, "start": 7000, "end": -1}
    assert cfg.losses["min_scale"]["weight"] == 100.0 and cfg.losses["l1_exposure"]["weight"] == 0.8
    assert cfg.method["exposure_compensation"] is False  # DTU layer: PGSR's DTU script trains without it
    assert (cfg.mesh.sdf_trunc, cfg.mesh.depth_trunc, cfg.mesh.num_clusters) == (0.016, 5.0, 1)
    tnt = resolve_run("pgsr", "synthetic/spot-tnt", preset="paper")
    assert tnt.method["exposure_compensation"] is True and tnt.method["tsdf_max_view_angle"] == 80.0
    assert (tnt.method["abs_grad_threshold"], tnt.method["prune_opacity"]) == (0.00015, 0.05)
    p = pgsr.Config()
    assert (p.percent_dense, p.abs_grad_threshold, p.multi_view_patch_half, p.multi_view_num) == (0.001, 0.0008, 3, 8)
    assert p.exposure_compensation is True
    reported = reported_numbers("pgsr")
    assert reported["dtu"]["mean"] == 0.53 and reported["tnt"]["mean"] == 0.50
    scenes = reported["dtu"]["scenes"]
    assert len(scenes) == 15 and abs(sum(scenes.values()) / 15 - 0.53) < 0.005
    assert abs(sum(reported["tnt"]["scenes"].values()) / 6 - 0.50) < 0.005


def test_requested_outputs_follow_the_schedule(tiny_spot):
    m, scene, cfg = setup_method("pgsr", tiny_spot)
    early = required_outputs(active_terms(cfg.losses, 1, m.term_params()))
    late = required_outputs(active_terms(cfg.losses, 7000, m.term_params()))
    assert early == {"rgb"} and late == {"rgb", "alpha", "normal", "plane_distance"}
    with pytest.raises(Exception, match="exposure_compensation"):
        setup_method("pgsr", tiny_spot, "train.optimizer=visible_adam", "method.exposure_compensation=true")


def test_strategy_splits_by_the_abs_gradient():
    s = PGSRStrategy(grad_threshold=1.0, abs_grad_threshold=0.1, abs_split_radius=20.0, percent_dense=0.01)
    state = s.init_state(4)
    state["count"][:] = 1
    state["absgrad"][:] = torch.tensor([0.5, 0.5, 0.5, 0.01])
    state["radii"][:] = torch.tensor([30.0, 10.0, 30.0, 30.0])
    state["_big"] = torch.tensor([True, True, False, True])
    selected, _ = s._select(state)
    assert selected.tolist() == [True, False, False, False]


def test_exposure_is_learned_and_resumes_exactly(tiny_spot, tmp_path, monkeypatch):
    overrides = ("train.iterations=40", "train.checkpoint_every=20", "method.exposure_compensation=true",
                 "method.exposure_from=3000")
    straight, resumed = straight_and_resumed("pgsr", tiny_spot, tmp_path, monkeypatch, *overrides, crash_after=25)
    a, b = straight.method, resumed.method
    assert float(a.exposure.detach().abs().sum()) > 0
    assert torch.equal(a.exposure.detach(), b.exposure.detach())
    for k, v in a.gaussians.params.items():
        assert torch.equal(v, b.gaussians.params[k]), k
    assert "exposure" in {g["name"] for g in a.optimizer.param_groups}


def test_quick_end_to_end_run(tiny_spot, tmp_path):
    record = quick_run("pgsr", tiny_spot, tmp_path)
    assert record.timings["train.multiview"] > 0
