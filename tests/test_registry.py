"""Lazy registries: listing imports nothing, unknown names suggest, entries import on first use."""

import subprocess
import sys

import pytest

from gsbench.config.files import declared_plugins
from gsbench.errors import RegistryError
from gsbench.registry import EVALUATORS, LOSS_TERMS, METHODS, Registry


def test_listing_imports_nothing_heavy():
    code = (
        "import sys; from gsbench.registry import METHODS, EVALUATORS, LOSS_TERMS; "
        "from gsbench.data.synthetic.builtin import BUILTIN_SCENES; "
        "METHODS.names(); EVALUATORS.names(); LOSS_TERMS.names(); "
        "heavy = [m for m in ('torch', 'open3d', 'trimesh', 'pymeshlab', 'pycolmap', 'scipy') if m in sys.modules]; "
        "print(','.join(heavy))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_unknown_name_suggests():
    with pytest.raises(RegistryError, match="did you mean 'dtu_chamfer'"):
        EVALUATORS.get("dtu_chamfr")


def test_lazy_string_entries_and_register():
    reg = Registry("thing", {"path": "os.path:join"}, "gsbench.nothing")
    assert reg.names() == ["path"]
    import os.path

    assert reg.get("path") is os.path.join
    reg.register("obj", dict)
    assert reg.get("obj") is dict
    assert reg.path("obj") == "builtins:dict"
    reg.register("broken", "no_such_module_xyz:Thing")
    with pytest.raises(RegistryError, match="cannot be imported"):
        reg.get("broken")


def test_every_builtin_is_declared_by_its_own_file():
    """Methods, evaluators and loss terms are declared alike: configs/<kind>/<name>.yaml names the object
    (``plugin:``), whose own name is the file's."""
    for kind, registry in (("methods", METHODS), ("evaluators", EVALUATORS), ("loss_terms", LOSS_TERMS)):
        declared = declared_plugins(kind)
        assert declared and set(declared) <= set(registry.names()), kind
        for name in declared:
            assert registry.get(name).name == name, (kind, name)
