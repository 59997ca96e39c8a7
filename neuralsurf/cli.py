"""The one Hydra-aware module: config -> objects -> library calls.

Entry points: `train_main` (train.py, `neuralsurf-train`, `python -m neuralsurf train`), `evaluate_main`
(evaluate.py, `neuralsurf-evaluate`), `score_main` (`neuralsurf-score PRED GT`). The configs ship inside
the package (neuralsurf/configs; the repository's configs/ links to them), so an installed package runs
from any folder.
"""

from __future__ import annotations

import json
import logging
import os
import random
import time
from pathlib import Path

import hydra
import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from neuralsurf.training import fit

log = logging.getLogger("neuralsurf")


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def run_directory(cfg: DictConfig) -> Path:
    """Hydra's output directory for this run (or `cfg.run_dir` when called without @hydra.main)."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir)
    return Path(cfg.get("run_dir") or "outputs/run")


def format_table(metrics: dict[str, float]) -> str:
    """A two-column Markdown table of metric names and values."""
    rows = [f"| {name} | {value:.6g} |" if isinstance(value, float) else f"| {name} | {value} |"
            for name, value in metrics.items()]
    return "\n".join(["| metric | value |", "|---|---|", *rows])


RESULT_KEYS = ("data", "model", "observation", "optimizer", "seed")
"""Config sections that change what a fit computes (with the trainer's keys below)."""
TRAINER_BOOKKEEPING = ("resume", "progress", "log_every", "image_every", "mesh_every", "checkpoint_every", "cuda_graph")


def config_differences(stored: dict, current: dict) -> list[str]:
    """Dotted keys whose values differ between two run configs, among those that change the result
    (RESULT_KEYS, and the trainer's settings except its bookkeeping)."""
    def flat(value, prefix: str) -> dict:
        if isinstance(value, dict):
            return {k: v for key, item in value.items() for k, v in flat(item, f"{prefix}.{key}").items()}
        return {prefix: value}

    def relevant(cfg: dict) -> dict:
        trainer = {k: v for k, v in (cfg.get("trainer") or {}).items() if k not in TRAINER_BOOKKEEPING}
        return {**flat({k: cfg.get(k) for k in RESULT_KEYS}, "cfg"), **flat(trainer, "cfg.trainer")}

    old, new = relevant(stored), relevant(current)
    return sorted(key[4:] for key in set(old) | set(new) if old.get(key) != new.get(key))


def check_resume(run_dir: Path, cfg: dict) -> None:
    """Resume only into a run made with the same settings: else a ConfigError naming the keys."""
    from neuralsurf.errors import ConfigError
    from neuralsurf.training import CHECKPOINT_NAME, load_checkpoint

    path = run_dir / "checkpoints" / CHECKPOINT_NAME
    if not (cfg["trainer"].get("resume") and path.is_file()):
        return
    differences = config_differences(load_checkpoint(path).get("config") or {}, cfg)
    if differences:
        raise ConfigError(
            f"{run_dir} holds a run made with other settings ({', '.join(differences[:8])}"
            f"{' ...' if len(differences) > 8 else ''}); resuming would mix two runs. Use a new run directory "
            f"(hydra.run.dir=...) or start this one afresh with trainer.resume=false"
        )


def build_observations(cfg: DictConfig, scene) -> list:
    """The configured observations (cfg.observation: name -> partial of an Observation.from_scene) of `scene`."""
    return [instantiate(config, _convert_="all")(scene) for config in cfg.observation.values()]


def train(cfg: DictConfig) -> dict[str, float]:
    """Fit the configured model to the configured scene, extract, measure and write the outputs:
    <run dir>/mesh.ply, metrics.json, checkpoints/last.pt and TensorBoard events."""
    from neuralsurf.devices import resolve_device
    from neuralsurf.distributed import init_from_environment
    from neuralsurf.evaluation.methods import extract_scene_mesh
    from neuralsurf.io import write_mesh
    from neuralsurf.metrics import depth_metrics, evaluate_mesh
    from neuralsurf.priors import ShapeCollection

    device = resolve_device(init_from_environment(cfg.device))  # torchrun: the process group, a GPU per rank
    run_dir = shared_run_directory(cfg)
    config = OmegaConf.to_container(cfg, resolve=True)
    check_resume(run_dir, config)
    seed_everything(cfg.seed)
    scene = instantiate(cfg.data)
    log.info("scene %s: %s", scene.name, scene.description)
    if isinstance(scene, ShapeCollection):
        return train_prior(cfg, scene, run_dir, config, device)
    model = instantiate(cfg.model, _convert_="all")
    result = fit(model, build_observations(cfg, scene), optimizer=instantiate(cfg.optimizer), device=device,
                 seed=cfg.seed, run_dir=run_dir, config=config, **config["trainer"])

    started = time.perf_counter()
    mesh = extract_scene_mesh(result.field, scene, config["extract"])
    extract_seconds = time.perf_counter() - started
    mesh_path = run_dir / "mesh.ply"
    write_mesh(mesh_path, mesh)

    metrics = evaluate_mesh(mesh, scene.ground_truth, seed=cfg.seed) if scene.ground_truth is not None else {}
    if scene.held_out is not None:
        metrics.update(depth_metrics(mesh, scene.held_out))
    metrics = {**metrics, "watertight": mesh.is_watertight, "fit_seconds": result.seconds,
               "extract_seconds": extract_seconds, "steps": result.steps}
    (run_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, default=float))
    _log_hparams(run_dir, cfg, metrics)
    log.info("scene %s: mesh written to %s\n%s", scene.name, mesh_path.resolve(), format_table(metrics))
    return metrics


def shared_run_directory(cfg: DictConfig) -> Path:
    """The run directory; under torchrun, rank 0's on every rank (the others' own, made by Hydra
    before this code runs, is removed when empty: see `train_main`)."""
    from neuralsurf.distributed import broadcast_object

    own = run_directory(cfg)
    shared = Path(broadcast_object(str(own)))
    if shared != own and own.is_dir() and not any(own.iterdir()):
        own.rmdir()
    return shared


def train_prior(cfg: DictConfig, collection, run_dir: Path, config: dict, device: str) -> dict[str, float]:
    """Train a learned prior (cfg.model: a builder called with the collection's number of training
    shapes) over `collection` (built here, or found cached), then complete its test shapes from noisy
    clouds (cfg.score) and write mesh.ply (the first test shape), metrics.json (means and per-shape
    values) and checkpoints/last.pt (read back with neuralsurf.priors.load_prior). Under torchrun
    every rank trains; rank 0 alone builds, scores and writes. An auto-decoder also writes
    interpolation.png: the shapes between the codes of its first and last training shapes."""
    from neuralsurf.distributed import barrier, is_main_process, leave_process_group
    from neuralsurf.io import write_mesh
    from neuralsurf.models import AutoDecoder, OccupancyNetwork
    from neuralsurf.priors import interpolation_picture, score_completions
    from neuralsurf.structures import Normalization

    if is_main_process():
        collection.build(progress=bool(cfg.trainer.progress))
    barrier()
    model = instantiate(cfg.model, _convert_="all")(n_shapes=collection.count("train"))
    log.info("%s over %d training shapes in %s", type(model).__name__, collection.count("train"), collection.folder)
    trainer = dict(config["trainer"])
    if isinstance(model, OccupancyNetwork) and (trainer["image_every"] or trainer["mesh_every"]):
        log.info("no SDF previews of an occupancy network (no field without a cloud's code): image_every=0, "
                 "mesh_every=0")
        trainer.update(image_every=0, mesh_every=0)
    result = fit(model, build_observations(cfg, collection), optimizer=instantiate(cfg.optimizer), device=device,
                 seed=cfg.seed, run_dir=run_dir, config=config, normalization=Normalization(), **trainer)
    main = is_main_process()
    leave_process_group()  # training is over: rank 0 scores alone (its latent fits are single-process)
    if not main:
        return {}
    score = dict(config.get("score") or {})
    limit = score.pop("shapes", None)
    means, per_shape, mesh = score_completions(result.model, collection.test_shapes(limit), seed=cfg.seed,
                                               device=device, resolution=cfg.extract.resolution, **score)
    if mesh is not None:
        write_mesh(run_dir / "mesh.ply", mesh)
    if isinstance(result.model, AutoDecoder) and len(result.model.codes) >= 2:  # the first and last training shapes
        interpolation_picture(result.model, 0, len(result.model.codes) - 1, run_dir / "interpolation.png",
                              resolution=cfg.extract.resolution)
    metrics = {**means, "fit_seconds": result.seconds, "steps": result.steps}
    (run_dir / "metrics.json").write_text(json.dumps({**metrics, "per_shape": per_shape}, indent=2, default=float))
    _log_hparams(run_dir, cfg, metrics)
    log.info("%s: %d test shapes completed from %s noisy points; mesh of %s in %s\n%s", collection.name,
             len(per_shape), score.get("n_points", 3000), per_shape[0]["shape"], run_dir.resolve(),
             format_table(metrics))
    return metrics


def _log_hparams(run_dir: Path, cfg: DictConfig, metrics: dict) -> None:
    """Final metrics beside the flattened hyper-parameters, in TensorBoard's HPARAMS tab."""
    from torch.utils.tensorboard import SummaryWriter

    flat = json.loads(json.dumps(OmegaConf.to_container(cfg, resolve=True), default=str))
    hparams = {}

    def walk(prefix: str, value) -> None:
        if isinstance(value, dict):
            for key, item in value.items():
                walk(f"{prefix}.{key}" if prefix else key, item)
        else:
            hparams[prefix] = value if isinstance(value, (int, float, str, bool)) else str(value)

    walk("", flat)
    scores = {f"metric/{k}": float(v) for k, v in metrics.items() if isinstance(v, (int, float))}
    with SummaryWriter(str(run_dir / "tensorboard")) as writer:
        writer.add_hparams(hparams, scores, run_name="hparams")


def evaluate(cfg: DictConfig) -> list[dict]:
    """Run the selected methods on the selected scenes (cfg.methods x cfg.scenes) and write
    <run dir>/results.csv, results.json, results.md, plots/, renders/, meshes/ and report.html.
    Returns the rows (one dict per method x scene)."""
    import functools

    from neuralsurf.errors import ConfigError
    from neuralsurf.evaluation import run_benchmark, write_report
    from neuralsurf.evaluation.runner import environment

    run_dir = run_directory(cfg)
    scenes, methods = list(cfg.scenes), list(cfg.methods)
    for kind, names, known in (("scene", scenes, cfg.scene), ("method", methods, cfg.method)):
        unknown = [name for name in names if name not in known]
        if unknown:
            raise ConfigError(f"unknown {kind}(s) {unknown}; choose from {sorted(known)} "
                              f"(configs/{kind}/*.yaml)")

    def unwrapped(build, *args, **kwargs):
        """instantiate, re-raising the target's own error (SceneUnavailable stays a skip)."""
        from hydra.errors import InstantiationException

        try:
            return build(*args, **kwargs)
        except InstantiationException as error:
            if error.__cause__ is not None:
                raise error.__cause__ from None
            raise

    def scene_factory(name: str):
        return lambda: unwrapped(instantiate, cfg.scene[name])

    def method_factory(name: str):
        config = OmegaConf.to_container(cfg.method[name], resolve=True)

        def build():
            method = unwrapped(instantiate, cfg.method[name], _partial_=True, _convert_="all")
            return functools.partial(method, config=config)

        return build

    configs = {name: OmegaConf.to_container(cfg.method[name], resolve=True) for name in methods}
    started = time.perf_counter()
    rows = run_benchmark({name: scene_factory(name) for name in scenes},
                         {name: method_factory(name) for name in methods}, run_dir, seed=cfg.seed,
                         n_samples=cfg.n_samples, render=cfg.render, render_size=cfg.render_size,
                         save_meshes=cfg.save_meshes, configs=configs, log=log.info)
    seconds = time.perf_counter() - started
    extra = {"environment": environment(), "scenes": scenes, "methods": methods, "total_seconds": seconds,
             "config": OmegaConf.to_container(cfg, resolve=True)}
    table = write_report(rows, run_dir, extra)
    log.info("%d rows in %.1f min; results in %s (report.html, results.csv, results.json)\n%s",
             len(rows), seconds / 60, run_dir.resolve(), table)
    return rows


def check_run_dir_argument(argv: list[str]) -> None:
    """Exit with a clear message when `hydra.run.dir=` names a path under a file (Hydra's own mkdir
    would fail with a raw FileExistsError before any neuralsurf code runs)."""
    import sys

    for argument in argv:
        if argument.startswith(("hydra.run.dir=", "hydra.sweep.dir=")):
            key, value = argument.split("=", 1)
            path = Path(value)
            blocking = next((p for p in (path, *path.parents) if p.exists() and not p.is_dir()), None)
            if blocking is not None:
                sys.exit(f"error: {key}={value}: {blocking} is a file, not a folder; choose another run directory")


def train_main() -> None:
    """`neuralsurf-train [overrides]`: Hydra's command line around `train`."""
    import sys

    check_run_dir_argument(sys.argv[1:])
    if int(os.environ.get("RANK", "0")) > 0:  # torchrun: logs and the run's config from rank 0 only
        sys.argv += ["hydra.output_subdir=null", "hydra/job_logging=disabled"]
    hydra.main(version_base="1.3", config_path="configs", config_name="train")(train)()


def evaluate_main() -> None:
    """`neuralsurf-evaluate [overrides]`: Hydra's command line around `evaluate`."""
    import sys

    check_run_dir_argument(sys.argv[1:])
    hydra.main(version_base="1.3", config_path="configs", config_name="evaluate")(evaluate)()


def score_main(argv: list[str] | None = None) -> dict[str, float]:
    """`neuralsurf-score PRED GT [--samples N] [--json]`: the metrics of a mesh file against a
    ground-truth mesh file (evaluate_mesh: the ground truth's box centred, longest side 1)."""
    import argparse

    from neuralsurf.io import read_mesh
    from neuralsurf.metrics import evaluate_mesh

    parser = argparse.ArgumentParser(prog="neuralsurf-score", description=score_main.__doc__.split(":")[1].strip())
    parser.add_argument("pred", help="the reconstructed mesh (ply, obj, off, stl, glb)")
    parser.add_argument("gt", help="the ground-truth mesh")
    parser.add_argument("--samples", type=int, default=100_000, help="surface samples per mesh")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    args = parser.parse_args(argv)
    metrics = evaluate_mesh(read_mesh(args.pred), read_mesh(args.gt), n_samples=args.samples, seed=args.seed)
    print(json.dumps(metrics, indent=2) if args.json else format_table(metrics))
    return metrics
