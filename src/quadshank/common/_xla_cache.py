"""A compilation cache on disk for the command line: XLA programs that one command compiled are
loaded by the next, instead of compiled again.

Most of a short command's time is XLA compiling its programs; a user who fits, diagnoses and
evaluates the same data, or reruns ``discover`` after writing an effect, compiles the same
programs again and again.  JAX keeps compiled programs on disk where asked
(``jax_compilation_cache_dir``), keyed by the program, the compiler's options and the jax
version, so a program is only reused where it is exactly the same.  The command line asks for
it; the Python API leaves JAX's settings to the caller.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["use_compilation_cache", "CACHE_ENV", "MAX_CACHE_BYTES", "MIN_COMPILE_S"]

#: ``QUADSHANK_XLA_CACHE``: a folder for the cache, or ``off`` for none.
CACHE_ENV = "QUADSHANK_XLA_CACHE"
#: The cache's size on disk; the programs used longest ago are dropped first.
MAX_CACHE_BYTES = 2 * 1024**3
#: Programs that compile faster than this [s] are not kept.  Every program is: a command compiles
#: hundreds of small ones (operations run outside a jitted function, numpyro's set-up), 20–50 ms
#: each, several seconds in all that a rerun would otherwise compile again (``bench_cache``).
MIN_COMPILE_S = 0.0


def default_folder() -> Path:
    """``$XDG_CACHE_HOME/quadshank/xla``, or ``~/.cache/quadshank/xla``."""
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "quadshank" / "xla"


def use_compilation_cache() -> Path | None:
    """Keep compiled programs in the cache folder (:data:`CACHE_ENV`, else :func:`default_folder`);
    returns it, or ``None`` where the cache is off, or the folder cannot be made.  A cache the
    caller already chose (``JAX_COMPILATION_CACHE_DIR``, or ``jax.config``) is left as it is."""
    import jax

    setting = os.environ.get(CACHE_ENV, "").strip()
    if setting.lower() in ("off", "0", "no", "false"):
        return None
    chosen = jax.config.jax_compilation_cache_dir
    if chosen:
        return Path(chosen)
    folder = Path(setting).expanduser() if setting else default_folder()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:  # a read-only home, say: the commands work without the cache, only slower
        return None
    jax.config.update("jax_compilation_cache_dir", str(folder))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_S)
    try:
        import filelock  # noqa: F401 - JAX bounds the cache's size only with it; without, the cache works unbounded
    except ImportError:
        pass
    else:
        jax.config.update("jax_compilation_cache_max_size", MAX_CACHE_BYTES)
    return folder
