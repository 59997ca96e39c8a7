"""Splitting an evaluation into jobs: which rows a job runs, what decides a row, how many threads a job
may use. Plain values in, plain values out (evaluate.py reads them from its config and from Hydra's)."""

from __future__ import annotations

import os
from typing import Any

import neuralsurf
from neuralsurf.errors import ConfigError

THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def shard_pairs(scenes: list[str], methods: list[str], shard: int = 0, shards: int = 1) -> list[tuple[str, str]]:
    """The rows (scene, method) of job `shard` of `shards`: the scene-major list of every row cut into
    `shards` consecutive parts of (almost) equal length. Raises ConfigError for a shard out of range."""
    if not (isinstance(shards, int) and shards >= 1 and isinstance(shard, int) and 0 <= shard < shards):
        raise ConfigError(f"shard={shard} shards={shards}: need shards >= 1 and 0 <= shard < shards; sweep "
                          f"shard=range({shards}) with shards={shards} to run every row once")
    pairs = [(scene, method) for scene in scenes for method in methods]
    return pairs[shard * len(pairs) // shards:(shard + 1) * len(pairs) // shards]


def row_settings(scene: dict[str, Any], method: dict[str, Any], common: dict[str, Any]) -> dict[str, Any]:
    """Everything that decides a row's result and files: the scene's and method's resolved configs
    (plain dicts) and the run-wide settings in `common` (seed, n_samples, render, ...). Its hash
    (`store.settings_key`) tells a rerun whether a stored row can be reused."""
    return {"scene": scene, "method": method, **common, "neuralsurf": neuralsurf.__version__}


def job_threads(threads: int | None, launcher: dict[str, Any] | None, cpus: int | None = None) -> int | None:
    """Threads one job may use: `threads` when given; else the cores (`cpus`, default those this
    process may run on) shared by the joblib launcher's `n_jobs` parallel jobs; else the launcher's
    `cpus_per_task` (submitit); else None (leave torch's default). Raises ConfigError for threads < 1."""
    if threads is not None:
        if not (isinstance(threads, int) and threads >= 1):
            raise ConfigError(f"threads={threads}: give a positive number of threads per job, or threads=null")
        return threads
    launcher = launcher or {}
    cpus = cpus or available_cpus()
    n_jobs = launcher.get("n_jobs")
    if isinstance(n_jobs, int) and n_jobs != 0:
        parallel = cpus if n_jobs < 0 else min(n_jobs, cpus)  # joblib: -1 means every core
        return max(1, cpus // parallel)
    per_task = launcher.get("cpus_per_task")
    if isinstance(per_task, int) and per_task >= 1:
        return per_task
    return None


def available_cpus() -> int:
    """The cores this process may run on (its affinity: a SLURM allocation's), else os.cpu_count()."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def set_threads(threads: int) -> None:
    """Use `threads` threads for torch here and for OpenMP/BLAS in processes started from here."""
    import torch

    torch.set_num_threads(threads)
    for name in THREAD_VARIABLES:
        os.environ[name] = str(threads)
