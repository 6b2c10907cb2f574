"""Benchmark: pendulum tests judged by the angle, for each way of identifying the passive system.

Simulated pendulum tests as a lab records them (``quadshank.data.simulate_pendulum_test``): the
shank released from 60° of extension with the examiner's hand pushing for 0.3 s, 8 s of angle at
10 ms with goniometer noise, no accelerometer (the acceleration derived from the angle), the
release marked excluded.  One leg per passive system of the simulated cohort.  Each is
identified four ways:

- ``identify --passive-objective acceleration``: equation error, eq. (8) on every quiet sample;
- ``identify`` (its default for pendulum tests): output error, the free swing fitted to the angle;
- a plain output-error least-squares fit of the same eq. (8), written here on its own (NumPy RK4,
  finite-difference Jacobian, started at the priors' medians) as the reference;
- ``fit --model passive``: the hierarchical Bayesian fit, posterior medians, once with its default
  likelihood for the pendulum alone (the angle of free runs from the measured state, output
  error) and once with ``--likelihood acceleration`` (equation error).

Each is judged by the angle: the free run from the measured state (``evaluation.free_run_error``)
and J at 100 ms and 1 s (``evaluation.prediction_errors``), all on the samples not excluded.  The
Bayesian fits are judged by their intervals too: how many of the truth's parameters (4 per test)
lie in the reported 90 % interval.

    python benchmarks/bench_pendulum.py [--noise 0.2] [--chains 2] [--warmup 500] [--draws 500] [--out results/benchmarks.md]
"""

from __future__ import annotations

import argparse
import shlex
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_md import write_section  # noqa: E402

from quadshank.commands.fit import run_fit  # noqa: E402
from quadshank.common._io import write_json  # noqa: E402
from quadshank.data import Cohort, simulate_pendulum_test  # noqa: E402
from quadshank.data._simulate import PASSIVE_TRUTH  # noqa: E402
from quadshank.evaluation import free_run_error, horizon_samples, prediction_errors  # noqa: E402
from quadshank.inference import FitSettings, identify_cohort, passive_model  # noqa: E402

NAMES = ("damping", "gravity", "k1", "k2")
RELEASE_S = 0.35


def reference_output_error(trial) -> dict:
    """Plain output-error least squares of eq. (8) on the samples not excluded: a NumPy RK4 free run
    from the first such sample's measured angle and velocity, scipy's finite-difference Jacobian,
    started at the priors' medians.  Written apart from the package, to check it against."""
    dt = trial.sampling_period_s
    k0 = int(np.flatnonzero(~trial.exclude)[0])
    measured = trial.angle_deg[k0:]
    keep = ~trial.exclude[k0:]

    def run(p):
        D, G, k1, k2 = np.exp(p)

        def f(a, v):
            return v, -D * v - G * np.sin(np.deg2rad(a)) + k1 * np.expm1(-k2 * a)

        a, v = trial.angle_deg[k0], trial.velocity_deg_s[k0]
        out = np.empty(measured.size)
        for k in range(measured.size):
            out[k] = a
            k1a, k1v = f(a, v)
            k2a, k2v = f(a + dt / 2 * k1a, v + dt / 2 * k1v)
            k3a, k3v = f(a + dt / 2 * k2a, v + dt / 2 * k2v)
            k4a, k4v = f(a + dt * k3a, v + dt * k3v)
            a, v = a + dt / 6 * (k1a + 2 * k2a + 2 * k3a + k4a), v + dt / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
        return (out - measured)[keep]

    fit = least_squares(run, np.log([1.0, 1800.0, 25.0, 0.05]), x_scale="jac")
    return dict(zip(NAMES, map(float, np.exp(fit.x))))


def judge(passive: dict, trial) -> dict:
    model = passive_model(passive, trial.sampling_period_s)
    h = horizon_samples(trial.sampling_period_s, (100, 1000))
    J = prediction_errors(model, trial, tuple(h.values()))
    return {"free_run_deg": free_run_error(model, trial), "J_100ms": J[h[100]], "J_1000ms": J[h[1000]]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--noise", type=float, default=0.2, help="goniometer noise [deg]")
    ap.add_argument("--chains", type=int, default=2)
    ap.add_argument("--warmup", type=int, default=500)
    ap.add_argument("--draws", type=int, default=500)
    ap.add_argument("--out", default="results/benchmarks.md")
    args = ap.parse_args(argv)
    command = " ".join(["python benchmarks/bench_pendulum.py", *(shlex.quote(a) for a in (argv or sys.argv[1:]))])
    warnings.simplefilter("ignore")

    trials = []
    for i, (leg, passive) in enumerate(PASSIVE_TRUTH.items()):
        subject = leg.replace("-", "")[:2] + str(i)  # one subject per test
        t = simulate_pendulum_test(passive, subject=subject, seed=i, angle_noise_deg=args.noise,
                                   acceleration_noise_deg_s2=None)
        trials.append((leg, t.replace(exclude=t.time_s < RELEASE_S)))
    cohort = Cohort(tuple(t for _, t in trials))

    methods: dict[str, dict] = {}
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    ident = identify_cohort(cohort, passive_objective="acceleration")
    seconds["equation error"] = time.perf_counter() - t0
    methods["equation error"] = {t.key: ident[t.key].passive for _, t in trials}
    t0 = time.perf_counter()
    ident = identify_cohort(cohort)
    seconds["output error"] = time.perf_counter() - t0
    methods["output error"] = {t.key: ident[t.key].passive for _, t in trials}
    t0 = time.perf_counter()
    methods["reference"] = {t.key: reference_output_error(t) for _, t in trials}
    seconds["reference"] = time.perf_counter() - t0
    fits, covered = {}, {}
    for likelihood in ("angle", "acceleration"):
        name = f"Bayesian fit, {likelihood}"
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            fits[likelihood] = fit = run_fit(cohort, tmp, model="passive", settings=FitSettings(
                chains=args.chains, warmup=args.warmup, draws=args.draws, likelihood=likelihood))
            seconds[name] = time.perf_counter() - t0
        methods[name] = {leg: {k: fit.legs[leg]["params"][k]["median"] for k in NAMES} for leg in fit.legs}
        covered[name] = [fit.legs[t.key]["params"][k]["lo"] <= PASSIVE_TRUTH[leg][k] <= fit.legs[t.key]["params"][k]["hi"]
                         for leg, t in trials for k in NAMES]

    scores = {name: {t.key: judge(p[t.key], t) for _, t in trials} for name, p in methods.items()}
    scores["truth"] = {t.key: judge(PASSIVE_TRUTH[leg], t) for leg, t in trials}
    labels = {
        "truth": "the truth (the simulator's parameters)",
        "equation error": "`identify --passive-objective acceleration` (equation error)",
        "output error": "`identify` (output error on the angle; its default for pendulum tests)",
        "reference": "plain output-error least squares (the reference, written in the benchmark)",
        **{f"Bayesian fit, {lik}": f"`fit --model passive{flag}` (likelihood on the {lik}; {args.chains} × "
                                   f"({args.warmup} + {args.draws}), posterior medians; checks "
                                   f"{'passed' if fits[lik].diagnostics['ok'] else 'failed'})"
           for lik, flag in (("angle", ""), ("acceleration", " --likelihood acceleration"))},
    }
    rows = []
    for name in ("truth", "equation error", "output error", "reference", "Bayesian fit, angle",
                 "Bayesian fit, acceleration"):
        per = scores[name]
        mean = {m: float(np.mean([v[m] for v in per.values()])) for m in ("free_run_deg", "J_100ms", "J_1000ms")}
        worst = float(max(v["free_run_deg"] for v in per.values()))
        inside = f"{sum(covered[name])} of {len(covered[name])}" if name in covered else "–"
        rows.append(f"| {labels[name]} | {mean['free_run_deg']:.3f} | {worst:.3f} | {mean['J_100ms']:.3f} | "
                    f"{mean['J_1000ms']:.3f} | {seconds.get(name, float('nan')):.1f} | {inside} |".replace("| nan |", "| – |"))
    def worst_ratio(name):
        return max(scores[name][k]["free_run_deg"] / scores["reference"][k]["free_run_deg"] for k in scores["reference"])

    text = "\n".join([
        "## Pendulum tests judged by the angle: output error, equation error, the Bayesian fit",
        "",
        f"Command: `{command}`",
        "",
        f"{len(trials)} simulated pendulum tests (one per passive system of the simulated cohort): released from "
        f"60° with the examiner's hand pushing for 0.3 s, 8 s at 10 ms, goniometer noise {args.noise:g}°, no "
        f"accelerometer, the first {RELEASE_S:g} s excluded. Errors in degrees on the samples not excluded, the "
        "mean over the tests (and the largest free-run error); seconds for all tests together.",
        "",
        "| identified by | free run (mean) | free run (largest) | J 100 ms | J 1 s | seconds | truth in the 90 % interval |",
        "|---|---|---|---|---|---|---|",
        *rows,
        "",
        "Against the reference, test by test, the free-run error of `identify` is at most "
        f"{worst_ratio('output error'):.3f} times the reference's, and that of `fit --model passive` (posterior "
        f"medians, likelihood on the angle) at most {worst_ratio('Bayesian fit, angle'):.3f} times. A calibrated "
        f"90 % interval holds the truth {0.9 * 4 * len(trials):.0f} times in {4 * len(trials)} on average.",
        "",
        *(f"- The checks of the fit on the {lik}: {fits[lik].banner or 'passed'}." for lik in ("angle", "acceleration")),
    ])
    write_section(args.out, "bench_pendulum", text)
    record = Path(args.out).with_name("bench_pendulum.json")
    write_json(record, {"command": command, "methods": methods, "scores": scores, "seconds": seconds,
                        "covered": covered, "banners": {lik: f.banner for lik, f in fits.items()}})
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
