"""Benchmark: one gradient of the fit's log density, the pulse-level path against one term per (pulse, lag).

The fit's potential (numpyro's negative log joint, the delay and the angle-delay
threshold summed out) of model 3 + angle_delay on the simulated cohort (5 legs,
trial 1 of 5 minutes), in double precision as the fit runs it, at its initial
point.  The two paths differ only in the arrays given: without the pulse-level
tables (``pulse_slot`` ...) the likelihood takes the (pulse, lag) path.  Both are
compiled first (compilation reported separately), then timed alternately,
``--repeats`` rounds of ``--calls`` calls each; the median round is reported, so
both see the same load on a shared machine.  Their values must agree.

    python benchmarks/bench_likelihood.py [--minutes 5] [--repeats 7] [--calls 30] [--out results/benchmarks.md]
"""

from __future__ import annotations

import argparse
import platform
import shlex
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_md import write_section  # noqa: E402

from quadshank.inference._priors import build_model
from quadshank.inference._density import numpyro_model
from quadshank.model._likelihood import PULSE_LEVEL_FIELDS, prepare  # noqa: E402
from quadshank.data._paper import LEGS  # noqa: E402
from quadshank.data._simulate import simulate_cohort  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--legs", default=",".join(LEGS[:5]))
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--calls", type=int, default=30)
    ap.add_argument("--out", default="results/benchmarks.md")
    args = ap.parse_args(argv)
    command = " ".join(["python benchmarks/bench_likelihood.py", *(shlex.quote(a) for a in (argv or sys.argv[1:]))])
    from numpyro.infer.util import initialize_model

    legs = [x for x in args.legs.split(",") if x]
    cohort, _ = simulate_cohort(legs=legs, minutes=args.minutes, seed=0, effects=["angle_delay"], trials=(1,))
    model = build_model("model3", ["angle_delay"])
    data = prepare(cohort, model, trials=(1,))
    if data.pulse_slot is None:
        raise SystemExit("the pulse-level path does not apply to this data")
    with jax.enable_x64(True):
        arrays = {k: v.astype(jnp.float64) if jnp.issubdtype(v.dtype, jnp.floating) else v for k, v in data.leg_arrays().items()}
        paths = {"pulse level": arrays, "(pulse, lag)": {k: v for k, v in arrays.items() if k not in PULSE_LEVEL_FIELDS}}
        funcs, values, compile_s = {}, {}, {}
        for name, x in paths.items():
            info = initialize_model(jax.random.PRNGKey(0), lambda a: numpyro_model(model, data, a), model_args=(x,))
            z = info.param_info.z
            f = jax.jit(jax.value_and_grad(info.potential_fn))
            t = time.perf_counter()
            values[name] = float(jax.block_until_ready(f(z))[0])
            compile_s[name] = time.perf_counter() - t
            funcs[name] = (f, z)
        if not np.isclose(values["pulse level"], values["(pulse, lag)"], rtol=1e-10):
            raise SystemExit(f"the two paths disagree: {values}")
        rounds = {name: [] for name in paths}
        for _ in range(args.repeats):
            for name, (f, z) in funcs.items():
                t = time.perf_counter()
                for _ in range(args.calls):
                    out = f(z)
                jax.block_until_ready(out)
                rounds[name].append((time.perf_counter() - t) / args.calls)
    ms = {name: 1e3 * float(np.median(r)) for name, r in rounds.items()}
    ratio = ms["(pulse, lag)"] / ms["pulse level"]
    P = int((data.pulse_u > 0).sum())
    text = f"""## The fit's gradient: pulse-level path against one term per (pulse, lag)

Regenerate: `{command}`

Machine: {platform.machine()}, {jax.default_backend().upper()} (jax {jax.__version__}), Python {platform.python_version()}.
One value and gradient of the fit's log density (model 3 + angle_delay, delay and threshold summed out,
double precision) on the simulated cohort, {len(legs)} legs × {args.minutes:g} min of trial 1
({P} pulses in all, {int(data.sample_mask.sum())} samples compared), at numpyro's initial point.
Median of {args.repeats} alternating rounds of {args.calls} calls.  The two values agree
({values['pulse level']:.6f} and {values['(pulse, lag)']:.6f}).

| path | value and gradient [ms] | first call, with compilation [s] |
|---|---|---|
| pulse level (twitch windows) | {ms['pulse level']:.2f} | {compile_s['pulse level']:.1f} |
| one term per (pulse, lag) | {ms['(pulse, lag)']:.2f} | {compile_s['(pulse, lag)']:.1f} |

The pulse-level path is {ratio:.1f} times faster.
"""
    write_section(args.out, "bench_likelihood", text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
