"""Benchmark: the modelling loop's wait, `quadshank discover` from its start to its end.

Three legs × 2 min of one trial with potentiation hidden, the default model, every registered
candidate, up to three rounds: the command as a user runs it, in a fresh process with the
compilation cache off (a first run), timed from start to end.  Side by side in one run: each
screen's L-BFGS in the coordinates the baseline's Laplace covariance whitens (the default) and
in the plain standardised coordinates (``quadshank.inference._screen.WHITEN_FROM_START = False``).

    python benchmarks/bench_discover.py [--legs TN-left,TN-right,JM-left] [--minutes 2]
        [--out results/benchmarks.md] [--record results/bench_discover.json]
"""

from __future__ import annotations

import argparse
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_md import discover_rounds, publish, run_quadshank  # noqa: E402

SECTION = "bench_discover"
VARIANTS = {"whitened (default)": True, "plain coordinates": False}


def discover(data: str, out: str, whiten: bool) -> float:
    """``quadshank -q discover DATA --out OUT`` in a fresh process, the cache off; its wall time [s]."""
    cli = ("import sys; from quadshank.inference import _screen; "
           f"_screen.WHITEN_FROM_START = {whiten}; from quadshank.cli import main; sys.exit(main())")
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", cli, "-q", "discover", data, "--out", out], capture_output=True,
                          text=True, env={**os.environ, "QUADSHANK_XLA_CACHE": "off"})
    seconds = time.perf_counter() - t
    if proc.returncode not in (0, 3):
        raise RuntimeError(f"discover failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return seconds


def rounds(out: Path) -> list[dict]:
    """Each round's verdict and its leader's ΔELPD ± SE, from the round's summary."""
    return [{"verdict": s.get("verdict"), "leader": top.get("effect"), "delta_elpd": top.get("delta_elpd"),
             "delta_elpd_se": top.get("delta_elpd_se")} for s, top in discover_rounds(out)]


def render(record: dict) -> str:
    lines = [
        "## The modelling loop's wait: `discover` on 3 legs × 2 min",
        "",
        f"Command: `{record['command']}`",
        "",
        f"{', '.join(record['legs'])}, {record['minutes']:g} min of trial 1 each with potentiation hidden; "
        "`quadshank discover DATA` (model3s, every registered candidate, up to three rounds) in a fresh process "
        "with the compilation cache off, wall time from its start to its end. Each screen's modes are sought by "
        "L-BFGS in the coordinates the baseline's Laplace covariance whitens (the default), or in the plain "
        "standardised coordinates.",
        "",
        "| screen's coordinates | wall [s] | rounds: verdict (leader's ΔELPD ± SE) |",
        "|---|---|---|",
    ]
    for r in record["rows"]:
        said = "; ".join(f"{x['verdict']} ({x['leader']} {x['delta_elpd']:.0f} ± {x['delta_elpd_se']:.0f})"
                         for x in r["rounds"])
        lines.append(f"| {r['variant']} | {r['seconds']:.0f} | {said} |")
    base, fast = record["rows"][1]["seconds"], record["rows"][0]["seconds"]
    lines += ["", f"Whitened, the loop took {fast / base:.2f}× the wall time of the plain coordinates.",
              "", f"Measured {record['date']} on {record['machine']}."]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--legs", default="TN-left,TN-right,JM-left")
    ap.add_argument("--minutes", type=float, default=2.0)
    ap.add_argument("--out", default="results/benchmarks.md")
    ap.add_argument("--record", default="results/bench_discover.json")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        data = str(tmp / "data")
        run_quadshank("simulate", "--out", data, "--legs", args.legs, "--minutes", str(args.minutes), "--trials", "1",
                      "--effects", "potentiation", "--seed", "2")
        for variant, whiten in VARIANTS.items():
            out = tmp / f"discover-{whiten}"
            seconds = discover(data, str(out), whiten)
            rows.append({"variant": variant, "seconds": seconds, "rounds": rounds(out)})
            print(variant, f"{seconds:.0f} s", flush=True)
    record = {"command": "python benchmarks/bench_discover.py " + shlex.join(sys.argv[1:]), "legs": args.legs.split(","),
              "minutes": args.minutes, "rows": rows}
    publish(record, args.record, args.out, SECTION, render)


if __name__ == "__main__":
    main()
