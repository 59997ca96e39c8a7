"""Progress bars for the steps a user waits on (loading, fusion, registration, extraction).

One helper, so that every bar behaves the same: it shows only after `DELAY_S` seconds (short steps
stay silent), disappears when done (`leave=False`), and is off when the caller passes
`enabled=False` or the environment sets NEURALSURF_PROGRESS=0 (the test suite does).
"""

from __future__ import annotations

import os
from collections.abc import Iterable

DELAY_S = 2.0
"""Seconds before a bar appears: steps shorter than this print nothing."""


def progress_enabled(enabled: bool = True) -> bool:
    """`enabled`, unless the environment variable NEURALSURF_PROGRESS is "0"."""
    return bool(enabled) and os.environ.get("NEURALSURF_PROGRESS", "1") != "0"


def progress_bar(iterable: Iterable | None = None, *, desc: str, total: int | None = None, unit: str = "it",
                 enabled: bool = True, initial: int = 0, unit_scale: bool = False):
    """A tqdm bar over `iterable` (or a manual one of `total` steps: call `.update(n)`), on stderr;
    `initial` steps already done (a resumed download), `unit_scale` for bytes (k, M, G)."""
    from tqdm.auto import tqdm

    return tqdm(iterable, desc=desc, total=total, unit=unit, disable=not progress_enabled(enabled),
                delay=DELAY_S, leave=False, dynamic_ncols=True, initial=initial, unit_scale=unit_scale)
