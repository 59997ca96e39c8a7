"""The small models of the tests' fits (importable: pytest puts tests/ on sys.path)."""

from __future__ import annotations

import torch

from neuralsurf.models import SDFMLP, HashGrid


def tiny_model(width: int = 32, depth: int = 3, levels: int = 3, log2_table_size: int = 12, max_resolution: int = 32,
               seed: int = 0) -> SDFMLP:
    """A small SDFMLP (no skips, no weight norm) for fits of seconds, its weights drawn with `seed`: over a
    hash grid of `levels` levels up to `max_resolution`, or over the raw coordinates with `levels=0`."""
    torch.manual_seed(seed)
    encoding = HashGrid(levels=levels, log2_table_size=log2_table_size, max_resolution=max_resolution) if levels else None
    return SDFMLP(width=width, depth=depth, skip_layers=(), weight_norm=False, encoding=encoding)
