"""The one Hydra-aware module: config -> objects -> library calls.

Entry points: `train_main` (train.py, `neuralsurf-train`, `python -m neuralsurf train`), `evaluate_main`
(evaluate.py, `neuralsurf-evaluate`), `score_main` (`neuralsurf-score PRED GT`). The configs ship inside
the package (neuralsurf/configs; the repository's configs/ links to them), so an installed package runs
from any folder.
"""

from __future__ import annotations

import copy
import functools
import json
import logging
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import hydra
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf, open_dict

from neuralsurf.baselines import register_meshes
from neuralsurf.checkpoints import CHECKPOINT_NAME, load_checkpoint
from neuralsurf.config_checks import check_config, check_sweep_arguments
from neuralsurf.devices import resolve_device
from neuralsurf.distributed import (
    barrier,
    broadcast_object,
    init_from_environment,
    is_main_process,
    leave_process_group,
)
from neuralsurf.errors import ConfigError, NeuralsurfError
from neuralsurf.evaluation import run_benchmark
from neuralsurf.evaluation.jobs import job_threads, row_settings, set_threads, shard_pairs
from neuralsurf.evaluation.render import interpolation_picture
from neuralsurf.evaluation.report import metrics_table
from neuralsurf.evaluation.runner import environment
from neuralsurf.evaluation.store import cached_scene, rebuild_report, settings_key
from neuralsurf.io import read_mesh, write_mesh
from neuralsurf.io.meshes import mesh_format
from neuralsurf.io.trajectories import write_trajectory_log, write_tum_trajectory
from neuralsurf.metrics import box_overlap, depth_metrics, evaluate_mesh, json_ready, watertight
from neuralsurf.models import AutoDecoder
from neuralsurf.priors import Collection, score_completions, train_prior
from neuralsurf.rooms import RoomSettings, fit_room
from neuralsurf.runlock import busy_message, claim, run_lock
from neuralsurf.scenes import extract_scene_mesh
from neuralsurf.structures import Mesh
from neuralsurf.training import fit, seed_everything

log = logging.getLogger("neuralsurf")


def run_directory(cfg: DictConfig) -> Path:
    """Hydra's output directory for this run (or `cfg.run_dir` when called without @hydra.main)."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir)
    return Path(cfg.get("run_dir") or "outputs/run")


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
    """The selected observations (`observation_configs`: name -> partial of an Observation.from_scene) of `scene`."""
    return [instantiate(config, _convert_="all")(scene) for config in observation_configs(cfg).values()]


CONFIGS = Path(__file__).parent / "configs"
"""The shipped Hydra configs (train.py's and evaluate.py's config_path)."""


def observation_configs(cfg: DictConfig) -> dict[str, DictConfig]:
    """The entries of `cfg.observation` (name -> config of an Observation.from_scene partial), each one that the
    selected observation options define. An entry without a `_target_` sets options of an observation that is not
    selected (an experiment tuned `points`, the command line chose observation=depth_rays): a ConfigError naming it
    and how to drop it, as is an empty selection."""
    entries, selected = dict(cfg.observation.items()), targeted(cfg.observation)
    if not selected:
        raise ConfigError(f"no observation is selected (cfg.observation holds {list(entries)}, none with a "
                          f"_target_); choose one with observation=<{'|'.join(sorted(set(observation_options().values())))}>")
    unselected = [name for name in entries if name not in selected]
    if unselected:
        name, options = unselected[0], observation_options()
        keys = ", ".join(map(str, entries[name].keys())) if isinstance(entries[name], DictConfig) else repr(entries[name])
        chosen = selected_options(selected)
        fitting = experiments_selecting(set(chosen))
        raise ConfigError(
            f"observation.{name} ({keys}) sets options of observation={options.get(name, name)}, which is not "
            f"selected (observation={','.join(chosen)} is): drop them with '~observation.{name}'"
            + (f" or choose an experiment that selects {','.join(chosen)}: {named(fitting)}"
               if fitting else ""))
    return selected


def check_feeds(cfg: DictConfig, choices: dict | None = None) -> None:
    """Before anything is built: a ConfigError unless the data feeds every selected observation (`data.feeds`: the
    observation options it can feed), naming the selected experiment and observation, the data, what it feeds and
    the fix. `choices`: Hydra's group choices (experiment, data) for the message; default: the running job's."""
    from hydra.core.hydra_config import HydraConfig

    if choices is None:
        choices = dict(HydraConfig.get().runtime.choices) if HydraConfig.initialized() else {}
    chosen = selected_options(targeted(cfg.observation))
    data = f"data={choices.get('data') or cfg.data.get('name') or cfg.data.get('_target_')}"
    feeds = cfg.data.get("feeds")
    if feeds is None:
        raise ConfigError(f"{data} does not say which observations it feeds: give its config a feeds: [...] key "
                          f"listing the observation options it can feed (configs/data/*.yaml do)")
    missing = [option for option in chosen if option not in feeds]
    if not missing:
        observation_configs(cfg)  # nothing left over, something selected
        return
    experiment = choices.get("experiment")
    selected = f"observation={','.join(chosen)}" + (f" (experiment={experiment})" if experiment else "")
    fitting = [name for name in experiments_selecting(set(feeds), first_for=choices.get("data")) if name != experiment]
    tuned = [name for name in experiment_settings(experiment)["tunes"] if name in cfg.observation
             and observation_options().get(name) != feeds[0]] if experiment else []  # left over by observation=
    drop = "".join(f" '~observation.{name}'" for name in tuned)
    raise ConfigError(
        f"{selected} does not fit {data}, which feeds {', '.join(feeds)} (data.feeds), not {', '.join(missing)}. "
        + (f"Choose an experiment that fits it, {named(fitting)}, or " if fitting else "Choose ")
        + f"an observation it feeds: observation={feeds[0]}{drop}"
        + (f" (dropping experiment={experiment}'s settings of {', '.join(tuned)})" if tuned else ""))


def targeted(observation: DictConfig) -> dict[str, DictConfig]:
    """The entries of `cfg.observation` with a `_target_`: those the selected observation options define."""
    return {name: entry for name, entry in observation.items() if isinstance(entry, DictConfig) and "_target_" in entry}


def selected_options(selected: dict[str, DictConfig]) -> list[str]:
    """The observation options (configs/observation/<option>.yaml) that define these entries of `cfg.observation`."""
    options = observation_options()
    return list(dict.fromkeys(options.get(name, name) for name in selected))


@functools.cache
def observation_options() -> dict[str, str]:
    """Entry of `cfg.observation` -> the observation option that defines it ("rays" -> "depth_rays")."""
    return {name: path.stem for path in sorted((CONFIGS / "observation").glob("*.yaml"))
            for name in OmegaConf.load(path)}


@functools.cache
def experiment_settings(name: str) -> dict[str, Any]:
    """What experiment `name` chooses, read from its file and those it extends: {"data": its data option or None,
    "observations": the observation options it selects, "tunes": the cfg.observation entries it sets}; empty for
    an experiment that is not shipped."""
    path = CONFIGS / "experiment" / f"{name}.yaml"
    settings = {"data": None, "observations": (), "tunes": ()}
    if not path.is_file():
        return settings
    config = OmegaConf.load(path)
    for entry in config.get("defaults", []):
        if isinstance(entry, str) and entry != "_self_":  # an experiment it extends
            settings = dict(experiment_settings(entry))
        elif isinstance(entry, DictConfig):
            key, value = next(iter(entry.items()))
            if key == "override /data":
                settings["data"] = value
            elif key == "override /observation":
                settings["observations"] = (value,) if isinstance(value, str) else tuple(value)
    settings["tunes"] = tuple(dict.fromkeys([*settings["tunes"], *config.get("observation", {})]))
    return settings


def experiments_selecting(options: set[str], first_for: str | None = None) -> list[str]:
    """The shipped experiments whose observations are all among `options`, those made for data `first_for` first."""
    names = sorted(path.stem for path in (CONFIGS / "experiment").glob("*.yaml"))
    fitting = [name for name in names if set(experiment_settings(name)["observations"] or ("?",)) <= options]
    return sorted(fitting, key=lambda name: experiment_settings(name)["data"] != first_for)


def named(experiments: list[str]) -> str:
    """["room", "bunny_depth"] -> "experiment=room (or bunny_depth)"."""
    return f"experiment={experiments[0]}" + (f" (or {', '.join(experiments[1:])})" if len(experiments) > 1 else "")


def without_feeds(cfg: DictConfig) -> DictConfig:
    """A copy of `cfg` without the `feeds` of the data configs it holds (train.py's `data`, the collections that
    evaluate.py's scenes and methods nest): what data can feed is checked (`check_feeds`), never passed to its
    target, stored with a run or hashed into a result's settings."""
    def declaring(config: Any, path: str = "") -> list[str]:  # the dotted paths of the configs holding one
        if not isinstance(config, dict):
            return []
        own = [path] if "_target_" in config and "feeds" in config else []
        return own + [found for key, value in config.items() for found in declaring(value, f"{path}.{key}".lstrip("."))]

    stripped = copy.deepcopy(cfg)
    for path in declaring(OmegaConf.to_container(cfg, resolve=False)):
        node = OmegaConf.select(stripped, path) if path else stripped
        with open_dict(node):
            del node["feeds"]
    return stripped


def train(cfg: DictConfig) -> dict[str, float]:
    """Fit the configured model to the configured scene, extract, measure and write the outputs:
    <run dir>/mesh.<extract.format> (mesh.ply by default), metrics.json, checkpoints/last.pt and
    TensorBoard events."""
    extension = mesh_format(cfg.extract.get("format", "ply"))  # a bad format fails before the fit
    check_feeds(cfg)  # the data feeds the selected observations, before anything is built
    cfg = without_feeds(cfg)
    device = resolve_device(init_from_environment(cfg.device))  # torchrun: the process group, a GPU per rank
    run_dir = shared_run_directory(cfg)
    with run_lock(run_dir, hold=is_main_process()):  # one run per run directory
        config = OmegaConf.to_container(cfg, resolve=True)
        check_resume(run_dir, config)
        seed_everything(cfg.seed)
        scene = instantiate(cfg.data)
        log.info("scene %s: %s", scene.name, scene.description)
        if isinstance(scene, Collection):  # a prior's shapes: train the prior
            return train_collection(cfg, scene, run_dir, config, device, extension)
        model = instantiate(cfg.model, _convert_="all")
        if isinstance(model, RoomSettings):  # a room's voxel fit: a solve, not a training loop
            mesh, fit_seconds, extract_seconds, steps = room_mesh(scene, model, device)
        else:
            result = fit(model, build_observations(cfg, scene), optimizer=instantiate(cfg.optimizer), device=device,
                         seed=cfg.seed, run_dir=run_dir, config=config, **config["trainer"])
            started = time.perf_counter()
            mesh = extract_scene_mesh(result.field, scene, config["extract"], cfg.seed)
            fit_seconds, extract_seconds, steps = result.seconds, time.perf_counter() - started, result.steps
        mesh_path = run_dir / f"mesh{extension}"
        write_mesh(mesh_path, mesh)
        if scene.trajectory is not None:  # tracked camera poses, next to the mesh
            write_tum_trajectory(run_dir / "trajectory.txt", scene.trajectory)
            write_trajectory_log(run_dir / "trajectory.log", scene.trajectory)

        metrics = (evaluate_mesh(mesh, scene.ground_truth, n_samples=cfg.score.n_samples, seed=cfg.seed)
                   if scene.ground_truth is not None else {})
        if scene.held_out is not None:
            metrics.update(depth_metrics(mesh, scene.held_out))
        metrics = {**metrics, "watertight": watertight(mesh, metrics), "fit_seconds": fit_seconds,
                   "extract_seconds": extract_seconds, "steps": steps}
        (run_dir / "metrics.json").write_text(json.dumps(json_ready(metrics), indent=2, default=float,
                                                         allow_nan=False))
        _log_hparams(run_dir, cfg, metrics)
        log.info("scene %s: mesh written to %s\n%s", scene.name, mesh_path.resolve(), metrics_table(metrics))
        return metrics


def room_mesh(scene, settings: RoomSettings, device) -> tuple[Mesh, float, float, int]:
    """`fit_room` of a depth scene's frames: (coloured mesh, fit seconds, 0 extraction seconds (the mesh comes
    with the fit), 0 steps). ConfigError for a scene without depth frames."""
    if scene.frames is None:
        raise ConfigError(f"model=room_voxels fits depth frames; scene {scene.name!r} has none: use experiment=room "
                          f"data.path=<capture> (or data=redkitchen), or a neural model (model=sdf_hashgrid)")
    started = time.perf_counter()
    mesh = fit_room(scene.frames, settings, str(device)).mesh
    return mesh, time.perf_counter() - started, 0.0, 0


def shared_run_directory(cfg: DictConfig) -> Path:
    """The run directory; under torchrun, rank 0's on every rank (the others' own, made by Hydra
    before this code runs, is removed when empty: see `train_main`)."""
    own = run_directory(cfg)
    shared = Path(broadcast_object(str(own)))
    if shared != own and own.is_dir() and not any(own.iterdir()):
        own.rmdir()
    return shared


def train_collection(cfg: DictConfig, collection: Collection, run_dir: Path, config: dict,
                     device: str, extension: str = ".ply") -> dict[str, float]:
    """Train a learned prior (cfg.model: a builder called with the collection's number of training
    shapes) over `collection` (built here, or found cached) with `neuralsurf.priors.train_prior`, then
    complete its test shapes from noisy clouds (cfg.score) and write mesh<extension> (the first test
    shape), metrics.json (means and per-shape values) and checkpoints/last.pt (read back with
    neuralsurf.priors.load_prior). Under torchrun every rank trains; rank 0 alone builds, scores and
    writes. An auto-decoder also writes interpolation.png: the shapes between the codes of its first
    and last training shapes. A folder in Occupancy Networks' layout has no meshes: its prior is trained
    and kept, not scored (`Collection.check_prior`, checked before building)."""
    observations = observation_configs(cfg)
    scored = collection.check_prior(  # before building
        {name: OmegaConf.to_container(entry, resolve=True) for name, entry in observations.items()})
    if is_main_process():
        collection.build(progress=bool(cfg.trainer.progress))
    barrier()
    builders = [instantiate(entry, _convert_="all") for entry in observations.values()]
    result = train_prior(collection, instantiate(cfg.model, _convert_="all"), builders,
                         optimizer=instantiate(cfg.optimizer), trainer=config["trainer"], seed=cfg.seed, device=device,
                         run_dir=run_dir, config=config)
    main = is_main_process()
    leave_process_group()  # training is over: rank 0 scores alone (its latent fits are single-process)
    if not main:
        return {}
    if not scored:  # Occupancy Networks' layout: the checkpoint alone (check_prior warned)
        metrics = {"fit_seconds": result.seconds, "steps": result.steps}
        (run_dir / "metrics.json").write_text(json.dumps(json_ready(metrics), indent=2, default=float, allow_nan=False))
        return metrics
    score = dict(config.get("score") or {})
    limit = score.pop("shapes", None)
    means, per_shape, mesh = score_completions(result.model, collection.test_shapes(limit), seed=cfg.seed,
                                               device=device, resolution=cfg.extract.resolution, **score)
    if mesh is not None:
        write_mesh(run_dir / f"mesh{extension}", mesh)
    if isinstance(result.model, AutoDecoder) and len(result.model.codes) >= 2:  # the first and last training shapes
        interpolation_picture(result.model, 0, len(result.model.codes) - 1, run_dir / "interpolation.png",
                              resolution=cfg.extract.resolution)
    metrics = {**means, "fit_seconds": result.seconds, "steps": result.steps}
    (run_dir / "metrics.json").write_text(json.dumps(json_ready({**metrics, "per_shape": per_shape}), indent=2,
                                                     default=float, allow_nan=False))
    _log_hparams(run_dir, cfg, metrics)
    log.info("%s: %d test shapes completed from %s noisy points; mesh of %s in %s\n%s", collection.name,
             len(per_shape), score.get("n_points", 3000), per_shape[0]["shape"], run_dir.resolve(),
             metrics_table(metrics))
    return metrics


def _log_hparams(run_dir: Path, cfg: DictConfig, metrics: dict) -> None:
    """Final metrics beside the flattened hyper-parameters, in TensorBoard's HPARAMS tab."""
    from torch.utils.tensorboard import SummaryWriter
    from torch.utils.tensorboard.summary import hparams as hparams_summary

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
    # add_hparams would write into a sub-run of its own: the run would be listed twice
    with SummaryWriter(str(run_dir / "tensorboard")) as writer:
        for summary in hparams_summary(hparams, scores):
            writer.file_writer.add_summary(summary)
        for name, value in scores.items():
            writer.add_scalar(name, value)


def evaluate(cfg: DictConfig) -> list[dict]:
    """Run the selected methods on the selected scenes (cfg.methods x cfg.scenes; with cfg.shards > 1,
    only part cfg.shard of those rows) and write <results dir>/rows/ (one file per row, as soon as it is
    done; rows stored with the same settings are reused), meshes/, renders/, and the report rebuilt from
    every stored row after each one: results.csv, results.json, results.md, plots/ and report.html.
    The results dir: cfg.results_dir, else Hydra's run directory (a multirun: its sweep directory, shared
    by the jobs). With cfg.report set, only rebuilds the report of that folder. Returns this job's rows."""
    cfg = without_feeds(cfg)  # the collections that scenes and methods nest are data configs
    if cfg.get("report"):
        if not any((Path(cfg.report) / "rows").glob("*.json")):
            raise ConfigError(f"report={cfg.report}: no stored rows in {Path(cfg.report) / 'rows'}; give the results "
                              f"folder of an evaluate.py run (its hydra.run.dir, hydra.sweep.dir or results_dir)")
        rows, table = rebuild_report(cfg.report, {"environment": environment()})
        log.info("report of %d stored rows rebuilt in %s (report.html, results.csv, results.json)\n%s",
                 len(rows), Path(cfg.report).resolve(), table)
        return rows
    launcher, results_dir = evaluation_job(cfg)
    threads = job_threads(cfg.get("threads"), launcher)
    if threads is not None:
        set_threads(threads)
    scenes, methods = list(cfg.scenes), list(cfg.methods)
    for kind, names, known in (("scene", scenes, cfg.scene), ("method", methods, cfg.method)):
        unknown = [name for name in names if name not in known]
        if unknown:
            raise ConfigError(f"unknown {kind}(s) {unknown}; choose from {sorted(known)} "
                              f"(configs/{kind}/*.yaml)")
    pairs = shard_pairs(scenes, methods, cfg.get("shard", 0), cfg.get("shards", 1))

    scene_configs = {name: OmegaConf.to_container(cfg.scene[name], resolve=True) for name in scenes}

    def scene_factory(name: str):
        def build():
            return instantiate_unwrapped(cfg.scene[name])

        if not cfg.get("scene_cache", True):
            return build
        key = settings_key({"scene": scene_configs[name]})
        return lambda: cached_scene(results_dir / "scenes", name, key, build)

    def method_factory(name: str):
        config = OmegaConf.to_container(cfg.method[name], resolve=True)

        def build():
            method = instantiate_unwrapped(cfg.method[name], _partial_=True, _convert_="all")
            return functools.partial(method, config=config)

        return build

    configs = {name: OmegaConf.to_container(cfg.method[name], resolve=True) for name in methods}
    common = {key: cfg[key] for key in ("seed", "n_samples", "render", "render_size", "save_meshes", "mesh_format")}
    settings = {(s, m): row_settings(scene_configs[s], configs[m], common) for s, m in pairs}
    started, computed = time.perf_counter(), []

    def report() -> tuple[list[dict], str]:
        extra = {"environment": environment(), "total_seconds": time.perf_counter() - started,
                 "config": OmegaConf.to_container(cfg, resolve=True)}
        return rebuild_report(results_dir, extra, scenes, methods)

    log.info("%d of %d rows in this job (shard %d of %d), %s threads; results in %s", len(pairs),
             len(scenes) * len(methods), cfg.get("shard", 0), cfg.get("shards", 1), threads or "default",
             results_dir.resolve())
    rows = run_benchmark({name: scene_factory(name) for name in scenes},
                         {name: method_factory(name) for name in methods}, results_dir, seed=cfg.seed,
                         n_samples=cfg.n_samples, render=cfg.render, render_size=cfg.render_size,
                         save_meshes=cfg.save_meshes, mesh_format=cfg.mesh_format, configs=configs, log=log.info,
                         pairs=pairs, settings=settings, on_row=lambda row: (computed.append(row), report()))
    seconds = time.perf_counter() - started
    stored, table = report()
    reused = len(rows) - len(computed)
    log.info("%d rows in %.1f min (%d computed, %d reused); %d rows in %s (report.html, results.csv, "
             "results.json)\n%s", len(rows), seconds / 60, len(rows) - reused, reused, len(stored),
             results_dir.resolve(), table)
    return rows


def evaluation_job(cfg: DictConfig) -> tuple[dict, Path]:
    """(Hydra's launcher config as a dict, or {} without Hydra; the results dir): cfg.results_dir, else
    the sweep directory of a multirun (one folder for all its jobs), else the run directory."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized():
        return {}, Path(cfg.get("results_dir") or run_directory(cfg))
    hydra_cfg = HydraConfig.get()
    launcher = OmegaConf.to_container(hydra_cfg.launcher, resolve=True) if "launcher" in hydra_cfg else {}
    if cfg.get("results_dir"):
        return launcher, Path(cfg.results_dir)
    if hydra_cfg.mode == RunMode.MULTIRUN:
        return launcher, Path(hydra_cfg.sweep.dir)
    return launcher, run_directory(cfg)


def check_run_dir_argument(argv: list[str], lock: bool = False) -> None:
    """Exit with a clear message when `hydra.run.dir=` (or `hydra.sweep.dir=`) names a path under a
    file or one that cannot be created (a read-only or virtual file system such as /proc, no
    permission): Hydra's own mkdir would fail with a raw OSError before any neuralsurf code runs.
    A run directory another live run holds (`neuralsurf.runlock`) is refused too, before Hydra
    writes its config and log there; with `lock` (train.py) its lock is taken here (`claim`) and held
    through the run, so two runs started together cannot both pass."""
    import tempfile

    for argument in argv:
        if argument.startswith(("hydra.run.dir=", "hydra.sweep.dir=")):
            key, value = argument.split("=", 1)
            path = Path(value)
            blocking = next((p for p in (path, *path.parents) if p.exists() and not p.is_dir()), None)
            if blocking is not None:
                sys.exit(f"error: {key}={value}: {blocking} is a file, not a folder; choose another run directory")
            if "${" in value:  # resolved by Hydra later
                continue
            existing = next(p for p in (path.absolute(), *path.absolute().parents) if p.exists())
            try:  # a folder made and removed where the run directory's first missing folder would go
                os.rmdir(tempfile.mkdtemp(dir=existing, prefix=".neuralsurf-check-"))
            except OSError as error:
                sys.exit(f"error: {key}={value}: the run directory cannot be created in {existing} "
                         f"({error.strerror or error}); choose a folder you can write to")
            rank = int(os.environ.get("RANK", "0"))  # torchrun: rank 0's lock is the job's own
            busy = (claim if lock else busy_message)(path) if key == "hydra.run.dir" and rank == 0 else None
            if busy is not None:  # before Hydra writes its config and log into the other run's folder
                sys.exit(f"error: {key}={value}: {busy}")


def check_override_keys(argv: list[str], config_name: str) -> None:
    """Exit with the config groups and options when an override's first key names none of them
    (`dat=file`): Hydra would suggest `+dat=file`, which adds a key nothing reads."""
    configs = Path(__file__).parent / "configs"
    primary = OmegaConf.load(configs / f"{config_name}.yaml")
    groups = [next(iter(entry)) for entry in primary.defaults if isinstance(entry, DictConfig)
              and "@" not in next(iter(entry))]
    options = [key for key in primary if key not in ("defaults", "hydra")]
    known = {"hydra", *options, *(path.name for path in configs.iterdir() if path.is_dir())}
    for path in configs.glob("*/*.yaml"):  # keys that options of a group add at the top level
        if "@package _global_" in path.read_text().split("\n", 1)[0]:
            config = OmegaConf.load(path)
            known.update(key for key in config if key != "defaults")
            known.update(next(iter(entry)).split("@", 1)[1].split(".")[0]  # `- /data@folder: ...` adds folder
                         for entry in config.get("defaults", []) if isinstance(entry, DictConfig)
                         and "@" in next(iter(entry)))
    for argument in argv:
        if argument.startswith(("-", "+", "~")) or "=" not in argument:
            continue
        first = argument.split("=", 1)[0].replace("/", ".").replace("@", ".").split(".")[0]
        if first not in known:
            sys.exit(f"error: {argument}: {first!r} is not a config group or option. Config groups: "
                     f"{', '.join(groups)}; options: {', '.join(options)} (docs/configs.md lists them all)")


def target_error(error: BaseException) -> BaseException:
    """The error a config's target raised, behind Hydra's "Error in call to target" wrappers."""
    from hydra.errors import InstantiationException

    while isinstance(error, InstantiationException) and error.__cause__ is not None:
        error = error.__cause__
    return error


def instantiate_unwrapped(config: DictConfig, **kwargs: Any) -> Any:
    """Hydra's instantiate, raising the target's own error (a SceneUnavailable stays a skip)."""
    try:
        return instantiate(config, **kwargs)
    except Exception as error:
        cause = target_error(error)
        if cause is error:
            raise
        raise cause from None


def user_error(error: BaseException) -> NeuralsurfError | None:
    """The neuralsurf error behind Hydra's "Error in call to target" wrapper, a ConfigError for a
    mandatory key left out (`data=file` without `data.path`), or None for anything else (a bug)."""
    from omegaconf.errors import MissingMandatoryValue

    error = target_error(error)
    if isinstance(error, MissingMandatoryValue):
        key = getattr(error, "full_key", None) or "a mandatory key"
        return ConfigError(f"{key} is required: add {key}=<value> to the command (docs/configs.md lists the keys)")
    return error if isinstance(error, NeuralsurfError) else None


def reporting_errors(task: Callable[[DictConfig], Any]) -> Callable[[DictConfig], Any]:
    """`task` with its errors in the run's log: a neuralsurf error (also behind Hydra's wrappers) is
    logged as one line and ends the process with status 1, no traceback; anything else is logged
    with its traceback and raised."""
    @functools.wraps(task)
    def run(cfg: DictConfig) -> Any:
        try:
            check_config(OmegaConf.to_container(cfg, resolve=True))  # before anything is built
            return task(cfg)
        except Exception as error:
            known = user_error(error)
            if known is None:
                log.exception("%s failed", task.__name__)
                raise
            log.error("%s: %s", type(known).__name__, known)
            sys.exit(1)

    return run


def _hydra_main(task: Callable[[DictConfig], Any], config_name: str) -> None:
    """Hydra's command line around `task`, with Python's warnings in the run's log."""
    check_run_dir_argument(sys.argv[1:], lock=config_name == "train")
    check_override_keys(sys.argv[1:], config_name)
    try:
        check_sweep_arguments(sys.argv[1:])  # before a multirun launches any job
    except ConfigError as error:
        sys.exit(f"error: {error}")
    logging.captureWarnings(True)
    hydra.main(version_base="1.3", config_path="configs", config_name=config_name)(reporting_errors(task))()


def train_main() -> None:
    """`neuralsurf-train [overrides]`: Hydra's command line around `train`."""
    if int(os.environ.get("RANK", "0")) > 0:  # torchrun: logs and the run's config from rank 0 only
        sys.argv += ["hydra.output_subdir=null", "hydra/job_logging=disabled"]
    _hydra_main(train, "train")


def evaluate_main() -> None:
    """`neuralsurf-evaluate [overrides]`: Hydra's command line around `evaluate`."""
    _hydra_main(evaluate, "evaluate")


def score_main(argv: list[str] | None = None) -> int:
    """`neuralsurf-score PRED GT [--samples N] [--seed S] [--json]`: prints the metrics of a mesh file
    against a ground-truth mesh file; exit status 0, or 1 with the reason for an unreadable file."""
    import argparse

    parser = argparse.ArgumentParser(
        prog="neuralsurf-score",
        description="Score a reconstructed mesh against a ground-truth mesh with the metrics of the literature "
                    "(Chamfer-L1/-L2, exact point-to-mesh Chamfer-L1, F-scores, normal consistency, Hausdorff, "
                    "volumetric IoU when both are watertight), in the ground truth's normalised frame: its "
                    "bounding box centred, longest side 1.")
    parser.add_argument("pred", help="the reconstructed mesh (ply, obj, off, stl, glb)")
    parser.add_argument("gt", help="the ground-truth mesh (same formats)")
    parser.add_argument("--samples", type=int, default=100_000, help="surface samples per mesh (default 100000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the surface samples (default 0)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of a Markdown table")
    parser.add_argument("--align", action="store_true",
                        help="first move PRED onto GT rigidly (neuralsurf.baselines.register_meshes: box centres "
                             "matched, then ICP of surface samples); for meshes in different frames")
    args = parser.parse_args(argv)
    try:
        pred, gt = read_mesh(args.pred), read_mesh(args.gt)
        if args.align:
            registration = register_meshes(pred, gt, seed=args.seed)
            rotation, translation = registration.transform[:3, :3], registration.transform[:3, 3]
            moved = (pred.vertices.double() @ rotation.T + translation).to(pred.vertices.dtype)
            pred = Mesh(moved, pred.faces, pred.vertex_colors)
            print(f"neuralsurf-score: aligned {args.pred} to {args.gt} (ICP fitness {registration.fitness:.3f}, "
                  f"inlier RMSE {registration.inlier_rmse:.3g}); transform:\n{registration.transform.numpy()}",
                  file=sys.stderr)
        overlap = box_overlap(pred, gt)
        if overlap < 0.5:
            print(f"neuralsurf-score: warning: the bounding boxes of {args.pred} and {args.gt} overlap by only "
                  f"{overlap:.0%}: the meshes are likely in different frames or units, and the scores measure "
                  f"that offset; --align registers PRED to GT first", file=sys.stderr)
        metrics = evaluate_mesh(pred, gt, n_samples=args.samples, seed=args.seed)
    except NeuralsurfError as error:
        print(f"neuralsurf-score: {error}", file=sys.stderr)
        return 1
    print(json.dumps(json_ready(metrics), indent=2, allow_nan=False) if args.json else metrics_table(metrics))
    return 0
