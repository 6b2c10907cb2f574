"""Small array helpers that several stages share."""

from __future__ import annotations

import numpy as np

__all__ = ["stretches"]


def stretches(mask) -> list[tuple[int, int]]:
    """The runs of True in the boolean array ``mask``, as ``[start, stop)`` index pairs in order."""
    edges = np.diff(np.concatenate([[0], np.asarray(mask, dtype=np.int8), [0]]))
    return [(int(a), int(b)) for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1))]
