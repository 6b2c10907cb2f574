"""Benchmark: J_φ,p for one 5-minute trial, all starts, four horizons.

quadshank's vectorised JAX rollouts against a plain per-window NumPy loop
(benchmarks/reference_jphi.py), side by side in one run on the same trial.
The loop is timed on a slice of the starts and scaled to the whole trial
(its cost is exactly linear in the number of starts); JAX is timed on the
whole trial, after compilation (compile time reported separately).

    python benchmarks/bench_jphi.py [--minutes 5] [--loop-starts 1500] [--out results/benchmarks.md]
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from reference_jphi import j_phi_loop  # noqa: E402
from results_md import write_section  # noqa: E402

from quadshank.evaluation._prediction import prediction_errors  # noqa: E402
from quadshank.inference._identify import identify_leg  # noqa: E402
from quadshank.data._simulate import simulate_cohort  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--loop-starts", type=int, default=1500, help="starts timed for the loop (scaled to all)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default="results/benchmarks.md")
    args = ap.parse_args(argv)

    cohort, _ = simulate_cohort(legs=("TN-left",), minutes=args.minutes, seed=0, trials=(1, 2))
    model = identify_leg(cohort.get("TN-left", 1)).models["model3"]
    trial = cohort.get("TN-left", 2)
    n_starts = trial.n_samples - 100

    t0 = time.perf_counter()
    ours = prediction_errors(model, trial)
    t_first = time.perf_counter() - t0
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        ours = prediction_errors(model, trial)
        times.append(time.perf_counter() - t0)
    t_jax = float(np.median(times))

    p = model.flat_params()
    params = {**p, "damping": p["damping"], "gravity": p["gravity"]}
    k = min(args.loop_starts, n_starts)
    sl = slice(0, k + 100)
    t0 = time.perf_counter()
    j_phi_loop("model3", params, int(model.delay), trial.angle_deg[sl], trial.velocity_deg_s[sl], trial.stimulation[sl])
    t_loop = (time.perf_counter() - t0) * n_starts / k

    # agreement on the same slice
    from quadshank import Trial

    short = Trial.from_signals("TN", "left", 2, 0.01, trial.angle_deg[sl], trial.acceleration_deg_s2[sl],
                               trial.stimulation[sl], velocity_deg_s=trial.velocity_deg_s[sl])
    ref = j_phi_loop("model3", params, int(model.delay), short.angle_deg, short.velocity_deg_s, short.stimulation)
    mine = prediction_errors(model, short)
    max_rel = max(abs(mine[h] - ref[h]) / ref[h] for h in ref)

    speedup = t_loop / t_jax
    lines = [
        "## J_φ,p for one trial: vectorised JAX rollouts vs a per-window NumPy loop",
        "",
        f"Command: `python benchmarks/bench_jphi.py --minutes {args.minutes:g} --loop-starts {args.loop_starts}`",
        "",
        f"Machine: {platform.machine()}, {jax.devices()[0].platform.upper()} ({jax.__version__}), "
        f"Python {platform.python_version()}.",
        "",
        f"One {args.minutes:g}-minute trial (TN-left trial 2, simulated, seed 0), model 3 identified from trial 1, "
        f"{n_starts} starts × 100-step rollouts, read at p = 10, 25, 50, 100.",
        "",
        "| implementation | time per trial | ratio |",
        "|---|---|---|",
        f"| per-window NumPy loop (timed on {k} starts, scaled) | {t_loop:.1f} s | 1 |",
        f"| quadshank (JAX, after compilation; median of {args.repeats}) | {t_jax:.3f} s | {speedup:.0f}× faster |",
        f"| quadshank first call (includes compilation) | {t_first:.2f} s | |",
        "",
        f"Targets: ≥ 100× faster: {'met' if speedup >= 100 else 'NOT met'}; "
        f"< 0.5 s per trial after compilation: {'met' if t_jax < 0.5 else 'NOT met'}. "
        f"Largest relative difference in J between the two on {k} starts: {max_rel:.1e}.",
        "",
        "J_φ,p [deg] on the whole trial: " + ", ".join(f"{h * 10} ms: {v:.2f}" for h, v in ours.items()),
    ]
    block = "\n".join(lines)
    print(block)
    # one section per backend: a GPU run sits beside the CPU one
    write_section(args.out, "bench_jphi" if jax.default_backend() == "cpu" else f"bench_jphi_{jax.default_backend()}", block)
    return 0


if __name__ == "__main__":
    sys.exit(main())
