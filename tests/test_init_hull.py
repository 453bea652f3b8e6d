"""Random initialisation inside the masks' visual hull (methods/base.py, ``method.random_init_region``)."""

import dataclasses
import math

import numpy as np
import pytest
import torch

from gsbench.config.run_config import resolve
from gsbench.data.loader import load_scene
from gsbench.data.visual_hull import inside_visual_hull
from gsbench.errors import ConfigError, DataError
from gsbench.registry import METHODS
from gsbench.training.gaussians import Gaussians


def _cfg(method, scene_dir, *overrides):
    """The resolved run config (quick preset, 64x48) with the method plugin's Config, as `resolve_run` does."""
    return resolve(method, str(scene_dir), preset="quick", overrides=["data.downscale=1", *overrides],
                   method_config_cls=METHODS.get(method).Config)


@pytest.fixture(scope="module")
def spot_scene(tiny_spot):
    return load_scene(str(tiny_spot), downscale=1)


def _init(method, scene, cfg):
    m = METHODS.get(method)()
    m.setup(scene, cfg)
    return m.gaussians


def _candidates(n, radius, seed):
    """One batch drawn as `Gaussians.random_in_sphere` draws it: (points, colours)."""
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    points = direction * radius * rng.uniform(0, 1, size=(n, 1)) ** (1 / 3)
    return points, rng.uniform(0, 1, size=(n, 3))


def _training_hull(scene, points, dilate_px=1):
    views = scene.train_views
    return inside_visual_hull(points, [scene.cameras[i] for i in views], [scene.masks[i] for i in views],
                              dilate_px=dilate_px, min_views=1)


def _sphere_init(scene, cfg, n, dims):
    """The initialisation before the hull rule: random_in_sphere with the init opacity."""
    g = Gaussians.random_in_sphere(n, scene.sphere, dims=dims, max_sh_degree=cfg.raster.sh_degree, seed=cfg.seed)
    init = cfg.method["init_opacity"]
    g.params["opacity_logits"].data.fill_(math.log(init / (1 - init)))
    return g


def _same(a, b):
    return set(a.params) == set(b.params) and all(torch.equal(a.params[k], b.params[k]) for k in a.params)


@pytest.mark.parametrize("method", ["3dgs", "2dgs"])
def test_hull_init_is_inside_the_training_hull_at_the_sphere_density(method, tiny_spot, spot_scene):
    cfg = _cfg(method, tiny_spot, "method.random_init_points=20000", "train.max_gaussians=0")
    assert cfg.method["random_init_region"] == "visual_hull" and spot_scene.masks is not None
    assert spot_scene.points is None
    g = _init(method, spot_scene, cfg)
    means = g.params["means"].detach()
    assert _training_hull(spot_scene, means.double().numpy()).all()
    # exactly the sphere init's first batch of candidates that the hull keeps (position and colour)
    points, colors = _candidates(20000, spot_scene.sphere, cfg.seed)
    inside = _training_hull(spot_scene, points)
    assert len(g) == int(inside.sum()) < 20000 // 4
    assert torch.equal(means, torch.as_tensor(points[inside], dtype=torch.float32))
    sphere = _sphere_init(spot_scene, cfg, 20000, g.dims)
    assert torch.equal(g.params["sh_dc"], sphere.params["sh_dc"][torch.as_tensor(inside)])
    assert torch.equal(g.params["opacity_logits"], sphere.params["opacity_logits"][: len(g)])
    # the count is the hull's share of the ball: an independent estimate from other candidates agrees
    share = _training_hull(spot_scene, _candidates(20000, spot_scene.sphere, 12345)[0]).mean()
    assert len(g) / 20000 == pytest.approx(share, abs=0.015)


def test_floor_and_cap(tiny_spot, spot_scene):
    # 400 candidates leave ~60 in the hull, under the floor min(1000, 400): more batches fill it to 400
    cfg = _cfg("3dgs", tiny_spot, "method.random_init_points=400")
    g = _init("3dgs", spot_scene, cfg)
    assert len(g) == 400 and _training_hull(spot_scene, g.params["means"].detach().double().numpy()).all()
    # max_gaussians caps n (the batch size); the hull keeps its share of that
    cfg = _cfg("3dgs", tiny_spot, "method.random_init_points=100000", "train.max_gaussians=10000")
    g = _init("3dgs", spot_scene, cfg)
    assert 1000 <= len(g) == int(_training_hull(spot_scene, _candidates(10000, 1.0, cfg.seed)[0]).sum()) < 10000


def test_same_seed_same_init_other_seed_other_init(tiny_spot, spot_scene):
    a = _init("3dgs", spot_scene, _cfg("3dgs", tiny_spot, "method.random_init_points=20000"))
    b = _init("3dgs", spot_scene, _cfg("3dgs", tiny_spot, "method.random_init_points=20000"))
    c = _init("3dgs", spot_scene, _cfg("3dgs", tiny_spot, "method.random_init_points=20000", "seed=1"))
    assert _same(a, b)
    assert len(a) != len(c) or not torch.equal(a.params["means"], c.params["means"])


@pytest.mark.parametrize("method", ["3dgs", "2dgs"])
def test_sphere_region_is_the_old_init_bit_for_bit(method, tiny_spot, spot_scene):
    cfg = _cfg(method, tiny_spot, "method.random_init_points=3000", "method.random_init_region=sphere", "seed=3")
    g = _init(method, spot_scene, cfg)
    assert len(g) == 3000 and _same(g, _sphere_init(spot_scene, cfg, 3000, g.dims))


def test_scene_without_masks_falls_back_to_the_sphere(tiny_spot, spot_scene):
    cfg = _cfg("3dgs", tiny_spot, "method.random_init_points=3000")
    g = _init("3dgs", dataclasses.replace(spot_scene, masks=None), cfg)
    assert _same(g, _sphere_init(spot_scene, cfg, 3000, 3))


def test_unknown_region_is_a_config_error(tiny_spot, spot_scene):
    cfg = _cfg("3dgs", tiny_spot, "method.random_init_points=300", "method.random_init_region=box")
    with pytest.raises(ConfigError, match="random_init_region.*visual_hull, sphere.*'box'"):
        _init("3dgs", spot_scene, cfg)


def test_empty_hull_is_a_clear_error(tiny_spot, spot_scene):
    cfg = _cfg("3dgs", tiny_spot, "method.random_init_points=300")
    blank = dataclasses.replace(spot_scene, masks=[np.zeros_like(m) for m in spot_scene.masks])
    with pytest.raises(DataError, match="visual hull.*empty.*check the masks.*method.random_init_region=sphere"):
        _init("3dgs", blank, cfg)


def test_held_out_views_masks_are_not_used(tiny_spot, spot_scene):
    cfg = _cfg("3dgs", tiny_spot, "method.random_init_points=20000", "data.holdout_every=8")
    split_scene = dataclasses.replace(spot_scene, holdout_every=8)
    training, held = split_scene.train_views, split_scene.held_out_views
    assert held
    base = _init("3dgs", split_scene, cfg)

    def blanked(views, columns=slice(None)):
        masks = [m.copy() for m in spot_scene.masks]
        for i in views:
            masks[i][:, columns] = False
        return dataclasses.replace(split_scene, masks=masks)

    assert _same(_init("3dgs", blanked(held), cfg), base)
    # half of one training view's mask does carve the init (the check above is not vacuous)
    carved = _init("3dgs", blanked(training[:1], slice(0, 32)), cfg)
    assert 0 < len(carved) < len(base)


def test_measure_hull_share_of_100k(tiny_spot, spot_scene):
    """Measurement only: how many of the 100 000 sphere points the hull keeps on tiny_spot."""
    cfg = _cfg("3dgs", tiny_spot, "train.max_gaussians=0")
    g = _init("3dgs", spot_scene, cfg)
    print(f"\ntiny_spot 64x48: visual hull keeps {len(g)} of {cfg.method['random_init_points']} random points "
          f"({len(g) / cfg.method['random_init_points']:.1%})")
    assert 0 < len(g) < cfg.method["random_init_points"]
