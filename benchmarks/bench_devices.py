"""Benchmark: the chains of one fit on one JAX device against each chain on its own device.

On a CPU the devices are made with ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (they
share the machine's cores); on a machine with several GPUs, ``--platform gpu`` uses them as they
are.  Each fit is ``quadshank fit`` in a fresh process with the default ``--chain-method auto``
(parallel where there is a device per chain), timed from its start to its end, compilation
included; the same data, model, chains, warm-up and draws every time.

    python benchmarks/bench_devices.py [--legs TN-left,JM-left] [--minutes 1.5] [--model model3s]
        [--chains 2] [--warmup 300] [--draws 300] [--devices 1,2] [--platform cpu]
        [--out results/benchmarks.md] [--record results/bench_devices.json]
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

SECTION = "bench_devices"


def render(record: dict) -> str:
    lines = [
        "## Chains across JAX devices",
        "",
        f"Command: `{record['command']}`",
        "",
        f"`{record['model']}` on {record['legs']} simulated legs × {record['minutes']:g} min (trial 1), "
        f"{record['chains']} chains × ({record['warmup']} + {record['draws']}) from the screen, on the "
        f"{record['platform']}; wall time of `quadshank fit` in a fresh process (compilation included), "
        "`--chain-method auto`.",
        "",
        "| devices | chain method | wall [s] | R-hat max | bulk ESS min | bulk ESS / s |",
        "|---|---|---|---|---|---|",
    ]
    for r in record["rows"]:
        lines.append(f"| {r['devices']} | {r['chain_method']} | {r['seconds']:.0f} | {r['rhat_max']:.3f} | "
                     f"{r['ess_bulk_min']:.0f} | {r['bulk_ess_per_s']:.2f} |")
    first = record["rows"][0]
    for r in record["rows"][1:]:
        lines += ["", f"{r['devices']} devices took {r['seconds'] / first['seconds']:.2f}× the wall time of "
                      f"{first['devices']}."]
    lines += ["", f"Measured {record['date']} on {record['machine']}."]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--legs", default="TN-left,JM-left")
    ap.add_argument("--minutes", type=float, default=1.5)
    ap.add_argument("--model", default="model3s")
    ap.add_argument("--chains", type=int, default=2)
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--draws", type=int, default=300)
    ap.add_argument("--devices", default="1,2", help="device counts to compare (on the CPU, forced)")
    ap.add_argument("--platform", choices=("cpu", "gpu"), default="cpu")
    ap.add_argument("--out", default="results/benchmarks.md")
    ap.add_argument("--record", default="results/bench_devices.json")
    args = ap.parse_args(argv)
    command = " ".join(["python benchmarks/bench_devices.py", *(shlex.quote(a) for a in (argv or sys.argv[1:]))])
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        run_quadshank("simulate", "--out", str(tmp / "data"), "--legs", args.legs, "--minutes", str(args.minutes),
                      "--trials", "1")
        for n in (int(x) for x in args.devices.split(",")):
            if args.platform == "cpu":
                env = {"JAX_PLATFORMS": "cpu", "XLA_FLAGS": f"--xla_force_host_platform_device_count={n}"}
            else:  # the first n GPUs
                env = {"CUDA_VISIBLE_DEVICES": ",".join(str(i) for i in range(n))}
            out = tmp / f"fit{n}"
            seconds = run_quadshank("fit", str(tmp / "data"), "--model", args.model, "--chains", str(args.chains),
                                    "--warmup", str(args.warmup), "--draws", str(args.draws), "--out", str(out),
                                    env=env)
            s = json.loads((out / "summary.json").read_text())
            d = s["diagnostics"]
            rows.append({"devices": n, "chain_method": s["chain_method"], "seconds": round(seconds, 1),
                         "rhat_max": d["rhat_max"], "ess_bulk_min": d["ess_bulk_min"],
                         "bulk_ess_per_s": d["ess_bulk_min"] / seconds})
    record = {"command": command, "model": args.model, "legs": len(args.legs.split(",")), "minutes": args.minutes,
              "chains": args.chains, "warmup": args.warmup, "draws": args.draws, "platform": args.platform,
              "rows": rows}
    publish(record, args.record, args.out, SECTION, render)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
