"""`gsbench bench raster`'s roofline (gsbench/bench/roofline.py): the machine probes return physical numbers and
each phase is placed against its bound; the raster benchmark runs with it on a tiny workload. Times are not
asserted (bench numbers come from the command, written down with the machine)."""

from __future__ import annotations

import pytest

from gsbench.bench import roofline
from gsbench.bench.raster import format_table, run_raster_benchmark
from gsbench.errors import ConfigError


def test_machine_limits_are_physical():
    """A triad and an in-place update over 1 M floats and a short FMA probe: bandwidths between 0.1 and 10 000
    GB/s, the peak between 1 and 100 000 GFLOP/s, two flops per FMA lane operation."""
    m = roofline.machine_limits(1, elements=2**20, fma_iters=200_000)
    assert 0.1 < m["bandwidth_gb_s"] < 1e4 and 0.1 < m["update_gb_s"] < 1e4 and 1 < m["peak_gflops"] < 1e5
    assert m["peak_gflops"] == 2 * m["peak_lane_ops_s"] / 1e9


def test_phases_are_placed_against_their_bounds():
    """On a tiny raster workload every phase that ran has a positive rate and a bound; the bound is the
    smaller of the compute and memory ones, and the table prints the machine and the fractions."""
    result = run_raster_benchmark(kernels=("ewa", "surfel"), workloads=[dict(n=2000, width=64, height=48)],
                                  repeats=1, threads=1, reference_case=None)
    m = result["machine"]
    for row in result["results"]:
        phases = {p["phase"]: p for p in row["roofline"]}
        assert {"projection", "raster_fwd", "raster_bwd"} <= set(phases)
        for p in phases.values():
            compute = m["peak_lane_ops_s"] / p["ops"]
            memory = m["bandwidth_gb_s"] * 1e9 / p["bytes"]
            assert p["per_s"] > 0 and p["bound_per_s"] == min(compute, memory)
            assert p["limit"] == ("compute" if compute <= memory else "memory")
        assert phases["raster_fwd"]["limit"] == "compute"
    assert "GB/s (triad)" in format_table(result) and "raster_fwd" in format_table(result)


def test_unknown_raster_workload_or_kernel_is_an_error_listing_the_valid_ones():
    """A misspelt workload or kernel stops before any benchmark runs, naming what is available."""
    with pytest.raises(ConfigError, match="200k-800x600"):
        run_raster_benchmark(kernels=("ewa",), workloads=["10k-200x150"], repeats=1)
    with pytest.raises(ConfigError, match="surfel"):
        run_raster_benchmark(kernels=("gaussian",), workloads=["50k-400x300"], repeats=1)
