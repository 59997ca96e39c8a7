"""Training a learned prior over a shape collection: `train_prior` (one fit, as train.py's prior
experiments run it) and `trained_prior` (trained once into a folder and reused, as evaluate.py's
learned-prior methods take it)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path

from torch import nn

from neuralsurf.checkpoints import CHECKPOINT_NAME, load_checkpoint
from neuralsurf.locks import file_lock
from neuralsurf.models import OccupancyNetwork
from neuralsurf.priors.collection import Collection
from neuralsurf.structures import Normalization
from neuralsurf.training import FitResult, default_optimizer, fit

log = logging.getLogger("neuralsurf")


def train_prior(collection: Collection, model: Callable[..., nn.Module], observations: Sequence[Callable], *,
                optimizer: Callable | None = None, trainer: dict | None = None, seed: int = 0, device: str = "cpu",
                run_dir: str | Path | None = None, config: dict | None = None) -> FitResult:
    """Fit `model(n_shapes=<training shapes>)` over the built `collection` with the observations
    `observations[i](collection)` and `fit`'s `trainer` options, in the collection's unit frame
    (`normalization=Normalization()`), into `run_dir` (resumed there). An occupancy network has no
    field without a cloud's code, so its SDF previews are turned off (image_every=0, mesh_every=0)."""
    model = model(n_shapes=collection.count("train"))
    log.info("%s over %d training shapes in %s", type(model).__name__, collection.count("train"), collection.folder)
    trainer = dict(trainer or {})
    if isinstance(model, OccupancyNetwork) and (trainer.get("image_every") or trainer.get("mesh_every")):
        log.info("no SDF previews of an occupancy network (no field without a cloud's code): image_every=0, "
                 "mesh_every=0")
        trainer.update(image_every=0, mesh_every=0)
    return fit(model, [build(collection) for build in observations], optimizer=optimizer or default_optimizer,
               device=device, seed=seed, run_dir=run_dir, config=config, normalization=Normalization(), **trainer)


def trained_prior(run_dir: str | Path, collection: Collection, model: Callable[..., nn.Module],
                  observations: Sequence[Callable], *, optimizer: Callable | None = None, trainer: dict | None = None,
                  seed: int = 0, device: str = "cpu", config: dict | None = None) -> Path:
    """The checkpoint of `train_prior` into `run_dir` (the collection built here if needed; no progress
    bar or previews unless `trainer` asks), for `load_prior`. A finished run there is reused as it is, an
    unfinished one resumed. Processes that ask for the same `run_dir` together (the jobs of an evaluation
    sweep) train it once: the first holds the lock `<run_dir>.lock` while it trains, the others wait and
    then reuse its checkpoint."""
    trainer = {"progress": False, "image_every": 0, "mesh_every": 0, **(trainer or {})}
    path = Path(run_dir) / "checkpoints" / CHECKPOINT_NAME
    with file_lock(Path(run_dir).with_name(f"{Path(run_dir).name}.lock")):
        if path.is_file() and load_checkpoint(path).get("step", 0) >= trainer.get("steps", 2000):
            return path
        collection.build(progress=False)
        train_prior(collection, model, observations, optimizer=optimizer, trainer=trainer, seed=seed, device=device,
                    run_dir=run_dir, config=config)
    return path
