"""Shared test set-up: a persistent XLA compilation cache, and a user-written effect, written
exactly as the documentation shows.

The suite's time is mostly XLA compiling, and many tests compile the same programs
(the loop's screens of one-minute datasets, fits of the same shapes) in different
test files and worker processes.  A compilation cache on disk, shared by the workers
(``.jax-cache/`` at the top of the repository, not committed; ``JAX_COMPILATION_CACHE_DIR``
overrides it), compiles each once.  It holds compiled code only, keyed by the program,
the JAX version and the machine: results are the same with or without it.

Registering the effect here puts it in the registry before the tests are collected,
so the registry-driven checks of ``test_effects.py`` apply to it as to every
built-in effect.
"""

import dataclasses
import os
from pathlib import Path

os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".jax-cache"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES", "0")

import jax  # noqa: E402

jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"])
jax.config.update("jax_persistent_cache_min_compile_time_secs", float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))
jax.config.update("jax_persistent_cache_min_entry_size_bytes", int(os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"]))

from quadshank import Effect, Param, register_effect  # noqa: E402


@register_effect
@dataclasses.dataclass(frozen=True)
class CubicTorqueAngle(Effect):
    kind = "gain"
    name = "cubic_torque_angle"
    params = (Param("c3", "1/deg^3", prior=("normal", 0.0, 1e-6)),)
    c3: float = 0.0

    def factor(self, ctx):
        return 1.0 + self.c3 * ctx.angle**3


import pytest  # noqa: E402


@pytest.fixture
def scratch_registry(monkeypatch):
    """Effects registered inside a test stay inside it (the loop's tests screen every registered candidate)."""
    from quadshank import _effects

    monkeypatch.setattr(_effects, "_REGISTRY", dict(_effects._REGISTRY))


#: Test files by their time in a profile of the suite (``pytest --durations``), longest first.
#: ``--dist loadfile`` hands whole files to the two workers in collection order, so the
#: long ones start at once and the short ones fill in behind them.
LONGEST_FIRST = (
    "test_loop_none.py",
    "test_loop_cli.py",
    "test_effects.py",
    "test_notebooks.py",
    "test_fit.py",
    "test_cli.py",
    "test_posterior_eval.py",
    "test_loop.py",
    "test_recovery.py",
    "test_report.py",
)


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: order within a file kept
