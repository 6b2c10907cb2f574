"""Random streams: every draw a command makes comes from its one root seed, split by purpose.

A stream is named (``"hyperparameters"``, ``"delays"``, …, with integers for legs or
draws where needed), so two purposes never share draws and adding a stream changes no
other: NumPy's ``SeedSequence(seed, spawn_key=…)`` and JAX's ``fold_in`` of the root key.
"""

from __future__ import annotations

import zlib

import jax
import numpy as np

__all__ = ["numpy_rng", "jax_key"]


def _part(name: str | int) -> int:
    return zlib.crc32(name.encode()) if isinstance(name, str) else int(name)


def numpy_rng(seed: int, *stream: str | int) -> np.random.Generator:
    """A NumPy generator for the stream ``stream`` of the root ``seed``."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=tuple(_part(s) for s in stream)))


def jax_key(seed: int, *stream: str | int) -> jax.Array:
    """A JAX key for the stream ``stream`` of the root ``seed`` (its key folded with each part)."""
    key = jax.random.PRNGKey(int(seed))
    for s in stream:
        key = jax.random.fold_in(key, _part(s))
    return key
