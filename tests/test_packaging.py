"""What the installed package holds: what a user runs, not the lab notebook.

The package is built the way pip builds the wheel's contents: setuptools' ``build_py`` (the packages and their
package data from pyproject.toml) into a temporary folder, with the ``egg_info`` it needs written there too, so
the checkout is left as it was. No experiment ships: nothing of experiments/, no findings.yaml, no Markdown; the
sweeps that ship are configs/sweeps/, each free of lab-notebook references (an issue number, an experiment).
"""

from __future__ import annotations

import re
import subprocess
import sys

from sweep_files import EXPERIMENTS, REPO, SHIPPED

LAB_NOTEBOOK = re.compile(r"\bissues? \d+|experiments/")


def test_the_built_package_holds_no_experiment(tmp_path):
    built = tmp_path / "lib"
    subprocess.run([sys.executable, "-c", "from setuptools import setup; setup()", "-q",
                    "egg_info", "--egg-base", str(tmp_path), "build_py", "--build-lib", str(built)],
                   cwd=REPO, check=True, capture_output=True, text=True)
    files = sorted(p.relative_to(built).as_posix() for p in built.rglob("*") if p.is_file())
    assert "gsbench/cli/__init__.py" in files and "gsbench/configs/presets/cpu.yaml" in files  # the build ran
    assert not [f for f in files if "experiments" in f or f.endswith(("findings.yaml", ".md"))]
    shipped = sorted(f.removeprefix("gsbench/configs/sweeps/") for f in files if f.startswith("gsbench/configs/sweeps/"))
    assert shipped == [p.name for p in SHIPPED]
    assert not {p.name for p in EXPERIMENTS} & set(shipped)
    for path in SHIPPED:
        assert not LAB_NOTEBOOK.search(path.read_text()), f"{path.name} cites the lab notebook; keep what a user needs"
