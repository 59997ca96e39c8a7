"""Rows as units of work: each (scene, method) result stored on its own, the moment it is done.

A results folder holds, per row, `rows/<scene>__<method>.json`:
`{"key": <hash of the row's settings>, "settings": {...}, "final": bool, "row": {...}}`, written after
the row's mesh and render, through a temporary file and a rename: a row file is whole or absent, and
the files it names are complete. A later run with the same settings (same key) reuses a final row
(status "ok", or skipped because the method does not apply) instead of computing it again; failed rows
and rows of scenes that could not be built are computed again. The report (results.csv, results.json,
results.md, plots/, report.html) is rebuilt from every stored row by `rebuild_report`, under a lock,
so jobs of one sweep that finish together write one consistent report.

Built scenes are kept too (`scenes/<scene>-<key>.pt`, `cached_scene`), so the jobs of a sweep and a
resumed run build each scene once.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from neuralsurf.errors import FileFormatError
from neuralsurf.evaluation.distances import with_common_pixel_errors
from neuralsurf.evaluation.filenames import NPZ, PNG, row_stem, safe_name, stored_file
from neuralsurf.evaluation.report import TABLE_COLUMNS, write_report
from neuralsurf.locks import file_lock, replaced, write_atomic
from neuralsurf.metrics import json_ready

ROWS = "rows"
"""The folder of the row files inside a results folder."""

log = logging.getLogger("neuralsurf")


def settings_key(settings: dict[str, Any]) -> str:
    """A row's key: the first 16 hex digits of the SHA-256 of its settings (a JSON-able dict, keys sorted)."""
    text = json.dumps(settings, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def row_path(results_dir: str | Path, scene: str, method: str) -> Path:
    """<results_dir>/rows/<scene>__<method>.json."""
    return Path(results_dir) / ROWS / f"{row_stem(scene, method)}.json"


def _plain(value: Any) -> Any:
    """JSON's fallback for numpy scalars and arrays, tensors and paths."""
    if hasattr(value, "tolist"):
        return value.tolist()
    return str(value)


def store_row(results_dir: str | Path, row: dict[str, Any], key: str | None, settings: dict[str, Any] | None,
              final: bool) -> Path:
    """Write one row (a dict with "scene" and "method") atomically; `final` rows with a `key` are reused
    by later runs with the same key. Returns the row file's path."""
    path = row_path(results_dir, row["scene"], row["method"])
    record = {"key": key, "settings": settings, "final": bool(final), "row": json_ready(row)}  # NaN: null + reason
    return write_atomic(path, json.dumps(record, indent=1, default=_plain))


def _read(path: Path) -> dict[str, Any] | None:
    """The record of one row file, or None (with a warning) when it is not a row file."""
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        log.warning("ignoring %s: not a readable row file (%s); delete it", path, error)
        return None
    row = record.get("row") if isinstance(record, dict) else None
    if isinstance(row, dict) and isinstance(row.get("undefined"), dict):  # written as null by store_row
        row.update({name: math.nan for name in row.pop("undefined") if row.get(name) is None})
    if not (isinstance(record, dict) and isinstance(record.get("row"), dict)
            and {"scene", "method", "status"} <= set(record["row"])):
        log.warning("ignoring %s: not a row file written by neuralsurf evaluate; delete it", path)
        return None
    row = record["row"]
    problem = row_problem(row)
    if problem is None and path.name != f"{row_stem(row['scene'], row['method'])}.json":
        problem = f"it holds the row of {row['method']!r:.80} on {row['scene']!r:.80}, whose file is " \
                  f"{row_stem(row['scene'], row['method'])}.json"
    if problem is not None:
        log.warning("ignoring %s: %s; delete it or evaluate its row again", path, problem)
        return None
    return record


STATUSES = ("ok", "skipped", "failed")
TEXT_FIELDS = ("reason", "scene_description", "config", "render", "held_out_render", "class_render", "mesh",
               "distances")
"""Row entries that are text when present."""
NUMBER_FIELDS = tuple(key for key, _ in TABLE_COLUMNS if key not in ("method", "scene", "status"))
"""Row entries that are numbers (or booleans, or null) when present."""


def row_problem(row: dict[str, Any]) -> str | None:
    """What makes `row` (read from a row file) unusable by the report, or None: its scene and method must be
    non-empty text, its status one of STATUSES, TEXT_FIELDS text, NUMBER_FIELDS numbers, and an ok row must
    carry its seconds."""
    for key in ("scene", "method"):
        if not isinstance(row[key], str) or not row[key]:
            return f"its {key} is {row[key]!r:.80}, not a name"
    if row["status"] not in STATUSES:
        return f"its status is {row['status']!r:.80}, not one of {', '.join(STATUSES)}"
    for key in TEXT_FIELDS:
        if row.get(key) is not None and not isinstance(row[key], str):
            return f"its {key} is {row[key]!r:.80}, not text"
    for key in NUMBER_FIELDS:
        if row.get(key) is not None and not isinstance(row[key], (bool, int, float)):
            return f"its {key} is {row[key]!r:.80}, not a number"
    if row["status"] == "ok" and not isinstance(row.get("seconds"), (int, float)):
        return "it is an ok row without its seconds"
    return None


def reusable_row(results_dir: str | Path, scene: str, method: str, key: str) -> dict[str, Any] | None:
    """The stored row of (scene, method) when it was stored final with this `key` and the mesh, render
    and distances it names still exist; else None (the row is to be computed)."""
    path = row_path(results_dir, scene, method)
    if not path.is_file():
        return None
    record = _read(path)
    if record is None or record.get("key") != key or not record.get("final"):
        return None
    row = record["row"]
    signatures = {"mesh": b"", "render": PNG, "class_render": PNG, "distances": NPZ}
    if any(row.get(name) and stored_file(results_dir, row[name], name, signature=signature) is None
           for name, signature in signatures.items()):
        return None
    return row


def read_rows(results_dir: str | Path) -> list[dict[str, Any]]:
    """Every stored row of a results folder (list of row dicts), in file-name order: one per (scene,
    method), from the file named by its `row_stem`; temporary files (names starting with ".") and files
    that are not valid rows (`row_problem`) are skipped, the latter with a warning."""
    folder = Path(results_dir) / ROWS
    records = (_read(path) for path in sorted(folder.glob("*.json")) if not path.name.startswith("."))
    return [record["row"] for record in records if record is not None]


def ordered(rows: Iterable[dict[str, Any]], scenes: Iterable[str] = (), methods: Iterable[str] = ()) -> list[dict]:
    """`rows` scene-major: the scenes and methods named in `scenes`/`methods` first, in that order, then
    the others by name."""
    scene_rank = {name: i for i, name in enumerate(scenes)}
    method_rank = {name: i for i, name in enumerate(methods)}

    def rank(row: dict) -> tuple:
        scene, method = row["scene"], row["method"]
        return (scene_rank.get(scene, math.inf), scene, method_rank.get(method, math.inf), method)

    return sorted(rows, key=rank)


def rebuild_report(results_dir: str | Path, extra: dict[str, Any] | None = None, scenes: Iterable[str] = (),
                   methods: Iterable[str] = ()) -> tuple[list[dict[str, Any]], str]:
    """Rewrite the report of a results folder from all its stored rows, under `<results_dir>/.report.lock`
    (jobs finishing together take turns; each file is replaced whole). `extra` goes to results.json and
    report.html, with "scenes" and "methods": those of the stored rows. Returns (rows, Markdown table)."""
    results_dir = Path(results_dir)
    with file_lock(results_dir / ".report.lock"):
        rows = with_common_pixel_errors(ordered(read_rows(results_dir), scenes, methods), results_dir)
        extra = {**(extra or {}), "scenes": list(dict.fromkeys(r["scene"] for r in rows)),
                 "methods": list(dict.fromkeys(r["method"] for r in rows))}
        try:
            table = write_report(rows, results_dir, extra)
        except OSError as error:
            where = getattr(error, "filename2", None) or error.filename or results_dir
            raise FileFormatError(f"cannot write the report of {results_dir}: {error.strerror or error} ({where}); "
                                  f"each report file must be a writable file: move what stands there away, then run "
                                  f"python evaluate.py report={results_dir}") from None
    return rows, table


SCENE_CLASSES = ("neuralsurf.scenes.recipes:Scene", "neuralsurf.scenes.recipes:SceneSet",
                 "neuralsurf.structures:PointCloud", "neuralsurf.structures:Mesh", "neuralsurf.structures:DepthFrames",
                 "neuralsurf.structures:PhotometricCapture", "neuralsurf.photometric:PhotometricStereoResult")
"""The classes a stored scene may hold (read back with torch.load(weights_only=True): plain data only)."""


def _scene_classes() -> list[type]:
    import importlib

    classes = []
    for name in SCENE_CLASSES:
        module, _, attribute = name.partition(":")
        classes.append(getattr(importlib.import_module(module), attribute))
    return classes


def load_scene(path: str | Path) -> Any:
    """A scene stored by `cached_scene`, read back with torch.load(weights_only=True) allowing only
    SCENE_CLASSES; torch's error for a file that holds anything else."""
    import torch

    with torch.serialization.safe_globals(_scene_classes()):
        return torch.load(path, weights_only=True)


def cached_scene(folder: str | Path, name: str, key: str, build: Callable[[], Any]) -> Any:
    """The scene `build()` makes, kept as `<folder>/<name>-<key>.pt` (key: a hash of the scene's
    settings): built by the first process that asks (under a lock; the others wait, then read it),
    read back by every later one. A file that cannot be read back (a scene holding other classes than
    SCENE_CLASSES) is built again and not kept. Errors of `build` (SceneUnavailable, ...) propagate."""
    import torch

    path = Path(folder) / f"{safe_name(name)}-{key}.pt"
    with file_lock(path.with_suffix(".lock")):
        if path.is_file():
            try:
                return load_scene(path)
            except Exception as error:  # noqa: BLE001 - a file that cannot be read is built again
                log.warning("scene %s: cannot read %s (%s); building it again", name, path,
                            str(error).splitlines()[0][:200])
                path.unlink(missing_ok=True)
        scene = build()
        try:
            with replaced(path) as temporary:
                torch.save(scene, temporary)
                load_scene(temporary)  # kept only when it reads back (no classes outside SCENE_CLASSES)
        except Exception as error:  # noqa: BLE001 - not kept: every process builds it then
            log.warning("scene %s is not kept in %s (%s)", name, folder, str(error).splitlines()[0][:200])
        return scene
