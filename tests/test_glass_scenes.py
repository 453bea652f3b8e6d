"""Glass in the scene generator (gsbench/geometry/optics.py, gsbench/data/synthetic/render.py): Snell's law and the Fresnel
terms against their closed forms at a flat interface, total internal reflection, index 1 (no interface),
conservation of the ray tree's weights, the hard rays (grazing, trapped), and the glass built-ins."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from gsbench.data.camera import Camera
from gsbench.data.synthetic.builtin import BUILTIN_SCENES
from gsbench.data.synthetic.generator import GLASS_IOR, SPECS, plan_meta, plan_scene
from gsbench.data.synthetic.primitives import Surface, box, merge
from gsbench.data.synthetic.render import MAX_BOUNCES, Renderer
from gsbench.geometry.optics import fresnel, reflect, refract

N_GLASS = 1.5


def _direction(theta):
    """Unit direction travelling down (−z) at angle ``theta`` from the normal +z, in the xz plane."""
    return torch.tensor([[math.sin(theta), 0.0, -math.cos(theta)]], dtype=torch.float64)


UP = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)


def test_snell_refraction_and_mirror_reflection_at_a_flat_interface():
    """Air to glass at 0° to 80°: n₁ sin θ_i = n₂ sin θ_t, the refracted ray stays in the plane of incidence
    and is unit; the reflected ray mirrors z."""
    n = UP
    for degrees in (0.0, 20.0, 45.0, 80.0):
        theta = math.radians(degrees)
        d = _direction(theta)
        t, tir = refract(d, n, 1.0 / N_GLASS)
        assert not tir[0] and math.isclose(float(t.norm()), 1.0, rel_tol=1e-12)
        sin_t = math.hypot(float(t[0, 0]), float(t[0, 1]))
        assert math.isclose(N_GLASS * sin_t, math.sin(theta), abs_tol=1e-12) and t[0, 2] < 0 and t[0, 1] == 0
        assert torch.allclose(reflect(d, n), d * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64), atol=1e-15)


def test_fresnel_matches_its_closed_forms():
    """Normal incidence ((n₁ − n₂)/(n₁ + n₂))² = 0.04 both ways; at Brewster's angle arctan(n₂/n₁) the p
    part vanishes, R = R_s/2 with R_s = sin²(θ_i − θ_t)/sin²(θ_i + θ_t); 1 at grazing incidence; glass to air: below the critical angle arcsin(1/1.5) = 41.81° R < 1 and the
    ray refracts, above it R = 1 and it is totally reflected."""
    one = torch.tensor(1.0, dtype=torch.float64)
    assert math.isclose(float(fresnel(one, 1.0, N_GLASS)), 0.04, rel_tol=1e-12)
    assert math.isclose(float(fresnel(one, N_GLASS, 1.0)), 0.04, rel_tol=1e-12)
    brewster = math.atan(N_GLASS)
    theta_t = math.asin(math.sin(brewster) / N_GLASS)
    r_s = math.sin(brewster - theta_t) ** 2 / math.sin(brewster + theta_t) ** 2
    cosine = lambda angle: torch.tensor(math.cos(angle), dtype=torch.float64)  # noqa: E731
    assert math.isclose(float(fresnel(cosine(brewster), 1.0, N_GLASS)), r_s / 2, rel_tol=1e-12)
    assert float(fresnel(cosine(math.pi / 2) * 0, 1.0, N_GLASS)) == 1.0
    critical = math.asin(1.0 / N_GLASS)
    n = UP
    below, above = critical - 1e-3, critical + 1e-3
    assert float(fresnel(cosine(below), N_GLASS, 1.0)) < 1.0 and float(fresnel(cosine(above), N_GLASS, 1.0)) == 1.0
    assert not refract(_direction(below), n, N_GLASS)[1][0]
    t, tir = refract(_direction(above), n, N_GLASS)
    assert tir[0] and torch.all(t == 0)


def test_index_one_is_no_interface():
    """eta = 1: R = 0 at every angle (grazing too) and the ray goes straight on."""
    cosines = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    assert torch.all(fresnel(cosines, 1.0, 1.0) == 0.0)
    d = _direction(1.2)
    t, tir = refract(d, UP, 1.0)
    assert not tir[0] and torch.allclose(t, d, atol=1e-15)


def _ball_in_a_room(albedo=None, unlit=False):
    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    room_v, room_t = box((-3.0, -3.0, -2.0), (3.0, 3.0, 4.0), inward=True)
    v, t = merge([(np.asarray(ball.vertices), np.asarray(ball.faces)), (room_v, room_t)])
    parts = np.concatenate([np.zeros(len(ball.faces), int), np.ones(len(room_t), int)])

    def checker(points, ids, uvs):  # squares whose edges avoid the room's faces (x, y, z = ±3, −2, 4)
        c = (np.floor(points[:, 0] * 4 + 0.37) + np.floor(points[:, 1] * 4 + 0.21) + np.floor(points[:, 2] * 4 + 0.13)) % 2
        return np.stack([0.2 + 0.6 * c, 0.3 + 0.2 * c, 0.8 - 0.5 * c], axis=1)

    surface = Surface(vertices=v, triangles=t, albedo=albedo or checker, parts=parts,
                      unlit=np.concatenate([np.zeros(len(ball.faces), bool), np.full(len(room_t), unlit)]))
    room = Surface(vertices=room_v, triangles=room_t, albedo=albedo or checker, unlit=np.full(len(room_t), unlit))
    return surface, room


def _camera(width=64, height=48):
    K = np.array([[1.4 * width, 0.0, width / 2], [0.0, 1.4 * width, height / 2], [0.0, 0.0, 1.0]])
    R = np.diag([1.0, -1.0, -1.0])  # looking down −z from above the ball
    return Camera(K=K, R=R, t=-R @ np.array([0.05, 0.02, 2.5]), width=width, height=height, name="000000.png")


def test_a_ball_of_index_one_renders_the_room_unchanged():
    """Index 1: the ball vanishes, the image is exactly the room's (area-sampled, every pixel)."""
    surface, room = _ball_in_a_room()
    cam = _camera()
    seen = Renderer(surface, glass_ior=1.0).render(cam)
    assert seen.mask.sum() > 200  # the ball covers the middle of the view
    assert np.array_equal(seen.rgb, Renderer(room).render(cam).rgb)


def test_the_ray_tree_conserves_the_light():
    """A glass ball in a white unlit room: each pixel is the sum of its branches' weights, Fresnel R + T = 1
    at every split, so it is 1 up to the dropped branches (below 1e-3 each, and the bounce limit); never
    more. Measured at 64x48: median 0.9999, 1% quantile 0.998, the worst rim pixel 0.87 (grazing entry,
    light still circling at the bounce limit). A glass ball of index 1.5 changes the room's image (it is not transparent to the test)."""
    white = lambda points, ids, uvs: np.ones((len(points), 3))  # noqa: E731
    surface, _ = _ball_in_a_room(albedo=white, unlit=True)
    cam = _camera()
    view = Renderer(surface, glass_ior=GLASS_IOR).render(cam)
    assert view.rgb.max() <= 1.0 + 1e-6 and np.isfinite(view.rgb).all()
    inside = view.rgb[view.mask][:, 0]
    assert np.median(inside) > 0.995 and np.percentile(inside, 1) > 0.99 and inside.min() > 0.8
    checker_ball, room = _ball_in_a_room()
    assert np.abs(Renderer(checker_ball, glass_ior=GLASS_IOR).render(cam).rgb - Renderer(room).render(cam).rgb).max() > 0.3


def test_trapped_and_grazing_rays_are_defined():
    """A ray inside the ball beyond the critical angle is totally reflected round and round: it stops at
    the bounce limit, adding nothing (black), with no NaN; rays grazing the ball's silhouette stay finite."""
    surface, _ = _ball_in_a_room()
    renderer = Renderer(surface, glass_ior=GLASS_IOR)
    centre = np.array([0.0, 0.0, 0.0])
    start = centre + np.array([0.0, 0.45, 0.0])  # near the wall, heading along it: incidence ~64° > 41.8°
    d = np.array([[1.0, 0.0, 0.0]])
    out = renderer._trace(start[None], d, renderer.cast(start[None], d))
    assert np.all(out == 0.0)
    origin = np.array([[0.0, -0.5, 3.0]])
    for offset in (-1e-4, 0.0, 1e-4):  # tangent to the ball (radius 0.5) from above, just inside and outside
        ray = np.array([[0.0, offset, -1.0]])
        colour = renderer._trace(origin, ray, renderer.cast(origin, ray))
        assert np.isfinite(colour).all() and 0.0 <= colour.min() and colour.max() <= 1.0
    assert MAX_BOUNCES >= 4


@pytest.mark.parametrize("name", ["dtu-glass-orb", "dtu-glass-wine", "dtu-glass-bottle"])
def test_glass_built_ins_have_an_opaque_twin_and_record_their_glass(name):
    """Each glass built-in is listed with its opaque twin; the twin's spec is the same but opaque; the meta file
    records the index and the tracing limits."""
    glass, twin = SPECS[f"synthetic/{name}"], SPECS[f"synthetic/{name}-opaque"]
    assert glass.glass_ior == GLASS_IOR and twin.glass_ior is None
    assert {k: v for k, v in vars(glass).items() if k != "glass_ior"} == {k: v for k, v in vars(twin).items() if k != "glass_ior"}
    assert f"synthetic/{name}-opaque" in BUILTIN_SCENES
    meta = plan_meta(plan_scene(f"synthetic/{name}", res=(64, 48)))
    assert meta["glass"] == {"ior": GLASS_IOR, "max_bounces": MAX_BOUNCES, "min_weight": 1e-3}
    assert "glass" not in plan_meta(plan_scene(f"synthetic/{name}-opaque", res=(64, 48)))
