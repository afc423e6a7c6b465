"""The engine's old flat module names import as the new modules, with a DeprecationWarning (voxnerf/__init__.py)."""

from __future__ import annotations

import importlib
import subprocess
import sys

import pytest

import voxnerf


def _fresh(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-W", "always::DeprecationWarning", "-c", code],
                          capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("old", sorted(voxnerf.MOVED_MODULES))
def test_every_old_module_name_is_the_new_module(old):
    new = voxnerf.MOVED_MODULES[old]
    sys.modules.pop(old, None)  # only the alias's entry: the new module stays loaded, once
    with pytest.warns(DeprecationWarning, match=new.replace(".", r"\.")):
        module = importlib.import_module(old)
    assert module is importlib.import_module(new)


def test_a_submodule_of_a_moved_package_is_not_loaded_twice():
    result = _fresh("import sys, voxnerf.importers.colmap as old, voxnerf.data.importers.colmap as new; "
                    "print(old is new, sys.modules['voxnerf.importers.colmap'] is new)")
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["True", "True"]
    assert "voxnerf.importers.colmap is now voxnerf.data.importers.colmap" in result.stderr


@pytest.mark.parametrize(("package", "name", "module"), [
    ("voxnerf.model", "VoxNeRFModel", "voxnerf.model.voxnerf_model"),
    ("voxnerf.cameras", "Intrinsics", "voxnerf.cameras.rays"),
    ("voxnerf.prior", "load_prior", "voxnerf.prior.loading"),
    ("voxnerf.inference", "render_rays_fast", "voxnerf.inference.fast_path"),
])
def test_names_of_an_old_module_that_is_now_a_package_still_import(package, name, module):
    result = _fresh(f"from {package} import {name} as a; from {module} import {name} as b; print(a is b)")
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "True"
    assert f"{package}.{name} is now {module}.{name}" in result.stderr


def test_a_package_still_imports_its_submodules_and_refuses_unknown_names():
    from voxnerf.model import field  # a submodule, not an old name: no warning, the module itself

    assert field is importlib.import_module("voxnerf.model.field")
    with pytest.raises(ImportError):
        exec("from voxnerf.model import no_such_name", {})


def test_new_names_import_without_warnings():
    result = _fresh("import voxnerf.data.scene, voxnerf.cameras.rules, voxnerf.model.voxnerf_model, "
                    "voxnerf.inference.render, voxnerf.prior.octree")
    assert result.returncode == 0, result.stderr
    assert "DeprecationWarning" not in result.stderr
