"""Benchmark: posterior J bands to a stated accuracy (``evaluate --band-mcse``) against the brute force.

The cohort: the simulated paper legs, trials 1–3 of ``--minutes`` each, data simulated with the
angle-dependent delay; one fit of model 3 + ``angle_delay`` on trial 1 (``quadshank fit
--target-ess 400``, or ``--fit DIR`` to reuse one).  Then, on every leg and trial, J bands twice,
each ``quadshank evaluate`` in a fresh process: every start of ``--draws`` draws (the brute force),
and ``--band-mcse`` (draws and stride chosen for the accuracy).  Reported side by side: the time of
the J computation (``evaluation_seconds``), the draws and stride used, the largest Monte Carlo
standard error of a band end, and how far the two evaluations' band ends lie apart, in units of
their combined standard error.

    python benchmarks/bench_jbands.py [--minutes 5] [--band-mcse 0.05] [--draws 200] [--fit DIR]
        [--out results/benchmarks.md] [--record results/bench_jbands.json]
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
from pathlib import Path

import numpy as np

from quadshank.data._paper import LEGS

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_md import publish, run_quadshank  # noqa: E402

SECTION = "bench_jbands"


def _row(name: str, folder: Path) -> dict:
    s = json.loads((folder / "summary.json").read_text())
    m = s["band_mcse"]
    return {"evaluation": name, "seconds": s["evaluation_seconds"], "draws": s["n_draws"],
            "start_stride": s["start_stride"], "largest_mcse_cohort": m["largest_cohort"],
            "largest_mcse_legs": m["largest_legs"], "met": m.get("met"), "J": s["J"], "mcse": m["cohort"]}


def _apart(a: dict, b: dict) -> float:
    """The largest distance between the two evaluations' cohort band ends, in combined standard errors."""
    z = []
    for label, trials in a["J"].items():
        for tr, hs in trials.items():
            for h, v in hs.items():
                for end in ("lo", "hi"):
                    se = np.hypot(a["mcse"][label][tr][h][end], b["mcse"][label][tr][h][end])
                    z.append(abs(v[end] - b["J"][label][tr][h][end]) / se if se > 0 else 0.0)
    return float(max(z))


def render(record: dict) -> str:
    a, b = record["rows"]
    lines = [
        "## Posterior J bands to a stated accuracy: `evaluate --band-mcse` against every start",
        "",
        f"Command: `{record['command']}`",
        "",
        f"Model 3 + `angle_delay` fitted to trial 1 of {record['legs']} simulated legs × {record['minutes']:g} min "
        "(`fit --target-ess 400`); J on every leg and trial (3 each), four horizons. Seconds: the J computation "
        "(`evaluation_seconds`), compilation included. MCSE: the largest Monte Carlo standard error of a band end "
        "(quantile and start stride), on the bands of the mean over legs and on one leg's.",
        "",
        "| evaluation | J seconds | draws | one start in | largest MCSE, mean over legs [deg] | "
        "largest MCSE, one leg [deg] |",
        "|---|---|---|---|---|---|",
    ]
    for r in record["rows"]:
        lines.append(f"| {r['evaluation']} | {r['seconds']:.1f} | {r['draws']} | {r['start_stride']} | "
                     f"{r['largest_mcse_cohort']:.4f} | {r['largest_mcse_legs']:.4f} |")
    lines += [
        "",
        f"The brute force took {a['seconds'] / b['seconds']:.1f}× the time. The two evaluations' band ends of the mean "
        f"over legs lie at most {record['apart_se']:.1f} combined standard errors apart.",
        "",
        f"Measured {record['date']} on {record['machine']}.",
    ]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--legs", default=",".join(LEGS))
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--band-mcse", type=float, default=0.05)
    ap.add_argument("--draws", type=int, default=200, help="draws of the brute force")
    ap.add_argument("--fit", default=None, help="a fit folder of this data to reuse (default: fit now)")
    ap.add_argument("--data", default=None, help="the data of --fit")
    ap.add_argument("--out", default="results/benchmarks.md")
    ap.add_argument("--record", default="results/bench_jbands.json")
    args = ap.parse_args(argv)
    command = "python benchmarks/bench_jbands.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    legs = [x for x in args.legs.split(",") if x]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        data = Path(args.data) if args.data else tmp / "data"
        if not args.data:
            run_quadshank("simulate", "--out", str(data), "--legs", ",".join(legs), "--minutes", str(args.minutes),
                       "--trials", "1,2,3", "--effects", "angle_delay")
        fit = Path(args.fit) if args.fit else tmp / "fit"
        if not args.fit:
            run_quadshank("fit", str(data), "--model", "model3", "--add-effect", "angle_delay", "--target-ess", "400",
                       "--out", str(fit))
        run_quadshank("evaluate", str(data), "--fit", str(fit), "--draws", str(args.draws), "--out", str(tmp / "brute"))
        run_quadshank("evaluate", str(data), "--fit", str(fit), "--band-mcse", str(args.band_mcse), "--out",
                   str(tmp / "accurate"))
        rows = [_row(f"{args.draws} draws, every start", tmp / "brute"),
                _row(f"`--band-mcse {args.band_mcse:g}`", tmp / "accurate")]
    record = {
        "command": command, "legs": len(legs), "minutes": args.minutes, "rows": rows, "apart_se": _apart(*rows),
    }
    publish(record, args.record, args.out, SECTION, render)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
