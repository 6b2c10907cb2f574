"""One section of results/benchmarks.md per benchmark, between its own markers."""

from __future__ import annotations

from pathlib import Path

from quadshank.common._io import atomic_write_text

HEADER = "# Benchmarks\n\nEach section is written by the command shown in it.\n"


def write_section(path: str | Path, name: str, text: str) -> None:
    """Put ``text`` between ``<!-- name:begin -->`` and ``<!-- name:end -->`` in ``path``,
    replacing that section where it exists and appending it otherwise; the rest stays."""
    path = Path(path)
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    old = path.read_text() if path.exists() else HEADER
    block = f"{begin}\n{text.rstrip()}\n{end}"
    if begin in old and end in old:
        head, rest = old.split(begin, 1)
        new = head + block + rest.split(end, 1)[1]
    else:
        new = old.rstrip() + "\n\n" + block + "\n"
    atomic_write_text(path, new)
