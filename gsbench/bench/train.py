"""`gsbench bench train`: the training step of every method on fixed workloads, timed by phase.

Workloads (`WORKLOADS`): each method at the cpu preset on ``synthetic/spot`` (200x150, 49 views,
initial points in the masks' visual hull), stepped from a quarter of the cpu schedule (step 750 of
3000, in the densification window) or, when a loss term starts later, from the step after the last
term starts (GOF / RaDe-GS / IBGS 1501, SuGaR 1801, NeuSG's SDF terms 1001, past the window), so every term is
timed (``synthetic/spot`` has no glass: rt2dgs's passes run there at their cost on an opaque object); and ``3dgs-random-100k``: 3DGS from 100 000 random points in the scene sphere, stepped from
step 1 (what a capture without points and masks costs at the start); ``3dgs-visible-adam``: 3DGS
with the opt-in visible-only Adam (`gsbench.training.optim`); ``<method>-800x600-300k`` and ``-1m`` (every
method of `PAPER_METHODS`): the papers' size, ``synthetic/dtu-bunny`` made at 800x600 (DTU's 1600x1200 at
the papers' ``-r 2``) in the IDR layout, from 300 000 or 1 000 000 random Gaussians in the scene sphere, as
``3dgs-random-100k`` (the DTU-like and, by count, TnT-like sizes the papers reach; TnT's 980x545 images
have 11% more pixels), the budget twice that, stepped as the cpu-preset workloads. Each workload runs ``warmup``
steps, then ``steps`` timed steps of `gsbench.training.trainer.Trainer.train_step` (the real step: schedules,
render, loss, backward, densification, Adam, checks), seeded, in a temporary run folder. ``--run RUN_DIR``
(`bench_run_folder`) times a real run's steps instead, from its checkpoint: the state a training reaches, not a
workload's random Gaussians.

Phases, milliseconds per step (mean over the timed steps):

- ``projection``, ``sort_bin``, ``raster_fwd``, ``raster_bwd``, ``solid_fwd``, ``solid_bwd``: the rasterizer's own
  timers (`gsbench.raster.profiling.profile`; ``solid_*``: GGGS's stochastic-solid depth, docs/rasterizer.md §9a);
- ``render_rest``: the rest of the method's render call (building the raster input, 3D filter, IBGS's
  kNN covariance, …) = Trainer ``render`` − projection − sort_bin − raster_fwd;
- ``fwd.<term>``: each loss term's forward (the Trainer's ``loss`` phase split by term), ``loss_rest``
  the rest of that phase (the weighted sum, reading the values);
- ``bwd.<term>``: each term's own backward, from its value to the render outputs (made leaves) and
  the parameters it reads, measured in a separate pass of ``probe_steps`` steps (``torch.autograd.grad`` with the graph
  kept) so the timed steps are untouched;
- PGSR's multi-view terms render a neighbouring view themselves (docs/methods/pgsr.md §4.3): that render and its
  backward are in the first active one of the two terms (``fwd.pgsr_geo`` / ``bwd.pgsr_geo``; ``pgsr_ncc``'s when
  ``pgsr_geo`` has weight 0), not in the rasterizer timers above, which time the step's own render;
  ``neighbour.<phase>`` are the neighbour's rasterizer timers (`gsbench.raster.profiling.profile_as`), ``neighbour_raster``
  their sum: parts of those two terms, not more phases of the step;
- ``backward_rest`` = Trainer ``backward`` − raster_bwd − Σ bwd.<term>: the autograd glue and the
  projection's backward (not timed on its own: the fused projections run inside autograd);
- ``optimizer``, ``densify``, ``checks``: the Trainer's phases; ``other``: the step's wall time minus
  every Trainer phase (schedules, camera sampling).

``non_raster_share`` = 1 − (projection + sort_bin + raster_fwd + raster_bwd + neighbour_raster +
backward_rest) / step: what is neither rasterizer nor projection, counting all of ``backward_rest`` as
projection (so the share is a lower bound; the neighbour projection's backward stays in ``bwd.pgsr_geo``).
"""

from __future__ import annotations

import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch

import gsbench.training.trainer as train
from gsbench.config.files import paper_methods
from gsbench.data.cache import cache_dir
from gsbench.data.method_scene import scene_for_method
from gsbench.data.synthetic.make import make_scene
from gsbench.errors import ConfigError
from gsbench.losses.terms import Batch, active_terms, required_outputs
from gsbench.raster import profiling
from gsbench.registry import METHODS
from gsbench.resources import set_threads
from gsbench.run_folder import RunFolder
from gsbench.runs.finished_run import read_run_config
from gsbench.runs.runner import load_run_scene, make_run_scene, resolve_run

WARMUP, STEPS, PROBE_STEPS = 10, 30, 5
SCENE = "synthetic/spot"


@dataclass(frozen=True)
class Workload:
    method: str
    overrides: tuple[str, ...] = ()
    start: float = 0.25  # fraction of train.iterations to start at, or later when a term starts later (0: step 1)
    resolution: tuple[int, int] | None = None  # the papers' size: the scene made at (W, H) in the IDR layout
    gaussians: int = 0  # with ``resolution``: this many random initial Gaussians in the scene sphere

    def run_overrides(self) -> tuple[str, ...]:
        """The run config overrides of the workload (the papers' size: images, initial Gaussians and budget)."""
        if self.resolution is None:
            return self.overrides
        w, h = self.resolution
        return (*self.overrides, "data.downscale=1", f"data.max_size=[{w}, {h}]",
                f"method.random_init_points={self.gaussians}", "method.random_init_region=sphere",
                f"train.max_gaussians={2 * self.gaussians}")


PAPER_SCENE = "synthetic/dtu-bunny"  # scanned, framed as DTU
PAPER_METHODS = paper_methods()  # paper_benchmark: in configs/methods/<method>.yaml
PAPER_SIZES = {"800x600-300k": ((800, 600), 300_000), "800x600-1m": ((800, 600), 1_000_000)}


WORKLOADS = {
    **{m: Workload(m) for m in PAPER_METHODS},
    "3dgs-random-100k": Workload("3dgs", ("method.random_init_region=sphere",), start=0.0),
    "3dgs-visible-adam": Workload("3dgs", ("train.optimizer=visible_adam",)),
    **{f"{m}-{size}": Workload(m, resolution=res, gaussians=n) for m in PAPER_METHODS
       for size, (res, n) in PAPER_SIZES.items()},
}
RASTER_PHASES = ("projection", "sort_bin", "raster_fwd", "raster_bwd", "solid_fwd", "solid_bwd")
NEIGHBOUR = "neighbour."  # the profile tag of PGSR's neighbour render (methods/pgsr.py)


class _TermClock:
    """Replaces `gsbench.training.trainer.total_loss` during the timed steps: the same sum, each term's forward timed."""

    def __init__(self):
        self.seconds: dict[str, float] = {}

    def __call__(self, active, render, batch, state):
        total, values = torch.zeros(()), {}
        for term in active:
            t0 = time.perf_counter()
            value = term.spec(render, batch, state)
            self.seconds[term.name] = self.seconds.get(term.name, 0.0) + time.perf_counter() - t0
            values[term.name] = float(value.detach())
            total = total + term.weight * value
        return total, values


def _term_backward_seconds(trainer, step: int) -> dict[str, float]:
    """Each active term's own backward at ``step`` (module docstring, ``bwd.<term>``); no parameter changes."""
    m = trainer.method
    active = active_terms(trainer.losses, step, m.term_params())
    idx = trainer.views[step % len(trainer.views)]
    with torch.no_grad():
        render = m.render(trainer.scene.cameras[idx], required_outputs(active))
    leaves = []  # the render outputs as leaves: a term's backward stops there, not in the rasterizer
    for key, value in vars(render).items():
        if isinstance(value, torch.Tensor) and value.is_floating_point():
            setattr(render, key, value.detach().requires_grad_(True))
            leaves.append(getattr(render, key))
    inputs = leaves + [p for p in m.gaussians.params.values() if p.requires_grad]
    batch = Batch(trainer.images[idx], trainer.masks[idx], trainer.scene.cameras[idx], step, idx)
    seconds = {}
    for term in active:
        value = term.spec(render, batch, m.loss_state())
        t0 = time.perf_counter()
        if value.requires_grad:
            torch.autograd.grad(value, inputs, retain_graph=True, allow_unused=True)
        seconds[term.name] = time.perf_counter() - t0
    m.optimizer.zero_grad(set_to_none=True)
    return seconds


def paper_scene(resolution: tuple[int, int]) -> str:
    """The folder of `PAPER_SCENE` made at ``resolution`` in the IDR layout (no SfM points, so the initial
    Gaussians are the workload's random ones), generated once into the data cache."""
    w, h = resolution
    return str(make_scene(PAPER_SCENE, fmt="dtu", out=cache_dir() / "bench" / f"dtu-bunny-{w}x{h}", res=(w, h)))


def bench_workload(name: str, workload: Workload, *, steps: int = STEPS, warmup: int = WARMUP,
                   probe_steps: int = PROBE_STEPS, threads: int = 2, scenes: dict | None = None,
                   scene_name: str | None = None) -> dict:
    """Time one workload (module docstring); ``scenes`` caches loaded scenes between workloads. ``scene_name``
    replaces the workload's scene (`SCENE`, or the papers'-size scene made at its resolution)."""
    if scene_name is None:
        scene_name = SCENE if workload.resolution is None else paper_scene(workload.resolution)
    cfg = resolve_run(workload.method, scene_name, preset="cpu",
                      overrides=(*workload.run_overrides(), "train.checkpoint_every=0"))
    cfg.threads = threads
    scenes = {} if scenes is None else scenes
    key = (cfg.scene, tuple(cfg.data.max_size), cfg.data.downscale)
    if key not in scenes:
        make_run_scene(cfg)
        scenes[key] = load_run_scene(cfg)
    scene = scene_for_method(scenes[key], workload.method)
    method = METHODS.get(workload.method)()
    set_threads(threads)
    train.seed_everything(cfg.seed)
    method.setup(scene, cfg)
    with tempfile.TemporaryDirectory() as folder:
        trainer = train.Trainer(method, scene, cfg, folder)
        first = 1 if workload.start == 0 else max(round(workload.start * cfg.train.iterations),
                                                  max(t["start"] for t in trainer.losses.values() if t["weight"] > 0) + 1)
        result = _time_steps(name, workload, trainer, first, steps, warmup, probe_steps)
    result["resolution"] = [scene.cameras[0].width, scene.cameras[0].height]
    result["scene"] = scene_name
    return result


def bench_run_folder(folder, *, steps: int = STEPS, warmup: int = WARMUP, probe_steps: int = PROBE_STEPS,
                     threads: int = 2) -> dict:
    """Time the steps of a real run (``gsbench bench train --run RUN_DIR``) from its checkpoint: its resolved config,
    scene and trained state (``checkpoint.pt`` of a run in progress, else ``checkpoint-final.pt``), stepped on from
    the checkpoint's step (or, from a final checkpoint, over the schedule's last steps) in a temporary folder; the run's
    own folder is only read. What a step costs at that state: the Gaussians a real training has there, not a
    workload's."""
    cfg, checkpoint = read_run_config(folder, "gsbench bench train --run",
                                      (RunFolder.CHECKPOINT, RunFolder.FINAL_CHECKPOINT))
    cfg.threads = threads
    cfg.train.checkpoint_every = 0
    make_run_scene(cfg)
    scene = scene_for_method(load_run_scene(cfg), cfg.method["name"])
    method = METHODS.get(cfg.method["name"])()
    set_threads(threads)
    train.seed_everything(cfg.seed)
    method.setup(scene, cfg)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = train.Trainer(method, scene, cfg, tmp)
        trainer.load_state_dict(train.load_checkpoint(checkpoint))
        saved = trainer.step
        first = max(1, min(saved + 1, cfg.train.iterations - warmup - steps - probe_steps + 1))
        result = _time_steps(f"run {Path(folder).name}", Workload(cfg.method["name"]), trainer, first, steps, warmup,
                             probe_steps)
    result.update(resolution=[scene.cameras[0].width, scene.cameras[0].height], scene=cfg.scene, run=str(folder),
                  checkpoint_step=saved, preset=cfg.preset)
    return result


def _time_steps(name: str, workload: Workload, trainer, first: int, steps: int, warmup: int, probe_steps: int) -> dict:
    """``warmup`` untimed then ``steps`` timed steps of ``trainer`` from ``first``, and the terms' backward probe
    (module docstring); the result of `_phases_ms`."""
    method = trainer.method
    initial = len(method.gaussians)
    for step in range(first, first + warmup):
        trainer.train_step(step)
    trainer.phases = dict.fromkeys(trainer.phases, 0.0)
    clock, original = _TermClock(), train.total_loss
    profiling.profile, train.total_loss = {}, clock
    n_start = len(method.gaussians)
    per_step = []
    try:
        for step in range(first + warmup, first + warmup + steps):
            t0 = time.perf_counter()
            trainer.train_step(step)
            per_step.append(time.perf_counter() - t0)
        prof = dict(profiling.profile)
    finally:
        profiling.profile, train.total_loss = None, original
    n_end = len(method.gaussians)
    probe = [_term_backward_seconds(trainer, first + warmup + steps + k) for k in range(probe_steps)]
    return _phases_ms(name, workload, per_step, trainer.phases, prof, clock.seconds, probe,
                      {"initial": initial, "timed_start": n_start, "timed_end": n_end}, first + warmup)


def _phases_ms(name, workload, per_step, phases, prof, term_fwd, probe, gaussians, first_timed) -> dict:
    n = len(per_step)
    ms = {k: 1e3 * v / n for k, v in prof.items() if k in RASTER_PHASES}
    ms.update({k: ms.get(k, 0.0) for k in RASTER_PHASES})
    step_ms = 1e3 * sum(per_step) / n
    trainer_ms = {k: 1e3 * v / n for k, v in phases.items()}
    ms["render_rest"] = trainer_ms["render"] - ms["projection"] - ms["sort_bin"] - ms["raster_fwd"] - ms["solid_fwd"]
    ms.update({f"fwd.{t}": 1e3 * s / n for t, s in term_fwd.items()})
    ms["loss_rest"] = trainer_ms["loss"] - sum(1e3 * s / n for s in term_fwd.values())
    bwd = {t: 1e3 * statistics.mean(p.get(t, 0.0) for p in probe) for t in term_fwd} if probe else {}
    ms.update({f"bwd.{t}": v for t, v in bwd.items()})
    ms["backward_rest"] = trainer_ms["backward"] - ms["raster_bwd"] - ms["solid_bwd"] - sum(bwd.values())
    for k in ("optimizer", "densify", "checks"):
        ms[k] = trainer_ms[k]
    ms["other"] = step_ms - sum(trainer_ms.values())
    ms.update({NEIGHBOUR + k: 1e3 * prof.get(NEIGHBOUR + k, 0.0) / n for k in RASTER_PHASES})
    ms["neighbour_raster"] = sum(ms[NEIGHBOUR + k] for k in RASTER_PHASES)
    raster_ms = sum(ms[k] for k in RASTER_PHASES) + ms["neighbour_raster"] + ms["backward_rest"]
    return {"workload": name, "method": workload.method, "overrides": list(workload.overrides),
            "preset": "cpu", "first_timed_step": first_timed, "steps": n,
            "step_ms": step_ms, "step_ms_median": 1e3 * statistics.median(per_step), "it_per_s": 1e3 / step_ms,
            "phases_ms": ms, "non_raster_share": 1.0 - raster_ms / step_ms, "gaussians": gaussians}


def run_train_benchmark(workloads=None, *, steps: int = STEPS, warmup: int = WARMUP, probe_steps: int = PROBE_STEPS,
                        threads: int = 2, echo=print) -> dict:
    """Every workload named (default: all of `WORKLOADS`); returns {"threads", "results": [...]}."""
    names = list(workloads or WORKLOADS)
    unknown = [n for n in names if n not in WORKLOADS]
    if unknown:
        raise ConfigError(f"unknown train workload(s) {unknown}; available: {', '.join(WORKLOADS)}")
    scenes: dict = {}
    results = []
    for name in names:
        echo(f"bench train: {name} ({warmup} warm-up + {steps} timed steps, {threads} threads)")
        results.append(bench_workload(name, WORKLOADS[name], steps=steps, warmup=warmup, probe_steps=probe_steps,
                                      threads=threads, scenes=scenes))
    return {"threads": threads, "steps": steps, "warmup": warmup, "probe_steps": probe_steps, "results": results}


def format_table(result: dict) -> str:
    """Rows: workloads; columns: ms/step, it/s, the rasterizer phases (s.: the solid depth), loss terms (fwd+bwd; in brackets the
    neighbour render's rasterizer share of them), the rest."""
    header = ["workload", "N", "ms/step", "it/s", "proj", "sort", "r.fwd", "r.bwd", "s.fwd", "s.bwd", "bwd.rest",
              "render.rest", "terms", "(nb.raster)", "optim", "densify", "checks", "other", "non-raster"]
    rows = [header]
    for r in result["results"]:
        p = r["phases_ms"]
        terms = sum(v for k, v in p.items() if k.startswith(("fwd.", "bwd."))) + p["loss_rest"]
        rows.append([r["workload"], str(r["gaussians"]["timed_start"]), f"{r['step_ms']:.1f}", f"{r['it_per_s']:.2f}",
                     *(f"{p[k]:.1f}" for k in ("projection", "sort_bin", "raster_fwd", "raster_bwd", "solid_fwd",
                                                 "solid_bwd", "backward_rest", "render_rest")),
                     f"{terms:.1f}", f"({p['neighbour_raster']:.1f})",
                     *(f"{p[k]:.1f}" for k in ("optimizer", "densify", "checks", "other")),
                     f"{100 * r['non_raster_share']:.0f}%"])
    widths = [max(len(row[i]) for row in rows) for i in range(len(header))]
    lines = ["  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(row, widths))) for row in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    terms = []
    for r in result["results"]:
        p = r["phases_ms"]
        parts = [f"{k[4:]} {p[k]:.1f}+{p.get('bwd.' + k[4:], 0.0):.1f}" for k in p if k.startswith("fwd.")]
        terms.append(f"  {r['workload']}: " + ", ".join(parts))
    return "\n".join(lines + ["loss terms, ms forward+backward:"] + terms)
