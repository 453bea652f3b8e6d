"""Pictures of surfaces (`gsbench.report.surfaces`): the report's Surfaces section and ``gsbench render`` draw
the same picture of a run; every picture is a valid PNG of the size the page states, and the page shows each."""

from __future__ import annotations

import base64
import io
import re
import shutil

import pytest
from PIL import Image

from gsbench.cli import main
from gsbench.report.build import write_report
from gsbench.runs.runner import resolve_run, run, run_dir
from tests.method_setup import QUICK


@pytest.fixture(scope="module")
def runs(tiny_spot, tmp_path_factory):
    """Two finished quick runs on tiny_spot (with its ground truth) and one on its photos alone (no ground truth)."""
    out = tmp_path_factory.mktemp("surfaces") / "runs"
    capture = out.parent / "scan1001"
    for part in ("image", "mask"):
        shutil.copytree(tiny_spot / part, capture / part)
    shutil.copy(tiny_spot / "cameras.npz", capture / "cameras.npz")
    folders = {}
    for method, scene in (("3dgs", tiny_spot), ("2dgs", tiny_spot), ("3dgs", capture)):
        no_gt = ["eval.evaluators=[mesh_stats]"] if scene == capture else []  # nothing to score it against
        cfg = resolve_run(method, str(scene), preset="quick", overrides=[*QUICK, *no_gt])
        cfg.out = str(out)
        assert run(cfg, echo=lambda *a: None).status == "ok"
        folders[(method, scene.name)] = run_dir(cfg)
    return out, folders


def _size(png: bytes) -> tuple[int, int]:
    with Image.open(io.BytesIO(png)) as image:
        image.verify()
    with Image.open(io.BytesIO(png)) as image:
        assert image.format == "PNG"
        return image.size


def test_every_surface_picture_is_a_valid_image_of_the_stated_size_and_on_the_page(runs, tmp_path):
    out, _ = runs
    report = tmp_path / "report"
    write_report(out, report, generated="2026-01-01T00:00:00+00:00")
    md = (report / "leaderboard.md").read_text()
    page = (report / "index.html").read_text()
    pictures = sorted((report / "plots").glob("surface-*.png"))
    assert len(pictures) == 3  # 3dgs and 2dgs with ground truth, 3dgs on the capture without
    assert "## Surfaces" in md
    for path in pictures:
        stated = re.search(rf"!\[[^\]]*, (\d+)x(\d+) px\]\(plots/{re.escape(path.name)}\)", md)
        assert stated, f"{path.name} is not referenced with its size"
        assert _size(path.read_bytes()) == (int(stated.group(1)), int(stated.group(2)))
        assert base64.b64encode(path.read_bytes()).decode() in page  # embedded: the page stands alone


def test_render_draws_the_reports_picture_of_one_run(runs, tmp_path, capsys):
    _, folders = runs
    folder = folders[("3dgs", "scan1001")]
    assert main(["render", str(folder), "--out", str(tmp_path / "capture.png")]) == 0
    width, height = _size((tmp_path / "capture.png").read_bytes())
    assert f"{width}x{height} PNG" in capsys.readouterr().out
    assert main(["render", str(folder.parent)]) == 2  # not a run folder: one line, no traceback
    assert "config.yaml not found: the pictures show a finished run" in capsys.readouterr().err
