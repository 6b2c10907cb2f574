"""Benchmark: `quadshank demo` (what `make demo` runs) from its start to its end, step by step.

The demo runs as a user runs it, in a fresh process with the compilation cache off (a first
run), and its wall time is measured from the command's start to its end; the seconds of each
step are the demo's own (`summary.json`), and whether its fit passed its checks and its
diagnosis found the hidden effect are recorded beside them.

    python benchmarks/bench_demo.py [--out results/benchmarks.md] [--record results/bench_demo.json]
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_md import publish, run_quadshank  # noqa: E402

SECTION = "bench_demo"


def render(record: dict) -> str:
    steps = record["steps"]
    lines = [
        "## `make demo`: the main job, step by step",
        "",
        f"Command: `{record['command']}`",
        "",
        "`quadshank demo` in a fresh process with the compilation cache off, after the install; wall time from its "
        "start to its end, and the seconds of each step as the demo records them.",
        "",
        "| wall [s] | " + " | ".join(f"{k} [s]" for k in steps) + " | fit passes its checks | hidden | verdict |",
        "|---" * (len(steps) + 4) + "|",
        f"| {record['seconds']:.0f} | " + " | ".join(f"{v:.1f}" for v in steps.values())
        + f" | {'yes' if record['fit_ok'] else 'no: ' + str(record['fit_banner'])} | {', '.join(record['hidden'])} | "
        f"{record['verdict']} |",
        "",
        f"Measured {record['date']} on {record['machine']}.",
    ]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/benchmarks.md")
    ap.add_argument("--record", default="results/bench_demo.json")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        seconds = run_quadshank("demo", "--out", str(Path(tmp) / "demo"))
        s = json.loads((Path(tmp) / "demo" / "summary.json").read_text())
    record = {"command": "python benchmarks/bench_demo.py " + shlex.join(sys.argv[1:]), "seconds": seconds,
              "steps": s["seconds"], "fit_ok": s["fit_ok"], "fit_banner": s["fit_banner"], "hidden": s["hidden"],
              "verdict": s["verdict"]}
    publish(record, args.record, args.out, SECTION, render)


if __name__ == "__main__":
    main()
