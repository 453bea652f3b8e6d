"""The one training loop (docs/design.md §4: the Trainer owns the loop, methods declare data).

Per step ``t = 1 … train.iterations`` (3DGS ``train.py`` order, docs/methods/3dgs.md §5.2):

1. ``method.update_schedules(t, scale)`` — position lr decay and SH degree;
2. next camera from a seeded shuffled stack, refilled when empty (one epoch = one pass, docs/methods/3dgs.md §1.4);
3. active terms = `gsbench.losses.terms.active_terms` of the scaled loss config with the method's term
   parameters; the render computes only their `required_outputs` (weight 0 removes a term's outputs);
4. L = Σ weight·term; non-finite L is a `NumericalError` naming the terms and the step;
5. backward; ``strategy.step_post_backward`` (densify / prune / opacity reset);
6. Adam step (skipped on the last step, as 3DGS); with ``train.optimizer: visible_adam`` only the
   rows of the Gaussians this view sees (`gsbench.training.optim`).

Checks: a non-finite loss is a `NumericalError` at once (one scalar test a step); the parameters are
tested every `PARAMETER_CHECK_EVERY` steps, before every checkpoint and at the last step, with one
reduction per parameter group (`Gaussians.check_finite`), and the error names the parameter and the
step it was found at. A parameter gone non-finite between two checks is caught earlier anyway: the
rasterizer tests its inputs on every render (`gsbench.raster.validate_gaussians`), so the next step
fails naming the rendered quantity.

Schedule scaling — the one place presets change the schedule: every step-valued setting of the
paper's 30 000-step run (loss ``start``/``end``, the densification window/interval/opacity reset via
`DefaultStrategy.scaled`, the position-lr decay length and the SH interval via
``method.update_schedules``) is multiplied by ``scale = train.iterations / 30000`` with `scale_step`
(rounded, at least 1; 0 and negative "unset" values stay), except the refinement interval, which
stays 100 steps unless ``train.scale_refine_interval`` (`scaled_strategy` says why). A 3 000-step cpu
run therefore densifies every 100 steps over steps 50–1500, resets opacity every 300 steps, starts
λ_d at 300 and λ_n at 700: the same fractions of the run as the paper's 30 000 steps.

Masks (``data.use_masks`` with a scene that has masks): ``batch.mask`` is passed to the terms (their
``use_mask`` parameter, off by default); the GT image is used whole, as 2DGS, GOF and RaDe-GS train on
DTU. With ``data.mask_target`` as well, the GT image is composited over the render background,
``gt' = mask·gt + (1 − mask)·bg`` (the 2023 3DGS intent), so background pixels ask for empty space:
Gaussians there only raise the loss and are pruned instead of spawned. On a scene whose background
is black anyway (synthetic/spot and the other object-in-black scenes) the two differ only at the
anti-aliased silhouette pixels.

Checkpoints (``checkpoint.pt`` every ``train.checkpoint_every`` steps, ``checkpoint-final.pt`` at the
end, both written atomically) hold the method state (parameters, Adam moments), the strategy state,
the python/numpy/torch RNG states, the camera stack and the step, so a resumed run is bit-identical
to an uninterrupted one with the same seed and thread count. ``metrics.jsonl`` gets one line every
``train.log_every`` steps: step, each term (unweighted), total, num_gaussians, it/s. Training time
(`TrainResult.seconds`, summed over resumes) counts the steps and logging, not checkpoint writes;
`TrainResult.cpu_seconds` is the process's CPU time over the same intervals (`time.process_time`: every
thread's, so about ``threads`` times the wall time when the cores are free, and at one thread the time a
quiet core would take when other processes share the cores); None for a run resumed from a checkpoint written
before it was kept, whose earlier steps' CPU time is unknown.

Phases: `Trainer.train_step` times each part of a step with ``time.perf_counter`` and adds it to
`Trainer.phases` (`STEP_PHASES`): ``render`` (the method's forward render), ``loss`` (`total_loss`),
``backward`` (``strategy.step_pre_backward`` + ``loss.backward()``), ``densify``
(``strategy.step_post_backward``), ``optimizer`` (Adam step + ``zero_grad``) and ``checks`` (the
finiteness tests of the loss and of the parameters). The sums are part of the checkpoint (a
checkpoint without them, written before they existed, resumes from zeros), so a resumed run's phases
cover all its steps like `TrainResult.seconds`, and they sum to at most that (the rest is the
schedule update, camera sampling, logging and progress output). `TrainResult.phases` holds them next
to the method's own phases (`Method.training_phases`, e.g. IBGS's ``knn`` and ``local_geometry``
in methods/ibgs.py); the method's keep their names, and a step phase whose name a method also uses
is reported as ``step.<name>`` instead. Method phases run *inside* the step phases (IBGS's
eigen-decomposition within ``render`` and ``backward``), so the two sets overlap and must not be
added together. The runner (gsbench/runs/runner.py) records every entry as ``train.<name>``.

Budget: with ``train.max_gaussians`` > 0 a refinement may leave densification candidates out
(`DefaultStrategy` clone/split candidates, IBGS's SADC pairs: the info's ``budget_cut``).
`DensifyBudget` keeps the first step at which one did and how many it left out in all; it is part of
the checkpoint and of `TrainResult`, and the runner records it as ``densify_budget``, so a report can
say which methods' geometry was made under a binding budget and from when.

Progress: the tqdm bar draws itself only on a terminal; when stderr is not one (a run logged to a
file), `gsbench.training.progress.ProgressLines` prints a line with the step, it/s, the latest total loss, N
and the ETA every `Trainer.progress_interval` seconds (30 by default) and a final line at the end.
"""

from __future__ import annotations

import dataclasses
import json
import pickle
import random
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from gsbench.atomic import atomic_path
from gsbench.config.run_config import RunConfig
from gsbench.data.camera import Scene
from gsbench.errors import CheckpointError, ConfigError, NumericalError, one_line
from gsbench.losses.terms import Batch, active_terms, required_outputs, total_loss
from gsbench.resources import keep_freed_memory, set_threads
from gsbench.run_folder import RunFolder
from gsbench.training.optim import VisibleAdam
from gsbench.training.progress import DEFAULT_INTERVAL, ProgressLines
from gsbench.training.strategies.base import REFERENCE_ITERATIONS

STEP_PHASES = ("render", "loss", "backward", "densify", "optimizer", "checks")
PARAMETER_CHECK_EVERY = 50  # steps between finiteness checks of the parameters (module docstring, "Checks")
STEP_PHASE_PREFIX = "step."


def scale_step(value: int, scale: float) -> int:
    """A paper step count scaled to this run: ``max(1, round(value·scale))``; values <= 0 unchanged."""
    return int(value) if value <= 0 else max(1, round(value * scale))


def schedule_scale(iterations: int) -> float:
    """iterations / 30000: the factor every step-valued setting is multiplied by (module docstring)."""
    return iterations / REFERENCE_ITERATIONS


def scaled_losses(losses: dict, scale: float) -> dict:
    """The loss config with ``start`` and ``end`` scaled (weights unchanged): the effective terms."""
    return {name: {"weight": float(t["weight"]), "start": scale_step(t["start"], scale),
                   "end": scale_step(t["end"], scale)} for name, t in losses.items()}


def scaled_strategy(strategy, iterations: int, scale_refine_interval: bool = False):
    """The strategy's schedule for this run (module docstring, "Schedule scaling").

    `DefaultStrategy.scaled` scales the window and the reset interval. By default the refinement
    interval keeps the paper's absolute value and the reset interval is rounded to a multiple of it,
    because both are counts of Adam steps, not fractions of the run: a reset sets o <= 0.01 and the
    next refinement, ``refine_every`` steps later, prunes o < ``prune_opacity`` (0.05 for 2DGS),
    which Adam (opacity lr 0.05 per step on the logit) can only climb back above after ~40+ steps.

    ``scale_refine_interval`` (``train.scale_refine_interval``) scales the interval too, so a short
    run keeps the paper's number of refinement rounds (145), and sets ``prune_grace`` to the paper's
    interval, so low-opacity pruning still waits that many Adam steps after each reset (at the
    paper's schedule both choices are the same). Measured on synthetic/spot, cpu preset, 2DGS:
    Chamfer 1.157 mm with it vs 1.312 mm without (13.7k vs 4.3k surfels; 657 vs 415 s training, 2 threads).
    """
    if not hasattr(strategy, "scaled"):
        return strategy
    paper_every = strategy.refine_every
    scaled = strategy.scaled(iterations)
    every = scaled.refine_every if scale_refine_interval else paper_every
    grace = paper_every if scale_refine_interval else strategy.prune_grace
    return dataclasses.replace(scaled, refine_every=every, prune_grace=grace,
                               reset_every=every * max(1, round(scaled.reset_every / every)))


def seed_everything(seed: int) -> None:
    """One seed for python, numpy and torch (docs/design.md §12.2)."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def save_atomic(obj, path: Path) -> None:
    """``torch.save`` to a temp file in the same folder, then ``os.replace`` (`gsbench.atomic`)."""
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def load_checkpoint(path: Path) -> dict:
    """A checkpoint read as data: ``torch.load(weights_only=True)`` accepts tensors and plain values (numbers,
    strings, lists, tuples, dicts) and never runs code from the file. A file that holds anything else (an
    object to unpickle, as a checkpoint made to run code does, or a gsbench checkpoint from before the RNG
    states were stored as tensors) or that is damaged is a `CheckpointError` naming it, before anything in it
    is executed."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise CheckpointError(
            f"{path} is refused: it holds objects other than tensors and plain values, which loading would run "
            f"as code ({one_line(exc, 160)}); gsbench checkpoints are data. Fix: delete it, and the run trains "
            "again from the start (a checkpoint written by gsbench before 2026-11-27 stored the RNG states as "
            "numpy objects), or get the run folder from a source you trust") from None
    except (OSError, RuntimeError, EOFError) as exc:
        raise CheckpointError(f"{path} cannot be read ({type(exc).__name__}: {one_line(exc, 160)}); fix: delete it "
                              "and the run trains again from the start") from None


def rng_state() -> dict:
    """The python, numpy and torch RNG states as plain values and tensors (what `load_checkpoint` reads back)."""
    algorithm, keys, position, has_gauss, cached_gaussian = np.random.get_state()
    return {"python": random.getstate(),
            "numpy": {"algorithm": str(algorithm), "keys": torch.from_numpy(keys.astype(np.int64)),
                      "position": int(position), "has_gauss": int(has_gauss), "cached_gaussian": float(cached_gaussian)},
            "torch": torch.get_rng_state()}


def set_rng_state(state: dict) -> None:
    """Restore the states `rng_state` stored."""
    random.setstate(state["python"])
    numpy = state["numpy"]
    np.random.set_state((numpy["algorithm"], numpy["keys"].numpy().astype(np.uint32), numpy["position"],
                         numpy["has_gauss"], numpy["cached_gaussian"]))
    torch.set_rng_state(state["torch"])


class CameraSampler:
    """Views drawn without replacement from a shuffled stack, refilled each epoch (seeded, docs/methods/3dgs.md §1.4)."""

    def __init__(self, indices, seed: int):
        self.indices = list(indices)
        self.rng = random.Random(seed)
        self.stack: list[int] = []

    def next(self) -> int:
        if not self.stack:
            self.stack = list(self.indices)
            self.rng.shuffle(self.stack)
        return self.stack.pop()

    def state_dict(self) -> dict:
        return {"rng": self.rng.getstate(), "stack": list(self.stack)}

    def load_state_dict(self, state: dict) -> None:
        self.rng.setstate(state["rng"])
        self.stack = list(state["stack"])


@dataclass
class DensifyBudget:
    """How ``train.max_gaussians`` bound densification (module docstring, "Budget"): the first step at
    which a refinement left candidates out (None: never) and the candidates left out over the run."""

    max_gaussians: int = 0
    first_cut_step: int | None = None
    candidates_cut: int = 0

    def add(self, step: int, info: dict) -> None:
        """Count a refinement's ``budget_cut`` (the strategies' info) at ``step``."""
        cut = int(info.get("budget_cut", 0))
        if cut:
            self.first_cut_step = step if self.first_cut_step is None else self.first_cut_step
            self.candidates_cut += cut


@dataclass
class TrainResult:
    """What training produced: steps done in total, seconds spent (over all resumes), it/s, final N, and
    the seconds per phase within training: the Trainer's step phases (`STEP_PHASES`) and the method's
    own (`Method.training_phases`), both over all resumes (module docstring, "Phases")."""

    steps: int
    seconds: float
    it_per_s: float
    cpu_seconds: float | None
    num_gaussians: int
    resumed_from: int = 0
    phases: dict = dataclasses.field(default_factory=dict)
    budget: DensifyBudget = dataclasses.field(default_factory=DensifyBudget)


def _target_images(scene: Scene, cfg: RunConfig, background) -> tuple[list, list]:
    """GT tensors per view (composited over ``background`` outside the mask with ``data.mask_target``)
    and the masks handed to the loss terms (None without ``data.use_masks``)."""
    bg = torch.tensor(background, dtype=torch.float32)
    use = cfg.data.use_masks and scene.masks is not None
    images, masks = [], []
    for i, img in enumerate(scene.images):
        image = torch.as_tensor(np.asarray(img, dtype=np.float32))
        mask = torch.as_tensor(np.asarray(scene.masks[i], dtype=bool)) if use else None
        if mask is not None and cfg.data.mask_target:
            image = torch.where(mask[..., None], image, bg)
        images.append(image)
        masks.append(mask)
    return images, masks


def merge_phases(step_phases: dict, method_phases: dict) -> dict:
    """The method's phases under their own names plus the step phases; a step phase whose name the
    method also uses gets `STEP_PHASE_PREFIX` (module docstring, "Phases")."""
    merged = {name: float(v) for name, v in method_phases.items()}
    for name, seconds in step_phases.items():
        merged[STEP_PHASE_PREFIX + name if name in method_phases else name] = float(seconds)
    return merged


class Trainer:
    """Runs ``method`` (already `setup`) on ``scene`` for ``cfg.train.iterations`` steps in ``run_dir``.

    ``progress_interval``: seconds between the progress lines printed when stderr is not a terminal
    (`gsbench.training.progress.ProgressLines`)."""

    progress_interval: float = DEFAULT_INTERVAL

    def __init__(self, method, scene: Scene, cfg: RunConfig, run_dir, progress_interval: float | None = None):
        self.method, self.scene, self.cfg = method, scene, cfg
        self.threads = set_threads(cfg.threads)
        keep_freed_memory()
        self.run_dir = Path(run_dir)
        self.iterations = int(cfg.train.iterations)
        if self.iterations < 1:
            raise ConfigError(f"train.iterations must be >= 1, got {self.iterations}")
        self.scale = schedule_scale(self.iterations)
        self.losses = scaled_losses(cfg.losses, self.scale)
        self.strategy = scaled_strategy(method.strategy(), self.iterations, cfg.train.scale_refine_interval)
        self.strategy_state = self.strategy.init_state(len(method.gaussians))
        self.budget = DensifyBudget(int(cfg.train.max_gaussians))
        self.views = scene.train_views
        self.sampler = CameraSampler(self.views, cfg.seed)
        self.images, self.masks = _target_images(scene, cfg, method.background)
        self.step = 0
        self.seconds = 0.0
        self.cpu_seconds = 0.0
        self.phases = dict.fromkeys(STEP_PHASES, 0.0)
        if progress_interval is not None:
            self.progress_interval = float(progress_interval)
        active_terms(self.losses, 0, method.term_params())  # validate names now

    # ---- checkpoints --------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"step": self.step, "seconds": self.seconds, "cpu_seconds": self.cpu_seconds,
                "phases": dict(self.phases),
                "method": self.method.state_dict(),
                "strategy": {k: v.clone() for k, v in self.strategy_state.items()},
                "budget": dataclasses.asdict(self.budget),
                "sampler": self.sampler.state_dict(),
                "rng": rng_state()}

    def load_state_dict(self, state: dict) -> None:
        self.method.load_state_dict(state["method"])
        self.strategy_state = {k: v.clone() for k, v in state["strategy"].items()}
        # checkpoints written before the budget was tracked resume with no cut counted
        self.budget = DensifyBudget(**{**dataclasses.asdict(self.budget), **state.get("budget", {})})
        self.sampler.load_state_dict(state["sampler"])
        set_rng_state(state["rng"])
        self.step, self.seconds = int(state["step"]), float(state["seconds"])
        cpu = state.get("cpu_seconds")  # None in checkpoints from before it was kept: the total stays unknown
        self.cpu_seconds = None if cpu is None else float(cpu)
        self.phases = dict.fromkeys(STEP_PHASES, 0.0)  # checkpoints from before phases existed: zeros
        self.phases.update({k: float(v) for k, v in state.get("phases", {}).items()})

    def _truncate_metrics(self) -> None:
        """Drop metrics lines past the resumed step (written after the last checkpoint)."""
        path = RunFolder(self.run_dir).metrics
        if path.is_file():
            lines = [ln for ln in path.read_text().splitlines() if ln and json.loads(ln)["step"] <= self.step]
            path.write_text("".join(ln + "\n" for ln in lines))

    # ---- the loop -----------------------------------------------------------------------------
    def train_step(self, step: int) -> dict[str, float]:
        """One optimisation step (module docstring); returns the unweighted term values and the total.

        Each part's wall time is added to `phases` (module docstring, "Phases")."""
        m, phases, clock = self.method, self.phases, time.perf_counter
        m.update_schedules(step, self.scale)
        idx = self.sampler.next()
        camera = self.scene.cameras[idx]
        active = active_terms(self.losses, step, m.term_params())
        if not active:
            raise ConfigError(f"step {step}: no loss term is active (all weights 0 or outside start/end); "
                              f"configured: {self.losses}")
        t = clock()
        try:
            render = m.render(camera, required_outputs(active))
        except NumericalError as exc:
            raise NumericalError(f"step {step}: {exc}") from exc
        t1 = clock()
        phases["render"] += t1 - t
        t = t1
        loss, values = total_loss(active, render, Batch(self.images[idx], self.masks[idx], camera, step, idx),
                                  m.loss_state())
        t1 = clock()
        phases["loss"] += t1 - t
        finite = bool(torch.isfinite(loss))
        t = clock()
        phases["checks"] += t - t1
        if not finite:
            bad = [k for k, v in values.items() if not np.isfinite(v)] or ["(weighted sum)"]
            raise NumericalError(f"step {step}: the loss is not finite (terms {bad}, view {idx}); lower the "
                                 "learning rates or the term weights, or resume from an earlier checkpoint")
        self.strategy.step_pre_backward(render)
        loss.backward()
        t1 = clock()
        phases["backward"] += t1 - t
        self.budget.add(step, self.strategy.step_post_backward(m.gaussians, m.optimizer, self.strategy_state, step,
                                                               render))
        t = clock()
        phases["densify"] += t - t1
        if len(m.gaussians) == 0:
            raise NumericalError(f"step {step}: densification pruned every Gaussian (prune opacity "
                                 f"{getattr(self.strategy, 'prune_opacity', '?')}); check the schedule and the data")
        if step < self.iterations:
            if isinstance(m.optimizer, VisibleAdam):  # rows the view saw; after a refinement round, every row
                m.optimizer.visible = render.visible if len(render.visible) == len(m.gaussians) else None
            m.optimizer.step()
        m.optimizer.zero_grad(set_to_none=True)
        t1 = clock()
        phases["optimizer"] += t1 - t
        if step % PARAMETER_CHECK_EVERY == 0 or step == self.iterations:
            try:
                self.check_parameters(step)
            finally:
                phases["checks"] += clock() - t1
        values["total"] = float(loss.detach())
        return values

    def check_parameters(self, step: int) -> None:
        """`Gaussians.check_finite`, its error naming the step (module docstring, "Checks")."""
        try:
            self.method.gaussians.check_finite()
        except NumericalError as exc:
            raise NumericalError(f"step {step}: {exc} (parameters are checked every {PARAMETER_CHECK_EVERY} steps "
                                 "and before every checkpoint; the loss every step)") from exc

    def fit(self) -> TrainResult:
        """Train (resuming from ``checkpoint.pt`` when present) and write ``checkpoint-final.pt``."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        resume = RunFolder(self.run_dir).checkpoint
        if resume.is_file():
            self.load_state_dict(load_checkpoint(resume))
        else:
            seed_everything(self.cfg.seed)
        resumed_from = self.step
        self._truncate_metrics()
        t_cfg = self.cfg.train
        bar = tqdm(total=self.iterations, initial=self.step, desc=f"train {self.method.name}", unit="it",
                   disable=None, dynamic_ncols=True)
        lines = ProgressLines(f"train {self.method.name}", self.iterations, initial=self.step,
                              interval=self.progress_interval)
        window_start, window_steps = time.perf_counter(), 0
        with open(RunFolder(self.run_dir).metrics, "a") as log:
            while self.step < self.iterations:
                t0, c0 = time.perf_counter(), time.process_time()
                values = self.train_step(self.step + 1)
                self.step += 1
                window_steps += 1
                bar.update(1)
                n = len(self.method.gaussians)
                lines.update(self.step, values.get("total"), n)
                if self.step % t_cfg.log_every == 0 or self.step == self.iterations:
                    rate = window_steps / max(time.perf_counter() - window_start, 1e-9)
                    log.write(json.dumps({"step": self.step, **values, "num_gaussians": n, "it_per_s": rate}) + "\n")
                    log.flush()
                    bar.set_postfix({k: f"{v:.4g}" for k, v in values.items()} | {"N": n}, refresh=False)
                    window_start, window_steps = time.perf_counter(), 0
                self.seconds += time.perf_counter() - t0
                if self.cpu_seconds is not None:
                    self.cpu_seconds += time.process_time() - c0
                every = t_cfg.checkpoint_every
                if self.step < self.iterations and every > 0 and self.step % every == 0:
                    self.check_parameters(self.step)
                    save_atomic(self.state_dict(), resume)
        bar.close()
        lines.close()
        save_atomic(self.state_dict(), RunFolder(self.run_dir).final_checkpoint)
        resume.unlink(missing_ok=True)
        return self.result(resumed_from)

    def result(self, resumed_from: int = 0) -> TrainResult:
        return TrainResult(steps=self.step, seconds=self.seconds, it_per_s=self.step / max(self.seconds, 1e-9),
                           cpu_seconds=self.cpu_seconds,
                           num_gaussians=len(self.method.gaussians), resumed_from=resumed_from,
                           phases=merge_phases(self.phases, self.method.training_phases()),
                           budget=dataclasses.replace(self.budget))
