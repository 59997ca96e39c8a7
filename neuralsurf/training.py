"""The fit loop, readable top to bottom: samples -> batches -> losses -> Adam, with TensorBoard,
atomic checkpoints and exact resume."""

from __future__ import annotations

import math
import os
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from neuralsurf.devices import resolve_device
from neuralsurf.errors import ConfigError, InputError, NeuralsurfError
from neuralsurf.geometry import estimate_normals, orient_normals
from neuralsurf.losses import LossWeights, evaluate_sdf_batch, sdf_losses
from neuralsurf.models.field import NormalizedField
from neuralsurf.sampling import draw_batch, make_sdf_samples
from neuralsurf.structures import Normalization, PointCloud

CHECKPOINT_NAME = "last.pt"


def cosine_schedule(step: int, steps: int, warmup_steps: int, min_ratio: float) -> float:
    """Learning-rate factor: linear warm-up, then cosine decay from 1 to `min_ratio`."""
    if step < warmup_steps:
        return (step + 1) / warmup_steps
    progress = (step - warmup_steps) / max(1, steps - warmup_steps)
    return min_ratio + (1 - min_ratio) * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0)))


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write `state` atomically: a temporary file in the same folder, then a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(path.name + ".tmp")
    torch.save(state, temporary)
    os.replace(temporary, path)


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Read a checkpoint written by `save_checkpoint` (tensors and plain containers only)."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # a truncated or foreign file
        raise NeuralsurfError(f"cannot read checkpoint {path}: {error}; delete it to start afresh") from None


@dataclass
class FitResult:
    """What `fit` returns."""

    model: nn.Module
    """The trained unit-frame model (in eval mode)."""
    normalization: Normalization
    """World <-> unit frame of this fit."""
    field: NormalizedField
    """The model seen from the world frame: pass it to `extract_mesh`."""
    history: dict[str, list[float]] = field(default_factory=dict)
    """Logged values per logging step ("step", "total", each term, "lr", "grad_norm", "steps_per_s")."""
    steps: int = 0
    """Optimisation steps done, counting those before a resume."""
    seconds: float = 0.0
    """Wall time of the optimisation, counting those before a resume."""


def prepare_cloud(cloud: PointCloud, normals: str, normal_k: int) -> PointCloud:
    """Check the input and supply normals: "given" (must be there), "estimate" (when absent:
    PCA + MST orientation), "ignore" (drop them: fit with surface, eikonal and off-surface terms)."""
    if not isinstance(cloud, PointCloud):
        raise InputError(f"fit expects a neuralsurf.PointCloud, got {type(cloud).__name__}")
    if len(cloud) < 3:
        raise InputError(f"fit needs at least 3 points, the cloud has {len(cloud)}")
    if normals == "ignore":
        return cloud.with_normals(None)
    if normals == "given" and cloud.normals is None:
        raise InputError("normals='given' but the cloud has no normals; use normals='estimate' or 'ignore'")
    if normals not in ("given", "estimate"):
        raise ConfigError(f"unknown normals={normals!r}; choose given, estimate or ignore")
    if cloud.normals is not None:
        return cloud.with_normals(torch.nn.functional.normalize(cloud.normals, dim=-1))
    estimated = estimate_normals(cloud.points, normal_k)
    return cloud.with_normals(orient_normals(cloud.points, estimated, normal_k))


def _param_groups(model: nn.Module, lr: float, encoding_lr: float) -> list[dict]:
    """Encoding tables (hash grids) learn at `encoding_lr`, the network at `lr`."""
    encoding = getattr(model, "encoding", None)
    encoding_ids = {id(p) for p in encoding.parameters()} if isinstance(encoding, nn.Module) else set()
    groups = [
        {"params": [p for p in model.parameters() if id(p) not in encoding_ids], "lr": lr},
        {"params": [p for p in model.parameters() if id(p) in encoding_ids], "lr": encoding_lr},
    ]
    return [g for g in groups if g["params"]]


def _grad_norm(model: nn.Module) -> float:
    norms = [p.grad.detach().norm() for p in model.parameters() if p.grad is not None]
    return float(torch.stack(norms).norm()) if norms else 0.0


def fit(
    model: nn.Module,
    cloud: PointCloud,
    *,
    steps: int = 2000,
    batch_size: int = 8192,
    free_fraction: float = 0.25,
    lr: float = 1e-3,
    encoding_lr: float = 1e-2,
    warmup_steps: int = 0,
    min_lr_ratio: float = 0.01,
    loss: LossWeights | None = None,
    sampling: dict[str, Any] | None = None,
    normals: str = "estimate",
    normal_k: int = 30,
    device: str | torch.device = "auto",
    seed: int = 0,
    run_dir: str | Path | None = None,
    resume: bool = True,
    log_every: int = 50,
    image_every: int = 500,
    mesh_every: int = 0,
    checkpoint_every: int = 500,
    config: dict | None = None,
    progress: bool = True,
) -> FitResult:
    """Fit `model` (unit frame, x[..., 3] -> sdf) to `cloud` (world frame) and return a FitResult.

    With `run_dir`, TensorBoard events go there and checkpoints to `run_dir/checkpoints/last.pt`
    every `checkpoint_every` steps (and at the end); with `resume`, an existing checkpoint there is
    loaded and training continues exactly where it stopped. `sampling` holds keyword arguments of
    `make_sdf_samples`; `config` is stored in checkpoints for the record.
    """
    if steps < 1 or batch_size < 1:
        raise ConfigError(f"fit needs steps >= 1 and batch_size >= 1, got steps={steps}, batch_size={batch_size}")
    loss = loss or LossWeights()
    device = resolve_device(device)
    cloud = prepare_cloud(cloud, normals, normal_k)
    normalization = Normalization.from_points(cloud.points)
    sampling = dict(sampling or {})
    samples = make_sdf_samples(normalization.cloud_to_unit(cloud), seed=seed, **sampling).to(device)
    model = model.to(device).train()
    optimizer = torch.optim.Adam(_param_groups(model, lr, encoding_lr), eps=1e-15)
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda s: cosine_schedule(s, steps, warmup_steps, min_lr_ratio)
    )
    generator = torch.Generator().manual_seed(seed)
    history: dict[str, list[float]] = {}
    start_step, seconds_before = 0, 0.0

    run_dir = Path(run_dir) if run_dir is not None else None
    checkpoint_path = run_dir / "checkpoints" / CHECKPOINT_NAME if run_dir else None
    if resume and checkpoint_path is not None and checkpoint_path.exists():
        state = load_checkpoint(checkpoint_path)
        try:
            model.load_state_dict(state["model"])
            optimizer.load_state_dict(state["optimizer"])
        except (RuntimeError, ValueError, KeyError) as error:
            raise NeuralsurfError(
                f"checkpoint {checkpoint_path} does not match this model ({error}); "
                f"use another run directory or resume=False"
            ) from None
        scheduler.load_state_dict(state["scheduler"])
        generator.set_state(state["generator"])
        torch.set_rng_state(state["torch_rng"])
        history = {k: list(v) for k, v in state["history"].items()}
        start_step, seconds_before = int(state["step"]), float(state["seconds"])
        if start_step >= steps:
            warnings.warn(f"{checkpoint_path} already holds {start_step} >= {steps} steps; nothing to train")

    writer = _summary_writer(run_dir)
    box = float(sampling.get("box", 0.55))
    world_field = NormalizedField(model, normalization, margin=box - 0.5)

    def checkpoint(step: int, seconds: float) -> None:
        if checkpoint_path is None:
            return
        save_checkpoint(checkpoint_path, {
            "model": model.state_dict(), "optimizer": optimizer.state_dict(),
            "scheduler": scheduler.state_dict(), "generator": generator.get_state(),
            "torch_rng": torch.get_rng_state(), "history": history, "step": step, "seconds": seconds,
            "normalization": normalization.state_dict(), "config": config or {},
        })

    from tqdm.auto import tqdm

    bar = tqdm(range(start_step, steps), initial=start_step, total=steps, disable=not progress,
               desc="fit", dynamic_ncols=True)
    started, window_start, window_steps = time.perf_counter(), time.perf_counter(), 0
    done = start_step
    for step in bar:
        batch = draw_batch(samples, batch_size, free_fraction, generator)
        terms = sdf_losses(evaluate_sdf_batch(model, batch), batch, loss)
        if not torch.isfinite(terms["total"]):
            checkpoint(step, seconds_before + time.perf_counter() - started)
            raise NeuralsurfError(
                f"loss became {terms['total'].item()} at step {step}; lower lr (now {lr}) or check the input"
            )
        optimizer.zero_grad(set_to_none=True)
        terms["total"].backward()
        optimizer.step()
        scheduler.step()
        window_steps += 1

        done = step + 1
        if done % log_every == 0 or done == steps:
            now = time.perf_counter()
            record = {name: float(value.detach()) for name, value in terms.items()}
            record.update(step=done, lr=optimizer.param_groups[0]["lr"], grad_norm=_grad_norm(model),
                          steps_per_s=window_steps / (now - window_start))
            window_start, window_steps = now, 0
            for name, value in record.items():
                history.setdefault(name, []).append(value)
            bar.set_postfix(loss=f"{record['total']:.2e}")
            if writer is not None:
                for name, value in record.items():
                    if name != "step":
                        writer.add_scalar(f"loss/{name}" if name in terms else f"train/{name}", value, done)
        if writer is not None and image_every and (done % image_every == 0 or done == steps):
            _log_slices(writer, world_field, done)
        if writer is not None and mesh_every and done % mesh_every == 0:
            _log_mesh(writer, world_field, done)
        if done % checkpoint_every == 0 or done == steps:
            checkpoint(done, seconds_before + time.perf_counter() - started)
    bar.close()
    model.eval()
    if writer is not None:
        _log_mesh(writer, world_field, steps)
        writer.close()
    return FitResult(model, normalization, world_field.eval(), history, max(done, start_step),
                     seconds_before + time.perf_counter() - started)


def _summary_writer(run_dir: Path | None):
    if run_dir is None:
        return None
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(str(run_dir / "tensorboard"))


def _log_slices(writer, world_field: NormalizedField, step: int) -> None:
    """SDF on the three mid-planes of the box, as images."""
    from neuralsurf.extract import field_slice, slice_image

    was_training = world_field.model.training
    world_field.model.eval()
    for axis in "xyz":
        values = field_slice(world_field, world_field.bounds, axis=axis, position=0.5, resolution=192)
        writer.add_image(f"sdf_slice/{axis}", slice_image(values), step, dataformats="HWC")
    world_field.model.train(was_training)


def _log_mesh(writer, world_field: NormalizedField, step: int, resolution: int = 128) -> None:
    """A coarse mesh of the current field for TensorBoard's mesh plugin (skipped if empty)."""
    from neuralsurf.errors import ExtractionError
    from neuralsurf.extract import extract_mesh

    was_training = world_field.model.training
    world_field.model.eval()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mesh = extract_mesh(world_field, resolution=resolution)
        writer.add_mesh("mesh", vertices=mesh.vertices.float()[None], faces=mesh.faces.int()[None], global_step=step)
    except ExtractionError:
        pass  # no surface yet: nothing to show
    finally:
        world_field.model.train(was_training)

