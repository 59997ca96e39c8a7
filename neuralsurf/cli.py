"""The one Hydra-aware module: config -> objects -> library calls. train.py and evaluate.py call in."""

from __future__ import annotations

import json
import random
import time
from pathlib import Path

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from neuralsurf.training import fit


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


def train(cfg: DictConfig) -> dict[str, float]:
    """Fit the configured model to the configured scene, extract, measure and write the outputs:
    <run dir>/mesh.ply, metrics.json, checkpoints/last.pt and TensorBoard events."""
    from neuralsurf.extract import extract_mesh
    from neuralsurf.io import write_mesh
    from neuralsurf.metrics import evaluate_mesh

    run_dir = run_directory(cfg)
    seed_everything(cfg.seed)
    scene = instantiate(cfg.data)
    model = instantiate(cfg.model, _convert_="all")
    trainer = OmegaConf.to_container(cfg.trainer, resolve=True)
    result = fit(model, scene.cloud, loss=instantiate(cfg.loss), device=cfg.device, seed=cfg.seed,
                 run_dir=run_dir, config=OmegaConf.to_container(cfg, resolve=True), **trainer)

    started = time.perf_counter()
    mesh = extract_mesh(result.field, **OmegaConf.to_container(cfg.extract, resolve=True))
    extract_seconds = time.perf_counter() - started
    mesh_path = run_dir / "mesh.ply"
    write_mesh(mesh_path, mesh)

    metrics = evaluate_mesh(mesh, scene.ground_truth, seed=cfg.seed) if scene.ground_truth is not None else {}
    metrics = {**metrics, "watertight": mesh.is_watertight, "fit_seconds": result.seconds,
               "extract_seconds": extract_seconds, "steps": result.steps}
    (run_dir / "metrics.json").write_text(json.dumps(metrics, indent=2, default=float))
    _log_hparams(run_dir, cfg, metrics)
    print(f"\nscene {scene.name}: mesh written to {mesh_path.resolve()}")
    print(format_table(metrics))
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
                         save_meshes=cfg.save_meshes, configs=configs)
    seconds = time.perf_counter() - started
    extra = {"environment": environment(), "scenes": scenes, "methods": methods, "total_seconds": seconds,
             "config": OmegaConf.to_container(cfg, resolve=True)}
    table = write_report(rows, run_dir, extra)
    print(f"\n{len(rows)} rows in {seconds / 60:.1f} min; results in {run_dir.resolve()} (report.html, "
          f"results.csv, results.json)\n")
    print(table)
    return rows
