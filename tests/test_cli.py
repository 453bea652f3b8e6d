"""CLI: sub-commands print what they should; errors are one line naming the fix; --debug re-raises."""

import subprocess
import sys
from dataclasses import dataclass

import pytest
import yaml

from gsbench.cli import main
from gsbench.errors import ConfigError
from gsbench.registry import METHODS


@dataclass
class _ToyConfig:
    knn_k: int = 5


class _ToyMethod:
    Config = _ToyConfig


@pytest.fixture
def toy_method():
    METHODS.register("toy", _ToyMethod)
    yield "toy"
    METHODS._entries.pop("toy", None)


def test_config_prints_resolved_yaml_with_run_id(toy_method, capsys):
    assert main(["config", "--method", "toy", "--preset", "quick", "--set", "method.knn_k=8", "--seed", "4"]) == 0
    out = capsys.readouterr().out
    first, _, body = out.partition("\n")
    assert first.startswith("# run id ") and len(first.split()[-1]) == 12
    cfg = yaml.safe_load(body)
    assert cfg["method"] == {"name": "toy", "knn_k": 8}
    assert cfg["seed"] == 4 and cfg["preset"] == "quick"


def test_config_error_is_one_line_and_debug_raises(toy_method, capsys):
    assert main(["config", "--method", "toy", "--set", "train.iteratons=5"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "did you mean 'iterations'" in err
    with pytest.raises(ConfigError):
        main(["--debug", "config", "--method", "toy", "--set", "train.iteratons=5"])


def test_list(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    assert "synthetic/spot-km" in out and "tnt_f1" in out


def test_scene_make_and_check(tmp_path, capsys):
    out = tmp_path / "spot"
    assert main(["scene", "make", "synthetic/spot", "--res", "64", "48", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"scene written to {out}" in text and '"ok": true' in text
    assert main(["scene", "check", str(out)]) == 0
    assert '"cameras": 49' in capsys.readouterr().out


def test_scene_check_reports_a_broken_folder(tmp_path, capsys):
    (tmp_path / "image").mkdir()
    assert main(["scene", "check", str(tmp_path)]) == 1
    assert '"ok": false' in capsys.readouterr().out


def test_help_and_list_start_without_torch():
    """Each command module imports its stage inside the function it runs, so the parser alone loads no stage."""
    code = ("import sys; from gsbench.cli import main\n"
            "try:\n    main(['--help'])\nexcept SystemExit:\n    pass\n"
            "main(['list']); print('heavy:', [m for m in ('torch', 'open3d', 'trimesh') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().endswith("heavy: []")
