"""Exact ellipse/tile overlap binning (ewa, rade, surfel): fewer tile pairs, bit-identical images and gradients.

``GSBENCH_EXACT_OVERLAP`` (`gsbench.switches.EXACT_OVERLAP`, default on) switches between the exact test and
the old binning (every tile of the Gaussian's bounding rectangle). A tile is dropped only if no pixel
centre in it can get alpha >= 1/255, so every output and gradient must be bit-identical (torch.equal).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))

from raster_scenes import concat, make_camera, random_gaussians, random_quats, single_gaussian, with_grad  # noqa: E402

from gsbench.raster import OUTPUTS, RasterSettings, rasterize  # noqa: E402
from gsbench.switches import EXACT_OVERLAP  # noqa: E402

PARAMS = ("means", "quats", "scales", "opacities", "sh")


def _render(g, cam, kernel, exact, outputs=OUTPUTS, settings=RasterSettings(), seed=0):
    """Outputs and gradients of one render with the exact overlap on (True), off (False) or as the environment
    says (None), and its tile pair and pair counts."""
    with pytest.MonkeyPatch.context() as env:
        if exact is not None:
            env.setenv(EXACT_OVERLAP.name, "on" if exact else "off")
        gg = with_grad(g)
        out = rasterize(gg, cam, kernel=kernel, outputs=outputs, settings=settings)
        gen = torch.Generator().manual_seed(seed)
        loss = 0.0
        res = {}
        for o in outputs:
            t = getattr(out, o)
            res[o] = t.detach().clone()
            w = torch.rand(t.shape, generator=gen, dtype=torch.float64).to(t.dtype)
            loss = loss + (t * w).sum()
        loss.backward()
        for p in PARAMS:
            res[f"grad_{p}"] = getattr(gg, p).grad.clone()
        res["grad_means2d"] = out.means2d.grad.clone()
        res["absgrad"] = out.extras["absgrad"].clone()
        return res, int(out.extras["tile_pairs"]), int(out.extras["pairs"])


def _assert_identical(kernel, g, cam, outputs=OUTPUTS, settings=RasterSettings()):
    a, pa, la = _render(g, cam, kernel, True, outputs, settings)
    b, pb, lb = _render(g, cam, kernel, False, outputs, settings)
    for k in b:
        assert a[k].dtype == b[k].dtype and torch.equal(a[k], b[k]), (
            f"{kernel}: {k} differs (max {float((a[k].double() - b[k].double()).abs().max())})"
        )
    assert pa <= pb, f"{kernel}: exact binning has more tile pairs ({pa} > {pb})"
    assert la <= lb
    return pa, pb


def thin_scene(n, seed, dtype, cam, kernel="ewa"):
    """Elongated, randomly rotated Gaussians (one long axis, two thin ones)."""
    g = random_gaussians(n, kernel, seed=seed, dtype=torch.float64, camera=cam, scale_range=(0.005, 0.02),
                         opacity_range=(0.2, 0.99))
    gen = torch.Generator().manual_seed(seed + 100)
    long = 0.15 + 0.5 * torch.rand(n, generator=gen, dtype=torch.float64)
    g.scales[:, 0] = long
    g.quats.copy_(random_quats(n, gen))
    f = lambda x: None if x is None else x.to(dtype)  # noqa: E731
    return type(g)(f(g.means), f(g.quats), f(g.scales), f(g.opacities), f(g.sh), f(g.filter3d))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("kernel", ["ewa", "rade", "surfel"])
def test_thin_rotated_identical_and_fewer_pairs(kernel, dtype):
    cam = make_camera(112, 80, fov_x_deg=50.0)
    g = thin_scene(150, 1, dtype, cam, kernel)
    pa, pb = _assert_identical(kernel, g, cam)
    print(f"{kernel} {dtype}: tile pairs exact {pa} vs rectangle {pb}")
    assert pa < 0.85 * pb


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("kernel", ["ewa", "rade", "surfel"])
def test_random_scenes_and_output_subsets(kernel, seed):
    cam = make_camera(70, 53, fov_x_deg=60.0)
    g = concat(
        random_gaussians(80, kernel, seed=seed, dtype=torch.float32, camera=cam, opacity_range=(0.05, 1.0)),
        thin_scene(60, seed + 7, torch.float32, cam, kernel),
    )
    for outs in (("rgb",), ("rgb", "alpha"), ("depth", "normal"), ("median_depth", "distortion"), OUTPUTS):
        _assert_identical(kernel, g, cam, outs)


@pytest.mark.parametrize("kernel", ["ewa", "rade"])
def test_settings_variants(kernel):
    cam = make_camera(64, 48)
    g = thin_scene(80, 3, torch.float32, cam, kernel)
    for st in (RasterSettings(eps2d=0.0), RasterSettings(eps2d=0.3, antialias2d=0.3), RasterSettings(eps2d=1.0),
               RasterSettings(detach_distortion_weights=True)):
        _assert_identical(kernel, g, cam, settings=st)


def test_surfel_filter_variants():
    """The surfel's contributing set is its 3D ellipse united with the low-pass disc (k = 2), or the ellipse
    alone (k = 0); a wide disc (k = 0.5) reaches tiles the ellipse does not."""
    cam = make_camera(64, 48)
    g = thin_scene(80, 3, torch.float32, cam, "surfel")
    for k in (0.0, 0.5, 2.0, 8.0):
        _assert_identical("surfel", g, cam, settings=RasterSettings(surfel_filter=k))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_surfels_near_the_camera_plane(dtype):
    """Long thin surfels 0.3-1.5 units from the camera, many reaching behind it: projected centres far off the
    image (a sentinel) and conics that are hyperbolas; each must keep every contribution."""
    cam = make_camera(96, 72)
    g = random_gaussians(120, "surfel", seed=11, dtype=torch.float64, camera=cam, depth_range=(0.3, 1.5),
                         scale_range=(0.003, 0.01), opacity_range=(0.1, 1.0))
    gen = torch.Generator().manual_seed(12)
    g.scales[:, 0] = 0.2 + 0.6 * torch.rand(120, generator=gen, dtype=torch.float64)
    g.quats.copy_(random_quats(120, gen))
    f = lambda x: None if x is None else x.to(dtype)  # noqa: E731
    g = type(g)(f(g.means), f(g.quats), f(g.scales), f(g.opacities), f(g.sh))
    settings = RasterSettings(near_plane=0.01)
    _assert_identical("surfel", g, cam, settings=settings)
    for i in range(0, 120, 3):
        sub = type(g)(*(getattr(g, p)[i:i + 1] for p in PARAMS))
        _assert_identical("surfel", sub, cam, ("rgb", "alpha"), settings=settings)
    # one found by a random search: its disc reaches behind the camera, so its projected centre is the far-away
    # sentinel of a crossing disc, and its conic written about that centre lost every digit (the whole splat
    # was dropped); about the ray's own origin it is exact
    crossing = single_gaussian((-0.31370750069618225, 0.27148959040641785, 1.4304492473602295), kernel="surfel",
                               scales=(0.615109920501709, 0.008506668731570244), opacity=0.23604248464107513,
                               quat=(-0.18410341441631317, 0.6360309720039368, 0.2786305546760559, -0.6956547498703003),
                               dtype=dtype)
    _assert_identical("surfel", crossing, make_camera(160, 120, fov_x_deg=2 * math.degrees(math.atan(80 / 176))),
                      ("rgb", "alpha"), settings=settings)


def test_raymax_keeps_the_rectangle():
    """raymax keeps the rectangle (same pairs either way), and the flag changes nothing."""
    cam = make_camera(48, 40)
    g = thin_scene(40, 4, torch.float32, cam, "raymax")
    pa, pb = _assert_identical("raymax", g, cam, ("rgb", "alpha", "depth"))
    assert pa == pb


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("kernel", ["ewa", "rade", "surfel"])
def test_hard_cases(kernel, dtype):
    cam = make_camera(80, 64)
    sc = (0.5, 0.02, 0.01)
    rot = (math.cos(0.4), 0.0, 0.0, math.sin(0.4))
    gs = [
        single_gaussian((0.05, 0.0, 0.21), kernel=kernel, scales=sc, quat=rot, opacity=0.8),  # straddles near
        single_gaussian((0.0, -0.05, 0.5), kernel=kernel, scales=(2.0, 0.01, 2.0), opacity=0.8),  # around the camera
        single_gaussian((0.1, 0.0, -1.0), kernel=kernel, scales=sc, opacity=0.8),  # behind
        single_gaussian((3.0, 0.2, 2.0), kernel=kernel, scales=(1.5, 0.01, 0.01), quat=rot, opacity=0.9),  # off-screen
        single_gaussian((-2.2, -1.5, 2.0), kernel=kernel, scales=(1.0, 0.01, 0.3), quat=rot, opacity=0.9),
        single_gaussian((0.0, 0.0, 2.0), kernel=kernel, scales=(1.0, 1e-8, 1e-8), quat=rot, opacity=0.9),  # needle
        single_gaussian((0.1, 0.1, 2.0), kernel=kernel, scales=(1e-8, 1e-8, 1e-8), opacity=0.9),  # point
        single_gaussian((-0.2, 0.1, 2.0), kernel=kernel, scales=(1e4, 1e-8, 1e4), quat=rot, opacity=0.9),  # sheet
        single_gaussian((0.3, -0.1, 3.0), kernel=kernel, scales=(0.8, 1e-6, 1e-3), quat=rot, opacity=1.0),
        single_gaussian((0.2, 0.2, 2.5), kernel=kernel, scales=(0.4, 0.001, 0.002), quat=rot, opacity=0.0039),
        single_gaussian((-0.3, 0.2, 2.5), kernel=kernel, scales=(0.4, 0.001, 0.002), quat=rot, opacity=0.004),
        single_gaussian((0.0, 0.3, 2.5), kernel=kernel, scales=(0.4, 0.001, 0.002), quat=rot, opacity=0.0),
    ]
    g = concat(*gs)
    gen = torch.Generator().manual_seed(5)
    g.quats[5:9] = random_quats(4, gen)
    f = lambda x: None if x is None else x.to(dtype)  # noqa: E731
    g = type(g)(f(g.means), f(g.quats), f(g.scales), f(g.opacities), f(g.sh))
    for st in (RasterSettings(), RasterSettings(eps2d=0.0)):
        a, _, _ = _render(g, cam, kernel, True, settings=st)
        assert all(bool(torch.isfinite(v).all()) for v in a.values())
        _assert_identical(kernel, g, cam, settings=st)
        # the Gaussians one at a time: each must keep every contribution
        for i in range(len(gs)):
            sub = type(g)(*(getattr(g, p)[i:i + 1] for p in PARAMS))
            _assert_identical(kernel, sub, cam, ("rgb", "alpha"), settings=st)


def test_elongated_scene_strictly_fewer_pairs_and_env_switch(monkeypatch):
    cam = make_camera(160, 120)
    g = thin_scene(300, 9, torch.float32, cam)
    _, pa, _ = _render(g, cam, "ewa", True, ("rgb",))
    _, pb, _ = _render(g, cam, "ewa", False, ("rgb",))
    assert pa < pb
    monkeypatch.setenv(EXACT_OVERLAP.name, "0")
    _, pc, _ = _render(g, cam, "ewa", None, ("rgb",))
    assert pc == pb
    monkeypatch.setenv(EXACT_OVERLAP.name, "1")
    _, pd, _ = _render(g, cam, "ewa", None, ("rgb",))
    assert pd == pa


def test_float32_float64_many_tiny_random_scenes():
    """Many small random scenes (isotropic and thin, varied opacity): identical and never more pairs."""
    cam = make_camera(50, 37, fov_x_deg=70.0)
    for seed in range(6):
        for dtype in (torch.float32, torch.float64):
            g = concat(
                random_gaussians(25, "ewa", seed=seed, dtype=dtype, camera=cam, scale_range=(0.01, 0.5),
                                 opacity_range=(0.003, 1.0), spread=1.3),
                thin_scene(25, seed + 50, dtype, cam),
            )
            for kernel in ("ewa", "rade"):
                _assert_identical(kernel, g, cam, ("rgb", "alpha", "distortion"))


@pytest.mark.parametrize("kernel", ["ewa", "rade"])
def test_tile_lists_are_depth_ordered_subsequences_at_any_thread_count(kernel):
    """Each exact tile list is the rectangle list with some entries removed (same order), whatever the threads."""
    cam = make_camera(96, 72)
    g = concat(thin_scene(200, 11, torch.float32, cam, kernel),
               random_gaussians(100, kernel, seed=12, dtype=torch.float32, camera=cam))

    def lists(exact, threads, outputs=("rgb",)):
        old_t = torch.get_num_threads()
        torch.set_num_threads(threads)
        try:
            with torch.no_grad(), pytest.MonkeyPatch.context() as env:
                env.setenv(EXACT_OVERLAP.name, "on" if exact else "off")
                out = rasterize(g, cam, kernel=kernel, outputs=outputs)
        finally:
            torch.set_num_threads(old_t)
        offsets, tile_list = out.extras["state"].bufs[2:4]
        assert int(offsets[-1]) == out.extras["tile_pairs"]
        return [tile_list[offsets[t]:offsets[t + 1]].tolist() for t in range(offsets.numel() - 1)]

    rect = lists(False, 2)
    ref = lists(True, 1)
    for threads in (2, 3):
        assert lists(True, threads) == ref
    assert sum(map(len, ref)) < sum(map(len, rect))
    for a, b in zip(ref, rect):
        it = iter(b)
        assert all(x in it for x in a)  # a is a subsequence of b
    # with distortion each non-empty tile keeps the rectangle list's first entry (the distortion shift)
    for a, b in zip(lists(True, 2, ("distortion",)), rect):
        assert (a[:1] == b[:1]) and all(x in iter(b) for x in a)
