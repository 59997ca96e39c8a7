"""Types and ranges of the common config keys, checked before anything is built (`check_config`), and
of the shard sweep of evaluate.py's command line before any job starts (`check_sweep_arguments`).

The checks read a plain dict (`OmegaConf.to_container(cfg, resolve=True)`): a key is checked wherever
it appears, by its last two names, so `optimizer.lr` of train.py and `method.neural_sdf.optimizer.lr`
of evaluate.py are held to the same range. Each failure is one ConfigError naming the key, the value
and the allowed range.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable, Iterator
from typing import Any

from neuralsurf.errors import ConfigError

GRID_BYTES_PER_POINT = 5
"""Memory of extraction per grid point at least: the float32 value grid and a one-byte mask."""
MAX_SEED = 2**32 - 1
"""numpy's seeds lie in 0 .. 2**32 - 1."""


def _integer(low: int, high: int | None = None, none: bool = False) -> Callable[[Any], str | None]:
    def check(value: Any) -> str | None:
        if value is None and none:
            return None
        if isinstance(value, bool) or not isinstance(value, int) or value < low or (high is not None and value > high):
            return (f"an integer in {low}..{high}" if high is not None else f"an integer >= {low}") + \
                (" or null" if none else "")
        return None

    return check


def _positive(none: bool = False) -> Callable[[Any], str | None]:
    def check(value: Any) -> str | None:
        if value is None and none:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < math.inf:
            return "a finite number > 0" + (" or null" if none else "")
        return None

    return check


RULES: dict[tuple[str, str], Callable[[Any], str | None]] = {
    ("optimizer", "lr"): _positive(),
    ("trainer", "encoding_lr"): _positive(none=True),
    ("trainer", "steps"): _integer(0),
    ("model", "width"): _integer(1, 16_384),
    ("model", "depth"): _integer(1, 256),
    ("data", "n_points"): _integer(1, 10**9),
    ("scene", "n_points"): _integer(1, 10**9),
    ("extract", "resolution"): _integer(2, 65_536),
    ("", "seed"): _integer(0, MAX_SEED, none=True),
    ("", "n_samples"): _integer(1, 10**9),
    ("", "render_size"): _integer(16, 8192),
}
"""(parent, key) -> check returning the allowed range when a value is outside it. The parent "" matches
any; "scene" matches the scenes of evaluate.py (scene.<name>.n_points)."""


def _leaves(value: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], Any]]:
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _leaves(item, (*path, str(key)))
    else:
        yield path, value


def _rule(path: tuple[str, ...]) -> Callable[[Any], str | None] | None:
    parent = path[-2] if len(path) > 1 else ""
    if len(path) > 2 and path[-3] == "scene":
        parent = "scene"
    return RULES.get((parent, path[-1])) or RULES.get(("", path[-1]))


def available_memory() -> int | None:
    """Bytes this process can still allocate: the smaller of the system's available memory
    (/proc/meminfo's MemAvailable) and the address-space limit (RLIMIT_AS); None when neither is known."""
    limits = []
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    limits.append(int(line.split()[1]) * 1024)
    except (OSError, ValueError, IndexError):
        pass
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
        if soft != resource.RLIM_INFINITY:
            limits.append(soft)
    except (ImportError, OSError, ValueError):
        pass
    return min(limits) if limits else None


def check_resolution(key: str, resolution: int, memory: int | None = None) -> None:
    """ConfigError when extraction's grid at `resolution` cells along the longest side needs more than
    `memory` bytes (default `available_memory()`), naming the largest resolution that fits."""
    memory = available_memory() if memory is None else memory
    if memory is None:
        return
    needed = (resolution + 1) ** 3 * GRID_BYTES_PER_POINT
    if needed > memory:
        largest = max(2, int((memory / GRID_BYTES_PER_POINT) ** (1 / 3)) - 1)
        raise ConfigError(f"{key}={resolution}: its extraction grid needs at least {needed / 2**30:.1f} GiB, more "
                          f"than the {memory / 2**30:.1f} GiB available; use {key}={largest} or less")


def _parent(config: dict[str, Any], path: tuple) -> dict[str, Any]:
    """The dict that holds the leaf at `path` of `config`."""
    for key in path[:-1]:
        config = config[key]
    return config


def check_config(config: dict[str, Any], memory: int | None = None) -> None:
    """Raise ConfigError for the first common key of `config` (a run's resolved config as a plain dict)
    whose type or range is wrong (RULES), for shard/shards out of range, and for an extraction
    resolution whose grid cannot fit in `memory` bytes (default: what is available now)."""
    for path, value in sorted(_leaves(config), key=lambda leaf: len(leaf[0])):  # `seed` before `data.seed`
        rule = _rule(path)
        allowed = rule(value) if rule is not None else None
        if allowed is not None:
            key = ".".join(path)
            raise ConfigError(f"{key}={value!r:.60}: expected {allowed}; set {key}=<value> in that range")
        if path[-2:] == ("extract", "resolution") and not _parent(config, path).get("sparse"):  # sparse: no grid
            check_resolution(".".join(path), value, memory)
    if "shard" in config or "shards" in config:
        check_shards(config.get("shard", 0), config.get("shards", 1))
    if config.get("results_dir") is not None:
        check_writable_folder("results_dir", config["results_dir"])


def check_writable_folder(key: str, value: Any) -> None:
    """ConfigError unless the folder `value` (given as `key`) exists as a folder or can be made: no file
    stands where it or a parent should be, and a folder can be created in its first existing parent
    (one is made and removed there: read-only and virtual file systems fail)."""
    import tempfile
    from pathlib import Path

    if not isinstance(value, str) or not value:
        raise ConfigError(f"{key}={value!r:.60}: expected a folder path")
    path = Path(value).expanduser().absolute()
    existing = next(p for p in (path, *path.parents) if p.exists())
    if not existing.is_dir():
        raise ConfigError(f"{key}={value}: {existing} is a file, not a folder; choose another folder")
    try:
        os.rmdir(tempfile.mkdtemp(dir=existing, prefix=".neuralsurf-check-"))
    except OSError as error:
        raise ConfigError(f"{key}={value}: a folder cannot be created in {existing} ({error.strerror or error}); "
                          f"choose a folder you can write to") from None


def check_shards(shard: Any, shards: Any) -> None:
    """ConfigError unless shards >= 1 and 0 <= shard < shards (integers)."""
    if not (isinstance(shards, int) and not isinstance(shards, bool) and shards >= 1
            and isinstance(shard, int) and not isinstance(shard, bool) and 0 <= shard < shards):
        raise ConfigError(f"shard={shard!r:.40} shards={shards!r:.40}: expected integers with shards >= 1 and "
                          f"0 <= shard < shards; sweep shard=range(N) with shards=N to run every row once")


def _sweep_values(text: str) -> list[int] | None:
    """The integers a sweep value of Hydra's command line stands for ("3", "0,1,2", "range(3)",
    "range(0,4,2)"), or None when it is not such a value (left to Hydra and `check_shards` in the job)."""
    match = re.fullmatch(r"\s*range\(\s*(-?\d+)\s*(?:,\s*(-?\d+)\s*)?(?:,\s*(-?\d+)\s*)?\)\s*", text)
    if match:
        numbers = [int(n) for n in match.groups() if n is not None]
        if len(numbers) == 3 and numbers[2] == 0:
            return None
        return list(range(*numbers))[:100_000]
    parts = [part.strip() for part in text.split(",")]
    if all(re.fullmatch(r"-?\d+", part) for part in parts):
        return [int(part) for part in parts]
    return None


def check_sweep_arguments(argv: list[str]) -> None:
    """ConfigError when the `shard=` and `shards=` arguments of a command line (a multirun's sweep
    included) give a job whose shard lies outside 0..shards-1, before any job is launched. Values that
    are not integers, lists or ranges of them are left to Hydra and to the job's `check_shards`."""
    given: dict[str, list[int]] = {}
    for argument in argv:
        key, _, value = argument.partition("=")
        values = _sweep_values(value.strip("'\"")) if key in ("shard", "shards") else None
        if values is not None:
            given[key] = values
    if "shard" in given and "shards" in given:
        for shards in given["shards"]:
            for shard in given["shard"]:
                check_shards(shard, shards)
