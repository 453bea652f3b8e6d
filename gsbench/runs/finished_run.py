"""A finished run's folder, loaded back: its resolved config, its scene and its trained method.

The diagnostics that look inside a trained model (`gsbench depth`, `gsbench gaussians`) read the folder
`gsbench run` wrote (``<out>/<dataset>/<scene>/<method>/<run_id>``): ``config.yaml``, the resolved
configuration it wrote itself, and ``checkpoint-final.pt``. A folder without them, or a config that is
not a run's, is a `GsbenchError` naming the file and the fix.
"""

from __future__ import annotations

import yaml

from gsbench.errors import GsbenchError
from gsbench.registry import METHODS
from gsbench.run_folder import RunFolder
from gsbench.runs.runner import load_run_scene, resolve_run
from gsbench.training.trainer import load_checkpoint


def load_finished_run(folder, command: str, *, load_images: bool = True):
    """``(cfg, scene, method)`` of the finished run in ``folder``, the method set up on the scene and
    loaded from the final checkpoint; ``command`` names the caller in the errors."""
    files = RunFolder(folder)
    config, final = files.config, files.final_checkpoint
    for path in (config, final):
        if not path.is_file():
            raise GsbenchError(f"{path} not found: `{command}` reads a finished run's folder (config.yaml and "
                               f"{RunFolder.FINAL_CHECKPOINT}); fix: pass <out>/<dataset>/<scene>/<method>/<run_id> of a run "
                               "whose training finished")
    resolved = yaml.safe_load(config.read_text())
    if not (isinstance(resolved, dict) and isinstance(resolved.get("method"), dict) and "name" in resolved["method"]
            and "scene" in resolved and "preset" in resolved):
        raise GsbenchError(f"{config}: not a run's resolved config (needs method.name, scene and preset); fix: pass the "
                           "folder gsbench run wrote, whose config.yaml it wrote itself")
    cfg = resolve_run(resolved["method"]["name"], resolved["scene"], preset=resolved["preset"], user_files=(config,))
    scene = load_run_scene(cfg, load_images=load_images)
    method = METHODS.get(cfg.method["name"])()
    method.setup(scene, cfg)
    method.load_state_dict(load_checkpoint(final)["method"])
    return cfg, scene, method
