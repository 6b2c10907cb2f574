"""Benchmark: the hierarchical NUTS fit and the posterior bands on J_φ,p.

The default configuration is the full size: model 3 with the angle-dependent
delay on the simulated cohort (5 legs, trial 1 of 5 minutes, data simulated
with the delay step), 4 chains × 1000 draws after 1000 warm-up; then J_φ,p
for 200 posterior draws on all 15 trials, every start, four horizons.
Smaller sizes are arguments, and the section written records what ran.

Compilation is timed separately: JAX reports the duration of every trace,
lowering and backend compile through ``jax.monitoring``, and their sum is
subtracted from the wall time of the same call.

    python benchmarks/bench_fit.py [--legs ...] [--minutes 5] [--chains 4] [--warmup 1000] [--draws 1000]
        [--j-draws 200] [--out results/benchmarks.md]

The peer is the same model written in PyMC (benchmarks/peer_pymc.py) and
sampled by nutpie, on the same data with the same chains, warm-up and draws;
it needs the optional ``bench`` extra (``pip install -e ".[bench]"``).  Its
log density is checked against quadshank's at a common point first.  nutpie
runs its chains in parallel threads, numpyro here as the fit runs them
(``--chain-method auto``, the default: one after another at the full size,
one batched program on small data): the comparison is ESS per second of wall
time, each sampler used as it is meant to be.  ``--no-peer`` skips it.
"""

from __future__ import annotations

import argparse
import json
import platform
import shlex
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

import arviz as az
import jax
import numpy as np

from quadshank.inference._nuts import (
    CHAIN_METHODS,
    STARTS,
    FitSettings,
    uses_screen,
)
from quadshank.inference._priors import build_model
from quadshank.inference._fitio import THRESHOLDS
from quadshank.common._io import write_json
from quadshank.data._paper import LEGS
import quadshank.inference._nuts as fit_module
from quadshank.commands.fit import run_fit
from quadshank.evaluation._posterior import load_fits, posterior_j
from quadshank.data._simulate import simulate_cohort

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_md import write_section  # noqa: E402


_COMPILE_EVENTS = (
    "/jax/core/compile/jaxpr_trace_duration",
    "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "/jax/core/compile/backend_compile_duration",
)


class CompileClock:
    """Seconds JAX spent tracing, lowering and compiling while the clock was on."""

    def __init__(self):
        self.seconds = 0.0
        self.on = False
        jax.monitoring.register_event_duration_secs_listener(self._listen)

    def _listen(self, event, duration, **kwargs):
        if self.on and event in _COMPILE_EVENTS:
            self.seconds += duration

    def timed(self, fn, *args, **kwargs):
        self.seconds, self.on = 0.0, True
        t0 = time.perf_counter()
        try:
            out = fn(*args, **kwargs)
        finally:
            self.on = False
        return out, time.perf_counter() - t0, self.seconds


def _start_at(compiled, starts: dict, chains: int):
    """``compiled`` with its chains started at ``starts`` (unconstrained values per chain, keyed by
    numpyro's site names, as :func:`quadshank.inference._nuts.screen_start` gives them) in place of nutpie's
    jittered default.  nutpie asks for one start per chain (again where a start's density is not
    finite); the k-th request gets chain k mod ``chains``'s values, so the peer's chains start at
    the points the fit's chains started at."""
    import dataclasses
    import threading

    # shape_info lists the unconstrained values (the first n_dim entries, in the order nutpie's
    # start vector takes them), then the constrained values it also stores
    free = [(n, shape) for n, sl, shape in zip(*compiled.shape_info, strict=True) if sl.stop <= compiled.n_dim]
    rows = []
    for c in range(chains):
        parts = []
        for name, shape in free:
            v = np.asarray(starts[name.removesuffix("_log__")][c], np.float64)
            if v.size != int(np.prod(shape)):
                raise ValueError(f"the fit's start for {name} has shape {v.shape}, the PyMC model's {tuple(shape)}")
            parts.append(v.ravel())
        rows.append(np.concatenate(parts))
    if rows[0].size != compiled.n_dim:
        raise ValueError(f"the fit's start has {rows[0].size} values, the PyMC model {compiled.n_dim}")
    lock, asked = threading.Lock(), [0]

    def start(seed=None):
        with lock:
            k, asked[0] = asked[0], asked[0] + 1
        return rows[k % chains].copy()

    return dataclasses.replace(compiled, initial_point_func=start)


PEER_METRICS = {
    "low_rank": "its low-rank modified mass matrix (`--peer-metric low_rank`)",
    "diag": "its diagonal mass matrix (`--peer-metric diag`)",
}


def run_peer(cohort, model_name: str, effects, settings, starts: dict | None = None, metric: str = "low_rank") -> dict:
    """The same model in PyMC sampled by nutpie: timings and diagnostics, or the reason it could not run.

    ``starts``: the fit's starting points (see :func:`_start_at`); None leaves nutpie's own start.
    ``metric``: the mass matrix nutpie adapts in warm-up, a key of :data:`PEER_METRICS` (low_rank:
    a diagonal metric updated along the directions where draws and gradients show correlation, nutpie's
    answer to a dense metric)."""
    try:
        import nutpie
        import pymc
    except ImportError as exc:
        return {"error": f"{exc.name} is not installed (pip install -e '.[bench]')"}
    from numpyro.infer import init_to_median
    from numpyro.infer.util import initialize_model

    from peer_pymc import build_pymc_model, check_same_density

    from quadshank.inference._density import numpyro_model
    from quadshank.model._likelihood import prepare

    m = build_model(model_name, effects)
    data = prepare(cohort, m, trials=settings.trials)
    arrays = data.leg_arrays()
    info, potential, _, _ = initialize_model(
        jax.random.PRNGKey(settings.seed), lambda a: numpyro_model(m, data, a), model_args=(arrays,),
        init_strategy=init_to_median(num_samples=15), dynamic_args=False,
    )  # fmt: skip
    point = {k: np.asarray(v, np.float64) for k, v in info.z.items()}
    pm_model = build_pymc_model(m, data)
    check = check_same_density(pm_model, potential, point)
    if not abs(check[0] - check[1]) <= 1e-4 * abs(check[1]) + 1e-2:
        return {"error": f"the PyMC model's log density {check[0]:.3f} differs from quadshank's {check[1]:.3f}"}
    t0 = time.perf_counter()
    compiled = nutpie.compile_pymc_model(pm_model, backend="numba")
    compile_s = time.perf_counter() - t0
    if starts is not None:
        compiled = _start_at(compiled, starts, settings.chains)
    t0 = time.perf_counter()
    trace = nutpie.sample(compiled, draws=settings.draws, tune=settings.warmup, chains=settings.chains,
                          seed=settings.seed, progress_bar=False,
                          low_rank_modified_mass_matrix=metric == "low_rank")  # fmt: skip
    sampling_s = time.perf_counter() - t0
    names = [v.name for v in pm_model.free_RVs]
    post = trace.posterior[names]
    ess = float(az.ess(post, method="bulk").to_array().min())
    rhat = float(az.rhat(post).to_array().max()) if settings.chains > 1 else float("nan")
    return {
        "pymc": pymc.__version__,
        "nutpie": nutpie.__version__,
        "backend": "numba",
        "density_check": list(check),
        "compile_s": compile_s,
        "sampling_s": sampling_s,
        "rhat_max": rhat,
        "ess_bulk_min": ess,
        "divergences": int(trace.sample_stats["diverging"].sum()),
        "ess_bulk_min_per_s": ess / sampling_s,
        "start": "nutpie" if starts is None else "fit",
        "metric": metric,
        "steps_per_draw": float(trace.sample_stats["n_steps"].mean()),
    }


def _ratio(x: float) -> str:
    return f"{x:.0f}" if abs(x) >= 100 else f"{x:.3g}"


def _converged(rhat: float, ess: float, divergences: int, chains: int) -> bool:
    """The fit's own thresholds (``_fitio.THRESHOLDS``) on R-hat, bulk ESS and divergences, for the peer."""
    th = THRESHOLDS
    return rhat < th["rhat_max"] and ess >= th["ess_per_chain"] * chains and divergences <= th["divergences"]


def render(record: dict, section: str) -> str:
    """The section of results/benchmarks.md for one run, from its JSON record alone."""
    r = record
    effects, legs, peer = r["effects"], r["legs"], r["peer"]
    sampling, compile_s, evidence_s = r["fit_sampling_s"], r["fit_compile_s"], r["delay_evidence_s"]
    ess_per_s = r["ess_bulk_min_per_s"]
    full = (len(legs), r["minutes"], r["chains"], r["warmup"], r["draws"]) == (5, 5.0, 4, 1000, 1000)
    if peer is None or "error" in peer:
        against = "no peer"
    else:
        against = (f"the peer with {PEER_METRICS[peer.get('metric', 'diag')].split(' (')[0]} from "
                   + ("the same starts" if peer.get("start") == "fit" else "its own starts"))
    t = [
        # the configuration in the title: the sections of several runs stand apart in the contents
        f"## Hierarchical fit and posterior J bands: {len(legs)} legs × {r['minutes']:g} min, "
        f"{r['chains']} × ({r['warmup']} + {r['draws']}), {r['chain_method']} chains from the {r['start']}, {against}",
        "",
        f"Command: `{r['command']}`",
        "",
        f"Machine: {r['machine']}. Record: `{section}.json` beside this file "
        f"(`python benchmarks/bench_fit.py --from-record results/{section}.json` writes this section again from it).",
        "",
        f"{r['model']} + {', '.join(effects) or 'nothing'} on the simulated cohort ({len(legs)} legs, trial 1 of "
        f"{r['minutes']:g} min, data simulated with {', '.join(effects) or 'no hidden effect'}), "
        f"{r['chains']} chains ({r['chain_method']}) × {r['draws']} draws after {r['warmup']} warm-up, "
        f"chains started from the {r['start']} (`--start {r['start']}`)"
        + (f", the density at {r['precision']} precision" if r.get("precision") else "")
        + ("" if full else " — **smaller than the full configuration (5 legs × 5 min, 4 × 1000 + 1000)**")
        + ".",
        "",
        "| measure | value | target |",
        "|---|---|---|",
        f"| fit wall time less compilation (sampling; also finding the start and saving) | {sampling:.0f} s | ≤ 60 s (full size) |",
        f"| compilation | {compile_s:.0f} s | reported separately |",
        f"| each leg's delays weighed by a Laplace approximation per delay (before sampling, less compilation; not in the row above) | "
        f"{evidence_s:.0f} s | – |",
        f"| R-hat max | {r['rhat_max']:.3f} | < 1.01 |",
        f"| bulk ESS min | {r['ess_bulk_min']:.0f} | ≥ 400 |",
        f"| divergences | {r['divergences']} | 0 |",
        f"| bulk ESS min per second of sampling | {ess_per_s:.3g} | ≥ the peer's |",
    ]
    if r["j_wall_s"] is not None:
        t.append(
            f"| posterior J: {r['j_draws']} draws × {r['j_trials']} trials, every start, 4 horizons | "
            f"{r['j_wall_s'] - r['j_compile_s']:.0f} s (+ {r['j_compile_s']:.0f} s compilation) | ≤ 30 s (full size) |"
        )
    t.append("")
    if peer is None:
        t.append("Peer (the same model in PyMC sampled by nutpie): not run (`--no-peer`).")
    elif "error" in peer:
        t.append(f"Peer (the same model in PyMC sampled by nutpie): not run: {peer['error']}.")
    else:
        ratio = ess_per_s / peer["ess_bulk_min_per_s"] if peer["ess_bulk_min_per_s"] > 0 else float("nan")
        t += [
            f"Peer: the same model in PyMC {peer['pymc']} sampled by nutpie {peer['nutpie']} ({peer['backend']} backend, "
            f"chains in parallel threads"
            + f", {PEER_METRICS[peer.get('metric', 'diag')]}"  # records from before the option: diag
            + "), same data, chains, warm-up and draws, "
            + ("its chains started at the points the fit's chains started at (`--peer-start fit`). "
               if peer.get("start") == "fit" else "its chains started at nutpie's own jittered defaults (`--peer-start nutpie`). ")
            + "Log densities at a common point: "
            f"quadshank {peer['density_check'][1]:.3f}, PyMC {peer['density_check'][0]:.3f}.",
            "",
            "| | quadshank (numpyro NUTS) | PyMC + nutpie |",
            "|---|---|---|",
            f"| compilation | {compile_s:.0f} s | {peer['compile_s']:.0f} s |",
            f"| sampling wall time | {sampling:.0f} s | {peer['sampling_s']:.0f} s |",
            f"| R-hat max | {r['rhat_max']:.3f} | {peer['rhat_max']:.3f} |",
            f"| bulk ESS min | {r['ess_bulk_min']:.0f} | {peer['ess_bulk_min']:.0f} |",
            f"| divergences | {r['divergences']} | {peer['divergences']} |",
            f"| bulk ESS min per second | {ess_per_s:.3g} | {peer['ess_bulk_min_per_s']:.3g} |",
        ]
        if r.get("steps_per_draw") is not None and "steps_per_draw" in peer:
            t.append(f"| leapfrog steps per draw (after warm-up) | {r['steps_per_draw']:.1f} | {peer['steps_per_draw']:.1f} |")
        t += [
            "",
            f"quadshank's ESS per second is {_ratio(ratio)}× the peer's (target: ≥ 1).",
        ]
        peer_ok = _converged(peer["rhat_max"], peer["ess_bulk_min"], peer["divergences"], r["chains"])
        if not peer_ok:
            both = "" if r["ok"] else " Neither fit has converged."
            t.append(
                f"The peer's fit fails the same checks (R-hat < {THRESHOLDS['rhat_max']}, "
                f"bulk ESS ≥ {THRESHOLDS['ess_per_chain'] * r['chains']}, no divergences): "
                "its chains have not mixed, so the ratio compares against a sample that does not describe the "
                f"posterior and measures little.{both}"
            )
    t += [
        "",
        "The fit " + ("passed its checks." if r["ok"] else "FAILED its checks: " + "; ".join(r["problems"]) + "."),
        "",
        "Delay mode per leg [samples]: " + ", ".join(f"{k} {v}" for k, v in r["delay_mode"].items()) + ".",
    ]
    return "\n".join(t)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="model3")
    ap.add_argument("--add-effect", action="append", default=None, help="default: angle_delay")
    ap.add_argument("--legs", default=",".join(LEGS))
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--chains", type=int, default=4)
    ap.add_argument("--warmup", type=int, default=1000)
    ap.add_argument("--draws", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--j-draws", type=int, default=200, help="posterior draws for the J bands (0: skip)")
    ap.add_argument("--no-peer", action="store_true", help="skip the PyMC + nutpie peer")
    ap.add_argument("--peer-start", default="fit", choices=("fit", "nutpie"),
                    help="where the peer's chains start: where the fit's chains started (fit: with --start screen), "
                         "or nutpie's own jittered default")
    ap.add_argument("--peer-metric", default="low_rank", choices=tuple(PEER_METRICS),
                    help="the mass matrix nutpie adapts: low_rank (its best for correlated posteriors) or diag")
    ap.add_argument("--start", default="screen", choices=STARTS,
                    help="where the chains start (quadshank fit --start); each start has its own section")
    ap.add_argument("--chain-method", default=FitSettings.chain_method, choices=CHAIN_METHODS)
    ap.add_argument("--precision", default=FitSettings.precision, choices=("mixed", "double"),
                    help="the precision of the sampled density's terms (quadshank fit --precision)")
    ap.add_argument("--out", default="results/benchmarks.md")
    ap.add_argument("--section", default=None,
                    help="name of the section (and JSON record) written; default bench_fit[_backend][_start]")
    ap.add_argument("--from-record", default=None, metavar="JSON",
                    help="write the section again from a run's JSON record (its name is the section's), "
                         "without running anything")
    args = ap.parse_args(argv)
    if args.from_record:
        path = Path(args.from_record)
        write_section(args.out, path.stem, render(json.loads(path.read_text()), path.stem))
        return 0
    effects = args.add_effect if args.add_effect is not None else ["angle_delay"]
    legs = [x for x in args.legs.split(",") if x]
    command = "python benchmarks/bench_fit.py " + " ".join(shlex.quote(a) for a in (argv or sys.argv[1:]))

    clock = CompileClock()
    cohort, _ = simulate_cohort(legs=legs, minutes=args.minutes, seed=args.seed, effects=effects, trials=(1, 2, 3))
    settings = FitSettings(
        chains=args.chains, warmup=args.warmup, draws=args.draws, seed=args.seed, chain_method=args.chain_method,
        start=args.start, precision=args.precision,
    )
    if args.peer_start == "fit" and not args.no_peer and not uses_screen(build_model(args.model, effects), settings):
        ap.error("--peer-start fit needs the fit's chains to start from the screen (--start screen, and every "
                 "parameter at the leg level); use --peer-start nutpie")
    # the per-delay Laplace evidence runs before sampling: its time (less its compilation, which
    # the compilation row holds) is reported on its own, not as sampling
    evidence = {"wall": 0.0, "compile": 0.0}
    evidence_fn = fit_module.delay_modes

    def timed_evidence(*a, **k):
        c0, t0 = clock.seconds, time.perf_counter()
        out = evidence_fn(*a, **k)
        evidence.update(wall=time.perf_counter() - t0, compile=clock.seconds - c0)
        return out

    fit_module.delay_modes = timed_evidence  # what delay_start calls
    # the fit's starting points, for the peer's chains (--peer-start fit)
    fit_starts = {}
    screen_start = fit_module.screen_start

    def kept_start(*a, **k):
        init_params, imm = screen_start(*a, **k)
        fit_starts.update({name: np.asarray(v) for name, v in init_params.items()})
        return init_params, imm

    fit_module.screen_start = kept_start
    with tempfile.TemporaryDirectory() as tmp:
        fit_dir = Path(tmp) / "fit"
        summary, wall, compile_s = clock.timed(run_fit, cohort, fit_dir, args.model, effects, settings, progress=True)
        diag = summary.diagnostics
        stats = az.from_netcdf(fit_dir / "fit.nc").sample_stats
        steps_per_draw = float(stats["n_steps"].mean()) if "n_steps" in stats else None
        evidence_s = evidence["wall"] - evidence["compile"]
        sampling = wall - compile_s - evidence_s
        j_wall = j_compile = None
        if args.j_draws:
            fits = load_fits([fit_dir])
            _, j_wall, j_compile = clock.timed(posterior_j, fits, cohort, n_draws=args.j_draws, progress=True)
    starts = fit_starts if args.peer_start == "fit" else None
    peer = None if args.no_peer else run_peer(cohort, args.model, effects, settings, starts, args.peer_metric)
    n_trials = len(cohort.trials)
    ess_per_s = diag["ess_bulk_min"] / sampling if sampling > 0 else float("nan")
    record = {
        "command": command,
        "date": date.today().isoformat(),
        "machine": f"{platform.machine()}, {jax.default_backend().upper()} (jax {jax.__version__}), Python {platform.python_version()}",
        "model": args.model,
        "effects": effects,
        "legs": legs,
        "minutes": args.minutes,
        "chains": args.chains,
        "chain_method": summary.chain_method,
        "precision": args.precision,
        "start": args.start,
        "warmup": args.warmup,
        "draws": args.draws,
        "fit_wall_s": wall,
        "fit_compile_s": compile_s,
        "fit_sampling_s": sampling,
        "delay_evidence_s": evidence_s,
        "ok": diag["ok"],
        "problems": diag["problems"],
        "rhat_max": diag["rhat_max"],
        "ess_bulk_min": diag["ess_bulk_min"],
        "ess_tail_min": diag.get("ess_tail_min"),
        "divergences": diag["divergences"],
        "ess_bulk_min_per_s": ess_per_s,
        "steps_per_draw": steps_per_draw,
        "delay_mode": {leg: s["delay_mode_samples"] for leg, s in summary.legs.items()},
        "j_draws": args.j_draws,
        "j_trials": n_trials,
        "j_wall_s": j_wall,
        "j_compile_s": j_compile,
        "peer": peer,
    }
    # one section (and JSON record) per backend and start: a GPU run sits beside the CPU one
    section = "bench_fit" if jax.default_backend() == "cpu" else f"bench_fit_{jax.default_backend()}"
    if args.start != "classical":
        section += f"_{args.start}"
    section = args.section or section
    write_json(Path(args.out).with_name(f"{section}.json"), record)

    write_section(args.out, section, render(record, section))
    print(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
