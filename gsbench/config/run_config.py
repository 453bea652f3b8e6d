"""Run configuration: stdlib dataclasses, YAML layering, ``--set a.b=c`` overrides, canonical run id.

Layers, each overriding the previous (docs/design.md §9.1):

    code defaults <- configs/methods/<method>.yaml <- configs/datasets/<dataset>.yaml
                  <- configs/methods/<method>.<dataset>.yaml
                  <- configs/presets/<preset>.yaml <- user YAML files
                  <- a finished run's recorded config (``recorded``, reading a run back) <- --set a.b=c

A method yaml that starts with ``extends: <base>`` is preceded by the base's method layer, and its
``<method>.<dataset>`` layer by the base's (`_method_layers`).

The optional ``<method>.<dataset>.yaml`` layer holds what a paper sets per dataset for one method
(e.g. GOF's λ_d 1000 on DTU and 100 on TnT, its tetrahedra mesh on TnT); it overrides the dataset
layer and is overridden by the preset.

Keys are strict: an unknown key anywhere is a `ConfigError` with a "did you mean" suggestion.
The ``method`` section holds the method name plus its hyper-parameters; a plain string
(``method: 2dgs`` in a sweep base) is shorthand for ``method: {name: 2dgs}``.
``losses`` maps a loss-term name to ``{weight, start, end}``; the term names are checked against the
loss registry when training starts.
The run id is the first 12 hex digits of sha1 over the canonical JSON of the resolved config without
execution-only fields (``threads``, ``out``, ``gt``) and without the fields `ADDED_AFTER_RECORDS` lists when
they hold the default stated there, so the same experiment always has the same id, and adding a field keeps
the ids of the runs recorded before it. The resolved config itself (shown by ``gsbench config``, saved in
a run's folder and record) holds every field.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import math
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from gsbench.config.files import DECLARATION_KEYS, config_root, load_yaml, suggest
from gsbench.config.suites import reject_suite_scene
from gsbench.data.loader import BUILTIN_SCENES, detect_format, has_ground_truth
from gsbench.data.tnt import TNT_FRAMES
from gsbench.errors import ConfigError

EXECUTION_ONLY_KEYS = ("threads", "out", "gt")
# (method, dotted key, default) of the fields added after records of that method existed (method None: of every
# method), the default being the value those records ran with (kept here should the field's own default change): at
# that value a field is left out of the run id, so those records keep theirs (`completed_config` fills it into their
# configs). SuGaR's refinement stage (docs/methods/sugar.md §6), the points of anytime evaluation
# (docs/training.md §9), the TnT training frame (docs/design.md §12.1), GGGS's surface depth
# (docs/methods/gggs.md §3.5) and NeuSG's hash encoding (docs/methods/neusg.md §5.1) came after the suites' records.
ADDED_AFTER_RECORDS = (
    ("sugar", "method.refinement", "none"),
    ("sugar", "method.refine_gaussians_per_triangle", 1),
    ("sugar", "method.refine_triangles", 50_000),
    ("gggs", "method.surface_depth", "solid"),
    ("neusg", "method.encoding", "dense"),
    ("neusg", "method.hash_table_log2", 19),
    ("neusg", "method.grid_active_start", 0),
    ("neusg", "method.grid_level_step", 300),
    (None, "eval.points", []),
    (None, "eval.dtu_sampled", True),
    (None, "data.tnt_frame", "extent"),
)
HOLDOUT_WITHOUT_GT = 8  # data.holdout_every "auto" (-1) on a scene without ground truth: 3DGS --eval


@dataclass
class DataConfig:
    """How the scene is loaded and its masks used. ``downscale`` divides the image size (DTU/TnT papers
    use 2); ``max_size`` [long side, short side] in pixels caps it whatever the files on disk
    (`gsbench.data.resolution.fit_downscale`; the cpu and quick presets set it, [] = no cap).
    ``holdout_every``: every k-th view (``i % k == 0``) is held out of training and scored by the
    ``image`` evaluator; 0 = none; -1 = auto: 8 on a scene without ground truth (its only image
    measure of quality, as 3DGS ``--eval``), else 0 — resolved when the config is (`resolve`).
    ``use_masks``: the scene's masks zero the depth outside the object before TSDF fusion and
    reach the loss terms (2DGS on DTU). ``mask_target``: also composite the GT image over the render
    background outside the mask, so training never sees the real background (the 2023 3DGS intent;
    off by default: the papers train DTU on full images). ``tnt_frame``: the training frame of a
    Tanks-and-Temples layout (`gsbench.data.tnt`): ``colmap``, the papers' (COLMAP units), which
    configs/datasets/tnt.yaml selects, or ``extent`` (divided by the cameras' extent), the frame of the
    records made before the key, and so its default (`ADDED_AFTER_RECORDS`; docs/design.md §12.1); a DTU
    scene has one frame and takes the default only."""

    downscale: float = 1.0
    max_size: list = field(default_factory=list)
    use_masks: bool = True
    mask_target: bool = False
    holdout_every: int = -1
    white_background: bool = False
    tnt_frame: str = "extent"


@dataclass
class TrainConfig:
    """Schedule-independent training settings; method-specific schedules live in ``method``."""

    iterations: int = 30000
    checkpoint_every: int = 5000
    log_every: int = 100
    max_gaussians: int = 0
    scale_refine_interval: bool = False  # gsbench.training.trainer.scaled_strategy
    optimizer: str = "adam"  # gsbench.training.optim: adam (the papers') or visible_adam (opt-in, not the papers' update)


@dataclass
class RasterConfig:
    """Rasterizer options; lengths relative to the scene radius (see `gsbench.raster.RasterSettings`)."""

    near_plane: float = 0.2
    far_plane: float = 100.0
    antialias2d: float = 0.0
    eps2d: float = -1.0  # screen-space dilation of the EWA covariance; < 0: the kernel's default (ewa 0.3)
    surfel_filter: float = 2.0  # k of the surfel kernel's low-pass term k|Δ|² (2DGS: 2); 0: off
    sh_degree: int = 3


@dataclass
class MeshConfig:
    """Mesh extraction; lengths relative to the scene radius unless ``absolute`` is true.

    ``extractor``: ``tsdf`` (fused rendered ``depth``; ``voxel_size``, ``sdf_trunc``, ``depth_trunc``,
    ``num_clusters``) or ``tets`` (GOF marching tetrahedra on the opacity ``level`` set with
    ``bisection_steps`` bisection steps, docs/methods/gof.md §7) or ``poisson`` (SuGaR: points on the
    density ``level`` set along the rays of the rendered ``depth``, screened Poisson,
    `gsbench.mesh.levelset`, docs/methods/sugar.md §4); which ones a method supports is its own.
    ``poisson_depth``: octree depth (SuGaR 10; 0 = from the pixel footprint, at most 10);
    ``poisson_density_quantile``: vertices below this quantile of the Poisson density are removed (0.1);
    ``poisson_points``: level-set points kept over all views (SuGaR's n_total_points, 10M);
    ``poisson_triangles``: quadric decimation target in triangles (1M; 0 = no decimation).
    """

    extractor: str = "tsdf"
    depth: str = "median"
    voxel_size: float = 0.004
    sdf_trunc: float = 0.016
    depth_trunc: float = 3.0
    absolute: bool = False
    num_clusters: int = 1
    level: float = 0.5
    bisection_steps: int = 8
    poisson_depth: int = 0
    poisson_density_quantile: float = 0.1
    poisson_points: int = 10_000_000
    poisson_triangles: int = 1_000_000


@dataclass
class EvalConfig:
    """Evaluators to run. Empty: the dataset's defaults (`gsbench.evaluators.resolve`), each skipped with
    its reason when the scene lacks what it needs; named: every one must apply, checked before loading.
    ``points``: where training stops to extract and evaluate the mesh as at its end (anytime evaluation,
    docs/training.md §9), steps (int >= 1) or fractions of the run (float in (0, 1)), `point_steps`; the end
    is always a point, [] = only the end."""

    evaluators: list = field(default_factory=list)
    dtu_culling: str = "2dgs"  # mask culling before the DTU protocol: 2dgs, gof or none (`gsbench.evaluators.culling`)
    points: list = field(default_factory=list)
    dtu_sampled: bool = True  # dtu_chamfer also on area samples (*_sampled, docs/evaluation.md §2.4); off: the official steps only


@dataclass
class LossTerm:
    """One weighted, scheduled loss term; ``end`` < 0 means until the last step."""

    weight: float = 0.0
    start: int = 0
    end: int = -1


@dataclass
class RunConfig:
    """The fully resolved description of one run (what the run id hashes)."""

    scene: str = "synthetic/spot"
    preset: str = "cpu"
    seed: int = 0
    threads: int = 0
    out: str = "runs"
    gt: str = ""  # --gt: folder holding the ground truth when it is not beside the scene (not part of the run id)
    method: dict = field(default_factory=lambda: {"name": ""})
    losses: dict = field(default_factory=dict)
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    raster: RasterConfig = field(default_factory=RasterConfig)
    mesh: MeshConfig = field(default_factory=MeshConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @property
    def run_id(self) -> str:
        return run_id(self.to_dict())


def point_steps(cfg: RunConfig) -> list[int]:
    """The steps of ``eval.points`` in order: a step as given, a fraction f of the run at
    ``max(1, round(f · train.iterations))``; the end, always a point, is not among them. A value that is neither,
    one at or past the end, and two at one step are each a `ConfigError` naming the fix."""
    iterations, steps = cfg.train.iterations, {}
    hint = "eval.points takes steps (int >= 1) or fractions of the run (float in (0, 1)), e.g. [0.1, 0.25, 0.5]"
    for value in cfg.eval.points:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"eval.points: {value!r} is not a number; {hint}")
        if isinstance(value, float) and not 0 < value < 1:
            raise ConfigError(f"eval.points: {value} is a fraction of the run and must be in (0, 1); {hint} (write "
                              "a step as an integer, e.g. 300)")
        if isinstance(value, int) and value < 1:
            raise ConfigError(f"eval.points: step {value} must be >= 1; {hint}")
        step = value if isinstance(value, int) else max(1, round(value * iterations))
        if step >= iterations:
            raise ConfigError(f"eval.points: {value} is step {step}, not before the end of the run (train.iterations "
                              f"{iterations}), which is always a point; fix: drop it or name an earlier step")
        if step in steps:
            raise ConfigError(f"eval.points: {steps[step]!r} and {value!r} are both step {step} of {iterations}; fix: "
                              "drop one (a short run has fewer distinct steps)")
        steps[step] = value
    return sorted(steps)


def run_id(resolved: dict) -> str:
    """sha1 of the canonical JSON (sorted keys, no whitespace) of ``resolved`` minus the execution-only keys and
    the `ADDED_AFTER_RECORDS` fields at their defaults, 12 hex."""
    identity = copy.deepcopy({k: v for k, v in resolved.items() if k not in EXECUTION_ONLY_KEYS})
    for section, name, default in _added_fields(identity):
        if section.get(name, default) == default:
            section.pop(name, None)
    canonical = json.dumps(identity, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha1(canonical.encode()).hexdigest()[:12]


def completed_config(recorded: dict) -> dict:
    """A copy of the resolved config ``recorded`` (a record's or a run folder's), with the `ADDED_AFTER_RECORDS` fields
    its method has and it predates at their defaults: what it was run with."""
    completed = copy.deepcopy(recorded)
    for section, name, default in _added_fields(completed):
        section.setdefault(name, default)
    return completed


def _added_fields(config: dict) -> list[tuple[dict, str, Any]]:
    """(the section of ``config`` holding it, its name, its default) of each `ADDED_AFTER_RECORDS` field of the
    config's method (or of every method) whose section ``config`` has."""
    method = config.get("method", {}).get("name") if isinstance(config.get("method"), dict) else None
    found = []
    for owner, key, default in ADDED_AFTER_RECORDS:
        *parents, name = key.split(".")
        section = config
        for part in parents:
            section = section.get(part) if isinstance(section, dict) else None
        if owner in (None, method) and isinstance(section, dict):
            found.append((section, name, default))
    return found


def parse_override(text: str) -> dict:
    """``a.b=c`` -> ``{"a": {"b": c}}`` with ``c`` parsed as YAML (numbers, bools, lists)."""
    if "=" not in text:
        raise ConfigError(f"override '{text}' must look like key.path=value, e.g. train.iterations=500")
    key, _, raw = text.partition("=")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError as exc:
        raise ConfigError(f"override '{text}': the value is not valid YAML ({exc})") from exc
    node: dict = {}
    cursor = node
    parts = key.strip().split(".")
    if not all(parts):
        raise ConfigError(f"override '{text}' has an empty key part")
    for part in parts[:-1]:
        cursor = cursor.setdefault(part, {})
    cursor[parts[-1]] = value
    return node


def _normalise_method(layer: dict) -> dict:
    if isinstance(layer.get("method"), str):
        layer = {**layer, "method": {"name": layer["method"]}}
    return layer


def _merge(base: dict, layer: dict) -> dict:
    """Recursive dict merge; ``layer`` wins; lists and scalars are replaced, not merged."""
    out = copy.deepcopy(base)
    for key, value in layer.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


_SCALAR_TYPES = {int: (int,), float: (int, float), bool: (bool,), str: (str,), list: (list,), dict: (dict,)}


def _check_value(path: str, value: Any, expected: type) -> Any:
    """Type-check one leaf; ints are accepted for floats; bools are not accepted as numbers."""
    allowed = _SCALAR_TYPES.get(expected)
    if allowed is None:
        return value
    if expected in (int, float) and isinstance(value, bool):
        allowed = ()
    if not isinstance(value, allowed):
        raise ConfigError(f"config key '{path}' must be {expected.__name__}, found {value!r}")
    return float(value) if expected is float else value


def _build(cls, data: dict, path: str):
    """Instantiate dataclass ``cls`` from ``data`` strictly (unknown keys and bad types fail)."""
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    kwargs = {}
    for key, value in data.items():
        full = f"{path}{key}"
        if key not in names:
            raise ConfigError(f"unknown config key '{full}'{suggest(key, names)}; valid keys: {', '.join(names)}")
        hint = hints[key]
        if dataclasses.is_dataclass(hint):
            if not isinstance(value, dict):
                raise ConfigError(f"config key '{full}' must be a mapping, found {value!r}")
            kwargs[key] = _build(hint, value, f"{full}.")
        else:
            origin = typing.get_origin(hint) or hint
            kwargs[key] = _check_value(full, value, origin)
    return cls(**kwargs)


def _build_losses(data: dict) -> dict:
    terms = {}
    for name, spec in data.items():
        if isinstance(spec, (int, float)) and not isinstance(spec, bool):
            spec = {"weight": spec}
        if not isinstance(spec, dict):
            raise ConfigError(f"losses.{name} must be a mapping {{weight, start, end}} or a number, found {spec!r}")
        term = _build(LossTerm, spec, f"losses.{name}.")
        if not math.isfinite(term.weight) or term.weight < 0:
            raise ConfigError(f"losses.{name}.weight must be a finite number >= 0 (0 switches the term off; a "
                              f"negative weight would reward the loss it weighs), got {term.weight}")
        if term.start < 0 or term.end < -1:
            raise ConfigError(f"losses.{name}: start must be >= 0 and end >= -1 (-1: until the last step), got "
                              f"start {term.start}, end {term.end}")
        terms[name] = dataclasses.asdict(term)
    return terms


def _build_method(data: dict, method_config_cls) -> dict:
    name = data.get("name", "")
    params = {k: v for k, v in data.items() if k != "name"}
    if method_config_cls is None:
        return {"name": name, **params}
    return {"name": name, **dataclasses.asdict(_build(method_config_cls, params, "method."))}


def dataset_of(scene: str) -> str:
    """The dataset config name of a scene, ``dtu`` or ``tnt``: from the built-in table or the folder layout."""
    if scene in BUILTIN_SCENES:
        return BUILTIN_SCENES[scene].format
    return detect_format(Path(scene)).split("-")[0]


def _method_layers(root: Path, method: str, dataset: str, chain: tuple = ()) -> tuple[list[dict], list[dict]]:
    """(method layers, method-per-dataset layers) of ``method``, its ``extends`` ancestors' first.

    ``configs/methods/<m>.yaml`` may start with ``extends: <base method>``: the base's layers come first,
    so a variant (e.g. ``ibgs`` on ``radegs``) states only what it adds. Cycles are errors.
    """
    if method in chain:
        raise ConfigError(f"configs/methods: 'extends' loops through {' -> '.join((*chain, method))}")
    own_file, own_dataset_file = root / "methods" / f"{method}.yaml", root / "methods" / f"{method}.{dataset}.yaml"
    own = load_yaml(own_file) if own_file.is_file() else {}
    own_dataset = load_yaml(own_dataset_file) if own_dataset_file.is_file() else {}
    for key in DECLARATION_KEYS:  # the method's class and its paper's numbers: what it is, not a setting
        own.pop(key, None)
    base = own.pop("extends", None)
    if base is None:
        return [own], [own_dataset]
    if not (root / "methods" / f"{base}.yaml").is_file():
        raise ConfigError(f"{own_file}: extends '{base}', which has no configs/methods/{base}.yaml")
    base_layers, base_dataset_layers = _method_layers(root, str(base), dataset, (*chain, method))
    return [*base_layers, own], [*base_dataset_layers, own_dataset]


def resolve(
    method: str,
    scene: str,
    *,
    preset: str = "cpu",
    user_files=(),
    overrides=(),
    method_config_cls=None,
    seed: int | None = None,
    gt: str | None = None,
    recorded: dict | None = None,
) -> RunConfig:
    """Resolve every layer into a validated `RunConfig`.

    ``method_config_cls`` is the method plugin's ``Config`` dataclass (its defaults are the paper's);
    when None the method section is taken as given (used before a method is registered). ``gt`` is
    the ground-truth folder (``--gt``). ``data.holdout_every = -1`` is resolved here (`DataConfig`).
    ``recorded``: a run's resolved config (its folder's ``config.yaml``, its record's), layered after the
    user files and completed first (`completed_config`), so a layer that now sets a field added after the
    run (``data.tnt_frame`` in the TnT dataset layer) does not change what the run was run with.
    """
    reject_suite_scene(scene)  # ``suite:<name>`` is several runs: a sweep, not one run
    root = config_root()
    merged: dict = {"method": {"name": method}, "scene": scene, "preset": preset}
    dataset = dataset_of(scene)
    preset_file = root / "presets" / f"{preset}.yaml"
    if not preset_file.is_file():
        available = sorted(p.stem for p in (root / "presets").glob("*.yaml"))
        raise ConfigError(f"unknown preset '{preset}'{suggest(preset, available)}; available: {', '.join(available)}")
    method_layers, method_dataset_layers = _method_layers(root, method, dataset)
    dataset_file = root / "datasets" / f"{dataset}.yaml"
    layers = [*method_layers, load_yaml(dataset_file) if dataset_file.is_file() else {}, *method_dataset_layers,
              load_yaml(preset_file)]
    for layer in layers:
        merged = _merge(merged, _normalise_method(layer))
    for user_file in user_files:
        merged = _merge(merged, _normalise_method(load_yaml(Path(user_file))))
    if recorded is not None:
        merged = _merge(merged, _normalise_method(completed_config(recorded)))
    for text in overrides:
        merged = _merge(merged, _normalise_method(parse_override(text)))
    if seed is not None:
        merged["seed"] = seed
    if gt:
        merged["gt"] = str(gt)
    if merged["method"].get("name") != method:
        raise ConfigError(
            f"a config layer changed the method to '{merged['method'].get('name')}'; "
            f"choose the method with --method instead"
        )
    merged["method"] = _build_method(merged["method"], method_config_cls)
    merged["losses"] = _build_losses(merged.get("losses", {}))
    cfg = _build(RunConfig, merged, "")
    if cfg.data.holdout_every < -1:
        raise ConfigError(f"data.holdout_every must be >= 0 (every k-th view held out; 0 = none) or -1 (auto), "
                          f"got {cfg.data.holdout_every}")
    if cfg.data.tnt_frame not in TNT_FRAMES:
        raise ConfigError(f"data.tnt_frame must be one of {', '.join(TNT_FRAMES)}, got '{cfg.data.tnt_frame}' "
                          "(docs/design.md §12.1)")
    if dataset != "tnt" and cfg.data.tnt_frame != DataConfig.tnt_frame:
        raise ConfigError(f"data.tnt_frame={cfg.data.tnt_frame} applies to Tanks-and-Temples layouts only; scene "
                          f"'{scene}' is a {dataset} layout, which has one training frame; fix: drop the key")
    if cfg.data.holdout_every == -1:
        cfg.data.holdout_every = 0 if has_ground_truth(cfg.scene, cfg.gt or None) else HOLDOUT_WITHOUT_GT
    return cfg
