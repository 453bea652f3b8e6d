"""A method reads no ground truth (docs/design.md §3.1): the scene it is given hides ``gt`` and ``root``, a method
that reads them fails with `GroundTruthRead` naming it, and every registered method sets up and trains without
them (and meshes, the slow check)."""

from __future__ import annotations

import copy
import json
import math
import os

import pytest

from gsbench.data.loader import load_scene
from gsbench.data.method_scene import HIDDEN_FIELDS, scene_for_method
from gsbench.errors import GroundTruthRead
from gsbench.registry import METHODS
from gsbench.runs.runner import resolve_run, run
from gsbench.training.trainer import Trainer
from tests.method_setup import TINY

STEPS = 2
COARSE_MESH = ["mesh.voxel_size=0.02", "mesh.sdf_trunc=0.08"]  # tests/method_setup.py QUICK's


def test_the_given_scene_shares_the_inputs_and_refuses_every_read_of_the_ground_truth(tiny_spot):
    scene = load_scene(tiny_spot)
    given = scene_for_method(scene, "toy")
    assert scene.gt is not None and scene.gt.kind == "dtu"  # the run's own scene keeps it
    assert given.images is scene.images and given.cameras is scene.cameras and given.masks is scene.masks
    assert given.train_views == scene.train_views and given.radius == scene.radius
    reads = {"gt": [lambda s: s.gt.root, lambda s: s.gt.depth_maps, lambda s: bool(s.gt)],
             "root": [lambda s: s.root / "gt_depth", lambda s: os.fspath(s.root), lambda s: s.root.glob("*.ply")]}
    assert set(reads) == set(HIDDEN_FIELDS)
    for field, tries in reads.items():
        for read in tries:
            with pytest.raises(GroundTruthRead, match=rf"method 'toy' read scene\.{field}.*fix: derive it from those"):
                read(given)
    assert "hidden from method 'toy'" in f"{given.gt} {given.root!r}"
    assert copy.deepcopy(given.gt).method == "toy"  # copy and pickle protocols are not reads


class _ReadsGroundTruthInSetup(METHODS.get("3dgs")):
    """3DGS that places its Gaussians around the GT point cloud, as a method must not."""

    def setup(self, scene, cfg):
        super().setup(scene, cfg)
        self.gt_points = scene.gt.root / "Points"


class _ReadsTheSceneFolderWhenMeshing(METHODS.get("3dgs")):
    """3DGS that meshes from the scene folder's exact depth maps, as a method must not."""

    def extract_mesh(self, scene, cfg, out_path):
        return sorted((scene.root / "gt_depth").glob("*.npy"))


@pytest.mark.parametrize("cheat, field", [(_ReadsGroundTruthInSetup, "gt"), (_ReadsTheSceneFolderWhenMeshing, "root")])
def test_a_method_that_reads_the_ground_truth_fails_its_run(cheat, field, tiny_spot, tmp_path):
    """Through the runner, as `gsbench run` runs it: the run fails with GroundTruthRead naming the method, in setup
    or when meshing after its one training step, and its record says so."""
    METHODS.register("cheat", cheat)
    try:
        cfg = resolve_run("3dgs", str(tiny_spot), preset="quick",
                          overrides=[*TINY, "train.iterations=1", "eval.evaluators=[dtu_chamfer]", "threads=1"])
        cfg.method["name"], cfg.out = "cheat", str(tmp_path / "runs")
        with pytest.raises(GroundTruthRead, match=rf"method 'cheat' read scene\.{field}"):
            run(cfg, echo=lambda *a: None)
    finally:
        METHODS._entries.pop("cheat", None)
        METHODS._imported.pop("cheat", None)
    records = [json.loads(path.read_text()) for path in (tmp_path / "runs").rglob("record.json")]
    assert len(records) == 1 and records[0]["status"] == "failed" and "GroundTruthRead" in records[0]["error_tail"]


def _trained_without_ground_truth(method, scene_dir, folder):
    """(method, the scene it was given, config): ``method`` set up on the scene at ``scene_dir`` with its ground truth
    hidden, after `STEPS` steps of the quick preset with every loss term switched on from the first step (so no
    term's start keeps it from running); Gaussians start opaque enough for every extractor (SuGaR's Poisson keeps
    opacity > 0.5)."""
    cfg = resolve_run(method, str(scene_dir), preset="quick",
                      overrides=[*TINY, *COARSE_MESH, "method.init_opacity=0.9", "threads=1"])
    for term in cfg.losses.values():
        term["start"] = 0
    scene = load_scene(cfg.scene, downscale=cfg.data.downscale)
    assert scene.gt is not None  # there is ground truth to hide
    given = scene_for_method(scene, method)
    m = METHODS.get(method)()
    m.setup(given, cfg)
    trainer = Trainer(m, given, cfg, folder)
    for step in range(1, STEPS + 1):
        assert math.isfinite(trainer.train_step(step)["total"])
    return m, given, cfg


@pytest.mark.parametrize("method", METHODS.names())
def test_every_method_sets_up_and_trains_without_the_ground_truth(method, tiny_spot, tmp_path):
    m, _, _ = _trained_without_ground_truth(method, tiny_spot, tmp_path)
    assert len(m.gaussians) > 0


@pytest.mark.slow
@pytest.mark.parametrize("method", METHODS.names())
def test_every_method_meshes_without_the_ground_truth(method, tiny_spot, tmp_path):
    m, given, cfg = _trained_without_ground_truth(method, tiny_spot, tmp_path)
    m.extract_mesh(given, cfg, tmp_path / "mesh.ply")
    assert (tmp_path / "mesh.ply").stat().st_size > 0
