"""TSDF fusion of depth frames (Curless & Levoy 1996; KinectFusion, Newcombe et al. 2011) in PyTorch.

`TSDFVolume(bounds, voxel_size, ..., fusion=FusionSettings(...))`, then `.integrate(frames)` any number of
times, then `.extract_mesh()`. The constructor takes the grid; `FusionSettings` (`settings.py`) the fusion
rule and its execution. Vectorised over voxels, on any torch device (CPU or CUDA).

The volume
    Grid points ("voxels") sit at `bounds[0] + (i, j, k) * voxel_size` and are stored in blocks of
    `block_size`^3 voxels: `tsdf` and `weight` are (slots, block_size^3) tensors (plus `color`,
    (slots, block_size^3, 3)). Dense mode allocates every block of the box up front (slot = linear
    block index); sparse mode allocates a block the first time a frame's band touches it and finds
    slots through a sorted tensor of block keys (`torch.searchsorted`), so memory follows the observed
    surfaces, not the box. Stored values are signed distances in metres, in [-truncation, truncation].

Integration, a pass of `fusion.frames_per_pass` frames at a time (one on a CPU, 32 on a GPU)
    1. The blocks that the frames' truncation bands touch (`bands.candidate_blocks`), for every
       pass first (allocated in sparse mode): as in Open3D's VoxelBlockGrid, a frame updates the
       voxels of these only.
    2. Their voxels' running weighted averages of the projective signed distance, nearest pixel,
       frame after frame (`voxels.fuse_blocks`), in chunks of _CHUNK_OBSERVATIONS.
    On a CPU, eager: each torch op on one thread (many short ops, whose thread synchronisation costs
    more than it gains on a few cores), the passes' blocks found on `fusion.threads` worker threads side by
    side, then each thread fusing its share of the blocks through all passes. Compiled (`fusion.compiled`, by default for calls of
    _COMPILE_PIXELS depth pixels or more): the band search and the voxel pass as loops compiled by
    torch.compile (`CompiledOnCPU`), for long sequences (20-35 s of compilation once per process).

Extraction
    Marching cubes in PyTorch (`neuralsurf.marching.cube_triangles`) on the blocks that may hold a sign
    change, each read as a cube of its voxels and the next point along each axis
    (`TSDFVolume._block_cubes`), groups of blocks on `fusion.threads` worker threads, cells with an unobserved
    corner skipped; a vertex is named by the grid edge it lies on, so the blocks' meshes join without
    seams (`neuralsurf.marching.merge_edge_vertices`).
"""

from __future__ import annotations

import contextlib
import math
import os
import warnings
from concurrent.futures import Executor, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neuralsurf.baselines.tsdf.bands import TILE, candidate_blocks, candidates_by_pass, tile_box_codes
from neuralsurf.baselines.tsdf.files import load_volume, save_volume
from neuralsurf.baselines.tsdf.settings import FusionSettings, positive
from neuralsurf.baselines.tsdf.voxels import (
    camera_to_grid,
    fuse_blocks,
    grid_to_pixel,
    pad_image,
    pixel_weights,
)
from neuralsurf.cameras import backproject_depth
from neuralsurf.devices import CompiledOnCPU, resolve_device
from neuralsurf.errors import ConfigError, ExtractionError, InputError
from neuralsurf.extract import as_bounds
from neuralsurf.marching import cube_triangles, merge_edge_vertices
from neuralsurf.progress import progress_bar
from neuralsurf.structures import DepthFrames, Mesh, float_colors

_CHUNK_OBSERVATIONS = {"cpu": 1 << 17, "compiled": 1 << 21, "cuda": 1 << 25}
"""Voxel observations (voxels x frames) per vectorised step, at most (temporary memory: ~40 bytes
each eager, cache-sized on a CPU; ~12 compiled, where a step costs ~0.5 ms more; on CUDA also at most
1/400 of the free memory)."""
_FRAMES_PER_PASS = {"cpu": 1, "cuda": 32}
"""Default frames fused per pass: one on a CPU (each frame visits only its own voxels); on a GPU a
batch, so that the fixed cost of a pass (kernel launches, a few host syncs) is shared."""
_FRAMES_PER_SEARCH = 5
"""Frames whose candidate blocks one `candidate_blocks` call finds, at least (a pass at least): on a CPU,
its many small ops on one frame's image tiles hold Python's lock long enough that two threads gain
little side by side (50 7-Scenes frames at 1 cm, 2 threads: 0.17-0.19 s a frame at a time, 0.12 s five
at a time; 0.21 s on one thread)."""
_FUSION_WORKERS = 4
"""Eager fusion's worker threads by default, at most: its many short ops hold Python's lock, so more
threads wait on each other (50 7-Scenes frames at 1 cm, a 16-core Xeon: 35, 26, 17, 24 and 36 ms a frame
on 1, 2, 4, 8 and 16 threads; extraction kept gaining up to 8)."""
_MESH_BLOCKS = 4096
"""Blocks meshed per marching-cubes call (about 25 bytes per voxel: 50 MB for blocks of 8^3)."""
_BYTES_PER_VOXEL = {False: 8, True: 20}
"""tsdf + weight (float32), plus three float32 colour channels."""


@contextlib.contextmanager
def torch_threads(threads: int | None):
    """Run the block with torch on `threads` intra-op threads (None: unchanged), then restore."""
    before = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def available_memory(device: torch.device) -> int:
    """Bytes that can still be allocated on `device` (free GPU memory, or MemAvailable on Linux)."""
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))


def depth_bounds(frames: DepthFrames, margin: float = 0.0) -> Tensor:
    """Float64[Tensor, "2 3"]: world bounding box of every valid depth pixel, grown by `margin`."""

    if not isinstance(frames, DepthFrames):
        raise InputError(f"depth_bounds needs DepthFrames, got {type(frames).__name__}")
    lo = torch.full((3,), math.inf, dtype=torch.float64)
    hi = -lo
    for start in range(0, len(frames), 8):
        part = frames[start : start + 8]
        points = backproject_depth(part)[part.depth > 0].double().cpu()
        if len(points):
            lo, hi = torch.minimum(lo, points.min(0).values), torch.maximum(hi, points.max(0).values)
    if not torch.isfinite(lo).all():
        raise InputError("depth_bounds: the frames have no valid depth pixel (all zeros)")
    return torch.stack([lo - margin, hi + margin])


_COMPILE_PIXELS = 300 * 640 * 480
"""FusionSettings(compiled=None) compiles an `integrate` call on a CPU from this many depth pixels on. Set on
7-Scenes at 1 cm, 2 cores: 19 ms a frame compiled after a compilation of 11 s (from torch's on-disk cache;
20-35 s without) against 56 ms for a one-thread eager path with 2 x 2 band tiles. The eager path with 4 x 4
tiles and worker threads takes about 18 ms of CPU a frame there, so compiling may not pay at all."""


_COMPILED = {function: CompiledOnCPU(function, "TSDF fusion") for function in (tile_box_codes, fuse_blocks)}


class TSDFVolume:
    """A truncated signed distance volume fused from depth frames (see the module docstring).

    Args:
        bounds: (2, 3) world box [[xmin, ymin, zmin], [xmax, ymax, zmax]] to reconstruct; the grid
            starts at its min corner and covers it (rounded up to whole blocks).
        voxel_size: grid spacing in metres (> 0).
        truncation: band half-width in metres (> 0); default 3 voxels. Below one voxel it warns:
            the band then misses grid points and the surface breaks up.
        sparse: allocate blocks where frames observe surfaces only (rooms); dense otherwise.
        block_size: voxels per block side (>= 2).
        with_color: also average the frames' colours (frames must carry `colors`).
        device: "auto" (CUDA if available), "cpu", "cuda", or a torch.device.
        max_memory: bytes the dense volume may take; default 80 % of the device's available memory.
        fusion: the fusion rule (weighting, weight cap, free space) and its execution (frames per pass,
            threads, torch.compile on a CPU): a `FusionSettings`; default `FusionSettings()`.
    """

    def __init__(
        self,
        bounds,
        voxel_size: float,
        truncation: float | None = None,
        *,
        sparse: bool = False,
        block_size: int = 8,
        with_color: bool = False,
        device="auto",
        max_memory: int | None = None,
        fusion: FusionSettings | None = None,
    ):
        box = as_bounds(bounds)
        voxel_size = positive(voxel_size, "voxel_size", "a length in metres")
        truncation = (
            3.0 * voxel_size
            if truncation is None
            else positive(truncation, "truncation", "a length in metres")
        )
        if truncation < voxel_size:
            warnings.warn(
                f"truncation {truncation:g} is smaller than a voxel ({voxel_size:g}): grid points on one side "
                f"of the surface are often not updated and the mesh gets holes; use 2 to 5 voxels",
                stacklevel=2,
            )
        fusion = FusionSettings() if fusion is None else fusion
        if not isinstance(fusion, FusionSettings):
            raise ConfigError(f"fusion must be a FusionSettings (the fusion rule and its execution), got "
                              f"{type(fusion).__name__}; pass fusion=FusionSettings(weighting=..., threads=...)")
        if not (isinstance(block_size, (int, np.integer)) and block_size >= 2):
            raise ConfigError(
                f"block_size must be an integer >= 2 (voxels per block side), got {block_size!r}"
            )
        self.device = resolve_device(device)
        self.bounds = torch.as_tensor(box)
        self.origin = box[0].copy()
        self.voxel_size, self.truncation, self.fusion = voxel_size, truncation, fusion
        self.sparse, self.block_size, self.with_color = bool(sparse), int(block_size), bool(with_color)
        kind = "cuda" if self.device.type == "cuda" else "cpu"
        self.frames_per_pass = _FRAMES_PER_PASS[kind] if fusion.frames_per_pass is None else fusion.frames_per_pass
        self._chunk_observations = _CHUNK_OBSERVATIONS[kind]
        if kind == "cuda":
            self._chunk_observations = min(self._chunk_observations, available_memory(self.device) // 400)
        points = np.floor((box[1] - box[0]) / voxel_size + 1e-9).astype(np.int64) + 1
        self.block_counts = torch.as_tensor(-(-points // block_size))
        self.frames_integrated = 0
        voxels = self.block_size**3
        local = torch.stack(torch.meshgrid(*[torch.arange(self.block_size)] * 3, indexing="ij"), -1).reshape(
            -1, 3
        )
        self._local = local.to(self.device, torch.float32)  # (B^3, 3) voxel offsets inside a block
        if self.sparse:
            self._keys = torch.empty(0, dtype=torch.int64, device=self.device)  # sorted block keys
            self._slots = torch.empty(0, dtype=torch.int64, device=self.device)  # their slots
            capacity = 1024
        else:
            capacity = int(self.block_counts.prod())
            needed = capacity * voxels * _BYTES_PER_VOXEL[self.with_color]
            budget = int(0.8 * available_memory(self.device)) if max_memory is None else int(max_memory)
            if needed > budget:
                coarser = self.voxel_size * (needed / budget) ** (1 / 3)
                raise ConfigError(
                    f"a dense TSDF volume of {tuple(int(c) * block_size for c in self.block_counts)} voxels "
                    f"({voxel_size:g} m over the box {box.tolist()}) needs {needed / 2**30:.2f} GiB but only "
                    f"{budget / 2**30:.2f} GiB may be used on {self.device}; pass sparse=True (memory follows the "
                    f"surfaces), a voxel_size of at least {coarser:.3g}, or smaller bounds"
                )
        self._used = 0 if self.sparse else capacity
        # storage rows: the blocks' slots, then at least one row of zeros (where absent blocks read)
        self._tsdf = torch.zeros(capacity + 1, voxels, device=self.device)
        self._weight = torch.zeros(capacity + 1, voxels, device=self.device)
        self._color = torch.zeros(capacity + 1, voxels, 3, device=self.device) if self.with_color else None

    # ----------------------------------------------------------------------------------- state

    @property
    def grid_shape(self) -> tuple[int, int, int]:
        """Voxels per axis of the (block-rounded) grid."""
        return tuple(int(c) * self.block_size for c in self.block_counts)

    @property
    def n_blocks(self) -> int:
        """Allocated blocks (all of them in dense mode)."""
        return self._used

    @property
    def memory_bytes(self) -> int:
        """Bytes held by the voxel storage (including unused sparse capacity)."""
        tensors = [self._tsdf, self._weight] + ([self._color] if self._color is not None else [])
        return sum(t.numel() * t.element_size() for t in tensors)

    def _slots_of(self, keys: Tensor) -> Tensor:
        """Int64[Tensor, "b"] block keys -> Int64[Tensor, "b"] slots, -1 where not allocated."""
        if not self.sparse:
            return keys.clone()
        if not len(self._keys):
            return torch.full_like(keys, -1)
        where = torch.searchsorted(self._keys, keys).clamp_max(len(self._keys) - 1)
        return torch.where(self._keys[where] == keys, self._slots[where], -1)

    def _allocate(self, keys: Tensor) -> Tensor:
        """New blocks for Int64[Tensor, "b"] keys (not yet allocated) -> their slots, Int64[Tensor, "b"]."""
        needed = self._used + len(keys)
        if needed >= len(self._tsdf):  # keep a row of zeros after the last slot
            capacity = max(needed + 1, int(len(self._tsdf) * 1.5))
            extra = (capacity - len(self._tsdf)) * self.block_size**3 * _BYTES_PER_VOXEL[self.with_color]
            if extra + self.memory_bytes > available_memory(self.device):  # the copy holds old and new
                raise ConfigError(
                    f"the sparse TSDF volume needs {capacity} blocks ({(extra + self.memory_bytes) / 2**30:.2f} GiB "
                    f"while growing) but {self.device} has {available_memory(self.device) / 2**30:.2f} GiB available; "
                    f"use a larger voxel_size, a smaller truncation or tighter bounds"
                )
            grow = lambda t: torch.cat([t, t.new_zeros((capacity - len(t),) + t.shape[1:])])
            self._tsdf, self._weight = grow(self._tsdf), grow(self._weight)
            self._color = None if self._color is None else grow(self._color)
        slots = torch.arange(self._used, needed, device=self.device)
        self._used = needed
        keys, order = torch.sort(torch.cat([self._keys, keys]))
        self._keys, self._slots = keys, torch.cat([self._slots, slots])[order]
        return slots

    def _workers(self, most: int | None = None) -> int:
        """Worker threads on a CPU: `fusion.threads`, or torch's intra-op thread count (at most `most`) when None
        or "auto"."""
        if self.fusion.threads in (None, "auto"):
            return min(torch.get_num_threads(), most or torch.get_num_threads())
        return self.fusion.threads

    def _block_coords(self, keys: Tensor) -> Tensor:
        """Int64[Tensor, "b"] linear block keys -> Int64[Tensor, "b 3"] block coordinates."""
        ny, nz = int(self.block_counts[1]), int(self.block_counts[2])
        return torch.stack([keys // (ny * nz), (keys // nz) % ny, keys % nz], -1)

    # ------------------------------------------------------------------------------ integration

    def integrate(self, frames: DepthFrames, progress: bool = True) -> TSDFVolume:
        """Fuse every frame of `frames` (any number, one after the other); returns the volume.
        `progress`: a bar over the frames when fusion lasts more than a few seconds (False: none)."""

        if not isinstance(frames, DepthFrames):
            raise InputError(
                f"integrate needs a neuralsurf.structures.DepthFrames (depth, K, cam_to_world), got "
                f"{type(frames).__name__}; build one with DepthFrames(depth, K, cam_to_world)"
            )
        if self.with_color and frames.colors is None:
            raise InputError(
                "this TSDFVolume was made with with_color=True but the frames have no colors; "
                "pass DepthFrames(..., colors=...) or make the volume with with_color=False"
            )
        # move the tensors, not the DepthFrames: no second validation, and any device works
        depth = frames.depth.to(self.device, non_blocking=True)
        colors = frames.colors.to(self.device, non_blocking=True) if self.with_color else None
        bar = progress_bar(desc="TSDF fusion", total=len(frames), unit="frame", enabled=progress)
        cpu = self.device.type == "cpu"
        compiled = cpu and (depth.numel() >= _COMPILE_PIXELS if self.fusion.compiled is None else self.fusion.compiled)
        workers = 1
        if cpu and not compiled:  # eager: shares of the blocks on `workers` threads, each torch op on one
            workers = self._workers(_FUSION_WORKERS)
            threads = 1
        else:
            threads = None if self.fusion.threads == "auto" else self.fusion.threads
        with torch_threads(threads if cpu else None), ThreadPoolExecutor(workers) as pool:
            self._integrate_all(frames, depth, colors, bar, compiled, pool if workers > 1 else None, workers)
        bar.close()
        return self

    def _integrate_all(
        self, frames: DepthFrames, depth: Tensor, colors: Tensor | None, bar, compiled: bool, pool: Executor | None,
        workers: int,
    ) -> None:
        """The passes of `integrate` over depth Float[Tensor, "n h w"] and colours (on the device),
        compiled or eager: first every pass's candidate blocks (`_candidates`, the passes side by side on
        a `pool`'s threads) and their slots, then the voxel passes in order; with a `pool`, each of its
        `workers` threads fuses one share of the blocks through all passes (a block's frames stay in order, and no
        thread waits for another between passes)."""
        per_pass, total = self.frames_per_pass, int(self.block_counts.prod())
        passes = [slice(start, start + per_pass) for start in range(0, len(frames), per_pass)]
        K, cam_to_world = frames.K.cpu(), frames.cam_to_world.cpu()
        per_search = per_pass * max(1, _FRAMES_PER_SEARCH // per_pass)

        def find(start: int) -> list[tuple[Tensor, Tensor | None]]:  # the blocks of the passes of some frames
            part = slice(start, start + per_search)
            found = self._candidates(depth[part], K[part], cam_to_world[part], compiled)
            return candidates_by_pass(*found, len(depth[part]), per_pass, total)

        starts = range(0, len(frames), per_search)
        blocks = [item for found in (pool.map(find, starts) if pool is not None else map(find, starts)) for item in found]
        slots = [self._slots_of(keys) for keys, _ in blocks]
        if self.sparse and any(bool((slot < 0).any()) for slot in slots):  # blocks touched for the first time
            self._allocate(torch.unique(torch.cat([keys[slot < 0] for (keys, _), slot in zip(blocks, slots)])))
            slots = [self._slots_of(keys) for keys, _ in blocks]
        shares = 1 if pool is None else workers
        origin = torch.as_tensor(self.origin, dtype=torch.float64)
        projections = grid_to_pixel(K, cam_to_world, origin, self.voxel_size).to(self.device)

        def fuse_share(share: int) -> None:
            for part, (keys, frame_keys), slot in zip(passes, blocks, slots):
                if shares > 1:
                    mine = slot % shares == share
                    keys, slot = keys[mine], slot[mine]
                self._integrate_frames(depth[part], projections[part], None if colors is None else float_colors(colors[part]),
                                       compiled, keys, frame_keys, slot)
                if share == 0:
                    bar.update(len(depth[part]))

        if shares == 1:
            fuse_share(0)
        else:
            list(pool.map(fuse_share, range(shares)))
        self.frames_integrated += len(depth)

    def _candidates(self, depth: Tensor, K: Tensor, cam_to_world: Tensor, compiled: bool) -> tuple[Tensor, Tensor | None]:
        """`candidate_blocks` of depth images Float[Tensor, "f h w"] seen by K Float[Tensor, "f 3 3"] at
        cam_to_world Float[Tensor, "f 4 4"] (both on the CPU)."""
        origin = torch.as_tensor(self.origin, dtype=torch.float64)
        rotation, translation = camera_to_grid(cam_to_world, origin, self.voxel_size)
        to = lambda t: t.to(self.device, depth.dtype)
        return candidate_blocks(
            depth, to(K), to(rotation), to(translation), self.truncation, self.fusion.free_space, self.block_size,
            self.block_counts, _COMPILED[tile_box_codes] if compiled else tile_box_codes,
            TILE["compiled" if compiled else "eager"],
        )

    def _integrate_frames(
        self, depth: Tensor, projection: Tensor, colors: Tensor | None, compiled: bool,
        keys: Tensor, frame_keys: Tensor | None, slots: Tensor,
    ) -> None:
        """Fuse depth images Float[Tensor, "f h w"] seen through projection Float[Tensor, "f 3 4"]
        (`grid_to_pixel`), colours Float[Tensor, "f h w 3"] | None, in order, into some of their candidate
        blocks (`_candidates`): keys Int64[Tensor, "b"] at slots Int64[Tensor, "b"]; `compiled`: through
        `_COMPILED` (CPU)."""
        n_frames, voxels, total = len(depth), self.block_size**3, int(self.block_counts.prod())
        padded = pad_image(depth)
        weighting = self.fusion.weighting
        weights = None if weighting == "constant" else pad_image(pixel_weights(depth, weighting))
        weights = None if weights is None else weights.reshape(-1)
        colors = None if colors is None else pad_image(colors).reshape(-1, 3)
        cap = math.inf if self.fusion.max_weight is None else self.fusion.max_weight
        limits = torch.tensor([self.truncation, cap], dtype=depth.dtype, device=self.device)
        fuse = _COMPILED[fuse_blocks] if compiled else fuse_blocks
        chunk_observations = _CHUNK_OBSERVATIONS["compiled"] if compiled else self._chunk_observations
        per_chunk = max(1, chunk_observations // (voxels * n_frames))
        for start in range(0, len(keys), per_chunk):
            chunk, chunk_slots = keys[start : start + per_chunk], slots[start : start + per_chunk]
            frame_mask = None
            if frame_keys is not None:  # a frame updates only the blocks its own band touches
                tagged = chunk + total * torch.arange(n_frames, device=self.device)[:, None]  # (f, m)
                where = torch.searchsorted(frame_keys, tagged).clamp_max(len(frame_keys) - 1)
                frame_mask = (frame_keys[where] == tagged).to(depth.dtype)
            fuse(
                self._tsdf, self._weight, self._color, chunk_slots, self._block_coords(chunk) * self.block_size,
                self._local, projection, padded, limits, frame_mask, weights, colors,
            )

    # ------------------------------------------------------------------------------ save / load

    def save(self, path) -> Path:
        """Write the volume (settings and fused voxels) to `path` as a compressed .npz, atomically (a
        temporary file in the same folder, then a rename): an interrupted save leaves any earlier
        file intact. Only numbers and strings are stored, so `load` needs no pickle.

        Returns the Path written (`path` itself; an extension other than .npz is kept as given).
        """
        return save_volume(self, path)

    @classmethod
    def load(cls, path, device="auto", fusion: FusionSettings | None = None) -> TSDFVolume:
        """A volume written by `save`, on `device`, ready to `integrate` more frames or `extract_mesh`.
        Its fusion rule is the file's; `fusion` sets the execution of further integrations (its rule
        must then be the file's: a ConfigError says which field differs).

        Read with `numpy.load(allow_pickle=False)`: a file holding anything but plain arrays is refused.
        Raises FileFormatError for a missing, truncated or foreign file (naming it).
        """
        return load_volume(cls, path, device, fusion)

    # ------------------------------------------------------------------------------- extraction

    def _points(self, lo: list[int], hi: list[int]) -> tuple[Tensor, Tensor, Tensor | None]:
        """The grid points lo <= (i, j, k) < hi (any box, possibly reaching outside the grid) -> their tsdf,
        weight Float[Tensor, "X Y Z"] and colour Float[Tensor, "X Y Z 3"] | None; 0 where no block is."""
        size = self.block_size
        first = [index // size for index in lo]
        counts = [(high - 1) // size + 1 - start for high, start in zip(hi, first)]
        axes = [torch.arange(start, start + n, device=self.device) for start, n in zip(first, counts)]
        blocks = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        limit = self.block_counts.to(self.device)
        inside = ((blocks >= 0) & (blocks < limit)).all(1)
        keys = (blocks[:, 0] * limit[1] + blocks[:, 1]) * limit[2] + blocks[:, 2]
        slots = torch.full_like(keys, -1)
        slots[inside] = self._slots_of(keys[inside])
        present = (slots >= 0).nonzero()[:, 0]
        start = [low - f * size for low, f in zip(lo, first)]

        def assemble(storage: Tensor) -> Tensor:
            values = storage.new_zeros((len(keys),) + storage.shape[1:])
            values[present] = storage[slots[present]]
            channels = storage.shape[2:]
            values = values.view(*counts, size, size, size, *channels).permute(0, 3, 1, 4, 2, 5, *range(6, 6 + len(channels)))
            values = values.reshape(counts[0] * size, counts[1] * size, counts[2] * size, *channels)
            return values[tuple(slice(s, s + high - low) for s, low, high in zip(start, lo, hi))]

        color = None if self._color is None else assemble(self._color)
        return assemble(self._tsdf), assemble(self._weight), color

    def observed_voxels(self) -> tuple[Tensor, Tensor]:
        """(Int64[Tensor, "n"] linear indices of the grid points with weight > 0 in `grid_shape`, i-major, ascending
        within each block; Float[Tensor, "n"] their signed distances), read from the blocks without a dense grid."""
        keys = self._keys if self.sparse else torch.arange(self._used, device=self.device)
        slots = self._slots if self.sparse else keys
        size, (_, ny, nz) = self.block_size, self.grid_shape
        corner = self._block_coords(keys) * size
        base = (corner[:, 0] * ny + corner[:, 1]) * nz + corner[:, 2]
        local = self._local.long()
        offset = (local[:, 0] * ny + local[:, 1]) * nz + local[:, 2]
        seen = self._weight[slots] > 0
        return (base[:, None] + offset)[seen], self._tsdf[slots][seen]

    def to_dense(self) -> tuple[Tensor, Tensor]:
        """Float[Tensor, "X Y Z"] signed distances (NaN where unobserved) and weights of the whole grid
        (small volumes: tests, plots)."""
        tsdf, weight, _ = self._points([0, 0, 0], list(self.grid_shape))
        return torch.where(weight > 0, tsdf, torch.nan), weight

    def _color_at(self, points: np.ndarray) -> Tensor:
        """Float64[ndarray, "v 3"] vertices (grid units, each on a grid edge) -> Float[Tensor, "v 3"] the
        colour interpolated along that edge."""
        lower = np.floor(points).astype(np.int64)
        fraction = points - lower
        axis = fraction.argmax(1)
        upper = lower.copy()
        upper[np.arange(len(points)), axis] += 1
        t = torch.from_numpy(fraction[np.arange(len(points)), axis]).to(self.device, torch.float32)[:, None]

        def lookup(index: np.ndarray) -> Tensor:
            index = torch.from_numpy(np.minimum(index, np.array(self.grid_shape) - 1)).to(self.device)
            block, local = index // self.block_size, index % self.block_size
            limit = self.block_counts.to(self.device)
            slots = self._slots_of((block[:, 0] * limit[1] + block[:, 1]) * limit[2] + block[:, 2])
            offset = (local[:, 0] * self.block_size + local[:, 1]) * self.block_size + local[:, 2]
            return self._color[slots.clamp_min(0), offset]

        return torch.lerp(lookup(lower), lookup(upper), t).clamp(0, 1).cpu()

    def _block_cubes(self, keys: Tensor, tsdf: Tensor, weight: Tensor) -> tuple[Tensor, Tensor]:
        """The grid points of some blocks and the next point along each axis, a cube of side B + 1 per
        block: its cells are the cells whose first corner is one of the block's voxels.
        Args: keys Int64[Tensor, "m"] block keys; tsdf, weight: Float[Tensor, "(used + 1) B^3"] the stored
        blocks and a last one of zeros (where absent blocks read). Returns tsdf Float[Tensor, "m S S S"]
        and valid Bool[Tensor, "m S S S"] (observed), S = B + 1.
        """
        size, side, absent = self.block_size, self.block_size + 1, len(tsdf) - 1
        upper = torch.stack(torch.meshgrid(*[torch.arange(2, device=self.device)] * 3, indexing="ij"), -1)
        slots = self._slots_of(self._keys_around(keys, upper.reshape(8, 3)))  # (m, 8)
        slots.masked_fill_(slots < 0, absent)
        step = torch.arange(side, device=self.device)
        near, within = step.div(size, rounding_mode="floor"), step % size  # neighbour 0..1, voxel in it
        neighbour = (near[:, None, None] * 4 + near[None, :, None] * 2 + near[None, None, :]).view(-1)
        voxel = ((within[:, None, None] * size + within[None, :, None]) * size + within[None, None, :]).view(-1)
        index = torch.add(voxel, slots[:, neighbour], alpha=size**3)  # (m, S^3)
        cube = (len(keys), side, side, side)
        return tsdf.view(-1)[index].view(cube), (weight.view(-1)[index] > 0).view(cube)

    def _keys_around(self, keys: Tensor, shifts: Tensor) -> Tensor:
        """Int64[Tensor, "m"] block keys, Int64[Tensor, "s 3"] block offsets -> Int64[Tensor, "m s"] the keys
        of the shifted blocks, -1 outside the grid."""
        blocks = self._block_coords(keys)[:, None] + shifts
        limit = self.block_counts.to(self.device)
        inside = ((blocks >= 0) & (blocks < limit)).all(-1)
        return torch.where(inside, (blocks[..., 0] * limit[1] + blocks[..., 1]) * limit[2] + blocks[..., 2], -1)

    def extract_mesh(self) -> Mesh:
        """The 0-level set of the fused TSDF as a Mesh in the world frame, faces oriented outward
        (towards positive TSDF, i.e. the cameras), with vertex colours when `with_color`.

        The blocks that may own a cell with a sign change (an observed value <= 0 in them or in one of
        the seven blocks after them), at most _MESH_BLOCKS at a time (on `fusion.threads` worker threads), are
        read as cubes (`_block_cubes`) and marched by `neuralsurf.marching.cube_triangles`, cells with an
        unobserved corner skipped. A vertex on a block's face is found from the same values in each
        block that shares it and named by its grid edge, so the mesh has no seams between blocks."""
        if self.frames_integrated == 0:
            raise ExtractionError("the TSDF volume is empty: call integrate(frames) before extract_mesh()")
        cpu = self.device.type == "cpu"
        workers = self._workers() if cpu else 1
        with torch_threads(1 if cpu else None), ThreadPoolExecutor(workers) as pool:
            return self._extract_mesh(pool, workers)

    def _extract_mesh(self, pool: Executor, workers: int) -> Mesh:
        tsdf, weight = self._tsdf[: self._used], self._weight[: self._used]
        observed = weight > 0
        if not observed.any():
            raise ExtractionError(
                f"none of the {self.frames_integrated} integrated frames observed a surface inside the bounds "
                f"{self.bounds.tolist()}: check the bounds, the poses (cam_to_world, not world_to_camera) and "
                f"the depth units (metres)"
            )
        slots = torch.arange(self._used, device=self.device)
        keys, slots = (self._keys, self._slots) if self.sparse else (slots, slots)
        inside = (observed & (tsdf <= 0)).any(1)[slots]  # per key
        upper = torch.stack(torch.meshgrid(*[torch.arange(2, device=self.device)] * 3, indexing="ij"), -1)
        around = self._keys_around(keys, upper.reshape(8, 3))
        where = torch.searchsorted(keys, around).clamp_max(len(keys) - 1)
        keys = keys[observed.any(1)[slots] & ((keys[where] == around) & inside[where]).any(1)]
        tsdf, weight = self._tsdf[: self._used + 1], self._weight[: self._used + 1]  # the last: zeros
        origins = self._block_coords(keys) * self.block_size

        def mesh_part(part: Tensor) -> tuple[Tensor, Tensor]:  # cube_triangles of some blocks
            values, valid = self._block_cubes(keys[part], tsdf, weight)
            return cube_triangles(values, valid, origins[part], self.grid_shape)

        per_call = max(64, min(_MESH_BLOCKS, -(-len(keys) // (2 * workers))))  # a few calls a worker
        pieces = list(pool.map(mesh_part, torch.arange(len(keys), device=self.device).split(per_call)))
        edges, positions = (torch.cat(items) for items in zip(*pieces)) if pieces else (torch.zeros(0), None)
        if not len(edges):
            raise ExtractionError(
                "the fused TSDF has no zero crossing between observed voxels: the frames see no surface with "
                "both sides inside the truncation band; check the truncation (a few voxels) and the poses"
            )
        points, faces = merge_edge_vertices(edges, positions)
        points = points.cpu().double().numpy()
        vertices = torch.from_numpy((self.origin + points * self.voxel_size).astype(np.float32))
        colors = self._color_at(points) if self.with_color else None
        return Mesh(vertices, faces.cpu(), colors)


__all__ = ["TSDFVolume", "available_memory", "depth_bounds"]
