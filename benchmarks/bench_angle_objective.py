"""Benchmark: a model with a muscle identified on the acceleration or on the angle, judged by J.

A simulated cohort (the built-in simulator, ``--legs`` × ``--minutes`` per trial, seed
``--seed``) is identified on trial 1 by the screen (``inference.laplace_fit``: each leg's MAP
and Laplace approximation, the start of every ``quadshank fit``) twice per model: with the
likelihood on the equivalent acceleration (equation error, the default) and on the angle
(``objective="angle"``: 1-s shooting segments from the measured state).  Each leg's model at its
mode, at its most probable delay, is then judged on trial 2 by J_φ,p at 100, 250, 500 and
1000 ms (``evaluation.prediction_errors``), the measure the paper and ``quadshank evaluate`` use.

    python benchmarks/bench_angle_objective.py [--legs 5] [--minutes 1] [--seed 2] [--out results/benchmarks.md]

Writes ``results/bench_angle_objective.json`` and the section ``bench_angle_objective`` of
``--out``.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
import warnings
from pathlib import Path

import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_md import write_section  # noqa: E402

from quadshank.common import atomic_write_text  # noqa: E402
from quadshank.data import LEGS, simulate_cohort  # noqa: E402
from quadshank.evaluation import horizon_samples, prediction_errors  # noqa: E402
from quadshank.inference import laplace_fit  # noqa: E402
from quadshank.model import paper_model  # noqa: E402

MODELS = ("model3s", "model3")
OBJECTIVES = ("acceleration", "angle")


def mode_model(fit, leg: str):
    """``leg``'s model at the screen's mode and its most probable delay."""
    values = {k: jnp.asarray(v, jnp.float32) for k, v in fit.values(leg).items() if k not in ("sigma", "nu")}
    d = int(np.argmax(fit.delay_posterior[fit.legs.index(leg)]))
    return fit.model.with_params(values, delay=d)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--legs", type=int, default=5, help="the first N of the simulator's legs")
    ap.add_argument("--minutes", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--out", default="results/benchmarks.md")
    args = ap.parse_args(argv)
    command = " ".join(["python benchmarks/bench_angle_objective.py", shlex.join(argv if argv is not None else sys.argv[1:])]).rstrip()

    legs = LEGS[: args.legs]
    cohort, _ = simulate_cohort(legs=legs, minutes=args.minutes, seed=args.seed, trials=(1, 2))
    period = cohort.trials[0].sampling_period_s
    horizons = horizon_samples(period)
    rows = []
    for name in MODELS:
        for objective in OBJECTIVES:
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                fit = laplace_fit(cohort, paper_model(name.removeprefix("model")), trials=(1,), objective=objective,
                                  loo=False)
            seconds = time.perf_counter() - t0
            per_leg = {}
            for leg in fit.legs:
                m = mode_model(fit, leg)
                J = prediction_errors(m, cohort.get(leg, 2), tuple(horizons.values()))
                per_leg[leg] = {"delay": int(m.delay), "J": {h: J[p] for h, p in horizons.items()}}
            mean = {h: float(np.mean([v["J"][h] for v in per_leg.values()])) for h in horizons}
            rows.append({"model": name, "objective": objective, "screen_s": seconds, "J_mean": mean, "legs": per_leg})
            print(name, objective, f"{seconds:.0f} s", {h: round(v, 2) for h, v in mean.items()}, flush=True)

    out = Path(args.out)
    atomic_write_text(out.parent / "bench_angle_objective.json",
                      json.dumps({"command": command, "legs": list(legs), "minutes": args.minutes, "seed": args.seed,
                                  "rows": rows}, indent=1))
    hs = list(horizons)
    lines = [
        "## A model with a muscle identified on the acceleration or on the angle, judged by J",
        "",
        f"`{command}`",
        "",
        f"The simulated cohort ({len(legs)} legs × {args.minutes:g} min, seed {args.seed}) identified on trial 1 by "
        "the screen (each leg's MAP), with the likelihood on the equivalent acceleration or on the angle "
        "(1-s shooting segments from the measured state); J on trial 2 from each leg's mode at its most "
        "probable delay, mean over legs [deg]. The delays are each leg's, in samples of 10 ms.",
        "",
        "| model | likelihood | " + " | ".join(f"J {h} ms" for h in hs) + " | delays | screen [s] |",
        "|---|---|" + "---:|" * len(hs) + "---|---:|",
    ]
    for r in rows:
        delays = ", ".join(str(v["delay"]) for v in r["legs"].values())
        lines.append(f"| {r['model']} | {r['objective']} | " + " | ".join(f"{r['J_mean'][h]:.2f}" for h in hs)
                     + f" | {delays} | {r['screen_s']:.0f} |")
    write_section(out, "bench_angle_objective", "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
