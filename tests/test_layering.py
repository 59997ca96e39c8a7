"""The package's layers and its freedom from import circles, as pyproject.toml's import-linter
contracts state them (docs/architecture.md): checked on the package, and shown to catch an import
that runs up the layers."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

import neuralsurf

PACKAGE = Path(neuralsurf.__file__).parent
PYPROJECT = PACKAGE.parent / "pyproject.toml"

pytest.importorskip("importlinter")


def lint_imports(package_parent: Path) -> subprocess.CompletedProcess:
    """import-linter's contracts of pyproject.toml, run on the neuralsurf package found in `package_parent`."""
    script = "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())"
    return subprocess.run([sys.executable, "-c", script, str(PYPROJECT), "--no-cache"], cwd=package_parent,
                          env={**os.environ, "PYTHONPATH": str(package_parent)}, capture_output=True, text=True,
                          timeout=120, check=False)


@pytest.fixture(scope="module")
def contracts() -> str:
    if not PYPROJECT.is_file():
        pytest.skip("pyproject.toml is not beside the package (an installed copy): the contracts live there")
    return PYPROJECT.read_text()


def test_the_package_keeps_its_layers_and_has_no_import_circles(contracts):
    result = lint_imports(PACKAGE.parent)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "neuralsurf layers KEPT" in result.stdout and "no import circles KEPT" in result.stdout


def test_an_import_up_the_layers_breaks_the_contract(contracts, tmp_path):
    copy = tmp_path / "neuralsurf"
    shutil.copytree(PACKAGE, copy, ignore=shutil.ignore_patterns("__pycache__"))
    geometry = copy / "geometry.py"  # geometry sits below training: importing it runs up the layers
    geometry.write_text(geometry.read_text() + "\nfrom neuralsurf.training import fit  # noqa: E402\n")
    result = lint_imports(tmp_path)
    assert result.returncode == 1, result.stdout + result.stderr
    assert "neuralsurf layers BROKEN" in result.stdout
    assert "neuralsurf.geometry -> neuralsurf.training" in result.stdout


def test_camera_operations_have_one_home():
    """Every name of neuralsurf.cameras is defined there only: a module that has one imported it."""
    import importlib
    import pkgutil

    import neuralsurf
    from neuralsurf import cameras

    modules = [importlib.import_module(info.name) for info in pkgutil.walk_packages(neuralsurf.__path__, "neuralsurf.")
               if ".configs" not in info.name and not info.name.endswith("__main__")]
    elsewhere = [(module.__name__, name) for module in modules for name in cameras.__all__
                 if getattr(getattr(module, name, None), "__module__", "neuralsurf.cameras") != "neuralsurf.cameras"]
    assert len(modules) > 50 and elsewhere == []
