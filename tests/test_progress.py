"""gsbench.training.progress (progress lines when stderr is not a terminal, stage lines) and the Trainer's use of
it, plus the Trainer's step phases (TrainResult.phases) over a fresh and a resumed run."""

from __future__ import annotations

import io
import re

import pytest

from gsbench.data.loader import load_scene
from gsbench.registry import METHODS
from gsbench.run_folder import RunFolder
from gsbench.runs.runner import resolve_run
from gsbench.training.progress import ProgressLines, format_duration, is_terminal, stage
from gsbench.training.trainer import (
    STEP_PHASES,
    Trainer,
    load_checkpoint,
    merge_phases,
    save_atomic,
    seed_everything,
)
from tests.method_setup import interrupt_at

TINY = ["data.downscale=1", "method.random_init_points=400", "train.log_every=5"]
LINE = re.compile(r"^train 3dgs: step (\d+)/(\d+) \((\d+)%\) ([\d.e+-]+) it/s loss ([\d.e+-]+) N (\d+) ETA (\S+)$")


class Tty(io.StringIO):
    def isatty(self):
        return True


class FakeClock:
    def __init__(self):
        self.now = 100.0

    def __call__(self):
        return self.now


def make_trainer(method, scene_dir, run_dir, *overrides, **kwargs):
    cfg = resolve_run(method, str(scene_dir), preset="quick", overrides=[*TINY, *overrides])
    scene = load_scene(cfg.scene, downscale=cfg.data.downscale)
    m = METHODS.get(method)()
    m.setup(scene, cfg)
    return Trainer(m, scene, cfg, run_dir, **kwargs)


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("GSBENCH_DATA", str(tmp_path / "cache"))


# ---- ProgressLines / stage -----------------------------------------------------------------------


def test_lines_every_interval_with_rate_and_eta():
    out, clock = io.StringIO(), FakeClock()
    p = ProgressLines("train 2dgs", 3000, initial=0, interval=30, stream=out, clock=clock)
    assert p.enabled
    clock.now += 10
    p.update(31, 0.5, 1000)
    assert out.getvalue() == ""  # 10 s < 30 s
    clock.now += 390
    p.update(1200, 0.07123, 23456)  # 1200 steps in 400 s: 3 it/s, 1800 left: 10 min
    assert out.getvalue() == "train 2dgs: step 1200/3000 (40%) 3 it/s loss 0.07123 N 23456 ETA 10m00s\n"
    clock.now += 5
    p.update(1215, 0.07, 23460)
    assert out.getvalue().count("\n") == 1
    clock.now += 595
    p.update(3000, 0.05, 30000)
    p.close()
    p.close()
    lines = out.getvalue().splitlines()
    assert len(lines) == 3 and lines[-1] == "train 2dgs: step 3000/3000 (100%) 3 it/s loss 0.05 N 30000 done in 16m40s"


def test_rate_counts_only_the_steps_of_this_process_after_a_resume():
    out, clock = io.StringIO(), FakeClock()
    p = ProgressLines("train 3dgs", 100, initial=60, interval=0, stream=out, clock=clock)
    clock.now += 4
    p.update(80)
    assert out.getvalue() == "train 3dgs: step 80/100 (80%) 5 it/s ETA 4s\n"


def test_a_count_of_views_says_view():
    out, clock = io.StringIO(), FakeClock()
    p = ProgressLines("rendering spot", 49, interval=0, stream=out, clock=clock, unit="view")
    clock.now += 7
    p.update(7)
    assert out.getvalue() == "rendering spot: view 7/49 (14%) 1 it/s ETA 42s\n"


def test_nothing_on_a_terminal():
    out = Tty()
    p = ProgressLines("train 3dgs", 10, interval=0, stream=out)
    assert not p.enabled
    for step in range(1, 11):
        p.update(step, 0.1, 5)
    p.close()
    assert out.getvalue() == ""


def test_stage_prints_one_line_terminal_or_not(capsys):
    stage("loading 49 views at 800x600")
    assert capsys.readouterr().err == "gsbench: loading 49 views at 800x600\n"
    tty = Tty()
    stage("training", stream=tty)
    assert tty.getvalue() == "gsbench: training\n"


class _Writes:
    """A non-terminal stream that keeps each ``write`` call apart."""

    def __init__(self):
        self.writes = []

    def write(self, text):
        self.writes.append(text)

    def flush(self):
        pass

    def isatty(self):
        return False


def test_stage_and_progress_lines_are_written_whole_so_parallel_workers_cannot_split_them():
    """Sweep workers share stderr: each line must reach it in one write, text and newline together."""
    out = _Writes()
    stage("training 3000 steps from 7770 Gaussians", stream=out)
    p = ProgressLines("train 3dgs", 10, interval=0, stream=out, enabled=True)
    p.update(5, 0.25, 100)
    p.close()
    assert len(out.writes) >= 3
    assert all(w.endswith("\n") and w.count("\n") == 1 for w in out.writes), out.writes
    assert out.writes[0] == "gsbench: training 3000 steps from 7770 Gaussians\n"


def test_is_terminal_and_durations():
    assert not is_terminal(io.StringIO()) and is_terminal(Tty()) and not is_terminal(object())
    closed = io.StringIO()
    closed.close()
    assert not is_terminal(closed)
    assert [format_duration(s) for s in (0, 41.4, 581, 3600 + 5 * 60 + 20, float("inf"))] == \
        ["0s", "41s", "9m41s", "1h05m", "?"]


# ---- the Trainer ---------------------------------------------------------------------------------


def test_fit_prints_progress_lines_when_stderr_is_not_a_terminal(tiny_spot, tmp_path, capsys):
    trainer = make_trainer("3dgs", tiny_spot, tmp_path / "run", "train.iterations=6", progress_interval=0)
    trainer.fit()
    lines = capsys.readouterr().err.splitlines()
    progress = [m for m in map(LINE.match, lines) if m]
    assert [int(m.group(1)) for m in progress] == [1, 2, 3, 4, 5, 6]
    assert all(int(m.group(2)) == 6 and float(m.group(4)) > 0 and int(m.group(6)) > 0 for m in progress)
    assert progress[-1].group(7) == "0s" and progress[0].group(7) != "?"
    assert re.match(r"^train 3dgs: step 6/6 \(100%\) \S+ it/s loss \S+ N \d+ done in \S+$", lines[-1])


def test_fit_prints_nothing_on_a_terminal(tiny_spot, tmp_path, monkeypatch):
    tty = Tty()
    monkeypatch.setattr("sys.stderr", tty)
    trainer = make_trainer("3dgs", tiny_spot, tmp_path / "run", "train.iterations=3", progress_interval=0)
    trainer.fit()
    assert "train 3dgs: step" not in tty.getvalue() and "done in" not in tty.getvalue()


def test_progress_interval_defaults_to_30s(tiny_spot, tmp_path):
    assert make_trainer("3dgs", tiny_spot, tmp_path / "run", "train.iterations=3").progress_interval == 30.0


# ---- phases --------------------------------------------------------------------------------------


def test_phases_cover_the_steps_and_continue_over_a_resume(tiny_spot, tmp_path, monkeypatch):
    overrides = ("train.iterations=12", "train.checkpoint_every=6", "method.refine_every=4",
                 "method.refine_stop=30000", "method.reset_every=30000")
    straight = make_trainer("3dgs", tiny_spot, tmp_path / "a", *overrides).fit()
    assert set(straight.phases) == set(STEP_PHASES)
    assert all(v >= 0 for v in straight.phases.values()) and straight.phases["render"] > 0
    assert sum(straight.phases.values()) <= straight.seconds + 1e-6

    interrupted = make_trainer("3dgs", tiny_spot, tmp_path / "b", *overrides)
    interrupt_at(interrupted, 7, monkeypatch)
    with pytest.raises(KeyboardInterrupt):
        interrupted.fit()
    monkeypatch.undo()
    saved = load_checkpoint(tmp_path / "b" / RunFolder.CHECKPOINT)["phases"]
    assert set(saved) == set(STEP_PHASES) and saved["render"] > 0
    resumed = make_trainer("3dgs", tiny_spot, tmp_path / "b", *overrides).fit()
    assert resumed.resumed_from == 6
    for name in STEP_PHASES:
        assert resumed.phases[name] >= saved[name]
    assert resumed.phases["render"] > saved["render"] and resumed.phases["backward"] > saved["backward"]
    assert sum(resumed.phases.values()) <= resumed.seconds + 1e-6


def test_a_checkpoint_without_phases_resumes_from_zeros(tiny_spot, tmp_path):
    overrides = ("train.iterations=8", "train.checkpoint_every=4")
    run = tmp_path / "run"
    first = make_trainer("3dgs", tiny_spot, run, *overrides)
    seed_everything(first.cfg.seed)
    for t in range(1, 5):
        first.train_step(t)
        first.step = t
    state = first.state_dict()
    del state["phases"]  # a checkpoint written before phases existed
    save_atomic(state, run / RunFolder.CHECKPOINT)
    result = make_trainer("3dgs", tiny_spot, run, *overrides).fit()
    assert result.steps == 8 and result.resumed_from == 4
    assert set(result.phases) == set(STEP_PHASES) and result.phases["render"] > 0
    assert sum(result.phases.values()) <= result.seconds + 1e-6


def test_method_phases_keep_their_names_and_colliding_step_phases_are_prefixed():
    step = dict.fromkeys(STEP_PHASES, 1.0)
    merged = merge_phases(step, {"knn": 2.0, "render": 3.0})
    assert merged["knn"] == 2.0 and merged["render"] == 3.0 and merged["step.render"] == 1.0
    assert set(merged) == {"knn", "render", "step.render", *(set(STEP_PHASES) - {"render"})}
    assert merge_phases(step, {}) == step
