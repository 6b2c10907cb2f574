"""Shared test set-up: a user-written effect, written exactly as the documentation shows.

Registering it here puts it in the registry before the tests are collected, so
the registry-driven checks of ``test_effects.py`` apply to it as to every
built-in effect.
"""

import dataclasses
import os
import shutil
import tempfile

from quadshank import Effect, Param, register_effect


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
    from quadshank.model import _effects as _effects
    monkeypatch.setattr(_effects, "_REGISTRY", dict(_effects._REGISTRY))


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop JAX's compiled programs after each test file.  Every program XLA compiles for the CPU
    holds a few memory mappings until it is dropped: one file of fits leaves about 10 000, and a
    worker that runs many such files reaches the kernel's limit on a process's mappings
    (vm.max_map_count, 65 530 by default), where the next compilation crashes the worker."""
    yield
    import gc

    import jax

    jax.clear_caches()
    gc.collect()


#: Test files by their time in a profile of the suite (``pytest --durations``), longest first.
#: ``--dist loadfile`` with ``--no-loadscope-reorder`` (the Makefile's) hands whole files to the
#: two workers in collection order, so the long ones start at once and the short ones fill in
#: behind them; without that flag xdist orders the files by their number of tests instead.
LONGEST_FIRST = (
    "test_loop_none.py",
    "test_loop.py",
    "test_loop_cli.py",
    "test_effects.py",
    "test_notebooks.py",
    "test_fit.py",
    "test_cli.py",
    "test_posterior_eval.py",
    "test_recovery.py",
    "test_report.py",
    "test_user_effects.py",
    "test_sampling_period.py",
    "test_trains.py",
    "test_pendulum.py",
)


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: order within a file kept


#: Programs that took at least this long to compile [s] are kept in the run's compilation cache.
XLA_CACHE_MIN_COMPILE_S = "0.2"


def pytest_configure(config):
    """One persistent XLA compilation cache for the whole run, shared by both workers, every test
    file and the command-line subprocesses: a program that one test compiled (the same model on
    data of the same shape, under a new closure or in another process) is loaded, not compiled
    again.  Compilation is most of the suite's time.  The cache starts empty in a temporary
    folder (a run never inherits another's) and is removed at the end; a cache the caller set
    (``JAX_COMPILATION_CACHE_DIR``) is used as it is."""
    if hasattr(config, "workerinput") or os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return  # a worker: its environment, the cache included, is the controller's
    folder = tempfile.mkdtemp(prefix="quadshank-xla-cache-")
    config.stash[_CACHE] = folder
    os.environ["JAX_COMPILATION_CACHE_DIR"] = folder  # read by workers and subprocesses at import
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = XLA_CACHE_MIN_COMPILE_S
    os.environ["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "-1"
    import jax  # already imported here (the effect above): without workers, this process compiles

    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(XLA_CACHE_MIN_COMPILE_S))
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)


def pytest_unconfigure(config):
    folder = config.stash.get(_CACHE, None)
    if folder:
        shutil.rmtree(folder, ignore_errors=True)


_CACHE = pytest.StashKey[str]()
