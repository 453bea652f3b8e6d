"""The installed package: methods/ and evaluators/ import as gsbench.*, the console script works."""

import subprocess
import sys
from pathlib import Path


def test_plugin_folders_install_under_gsbench():
    import gsbench.evaluators
    import gsbench.methods

    repo = Path(gsbench.__file__).resolve().parent.parent
    assert Path(gsbench.methods.__file__).resolve().parent == repo / "methods"
    assert Path(gsbench.evaluators.__file__).resolve().parent == repo / "evaluators"


def test_no_generic_top_level_packages_installed():
    out = subprocess.run([sys.executable, "-c", "import methods"], capture_output=True, text=True,
                         cwd="/")
    assert out.returncode != 0


def test_console_script_lists():
    out = subprocess.run(["gsbench", "list"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "synthetic/spot" in out.stdout and "dtu_chamfer" in out.stdout


def test_errors_print_one_line_without_traceback():
    out = subprocess.run(["gsbench", "config", "--method", "nosuch"], capture_output=True, text=True)
    assert out.returncode == 2
    assert out.stderr.startswith("gsbench: error: unknown method 'nosuch'")
    assert "Traceback" not in out.stderr
