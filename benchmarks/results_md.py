"""One section of results/benchmarks.md per benchmark, between its own markers."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from datetime import date
from pathlib import Path

from quadshank.common._io import atomic_write_text, write_json

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


def run_quadshank(*args: str, env: dict | None = None) -> float:
    """Run ``quadshank -q ARGS`` in a fresh process, as a user runs it; its wall time [s].  Exit code 3
    (a fit that ran and failed its checks, which the benchmark's record shows) is not an error.
    ``env``: variables set for that process on top of this one's.  The command line's compilation
    cache is off unless ``env`` sets it (``QUADSHANK_XLA_CACHE``): a time measured with compilation
    included must not depend on what earlier commands left on disk."""
    cli = "import sys; from quadshank.cli import main; sys.exit(main())"
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", cli, "-q", *args], capture_output=True, text=True,
                          env={**os.environ, "QUADSHANK_XLA_CACHE": "off", **(env or {})})
    seconds = time.perf_counter() - t
    if proc.returncode not in (0, 3):
        raise RuntimeError(f"quadshank {' '.join(args)} failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return seconds


def stamp(record: dict) -> dict:
    """``record`` with the date and the machine it was measured on."""
    record.update(date=date.today().isoformat(), machine=f"{platform.machine()}, {os.cpu_count()} CPU cores")
    return record


def publish(record: dict, record_path: str | Path, md_path: str | Path, name: str, render) -> None:
    """Date and machine into ``record``, written as JSON, and its section ``render(record)`` into ``md_path``."""
    write_json(record_path, stamp(record))
    write_section(md_path, name, render(record))
    print(render(record))


def discover_rounds(out: str | Path) -> list[tuple[dict, dict]]:
    """A ``quadshank discover`` folder's rounds in order: each round's summary and the top row of
    its ranking (an empty dict where nothing was ranked)."""
    folders = sorted(Path(out).glob("round-*"), key=lambda p: int(p.name.split("-")[1]))
    summaries = [json.loads((f / "summary.json").read_text()) for f in folders]
    return [(s, (s.get("ranking") or [{}])[0]) for s in summaries]
