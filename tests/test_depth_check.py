"""`gsbench depth` (gsbench/diagnostics/depth_check.py): per-view relative depth error of a finished run against its
synthetic scene's exact depth."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from gsbench.cli import main
from gsbench.diagnostics.depth_check import check_run_depth, depth_errors
from gsbench.errors import ConfigError
from tests.method_setup import quick_run


def test_depth_errors_counts_the_masked_pixels_by_tolerance():
    exact = np.full((4, 5), 2.0)
    rel = np.array([[0.0, 0.005, -0.02, 0.03, 0.1],
                    [-0.2, 0.0, 0.0, 0.0, 0.0],
                    [9.0, 9.0, 9.0, 9.0, 9.0],  # masked out
                    [0.0, 0.0, 0.0, np.nan, 0.0]])
    depth = exact * (1 + rel)
    mask = np.ones_like(exact, bool)
    mask[2] = False
    exact[3, 4] = 0.0  # no surface there: not counted
    got = depth_errors(depth, exact, mask)
    assert got["pixels"] == 14
    # errors counted: 0.005 (<=1%), −0.02 and 0.03 (1–5%), 0.1 and −0.2 (>5%), NaN (over both)
    assert got["over_0.01"] == pytest.approx(5 / 14) and got["over_0.05"] == pytest.approx(3 / 14)
    assert got["median_rel"] == 0.0
    assert depth_errors(exact, exact, mask)["over_0.01"] == 0.0


def test_depth_errors_of_an_empty_mask_are_nan_not_zero():
    got = depth_errors(np.ones((2, 2)), np.ones((2, 2)), np.zeros((2, 2), bool))
    assert got["pixels"] == 0 and math.isnan(got["median_rel"]) and math.isnan(got["over_0.05"])


def test_depth_of_a_finished_run_against_the_exact_depth(tiny_spot, tmp_path, capsys):
    folder = Path(quick_run("2dgs", tiny_spot, tmp_path).mesh["checkpoint"]).parent
    capsys.readouterr()
    assert main(["depth", str(folder), "--views", "0", "3"]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[-2].split()[0] == "0" and printed[-1].split()[0] == "3"
    rows = check_run_depth(folder, [0, 3])
    for row in rows:
        assert row["pixels"] > 100 and math.isfinite(row["median_rel"])
        assert 0.0 <= row["over_0.05"] <= row["over_0.01"] <= 1.0
        assert abs(row["median_rel"]) < 0.2  # 60 steps: rough, but the depth is of the object, not the background
    with pytest.raises(ConfigError, match="out of range"):
        check_run_depth(folder, [999])


def test_depth_names_the_missing_checkpoint_and_a_foreign_config(tmp_path, capsys):
    (tmp_path / "config.yaml").write_text("scene: synthetic/spot\n")
    assert main(["depth", str(tmp_path)]) == 2
    assert "checkpoint-final.pt not found" in capsys.readouterr().err
    (tmp_path / "checkpoint-final.pt").write_bytes(b"")
    assert main(["depth", str(tmp_path)]) == 2
    assert "not a run's resolved config" in capsys.readouterr().err
