"""Which blocks of a TSDF grid the truncation bands of depth frames touch (`candidate_blocks`).

A frame updates the voxels of the blocks that the segment z in [d - truncation - free_space,
d + truncation] of some valid pixel's footprint meets (depth d), as Open3D's VoxelBlockGrid does with
[d - truncation, d + truncation]. They are found from the exact boxes of small image tiles: along each
axis a point of a tile's piece of the band is z times an affine function of (u, v) plus a constant, so
its extremes lie at the footprint's corners and at the two ends of z.
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

_MAX_KEYS = 1 << 24
"""Candidate block keys enumerated at a time (bounds memory when boxes are large)."""
_BITMAP_LIMIT = 1 << 27
"""Candidate blocks are deduplicated in a bitmap over all blocks up to this many blocks, else sorted."""

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


TILE = {"compiled": 1, "eager": 4}
"""Pixels per side of the tiles that `candidate_blocks` boxes. Measured on 7-Scenes at 1 cm (one frame:
tiles of 1 pixel give 2,737 blocks, of 2 pixels 2,782, of 4 pixels 2,826; on 50 frames, eager fusion
took 23.4, 20.5 and 28.6 ms of CPU a frame with tiles of 2, 4 and 8 pixels): compiled, single pixels (a
fused loop; their boxes never need `box_keys`); eager, 4 x 4 tiles."""
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
    tile: int = TILE["eager"],
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
        block_counts: Int[Tensor, "3"] blocks per axis; tile: see TILE.
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


def candidates_by_pass(
    keys: Tensor, frame_keys: Tensor | None, frames: int, per_pass: int, total: int
) -> list[tuple[Tensor, Tensor | None]]:
    """`candidate_blocks`' (keys, frame_keys) of some frames -> the same for each pass of `per_pass`
    consecutive frames of them (the last pass may hold fewer); `total`: blocks in the volume."""
    if frame_keys is None:  # one frame
        return [(keys, None)]
    starts = torch.arange(0, frames + per_pass, per_pass).clamp_max(frames)
    bounds = torch.searchsorted(frame_keys, (starts * total).to(frame_keys.device)).tolist()
    passes = []
    for first, (low, high) in enumerate(zip(bounds[:-1], bounds[1:])):
        own = frame_keys[low:high] - int(starts[first]) * total  # frame_keys of this pass's frames
        single = int(starts[first + 1] - starts[first]) == 1
        passes.append((own, None) if single else (_unique_keys(own % total, total), own))
    return passes


__all__ = ["box_keys", "candidate_blocks", "candidates_by_pass", "tile_block_ranges", "tile_box_codes"]
