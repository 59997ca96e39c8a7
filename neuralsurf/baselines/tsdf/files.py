"""TSDFVolume to and from .npz files (`TSDFVolume.save`, `TSDFVolume.load`): plain arrays, no pickle."""

from __future__ import annotations

import math
import zipfile
from pathlib import Path

import numpy as np
import torch

from neuralsurf.baselines.tsdf.settings import FusionSettings
from neuralsurf.errors import ConfigError, FileFormatError
from neuralsurf.io.npz import write_npz

TSDF_FORMAT = "neuralsurf.TSDFVolume/1"
"""Tag of the .npz files written by `TSDFVolume.save` (bumped when their layout changes)."""


def save_volume(volume, path) -> Path:
    """`TSDFVolume.save`: write `volume` to `path`; returns the Path written."""
    path = Path(path)
    if path.is_dir():
        raise FileFormatError(f"cannot save the TSDF volume to {str(path)!r}: it is a folder; pass a file name")
    used = volume._used
    arrays = {
        "format": np.array(TSDF_FORMAT),
        "bounds": volume.bounds.cpu().numpy().astype(np.float64),
        "voxel_size": np.float64(volume.voxel_size),
        "truncation": np.float64(volume.truncation),
        "free_space": np.float64(volume.fusion.free_space),
        "weighting": np.array(volume.fusion.weighting),
        "max_weight": np.float64(np.nan if volume.fusion.max_weight is None else volume.fusion.max_weight),
        "sparse": np.bool_(volume.sparse),
        "block_size": np.int64(volume.block_size),
        "with_color": np.bool_(volume.with_color),
        "frames_integrated": np.int64(volume.frames_integrated),
        "tsdf": volume._tsdf[:used].cpu().numpy(),
        "weight": volume._weight[:used].cpu().numpy(),
    }
    if volume._color is not None:
        arrays["color"] = volume._color[:used].cpu().numpy()
    if volume.sparse:
        arrays["keys"], arrays["slots"] = volume._keys.cpu().numpy(), volume._slots.cpu().numpy()
    write_npz(path, arrays, compressed=True)
    return path


def load_volume(cls, path, device="auto", fusion: FusionSettings | None = None):
    """`TSDFVolume.load`: the volume of class `cls` in the file at `path`, on `device`, fusing further frames
    with the file's fusion rule and `fusion`'s execution (default: `FusionSettings`'s)."""
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"TSDF volume file not found: {str(path)!r}; check the path (written by TSDFVolume.save)")
    try:
        data = np.load(path, allow_pickle=False)
        if not hasattr(data, "files"):  # a single .npy array, not an .npz archive
            raise ValueError("it holds one array, not an .npz archive")
        with data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:  # pickled data is a ValueError
        raise FileFormatError(
            f"cannot read the TSDF volume {str(path)!r}: {type(error).__name__}: {error}; it is truncated or "
            f"not a file written by TSDFVolume.save"
        ) from error
    required = {"format", "bounds", "voxel_size", "truncation", "free_space", "weighting", "max_weight",
                "sparse", "block_size", "with_color", "frames_integrated", "tsdf", "weight"}
    missing = sorted(required - arrays.keys())
    if missing or str(arrays["format"]) != TSDF_FORMAT:
        found = str(arrays.get("format", "(none)"))
        raise FileFormatError(
            f"{str(path)!r} is not a TSDF volume written by TSDFVolume.save (format {found!r}, expected "
            f"{TSDF_FORMAT!r}; missing {missing})"
        )
    max_weight = float(arrays["max_weight"])
    rule = {"weighting": str(arrays["weighting"]), "max_weight": None if math.isnan(max_weight) else max_weight,
            "free_space": float(arrays["free_space"])}
    if fusion is None:
        fusion = FusionSettings(**rule)
    elif fusion.rule() != FusionSettings(**rule).rule():
        raise ConfigError(f"{str(path)!r} was fused with {FusionSettings(**rule).rule()}, but fusion= asks for "
                          f"{fusion.rule()}: a volume keeps its fusion rule; give fusion= the file's rule (or leave "
                          f"it out), or fuse a new volume")
    volume = cls(
        arrays["bounds"], float(arrays["voxel_size"]), float(arrays["truncation"]), device=device,
        sparse=bool(arrays["sparse"]), block_size=int(arrays["block_size"]),
        with_color=bool(arrays["with_color"]), fusion=fusion,
    )
    voxels = volume.block_size**3
    used = len(arrays["tsdf"])
    expected = {"tsdf": (used, voxels), "weight": (used, voxels)}
    if volume.with_color:
        expected["color"] = (used, voxels, 3)
    if volume.sparse:
        expected["keys"] = expected["slots"] = (used,)
    else:
        expected["tsdf"] = expected["weight"] = (volume._used, voxels)
        if volume.with_color:
            expected["color"] = (volume._used, voxels, 3)
    for key, shape in expected.items():
        if key not in arrays or arrays[key].shape != shape:
            raise FileFormatError(
                f"{str(path)!r}: {key} has shape {None if key not in arrays else arrays[key].shape}, expected "
                f"{shape} for its settings; the file is damaged"
            )
    to = lambda key, dtype: torch.from_numpy(np.ascontiguousarray(arrays[key])).to(volume.device, dtype)

    def rows(key: str) -> torch.Tensor:  # the stored blocks, then a row of zeros (where absent blocks read)
        stored = to(key, torch.float32)
        return torch.cat([stored, stored.new_zeros((1,) + stored.shape[1:])])

    volume._tsdf, volume._weight = rows("tsdf"), rows("weight")
    volume._color = rows("color") if volume.with_color else None
    volume._used = used
    if volume.sparse:
        volume._keys, volume._slots = to("keys", torch.int64), to("slots", torch.int64)
    volume.frames_integrated = int(arrays["frames_integrated"])
    return volume


__all__ = ["TSDF_FORMAT", "load_volume", "save_volume"]
