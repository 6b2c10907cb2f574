"""Benchmark: the command line's compilation cache, a command run again on the same data.

A user iterating on a model runs the same commands on the same data again and again: `discover`
after writing an effect, `fit` with other settings.  Each command runs as a user runs it, in a
fresh process, and its wall time is measured from start to end: with the cache off, with an
empty cache (the first run, which fills it) and with the cache the first run left (the rerun).

    python benchmarks/bench_cache.py [--leg JM-left] [--minutes 1] [--out results/benchmarks.md]
        [--record results/bench_cache.json]
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_md import publish, run_quadshank  # noqa: E402

SECTION = "bench_cache"


def render(record: dict) -> str:
    lines = [
        "## Commands run again: the compilation cache on disk",
        "",
        f"Command: `{record['command']}`",
        "",
        f"{record['leg']}, {record['minutes']:g} min of trial 1 with potentiation hidden; each command in a fresh "
        "process, wall time from its start to its end. Off: `QUADSHANK_XLA_CACHE=off`; first run: an empty cache, "
        "which it fills; rerun: the same command again with that cache.",
        "",
        "| command | cache off [s] | first run [s] | rerun [s] | rerun / off |",
        "|---|---|---|---|---|",
    ]
    for r in record["rows"]:
        lines.append(f"| `{r['command']}` | {r['off']:.1f} | {r['first']:.1f} | {r['rerun']:.1f} | "
                     f"{r['rerun'] / r['off']:.2f} |")
    lines += ["", f"Measured {record['date']} on {record['machine']}."]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--leg", default="JM-left")
    ap.add_argument("--minutes", type=float, default=1.0)
    ap.add_argument("--out", default="results/benchmarks.md")
    ap.add_argument("--record", default="results/bench_cache.json")
    args = ap.parse_args()
    commands = {
        "discover --max-rounds 1": lambda data, out: ("discover", data, "--max-rounds", "1", "--out", out),
        "fit --chains 2 --warmup 200 --draws 200": lambda data, out: (
            "fit", data, "--chains", "2", "--warmup", "200", "--draws", "200", "--out", out),
    }
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        data = str(tmp / "data")
        run_quadshank("simulate", "--out", data, "--legs", args.leg, "--minutes", str(args.minutes), "--trials", "1",
                      "--effects", "potentiation", "--seed", "2")
        for name, argv in commands.items():
            cache = {"QUADSHANK_XLA_CACHE": str(tmp / f"cache-{len(rows)}")}
            row = {"command": name}
            for run, env in (("off", None), ("first", cache), ("rerun", cache)):
                row[run] = run_quadshank(*argv(data, str(tmp / f"{len(rows)}-{run}")), env=env)
                print(name, run, f"{row[run]:.1f} s", flush=True)
            rows.append(row)
    record = {"command": "python benchmarks/bench_cache.py " + shlex.join(sys.argv[1:]), "leg": args.leg,
              "minutes": args.minutes, "rows": rows}
    publish(record, args.record, args.out, SECTION, render)


if __name__ == "__main__":
    main()
