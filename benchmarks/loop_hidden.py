"""The modelling loop against each effect the simulator can hide: found, and from how much data.

For each hidden effect (and for none) one leg of the default simulated cohort (its twitches
varying from pulse to pulse) is simulated, and ``quadshank discover`` runs on it as a user runs
it: from ``model3s``, every registered candidate screened, up to three rounds.  Where the hidden
effect is not added, the same is done on longer data (the lengths in turn), so that the table
says at which length it is found.  Each dataset and loop is made by the package's commands:

    quadshank simulate --out DATA --legs LEG --minutes M --trials 1 --seed SEED [--effects EFFECT]
    quadshank -q discover DATA --out OUT [--confirm [--target-accept P]]

(for ``recruitment_power``, trials 1–3 simulated and ``--trials 1,3`` fitted: see :data:`TRIALS`)

    python benchmarks/loop_hidden.py [--effects a,b] [--minutes 1,2,4] [--leg JM-left] [--seed 4]
        [--jobs 2] [--confirm [--target-accept P]] [--out results/loop-hidden.md]
        [--record results/loop_hidden.json]

With ``--confirm`` each round's leader is also fitted by hierarchical NUTS (``discover --confirm``)
and the table gives NUTS's ΔELPD and whether it clears the bar beside the screen's; ``--target-accept``
is passed on to those fits (a higher one for a fit that stopped at a divergent transition).  The rows of a
run replace those of the same effect and length in the record (same leg and seed), so that the
lengths at which the screen found each effect can be confirmed one run at a time; each row keeps
the command that made it, and the table names it.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_md import discover_rounds, run_quadshank, stamp  # noqa: E402

from quadshank.common._io import atomic_write_text, write_json  # noqa: E402

from quadshank.data._simulate import EFFECTS  # noqa: E402

#: The loop adds the noise effect for the twitches' variation, then the hidden effect, then ends.
MAX_ROUNDS = 3
#: Trials simulated and fitted per hidden effect (default: trial 1 alone): a recruitment curve shows
#: only between pulses of different levels, trial 1's (u = 1) and trial 3's (u = 0.5); a folder
#: numbers its trials from 1, so trial 2 is simulated too and left out of the loop.
TRIALS = {"recruitment_power": ("1,2,3", "1,3")}


def one(effect: str, minutes: float, leg: str, seed: int, work: Path, confirm: tuple[str, ...] = ()) -> dict:
    """Simulate, run the loop, and read each round's verdict and leader; ``confirm``: the options
    of ``discover --confirm`` (empty: the screen alone)."""
    data, out = work / f"{effect}-{minutes:g}min-data", work / f"{effect}-{minutes:g}min-loop"
    simulated, trials = TRIALS.get(effect, ("1", "1"))
    sim = ["simulate", "--out", str(data), "--legs", leg, "--minutes", f"{minutes:g}", "--trials", simulated,
           "--seed", str(seed)] + ([] if effect == "none" else ["--effects", effect])
    run_quadshank(*sim)
    seconds = run_quadshank("discover", str(data), "--out", str(out), "--max-rounds", str(MAX_ROUNDS),
                            "--trials", trials, *confirm)
    return {**loop_row(effect, minutes, out, seconds), "trials": trials}


def loop_row(effect: str, minutes: float, out: Path, seconds: float) -> dict:
    """A ``discover`` folder's rounds (verdict and leader of each) and whether it found ``effect``:
    added in some round, or for ``none`` nothing added but the noise term for varying twitches."""
    rounds = []
    for summary, top in discover_rounds(out):
        rounds.append({"model": summary.get("model"), "verdict": summary.get("verdict"), "leader": top.get("effect"),
                       "delta_elpd": top.get("delta_elpd"), "delta_elpd_se": top.get("delta_elpd_se")})
        nuts = top.get("nuts")
        if nuts is not None:  # discover --confirm: the leader's NUTS fit against the previous round's
            rounds[-1].update(screen_verdict=summary.get("screen_verdict"), nuts={
                k: nuts.get(k) for k in ("delta_elpd", "delta_elpd_se", "clears_bar", "banner")})
    added = [r["verdict"] for r in rounds if r["verdict"] not in (None, "none")]
    found = set(added) <= {"twitch_variability"} if effect == "none" else effect in added
    return {"effect": effect, "minutes": minutes, "rounds": rounds, "added": added, "found": bool(found),
            "seconds": seconds}


def study(effect: str, lengths, leg: str, seed: int, work: Path, confirm: tuple[str, ...] = ()) -> list[dict]:
    """The loop at each length in turn until the hidden effect is found (for none, the first length only)."""
    rows = []
    for minutes in lengths:
        rows.append(one(effect, minutes, leg, seed, work, confirm))
        print(json.dumps(rows[-1]), flush=True)
        if rows[-1]["found"] or effect == "none":
            break
    return rows


def _nuts(n: dict) -> str:
    said = "clears the bar" if n["clears_bar"] else "does not clear it"
    failed = "; its fit failed its checks" if n.get("banner") else ""
    return f"; NUTS {n['delta_elpd']:.0f} ± {n['delta_elpd_se']:.0f}, {said}{failed}"


def _round(r: dict) -> str:
    nuts = _nuts(r["nuts"]) if r.get("nuts") else ""
    if r["verdict"] in (None, "none"):
        lead = f" (leader {r['leader']} {r['delta_elpd']:.0f} ± {r['delta_elpd_se']:.0f}{nuts})" if r.get("leader") else ""
        return f"none{lead}"
    return f"`{r['verdict']}` ({r['delta_elpd']:.0f} ± {r['delta_elpd_se']:.0f}{nuts})"


def _commands(record: dict) -> list[str]:
    """The commands behind ``record``'s rows (one, or several where runs were merged)."""
    return record.get("commands", [record["command"]])


def _covers(command: str, row: dict) -> bool:
    """Whether ``command`` (this script's, as recorded) runs the loop on ``row``'s effect and length."""
    args, _ = _parser().parse_known_args(shlex.split(command)[2:])  # a flag since dropped does not stop it
    return row["effect"] in args.effects.split(",") and row["minutes"] in [float(m) for m in args.minutes.split(",")]


def _row_command(row: dict, commands: list[str]) -> str:
    """The command that made ``row``: its own, or in a record made before rows kept theirs, the last
    of the record's commands that ran it."""
    return row.get("command") or next((c for c in reversed(commands) if _covers(c, row)), commands[-1])


def merged(old: dict | None, record: dict) -> dict:
    """``record`` with the rows of ``old`` (an earlier record of the same leg and seed) that it
    does not redo: a row is one effect at one length, and the new one replaces the old.  Each row
    keeps the command that made it; the record's ``commands`` are those of its rows."""
    if not old or (old.get("leg"), old.get("seed")) != (record["leg"], record["seed"]):
        return record
    new = {(r["effect"], r["minutes"]) for r in record["rows"]}
    kept = [{**r, "command": _row_command(r, _commands(old))}
            for r in old["rows"] if (r["effect"], r["minutes"]) not in new]
    order = {e: i for i, e in enumerate(dict.fromkeys(r["effect"] for r in old["rows"] + record["rows"]))}
    made = [{**r, "command": r.get("command", record["command"])} for r in record["rows"]]
    rows = sorted(kept + made, key=lambda r: (order[r["effect"]], r["minutes"]))
    commands = [c for c in dict.fromkeys([*_commands(old), record["command"]]) if any(r["command"] == c for r in rows)]
    return {**record, "rows": rows, "commands": commands, "command": commands[0]}


def render(record: dict) -> str:
    commands = _commands(record)
    number = {c: i for i, c in enumerate(commands, start=1)}
    lines = [
        ("Command: " if len(commands) == 1 else "Commands (the table's last column names each row's): ")
        + ", ".join(f"({number[c]}) `{c}`" if len(commands) > 1 else f"`{c}`" for c in commands),
        "",
        f"{record['leg']}, trial 1 of the default simulated cohort (seed {record['seed']}, twitches varying by a CV "
        "of 0.2 from pulse to pulse) with one effect hidden: `quadshank simulate --out DATA --legs "
        f"{record['leg']} --minutes M --trials 1 --seed {record['seed']} --effects EFFECT`, then `quadshank -q "
        f"discover DATA --out OUT` (from `model3s`, every registered candidate, at most {MAX_ROUNDS} rounds). "
        "For `recruitment_power` trials 1–3 are simulated and the loop fits trials 1 and 3 (`--trials 1,3`), whose "
        "recruitment levels differ (1 and 0.5). Where the hidden effect is not added, the loop runs again on longer "
        "data. Each round's verdict, with "
        "its ΔELPD ± SE on the screen; a round whose verdict is none names its leader. Rows run with `--confirm` "
        "give NUTS's ΔELPD ± SE of the same leader beside the screen's (`discover --confirm`: a hierarchical NUTS "
        "fit of the leader against the previous round's), and the round's verdict is then NUTS's.",
        "",
        "| hidden | minutes | found | round 1 | round 2 | round 3 | loop [s] |" + (" command |" if len(commands) > 1 else ""),
        "|---|---|---|---|---|---|---|" + ("---|" if len(commands) > 1 else ""),
    ]
    for row in record["rows"]:
        cells = [_round(r) for r in row["rounds"]] + [""] * (MAX_ROUNDS - len(row["rounds"]))
        found = "yes" if row["found"] else "no"
        by = f" ({number[_row_command(row, commands)]}) |" if len(commands) > 1 else ""
        lines.append(f"| {row['effect']} | {row['minutes']:g} | {found} | " + " | ".join(cells)
                     + f" | {row['seconds']:.0f} |" + by)
    return "\n".join(lines) + "\n"


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--effects", default=",".join(("none", *EFFECTS)))
    ap.add_argument("--minutes", default="1,2,4", help="lengths tried in turn until the effect is found")
    ap.add_argument("--leg", default="JM-left")
    ap.add_argument("--seed", type=int, default=4)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--confirm", action="store_true", help="confirm each round's leader with NUTS (discover --confirm)")
    ap.add_argument("--target-accept", type=float, default=None, metavar="P",
                    help="with --confirm: NUTS's target acceptance probability (discover's default without it)")
    ap.add_argument("--out", default="results/loop-hidden.md")
    ap.add_argument("--record", default="results/loop_hidden.json")
    return ap


def main(argv=None) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    effects = [e for e in args.effects.split(",") if e]
    lengths = [float(m) for m in args.minutes.split(",")]
    if args.target_accept is not None and not args.confirm:
        ap.error("--target-accept acts only with --confirm (the NUTS fits)")
    confirm = ("--confirm",) if args.confirm else ()
    if args.target_accept is not None:
        confirm += ("--target-accept", str(args.target_accept))
    with tempfile.TemporaryDirectory(prefix="loop-hidden-") as tmp, ThreadPoolExecutor(args.jobs) as pool:
        studies = list(pool.map(lambda e: study(e, lengths, args.leg, args.seed, Path(tmp), confirm), effects))
    command = "python benchmarks/loop_hidden.py " + shlex.join(argv if argv is not None else sys.argv[1:])
    record = {"command": command, "leg": args.leg, "seed": args.seed, "lengths": lengths,
              "rows": [{**row, "command": command} for rows in studies for row in rows]}
    old = json.loads(Path(args.record).read_text()) if Path(args.record).exists() else None
    record = stamp(merged(old, record))
    write_json(args.record, record)
    atomic_write_text(args.out, "# The modelling loop against hidden effects\n\n" + render(record))
    print(render(record))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
