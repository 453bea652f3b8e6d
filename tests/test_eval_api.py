"""CLI-facing helpers: evaluator lookup, evaluate_mesh_file, the text table, the benchmark workload."""

import eval_fixtures as F
import numpy as np
import pytest

from gsbench.bench.eval import latlong_sphere, run_eval_benchmark, run_tnt_benchmark
from gsbench.errors import EvaluationError, RegistryError
from gsbench.evaluators import api
from gsbench.evaluators.base import MetricInfo
from gsbench.registry import EVALUATORS


def test_versions_of_changed_headlines():
    """tnt_f1's headline became the official vertices (v2); normal_similarity's the ungated mean on the
    protocol's points (v2); dtu_chamfer's headline is unchanged (v1)."""
    assert {n: api.get_evaluator(n).version for n in ("tnt_f1", "normal_similarity", "dtu_chamfer")} == \
        {"tnt_f1": 2, "normal_similarity": 2, "dtu_chamfer": 1}


def test_lookup_and_metric_declarations():
    for name in EVALUATORS.names():
        ev = api.get_evaluator(name)
        assert ev.name == name and ev.version >= 1 and ev.protocol_id == f"{name}@{ev.version}"
        assert ev.requires and all(isinstance(m, MetricInfo) for m in ev.metrics.values())
    with pytest.raises(RegistryError, match="did you mean 'dtu_chamfer'"):
        api.get_evaluator("dtu_chamfr")


def test_evaluate_mesh_file_and_table(tmp_path):
    scene = F.dtu_scene(F.make_dtu_gt(tmp_path / "gt"))
    mesh = tmp_path / "mesh.ply"
    F.dtu_sphere_mesh(subdivisions=4).export(mesh)
    report = api.evaluate_mesh_file(mesh, scene, options={"normal_similarity": {"n_samples": 5000}})
    assert set(report["results"]) == {"dtu_chamfer", "normal_similarity", "silhouette", "mesh_stats"}
    table = api.format_table(report)
    assert "dtu_chamfer@1" in table and "accuracy" in table and "mm" in table and "lower" in table
    vertices = next(line for line in table.splitlines() if line.split()[:2] == ["mesh_stats@1", "vertices"])
    assert vertices.endswith("(describes)") and "lower" not in vertices  # a description is shown, not ranked
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


def test_tnt_benchmark_workload_small():
    out = run_tnt_benchmark(n_vertices=5_000, n_gt=20_000)
    partial, noisy = out["meshes"]["partial"], out["meshes"]["noisy"]
    for mesh in (partial, noisy):
        assert mesh["scoring"]["capped_fractions"] == mesh["scoring"]["uncapped_fractions"]
    assert partial["metrics"]["recall_sampled"] < 0.6 < noisy["metrics"]["recall_sampled"]  # half the sphere is missing


def test_plan_skips_defaults_the_scene_cannot_feed_and_rejects_named_ones(tmp_path):
    from dataclasses import replace

    from gsbench.evaluators.resolve import DEFAULT_EVALUATORS, plan_evaluation

    scene = F.dtu_scene(F.make_dtu_gt(tmp_path / "gt"))
    bare = replace(scene, gt=None, gt_missing="/data/Points/stl/stl024_total.ply not found", masks=None, mask_paths=None)
    full = plan_evaluation(scene, "dtu", (), held_out=3)
    assert full.names == DEFAULT_EVALUATORS["dtu"] and full.skipped == {} and full.image
    plan = plan_evaluation(bare, "dtu", (), held_out=0)
    assert plan.mesh == ("mesh_stats",) and not plan.image and not plan.named
    assert set(plan.skipped) == {"dtu_chamfer", "normal_similarity", "silhouette"}  # no hold-out: a choice
    assert "stl024_total.ply not found" in plan.skipped["dtu_chamfer"] and "--gt" in plan.skipped["dtu_chamfer"]
    assert "masks" in plan.skipped["silhouette"]
    with pytest.raises(EvaluationError, match=r"dtu_chamfer: no ground truth.*image: no view is held out"):
        plan_evaluation(bare, "dtu", ["dtu_chamfer", "mesh_stats", "image"], held_out=0)
    only_images = plan_evaluation(bare, "dtu", ["image"], held_out=2)
    assert only_images.mesh == () and only_images.image and only_images.named
    with pytest.raises(RegistryError, match="did you mean"):
        plan_evaluation(scene, "dtu", ["dtu_chamfr"], held_out=0)
