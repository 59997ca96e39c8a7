"""TSDF fusion of depth frames (Curless & Levoy 1996; KinectFusion, Newcombe et al. 2011) in PyTorch.

`TSDFVolume(bounds, voxel_size, ...)`, then `.integrate(frames)` any number of times, then
`.extract_mesh()`. Vectorised over voxels, on any torch device (CPU or CUDA).

The volume
    Grid points ("voxels") sit at `bounds[0] + (i, j, k) * voxel_size` and are stored in blocks of
    `block_size`^3 voxels: `tsdf` and `weight` are (slots, block_size^3) tensors (plus `color`,
    (slots, block_size^3, 3)). Dense mode allocates every block of the box up front (slot = linear
    block index); sparse mode allocates a block the first time a frame's band touches it (see
    below) and finds slots through a sorted tensor of block keys (`torch.searchsorted`), so memory follows
    the observed surfaces, not the box.

Integration, a pass of `frames_per_pass` frames at a time (one on a CPU, 32 on a GPU)
    1. The band's blocks: the blocks that the segment z in [d - truncation - free_space,
       d + truncation] of some valid pixel's footprint meets (depth d), found from the exact boxes
       of small image tiles (`candidate_blocks`); as in Open3D's VoxelBlockGrid (whose band is [d - truncation,
       d + truncation]), a frame updates the voxels of these blocks only, and in sparse mode they
       are allocated.
    2. For the voxels of those blocks and each frame of the pass: pixel coordinates by one small
       matmul per block and one per block-local offset (K [R | t] folded with the grid),
       nearest-pixel projection, projective signed distance sdf = depth(pixel) - z (positive in
       front of the surface, i.e. outside); then, frame after frame, for the voxels where the depth
       is valid and sdf >= -truncation (in front of the surface at any distance: the free space of
       the band's blocks is observed too), the running weighted averages of min(sdf, truncation):
       tsdf <- (W tsdf + w sdf) / (W + w), colour likewise, W <- min(W + w, max_weight), so a pass
       gives what one frame at a time gives. Voxels never updated have weight 0 and count as
       unobserved.
       Why the free space in the band's blocks matters: a surface seen at a grazing angle has
       voxels just in front of it whose projective distances are many truncations (1 / cos of the
       angle); an update limited to sdf <= some margin leaves them unobserved and their cells
       unmeshed (that update, with a margin of half a voxel, kept 0.64 of VoxelBlockGrid's mesh
       vertices on 10 frames of 7-Scenes at 1 cm; the band's blocks keep 0.98-1.0). Behind the
       surface the band ends at -truncation along the ray, as in Open3D: a single grazing view
       still leaves stripes there, which other views fill. `free_space` > 0 carves further towards
       the camera (removes floating outliers, closes holes seen from afar), at a cost.
    Speed on a CPU: the voxels go through in chunks of _CHUNK_OBSERVATIONS (cache-sized) in float
    arithmetic only (bool tensors are several times slower there), and `integrate` runs torch on
    `threads` threads (eager, 1: many short vectorised ops, whose thread synchronisation costs more
    than it gains on a few cores and stalls badly when other processes hold the cores).
    Compiled (`compiled`, by default for calls of _COMPILE_PIXELS depth pixels or more), the tiles'
    boxes and the voxel pass run as loops compiled by torch.compile (`CompiledOnCPU`) on all of torch's
    threads: on 7-Scenes at 1 cm, 2 cores, 19 ms a frame instead of 56, after a compilation of 20-35 s
    once per process (about 11 s from torch's on-disk cache when compiled before): for long sequences.
    Stored values are signed distances in metres (not normalised), in [-truncation, truncation].

Extraction
    Marching cubes (scikit-image) of the 0-level runs per chunk of blocks, on the chunk's voxels
    plus the first layer of the next chunk, so every cell is meshed by exactly one chunk. Cells
    with an unobserved corner produce no faces. Vertices are welded across chunks by the grid edge
    they lie on (a key computed from the voxel values, identical in both chunks), and placed by
    float64 interpolation of those values, so the mesh is the one a single marching-cubes call on
    the whole grid would give, with no seams between chunks or blocks.
"""

from __future__ import annotations

import contextlib
import functools
import math
import numbers
import os
import warnings
import zipfile
from concurrent.futures import Executor, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neuralsurf.devices import resolve_device
from neuralsurf.errors import ConfigError, ExtractionError, FileFormatError, InputError
from neuralsurf.extract import as_bounds, level_set
from neuralsurf.geometry import kinect_sigma
from neuralsurf.io.npz import write_npz
from neuralsurf.structures import DepthFrames, Mesh

WEIGHTINGS = ("constant", "depth")
"""Per-observation weights: "constant" = 1; "depth" = inverse variance of the Kinect v1 axial noise
model (Nguyen et al. 2012), (sigma(0.4 m) / sigma(z))^2, which is 1 at 0.4 m and 0.2 at 1.5 m."""

_CHUNK_OBSERVATIONS = {"cpu": 1 << 17, "compiled": 1 << 21, "cuda": 1 << 25}
"""Voxel observations (voxels x frames) per vectorised step, at most (temporary memory: ~40 bytes
each eager, cache-sized on a CPU; ~12 compiled, where a step costs ~0.5 ms more; on CUDA also at most
1/400 of the free memory)."""
_FRAMES_PER_PASS = {"cpu": 1, "cuda": 32}
"""Default frames fused per pass: one on a CPU (each frame visits only its own voxels); on a GPU a
batch, so that the fixed cost of a pass (kernel launches, a few host syncs) is shared."""
_MESH_BLOCKS = 4096
"""Blocks meshed per marching-cubes call (about 60 bytes per voxel: 0.15 GB for blocks of 8^3)."""
_OFF_POINT = 5e-5
"""A marching-cubes vertex nearer than this (grid units) to a grid point in every coordinate is on it."""
_MAX_KEYS = 1 << 24
"""Candidate block keys enumerated at a time (bounds memory when boxes are large)."""
_BITMAP_LIMIT = 1 << 27
"""Candidate blocks are deduplicated in a bitmap over all blocks up to this many blocks, else sorted."""
_BYTES_PER_VOXEL = {False: 8, True: 20}
"""tsdf + weight (float32), plus three float32 colour channels."""
TSDF_FORMAT = "neuralsurf.TSDFVolume/1"
"""Tag of the .npz files written by `TSDFVolume.save` (bumped when their layout changes)."""


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


def _positive(value, name: str, what: str) -> float:
    """`value` as a float, or ConfigError unless it is a positive finite number."""
    if not (isinstance(value, numbers.Real) and math.isfinite(value) and value > 0):
        raise ConfigError(f"{name} must be positive and finite ({what}), got {value!r}")
    return float(value)


def depth_bounds(frames: DepthFrames, margin: float = 0.0) -> Tensor:
    """Float64[Tensor, "2 3"]: world bounding box of every valid depth pixel, grown by `margin`."""
    from neuralsurf.geometry import backproject_depth

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


def pixel_weights(depth: Tensor, weighting: str) -> Tensor:
    """Float[Tensor, "h w"] z-depth -> Float[Tensor, "h w"] weight of each pixel's observation."""
    if weighting == "constant":
        return torch.ones_like(depth)
    return (kinect_sigma(torch.tensor(0.4)) / kinect_sigma(depth)) ** 2


def world_to_camera(cam_to_world: Tensor) -> tuple[Tensor, Tensor]:
    """Float[Tensor, "... 4 4"] rigid poses -> rotations Float64[Tensor, "... 3 3"] and translations
    Float64[Tensor, "... 3"] with x_camera = rotation @ x_world + translation."""
    pose = cam_to_world.double()
    rotation = pose[..., :3, :3].transpose(-1, -2)
    return rotation, -(rotation @ pose[..., :3, 3:])[..., 0]


def camera_to_grid(cam_to_world: Tensor, origin: Tensor, voxel_size: float) -> tuple[Tensor, Tensor]:
    """Float[Tensor, "f 4 4"] poses -> rotations Float64[Tensor, "f 3 3"] and translations Float64[Tensor,
    "f 3"] with x_grid = rotation @ x_camera + translation, grid coordinates being voxel indices from
    `origin` Float64[Tensor, "3"]."""
    pose = cam_to_world.double()
    return pose[:, :3, :3] / voxel_size, (pose[:, :3, 3] - origin) / voxel_size


def grid_to_pixel(K: Tensor, cam_to_world: Tensor, origin: Tensor, voxel_size: float) -> Tensor:
    """Float[Tensor, "f 3 4"]: per frame, grid index (homogeneous) -> (z u, z v, z) with (u, v) pixel
    coordinates, K [R | t] composed with the grid (relative to `origin` for precision)."""
    rotation, translation = world_to_camera(cam_to_world)
    extrinsic = torch.cat([rotation * voxel_size, (rotation @ origin + translation)[..., None]], 2)
    return (K.double() @ extrinsic).float()


def _unique_keys(keys: Tensor, total: int) -> Tensor:
    """Int64[Tensor, "n"] keys in [0, total) -> sorted unique keys: by a bitmap over [0, total), or by
    sorting where there are far fewer keys than that (measured on 2 cores: a bitmap costs about 2 ns per
    entry, a sort about 80 ns per key) or the bitmap would be too large."""
    if total <= _BITMAP_LIMIT and 40 * len(keys) >= total:
        return torch.zeros(total, dtype=torch.bool, device=keys.device).index_fill_(0, keys, True).nonzero()[:, 0]
    return torch.unique(keys)


def box_keys(lo: Tensor, hi: Tensor, block_counts: Tensor, tags: Tensor | None = None) -> Tensor:
    """Keys of every block in some boxes: lo, hi Float[Tensor, "n 3"] inclusive block ranges (clipped
    to the volume) -> Int64[Tensor, "k"] linear keys (i * ny + j) * nz + k, with repeats, plus each
    box's Int64[Tensor, "n"] `tags` (an offset such as frame * blocks) when given. Boxes are
    enumerated in groups of equal span, at most _MAX_KEYS keys at a time."""
    counts = block_counts.to(lo.device, torch.float32)
    keep = ((hi >= 0) & (lo < counts) & (hi >= lo)).all(1)
    lo, hi = lo[keep].clamp_min(0), torch.minimum(hi[keep], counts - 1)
    small = tags is None and int(block_counts.prod()) < 2**31
    dtype = torch.int32 if small else torch.int64
    strides = torch.tensor(
        [int(block_counts[1] * block_counts[2]), int(block_counts[2]), 1], dtype=dtype, device=lo.device
    )
    extent = (hi - lo).to(dtype)
    first = (lo.to(dtype) * strides).sum(1, dtype=dtype)
    if tags is not None:
        first = first + tags[keep]
    span = extent.amax(1)
    keys = [torch.empty(0, dtype=torch.int64, device=lo.device)]
    for size in torch.unique(span).tolist():
        pick = (span == size).nonzero()[:, 0]
        steps = torch.arange(size + 1, dtype=dtype, device=lo.device)
        for part in pick.split(max(1, _MAX_KEYS // (size + 1) ** 3)):
            # key offsets along each axis, (p, 3, size + 1); steps past a box's end repeat its last block
            offsets = torch.minimum(steps, extent[part][..., None]) * strides[:, None]
            box = (
                first[part][:, None, None, None]
                + offsets[:, 0, :, None, None]
                + offsets[:, 1, None, :, None]
                + offsets[:, 2, None, None, :]
            )
            keys.append(box.reshape(-1).long())
    return torch.cat(keys)


_COMPILE_PIXELS = 300 * 640 * 480
"""TSDFVolume(compiled=None) compiles an `integrate` call on a CPU from this many depth pixels on. Measured on
7-Scenes at 1 cm, 2 cores: 56 ms a frame eager, 19 compiled after a compilation of 11 s (from torch's
on-disk cache; 20-35 s without): compiling pays from about 300 frames of 640 x 480."""
_TILE = {"compiled": 1, "eager": 2}
"""Pixels per side of the tiles that `candidate_blocks` boxes. Measured on 7-Scenes at 1 cm (one frame:
tiles of 1 pixel give 2,737 blocks, of 2 pixels 2,782 for a quarter of the vectorised ops, of 4 pixels
2,826): compiled, single pixels (a fused loop; their boxes never need `box_keys`); eager, 2 x 2 tiles."""
_NO_BLOCK, _WIDE = -1, -2
"""`tile_box_codes` of a tile that adds no box and of one whose box spans more than two blocks on an axis."""


def tile_block_ranges(
    depth: Tensor, pixel_to_grid: Tensor, translation: Tensor, band: Tensor, tile: int
) -> tuple[list[Tensor], list[Tensor], Tensor]:
    """The blocks that the box of each image tile's piece of the band spans.

    A tile's piece: the points whose pixel coordinates lie in the footprint of its tile x tile pixels
    and whose z lies in [nearest - band[0], deepest + band[1]] (its smallest and largest valid depths).
    Its box is exact: along each axis a point is z times an affine function of (u, v) plus a constant,
    so the extremes lie at the footprint's corners and at the two ends of z; it holds the pieces of the
    tile's pixels.

    Args:
        depth: Float[Tensor, "f h w"] z-depth (0 = invalid), h and w multiples of `tile`.
        pixel_to_grid: Float[Tensor, "f 3 3"] rotation @ K^-1; translation: Float[Tensor, "f 3"] the camera
            centre in grid units (x_grid = rotation @ x_camera + translation).
        band: Float[Tensor, "3"] metres in front of and behind the depth, and voxels per block side.
        tile: pixels per tile side.
    Returns:
        first, last: per axis, Float[Tensor, "f h/tile w/tile"] the box's first and last block (not clipped to
        the volume; one tensor an axis, as a tile's three axes side by side vectorise badly); seen:
        Bool[Tensor, "f h/tile w/tile"] where the tile has a valid depth.
    """
    pixels = lambda image: [image[:, i::tile, j::tile] for i in range(tile) for j in range(tile)]  # of each tile
    nearest = functools.reduce(torch.minimum, pixels(torch.where(depth > 0, depth, math.inf)))
    deepest = functools.reduce(torch.maximum, pixels(depth))
    centres = lambda n: torch.arange(n, device=depth.device, dtype=depth.dtype) * tile + (tile - 1) / 2
    u, v = centres(depth.shape[2] // tile), centres(depth.shape[1] // tile)[:, None]  # pixel units
    near, far = (nearest - band[0]).clamp_min(1e-6), deepest + band[1]
    first, last = [], []
    for axis in range(3):
        a, b, c = (pixel_to_grid[:, axis, k, None, None] for k in range(3))
        centre, half = u * a + v * b + c, tile / 2 * (a.abs() + b.abs())  # ray per metre of z, over the tile
        low, high = centre - half, centre + half
        shift = translation[:, axis, None, None]
        first.append(torch.floor((torch.minimum(low * near, low * far) + shift) / band[2]))
        last.append(torch.floor((torch.maximum(high * near, high * far) + shift) / band[2]))
    return first, last, deepest > 0


def tile_box_codes(
    depth: Tensor, pixel_to_grid: Tensor, translation: Tensor, band: Tensor, block_counts: Tensor, tile: int
) -> Tensor:
    """Each image tile's box (`tile_block_ranges`), clipped to the volume, as one integer. With a band
    thinner than a block, the box of a tile without a depth edge meets one or two blocks per axis.

    Args: as `tile_block_ranges`, and block_counts: Float[Tensor, "3"] blocks per axis.
    Returns:
        Int64[Tensor, "f h/tile w/tile"]: (frame * blocks + key) * 8 + bits, with key = (i * ny + j) * nz
        + k the box's first block (clipped to the volume) and bits (4, 2, 1 for i, j, k) the axes on which
        it meets two blocks; _WIDE where it meets more than two on an axis; _NO_BLOCK where the tile adds
        no box (no valid depth, a piece outside the volume, or the box of its left or upper neighbour:
        each box stays at its first tile, so a frame gives a few thousand boxes, not 300,000).
    """
    firsts, lasts, inside = tile_block_ranges(depth, pixel_to_grid, translation, band, tile)
    wide = torch.zeros_like(inside)
    key = bits = torch.zeros_like(inside, dtype=torch.int64)
    for axis, (first, last) in enumerate(zip(firsts, lasts)):
        inside = inside & (last >= 0) & (first < block_counts[axis])
        first, last = first.clamp_min(0), torch.minimum(last, block_counts[axis] - 1)
        wide = wide | (last - first > 1)
        key = key * block_counts[axis].long() + first.long()
        bits = bits * 2 + (last > first).long()
    frame = torch.arange(len(depth), device=depth.device)[:, None, None]
    code = torch.where(inside, torch.where(wide, _WIDE, (frame * block_counts.prod().long() + key) * 8 + bits), _NO_BLOCK)
    # a box is kept at its first tile in raster order: neither its left nor its upper neighbour has it
    left = torch.nn.functional.pad(code[:, :, :-1], (1, 0), value=_NO_BLOCK)
    up = torch.nn.functional.pad(code[:, :-1], (0, 0, 1, 0), value=_NO_BLOCK)
    return torch.where((code >= 0) & ((code == left) | (code == up)), _NO_BLOCK, code)


def candidate_blocks(
    depth: Tensor,
    K: Tensor,
    rotation: Tensor,
    translation: Tensor,
    truncation: float,
    free_space: float,
    block_size: int,
    block_counts: Tensor,
    box_codes=tile_box_codes,
    tile: int = _TILE["eager"],
) -> tuple[Tensor, Tensor | None]:
    """The blocks that the bands of some frames touch: those meeting the segment z in
    [d - truncation - free_space, d + truncation] of a valid pixel's footprint (depth d).

    The boxes of image tiles of tile x tile pixels (`tile_box_codes`; `box_codes` is that function,
    compiled or not) give their blocks; a tile whose box spans more than two blocks on an axis (a depth
    edge, a grazing view, a long segment) gives the boxes of its pixels (`box_codes` again, then
    `box_keys` over `tile_block_ranges` for those still wider). So the candidates hold every block that a pixel's segment meets,
    and few more.

    Args:
        depth: Float[Tensor, "f h w"] z-depth (0 = invalid); K: Float[Tensor, "f 3 3"];
        rotation, translation: camera -> grid, x_grid = rotation @ x_camera + translation, Float[Tensor,
            "f 3 3"] and "f 3" (grid units = voxels);
        truncation, free_space: metres; block_size: voxels per block side;
        block_counts: Int[Tensor, "3"] blocks per axis; tile: see _TILE.
    Returns:
        keys: Int64[Tensor, "b"] sorted unique block keys, the union over the frames; and with more
        than one frame, frame_keys: Int64[Tensor, "k"] sorted unique frame * blocks + key (which
        frame touches which block), else None.
    """
    frames, height, width = depth.shape
    total = int(block_counts.prod())
    ny, nz = int(block_counts[1]), int(block_counts[2])
    if width % tile or height % tile:
        depth = torch.nn.functional.pad(depth, (0, -width % tile, 0, -height % tile))
    pixel_to_grid = rotation @ torch.linalg.inv(K)
    band = torch.tensor([truncation + free_space, truncation, block_size], dtype=depth.dtype, device=depth.device)
    counts = block_counts.to(depth.device, depth.dtype)
    codes = box_codes(depth, pixel_to_grid, translation, band, counts, tile).view(-1)
    tiles = (codes != _NO_BLOCK).nonzero()[:, 0]
    codes = codes[tiles]
    boxes = [codes[codes >= 0]]  # with some repeats (boxes met again further on), as their blocks
    wide = tiles[codes == _WIDE]
    keys = []
    if len(wide):  # the pixels of these tiles, as images of one-pixel tiles (pixel (u, v) is u + col, v + row)
        rows, columns = depth.shape[1] // tile, depth.shape[2] // tile
        frame, row, col = wide // (rows * columns), wide // columns % rows * tile, wide % columns * tile
        step = torch.arange(tile, device=depth.device)
        pixels = depth[frame[:, None, None], row[:, None, None] + step[:, None], col[:, None, None] + step]
        shifted = pixel_to_grid[frame].clone()
        shifted[:, :, 2] += shifted[:, :, 0] * col[:, None] + shifted[:, :, 1] * row[:, None]
        if tile > 1:  # their own boxes, mostly narrower
            codes = box_codes(pixels, shifted, translation[frame], band, counts, 1)
            boxes.append((codes % (total * 8) + (frame * total * 8)[:, None, None])[codes >= 0])
            pixels = torch.where(codes == _WIDE, pixels, 0.0)
        first, last, seen = tile_block_ranges(pixels, shifted, translation[frame], band, 1)  # the widest
        tags = (frame * total)[:, None, None].expand_as(seen)
        keys.append(box_keys(torch.stack(first, -1)[seen], torch.stack(last, -1)[seen], block_counts, tags[seen]))
    boxes = torch.cat(boxes)
    corner = torch.arange(8, device=depth.device)  # bits of the second block taken on each axis
    offset = (corner >> 2) * (ny * nz) + ((corner >> 1) & 1) * nz + (corner & 1)
    first, bits = boxes[:, None] // 8, boxes[:, None] % 8
    keys.append(torch.where((bits & corner) == corner, first + offset, first).view(-1))
    frame_keys = _unique_keys(torch.cat(keys), frames * total)
    if frames == 1:
        return frame_keys, None
    return _unique_keys(frame_keys % total, total), frame_keys


def pad_image(image: Tensor) -> Tensor:
    """Float[Tensor, "f h w ..."] -> Float[Tensor, "f h+2 w+2 ..."] with a border of zeros (invalid
    depth): pixel lookups clamped into the border need no bounds test."""
    border = [0, 0] * (image.ndim - 3) + [1, 1, 1, 1]
    return torch.nn.functional.pad(image, border)


def observe_blocks(
    blocks: Tensor, local: Tensor, projection: Tensor, padded: Tensor, truncation: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Projective signed distances of the voxels of some blocks, as each of some depth images sees them.

    Args:
        blocks: Int64[Tensor, "m 3"] grid index of each block's first voxel.
        local: Float[Tensor, "v 3"] voxel offsets inside a block (v = block_size^3).
        projection: Float[Tensor, "f 3 4"] per frame, grid index (homogeneous) -> (z u, z v, z) with
            (u, v) pixel coordinates (K [R | t] composed with the grid's voxel size and origin).
        padded: Float[Tensor, "f h+2 w+2"] z-depth (0 = invalid) with a border of zeros (`pad_image`).
        truncation: Float[Tensor, ""] metres.
    Returns, over the voxels (f, m, v):
        seen Float[Tensor, "f m v"]: 1 where the voxel is in front of the camera and projects (nearest
        pixel) onto a valid depth d with d - z >= -truncation (any distance in front: free space
        too), else 0; sdf Float[Tensor, "f m v"] = min(d - z, truncation); pixel Int64[Tensor,
        "f m v"] index into the padded images flattened together (frame-major).
    """
    frames, rows, cols = padded.shape
    shifted = projection.clone()
    shifted[:, :2] += 1.5 * shifted[:, 2:]  # (z (u + 1.5), z (v + 1.5), z): floor(u + 1.5) = padded column
    linear = shifted[:, :, :3].transpose(1, 2)  # (f, 3, 3)
    base = (blocks.to(linear.dtype) @ linear + shifted[:, None, :, 3])[..., None]  # (f, m, 3, 1)
    offset = (local @ linear).transpose(1, 2)[:, None]  # (f, 1, 3, v)
    z = base[:, :, 2] + offset[:, :, 2]  # (f, m, v)
    # voxels at or behind the camera plane look up the zero border (an invalid depth)
    inverse = torch.where(z > 0, z.reciprocal(), 0.0)
    column = (base[:, :, 0] + offset[:, :, 0]).mul_(inverse).clamp_(0, cols - 1).floor_()
    row = (base[:, :, 1] + offset[:, :, 1]).mul_(inverse).clamp_(0, rows - 1).floor_()
    if rows * cols * frames < 2**24:  # whole numbers stay exact in float32
        if frames > 1:
            row += (torch.arange(frames, device=z.device) * rows)[:, None, None]
        pixel = column.add_(row, alpha=cols).int()
    else:
        frame = torch.arange(frames, device=z.device)[:, None, None] * rows
        pixel = column.long() + (row.long() + frame) * cols
    observed = padded.view(-1).index_select(0, pixel.view(-1)).view(z.shape)
    valid = observed > 0
    sdf = observed.sub_(z)
    # 1 where sdf >= -truncation and the depth is valid, else 0, in float arithmetic: on a CPU, eager
    # bool tensors cost several float ops each; (sdf + truncation) * 1e30 + 1 is >= 1 or < 0
    seen = (sdf * 1e30).add_(truncation * 1e30 + 1.0).clamp_(0.0, 1.0).mul_(valid)
    return seen, torch.minimum(sdf, truncation), pixel


def fuse_blocks(
    tsdf: Tensor,
    weight: Tensor,
    color: Tensor | None,
    slots: Tensor,
    blocks: Tensor,
    local: Tensor,
    projection: Tensor,
    padded: Tensor,
    limits: Tensor,
    frame_mask: Tensor | None,
    weights: Tensor | None,
    colors: Tensor | None,
) -> None:
    """Fuse the observations of f frames, in order, into some blocks of a volume, in place: running
    weighted averages tsdf <- (W tsdf + w sdf) / (W + w), colour likewise, W <- min(W + w, cap); a
    voxel a frame does not see gets w = 0 from it, so nothing changes.

    Args:
        tsdf, weight: Float[Tensor, "s v"] the volume's values; color: Float[Tensor, "s v 3"] | None.
        slots: Int64[Tensor, "m"] the blocks' distinct slots in them; blocks, local, projection, padded:
            as `observe_blocks`.
        limits: Float[Tensor, "2"] truncation (metres) and the weight cap (inf: none).
        frame_mask: Float[Tensor, "f m"] 1 where a frame's band touches a block (None: all do).
        weights: Float[Tensor, "p"] per-pixel weights of the padded images, flattened (None = 1);
        colors: Float[Tensor, "p 3"] | None their colours.
    """
    seen, sdf, pixel = observe_blocks(blocks, local, projection, padded, limits[0])
    if frame_mask is not None:
        seen = seen * frame_mask[..., None]
    average, total = tsdf.index_select(0, slots), weight.index_select(0, slots)
    average_color = None if color is None else color.index_select(0, slots)
    for i in range(len(seen)):
        new = seen[i] if weights is None else seen[i] * weights[pixel[i]]
        share = new / (total + new).clamp_min(torch.finfo(total.dtype).tiny)  # of the new observation
        average = torch.lerp(average, sdf[i], share)
        total = torch.minimum(total + new, limits[1])
        if color is not None:
            average_color = torch.lerp(average_color, colors[pixel[i]], share[..., None])
    tsdf.index_copy_(0, slots, average)
    weight.index_copy_(0, slots, total)
    if color is not None:
        color.index_copy_(0, slots, average_color)


class CompiledOnCPU:
    """`function` compiled by torch.compile (dynamic shapes) for CPU tensors: one fused loop over the
    voxels or pixels instead of a pass over memory per operation (measured on 7-Scenes at 1 cm: the
    voxel pass 3.5x faster). torch.compile's CPU backend needs a C++ compiler: where it fails, a warning
    (once) and `function` itself, eager, which gives the same results."""

    def __init__(self, function):
        self.function, self.compiled, self.failed = function, None, False

    def __call__(self, *args):
        if not self.failed:
            self.compiled = self.compiled or torch.compile(self.function, dynamic=True)
            try:
                return self.compiled(*args)
            except torch._dynamo.exc.BackendCompilerFailed as error:
                self.failed = True
                warnings.warn(
                    f"TSDF fusion runs eager (slower): torch.compile failed for {self.function.__name__} "
                    f"({str(error).strip().splitlines()[0]}); install a C++ compiler (Debian: apt-get install g++) "
                    f"or pass TSDFVolume(compiled=False) to skip the attempt",
                    stacklevel=3,
                )
        return self.function(*args)


_COMPILED = {function: CompiledOnCPU(function) for function in (tile_box_codes, fuse_blocks)}


class TSDFVolume:
    """A truncated signed distance volume fused from depth frames (see the module docstring).

    Args:
        bounds: (2, 3) world box [[xmin, ymin, zmin], [xmax, ymax, zmax]] to reconstruct; the grid
            starts at its min corner and covers it (rounded up to whole blocks).
        voxel_size: grid spacing in metres (> 0).
        truncation: band half-width in metres (> 0); default 3 voxels. Below one voxel it warns:
            the band then misses grid points and the surface breaks up.
        device: "auto" (CUDA if available), "cpu", "cuda", or a torch.device.
        weighting: "constant" or "depth" (see WEIGHTINGS).
        max_weight: cap of the accumulated weight (a running average over the last ~max_weight
            observations, as in KinectFusion); None = no cap (the plain average of all frames).
        sparse: allocate blocks where frames observe surfaces only (rooms); dense otherwise.
        block_size: voxels per block side (>= 2).
        with_color: also average the frames' colours (frames must carry `colors`).
        free_space: metres (>= 0) by which the band's blocks reach further towards the camera than
            the truncation; there every voxel in front of the surface is observed (at +truncation).
            Default 0: the band only, as Open3D's VoxelBlockGrid. Larger values carve more free
            space (floating outliers, holes seen from afar), at a cost in speed and memory.
        max_memory: bytes the dense volume may take; default 80 % of the device's available memory.
        frames_per_pass: frames fused together in one vectorised pass over the union of their
            candidate blocks (the result is the same as one at a time, in order); default 1 on a
            CPU and 32 on a GPU, where per-pass costs dominate.
        threads: torch threads while `integrate` runs on a CPU (restored afterwards); "auto": 1 eager
            (see the module docstring: measured faster on a 2-core machine, and it keeps its speed
            when other processes are busy), torch's setting when compiled; None leaves torch's
            setting. Compiled loops keep the thread count of the process's first compiled fusion.
        compiled: on a CPU, compile the fusion with torch.compile (see the module docstring; needs a
            C++ compiler, else a warning and eager fusion); None: for `integrate` calls of at least
            _COMPILE_PIXELS depth pixels, where compilation pays for itself. No effect on a GPU.
    """

    def __init__(
        self,
        bounds,
        voxel_size: float,
        truncation: float | None = None,
        device="auto",
        weighting: str = "constant",
        max_weight: float | None = None,
        sparse: bool = False,
        block_size: int = 8,
        with_color: bool = False,
        free_space: float = 0.0,
        max_memory: int | None = None,
        frames_per_pass: int | None = None,
        threads: int | str | None = "auto",
        compiled: bool | None = None,
    ):
        box = as_bounds(bounds)
        voxel_size = _positive(voxel_size, "voxel_size", "a length in metres")
        truncation = (
            3.0 * voxel_size
            if truncation is None
            else _positive(truncation, "truncation", "a length in metres")
        )
        if truncation < voxel_size:
            warnings.warn(
                f"truncation {truncation:g} is smaller than a voxel ({voxel_size:g}): grid points on one side "
                f"of the surface are often not updated and the mesh gets holes; use 2 to 5 voxels",
                stacklevel=2,
            )
        if not (isinstance(free_space, numbers.Real) and math.isfinite(free_space) and free_space >= 0):
            raise ConfigError(f"free_space must be a length >= 0 in metres (0: the band only), got {free_space!r}")
        free_space = float(free_space)
        max_weight = (
            None
            if max_weight is None
            else _positive(max_weight, "max_weight", "a weight, or None for no cap")
        )
        if weighting not in WEIGHTINGS:
            raise ConfigError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}")
        if not (isinstance(block_size, (int, np.integer)) and block_size >= 2):
            raise ConfigError(
                f"block_size must be an integer >= 2 (voxels per block side), got {block_size!r}"
            )
        self.device = resolve_device(device)
        self.bounds = torch.as_tensor(box)
        self.origin = box[0].copy()
        self.voxel_size, self.truncation, self.free_space = voxel_size, truncation, free_space
        self.weighting, self.max_weight = weighting, max_weight
        self.sparse, self.block_size, self.with_color = bool(sparse), int(block_size), bool(with_color)
        kind = "cuda" if self.device.type == "cuda" else "cpu"
        frames_per_pass = _FRAMES_PER_PASS[kind] if frames_per_pass is None else frames_per_pass
        if not (isinstance(frames_per_pass, (int, np.integer)) and frames_per_pass >= 1):
            raise ConfigError(f"frames_per_pass must be an integer >= 1, got {frames_per_pass!r}")
        self.frames_per_pass = int(frames_per_pass)
        if not (threads in (None, "auto") or (isinstance(threads, (int, np.integer)) and threads >= 1)):
            raise ConfigError(
                f"threads must be an integer >= 1, 'auto', or None to keep torch's setting; got {threads!r}"
            )
        self.threads = threads if threads in (None, "auto") else int(threads)
        if compiled not in (None, True, False):
            raise ConfigError(f"compiled must be True, False or None (compile long integrations), got {compiled!r}")
        self.compiled = compiled
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
        self._tsdf = torch.zeros(capacity, voxels, device=self.device)
        self._weight = torch.zeros(capacity, voxels, device=self.device)
        self._color = torch.zeros(capacity, voxels, 3, device=self.device) if self.with_color else None

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
        if needed > len(self._tsdf):
            capacity = max(needed, int(len(self._tsdf) * 1.5))
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

    def _block_coords(self, keys: Tensor) -> Tensor:
        """Int64[Tensor, "b"] linear block keys -> Int64[Tensor, "b 3"] block coordinates."""
        ny, nz = int(self.block_counts[1]), int(self.block_counts[2])
        return torch.stack([keys // (ny * nz), (keys // nz) % ny, keys % nz], -1)

    # ------------------------------------------------------------------------------ integration

    def integrate(self, frames: DepthFrames, progress: bool = True) -> TSDFVolume:
        """Fuse every frame of `frames` (any number, one after the other); returns the volume.
        `progress`: a bar over the frames when fusion lasts more than a few seconds (False: none)."""
        from neuralsurf.progress import progress_bar

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
        compiled = cpu and (depth.numel() >= _COMPILE_PIXELS if self.compiled is None else self.compiled)
        workers = 1
        if cpu and not compiled:  # eager: chunks on `workers` threads, each torch op on one
            workers = torch.get_num_threads() if self.threads in (None, "auto") else self.threads
            threads = 1
        else:
            threads = None if self.threads == "auto" else self.threads
        with torch_threads(threads if cpu else None), ThreadPoolExecutor(workers) as pool:
            self._integrate_all(frames, depth, colors, bar, compiled, pool if workers > 1 else None)
        bar.close()
        return self

    def _integrate_all(
        self, frames: DepthFrames, depth: Tensor, colors: Tensor | None, bar, compiled: bool, pool: Executor | None
    ) -> None:
        """The passes of `integrate` over depth Float[Tensor, "n h w"] and colours (on the device),
        compiled or eager; with a `pool`, a pass's candidate blocks are found while the pass before fuses."""
        passes = [slice(start, start + self.frames_per_pass) for start in range(0, len(frames), self.frames_per_pass)]
        candidates = lambda part: self._candidates(
            depth[part], frames.K[part].cpu(), frames.cam_to_world[part].cpu(), compiled
        )
        upcoming = None
        for i, part in enumerate(passes):
            blocks = candidates(part) if upcoming is None else upcoming.result()
            upcoming = None if pool is None or i + 1 == len(passes) else pool.submit(candidates, passes[i + 1])
            self._integrate_frames(
                depth[part],
                frames.K[part].cpu(),
                frames.cam_to_world[part].cpu(),
                None if colors is None else colors[part],
                compiled,
                blocks,
                pool,
            )
            self.frames_integrated += len(depth[part])
            bar.update(len(depth[part]))

    def _candidates(self, depth: Tensor, K: Tensor, cam_to_world: Tensor, compiled: bool) -> tuple[Tensor, Tensor | None]:
        """`candidate_blocks` of depth images Float[Tensor, "f h w"] seen by K Float[Tensor, "f 3 3"] at
        cam_to_world Float[Tensor, "f 4 4"] (both on the CPU)."""
        origin = torch.as_tensor(self.origin, dtype=torch.float64)
        rotation, translation = camera_to_grid(cam_to_world, origin, self.voxel_size)
        to = lambda t: t.to(self.device, depth.dtype)
        return candidate_blocks(
            depth, to(K), to(rotation), to(translation), self.truncation, self.free_space, self.block_size,
            self.block_counts, _COMPILED[tile_box_codes] if compiled else tile_box_codes,
            _TILE["compiled" if compiled else "eager"],
        )

    def _integrate_frames(
        self, depth: Tensor, K: Tensor, cam_to_world: Tensor, colors: Tensor | None, compiled: bool,
        blocks: tuple[Tensor, Tensor | None], pool: Executor | None,
    ) -> None:
        """Fuse depth images Float[Tensor, "f h w"] seen by K Float[Tensor, "f 3 3"] at cam_to_world
        Float[Tensor, "f 4 4"] (both on the CPU), colours Float[Tensor, "f h w 3"] | None, in order, into
        their candidate `blocks` (`_candidates`); `compiled`: through `_COMPILED` (CPU); with a `pool`,
        chunks of blocks side by side on its threads."""
        origin = torch.as_tensor(self.origin, dtype=torch.float64)
        run = lambda function: _COMPILED[function] if compiled else function
        keys, frame_keys = blocks
        slots = self._slots_of(keys)
        if self.sparse:  # allocate the blocks these frames touch for the first time
            fresh = slots < 0
            if fresh.any():
                slots[fresh] = self._allocate(keys[fresh])
        projection = grid_to_pixel(K, cam_to_world, origin, self.voxel_size).to(self.device)
        n_frames, voxels, total = len(depth), self.block_size**3, int(self.block_counts.prod())
        padded = pad_image(depth)
        weights = None if self.weighting == "constant" else pad_image(pixel_weights(depth, self.weighting))
        weights = None if weights is None else weights.reshape(-1)
        colors = None if colors is None else pad_image(colors).reshape(-1, 3)
        cap = math.inf if self.max_weight is None else self.max_weight
        limits = torch.tensor([self.truncation, cap], dtype=depth.dtype, device=self.device)
        fuse = run(fuse_blocks)
        chunk_observations = _CHUNK_OBSERVATIONS["compiled"] if compiled else self._chunk_observations
        per_chunk = max(1, chunk_observations // (voxels * n_frames))

        def fuse_chunk(start: int) -> None:
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

        starts = range(0, len(keys), per_chunk)
        if pool is None or len(starts) == 1:
            for start in starts:
                fuse_chunk(start)
        else:  # chunks hold distinct blocks: they can run side by side
            list(pool.map(fuse_chunk, starts))

    # ------------------------------------------------------------------------------ save / load

    def save(self, path) -> Path:
        """Write the volume (settings and fused voxels) to `path` as a compressed .npz, atomically (a
        temporary file in the same folder, then a rename): an interrupted save leaves any earlier
        file intact. Only numbers and strings are stored, so `load` needs no pickle.

        Returns the Path written (`path` itself; an extension other than .npz is kept as given).
        """
        path = Path(path)
        if path.is_dir():
            raise FileFormatError(f"cannot save the TSDF volume to {str(path)!r}: it is a folder; pass a file name")
        used = self._used
        arrays = {
            "format": np.array(TSDF_FORMAT),
            "bounds": self.bounds.cpu().numpy().astype(np.float64),
            "voxel_size": np.float64(self.voxel_size),
            "truncation": np.float64(self.truncation),
            "free_space": np.float64(self.free_space),
            "weighting": np.array(self.weighting),
            "max_weight": np.float64(np.nan if self.max_weight is None else self.max_weight),
            "sparse": np.bool_(self.sparse),
            "block_size": np.int64(self.block_size),
            "with_color": np.bool_(self.with_color),
            "frames_integrated": np.int64(self.frames_integrated),
            "tsdf": self._tsdf[:used].cpu().numpy(),
            "weight": self._weight[:used].cpu().numpy(),
        }
        if self._color is not None:
            arrays["color"] = self._color[:used].cpu().numpy()
        if self.sparse:
            arrays["keys"], arrays["slots"] = self._keys.cpu().numpy(), self._slots.cpu().numpy()
        write_npz(path, arrays, compressed=True)
        return path

    @classmethod
    def load(cls, path, device="auto", frames_per_pass: int | None = None) -> TSDFVolume:
        """A volume written by `save`, on `device`, ready to `integrate` more frames or `extract_mesh`.

        Read with `numpy.load(allow_pickle=False)`: a file holding anything but plain arrays is refused.
        Raises FileFormatError for a missing, truncated or foreign file (naming it).
        """
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
        volume = cls(
            arrays["bounds"], float(arrays["voxel_size"]), float(arrays["truncation"]), device=device,
            weighting=str(arrays["weighting"]), max_weight=None if math.isnan(max_weight) else max_weight,
            sparse=bool(arrays["sparse"]), block_size=int(arrays["block_size"]),
            with_color=bool(arrays["with_color"]), free_space=float(arrays["free_space"]),
            frames_per_pass=frames_per_pass,
        )
        voxels = volume.block_size**3
        used = len(arrays["tsdf"])
        expected = {"tsdf": (used, voxels), "weight": (used, voxels)}
        if volume.with_color:
            expected["color"] = (used, voxels, 3)
        if volume.sparse:
            expected["keys"] = expected["slots"] = (used,)
        else:
            expected["tsdf"] = expected["weight"] = (len(volume._tsdf), voxels)
            if volume.with_color:
                expected["color"] = (len(volume._tsdf), voxels, 3)
        for key, shape in expected.items():
            if key not in arrays or arrays[key].shape != shape:
                raise FileFormatError(
                    f"{str(path)!r}: {key} has shape {None if key not in arrays else arrays[key].shape}, expected "
                    f"{shape} for its settings; the file is damaged"
                )
        to = lambda key, dtype: torch.from_numpy(np.ascontiguousarray(arrays[key])).to(volume.device, dtype)
        volume._tsdf, volume._weight = to("tsdf", torch.float32), to("weight", torch.float32)
        volume._color = to("color", torch.float32) if volume.with_color else None
        volume._used = used
        if volume.sparse:
            volume._keys, volume._slots = to("keys", torch.int64), to("slots", torch.int64)
        volume.frames_integrated = int(arrays["frames_integrated"])
        return volume

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

    def _block_tiles(self, keys: Tensor, tsdf: Tensor, weight: Tensor) -> tuple[Tensor, Tensor, tuple[int, int, int]]:
        """The grid points of some blocks with a margin, one cube per block, packed side by side.

        A block's cube holds its points from one before its first to two after its last along each axis
        (side S = B + 3): its own cells and, for every point of them, the six neighbours (`off_level`).
        Args: keys Int64[Tensor, "m"] block keys; tsdf, weight: Float[Tensor, "(used + 1) B^3"] the stored
        blocks and a last one of zeros (where absent blocks read). Returns tsdf Float[Tensor, "aS bS cS"]
        and valid Bool[Tensor, "aS bS cS"] (observed), block i's cube at tile (i // (b c), i // c % b,
        i % c), and (a, b, c).
        """
        size, side, absent = self.block_size, self.block_size + 3, len(tsdf) - 1
        a = b = max(1, round(len(keys) ** (1 / 3)))
        c = -(-len(keys) // (a * b))
        shifts = torch.stack(torch.meshgrid(*[torch.arange(-1, 2, device=self.device)] * 3, indexing="ij"), -1)
        slots = self._slots_of(self._keys_around(keys, shifts.reshape(27, 3)))  # (m, 27)
        slots = torch.cat([slots.masked_fill_(slots < 0, absent), slots.new_full((a * b * c - len(keys), 27), absent)])
        step = torch.arange(side, device=self.device) - 1
        near, within = step.div(size, rounding_mode="floor") + 1, step % size  # neighbour 0..2, voxel in it
        neighbour = (near[:, None, None] * 9 + near[None, :, None] * 3 + near[None, None, :]).view(-1)
        voxel = ((within[:, None, None] * size + within[None, :, None]) * size + within[None, None, :]).view(-1)
        index = torch.add(voxel, slots[:, neighbour], alpha=size**3)  # (tiles, S^3)
        packed = lambda t: t.view(a, b, c, side, side, side).permute(0, 3, 1, 4, 2, 5).reshape(a * side, b * side, c * side)
        return packed(tsdf.view(-1)[index]), packed(weight.view(-1)[index] > 0), (a, b, c)

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
        the seven blocks after them), _MESH_BLOCKS at a time, are packed as cubes side by side
        (`_block_tiles`) and meshed by `neuralsurf.extract.level_set`, each cube's own cells only and
        cells with an unobserved corner skipped. A vertex on a block's face is found from the same values
        in each block that shares it; vertices are merged by the grid edge they lie on, so the mesh has
        no seams between blocks."""
        if self.frames_integrated == 0:
            raise ExtractionError("the TSDF volume is empty: call integrate(frames) before extract_mesh()")
        threads = (1 if self.threads == "auto" else self.threads) if self.device.type == "cpu" else None
        with torch_threads(threads):
            return self._extract_mesh()

    def _extract_mesh(self) -> Mesh:
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
        zero = tsdf.new_zeros(1, tsdf.shape[1])
        tsdf, weight = torch.cat([tsdf, zero]), torch.cat([weight, zero])
        size, side = self.block_size, self.block_size + 3
        own = torch.zeros(side, dtype=torch.bool)
        own[1 : size + 1] = True  # a cube's own cells: first corners at its block's voxels
        own = own[:, None, None] & own[None, :, None] & own[None, None, :]
        points, faces, count = [], [], 0
        for part in keys.split(_MESH_BLOCKS):
            values, valid, (a, b, c) = self._block_tiles(part, tsdf, weight)
            cells = own.repeat(a, b, c)[:-1, :-1, :-1].numpy()
            vertices, triangles = level_set(values.cpu().numpy(), 0.0, valid.cpu().numpy(), cells)
            tile = np.floor(vertices / side).astype(np.int64)
            block = self._block_coords(part).cpu().numpy()[(tile[:, 0] * b + tile[:, 1]) * c + tile[:, 2]]
            points.append(block * size - 1 + (vertices.astype(np.float64) - tile * side))
            faces.append(triangles + count)
            count += len(vertices)
        if not count:
            raise ExtractionError(
                "the fused TSDF has no zero crossing between observed voxels: the frames see no surface with "
                "both sides inside the truncation band; check the truncation (a few voxels) and the poses"
            )
        points, faces = _merge_by_edge(np.concatenate(points), np.concatenate(faces), self.grid_shape)
        vertices = torch.from_numpy((self.origin + points * self.voxel_size).astype(np.float32))
        colors = self._color_at(points) if self.with_color else None
        return Mesh(vertices, torch.from_numpy(faces), colors)


def _merge_by_edge(points: np.ndarray, faces: np.ndarray, shape) -> tuple[np.ndarray, np.ndarray]:
    """Merge the vertices that lie on the same grid edge (or grid point).

    A marching-cubes vertex lies on a grid edge, at least _OFF_POINT from its ends unless on a grid
    point (`off_level` keeps values off the level by 1e-4 of their differences), so its edge is the
    lower point of the one non-integral coordinate; a few lie inside a cell (Lewiner's ambiguous cases)
    and stay apart.
    Args: points Float64[ndarray, "v 3"] grid units; faces Int[ndarray, "f 3"]; shape: grid points per axis.
    Returns: the merged points and renumbered faces, without faces that lost a corner."""
    nearest = np.round(points)
    off = np.abs(points - nearest)
    axis = off.argmax(1)
    on_point = off.max(1) < _OFF_POINT
    lower = nearest.astype(np.int64)
    rows = np.arange(len(points))
    lower[rows, axis] = np.where(on_point, lower[rows, axis], np.floor(points[rows, axis]).astype(np.int64))
    linear = np.ravel_multi_index(tuple(lower.T), tuple(int(n) for n in shape), mode="clip")
    key = linear * 4 + np.where(on_point, 3, axis)
    inner = (off >= _OFF_POINT).sum(1) > 1  # a vertex inside a cell (an ambiguous case's): never merged
    key[inner] = -1 - rows[inner]
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    faces = inverse.reshape(-1)[faces]
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])]
    return points[first], faces


__all__ = [
    "WEIGHTINGS",
    "TSDFVolume",
    "available_memory",
    "box_keys",
    "camera_to_grid",
    "candidate_blocks",
    "depth_bounds",
    "grid_to_pixel",
    "observe_blocks",
    "pad_image",
    "pixel_weights",
    "world_to_camera",
]
