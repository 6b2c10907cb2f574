"""Progress bars for long steps (tqdm on stderr), silenced by ``enabled=False``."""

from __future__ import annotations

import sys
from collections.abc import Iterable

from tqdm.auto import tqdm


def progress_bar(iterable: Iterable, *, desc: str, enabled: bool = True, total: int | None = None):
    """Wrap ``iterable`` in a progress bar when ``enabled``; otherwise return it unchanged."""
    if not enabled:
        return iterable

    return tqdm(iterable, desc=desc, total=total, file=sys.stderr, leave=False, dynamic_ncols=True)
