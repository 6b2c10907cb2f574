"""``quadshank demo``: the package's whole path on the built-in simulated cohort, in a few minutes.

Five steps, each in its own folder under ``out``:

1. ``reproduce/``: the paper's section 7 (simulate the cohort, classical
   identification, Table V) — :func:`quadshank.commands.reproduce.run_reproduce`;
2. ``fit/``: a hierarchical NUTS fit of the loop's baseline (``model3s`` with the
   noise term for twitches that vary from pulse to pulse, ``twitch_variability``) to trial 1
   of two legs of two subjects (so the report can show shrinkage), simulated again
   with one effect hidden (``hidden``, a torque–angle maximum by default; ``loop-data/``) that
   ``model3s`` lacks;
3. ``evaluate/``: J_φ,p over posterior draws, trials 1–3, with PSIS-LOO;
4. ``diagnose/``: the modelling loop's question, which effect is missing, screened
   over the five effects of the paper's discussion: it should name the hidden
   effect, and its sentence says how far adding it lowers J;
5. ``report/``: the per-subject credible-parameter pages (``report/index.html``).

The sizes are the demo's (short trials, trees of at most 31 leapfrog steps, a
screen from one start per extension): small enough for a few minutes on a 2-core
CPU.  The fit draws to a target ESS (:attr:`FitSettings.target_ess`) in blocks
until it passes its checks or its time limit would pass; where it stops short, the
report says so at the top of every page, as it would for any fit.  ``summary.json``
(written last) records every step's folder, its seconds and the fit's checks.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import ClassVar

from ..common._io import atomic_write_text
from ..common._results import Result
from ..data._interchange import load_cohort, write_interchange
from ..data._paper import LEGS
from ..data._simulate import TWITCH_CV, check_effects, simulate_cohort, write_truth
from ..inference._nuts import FitSettings
from ..inference._priors import build_model
from ..outputs._tables import markdown_table
from .diagnose import run_diagnose
from .evaluate import run_posterior_evaluate
from .fit import run_fit
from .report import run_report
from .reproduce import run_reproduce

__all__ = ["Demo", "run_demo", "how_drawn", "DEMO_LEGS", "DEMO_EFFECTS"]


@dataclasses.dataclass
class Demo(Result):
    """What ``quadshank demo`` did: each step's folder and time, the fit's checks, the verdict."""

    KIND: ClassVar[str] = "demo"

    command: str
    minutes: float
    seed: int
    effects: list  # hidden in the simulated cohort
    hidden: list  # hidden besides in the legs the loop is shown on (fit, evaluate, diagnose)
    found: bool | None  # the diagnosis named the hidden effect (None: nothing hidden)
    legs: list
    fit_legs: list
    fit_settings: dict
    fit_ok: bool  # the short fit passed its sampling checks
    fit_banner: str | None
    verdict: str  # the diagnosis's
    recovery_ok: bool  # the reproduction's
    report: str  # the report's index page
    folders: dict  # step -> folder
    seconds: dict  # step -> seconds
    report_pages: dict
    twitch_cv: float | None = None  # the twitches' variation from pulse to pulse in the simulation

#: Legs of the demo's fit: two subjects, so subject and population levels differ.
DEMO_LEGS = ("TN-left", "JM-left")
#: Each extension's mode sought from the baseline's mode only (no prior draw besides the median:
#: half the screen's work of ``discover``'s default); the loop's tests find each hidden effect this way.
DEMO_N_STARTS = 0
#: The model fitted and diagnosed: the loop's baseline on twitches that vary (the simulator's default).
DEMO_BASELINE = ("model3s", ("twitch_variability",))
#: Candidates screened by the demo's diagnosis: the effects the paper's discussion names.
DEMO_EFFECTS = ("torque_angle_peak", "hill_velocity", "angle_delay", "fatigue", "potentiation")


def how_drawn(fit, warmup: int) -> str:
    """How the demo's fit drew, in words: to its target ESS (and how that ended) or a fixed number of draws."""
    draws = fit.diagnostics["draws"]
    if fit.target is None:
        return f"{draws} draws after {warmup} warm-up"
    t = fit.target
    return (f"{draws} draws per chain after {warmup} warm-up, drawn in {t['blocks']} block(s) to a target ESS of "
            f"{t['target_ess']} ({t['stopped']}, {t['seconds']:.0f} s)")


def run_demo(
    out: str | Path,
    *,
    minutes: float = 1.5,
    seed: int = 0,
    effects=(),
    hidden=("torque_angle_peak",),
    legs=None,
    chains: int = 2,
    warmup: int = 150,
    draws: int = 100,
    max_tree_depth: int = 5,
    target_ess: int | None = 200,
    time_limit_s: float = 150.0,
    progress: bool = False,
    command: str = "",
    twitch_cv: float = TWITCH_CV,
) -> Demo:
    """Reproduce, fit, evaluate, diagnose, report; returns the summary (also ``out/summary.json``).

    ``effects``: hidden in the whole simulated cohort; ``hidden``: hidden besides in the legs the
    loop is shown on, which are simulated again with them (the reproduction stays the paper's).
    ``target_ess``, ``time_limit_s``: the fit draws blocks of ``draws`` per chain to this ESS or
    until this many seconds from its start (None: exactly ``warmup`` + ``draws``)."""

    # every option checked before the first step writes anything
    check_effects((*effects, *hidden))
    settings = FitSettings(chains=chains, warmup=warmup, draws=draws, seed=seed, max_tree_depth=max_tree_depth,
                           target_ess=target_ess, time_limit_s=time_limit_s)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").unlink(missing_ok=True)
    legs = tuple(legs or LEGS)
    fit_legs = DEMO_LEGS if set(DEMO_LEGS) <= set(legs) else legs[:2]
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()

    def step(name: str) -> None:
        nonlocal t0
        now = time.perf_counter()
        seconds[name] = now - t0
        t0 = now

    def say(text: str) -> None:
        if progress:
            print(f"demo: {text}", flush=True)

    say(f"1/5 the paper's reproduction: {len(legs)} legs, {minutes:g} min per trial -> {out / 'reproduce'}")
    rep = run_reproduce(out / "reproduce", minutes=minutes, seed=seed, effects=effects, legs=legs,
                        progress=progress, command=command, twitch_cv=twitch_cv)
    step("reproduce")

    data = out / "reproduce" / "data"
    hidden = tuple(h for h in hidden if h not in effects)
    if hidden:
        say(f"   the loop's legs {', '.join(fit_legs)} simulated again with {', '.join(hidden)} hidden -> {out / 'loop-data'}")
        loop_cohort, truth = simulate_cohort(legs=fit_legs, minutes=minutes, seed=seed, effects=(*effects, *hidden),
                                             twitch_cv=twitch_cv)
        data = write_interchange(loop_cohort, out / "loop-data", overwrite=True)
        write_truth(truth, data / "truth.json")
    cohort = load_cohort(data)

    base_name, base_effects = DEMO_BASELINE
    baseline = build_model(base_name, base_effects, sampling_period_s=cohort.sampling_period_s)
    base_label = baseline.name  # "model3s+twitch_variability"
    say(f"2/5 hierarchical NUTS fit of {base_label} to trial 1 of {', '.join(fit_legs)} -> {out / 'fit'}")
    fit = run_fit(cohort, out / "fit", base_name, base_effects, settings, legs=fit_legs, progress=progress,
                  data_source=str(data.resolve()))
    step("fit")

    say(f"3/5 J over posterior draws, trials 1-3 -> {out / 'evaluate'}")
    fit_cohort = cohort.select(legs=fit_legs)
    run_posterior_evaluate(fit_cohort, [out / "fit"], out / "evaluate", n_draws=50, start_stride=10,
                           progress=progress)
    step("evaluate")

    say(f"4/5 which effect is missing: {', '.join(DEMO_EFFECTS)} screened"
        + (f" ({', '.join(hidden)} is hidden)" if hidden else "") + f" -> {out / 'diagnose'}")
    diag = run_diagnose(fit_cohort, baseline, out / "diagnose", legs=fit_legs, effects=DEMO_EFFECTS,
                        command=command, progress=progress, seed=seed, n_starts=DEMO_N_STARTS)
    step("diagnose")

    say(f"5/5 credible-parameter report -> {out / 'report'}")
    report = run_report(out / "fit", out / "report", cohort=fit_cohort, evaluation=out / "evaluate",
                        diagnosis=out / "diagnose", progress=progress)
    step("report")

    diagnostics = fit.diagnostics
    summary = Demo(
        command=command, minutes=minutes, seed=seed, effects=list(effects), hidden=list(hidden),
        found=(diag.verdict in hidden) if hidden else None, legs=list(legs), fit_legs=list(fit_legs),
        fit_settings={"model": base_label, "chains": chains, "warmup": warmup, "draws": draws,
                      "max_tree_depth": max_tree_depth, "trials": [1], "target_ess": target_ess,
                      "time_limit_s": time_limit_s},
        fit_ok=bool(diagnostics["ok"]), fit_banner=fit.banner, verdict=diag.verdict, recovery_ok=rep.recovery_ok,
        report=str(out / "report" / "index.html"),
        folders={k: str(out / k) for k in ("reproduce", "fit", "evaluate", "diagnose", "report")},
        seconds=seconds, report_pages=report.pages, twitch_cv=float(twitch_cv),
    )
    lines = [
        "# quadshank demo",
        "",
        f"Made by: `{command}`" if command else "",
        "",
        f"The built-in simulated cohort ({len(legs)} legs, {minutes:g} min per trial, seed {seed}, twitches varying "
        f"by a CV of {twitch_cv:g} from pulse to pulse, effects hidden in every leg: {', '.join(effects) or 'none'}).",
        "",
        *markdown_table([{"step": k, "folder": f"`{k}/`", "seconds": f"{v:.0f}"} for k, v in seconds.items()]).splitlines(),
        "",
        f"- Reproduction: parameters within tolerance of the truth: {'yes' if rep.recovery_ok else 'NO'} "
        "(`reproduce/report.md`).",
        f"- Fit: {base_label} on trial 1 of {', '.join(fit_legs)}, {chains} chains, {how_drawn(fit, warmup)} "
        f"(tree depth {max_tree_depth}): "
        + ("passed its checks." if diagnostics["ok"] else f"**{fit.banner}** — chains this short are a demo, "
           "not a result; see the advice in `fit/summary.json`."),
        (f"- The loop: {', '.join(hidden)} hidden in the legs fitted (`loop-data/`); the diagnosis "
         + ("found it" if diag.verdict in hidden else "did **not** find it") + "." if hidden else
         "- The loop: nothing hidden in the legs fitted."),
        f"- Diagnosis: verdict `{diag.verdict}`. {diag.sentence}",
        "- Report: `report/index.html`.",
        "",
    ]
    atomic_write_text(out / "README.md", "\n".join(lines))
    summary.write(out)
    return summary
