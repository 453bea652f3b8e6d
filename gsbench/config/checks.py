"""Every check of a run's configuration that needs no scene, made before anything is read or written.

`check_run_config` is called by ``gsbench run`` (before the scene's cameras are read), by ``gsbench
sweep`` for every expanded run (``--dry-run`` too) and by ``gsbench config``. It raises one
`ConfigError` naming the key, the value and the accepted range; checks that need the scene (its
views, points, masks, ground truth) stay where the scene is read (`gsbench.evaluators.resolve`,
the loaders).

- ``threads`` >= 0 (0: every core); ``train.iterations`` >= 1; ``train.log_every`` >= 1;
  ``train.checkpoint_every`` >= 0 (0: only the final checkpoint); ``train.max_gaussians`` >= 0;
- ``eval.dtu_culling`` one of the DTU culling conventions (`gsbench.evaluators.culling`) or ``none``;
- ``eval.points`` steps before the end or fractions in (0, 1), distinct once resolved (`point_steps`);
- the memory the run needs (`memory_check`, the method's ``memory_estimate``) against what is available;
- the method's own parameters, mesh and raster options (`gsbench.methods.base.Method.check_config`,
  when the plugin has it), and every configured loss term: its name and the parameters the method
  binds to it.
"""

from __future__ import annotations

from gsbench.config.run_config import RunConfig, point_steps
from gsbench.errors import ConfigError
from gsbench.evaluators.culling import CULL_CONVENTIONS, NO_CULLING
from gsbench.registry import METHODS
from gsbench.resources import available_memory_bytes, gib

NON_NEGATIVE = {"train.checkpoint_every": "0: only the final checkpoint", "train.max_gaussians": "0: no cap"}


def check_run_config(cfg: RunConfig) -> None:
    """Raise ConfigError for the first value out of range (module docstring)."""
    if cfg.threads < 0:
        raise ConfigError(f"threads must be >= 0 (0: every core), got {cfg.threads} (--threads or threads:)")
    if cfg.train.iterations < 1:
        raise ConfigError(f"train.iterations must be >= 1, got {cfg.train.iterations}")
    if cfg.train.log_every < 1:
        raise ConfigError(f"train.log_every must be >= 1 (a metric line every so many steps), got {cfg.train.log_every}")
    for key, meaning in NON_NEGATIVE.items():
        value = getattr(cfg.train, key.split(".")[1])
        if value < 0:
            raise ConfigError(f"{key} must be >= 0 ({meaning}), got {value}")
    if cfg.eval.dtu_culling not in (*CULL_CONVENTIONS, NO_CULLING):
        raise ConfigError(f"eval.dtu_culling must be one of {', '.join((*CULL_CONVENTIONS, NO_CULLING))}, "
                          f"got {cfg.eval.dtu_culling!r}")
    point_steps(cfg)
    method = METHODS.get(cfg.method["name"])
    check_method = getattr(method, "check_config", None)  # plugins need not have it
    if check_method is not None:
        check_method(cfg)
    memory_check(cfg, getattr(method, "memory_estimate", None))


def memory_check(cfg: RunConfig, estimate, available: int | None = None) -> None:
    """ConfigError when the method's `memory_estimate` of ``cfg`` (bytes by item) exceeds the memory available
    (`gsbench.resources.available_memory_bytes`, unless given), naming the items, so a run that cannot fit is
    refused before anything is read instead of being killed by the kernel mid-training."""
    available = available_memory_bytes() if available is None else available
    if estimate is None or available is None:
        return
    items = estimate(cfg)
    total = sum(items.values())
    if total > available:
        parts = ", ".join(f"{name} {gib(size)}" for name, size in sorted(items.items(), key=lambda kv: -kv[1]))
        raise ConfigError(f"this run needs about {gib(total)} ({parts}; the scene's images come on top) but "
                          f"{gib(available)} is available; fix: lower what dominates (e.g. method.knn_k, "
                          "train.max_gaussians or data.max_size) or run it on a larger machine")
