"""An MLP that refines a closed-form start: f(x) = start(x) + voxel * mlp(x).

The start is a `VoxelSDF` solved from the data before the fit (`observations.start.voxel_start` for oriented
points) and frozen; `fit` hands it over (`set_start`), which zeroes the MLP's output layer, so the fit begins at
the start and the network only learns what the start misses, in units of the start's voxel (so that the
optimiser's first steps move the surface by a fraction of a voxel, not of the box). Without a start (depth rays and the other
observations that offer none) the model is its `SDFMLP` alone, geometric initialisation included.

A state dict holds a start that is a whole grid compactly and without loss (`compact_grid`): its values at every
`STRIDE`-th grid point and those that differ from their trilinear upsampling (near the points), about 5 % of a
256-cell start.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from neuralsurf.errors import ConfigError
from neuralsurf.models.grid import VoxelSDF
from neuralsurf.models.sdf_mlp import SDFMLP
from neuralsurf.models.spec import rebuildable

STRIDE = 8
"""Grid points between the values a state dict keeps of the start everywhere (`compact_grid`)."""


def _upsampled(coarse: Tensor, shape: list[int]) -> Tensor:
    """Float[Tensor, "x y z"] -> Float[Tensor, "*shape"]: trilinear, the corners kept (CPU, float32: the same bits on
    save and load)."""
    return nn.functional.interpolate(coarse.float().cpu()[None, None], size=tuple(shape), mode="trilinear",
                                     align_corners=True)[0, 0]


def compact_grid(values: Tensor, stride: int = STRIDE) -> tuple[Tensor, Tensor, Tensor]:
    """Float[Tensor, "X Y Z"] grid values (each side 1 more than a multiple of `stride`) -> (their every `stride`-th
    point Float[Tensor, "x y z"], Int32[Tensor, "k"] linear indices where the upsampling of those differs, the values
    there Float[Tensor, "k"]): `expand_grid` gives `values` back bit for bit."""
    values = values.float().cpu()
    coarse = values[::stride, ::stride, ::stride].clone()
    index = (_upsampled(coarse, list(values.shape)) != values).reshape(-1).nonzero()[:, 0]
    return coarse, index.int(), values.reshape(-1)[index]


def expand_grid(coarse: Tensor, index: Tensor, exceptions: Tensor, shape: list[int]) -> Tensor:
    """`compact_grid`'s output -> the Float[Tensor, "*shape"] grid values."""
    values = _upsampled(coarse, shape)
    values.view(-1)[index.long()] = exceptions.float().cpu()
    return values


def _whole_grid(shape: list[int], rows: Tensor) -> bool:
    """Whether a VoxelSDF of `shape` with `rows` holds every grid point in order and can be compacted."""
    return (all((side - 1) % STRIDE == 0 for side in shape)
            and torch.equal(rows.reshape(-1).cpu(), torch.arange(rows.numel(), dtype=rows.dtype)))


def _compact_start(module: RefinedSDF, state: dict, prefix: str, local_metadata: dict) -> None:
    """state_dict post-hook: the start's values and rows as `compact_grid`'s three tensors."""
    key = prefix + "start."
    if module.start is None or key + "rows" not in state or not _whole_grid(module.start.shape, state[key + "rows"]):
        return
    values = state.pop(key + "values")[:, 0].reshape(module.start.shape)
    del state[key + "rows"]
    state[key + "coarse"], state[key + "exceptions"], state[key + "exception_values"] = compact_grid(values)


def _expand_start(module: RefinedSDF, state: dict, prefix: str, *_) -> None:
    """load_state_dict pre-hook: `_compact_start` undone."""
    key = prefix + "start."
    if module.start is None or key + "coarse" not in state:
        return
    shape = module.start.shape
    values = expand_grid(state.pop(key + "coarse"), state.pop(key + "exceptions"), state.pop(key + "exception_values"),
                         shape)
    state[key + "values"] = values.reshape(-1, 1)
    state[key + "rows"] = torch.arange(values.numel(), dtype=torch.int32).reshape(shape)


@rebuildable
class RefinedSDF(SDFMLP):
    """Unit-frame x[..., 3] -> start(x) + start.voxel * SDFMLP(x) [...]: `SDFMLP`'s arguments, and

    Args:
        start_resolution: the most cells per side of the start's grid over the fit's box (what `fit` asks the data for).
        start: the frozen start; None until `set_start` (then the MLP alone).
    """

    def __init__(
        self,
        width: int = 64,
        depth: int = 2,
        skip_layers: tuple[int, ...] = (),
        activation: Literal["relu", "softplus", "sine"] = "softplus",
        softplus_beta: float = 100.0,
        sine_omega: float = 30.0,
        weight_norm: bool = False,
        geometric_init: bool = True,
        init_radius: float = 0.3,
        encoding: nn.Module | None = None,
        latent_dim: int = 0,
        start_resolution: int = 256,
        start: VoxelSDF | None = None,
    ):
        super().__init__(width, depth, skip_layers, activation, softplus_beta, sine_omega, weight_norm, geometric_init,
                         init_radius, encoding, latent_dim)
        if not (isinstance(start_resolution, int) and start_resolution >= 8):
            raise ConfigError(f"RefinedSDF needs an integer start_resolution >= 8 (cells per side of its start), "
                              f"got {start_resolution!r}")
        if self.latent_dim:
            raise ConfigError("RefinedSDF refines one shape's start; it takes no latent code (latent_dim=0)")
        self.start_resolution = start_resolution
        self.start = None
        self.register_state_dict_post_hook(_compact_start)
        self.register_load_state_dict_pre_hook(_expand_start)
        if start is not None:  # rebuilt from a checkpoint: its weights follow
            self.set_start(start, zero_output=False)

    def set_start(self, start: VoxelSDF, zero_output: bool = True) -> RefinedSDF:
        """Take `start` (frozen) as the field the MLP refines; with `zero_output` the MLP's output layer is zeroed,
        so the model equals `start` until trained."""
        if not isinstance(start, VoxelSDF):
            raise ConfigError(f"RefinedSDF's start is a VoxelSDF, got {type(start).__name__}")
        self.start = start.requires_grad_(False)
        arguments = self.__dict__.get("constructor_arguments")
        if arguments is not None:  # a checkpoint's spec rebuilds the start too
            arguments["start"] = start
        if zero_output:
            last = self.layers[-1]
            weight = last.parametrizations.weight.original0 if parametrize.is_parametrized(last, "weight") else last.weight
            with torch.no_grad():  # a weight-normed layer: its gain, not its direction (0 / |0|)
                weight.zero_()
                last.bias.zero_()
        return self

    def forward(self, x: Tensor, latent: Tensor | None = None) -> Tensor:
        """x Float[Tensor, "... 3"] unit frame -> Float[Tensor, "..."]."""
        if self.start is None:
            return super().forward(x, latent)
        last = self.layers[-1]
        if not self.training and not (last.weight.any() or last.bias.any()):  # adds nothing: the start alone
            return self.start(x)
        return self.start(x) + self.start.voxel * super().forward(x, latent)
