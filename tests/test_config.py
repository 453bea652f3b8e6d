"""Config layering, --set overrides, strict keys with suggestions, run-id stability."""

from dataclasses import dataclass

import pytest

from gsbench.config.run_config import completed_config, parse_override, resolve, run_id
from gsbench.errors import ConfigError


@dataclass
class ToyConfig:
    knn_k: int = 5
    lr: float = 0.01


def test_layers_apply_in_order(tmp_path):
    user = tmp_path / "user.yaml"
    user.write_text("train: {iterations: 777}\nmethod: {knn_k: 7}\n")
    cfg = resolve("toy", "synthetic/spot", preset="quick", user_files=[user], method_config_cls=ToyConfig)
    assert cfg.data.downscale == 1.0 and cfg.data.max_size == [64, 48]  # preset beats dataset (2.0)
    assert cfg.mesh.voxel_size == 0.004  # dataset layer
    assert cfg.eval.evaluators == []  # the dataset's defaults, planned per scene (gsbench.evaluators.resolve)
    assert cfg.data.holdout_every == 0  # auto: a built-in scene has its ground truth
    assert cfg.train.iterations == 777  # user file beats preset
    assert cfg.method == {"name": "toy", "knn_k": 7, "lr": 0.01}
    cfg2 = resolve("toy", "synthetic/spot", preset="quick", user_files=[user], overrides=["method.knn_k=9"],
                   method_config_cls=ToyConfig)
    assert cfg2.method["knn_k"] == 9  # --set beats everything


def test_tnt_scene_takes_tnt_dataset_layer():
    cfg = resolve("toy", "synthetic/spot-tnt", preset="cpu", method_config_cls=ToyConfig)
    assert cfg.data.use_masks is False and cfg.data.max_size == [240, 150]
    paper = resolve("toy", "synthetic/spot-tnt", preset="paper", method_config_cls=ToyConfig)
    assert paper.data.downscale == 2.0 and paper.data.max_size == []  # the papers' -r 2


def test_tnt_runs_train_in_the_colmap_frame_and_the_records_before_keep_theirs():
    """docs/design.md §12.1: the TnT dataset layer selects the papers' COLMAP frame; a record made before
    data.tnt_frame (no key) keeps its id and, completed, says it ran in the extent frame; a DTU scene has one frame."""
    new = resolve("toy", "synthetic/tnt-rig-spot", preset="cpu", method_config_cls=ToyConfig)
    assert new.data.tnt_frame == "colmap"
    old = resolve("toy", "synthetic/tnt-rig-spot", preset="cpu", overrides=["data.tnt_frame=extent"],
                  method_config_cls=ToyConfig)
    recorded = old.to_dict()
    del recorded["data"]["tnt_frame"]
    assert run_id(recorded) == old.run_id != new.run_id
    assert completed_config(recorded)["data"]["tnt_frame"] == "extent"
    read_back = resolve("toy", "synthetic/tnt-rig-spot", preset="cpu", recorded=recorded, method_config_cls=ToyConfig)
    assert read_back.data.tnt_frame == "extent" and read_back.run_id == old.run_id
    dtu = resolve("toy", "synthetic/spot", preset="cpu", method_config_cls=ToyConfig)
    assert dtu.data.tnt_frame == "extent" and run_id({**dtu.to_dict(), "data": {
        k: v for k, v in dtu.to_dict()["data"].items() if k != "tnt_frame"}}) == dtu.run_id
    with pytest.raises(ConfigError, match="Tanks-and-Temples layouts only"):
        resolve("toy", "synthetic/spot", overrides=["data.tnt_frame=colmap"], method_config_cls=ToyConfig)
    with pytest.raises(ConfigError, match="data.tnt_frame must be one of colmap, extent"):
        resolve("toy", "synthetic/spot-tnt", overrides=["data.tnt_frame=nerfpp"], method_config_cls=ToyConfig)


def test_set_parses_yaml_values():
    assert parse_override("train.iterations=500") == {"train": {"iterations": 500}}
    assert parse_override("eval.evaluators=[a, b]") == {"eval": {"evaluators": ["a", "b"]}}
    assert parse_override("data.use_masks=false") == {"data": {"use_masks": False}}
    with pytest.raises(ConfigError, match="key.path=value"):
        parse_override("train.iterations")


@pytest.mark.parametrize(
    "override, message",
    [
        ("train.iteratons=5", "did you mean 'iterations'"),
        ("trian.iterations=5", "did you mean 'train'"),
        ("method.knn=3", "did you mean 'knn_k'"),
        ("train.iterations=abc", "must be int"),
        ("data.use_masks=3", "must be bool"),
    ],
)
def test_unknown_keys_and_bad_types_fail_with_a_suggestion(override, message):
    with pytest.raises(ConfigError, match=message):
        resolve("toy", "synthetic/spot", overrides=[override], method_config_cls=ToyConfig)


def test_unknown_preset_and_missing_file():
    with pytest.raises(ConfigError, match="did you mean 'quick'"):
        resolve("toy", "synthetic/spot", preset="quik")
    with pytest.raises(ConfigError, match="nope.yaml does not exist"):
        resolve("toy", "synthetic/spot", user_files=["nope.yaml"])


def test_losses_are_weighted_scheduled_terms():
    cfg = resolve("toy", "synthetic/spot", overrides=["losses.l1=0.8", "losses.depth_distortion.start=300"],
                  method_config_cls=ToyConfig)
    assert cfg.losses["l1"] == {"weight": 0.8, "start": 0, "end": -1}
    assert cfg.losses["depth_distortion"] == {"weight": 0.0, "start": 300, "end": -1}
    with pytest.raises(ConfigError, match="did you mean 'weight'"):
        resolve("toy", "synthetic/spot", overrides=["losses.l1.wieght=1"])


def test_run_id_is_stable_and_ignores_execution_only_fields():
    a = resolve("toy", "synthetic/spot", method_config_cls=ToyConfig)
    b = resolve("toy", "synthetic/spot", overrides=["threads=2", "out=elsewhere"], method_config_cls=ToyConfig)
    c = resolve("toy", "synthetic/spot", overrides=["method.knn_k=6"], method_config_cls=ToyConfig)
    assert a.run_id == b.run_id
    assert a.run_id != c.run_id
    assert a.run_id == run_id(a.to_dict()) and len(a.run_id) == 12
    # key order of the input must not matter
    assert run_id({"x": 1, "y": {"b": 2, "a": 1}}) == run_id({"y": {"a": 1, "b": 2}, "x": 1})


def test_seed_argument_and_method_change_guard(tmp_path):
    assert resolve("toy", "synthetic/spot", seed=3).seed == 3
    bad = tmp_path / "bad.yaml"
    bad.write_text("method: other\n")
    with pytest.raises(ConfigError, match="changed the method"):
        resolve("toy", "synthetic/spot", user_files=[bad])


def test_bench_preset_doubles_the_cpu_resolution_and_keeps_its_mesh():
    cpu, bench = (resolve("toy", "synthetic/dtu-spot", preset=name, method_config_cls=ToyConfig)
                  for name in ("cpu", "bench"))
    assert bench.data.max_size == [2 * v for v in cpu.data.max_size] == [480, 300]
    assert bench.train.iterations > cpu.train.iterations and bench.mesh == cpu.mesh
    assert cpu.data.max_size == [240, 150] and cpu.train.iterations == 3000  # the cpu preset is unchanged
