"""How a TSDFVolume fuses frames: the fusion rule and its execution, one record (`FusionSettings`).

The volume's constructor takes the grid (bounds, voxel size, truncation, blocks, storage); everything that
decides how a frame updates the grid, and how that work is run, is here.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

import numpy as np

from neuralsurf.errors import ConfigError

WEIGHTINGS = ("constant", "depth")
"""Per-observation weights: "constant" = 1; "depth" = inverse variance of the Kinect v1 axial noise
model (Nguyen et al. 2012), (sigma(0.4 m) / sigma(z))^2, which is 1 at 0.4 m and 0.2 at 1.5 m."""


def positive(value, name: str, what: str) -> float:
    """`value` as a float, or ConfigError unless it is a positive finite number."""
    if not (isinstance(value, numbers.Real) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{name} must be positive and finite ({what}), got {value!r}")
    return float(value)


@dataclass(frozen=True)
class FusionSettings:
    """The fusion rule and its execution (checked when made; ConfigError naming the bad field).

    The rule (what a frame does to the grid; stored with a saved volume):
        weighting: "constant" or "depth" (see WEIGHTINGS).
        max_weight: cap of the accumulated weight (a running average over the last ~max_weight
            observations, as in KinectFusion); None = no cap (the plain average of all frames).
        free_space: metres (>= 0) by which the band's blocks reach further towards the camera than
            the truncation; there every voxel in front of the surface is observed (at +truncation).
            Default 0: the band only, as Open3D's VoxelBlockGrid. Larger values carve more free
            space (floating outliers, holes seen from afar), at a cost in speed and memory.
    The execution (how the work is run; the result does not depend on it):
        frames_per_pass: frames fused together in one vectorised pass over the union of their
            candidate blocks (the result is the same as one at a time, in order); None: 1 on a
            CPU and 32 on a GPU, where per-pass costs dominate.
        threads: CPU threads of `integrate` and `extract_mesh`. Eager fusion: worker threads that fuse
            shares of the blocks side by side, each torch op on one thread (torch's setting restored
            afterwards); "auto" or None: as many as torch's threads, at most four. Compiled fusion:
            torch's threads ("auto" or None: torch's setting; compiled loops keep the thread count of
            the process's first compiled fusion). Extraction: worker threads that mesh groups of blocks
            side by side; "auto" or None: as many as torch's threads.
        compiled: on a CPU, compile the fusion with torch.compile (needs a C++ compiler, else a warning
            and eager fusion); None: for `integrate` calls long enough for compilation to pay for
            itself (see `neuralsurf.baselines.tsdf.volume`). No effect on a GPU.
    """

    weighting: str = "constant"
    max_weight: float | None = None
    free_space: float = 0.0
    frames_per_pass: int | None = None
    threads: int | str | None = "auto"
    compiled: bool | None = None

    def __post_init__(self) -> None:
        if self.weighting not in WEIGHTINGS:
            raise ConfigError(f"weighting must be one of {WEIGHTINGS}, got {self.weighting!r}")
        if self.max_weight is not None:
            object.__setattr__(self, "max_weight", positive(self.max_weight, "max_weight", "a weight, or None for no cap"))
        free_space = self.free_space
        if not (isinstance(free_space, numbers.Real) and math.isfinite(free_space) and free_space >= 0):
            raise ConfigError(f"free_space must be a length >= 0 in metres (0: the band only), got {free_space!r}")
        object.__setattr__(self, "free_space", float(free_space))
        per_pass = self.frames_per_pass
        if per_pass is not None:
            if not (isinstance(per_pass, (int, np.integer)) and per_pass >= 1):
                raise ConfigError(f"frames_per_pass must be an integer >= 1, or None for the device's default; "
                                  f"got {per_pass!r}")
            object.__setattr__(self, "frames_per_pass", int(per_pass))
        threads = self.threads
        if not (threads in (None, "auto") or (isinstance(threads, (int, np.integer)) and threads >= 1)):
            raise ConfigError(
                f"threads must be an integer >= 1, 'auto', or None to keep torch's setting; got {threads!r}"
            )
        object.__setattr__(self, "threads", threads if threads in (None, "auto") else int(threads))
        if self.compiled not in (None, True, False):
            raise ConfigError(f"compiled must be True, False or None (compile long integrations), got {self.compiled!r}")

    def rule(self) -> dict:
        """The fusion rule's fields (what a saved volume stores)."""
        return {"weighting": self.weighting, "max_weight": self.max_weight, "free_space": self.free_space}


__all__ = ["WEIGHTINGS", "FusionSettings", "positive"]
