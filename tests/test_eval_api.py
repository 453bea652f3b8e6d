"""CLI-facing helpers: evaluator lookup, evaluate_mesh_file, the text table, the benchmark workload."""

import numpy as np
import pytest

import eval_fixtures as F
from gsbench.errors import EvaluationError, RegistryError
from gsbench.evaluators import api
from gsbench.registry import EVALUATORS
from gsbench.evaluators.base import MetricInfo
from gsbench.evaluators.bench import latlong_sphere, run_eval_benchmark


def test_lookup_and_metric_declarations():
    for name in EVALUATORS.names():
        ev = api.get_evaluator(name)
        assert ev.name == name and ev.version == 1 and ev.protocol_id == f"{name}@1"
        assert ev.requires and all(isinstance(m, MetricInfo) for m in ev.metrics.values())
    with pytest.raises(RegistryError, match="did you mean 'dtu_chamfer'"):
        api.get_evaluator("dtu_chamfr")


def test_evaluate_mesh_file_and_table(tmp_path):
    scene = F.dtu_scene(F.make_dtu_gt(tmp_path / "gt"))
    mesh = tmp_path / "mesh.ply"
    F.dtu_sphere_mesh(subdivisions=4).export(mesh)
    report = api.evaluate_mesh_file(mesh, scene, options={"normal_similarity": {"n_samples": 5000}})
    assert set(report["results"]) == {"dtu_chamfer", "normal_similarity"}
    table = api.format_table(report)
    assert "dtu_chamfer@1" in table and "accuracy" in table and "mm" in table and "lower" in table
    with pytest.raises(RegistryError, match="renders"):
        api.evaluate_mesh_file(mesh, scene, names=["image"])
    with pytest.raises(EvaluationError, match="tnt"):
        api.evaluate_mesh_file(mesh, scene, names=["tnt_f1"])  # DTU scene, TnT evaluator


def test_suspect_alignment_is_flagged(tmp_path):
    scene = F.tnt_scene(F.make_tnt_gt(tmp_path, n_points=20_000))
    with pytest.warns(UserWarning, match="suspect"):
        res = api.get_evaluator("tnt_f1").evaluate(F.tnt_sphere_mesh(subdivisions=4), scene, suspect_fitness=1.01)
    assert res["diagnostics"]["suspect_alignment"] is True


def test_benchmark_workload_small():
    v, f = latlong_sphere(2000, 10.0, noise=0.0, seed=0)
    assert f.max() == len(v) - 1 and np.allclose(np.linalg.norm(v, axis=1), 10.0)
    out = run_eval_benchmark(n_vertices=5_000, n_gt=20_000, n_views=2)
    assert out["workload"]["n_gt"] == 20_000 and out["threads"] >= 1
    assert out["metrics"]["accuracy"] < 0.3 and {"cull", "sample", "downsample", "accuracy"} <= set(out["seconds"])
