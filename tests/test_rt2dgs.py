"""RT2DGS (methods/rt2dgs.py): the differentiable optics in float64, the traced interface against the generator's
ray-traced glass ball with surfels on the exact surfaces, index 1 (the interface vanishes), and a quick run."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
import trimesh

from gsbench.cli import main
from gsbench.data.camera import Camera
from gsbench.data.synthetic.make import make_scene
from gsbench.data.synthetic.primitives import Surface, box, merge
from gsbench.data.synthetic.render import Renderer
from gsbench.geometry.optics import fresnel, refract
from gsbench.methods import rt2dgs
from gsbench.methods.gs2d import GS2D
from gsbench.methods.rt2dgs import RT2DGS, surface_light, trace_interface
from gsbench.raster.types import RasterGaussians
from gsbench.runs.finished_run import load_finished_run
from gsbench.training.trainer import Trainer, schedule_scale
from tests.method_setup import setup_method, straight_and_resumed

BALL = 0.5
WALLS = [((-3, -3, -2), (3, 3, -2)), ((-3, -3, 4), (3, 3, 4)), ((-3, -3, -2), (-3, 3, 4)), ((3, -3, -2), (3, 3, 4)),
         ((-3, -3, -2), (3, -3, 4)), ((-3, 3, -2), (3, 3, 4))]  # floor, ceiling, x−, x+, y−, y+ (lo, hi corners)
WALL_COLOURS = np.array([[0.8, 0.3, 0.2], [0.2, 0.7, 0.3], [0.2, 0.3, 0.9], [0.9, 0.8, 0.2], [0.6, 0.2, 0.7],
                         [0.3, 0.8, 0.8]])


def test_optics_gradients_match_finite_differences():
    """gradcheck of Snell's refracted direction and the Fresnel reflectance w.r.t. direction, normal and index,
    away from the critical angle."""
    d = torch.nn.functional.normalize(torch.tensor([[0.3, 0.1, -1.0], [0.5, -0.2, -0.8]], dtype=torch.float64), dim=-1)
    n = torch.nn.functional.normalize(torch.tensor([[0.05, 0.0, 1.0], [0.0, 0.1, 1.0]], dtype=torch.float64), dim=-1)
    eta = torch.tensor(1 / 1.5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b, e: refract(a, b, e)[0], (d.requires_grad_(), n.requires_grad_(), eta))
    cos = torch.tensor([0.2, 0.6, 0.95], dtype=torch.float64, requires_grad=True)
    ior = torch.tensor(1.5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c, k: fresnel(c, 1.0, k), (cos, ior))
    assert torch.autograd.gradcheck(lambda c, k: fresnel(c * 0.6, k, 1.0), (cos, ior))  # inside, below critical


def _fibonacci_sphere(count: int) -> np.ndarray:
    k = np.arange(count) + 0.5
    z = 1 - 2 * k / count
    phi = math.pi * (3 - math.sqrt(5)) * k
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def _quat_from_normals(normals: np.ndarray) -> np.ndarray:
    """(w, x, y, z) rotating +z onto each unit normal."""
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, normals)
    w = 1.0 + normals @ z
    q = np.concatenate([w[:, None], axis], 1)
    flip = w < 1e-9  # normal = −z: rotate by π about x
    q[flip] = [0.0, 1.0, 0.0, 0.0]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _surfel_scene():
    """Surfels on the exact ball (τ = 1) and tiling the six walls (τ = 0, each wall's colour)."""
    normals = _fibonacci_sphere(6000)
    spacing = math.sqrt(4 * math.pi * BALL**2 / len(normals))
    means, quats, scales, colours, tau = [BALL * normals], [_quat_from_normals(normals)], [np.full((len(normals), 2), spacing)], \
        [np.zeros((len(normals), 3))], [np.ones(len(normals))]
    for (lo, hi), colour in zip(WALLS, WALL_COLOURS):
        lo, hi = np.array(lo, float), np.array(hi, float)
        flat = int(np.argmin(hi - lo))
        axes = [a for a in range(3) if a != flat]
        step = 0.1
        u, v = np.meshgrid(np.arange(lo[axes[0]] + step / 2, hi[axes[0]], step), np.arange(lo[axes[1]] + step / 2, hi[axes[1]], step))
        pts = np.zeros((u.size, 3))
        pts[:, axes[0]], pts[:, axes[1]], pts[:, flat] = u.ravel(), v.ravel(), lo[flat]
        normal = np.zeros((len(pts), 3))
        normal[:, flat] = 1.0
        means.append(pts), quats.append(_quat_from_normals(normal)), scales.append(np.full((len(pts), 2), step))
        colours.append(np.tile(colour, (len(pts), 1))), tau.append(np.zeros(len(pts)))
    as_t = lambda x: torch.from_numpy(np.concatenate(x)).double()  # noqa: E731
    n = sum(len(m) for m in means)
    g = RasterGaussians(means=as_t(means), quats=as_t(quats), scales=as_t(scales), opacities=torch.full((n,), 0.99, dtype=torch.float64),
                        sh=torch.zeros(n, 1, 3, dtype=torch.float64))
    return g, as_t(tau), as_t(colours)


def _mesh_scene():
    ball = trimesh.creation.icosphere(subdivisions=5, radius=BALL)
    parts, meshes = [np.zeros(len(ball.faces), int)], [(np.asarray(ball.vertices), np.asarray(ball.faces))]
    room_v, room_t = box((-3.0, -3.0, -2.0), (3.0, 3.0, 4.0), inward=True)
    meshes.append((room_v, room_t))
    parts.append(np.ones(len(room_t), int))
    v, t = merge(meshes)

    def albedo(points, ids, uvs):
        out = np.zeros((len(points), 3))
        for k, (lo, hi) in enumerate(WALLS):
            flat = int(np.argmin(np.array(hi, float) - np.array(lo, float)))
            on = np.abs(points[:, flat] - lo[flat]) < 1e-3
            out[on] = WALL_COLOURS[k]
        return out

    unlit = np.concatenate([np.zeros(len(ball.faces), bool), np.ones(len(room_t), bool)])
    return Surface(vertices=v, triangles=t, albedo=albedo, parts=np.concatenate(parts), unlit=unlit)


def _camera(width=48, height=36):
    """Looking at the ball from above and aside (the floor and two walls behind it)."""
    f = 1.6 * width
    K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    centre = np.array([0.4, -2.0, 0.9])
    z = -centre / np.linalg.norm(centre)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])  # rows: camera x, y (down), z (forward) in world coordinates
    return Camera(K=K, R=R, t=-R @ centre, width=width, height=height, name="000000.png")


def test_the_traced_interface_reproduces_the_generators_glass_ball():
    """Surfels on the exact ball and walls, the exact surface point and normal per pixel: the method's bounded
    light tree (one reflection, two refractions) against the generator's full one (up to 16 interactions) at
    index 1.5. It leaves out the light reflected inside the ball, and its walls are surfels 0.1 apart (their
    edges soft); measured at 48x36 over the ball's 968 pixels: mean |difference| 0.039, median 0.024, 90%
    within 0.078, the worst 0.49 (at the rim, where the ball's internal reflections carry the light)."""
    camera = _camera()
    view = Renderer(_mesh_scene(), glass_ior=1.5, supersample=1).render(camera)
    g, tau, colours = _surfel_scene()
    jj, ii = np.nonzero(view.mask)
    pix = np.stack([ii + 0.5, jj + 0.5, np.ones_like(ii, dtype=float)], 1) @ np.linalg.inv(camera.K).T @ camera.R
    rays = pix / np.linalg.norm(pix, axis=1, keepdims=True)
    centre = camera.center
    b = rays @ centre
    t = -b - np.sqrt(b * b - (centre @ centre - BALL**2))  # first hit of the exact ball
    x = centre + t[:, None] * rays
    with torch.no_grad():
        light = trace_interface(torch.from_numpy(x), torch.from_numpy(rays), torch.from_numpy(x / BALL),
                                torch.tensor(1.5, dtype=torch.float64), g, tau, colours, near=1e-4).numpy()
    diff = np.abs(light - view.rgb[jj, ii]).mean(1)
    assert len(diff) > 300 and np.isfinite(light).all()
    assert diff.mean() < 0.06 and np.median(diff) < 0.04 and np.percentile(diff, 90) < 0.12


def test_index_one_lets_the_view_ray_through_unchanged():
    """η = 1: no reflection (R = 0), no bending; the light at the ball is what the straight ray meets beyond
    it, the glass invisible."""
    g, tau, colours = _surfel_scene()
    camera = _camera(24, 18)
    pix = np.stack(np.meshgrid(np.arange(24) + 0.5, np.arange(18) + 0.5), -1).reshape(-1, 2)
    rays = np.concatenate([pix, np.ones((len(pix), 1))], 1) @ np.linalg.inv(camera.K).T @ camera.R
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    b = rays @ camera.center
    disc = b * b - (camera.center @ camera.center - BALL**2)
    hit = disc > 0.01
    t = -b[hit] - np.sqrt(disc[hit])
    x = camera.center + t[:, None] * rays[hit]
    with torch.no_grad():
        light = trace_interface(torch.from_numpy(x), torch.from_numpy(rays[hit]), torch.from_numpy(x / BALL),
                                torch.tensor(1.0, dtype=torch.float64), g, tau, colours, near=1e-4)
        straight = surface_light(torch.from_numpy(x), torch.from_numpy(rays[hit]), g, tau, colours, 1e-4, through_glass=True)[0]
    assert hit.sum() > 40 and torch.allclose(light, straight, atol=1e-6)


@pytest.fixture(scope="module")
def tiny_orb(tmp_path_factory):
    return make_scene("synthetic/dtu-glass-orb", out=tmp_path_factory.mktemp("glass") / "orb", res=(64, 48))


def test_quick_run_to_ok(tiny_orb, tmp_path, restore_threads):
    """rt2dgs trains on a small glass scene, meshes and evaluates: status ok, the smoothness term active."""
    assert main(["run", "--method", "rt2dgs", "--scene", str(tiny_orb), "--preset", "quick", "--out", str(tmp_path / "runs"),
                 "--set", "train.iterations=60", "--set", "losses.normal_smoothness.start=0"]) == 0
    record = json.loads(next((tmp_path / "runs").rglob("record.json")).read_text())
    assert record["status"] == "ok" and math.isfinite(record["metrics"]["chamfer"])
    assert "normal_smoothness" in record["losses"]["schedule"]


def test_a_finished_run_evaluated_or_loaded_again_traces_the_light(tiny_orb, tmp_path, monkeypatch, restore_threads):
    """trace_from 15 000 of 30 000 in a 12-step run: the light is traced from step 6. The run folder evaluated
    again from its final checkpoint (the runner after an interruption) and loaded back (`gsbench render`, the
    diagnostics) renders with the light, as at its last step, not 2DGS's render of step 0."""
    out = tmp_path / "runs"
    args = ["run", "--method", "rt2dgs", "--scene", str(tiny_orb), "--preset", "quick", "--out", str(out),
            "--set", "train.iterations=12", "--set", "method.trace_from=15000", "--set", "method.trace_pixels=64",
            "--set", "eval.evaluators=[image]", "--set", "data.holdout_every=4"]
    assert main(args) == 0
    folder = next(out.rglob("record.json")).parent
    (folder / "eval.json").unlink()
    traced = []
    tracing = RT2DGS.tracing
    monkeypatch.setattr(Trainer, "fit", lambda self: pytest.fail("training ran again"))
    monkeypatch.setattr(RT2DGS, "tracing", lambda self: traced.append(tracing(self)) or traced[-1])
    assert main(args) == 0
    assert traced and all(traced)
    _, _, method = load_finished_run(folder, "test")
    assert method.step == 12 and method.tracing()


def test_the_held_out_image_traces_the_light_at_every_candidate_pixel(tiny_orb, monkeypatch, restore_threads):
    """`render_image` (what the held-out metrics score) is the render with the light traced at every candidate
    pixel, in chunks that do not change it; the training render traces at most ``trace_pixels`` and fills the
    pixels between (docs/methods/rt2dgs.md §4), which differs."""
    method, scene, cfg = setup_method("rt2dgs", tiny_orb, "threads=1", "method.trace_pixels=16", "method.trace_from=0")
    camera = scene.cameras[0]
    with torch.no_grad():
        image = method.render_image(camera)
        monkeypatch.setattr(rt2dgs, "TRACE_CHUNK", 5)
        chunked = method.render_image(camera)
        subgrid = method.render(camera, {"rgb"}).rgb
        method.params = replace(method.params, trace_pixels=10**9)
        every = method.render(camera, {"rgb"}).rgb
    assert torch.allclose(chunked, image, rtol=0, atol=1e-6) and torch.allclose(every, image, rtol=0, atol=1e-6)
    assert float((subgrid - image).abs().max()) > 1e-3


def test_resume_is_bit_identical_with_the_traced_light(tiny_orb, tmp_path, monkeypatch, restore_threads):
    """12 steps straight vs 6 + crash + resume + 6, light traced from step 1 (τ starts at 0.1, above the 0.02
    threshold): surfels, transparencies, the index of refraction and the kNN index all equal."""
    straight, resumed = straight_and_resumed("rt2dgs", tiny_orb, tmp_path, monkeypatch, "train.iterations=12",
                                             "train.checkpoint_every=6", "threads=1", "losses.normal_smoothness.start=0",
                                             "method.trace_pixels=64", "method.trace_from=0", crash_after=6)
    assert torch.equal(straight.method.ior_raw, resumed.method.ior_raw) and float(straight.method.ior.detach()) != 1.5
    assert torch.equal(straight.method.neighbours.index, resumed.method.neighbours.index)
    for name, param in straight.method.gaussians.params.items():
        assert torch.equal(param, resumed.method.gaussians.params[name]), name


def test_the_light_is_traced_from_trace_from_only(tiny_orb, tmp_path, monkeypatch, restore_threads):
    """trace_from 15 000 of 30 000 in a 12-step run: the light is traced from step 6; before it the render is
    2DGS's (the transparency unused: no gradient reaches τ), from it τ gets one."""
    straight, _ = straight_and_resumed("rt2dgs", tiny_orb, tmp_path, monkeypatch, "train.iterations=12",
                                       "train.checkpoint_every=6", "threads=1", "method.trace_pixels=64",
                                       "method.trace_from=15000", crash_after=6)
    method = straight.method
    camera = straight.scene.cameras[0]
    grads = {}
    for step in (5, 6):
        method.update_schedules(step, 12 / 30000)
        logits = method.gaussians.params["transparency_logits"]
        logits.grad = None
        method.render(camera, {"rgb"}).rgb.sum().backward()
        grads[step] = logits.grad
    assert method.tracing() and (grads[5] is None or not bool(grads[5].any()))
    assert grads[6] is not None and bool(grads[6].any())


def test_a_trace_from_past_the_run_never_traces_the_light(tiny_orb, restore_threads):
    """experiments/rt2dgs/rt2dgs_light.yaml's rt2dgs never tracing: at the run's last step, where the held-out images
    are rendered, a trace_from past 30 000 leaves every image 2DGS's; 30 000 itself is reached there and traces."""
    for trace_from, traces in ((10**9, False), (30000, True)):
        method, scene, cfg = setup_method("rt2dgs", tiny_orb, "threads=1", f"method.trace_from={trace_from}")
        method.update_schedules(cfg.train.iterations, schedule_scale(cfg.train.iterations))
        with torch.no_grad():
            image, surfels = method.render_image(scene.cameras[0]), GS2D.render(method, scene.cameras[0], {"rgb"}).rgb
        assert method.tracing() is traces
        assert torch.equal(image, surfels) is not traces


def test_transparency_learns_only_where_the_light_was_traced(tiny_orb, tmp_path, monkeypatch, restore_threads):
    """L is traced on a sub-grid and copied to the pixels between (docs/methods/rt2dgs.md §4); τ's gradient comes
    from the traced pixels alone, the colours' and the surfels' from every pixel."""
    method, scene, cfg = setup_method("rt2dgs", tiny_orb, "train.iterations=4", "threads=1", "method.trace_pixels=64",
                                      "method.trace_from=0")
    Trainer(method, scene, cfg, tmp_path / "run").fit()
    camera = scene.cameras[0]
    traced_light = method._traced_light
    seen = {}

    def spy(*args):
        light, traced = traced_light(*args)
        seen["traced"] = traced
        return light, traced

    monkeypatch.setattr(method, "_traced_light", spy)
    logits = method.gaussians.params["transparency_logits"]
    means = method.gaussians.params["means"]
    grads = {}
    for where in ("untraced", "traced"):
        torch.manual_seed(0)  # the same sub-grid offset both times
        logits.grad = means.grad = None
        rgb = method.render(camera, {"rgb"}).rgb
        traced = seen["traced"]
        assert 0 < int(traced.sum()) < traced.numel() // 4
        rgb[traced if where == "traced" else ~traced].sum().backward()
        grads[where] = (logits.grad, means.grad)
    assert grads["untraced"][0] is None or not bool(grads["untraced"][0].any())
    assert bool(grads["untraced"][1].any())
    assert grads["traced"][0] is not None and bool(grads["traced"][0].any())
    # "filled": the copied light's pixels teach τ too, and the image is the same
    method.params.transparency_gradient = "filled"
    torch.manual_seed(0)
    logits.grad = None
    filled = method.render(camera, {"rgb"}).rgb
    filled[~seen["traced"]].sum().backward()
    assert bool(logits.grad.any()) and torch.allclose(filled, rgb, atol=1e-6)
