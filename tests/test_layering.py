"""Import direction: io/ and baselines/ read sensors and data, never the synthetic-data package."""

import ast
from pathlib import Path

import neuralsurf

PACKAGE = Path(neuralsurf.__file__).parent


def _imported_modules(path: Path) -> set[str]:
    """Every module named by an import statement anywhere in the file (lazy imports included)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


def test_io_and_baselines_do_not_import_scenes():
    offenders = {
        str(path.relative_to(PACKAGE)): sorted(m for m in _imported_modules(path) if m.startswith("neuralsurf.scenes"))
        for folder in ("io", "baselines")
        for path in sorted((PACKAGE / folder).glob("*.py"))
    }
    offenders = {k: v for k, v in offenders.items() if v}
    assert offenders == {}, f"io/ and baselines/ must take sensor geometry from neuralsurf.geometry: {offenders}"


def test_sensor_geometry_lives_in_geometry_and_scanner_reexports_it():
    from neuralsurf import geometry
    from neuralsurf.scenes import scanner

    assert scanner.render_depth is geometry.render_depth
    assert scanner.kinect_sigma is geometry.kinect_sigma
