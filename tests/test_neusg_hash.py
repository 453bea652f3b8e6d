"""NeuSG's hash encoding (methods/csrc/neusg_hash.cpp via `gsbench.methods.neusg_hash`) against its PyTorch
reference: values and the tables' gradients on levels that hash and levels that do not, Instant-NGP's spatial hash
computed independently, a dense level against ``grid_sample`` of the same grid, float64 gradchecks of both paths,
determinism over thread counts, non-finite points, the fallbacks; and ``method.encoding=hash`` in NeuSG (the
coarse-to-fine levels, the config keys, a quick run)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from gsbench.cli import main
from gsbench.config.run_config import run_id
from gsbench.data.loader import load_scene
from gsbench.errors import ConfigError
from gsbench.methods.neusg import active_levels
from gsbench.methods.neusg_field import HashGrid
from gsbench.methods.neusg_grid import grid_features_reference
from gsbench.methods.neusg_hash import hash_features, hash_features_reference, vertex_rows
from gsbench.registry import METHODS
from gsbench.runs.runner import resolve_run
from gsbench.switches import NEUSG_GRID
from test_neusg_grid import assert_relative

TOL = {torch.float32: 1e-6, torch.float64: 1e-12}
RESOLUTIONS = (2, 7, 40)  # with 64 rows: 3³ = 27 vertices fit (dense), 8³ and 41³ do not (hashed)


def tables_and_points(resolutions=RESOLUTIONS, size=64, features=2, points=400, dtype=torch.float64, seed=0):
    """Tables (T_l, F), T_l = min((N_l + 1)³, ``size``), of random features, and points: most inside [0, 1]³, some
    outside (border clamping), some on vertices and corners."""
    gen = torch.Generator().manual_seed(seed)
    tables = [torch.randn(min((n + 1) ** 3, size), features, generator=gen, dtype=torch.float64).to(dtype)
              .requires_grad_() for n in resolutions]
    unit = torch.rand(points, 3, generator=gen, dtype=torch.float64)
    unit[:20] = unit[:20] * 1.6 - 0.3
    unit[20] = torch.tensor([0.0, 0.0, 0.0])
    unit[21] = torch.tensor([1.0, 1.0, 1.0])
    unit[22] = torch.tensor([0.5, 0.25, 1.0])
    return tables, unit.to(dtype)


def value_and_grads(impl, tables, resolutions, unit):
    out = hash_features(tables, resolutions, unit, impl=impl)
    weights = torch.linspace(-1.0, 2.0, out.numel(), dtype=out.dtype).reshape(out.shape)
    return [out.detach(), *torch.autograd.grad((out * weights).sum(), tables)]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fused_matches_the_reference(dtype):
    tables, unit = tables_and_points(dtype=dtype)
    fused = value_and_grads("fused", tables, RESOLUTIONS, unit)
    # the float32 reference rounds u·N in float32 (a relative error up to N·2⁻²⁴ in t); the kernel works in float64
    assert_relative(fused, value_and_grads("reference", tables, RESOLUTIONS, unit), 32 * TOL[dtype])
    exact = [t.detach().double().requires_grad_() for t in tables]
    assert_relative(fused, value_and_grads("reference", exact, RESOLUTIONS, unit.double()), TOL[dtype])


def test_the_spatial_hash_is_instant_ngps():
    """Rows of a hashed level: (x ⊕ y·2654435761 ⊕ z·805459861) mod T in wrapping uint32 (numpy's), and the fused
    forward reads exactly those rows: a point on a vertex gets that row's feature."""
    vertices = torch.tensor([[0, 0, 0], [3, 5, 7], [2048, 2047, 1], [1000, 0, 2000]])
    x, y, z = (vertices.numpy().astype(np.uint32).T)
    with np.errstate(over="ignore"):
        expected = (x ^ (y * np.uint32(2654435761)) ^ (z * np.uint32(805459861))) % np.uint32(1 << 19)
    assert vertex_rows(vertices, 2048, 1 << 19).tolist() == expected.astype(np.int64).tolist()
    table = torch.randn(1 << 19, 2, dtype=torch.float64)
    out = hash_features([table], [2048], vertices.double() / 2048, impl="fused")
    assert torch.equal(out, table[torch.from_numpy(expected.astype(np.int64))])


def test_a_level_that_fits_is_the_dense_grid_of_grid_sample():
    """A level whose (N+1)³ vertices fit in its table is the dense grid: table row x + (N+1)(y + (N+1) z) is
    grid[f, z, y, x], and the reference equals ``grid_sample`` of that grid (`gsbench.methods.neusg_grid`)."""
    n, features = 5, 3
    tables, unit = tables_and_points(resolutions=(n,), size=(n + 1) ** 3, features=features)
    grid = tables[0].detach().t().reshape(1, features, n + 1, n + 1, n + 1)
    assert_relative([hash_features_reference(tables, [n], unit).detach()], [grid_features_reference([grid], unit)],
                    1e-12)


def test_gradcheck_float64_of_both_paths():
    tables, unit = tables_and_points(resolutions=(1, 6), size=20, points=30)
    assert torch.autograd.gradcheck(lambda *t: hash_features(t, (1, 6), unit, impl="fused"), tables)
    inside = (unit.clamp(0.01, 0.99) * 6).round() / 6 + 0.03  # away from cell faces, where the blend has a kink
    moving = inside.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda p, *t: hash_features_reference(t, (1, 6), p), (moving, *tables))


def test_gradients_do_not_depend_on_the_thread_count(restore_threads):
    tables, unit = tables_and_points(resolutions=(3, 9, 17, 60), size=512, points=5000, dtype=torch.float32)
    results = []
    for threads in (1, 2, 3):
        torch.set_num_threads(threads)
        results.append(value_and_grads("fused", tables, (3, 9, 17, 60), unit))
    for other in results[1:]:
        assert all(torch.equal(a, b) for a, b in zip(results[0], other))


def test_non_finite_points_stay_inside_the_tables():
    tables, unit = tables_and_points(points=30)
    unit[0] = torch.tensor([float("nan"), 0.5, 0.5])
    unit[1] = torch.tensor([float("inf"), -float("inf"), 0.5])
    out = hash_features(tables, RESOLUTIONS, unit, impl="fused")
    grads = torch.autograd.grad(out[1:].sum(), tables)
    assert torch.isfinite(out[1:]).all() and all(torch.isfinite(g).all() for g in grads)


def test_environment_and_fallbacks(monkeypatch):
    tables, unit = tables_and_points(points=30)
    assert type(hash_features(tables, RESOLUTIONS, unit).grad_fn).__name__ == "_FusedHashBackward"
    monkeypatch.setenv(NEUSG_GRID.name, "reference")
    assert type(hash_features(tables, RESOLUTIONS, unit).grad_fn).__name__ != "_FusedHashBackward"
    monkeypatch.setenv(NEUSG_GRID.name, "fast")
    with pytest.raises(ConfigError, match=NEUSG_GRID.name):
        hash_features(tables, RESOLUTIONS, unit)
    monkeypatch.delenv(NEUSG_GRID.name)
    moving = unit.clone().requires_grad_()
    with pytest.raises(ValueError, match="require a gradient"):
        hash_features(tables, RESOLUTIONS, moving, impl="fused")
    out = hash_features(tables, RESOLUTIONS, moving)  # the reference, which differentiates the points too
    assert torch.autograd.grad(out.sum(), moving)[0].abs().sum() > 0
    with pytest.raises(ValueError, match="dtypes"):
        hash_features(tables, RESOLUTIONS, unit.float(), impl="fused")


def _hash_method(tiny_spot, *overrides):
    cfg = resolve_run("neusg", str(tiny_spot), preset="quick",
                      overrides=["method.encoding=hash", "method.grid_levels=6", "method.grid_max_res=512",
                                 "method.hash_table_log2=12", *overrides])
    method = METHODS.get("neusg")()
    method.setup(load_scene(cfg.scene, load_images=False), cfg)
    return method, cfg


def test_active_levels_follow_neuralangelos_schedule():
    """4 levels, then one more every ``level_step`` steps after ``start`` (none added before 5 steps have passed,
    as in Neuralangelo's max(init, ⌊(t − start) / step⌋)), at most L; every level when the step is 0."""
    counts = [active_levels(step, 100, 10, 6) for step in (0, 100, 149, 150, 159, 160, 170, 10_000)]
    assert counts == [4, 4, 4, 5, 5, 6, 6, 6]
    assert active_levels(0, 0, 0, 16) == 16


def test_the_hash_field_uses_its_active_levels_and_checkpoints_them(tiny_spot):
    """``method.encoding=hash`` builds a `HashGrid` with tables of min((N+1)³, 2^T) rows; `update_schedules` sets the
    active levels from the (scaled) schedule; inactive levels give 0 and get no gradient; the numerical gradient's
    step is the finest active cell; a checkpoint carries the count (a finished run is loaded without a step)."""
    method, cfg = _hash_method(tiny_spot, "method.grid_level_step=3000")  # 300 steps a level at the quick scale
    grid = method.field.sdf.grid
    assert isinstance(grid, HashGrid) and grid.resolutions[-1] == 512
    assert [t.shape[0] for t in grid.tables] == [min((n + 1) ** 3, 1 << 12) for n in grid.resolutions]
    scale = cfg.train.iterations / 30000
    method.update_schedules(0, scale)
    assert int(grid.active) == 4 and method.field.sdf.epsilon == 2 * method.field.radius / grid.resolutions[3]
    unit = torch.rand(50, 3, generator=torch.Generator().manual_seed(0))
    out = grid(unit)
    assert out.shape == (50, 12) and torch.equal(out[:, 8:], torch.zeros(50, 4)) and out[:, :8].abs().sum() > 0
    grads = torch.autograd.grad(out.sum(), list(grid.tables), allow_unused=True)
    assert all(g is not None for g in grads[:4]) and all(g is None for g in grads[4:])
    method.update_schedules(round(3000 * scale) * 5, scale)
    assert int(grid.active) == 5
    loaded, _ = _hash_method(tiny_spot, "method.grid_level_step=3000")  # as a finished run is loaded: no schedule
    loaded.load_state_dict(method.state_dict())
    assert int(loaded.field.sdf.grid.active) == 5 and loaded.field.sdf.epsilon == method.field.sdf.epsilon


def test_the_encoding_keys_are_checked_and_the_dense_default_keeps_the_run_id(tiny_spot):
    dense = resolve_run("neusg", str(tiny_spot), preset="quick")
    recorded = dense.to_dict()
    later = ("encoding", "hash_table_log2", "grid_active_start", "grid_level_step")
    before = {**recorded, "method": {k: v for k, v in recorded["method"].items() if k not in later}}
    assert run_id(before) == dense.run_id
    hashed = resolve_run("neusg", str(tiny_spot), preset="quick", overrides=["method.encoding=hash"])
    assert hashed.run_id != dense.run_id
    with pytest.raises(ConfigError, match="method.encoding must be one of dense, hash"):
        _hash_method(tiny_spot, "method.encoding=tree")
    with pytest.raises(ConfigError, match="read by the hash encoding only"):
        _hash_method(tiny_spot, "method.encoding=dense")


def test_quick_hash_run_to_ok(tiny_spot, tmp_path, restore_threads):
    assert main(["run", "--method", "neusg", "--scene", str(tiny_spot), "--preset", "quick", "--out", str(tmp_path),
                 "--set", "train.iterations=60", "--set", "mesh.voxel_size=0.02", "--set", "method.encoding=hash",
                 "--set", "method.hash_table_log2=14", "--set", "method.grid_levels=8",
                 "--set", "method.grid_max_res=512", "--set", "eval.evaluators=[mesh_stats]"]) == 0
    record = json.loads(next(tmp_path.rglob("record.json")).read_text())
    assert record["status"] == "ok" and record["config"]["method"]["encoding"] == "hash"
