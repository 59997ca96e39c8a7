"""The fit's training step replayed as one CUDA graph.

On a GPU a small field's step is bound by kernel launches, not arithmetic: the bunny's hash-grid
step issues about 300 kernels (forward, the eikonal term's double backward, Adam) worth 1 ms of GPU
work behind 10 to 15 ms of Python and launches. A CUDA graph records the step once and replays it
with one launch. The batches are copied into the graph's static tensors each step; the learning
rates live in tensors that the scheduler's values are copied into. A step that cannot be recorded
(a batch of another shape, a sampler whose batch is not a flat dataclass of tensors, an operation
that waits for the CPU) runs eagerly instead, with the same result.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable

import torch
from torch import Tensor

WARMUP_STEPS = 3  # eager steps on a side stream before recording, as torch.cuda.graphs asks


def graphable(optimizer: torch.optim.Optimizer, device: torch.device, world: int) -> bool:
    """Whether the step can be recorded: one process on a CUDA device, an optimiser that can update
    its state inside a graph (Adam, AdamW: `capturable`)."""
    return device.type == "cuda" and world == 1 and "capturable" in optimizer.defaults


def batch_fields(batch) -> list | None:
    """The fields of a batch dataclass if each is a tensor, None or a plain value; else None."""
    if not dataclasses.is_dataclass(batch):
        return None
    values = [getattr(batch, f.name) for f in dataclasses.fields(batch)]
    plain = (Tensor, type(None), int, float, bool, str)
    return values if all(isinstance(v, plain) for v in values) else None


class GraphedStep:
    """`step(batches) -> (terms, total)` (forward, backward and optimiser step of `step`), recorded as a
    CUDA graph after WARMUP_STEPS eager calls and replayed from then on. Call `set_learning_rates`
    after each scheduler step. The finiteness of the loss is the caller's to check (a replayed step
    has already been applied)."""

    def __init__(self, step: Callable, optimizer: torch.optim.Optimizer, device: torch.device) -> None:
        self.step, self.optimizer = step, optimizer
        for group in optimizer.param_groups:
            group["capturable"] = True
        for state in optimizer.state.values():  # a resumed optimiser's step counts live on the CPU
            if isinstance(state.get("step"), Tensor):
                state["step"] = state["step"].to(device, torch.float32)
        self.learning_rates = [torch.tensor(float(g["lr"]), device=device) for g in optimizer.param_groups]
        self.stream = torch.cuda.Stream(device)
        self.graph: torch.cuda.CUDAGraph | None = None
        self.static: list | None = None
        self.outputs = None
        self.calls = 0
        self.enabled = True

    def set_learning_rates(self) -> None:
        for rate, group in zip(self.learning_rates, self.optimizer.param_groups):
            rate.fill_(float(group["lr"]))

    def __call__(self, batches: list):
        fields = [batch_fields(b) for b in batches]
        if not self.enabled or any(f is None for f in fields):
            return self._eager(batches)
        flat = [v for f in fields for v in f]
        if self.graph is None:
            self.calls += 1
            if self.calls <= WARMUP_STEPS:
                return self._eager(batches, side_stream=True)
            return self._record(batches, flat)
        if not self._fits(flat):
            self._disable("a batch changed shape")
            return self._eager(batches)
        for static, value in zip(self.static, flat):
            if isinstance(value, Tensor):
                static.copy_(value)
        self.graph.replay()
        return self.outputs

    def _fits(self, flat: list) -> bool:
        return len(flat) == len(self.static) and all(
            (s.shape == v.shape and s.dtype == v.dtype) if isinstance(v, Tensor) else s == v
            for s, v in zip(self.static, flat)
        )

    def _eager(self, batches: list, side_stream: bool = False):
        if not side_stream:
            return self.step(batches)
        self.stream.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(self.stream):
            outputs = self.step(batches)
        torch.cuda.current_stream().wait_stream(self.stream)
        return outputs

    def _record(self, batches: list, flat: list):
        self.static = [v.clone() if isinstance(v, Tensor) else v for v in flat]
        values = iter(self.static)
        static_batches = [dataclasses.replace(b, **{f.name: next(values) for f in dataclasses.fields(b)})
                          for b in batches]
        floats = [group["lr"] for group in self.optimizer.param_groups]
        for rate, group in zip(self.learning_rates, self.optimizer.param_groups):
            group["lr"] = rate  # recorded as a tensor, so later values reach the replays
        self.optimizer.zero_grad(set_to_none=True)  # the gradients become the graph's own buffers
        graph, failure = torch.cuda.CUDAGraph(), None
        try:
            with torch.cuda.graph(graph):
                self.outputs = self.step(static_batches)
        except RuntimeError as error:  # an operation that synchronises or is not allowed in a graph
            failure = str(error).splitlines()[0]
        for value, group in zip(floats, self.optimizer.param_groups):
            group["lr"] = value
        if failure is not None:
            self._disable(f"recording failed ({failure})")
            return self._eager(batches)
        self.graph = graph
        self.graph.replay()
        return self.outputs

    def _disable(self, why: str) -> None:
        warnings.warn(f"the fit's step runs without a CUDA graph: {why}", stacklevel=3)
        self.enabled, self.graph, self.static, self.outputs = False, None, None, None
        self.optimizer.zero_grad(set_to_none=True)
