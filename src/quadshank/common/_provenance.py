"""Which code made a result: the package's version and a fingerprint of its source."""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path

__version__ = "0.1.0"


@functools.cache
def code_fingerprint() -> str:
    """The first 16 hex digits of a SHA-256 over the package's Python source (file names and
    contents, in name order).  Two fits with the same fingerprint were made by the same code;
    the version number alone does not change between commits."""
    h = hashlib.sha256()
    root = Path(__file__).resolve().parents[1]
    for path in sorted(root.rglob("*.py")):
        h.update(path.relative_to(root).as_posix().encode())
        h.update(b"\0")
        h.update(path.read_bytes())
        h.update(b"\0")
    return h.hexdigest()[:16]


def code_provenance() -> dict:
    """``{"version": …, "fingerprint": …}`` as a fit's summary.json records it under ``code``."""
    return {"version": __version__, "fingerprint": code_fingerprint()}
