"""`gsbench bench train` (gsbench/bench/train.py): the timers nest inside the training step and every
loss term is timed forward and backward. Times are not asserted here (bench numbers come from the
command, written down with the machine)."""

from __future__ import annotations

import math

import pytest

from gsbench.bench.train import (
    RASTER_PHASES,
    WORKLOADS,
    bench_run_folder,
    bench_workload,
    format_table,
    run_train_benchmark,
)
from gsbench.cli import main
from gsbench.errors import ConfigError
from gsbench.runs.records import RunRecord


@pytest.mark.parametrize("name, terms", [("2dgs", {"l1", "dssim", "normal_consistency", "depth_distortion"}),
                                         ("gof", {"l1", "dssim", "normal_consistency", "depth_distortion"})])
def test_phases_add_up_to_the_step_and_every_term_is_timed(tiny_spot, name, terms):
    result = bench_workload(name, WORKLOADS[name], steps=3, warmup=1, probe_steps=1, threads=1,
                            scene_name=str(tiny_spot))
    ms = result["phases_ms"]
    assert result["resolution"] == [64, 48] and result["steps"] == 3 and result["first_timed_step"] > 750
    assert {f"fwd.{t}" for t in terms} | {f"bwd.{t}" for t in terms} <= set(ms)
    assert set(RASTER_PHASES) <= set(ms) and ms["raster_fwd"] > 0 and ms["raster_bwd"] > 0
    assert all(math.isfinite(v) for v in ms.values())
    # the rasterizer's timers and the per-term forwards are measured inside the Trainer's phases, and
    # those inside the step: each remainder is non-negative (fails on a double count or a missed reset)
    assert ms["render_rest"] >= 0 and ms["loss_rest"] >= 0 and ms["other"] >= 0
    assert 0 < result["it_per_s"] and -1 < result["non_raster_share"] < 1
    assert name in format_table({"results": [result]})


def test_pgsr_neighbour_render_is_timed_as_rasterizer_inside_its_term(tiny_spot):
    """PGSR's neighbour render (docs/methods/pgsr.md §4.3) is rasterizer work made inside ``pgsr_geo``'s forward and
    backward: its timers are kept apart and counted as rasterizer in the share."""
    result = bench_workload("pgsr", WORKLOADS["pgsr"], steps=2, warmup=1, probe_steps=1, threads=1,
                            scene_name=str(tiny_spot))
    ms = result["phases_ms"]
    nb_fwd = sum(ms[f"neighbour.{k}"] for k in ("projection", "sort_bin", "raster_fwd"))
    assert nb_fwd > 0 and ms["neighbour.raster_bwd"] > 0
    assert nb_fwd <= ms["fwd.pgsr_geo"]  # measured inside the term's forward
    raster = sum(ms[k] for k in RASTER_PHASES) + ms["backward_rest"]
    assert result["non_raster_share"] == pytest.approx(1 - (raster + ms["neighbour_raster"]) / result["step_ms"])
    assert "(nb.raster)" in format_table({"results": [result]})


def test_unknown_workload_is_an_error_listing_the_workloads():
    with pytest.raises(ConfigError, match="3dgs-random-100k"):
        run_train_benchmark(["3dgs-random-1m"])


def test_papers_size_workloads_run_at_a_tiny_size(tmp_path, monkeypatch):
    """Every method has papers'-size workloads; one, shrunk to 64x48 and 3 000 Gaussians, runs: the scene is
    made at its resolution in the IDR layout and training starts from exactly that many Gaussians."""
    from gsbench.bench.train import PAPER_METHODS, PAPER_SIZES, Workload

    assert {f"{m}-{s}" for m in PAPER_METHODS for s in PAPER_SIZES} <= set(WORKLOADS)
    assert WORKLOADS["radegs-800x600-300k"].resolution == (800, 600)
    monkeypatch.setenv("GSBENCH_DATA", str(tmp_path))
    tiny = Workload("radegs", resolution=(64, 48), gaussians=3000)
    result = bench_workload("radegs-tiny", tiny, steps=1, warmup=1, probe_steps=1, threads=1)
    assert result["resolution"] == [64, 48] and result["gaussians"]["initial"] == 3000
    assert (tmp_path / "bench" / "dtu-bunny-64x48" / "cameras.npz").exists()


@pytest.mark.parametrize("method", ["neusg", "rt2dgs"])
def test_the_hybrid_and_the_glass_method_have_workloads_that_run(method, tmp_path, monkeypatch):
    """NeuSG's field and rt2dgs's ray tracing are timed like the other methods: at the cpu preset and the papers'
    size, here shrunk to 64x48 and 3 000 Gaussians."""
    from gsbench.bench.train import Workload

    assert {method, f"{method}-800x600-300k", f"{method}-800x600-1m"} <= set(WORKLOADS)
    monkeypatch.setenv("GSBENCH_DATA", str(tmp_path))
    result = bench_workload(method, Workload(method, resolution=(64, 48), gaussians=3000), steps=1, warmup=1,
                            probe_steps=1, threads=1)
    assert result["gaussians"]["initial"] == 3000 and result["step_ms"] > 0
    assert all(math.isfinite(v) for v in result["phases_ms"].values())


def test_a_runs_own_steps_are_timed_from_its_checkpoint(tiny_spot, tmp_path, capsys):
    """`bench train --run RUN_DIR`: the run's config, scene and trained state (not a workload's random Gaussians),
    stepped on in a temporary folder; the run's folder is left as it was."""
    out = tmp_path / "runs"
    sets = ["data.downscale=1", "method.random_init_points=2000", "train.iterations=60", "eval.evaluators=[mesh_stats]"]
    assert main(["run", "--method", "3dgs", "--scene", str(tiny_spot), "--preset", "quick", "--out", str(out),
                 *[arg for s in sets for arg in ("--set", s)]]) == 0
    folder = next(out.rglob("record.json")).parent
    before = {p.name: p.stat().st_mtime_ns for p in folder.iterdir()}
    trained = RunRecord.read(folder / "record.json").num_gaussians
    assert main(["--threads", "1", "bench", "train", "--run", str(folder), "--steps", "2", "--warmup", "1"]) == 0
    table = capsys.readouterr().out
    assert f"run {folder.name}" in table
    result = bench_run_folder(folder, steps=2, warmup=1, probe_steps=1, threads=1)
    assert result["checkpoint_step"] == 60 and result["first_timed_step"] == 60 - 2 - 1 + 1
    assert result["gaussians"]["initial"] == trained and result["resolution"] == [64, 48]
    assert all(math.isfinite(v) for v in result["phases_ms"].values())
    assert {p.name: p.stat().st_mtime_ns for p in folder.iterdir()} == before


def test_run_and_workloads_together_is_an_error(tmp_path, capsys):
    assert main(["bench", "train", "--run", str(tmp_path), "--workloads", "3dgs"]) == 2
    assert "--run" in capsys.readouterr().err
