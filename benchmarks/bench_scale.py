"""Benchmark: time to a usable posterior as the cohort grows, ``quadshank fit --target-ess`` at 5, 20 and 80 legs.

The simulator holds the truths of the paper's five legs.  A cohort of 5 × R legs is R replicas
of them: replica r is simulated with seed r (its own stimulation sequence, sensor noise and
twitch realisations) and its subjects renamed (``TN`` → ``TN2`` …), so each replica's legs are
legs of their own in the hierarchy.  Replicas share each paper leg's physiology: the figures
measure how the fit's cost grows with the number of legs, not how it copes with a more varied
population.

Model 3 + ``angle_delay`` on trial 1 of ``--minutes`` per leg (the delay step in the data),
``quadshank fit --target-ess`` in a fresh process, wall time from its start to its end
(compilation included), as ``bench_target`` measures the 5-leg figure.

    python benchmarks/bench_scale.py [--replicas 1,4,16] [--minutes 1] [--target-ess 400] [--time-limit 3600]
        [--out results/benchmarks.md] [--record results/bench_scale.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import shlex
import sys
import tempfile
from pathlib import Path

from quadshank.data import Cohort, simulate_cohort, write_interchange

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_target import _row  # noqa: E402
from results_md import publish, run_quadshank  # noqa: E402

SECTION = "bench_scale"


def replicated_cohort(replicas: int, minutes: float) -> Cohort:
    """``replicas`` copies of the simulated paper legs (trial 1, ``angle_delay`` in the data), copy r
    simulated with seed r and its subjects suffixed with r + 1 (the first keeps the paper's names)."""
    trials = []
    for r in range(replicas):
        cohort, _ = simulate_cohort(minutes=minutes, seed=r, effects=["angle_delay"], trials=(1,))
        suffix = "" if r == 0 else str(r + 1)
        trials += [dataclasses.replace(t, subject=t.subject + suffix, source="") for t in cohort]
    return Cohort(tuple(trials), attrs={"simulated": 1, "replicas": replicas, "minutes": minutes})


def render(record: dict) -> str:
    rows = record["rows"]
    lines = [
        "## Time to a usable posterior as the cohort grows",
        "",
        f"Command: `{record['command']}`",
        "",
        f"Model 3 + `angle_delay`, trial 1 of {record['minutes']:g} min per leg (delay step in the data), "
        f"{record['chains']} chains from the screen, `quadshank fit --target-ess {record['target_ess']}` "
        f"(time limit {record['time_limit_s']:g} s) in a fresh process, wall time from its start to its end "
        "(compilation included). The cohorts are replicas of the five simulated paper legs, each replica with "
        "its own seed and subject names: they share the five legs' physiology and differ in stimulation, noise "
        "and twitches. Usable: R-hat < 1.01, bulk and tail ESS ≥ the target for every parameter, no divergence.",
        "",
        "| legs | samples | wall [s] | wall per leg [s] | passes its checks | R-hat max | bulk ESS min | "
        "tail ESS min | draws per chain | stopped |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['legs']} | {r['samples']} | {r['seconds']:.0f} | {r['seconds'] / r['legs']:.1f} | "
            f"{'yes' if r['ok'] else 'no'} | {r['rhat_max']:.3f} | {r['ess_bulk_min']:.0f} | {r['ess_tail_min']:.0f} | "
            f"{r['draws_per_chain']} | {r['target']['stopped'] if r['target'] else 'fixed length'} |"
        )
    if len(rows) > 1:
        a = rows[0]
        growth = ", ".join(
            f"{r['legs'] / a['legs']:g}× the legs took {r['seconds'] / a['seconds']:.2f}× the time" for r in rows[1:]
        )
        lines += ["", f"Against {a['legs']} legs: {growth}."]
    lines += ["", f"Measured {record['date']} on {record['machine']}."]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--replicas", default="1,4,16", help="comma-separated numbers of replicas of the five legs")
    ap.add_argument("--minutes", type=float, default=1.0)
    ap.add_argument("--chains", type=int, default=4)
    ap.add_argument("--target-ess", type=int, default=400)
    ap.add_argument("--time-limit", type=float, default=3600.0)
    ap.add_argument("--out", default="results/benchmarks.md")
    ap.add_argument("--record", default="results/bench_scale.json")
    args = ap.parse_args(argv)
    command = "python benchmarks/bench_scale.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))
    record = {
        "command": command, "minutes": args.minutes, "chains": args.chains, "target_ess": args.target_ess,
        "time_limit_s": args.time_limit, "rows": [],
    }
    for replicas in (int(x) for x in args.replicas.split(",") if x):
        with tempfile.TemporaryDirectory() as tmp:
            tmp = Path(tmp)
            cohort = replicated_cohort(replicas, args.minutes)
            write_interchange(cohort, tmp / "data")
            seconds = run_quadshank(
                "fit", str(tmp / "data"), "--model", "model3", "--add-effect", "angle_delay",
                "--chains", str(args.chains), "--target-ess", str(args.target_ess),
                "--time-limit", str(args.time_limit), "--out", str(tmp / "fit"),
            )  # fmt: skip
            row = _row(f"{len(cohort.legs)} legs", tmp / "fit", seconds)
            row.update(legs=len(cohort.legs), samples=int(sum(t.n_samples for t in cohort)))
        record["rows"].append(row)
        # written after every size, so that a run stopped during a larger cohort keeps the smaller ones
        publish(record, args.record, args.out, SECTION, render)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
