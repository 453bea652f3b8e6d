"""A run's folder, loaded back: its resolved config and checkpoint, or its scene and its trained method.

The diagnostics that look inside a trained model (`gsbench depth`, `gsbench gaussians`) read the folder
`gsbench run` wrote (``<out>/<dataset>/<scene>/<method>/<run_id>``): ``config.yaml``, the resolved
configuration it wrote itself, and ``checkpoint-final.pt``. A folder without them, a config that is not a run's,
and a config or record that is not the folder's run (edited: `gsbench.runs.records.check_folder_identity`) are each
a `GsbenchError` naming the file and the fix.
"""

from __future__ import annotations

import yaml

from gsbench.data.method_scene import scene_for_method
from gsbench.errors import GsbenchError, one_line
from gsbench.registry import METHODS
from gsbench.run_folder import RunFolder
from gsbench.runs.records import check_folder_identity
from gsbench.runs.runner import load_run_scene, make_run_scene, resolve_recorded
from gsbench.training.trainer import load_checkpoint


def read_run_config(folder, command: str, checkpoints: tuple[str, ...] = (RunFolder.FINAL_CHECKPOINT,)):
    """``(cfg, checkpoint path)``: the resolved config a run wrote into ``folder`` and the first of ``checkpoints`` (file
    names, in order of preference) found there; ``command`` names the caller in the errors."""
    files = RunFolder(folder)
    found = [files.path / name for name in checkpoints if (files.path / name).is_file()]
    if not files.config.is_file() or not found:
        missing = files.config if not files.config.is_file() else files.path / checkpoints[0]
        raise GsbenchError(f"{missing} not found: `{command}` reads a run's folder (config.yaml and "
                           f"{' or '.join(checkpoints)}); fix: pass <out>/<dataset>/<scene>/<method>/<run_id> of a run "
                           "whose training wrote a checkpoint")
    try:
        resolved = yaml.safe_load(files.config.read_text())
    except yaml.YAMLError as exc:
        raise GsbenchError(f"{files.config}: not YAML ({one_line(exc, 120)}); fix: pass the folder gsbench run wrote, "
                           "whose config.yaml it wrote itself") from exc
    if not (isinstance(resolved, dict) and isinstance(resolved.get("method"), dict) and "name" in resolved["method"]
            and "scene" in resolved and "preset" in resolved):
        raise GsbenchError(f"{files.config}: not a run's resolved config (needs method.name, scene and preset); fix: pass "
                           "the folder gsbench run wrote, whose config.yaml it wrote itself")
    check_folder_identity(files)
    cfg = resolve_recorded(resolved)
    return cfg, found[0]


def load_finished_run(folder, command: str, *, load_images: bool = True):
    """``(cfg, scene, method)`` of the finished run in ``folder``, the method set up on the scene (its ground truth
    hidden, `scene_for_method`) and loaded from the final checkpoint; ``command`` names the caller in the errors."""
    cfg, final = read_run_config(folder, command)
    make_run_scene(cfg)
    scene = load_run_scene(cfg, load_images=load_images)
    method = METHODS.get(cfg.method["name"])()
    method.setup(scene_for_method(scene, cfg.method["name"]), cfg)
    method.load_state_dict(load_checkpoint(final)["method"])
    return cfg, scene, method
