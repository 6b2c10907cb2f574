"""Benchmark: the modelling loop on twitches that vary from pulse to pulse, confirmed by NUTS.

One leg, one trial, its twitches varying from pulse to pulse as the simulator's are by default (a
random gain per pulse, CV 0.2) and one effect hidden besides (or none): `quadshank discover DATA --confirm` from the default
model with every registered candidate, as a user runs it.  Each round's screen leader is refitted
by hierarchical NUTS against the previous round's NUTS fit and added only where NUTS agrees.  The
record keeps, round by round, the screen's leader and its ΔELPD, NUTS's ΔELPD and whether it
clears the bar there, whether each NUTS fit passed its checks, and the model the loop ends with.

    python benchmarks/bench_loop_confirm.py [--leg JM-left] [--minutes 2] [--seed 1]
        [--hidden none,torque_angle_peak,hill_velocity,angle_delay,fatigue,potentiation,goniometer_offset]
        [--keep] [--out results/benchmarks.md] [--record results/bench_loop_confirm.json]

``--keep`` keeps the record's rows (same leg and seed) other than those rerun (the effects of
``--hidden`` at ``--minutes``), each with the date it was measured: one row can be rerun alone, and
an effect that the default length does not show can be measured on longer data beside it.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
from datetime import date
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_md import discover_rounds, publish, run_quadshank  # noqa: E402

from quadshank.loop import ELPD_SE_BAR  # noqa: E402

SECTION = "bench_loop_confirm"
#: Every effect hidden by default: each built-in one the loop is expected to find on these data, and none.
HIDDEN = ("none", "torque_angle_peak", "hill_velocity", "angle_delay", "fatigue", "potentiation", "goniometer_offset")
#: Minutes of trial 1 by default; a row on other data says its length.
MINUTES = 2.0


def rounds(out: Path) -> list[dict]:
    """Each round's screen leader, the screen's and the final verdict, and the leader's NUTS evidence."""
    rows = []
    for s, top in discover_rounds(out):
        row = {"model": s.get("model"), "verdict": s.get("verdict"), "screen_verdict": s.get("screen_verdict", s.get("verdict")),
               "leader": top.get("effect"), "delta_elpd": top.get("delta_elpd"), "delta_elpd_se": top.get("delta_elpd_se"),
               "clears_bar": top.get("clears_bar"), "supported": top.get("supported"),
               "judged_at_ms": top.get("judged_at_ms"), "J_lowered_at_ms": top.get("J_lowered_at_ms"),
               "screened": len(s.get("ranking") or [])}
        nuts = top.get("nuts")
        if nuts:
            row["nuts"] = {"delta_elpd": nuts.get("delta_elpd"), "delta_elpd_se": nuts.get("delta_elpd_se"),
                           "clears_bar": nuts.get("clears_bar"), "fit_passed": nuts.get("banner") is None,
                           "banner": nuts.get("banner")}
        rows.append(row)
    return rows


def start_fit(out: Path) -> tuple[bool | None, str | None]:
    """Whether the NUTS fit of the start model passed its checks, and its banner where it did not
    (None, None where there is no such fit)."""
    path = out / "confirm" / "fit-start" / "summary.json"
    if not path.exists():
        return None, None
    banner = json.loads(path.read_text()).get("banner")
    return banner is None, banner


def render(record: dict) -> str:
    lines = [
        "## The modelling loop on varying twitches, confirmed by NUTS",
        "",
        f"Command: `{record['command']}`",
        "",
        f"{record['leg']}, {MINUTES:g} min of trial 1 (longer where a row says; seed {record['seed']}), simulated with "
        "its twitches varying from pulse to pulse (the simulator's default: a log-normal gain per pulse, CV 0.2) and "
        "the hidden effect besides; "
        "`quadshank discover DATA --confirm` (model3s, every registered candidate, up to three rounds; each NUTS "
        "fit of 2 chains drawn in blocks to an ESS of 400). Each round: the screen's leader with its ΔELPD ± SE, then NUTS's ΔELPD ± SE for it "
        "against the previous round's NUTS fit and whether it clears the bar there (✓ added, ✗ not); "
        "a round whose screen names no leader ends the loop, and says why where its leader had the evidence on its side. *fits passed*: the NUTS fits that passed their "
        "checks (R-hat, ESS, divergences, E-BFMI), of all made.",
        "",
        "| hidden | rounds: screen leader (ΔELPD ± SE) → NUTS (ΔELPD ± SE) | candidates screened | final model | NUTS fits passed | wall [s] | measured |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in record["rows"]:
        said = []
        for x in r["rounds"]:
            if x["screen_verdict"] == "none":
                said.append(f"none (leader {x['leader']} {x['delta_elpd']:.0f} ± {x['delta_elpd_se']:.0f}{why_not(x)})")
                continue
            n = x.get("nuts") or {}
            mark = "✓" if x["verdict"] != "none" else "✗"
            said.append(f"{x['screen_verdict']} ({x['delta_elpd']:.0f} ± {x['delta_elpd_se']:.0f}) → "
                        f"{n.get('delta_elpd', float('nan')):.0f} ± {n.get('delta_elpd_se', float('nan')):.0f} {mark}")
        fits = [r["start_fit_passed"]] + [x["nuts"]["fit_passed"] for x in r["rounds"] if x.get("nuts")]
        fits = [f for f in fits if f is not None]
        screened = max((x["screened"] for x in r["rounds"]), default=0)
        lines.append(f"| {label(r)} | {'; '.join(said)} | {screened} | {r['final_model']} | "
                     f"{sum(fits)} of {len(fits)} | {r['seconds']:.0f} | {r['date']} |")
    failed = [f"{label(r)}, {where}: {banner}" for r in record["rows"]
              for where, banner in [("the start model", r.get("start_fit_banner"))]
              + [(x["model"] + " + " + x["screen_verdict"], (x.get("nuts") or {}).get("banner")) for x in r["rounds"]]
              if banner]
    if failed:
        lines += ["", "NUTS fits that failed their checks: " + "; ".join(failed) + "."]
    lines += ["", f"Measured on {record['machine']}; a row is rerun alone with `--hidden NAME --keep` (and `--minutes M` where it gives a length)."]
    return "\n".join(lines)


def label(row: dict) -> str:
    """A row's hidden effect, with its data's length where that is not the default."""
    return row["hidden"] if row["minutes"] == MINUTES else f"{row['hidden']}, {row['minutes']:g} min"


def why_not(x: dict) -> str:
    """Why a leader with the evidence on its side did not clear the screen's bar, where the record says."""
    if x.get("supported") is False and x["delta_elpd"] > ELPD_SE_BAR * x["delta_elpd_se"]:
        return "; not supported where segments of high Pareto k are left out"
    if not x.get("supported") or x.get("judged_at_ms") is None:
        return ""
    missed = [h for h in x["judged_at_ms"] if h not in x["J_lowered_at_ms"]]
    return f"; J not lowered beyond the bands at {', '.join(str(h) for h in missed)} ms" if missed else ""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--leg", default="JM-left")
    ap.add_argument("--minutes", type=float, default=MINUTES)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--hidden", default=",".join(HIDDEN))
    ap.add_argument("--keep", action="store_true", help="keep the record's rows of the effects not rerun")
    ap.add_argument("--out", default="results/benchmarks.md")
    ap.add_argument("--record", default="results/bench_loop_confirm.json")
    args = ap.parse_args()
    record = {"command": "python benchmarks/bench_loop_confirm.py " + shlex.join(sys.argv[1:]), "leg": args.leg,
              "seed": args.seed, "rows": []}
    hidden_now = args.hidden.split(",")
    kept = kept_rows(args.record, record, hidden_now, args.minutes) if args.keep else []
    if args.keep:
        record["command"] = "python benchmarks/bench_loop_confirm.py"  # the rows together: what every row's run amounts to
    today = date.today().isoformat()
    with tempfile.TemporaryDirectory() as tmp:
        for hidden in hidden_now:
            data, out = Path(tmp) / f"data-{hidden}", Path(tmp) / f"discover-{hidden}"
            # the simulated twitches vary by default: only the hidden effect is named
            effects = [] if hidden == "none" else ["--effects", hidden]
            run_quadshank("simulate", "--out", str(data), "--legs", args.leg, "--minutes", str(args.minutes),
                          "--trials", "1", "--seed", str(args.seed), *effects)
            seconds = run_quadshank("discover", str(data), "--confirm", "--out", str(out))
            summary = json.loads((out / "summary.json").read_text())
            passed, banner = start_fit(out)
            record["rows"].append({"hidden": hidden, "seconds": seconds, "rounds": rounds(out), "final_model": summary["final_model"],
                                   "start_fit_passed": passed, "start_fit_banner": banner, "date": today,
                                   "minutes": args.minutes})
            print(hidden, f"{seconds:.0f} s", summary["final_model"], flush=True)
            publish(in_order(record, kept), args.record, args.out, SECTION, render)  # what is measured so far is kept


def kept_rows(path: str | Path, record: dict, rerun: list[str], minutes: float) -> list[dict]:
    """The rows of the record at ``path`` other than those of the effects in ``rerun`` on ``minutes``
    of data, each with its date and length; none where there is no record or it was made on another
    leg or seed."""
    path = Path(path)
    if not path.exists():
        return []
    old = json.loads(path.read_text())
    if any(old.get(k) != record[k] for k in ("leg", "seed")):
        return []
    rows = [{**r, "date": r.get("date", old.get("date")), "minutes": r.get("minutes", old.get("minutes"))}
            for r in old.get("rows", [])]
    return [r for r in rows if not (r["hidden"] in rerun and r["minutes"] == minutes)]


def in_order(record: dict, kept: list[dict]) -> dict:
    """``record`` with the ``kept`` rows beside its own, in the order of :data:`HIDDEN` (others last)."""
    rank = {h: i for i, h in enumerate(HIDDEN)}
    rows = sorted(kept + record["rows"], key=lambda r: (rank.get(r["hidden"], len(rank)), r["minutes"]))
    return {**record, "rows": rows}


if __name__ == "__main__":
    main()
