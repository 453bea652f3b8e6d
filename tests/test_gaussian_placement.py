"""`gsbench gaussians` (gsbench/diagnostics/gaussian_placement.py): the regions of a finished run's Gaussian centres
against its synthetic scene's exact surfaces."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from gsbench.cli import main
from gsbench.diagnostics.gaussian_placement import REGIONS, _distances, place
from gsbench.errors import ConfigError
from tests.method_setup import quick_run


def test_place_splits_by_the_object_then_by_any_surface_and_weights_by_opacity():
    d_object = np.array([0.5, 1.0, 3.0, 3.0, 9.0])
    d_scene = np.array([0.5, 1.0, 0.2, 2.0, 9.0])
    opacity = np.array([0.5, 0.5, 1.0, 1.0, 2.0])
    regions = place(d_object, d_scene, opacity, within=1.0)
    assert list(regions) == list(REGIONS)
    assert [regions[r]["count"] for r in REGIONS] == [2, 1, 2]  # τ itself counts as on the surface
    assert [regions[r]["share"] for r in REGIONS] == pytest.approx([0.4, 0.2, 0.4])
    assert [regions[r]["opacity_share"] for r in REGIONS] == pytest.approx([0.2, 0.2, 0.6])
    empty = place(np.zeros(0), np.zeros(0), np.zeros(0), within=1.0)
    assert all(r["count"] == 0 and r["share"] == 0.0 for r in empty.values())
    with pytest.raises(ConfigError, match="positive"):
        place(d_object, d_scene, opacity, within=0.0)


def test_distances_to_a_mesh_are_the_exact_point_to_surface_distances(tmp_path):
    path = tmp_path / "box.ply"
    trimesh.creation.box(extents=(2.0, 2.0, 2.0)).export(path)
    points = np.array([[0.0, 0.0, 3.0], [0.0, 0.0, 0.5], [2.0, 2.0, 1.0], [1000.0, 0.0, 0.0]])
    assert _distances(path, points) == pytest.approx([2.0, 0.5, np.sqrt(2.0), 999.0], abs=1e-4)


def test_gaussians_of_a_finished_run_on_an_object_only_scene(tiny_spot, tmp_path, capsys):
    folder = Path(quick_run("3dgs", tiny_spot, tmp_path).mesh["checkpoint"]).parent
    capsys.readouterr()
    assert main(["gaussians", str(folder)]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = {line.split()[0]: line.split()[-3:] for line in lines[2:]}  # "free space" is "free" here
    assert list(rows) == ["object", "environment", "free"]
    assert rows["environment"][0] == "0"  # synthetic/spot has no environment: every surface is the object's
    assert int(rows["object"][0].replace(",", "")) > 0
    assert sum(float(r[1]) for r in rows.values()) == pytest.approx(1.0, abs=2e-3)
    assert main(["gaussians", str(folder), "--within", "-1"]) == 2
    assert "positive" in capsys.readouterr().err


def test_gaussians_names_the_missing_checkpoint(tmp_path, capsys):
    (tmp_path / "config.yaml").write_text("scene: synthetic/spot\n")
    assert main(["gaussians", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "checkpoint-final.pt not found" in err and "`gsbench gaussians`" in err
