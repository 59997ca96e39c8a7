"""The Stanford bunny: the watertight copy shipped in the pymeshlab wheel (optional `data` extra)."""

from __future__ import annotations

from functools import lru_cache
from importlib.util import find_spec
from pathlib import Path

from neuralsurf.errors import MissingDependencyError
from neuralsurf.io import read_mesh
from neuralsurf.structures import Mesh


def bunny_path() -> Path:
    """Path of pymeshlab's watertight `bunny.obj`, found without importing pymeshlab (GPL-3)."""
    spec = find_spec("pymeshlab")
    if spec is None or not spec.submodule_search_locations:
        raise MissingDependencyError(
            "the Stanford bunny comes from the pymeshlab wheel (GPL-3), which is not installed; install the "
            "sample-data extra: ./install.sh (not lean), or pip install -e '.[data]' in a clone of neuralsurf "
            "(pip install 'neuralsurf[data]' from a package index)"
        )
    path = Path(next(iter(spec.submodule_search_locations))) / "tests" / "sample_meshes" / "bunny.obj"
    if not path.is_file():
        raise MissingDependencyError(
            f"pymeshlab is installed but has no sample bunny at {path}; "
            f"reinstall it: pip install --force-reinstall 'neuralsurf[data]'"
        )
    return path


@lru_cache(maxsize=1)
def _bunny() -> Mesh:
    return read_mesh(bunny_path())


def bunny() -> Mesh:
    """The watertight Stanford bunny (28,088 vertices, 56,172 faces) in its own frame (float64)."""
    return _bunny()
