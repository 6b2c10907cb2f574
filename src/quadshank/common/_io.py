"""Atomic file output: a file is either complete or absent, never half-written."""

from __future__ import annotations

import contextlib
import functools
import io
import json
import math
import os
import re
import tempfile
import unicodedata
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np


@functools.cache
def file_mode() -> int:
    """Permissions of a written file: mkstemp makes it 0600, but a result is read by others, so
    it gets 0666 less the process's umask (read once, at the first write; reading the umask
    means setting it)."""
    umask = os.umask(0)
    os.umask(umask)
    return 0o666 & ~umask


def temp_sibling(path: Path) -> Path:
    """An empty hidden file beside ``path`` (same folder, so renaming it onto ``path`` is
    atomic), with the permissions of a file written the usual way."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    os.chmod(tmp, file_mode())
    return Path(tmp)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path to write ``path``'s content to; when the block ends it is
    renamed onto ``path``, and on any error (an interrupt included) it is removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_sibling(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically: complete or absent, never half-written."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


#: Longest stem :func:`file_stem` gives: file systems take 255 bytes a name, and a stem is one
#: part of a name (``recording_STEM_trial12.png``, a temporary file's prefix and suffix).
FILE_STEM_MAX = 80


def file_stem(name: str, empty: str = "_") -> str:
    """``name`` as a portable file-name stem: ASCII letters (accents dropped: Müller → Muller),
    digits and ``._-``, any other character ``_`` (a path's ``/`` too), no leading dot, at most
    :data:`FILE_STEM_MAX` characters; ``empty`` where nothing is left."""
    letters = "".join(unicodedata.normalize("NFKD", ch).encode("ascii", "ignore").decode() or "_" for ch in name)
    return re.sub(r"[^A-Za-z0-9._-]", "_", letters).lstrip(".")[:FILE_STEM_MAX] or empty


def file_stems(names) -> dict[str, str]:
    """A :func:`file_stem` for each of ``names``, distinct even on a case-insensitive file system
    (``-2``, ``-3`` … where two would meet), so that no leg's or subject's files overwrite
    another's."""
    out, taken = {}, set()
    for name in names:
        base = file_stem(name)
        stem, k = base, 2
        while stem.lower() in taken:
            stem, k = f"{base}-{k}", k + 1
        taken.add(stem.lower())
        out[name] = stem
    return out


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if hasattr(o, "__array__"):  # a JAX array
        return _json_default(np.asarray(o))
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _strict(o):
    """``o`` with every number that is not finite (NaN, ±inf) as None: JSON has no such
    numbers, and strict readers (JavaScript, R's jsonlite) refuse Python's ``NaN``."""
    if isinstance(o, float):  # numpy's float64 too
        return o if math.isfinite(o) else None
    if isinstance(o, dict):
        return {k: _strict(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_strict(v) for v in o]
    if isinstance(o, (np.generic, np.ndarray)) or hasattr(o, "__array__"):
        return _strict(_json_default(o))
    return o


def nulls_as_nan(tree):
    """The inverse of writing a number that is not finite as null, for a tree read back whose
    leaves are all numbers (J's bands, a model's parameters): every None becomes NaN."""
    if tree is None:
        return math.nan
    if isinstance(tree, dict):
        return {k: nulls_as_nan(v) for k, v in tree.items()}
    if isinstance(tree, list):
        return [nulls_as_nan(v) for v in tree]
    return tree


def write_json(path: str | os.PathLike, obj) -> Path:
    """Write ``obj`` as indented, strict JSON atomically (numpy and JAX arrays as lists; a number
    that is not finite, such as R-hat of one chain, as ``null``)."""
    return atomic_write_text(path, json.dumps(_strict(obj), indent=2, allow_nan=False, default=_json_default) + "\n")


def read_json(path: str | os.PathLike):
    """Read a JSON file; a missing or malformed file raises an error that names it."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: file not found") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None


def figure_bytes(fig, fmt: str = "png", dpi: int = 110, tight: bool = True) -> bytes:
    """A matplotlib figure rendered (``tight``: cropped to its content) and closed."""

    buf = io.BytesIO()
    fig.savefig(buf, format=fmt, dpi=dpi, bbox_inches="tight" if tight else None)
    plt.close(fig)
    return buf.getvalue()


def save_figure(fig, path: str | os.PathLike, dpi: int = 110, tight: bool = True) -> Path:
    """Save a matplotlib figure atomically and close it."""
    return atomic_write_bytes(path, figure_bytes(fig, Path(path).suffix.lstrip(".") or "png", dpi, tight))
