"""The one training loop (docs/design.md §4: the Trainer owns the loop, methods declare data; the details
and their reasons: docs/training.md).

Per step t = 1 … ``train.iterations``, in 3DGS ``train.py`` order (docs/methods/3dgs.md §5.2): update the
schedules, draw the next view, render what the active terms need, L = Σ weight·term, backward and densify,
Adam step (skipped on the last step). Every step-valued setting of the paper's 30 000-step run is scaled by
``train.iterations / 30000`` (docs/training.md §1); a resumed run is bit-identical to an uninterrupted one.
At the steps of anytime evaluation the trained model is handed out between two steps and training goes on as if
it had not been (`Trainer.take_point`, docs/training.md §9).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import pickle
import random
import time
from collections.abc import Callable, Iterable
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
from gsbench.training.progress import DEFAULT_INTERVAL, ProgressLines, stage
from gsbench.training.strategies.base import REFERENCE_ITERATIONS

STEP_PHASES = ("render", "loss", "backward", "densify", "optimizer", "checks")
PARAMETER_CHECK_EVERY = 50  # steps between finiteness checks of the parameters (docs/training.md §3)
STEP_PHASE_PREFIX = "step."


def scale_step(value: int, scale: float) -> int:
    """A paper step count scaled to this run: ``max(1, round(value·scale))``; values <= 0 unchanged."""
    return int(value) if value <= 0 else max(1, round(value * scale))


def schedule_scale(iterations: int) -> float:
    """iterations / 30000: the factor every step-valued setting is multiplied by (docs/training.md §1)."""
    return iterations / REFERENCE_ITERATIONS


def scaled_losses(losses: dict, scale: float) -> dict:
    """The loss config with ``start`` and ``end`` scaled (weights unchanged): the effective terms."""
    return {name: {"weight": float(t["weight"]), "start": scale_step(t["start"], scale),
                   "end": scale_step(t["end"], scale)} for name, t in losses.items()}


def scaled_strategy(strategy, iterations: int, scale_refine_interval: bool = False):
    """The strategy's schedule for this run: `DefaultStrategy.scaled`'s window and reset interval; the
    refinement interval keeps the paper's 100 Adam steps (the reset interval a multiple of it) unless
    ``scale_refine_interval``, which scales it and sets ``prune_grace`` to the paper's (docs/training.md §1.1)."""
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
    """``torch.save`` to a temp file in the same folder, then ``os.replace`` (`gsbench.atomic`); through a Python
    file, whose OSError names the cause of a failed write (a full disk), where torch's own stream says only
    ``basic_ios::clear: iostream error``."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        torch.save(obj, fh)


def load_checkpoint(path: Path) -> dict:
    """A checkpoint read as data (``weights_only``: tensors and plain values, never code from the file); anything
    else, or a damaged file, is a `CheckpointError` naming it (docs/training.md §4)."""
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
    """How ``train.max_gaussians`` bound densification (docs/training.md §6): the first step at which a
    refinement left candidates out (None: never) and the candidates left out over the run."""

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
    """What training produced, over all resumes: steps, seconds, it/s, CPU seconds, final N, and the seconds
    per phase: the Trainer's step phases (`STEP_PHASES`) and the method's own (docs/training.md §4, §5)."""

    steps: int
    seconds: float
    it_per_s: float
    cpu_seconds: float | None
    num_gaussians: int
    resumed_from: int = 0
    phases: dict = dataclasses.field(default_factory=dict)
    budget: DensifyBudget = dataclasses.field(default_factory=DensifyBudget)


def _target_images(scene: Scene, cfg: RunConfig, background) -> tuple[list, list]:
    """GT tensors per view (``gt' = mask·gt + (1 − mask)·bg`` with ``data.mask_target``, docs/training.md §2)
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
    method also uses gets `STEP_PHASE_PREFIX` (docs/training.md §5)."""
    merged = {name: float(v) for name, v in method_phases.items()}
    for name, seconds in step_phases.items():
        merged[STEP_PHASE_PREFIX + name if name in method_phases else name] = float(seconds)
    return merged


class Trainer:
    """Runs ``method`` (already `setup`) on ``scene`` for ``cfg.train.iterations`` steps in ``run_dir``.

    ``progress_interval``: seconds between the progress lines printed when stderr is not a terminal
    (`gsbench.training.progress.ProgressLines`). ``points``: steps before the last at which ``on_point(method,
    result so far)`` is called (`take_point`)."""

    progress_interval: float = DEFAULT_INTERVAL

    def __init__(self, method, scene: Scene, cfg: RunConfig, run_dir, progress_interval: float | None = None,
                 points: Iterable[int] = (), on_point: Callable[[object, TrainResult], None] | None = None):
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
        self.points = frozenset(int(step) for step in points if int(step) < self.iterations)
        if self.points and on_point is None:
            raise ValueError("Trainer: points given without on_point")
        self.on_point = on_point
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
        """Drop metrics lines past the resumed step (written after the last checkpoint), and a last line without its
        newline (a write cut short, by a full disk)."""
        path = RunFolder(self.run_dir).metrics
        if path.is_file():
            text = path.read_text()
            whole = text[: text.rfind("\n") + 1].splitlines()
            lines = [ln for ln in whole if ln and json.loads(ln)["step"] <= self.step]
            path.write_text("".join(ln + "\n" for ln in lines))

    # ---- the loop -----------------------------------------------------------------------------
    def train_step(self, step: int) -> dict[str, float]:
        """One optimisation step; returns the unweighted term values and the total. Each part's wall time is
        added to `phases` (docs/training.md §5)."""
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
        """`Gaussians.check_finite`, its error naming the step (docs/training.md §3)."""
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
            stage(f"resuming at step {self.step} of {self.iterations} from {resume} ({len(self.method.gaussians)} "
                  "Gaussians)")
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
                if self.step in self.points:  # before the step's checkpoint: one written means the point is done
                    window_start += self.take_point(resumed_from)
                every = t_cfg.checkpoint_every
                if self.step < self.iterations and every > 0 and self.step % every == 0:
                    self.check_parameters(self.step)
                    save_atomic(self.state_dict(), resume)
        bar.close()
        lines.close()
        save_atomic(self.state_dict(), RunFolder(self.run_dir).final_checkpoint)
        resume.unlink(missing_ok=True)
        return self.result(resumed_from)

    def take_point(self, resumed_from: int) -> float:
        """``on_point(method, result so far)`` under ``torch.no_grad``, outside the training time; returns its wall
        seconds. Training goes on bit for bit as without it: the python, numpy and torch RNG states and the method's
        state (`Method.state_dict`, what a resume restores) are put back afterwards, so whatever the extraction
        and evaluation draw, cache or change in the model (e.g. IBGS's frames) is undone."""
        t0 = time.perf_counter()
        method_state, rng = copy.deepcopy(self.method.state_dict()), rng_state()
        try:
            with torch.no_grad():
                self.on_point(self.method, self.result(resumed_from))
        finally:
            self.method.load_state_dict(method_state)
            set_rng_state(rng)
        return time.perf_counter() - t0

    def result(self, resumed_from: int = 0) -> TrainResult:
        return TrainResult(steps=self.step, seconds=self.seconds, it_per_s=self.step / max(self.seconds, 1e-9),
                           cpu_seconds=self.cpu_seconds,
                           num_gaussians=len(self.method.gaussians), resumed_from=resumed_from,
                           phases=merge_phases(self.phases, self.method.training_phases()),
                           budget=dataclasses.replace(self.budget))
