"""Reconstruction methods of the benchmark: method(scene, *, seed, run_dir, **parameters) -> Mesh.

A method that does not apply to a scene raises `NotApplicable` (its row is "skipped"); any other
exception makes the row "failed". Every method also accepts `config` (its own plain config, kept for
provenance, e.g. in the neural checkpoints).
"""

from __future__ import annotations

import hashlib
import json
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from neuralsurf.baselines import FusionSettings, TSDFVolume, reconstruct_poisson
from neuralsurf.checkpoints import load_field
from neuralsurf.devices import resolve_device
from neuralsurf.errors import NeuralsurfError
from neuralsurf.observations import NotObserved
from neuralsurf.priors import (
    Refinement,
    complete_cloud,
    complete_view,
    extract_unit,
    load_prior,
    trained_prior,
)
from neuralsurf.scenes import Scene, extract_scene_mesh
from neuralsurf.structures import Mesh
from neuralsurf.training import default_optimizer, fit


class NotApplicable(NeuralsurfError):
    """This method does not take this scene's kind of input; the row is skipped with the reason."""


def scene_input(scene: Scene) -> str:
    """What a scene without depth frames offers, for the reason of a skipped row."""
    if scene.photometric:
        return (f"{scene.name} is a photometric capture (images under known lights)"
                f"{' with a point cloud' if scene.cloud is not None and not scene.cloud_from_truth else ''}")
    return f"{scene.name} is a point cloud"


def fit_and_extract(scene: Scene, model: nn.Module | None = None,
                    observations: Sequence[Callable] | Mapping[str, Callable | None] | None = None, *,
                    first_applicable: bool = False, optimizer: Callable | None = None,
                    trainer: dict[str, Any] | None = None, extract: dict[str, Any] | None = None,
                    device: str = "auto", checkpoint: str | None = None, save_checkpoint: bool = True, seed: int = 0,
                    run_dir: str | Path | None = None, config: dict | None = None) -> Mesh:
    """Fit a neural SDF to the scene with `neuralsurf.fit` (as train.py does) and extract it; or, with
    `checkpoint`, score an existing fit (`load_field`).

    `observations`: builders of the scene's Observations (`Observation.from_scene` partials: a
    method config's `observations` group, name -> builder, None entries left out), fitted together
    (a scene lacking one is NotApplicable); with `first_applicable`, only the first one the scene has
    (depth rays for a depth capture, else its point cloud)."""
    if checkpoint is not None:
        return extract_scene_mesh(load_field(checkpoint, device=device), scene, extract, seed)
    builders = [b for b in (observations.values() if isinstance(observations, Mapping) else observations or [])
                if b is not None]
    if model is None or not builders:
        raise NeuralsurfError("fit_and_extract needs a model and at least one observation (configs), or a checkpoint")
    fitted = []
    for build in builders:
        try:
            fitted.append(build(scene))
        except NotObserved as error:
            if not first_applicable or build is builders[-1]:
                raise NotApplicable(str(error)) from None
            continue
        if first_applicable:
            break
    trainer = {**(trainer or {}), "resume": False}
    fit_dir = Path(run_dir) if (run_dir is not None and save_checkpoint) else None
    result = fit(model, fitted, optimizer=optimizer or default_optimizer, device=device, seed=seed,
                 run_dir=fit_dir, config=config or {}, **trainer)
    return extract_scene_mesh(result.field, scene, extract, seed)


def poisson(scene: Scene, *, depth: int = 9, density_trim: float | None = None, scale: float = 1.1,
            normal_k: int = 30, n_threads: int = 1, seed: int = 0, run_dir=None, config=None) -> Mesh:
    """Screened Poisson (Open3D) on the scene's cloud; normals estimated where the scene has none."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*estimat.*")
        return reconstruct_poisson(scene.cloud, depth=depth, density_trim=density_trim, scale=scale,
                                   normal_k=normal_k, n_threads=n_threads)


def input_box(scene: Scene, margin_fraction: float) -> tuple[Tensor, float]:
    """The box of the scene's input points enlarged by `margin_fraction` of its longest side on each side,
    Float64[Tensor, "2 3"], and that longest side (the ground truth is not used)."""
    points = scene.cloud.points.double().cpu()
    lo, hi = points.min(0).values, points.max(0).values
    size = float((hi - lo).max())
    return torch.stack([lo - margin_fraction * size, hi + margin_fraction * size]), size


def tsdf(scene: Scene, *, voxel_fraction: float = 1 / 256, truncation_voxels: float = 4.0,
         margin_fraction: float = 0.05, room_voxel: float | None = 0.01, device: str = "auto",
         weighting: str = "constant", seed: int = 0, run_dir=None, config=None) -> Mesh:
    """TSDF fusion of the scene's depth frames, truncation `truncation_voxels` voxels; the voxel is
    `voxel_fraction` of the longest side of the box of the back-projected input (enlarged by
    `margin_fraction`; the ground truth is not used), or `room_voxel` metres for a room (a scene with a
    `near_distance`; sparse blocks, as the room fit and Open3D's VoxelBlockGrid fuse it; None: the fraction)."""
    if scene.frames is None:
        raise NotApplicable(f"TSDF fusion needs depth frames; {scene_input(scene)}")
    bounds, size = input_box(scene, margin_fraction)
    room = scene.near_distance is not None and room_voxel is not None
    voxel = room_voxel if room else voxel_fraction * size
    volume = TSDFVolume(bounds, voxel, truncation_voxels * voxel, sparse=room, device=device,
                        fusion=FusionSettings(weighting=weighting))
    return volume.integrate(scene.frames).extract_mesh()


NOT_TRAINED_ON = ("n_test", "workers", "root")
"""Collection settings that do not change a prior's training shapes or samples: the test split's size, the build's
parallelism and where the caches lie (their folder is named by the samples' settings)."""


def prior_settings(config: dict) -> dict:
    """What a trained prior depends on, from a learned-prior method's config: its collection (less
    `NOT_TRAINED_ON`), model, observation, optimizer and trainer. Its hash names the prior's run."""
    settings = {k: config.get(k) for k in ("collection", "model", "observation", "optimizer", "trainer")}
    if isinstance(settings["collection"], dict):
        settings["collection"] = {k: v for k, v in settings["collection"].items() if k not in NOT_TRAINED_ON}
    return settings


def learned_prior(scene: Scene, *, checkpoint: str | None = None, collection=None, model: Callable | None = None,
                  observation: dict[str, Callable] | None = None, optimizer: Callable | None = None,
                  trainer: dict[str, Any] | None = None, latent_steps: int = 200, resolution: int = 128,
                  refine: dict[str, Any] | None = None, refine_cloud: bool = False, device: str = "auto",
                  seed: int = 0, run_dir: str | Path | None = None, config: dict | None = None) -> Mesh:
    """Complete a shape with a learned prior (DeepSDF auto-decoder or Occupancy Network): from its one
    depth view (`scene.frames`, depth scenes) or its cloud. The scene must be in the prior's unit
    frame and canonical pose (the test shapes of `suite=priors`). With `refine` (`priors.Refinement`
    settings; {} for its defaults), a view's completion is held to what the view saw, and a cloud's to
    its points where `refine_cloud`.

    The prior is `checkpoint` (a train.py experiment=shapes_* run's last.pt), or else trained once per
    evaluation (`model(n_shapes)` over `collection` with the `observation` builders, `optimizer`,
    `trainer`) into `<run_dir>/../prior_<hash of those settings>` and reused by every later call."""
    device = str(resolve_device(device))
    if checkpoint is None:
        if None in (collection, model, observation, trainer, run_dir):
            raise NeuralsurfError("learned_prior needs a checkpoint, or collection, model, observation and "
                                  "trainer settings (configs/method/deepsdf.yaml) to train one")
        settings = prior_settings(config or {})
        digest = hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()[:10]
        checkpoint = trained_prior(Path(run_dir).parent / f"prior_{digest}", collection, model,
                                   list(observation.values()), optimizer=optimizer, trainer=trainer, seed=seed,
                                   device=device, config=settings)
    prior = load_prior(checkpoint, device=device)
    options = {"latent_steps": latent_steps, "seed": seed, "device": device}
    refinement = None if refine is None else Refinement(**refine)
    if scene.frames is not None and scene.depth_input:
        field = complete_view(prior, scene.frames, scene.cloud.points, refine=refinement, **options)
    else:
        field = complete_cloud(prior, scene.cloud.points, refine=refinement if refine_cloud else None, **options)
    return extract_unit(field, resolution)
