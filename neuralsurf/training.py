"""The fit loop, readable top to bottom: observations -> batches -> weighted loss terms -> optimiser,
with TensorBoard, atomic checkpoints, exact resume, and the saved field that `load_field` reads."""

from __future__ import annotations

import logging
import math
import random
import time
import warnings
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from neuralsurf.checkpoints import CHECKPOINT_NAME, field_state, load_checkpoint, save_checkpoint
from neuralsurf.devices import resolve_device
from neuralsurf.distributed import mean_over_ranks, rank_and_world
from neuralsurf.errors import CheckpointError, ConfigError, ExtractionError, InputError, NeuralsurfError
from neuralsurf.extract import extract_mesh, field_slice, slice_image
from neuralsurf.graphs import GraphedStep, graphable
from neuralsurf.models.field import NormalizedField
from neuralsurf.models.refined import RefinedSDF
from neuralsurf.observations import Observation, PointSamples, union_bounds
from neuralsurf.structures import Normalization, PointCloud

log = logging.getLogger(__name__)


def seed_everything(seed: int) -> None:
    """Seed Python's, numpy's and torch's global generators with `seed`."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def cosine_schedule(step: int, steps: int, warmup_steps: int, min_ratio: float) -> float:
    """Learning-rate factor: linear warm-up, then cosine decay from 1 to `min_ratio`."""
    if step < warmup_steps:
        return (step + 1) / warmup_steps
    progress = (step - warmup_steps) / max(1, steps - warmup_steps)
    return min_ratio + (1 - min_ratio) * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0)))


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
    """Logged values per logging step ("step", "total", each term as "<observation>/<term>", "lr",
    "grad_norm", "steps_per_s")."""
    steps: int = 0
    """Optimisation steps done, counting those before a resume."""
    seconds: float = 0.0
    """Wall time of the fit (its set-up, a start's solve included), counting that before a resume."""

    def save(self, path: str | Path) -> None:
        """Write the fitted field (model spec and weights, normalisation, margin) atomically; read it
        back with `load_field(path)`."""
        save_checkpoint(Path(path), field_state(self.model, self.normalization, self.field.margin, self.steps))



def default_optimizer(params, lr: float = 1e-3, eps: float = 1e-15) -> torch.optim.Optimizer:
    """Adam with eps 1e-15 (Instant-NGP's), the default of `fit` (configs/optimizer/adam). On a CPU
    it runs fused (one pass over each parameter: 2.2 ms a step on the bunny's 1.4M hash-grid
    entries against 6.4 ms for the foreach form); elsewhere in PyTorch's default form, which a CUDA
    graph records (`neuralsurf.graphs`)."""
    params = list(params)
    tensors = [p for group in params for p in (group["params"] if isinstance(group, dict) else [group])]
    on_cpu = all(p.device.type == "cpu" for p in tensors)
    return torch.optim.Adam(params, lr=lr, eps=eps, fused=True if on_cpu else None)


def parameter_groups(model: nn.Module, trainable: list[nn.Parameter] | None,
                     encoding_lr: float | None) -> list[dict]:
    """The optimised parameters: `trainable` (all of the model's by default), with those of the
    model's `encoding` (hash grids) in a group of their own at `encoding_lr` (None: the common lr)."""
    params = list(model.parameters()) if trainable is None else list(trainable)
    owned = {id(p) for p in model.parameters()}
    foreign = [p for p in params if id(p) not in owned]
    if foreign or not params:
        raise ConfigError("trainable must be a non-empty list of the model's own parameters "
                          f"({len(foreign)} of {len(params)} are not); wrap extra tensors such as latent codes "
                          f"in the model")
    encoding = getattr(model, "encoding", None)
    encoding_ids = {id(p) for p in encoding.parameters()} if isinstance(encoding, nn.Module) else set()
    groups = [{"params": [p for p in params if id(p) not in encoding_ids]},
              {"params": [p for p in params if id(p) in encoding_ids]}]
    if encoding_lr is not None:
        groups[1]["lr"] = encoding_lr
    return [g for g in groups if g["params"]]


class LossTerms(nn.Module):
    """The named, unweighted loss terms of `model` on one batch of each observation: the forward that
    DistributedDataParallel wraps under torchrun (the fit's only call into the model)."""

    def __init__(self, model: nn.Module, observations: list[Observation], samplers: list) -> None:
        super().__init__()
        self.model = model
        self.names = [o.name for o in observations]
        self.samplers = samplers

    def forward(self, batches: list) -> dict[str, torch.Tensor]:
        return {f"{name}/{term}": value for name, sampler, batch in zip(self.names, self.samplers, batches)
                for term, value in sampler.losses(self.model, batch).items()}


def _grad_norm(params: list[nn.Parameter]) -> float:
    norms = [p.grad.detach().norm() for p in params if p.grad is not None]
    return float(torch.stack(norms).norm()) if norms else 0.0


def _as_observations(observations) -> list[Observation]:
    if isinstance(observations, PointCloud):
        return [PointSamples(observations)]
    observations = [observations] if isinstance(observations, Observation) else list(observations)
    bad = [type(o).__name__ for o in observations if not isinstance(o, Observation)]
    if bad or not observations:
        raise InputError(f"fit takes observations (PointSamples, DepthRays, ...) or a PointCloud, got "
                         f"{bad or 'nothing'}; wrap data as e.g. neuralsurf.observations.DepthRays(frames)")
    names = [o.name for o in observations]
    if len(set(names)) < len(names):
        raise ConfigError(f"observations need distinct names (they prefix the loss terms), got {names}")
    return observations


class FitDiverged(NeuralsurfError):
    """The fit's loss became NaN or inf: lower the learning rate or check the input for outliers."""

    def __init__(self, terms: dict[str, torch.Tensor], total: torch.Tensor, step: int) -> None:
        bad = [name for name, value in terms.items() if not torch.isfinite(value)]
        super().__init__(f"the fit diverged: loss became {total.item()} at step {step} (terms {bad}); lower the "
                         f"learning rate (optimizer.lr, trainer.encoding_lr) or check the input for outliers")


class Checkpoints:
    """A fit's training state in `run_dir/checkpoints/last.pt` (nothing without `run_dir`).

    `save` writes the field (`field_state`: what `load_field` reads) with the optimiser, the scheduler, the
    sampling generator, torch's global RNG, the held-out stop's reads (`stopper`, an `EarlyStop`), the history, the
    wall time and `config`, atomically and only where `writes` (rank 0). `resume` loads all of it back (on every
    rank), so that the fit continues exactly where it stopped, and a fit the held-out points stopped stays stopped."""

    def __init__(self, run_dir: str | Path | None, model: nn.Module, normalization: Normalization, margin: float,
                 optimizer: torch.optim.Optimizer, scheduler: torch.optim.lr_scheduler.LRScheduler,
                 generator: torch.Generator, config: dict | None = None, writes: bool = True,
                 stopper: EarlyStop | None = None) -> None:
        self.path = Path(run_dir) / "checkpoints" / CHECKPOINT_NAME if run_dir is not None else None
        self.model, self.normalization, self.margin = model, normalization, margin
        self.optimizer, self.scheduler, self.generator, self.stopper = optimizer, scheduler, generator, stopper
        self.config, self.writes = config or {}, writes

    def resume(self, steps: int) -> tuple[int, float, dict[str, list[float]]]:
        """(steps done, seconds spent, history) of the saved fit, its state loaded into the model,
        optimiser, scheduler, generator and torch's RNG; (0, 0.0, {}) when there is no checkpoint.
        Warns when it already holds `steps` steps or more."""
        if self.path is None or not self.path.exists():
            return 0, 0.0, {}
        state = load_checkpoint(self.path)
        try:
            self.model.load_state_dict(state["model"])
            self.optimizer.load_state_dict(state["optimizer"])
        except (RuntimeError, ValueError, KeyError) as error:
            raise CheckpointError(f"checkpoint {self.path} does not match this model ({error}); "
                                  f"use another run directory or resume=False") from None
        self.scheduler.load_state_dict(state["scheduler"])
        self.generator.set_state(state["generator"])
        torch.set_rng_state(state["torch_rng"])
        if self.stopper is not None:
            self.stopper.load_state_dict(state.get("early_stop"))
        step = int(state["step"])
        if step >= steps:
            warnings.warn(f"{self.path} already holds {step} >= {steps} steps; nothing to train")
        return step, float(state["seconds"]), {k: list(v) for k, v in state["history"].items()}

    def save(self, step: int, seconds: float, history: dict[str, list[float]]) -> None:
        """Write the state after `step` steps (a no-op without a run directory or where not `writes`)."""
        if self.path is None or not self.writes:
            return
        save_checkpoint(self.path, {
            **field_state(self.model, self.normalization, self.margin, step),
            "optimizer": _portable(self.optimizer.state_dict()), "scheduler": self.scheduler.state_dict(),
            "generator": self.generator.get_state(), "torch_rng": torch.get_rng_state(),
            "early_stop": self.stopper and self.stopper.state_dict(), "history": history, "seconds": seconds,
            "config": self.config,
        })


class TrainStep:
    """One optimisation step of the weighted loss terms: `step(batches, index) -> (terms, total)`
    (forward of `LossTerms`, backward, the optimiser's step).

    Eager, a NaN or inf loss raises FitDiverged before the update, so the model still holds the state
    before step `index`. With `cuda_graph`, on one CUDA device with a capturable optimiser (`graphable`)
    the step is replayed as a CUDA graph (`GraphedStep`: the same steps without the launch cost); its
    update is then applied before the loss is read, so `check` raises FitDiverged when the caller
    reads the loss (logging and checkpoint steps). Under a process group (`world` > 1) the terms run
    inside DistributedDataParallel. Call `scheduled` after each scheduler step."""

    def __init__(self, model: nn.Module, observations: list[Observation], samplers: list,
                 optimizer: torch.optim.Optimizer, device: torch.device, world: int = 1, cuda_graph: bool = True):
        self.optimizer = optimizer
        self.weights = {f"{o.name}/{term}": w for o, s in zip(observations, samplers) for term, w in s.weights.items()}
        self.loss_terms: nn.Module = LossTerms(model, observations, samplers)
        if world > 1:  # after the resume: its broadcast of rank 0's weights also waits for every rank's reading
            self.loss_terms = torch.nn.parallel.DistributedDataParallel(self.loss_terms)
        self.graphed = (GraphedStep(self._forward_and_update, optimizer, device)
                        if cuda_graph and graphable(optimizer, device, world) else None)

    def __call__(self, batches: list, index: int) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        if self.graphed is not None:
            return self.graphed(batches)
        terms, total = self._forward(batches)
        if not torch.isfinite(total):
            raise FitDiverged(terms, total, index)
        self._update(total)
        return terms, total

    def scheduled(self) -> None:
        """After the scheduler's step: its learning rates reach the graph's copies of them."""
        if self.graphed is not None:
            self.graphed.set_learning_rates()

    def check(self, terms: dict[str, torch.Tensor], total: torch.Tensor, index: int) -> None:
        """FitDiverged for a replayed step whose loss is not finite (an eager step raised already)."""
        if self.graphed is not None and not torch.isfinite(total):
            raise FitDiverged(terms, total, index)

    def _forward(self, batches: list) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        terms = self.loss_terms(batches)
        return terms, sum(self.weights[name] * value for name, value in terms.items())

    def _update(self, total: torch.Tensor) -> None:
        self.optimizer.zero_grad(set_to_none=True)
        total.backward()
        self.optimizer.step()

    def _forward_and_update(self, batches: list) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        terms, total = self._forward(batches)
        self._update(total)  # detached below: a kept autograd graph would tie the next step to this one's stream
        return {name: value.detach() for name, value in terms.items()}, total.detach()


class FitMonitor:
    """What a fit shows as it goes: the history of logged values (every `log_every` steps and at the
    end), a progress bar over its steps (`bar`), a line in the log per tenth of the fit, and, with a
    `run_dir`, TensorBoard scalars, SDF slices every `image_every` steps and meshes every `mesh_every`
    steps; and its wall time, counting `seconds_before` (a resumed fit's)."""

    def __init__(self, steps: int, start_step: int, seconds_before: float, history: dict[str, list[float]],
                 params: list[nn.Parameter], optimizer: torch.optim.Optimizer, world_field: NormalizedField,
                 run_dir: str | Path | None, progress: bool, log_every: int, image_every: int, mesh_every: int):
        from tqdm.auto import tqdm

        self.steps, self.seconds_before, self.history = steps, seconds_before, history
        self.params, self.optimizer, self.world_field = params, optimizer, world_field
        self.log_every, self.image_every, self.mesh_every = log_every, image_every, mesh_every
        self.writer = _summary_writer(Path(run_dir)) if run_dir is not None else None
        self.bar = tqdm(range(start_step, steps), initial=start_step, total=steps, disable=not progress,
                        desc="fit", dynamic_ncols=True)
        self.started = self.window_start = time.perf_counter()
        self.window_steps = 0
        self.report_every = max(1, steps // 10)  # a progress line in the log per tenth of the fit, at a logging step
        self.next_report, self.reported, self.report_start = start_step + 1, start_step, self.started

    def seconds(self) -> float:
        """Wall time of the fit so far, counting the time before a resume."""
        return self.seconds_before + time.perf_counter() - self.started

    def after_step(self, done: int, terms: dict[str, torch.Tensor], total: torch.Tensor) -> None:
        """Record and show what is due after `done` steps."""
        self.window_steps += 1
        if done % self.log_every == 0 or done == self.steps:
            self._record(done, terms, total)
        if self.writer is not None and self.image_every and (done % self.image_every == 0 or done == self.steps):
            _log_slices(self.writer, self.world_field, done)
        if self.writer is not None and self.mesh_every and done % self.mesh_every == 0:
            _log_mesh(self.writer, self.world_field, done)

    def finish(self) -> None:
        """A last preview of the field (none for models without one, e.g. OccNet) and the events flushed."""
        if self.writer is not None:
            if self.image_every or self.mesh_every:
                _log_mesh(self.writer, self.world_field, self.steps)
            self.writer.close()

    def _record(self, done: int, terms: dict[str, torch.Tensor], total: torch.Tensor) -> None:
        now = time.perf_counter()
        record = mean_over_ranks({name: float(value.detach()) for name, value in terms.items()}
                                 | {"total": float(total.detach())})
        record.update(step=done, lr=self.optimizer.param_groups[0]["lr"], grad_norm=_grad_norm(self.params),
                      steps_per_s=self.window_steps / (now - self.window_start))
        self.window_start, self.window_steps = now, 0
        for name, value in record.items():
            self.history.setdefault(name, []).append(value)
        self.bar.set_postfix(loss=f"{record['total']:.2e}")
        if done >= self.next_report or done == self.steps:
            log.info(progress_line(record, self.steps, (done - self.reported) / (now - self.report_start)))
            self.next_report = (done // self.report_every + 1) * self.report_every
            self.reported, self.report_start = done, now
        if self.writer is not None:
            for name, value in record.items():
                if name != "step":
                    self.writer.add_scalar(f"loss/{name}" if name in terms or name == "total" else f"train/{name}",
                                           value, done)


@contextmanager
def only_trainable(model: nn.Module, params: list[nn.Parameter]):
    """Within the block, the model's parameters outside `params` do not require gradients (so that
    DistributedDataParallel leaves them alone); restored on leaving it."""
    frozen = [p for p in model.parameters() if p.requires_grad and all(p is not q for q in params)]
    for p in frozen:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in frozen:
            p.requires_grad_(True)


def fit(
    model: nn.Module,
    observations: Observation | PointCloud | Sequence[Observation],
    *,
    steps: int = 2000,
    optimizer: Callable[..., torch.optim.Optimizer] = default_optimizer,
    encoding_lr: float | None = 1e-2,
    trainable: Sequence[nn.Parameter] | None = None,
    warmup_steps: int = 0,
    min_lr_ratio: float = 0.01,
    margin: float = 0.05,
    normalization: Normalization | None = None,
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
    cuda_graph: bool = True,
    patience: int = 0,
    validate_every: int = 10,
) -> FitResult:
    """Fit `model` (unit frame, x[..., 3] -> sdf) to `observations` (world frame) and return a FitResult.

    `observations`: one Observation, several (their weighted terms are summed), or a PointCloud
    (`PointSamples(cloud)`). The unit frame maps the union of their bounds to [-0.5, 0.5]^3 (or is
    `normalization`, e.g. a learned prior's); the fit covers that cube plus `margin` on each side.
    `optimizer(param_groups)` builds the optimiser (default: Adam, lr 1e-3) over `trainable` (all of
    the model's parameters by default; e.g. only a latent code under a frozen decoder), the model's
    `encoding` at `encoding_lr`; the lr follows a warm-up and a cosine decay to `min_lr_ratio`.
    With `run_dir`: TensorBoard events there (`FitMonitor`), checkpoints every `checkpoint_every` steps
    and at the end, and with `resume` an existing one loaded to continue exactly (`Checkpoints`;
    `config` is stored in them). Under torchrun the gradients are averaged over the processes and
    only rank 0 writes. With `cuda_graph`, one GPU replays the step as a CUDA graph (`TrainStep`).
    A `RefinedSDF` without a start gets the first closed-form field an observation offers (`Sampler.start_field`)
    before the first step. With `patience` > 0 and an observation that holds data out (`Sampler.held_out_error`),
    the error there is read every `validate_every` steps (and before the first): the fit stops once it has not
    fallen by 1 % for `patience` reads in a row, and the model goes back to its best read.
    """
    if not (isinstance(steps, int) and not isinstance(steps, bool) and steps >= 1):
        raise ConfigError(f"fit needs an integer steps >= 1, got {steps!r}")
    begun = time.perf_counter()  # the fit's time counts its set-up: sample pools, a start's solve
    observations = _as_observations(observations)
    device = resolve_device(device)
    normalization = normalization or Normalization.from_points(union_bounds(observations))
    samplers = [o.prepare(normalization, 0.5 + margin, device, seed + i) for i, o in enumerate(observations)]
    if isinstance(model, RefinedSDF) and model.start is None:
        start = next((f for f in (s.start_field(model.start_resolution, 0.5 + margin) for s in samplers)
                      if f is not None), None)
        if start is not None:
            model.set_start(start)
    model = model.to(device).train()
    groups = parameter_groups(model, None if trainable is None else list(trainable), encoding_lr)
    params = [p for g in groups for p in g["params"]]
    optimizer = optimizer(groups)
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda s: cosine_schedule(s, steps, warmup_steps, min_lr_ratio))
    generator = torch.Generator().manual_seed(seed)
    rank, world = rank_and_world()
    stopper = EarlyStop(model, samplers, patience, validate_every)
    checkpoints = Checkpoints(run_dir, model, normalization, margin, optimizer, scheduler, generator, config,
                              writes=rank == 0, stopper=stopper)
    start_step, seconds, history = checkpoints.resume(steps) if resume else (0, 0.0, {})
    world_field = NormalizedField(model, normalization, margin=margin)
    seconds += time.perf_counter() - begun
    monitor = FitMonitor(steps, start_step, seconds, history, params, optimizer, world_field,
                         run_dir if rank == 0 else None, progress and rank == 0, log_every, image_every, mesh_every)

    done = start_step
    with only_trainable(model, params):
        train_step = TrainStep(model, observations, samplers, optimizer, device, world, cuda_graph)
        for step in monitor.bar:
            if stopper.stops(step):
                checkpoints.save(step, monitor.seconds(), history)
                break
            batches = [sampler.sample(generator) for sampler in samplers]
            try:
                terms, total = train_step(batches, step)
            except FitDiverged:
                checkpoints.save(step, monitor.seconds(), history)  # the state before the diverged step
                raise
            scheduler.step()
            train_step.scheduled()
            done = step + 1
            saving = done % checkpoint_every == 0 or done == steps
            if saving or done % log_every == 0:
                train_step.check(terms, total, step)  # a replayed step is applied already: not saved
            monitor.after_step(done, terms, total)
            if saving:
                checkpoints.save(done, monitor.seconds(), history)
    monitor.bar.close()
    model.eval()
    _check_converged(history)
    done = max(done, start_step)
    _check_field(model, done)
    monitor.finish()
    return FitResult(model, normalization, world_field.eval(), history, done, monitor.seconds())


class EarlyStop:
    """`fit`'s stop on held-out data: every `every` steps (and at the first) the mean of the samplers'
    `held_out_error`; `stops(step)` is True once it has not fallen by 1 % for `patience` reads in a row, and then
    puts the model back to the state of its best read (and stays True). Off (never stops) with `patience` 0 or no
    held-out data. Its reads so far are `state_dict()`, which a checkpoint keeps."""

    def __init__(self, model: nn.Module, samplers: list, patience: int, every: int) -> None:
        if not (isinstance(patience, int) and patience >= 0 and isinstance(every, int) and every >= 1):
            raise ConfigError(f"fit needs integers patience >= 0 and validate_every >= 1, got {patience!r} and {every!r}")
        self.model, self.samplers, self.patience, self.every = model, samplers, patience, every
        self.best, self.best_state, self.misses, self.stopped = math.inf, None, 0, False
        self.enabled = patience > 0  # until the first read finds no held-out data

    def _error(self) -> float | None:
        errors = [e for e in (s.held_out_error(self.model) for s in self.samplers) if e is not None]
        return sum(errors) / len(errors) if errors else None

    def state_dict(self) -> dict:
        return {"best": self.best, "best_state": self.best_state, "misses": self.misses, "stopped": self.stopped}

    def load_state_dict(self, state: dict | None) -> None:
        """The reads of `state_dict()` (None: a checkpoint written without them, nothing read yet)."""
        if state is not None:
            self.best, self.best_state = float(state["best"]), state["best_state"]
            self.misses, self.stopped = int(state["misses"]), bool(state["stopped"])

    def stops(self, step: int) -> bool:
        if self.stopped:
            return True
        if not self.enabled or step % self.every:
            return False
        error = self._error()
        if error is None:
            self.enabled = False
            return False
        if error < 0.99 * self.best:
            self.best, self.misses = error, 0
            self.best_state = {k: v.detach().clone() for k, v in (*self.model.named_parameters(),
                                                                   *self.model.named_buffers())
                               if not k.startswith("start.")}  # the frozen start never changes
            return False
        self.misses += 1
        if self.misses < self.patience:
            return False
        self.model.load_state_dict(self.best_state, strict=False)
        self.stopped = True
        return True


def progress_line(record: dict[str, float], steps: int, steps_per_s: float) -> str:
    """One line of the run log: "step 70/700 (10%): loss 1.2e-02 (points/sdf 3.4e-03, ...), lr 1.0e-03, 21.5 steps/s"."""
    named = {"step", "total", "lr", "grad_norm", "steps_per_s"}
    terms = ", ".join(f"{name} {value:.3g}" for name, value in record.items() if name not in named)
    step = int(record["step"])
    return (f"step {step}/{steps} ({100 * step / steps:.0f}%): loss {record['total']:.4g} ({terms}), "
            f"lr {record['lr']:.3g}, {steps_per_s:.1f} steps/s")


def _portable(optimizer_state: dict) -> dict:
    """An optimiser's state dict that loads on any device: a CUDA graph's `capturable` switched off."""
    for group in optimizer_state["param_groups"]:
        if "capturable" in group:
            group["capturable"] = False
    return optimizer_state


FIELD_PROBES = 4096
"""Points of the unit box at which `_check_field` reads the fitted model."""


def _check_field(model: nn.Module, steps: int) -> None:
    """Raise the "fit diverged" error when the unit-frame model (x[n, 3] -> values[n]) is NaN, inf or
    constant over the box [-0.5, 0.5]^3 after `steps` steps (a far too high learning rate can leave a
    huge constant field with a finite loss); warn when it has one sign everywhere (no surface). Models
    that need more than points (an occupancy network's code) are not read."""
    points = torch.rand(FIELD_PROBES, 3, generator=torch.Generator().manual_seed(0)) - 0.5
    parameter = next(model.parameters(), None)
    if parameter is None:
        return
    try:
        with torch.no_grad():
            values = model(points.to(parameter.device, parameter.dtype))
    except (TypeError, NeuralsurfError):  # needs a code or other inputs: nothing to read here
        return
    if not isinstance(values, torch.Tensor) or values.numel() != FIELD_PROBES:
        return
    values = values.detach().double().flatten()
    hint = "lower the learning rate (optimizer.lr, trainer.encoding_lr)"
    bad = int((~torch.isfinite(values)).sum())
    if bad:
        raise NeuralsurfError(f"the fit diverged: after {steps} steps the field is NaN or inf at {bad} of "
                              f"{FIELD_PROBES} points of the box; {hint}")
    low, high = float(values.min()), float(values.max())
    if high - low <= 1e-6 * max(1.0, abs(low), abs(high)):
        raise NeuralsurfError(f"the fit diverged: after {steps} steps the field is constant ({low:.4g}) over the "
                              f"box, so it has no surface; {hint}")
    if low > 0 or high < 0:
        warnings.warn(f"after {steps} steps the field has one sign over the whole box (values in [{low:.4g}, "
                      f"{high:.4g}]), so it has no surface: the fit diverged ({hint}) or needs more steps",
                      stacklevel=3)


def _check_converged(history: dict[str, list[float]]) -> None:
    """Warn when the loss ended above where it started (a diverged fit that stayed finite)."""
    total = history.get("total", [])
    if len(total) >= 2 and total[-1] > total[0]:
        warnings.warn(f"the fit's loss rose from {total[0]:.3g} to {total[-1]:.3g}: it probably diverged; "
                      f"lower the learning rate (optimizer.lr, trainer.encoding_lr)", stacklevel=3)


def _summary_writer(run_dir: Path | None):
    if run_dir is None:
        return None
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(str(run_dir / "tensorboard"))


def _log_slices(writer, world_field: NormalizedField, step: int) -> None:
    """SDF on the three mid-planes of the box, as images."""

    was_training = world_field.model.training
    world_field.model.eval()
    for axis in "xyz":
        values = field_slice(world_field, world_field.bounds, axis=axis, position=0.5, resolution=192)
        writer.add_image(f"sdf_slice/{axis}", slice_image(values), step, dataformats="HWC")
    world_field.model.train(was_training)


def _log_mesh(writer, world_field: NormalizedField, step: int, resolution: int = 128, chunk_size: int = 32_768) -> None:
    """A coarse mesh of the current field for TensorBoard's mesh plugin (skipped if empty); `chunk_size`
    points per field call (extract_mesh's larger default made this preview the peak of a bunny run: +0.8 GB)."""

    was_training = world_field.model.training
    world_field.model.eval()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mesh = extract_mesh(world_field, resolution=resolution, chunk_size=chunk_size)
        writer.add_mesh("mesh", vertices=mesh.vertices.float()[None], faces=mesh.faces.int()[None], global_step=step)
    except ExtractionError:
        pass  # no surface yet: nothing to show
    finally:
        world_field.model.train(was_training)

