"""Benchmark: time to a usable posterior, ``quadshank fit --target-ess`` at each precision against a fit of fixed length.

The cohort: the simulated paper legs, trial 1 of ``--minutes`` each, data simulated with the
angle-dependent delay; the model: model 3 + ``angle_delay``.  Both fits run as a user runs
them, ``quadshank fit`` in a fresh process, and their wall time is measured from the command's
start to its end (import, loading, the screen, compilation and the writing of the fit
included).  "Usable" is what the fit's checks ask: R-hat < 1.01, bulk and tail ESS at least
the target (and 100 per chain) for every parameter, no divergence.  The fit to the target runs
at each of ``--precisions`` (``fit --precision``: mixed, the default, and double), the fit of
fixed length at the first.

    python benchmarks/bench_target.py [--legs ...] [--minutes 5] [--target-ess 400] [--time-limit 600]
        [--precisions mixed,double] [--fixed 1000,1000] [--out results/benchmarks.md] [--record results/bench_target.json]

``--fixed 0`` skips the fit of fixed length.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
from pathlib import Path

import arviz as az
import numpy as np

from quadshank.data._paper import LEGS

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_md import publish, run_quadshank  # noqa: E402

SECTION = "bench_target"


def _row(name: str, folder: Path, seconds: float) -> dict:
    s = json.loads((folder / "summary.json").read_text())
    d = s["diagnostics"]
    return {
        "fit": name, "seconds": round(seconds, 1), "ok": bool(d["ok"]), "rhat_max": d["rhat_max"],
        "ess_bulk_min": d["ess_bulk_min"], "ess_tail_min": d["ess_tail_min"], "divergences": d["divergences"],
        "draws_per_chain": d["draws"], "chains": d["chains"], "target": s.get("target"),
        "bulk_ess_per_s": d["ess_bulk_min"] / seconds,
        "steps_per_draw": float(np.mean(az.from_netcdf(folder / "fit.nc").sample_stats["n_steps"])),
    }


def render(record: dict) -> str:
    lines = [
        "## Time to a usable posterior: `fit --target-ess` against a fit of fixed length",
        "",
        f"Command: `{record['command']}`",
        "",
        f"Model 3 + `angle_delay`, {record['legs']} simulated legs × {record['minutes']:g} min (trial 1, delay step "
        f"in the data), {record['chains']} chains from the screen; wall time of `quadshank fit` in a fresh process, "
        "from its start to its end (compilation included). Usable: R-hat < 1.01, bulk and tail ESS ≥ the target for "
        "every parameter, no divergence.",
        "",
        "| fit | wall [s] | passes its checks | R-hat max | bulk ESS min | tail ESS min | draws per chain | "
        "bulk ESS / s | leapfrog steps per draw | stopped |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in record["rows"]:
        stopped = r["target"]["stopped"] if r["target"] else "fixed length"
        lines.append(
            f"| {r['fit']} | {r['seconds']:.0f} | {'yes' if r['ok'] else 'no'} | {r['rhat_max']:.3f} | "
            f"{r['ess_bulk_min']:.0f} | {r['ess_tail_min']:.0f} | {r['draws_per_chain']} | "
            f"{r['bulk_ess_per_s']:.2f} | {r['steps_per_draw']:.1f} | {stopped} |"
        )
    rows = record["rows"]
    first = rows[0]
    for r in rows[1:]:
        what = "fit of fixed length" if r["target"] is None else f"fit to the target at {r['precision']} precision"
        lines += ["", f"The {what} took {r['seconds'] / first['seconds']:.2f}× the wall time of the fit to the "
                      f"target at {first['precision']} precision."]
    lines += ["", f"Measured {record['date']} on {record['machine']}."]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--legs", default=",".join(LEGS))
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--chains", type=int, default=4)
    ap.add_argument("--target-ess", type=int, default=400)
    ap.add_argument("--time-limit", type=float, default=600.0)
    ap.add_argument("--fixed", default="1000,1000", help="warm-up,draws of the fit of fixed length (0: none)")
    ap.add_argument("--precisions", default="mixed,double", help="the precisions of the fits to the target")
    ap.add_argument("--out", default="results/benchmarks.md")
    ap.add_argument("--record", default="results/bench_target.json")
    args = ap.parse_args(argv)
    command = "python benchmarks/bench_target.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    legs = [x for x in args.legs.split(",") if x]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        run_quadshank("simulate", "--out", str(tmp / "data"), "--legs", ",".join(legs), "--minutes", str(args.minutes),
                   "--trials", "1", "--effects", "angle_delay")
        fit = ["fit", str(tmp / "data"), "--model", "model3", "--add-effect", "angle_delay", "--chains", str(args.chains)]
        rows = []
        precisions = [p for p in args.precisions.split(",") if p]
        for precision in precisions:
            seconds = run_quadshank(*fit, "--target-ess", str(args.target_ess), "--time-limit", str(args.time_limit),
                                    "--precision", precision, "--out", str(tmp / f"target-{precision}"))
            name = f"--target-ess {args.target_ess} --precision {precision}"
            rows.append({**_row(name, tmp / f"target-{precision}", seconds), "precision": precision})
        if args.fixed != "0":
            warmup, draws = (int(x) for x in args.fixed.split(","))
            seconds = run_quadshank(*fit, "--warmup", str(warmup), "--draws", str(draws), "--precision", precisions[0],
                                    "--out", str(tmp / "fixed"))
            name = f"--warmup {warmup} --draws {draws} --precision {precisions[0]}"
            rows.append({**_row(name, tmp / "fixed", seconds), "precision": precisions[0]})
    record = {
        "command": command, "legs": len(legs), "minutes": args.minutes, "chains": args.chains, "rows": rows,
    }
    publish(record, args.record, args.out, SECTION, render)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
