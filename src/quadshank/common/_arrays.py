"""Small array helpers that several stages share."""

from __future__ import annotations

import numpy as np

__all__ = ["stretches", "is_whole_number"]


def stretches(mask) -> list[tuple[int, int]]:
    """The runs of True in the boolean array ``mask``, as ``[start, stop)`` index pairs in order."""
    edges = np.diff(np.concatenate([[0], np.asarray(mask, dtype=np.int8), [0]]))
    return [(int(a), int(b)) for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1))]


def is_whole_number(value) -> bool:
    """Whether ``value`` is an integer (Python or NumPy), not a bool, a float or a string of digits:
    what a count, a trial number or a seed must be."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
