"""The paper's pipeline end to end: identify, evaluate, reproduce.

Each ``run_*`` function takes data in memory, writes its tables, figures and
``summary.json`` into an output folder (every file atomically, ``summary.json``
last, so a folder with a summary is complete) and returns the summary.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import jax
import numpy as np

from ..data._cohort import Cohort
from ..evaluation._prediction import evaluate_cohort, predictions, sign_tests, table_v
from ..inference._identify import LegIdentification, identify_cohort
from ..common._io import atomic_write_text, read_json, save_figure, write_json
from ..model._model import Model, equivalent_acceleration, paper_model, passive_effects
from ..outputs._figures import plot_delay_scan, plot_j_vs_horizon, plot_predictions, plot_signals, plot_twitch_dependence
from ..data._paper import HORIZONS
from ..outputs._tables import (
    markdown_table,
    sign_test_rows,
    table_i,
    table_ii,
    table_iii,
    table_iv,
    table_passive,
    table_v_rows,
    write_table,
)

__all__ = [
    "run_identify",
    "run_evaluate",
    "run_reproduce",
    "models_from_summary",
    "recovery",
    "TOLERANCES",
]

#: Relative tolerances (|estimate - truth| / |truth|) within which the classical
#: identification must recover the simulator's truth; see README "Recovery".
TOLERANCES = {
    "damping": 0.25,
    "gravity": 0.05,
    "k1": 0.6,
    "k2": 0.5,
    "G2": 0.25,
    "gamma_angle": 0.5,
    "gamma_velocity": 0.5,
}
#: The identified delay must be within this many samples of the true (fractional) delay.
DELAY_TOLERANCE = 1.0


def _pick(preferred: str, available) -> str:
    available = list(available)
    return preferred if preferred in available else available[0]


# ============================================================================ identify


def run_identify(
    cohort: Cohort, out: str | Path, *, truth: dict | None = None, trial: int = 1, progress: bool = False
) -> dict:
    """Classical identification of every leg; Tables I–IV, figures, summary.json."""
    out = Path(out)
    ident = identify_cohort(cohort, trial=trial, progress=progress)
    md = [f"# Classical identification (trial {trial})", ""]
    md.append(write_table(table_passive(ident, truth), out / "tables", "passive", "Passive system (eq. 8)"))
    md.append(write_table(table_i(ident, truth), out / "tables", "table1", "Table I: model 1 and delay"))
    md.append(write_table(table_ii(ident, truth), out / "tables", "table2", "Table II: model 2 (DARMA)"))
    md.append(write_table(table_iii(ident, truth), out / "tables", "table3", "Table III: model 3"))
    md.append(write_table(table_iv(ident), out / "tables", "table4", "Table IV: % RMS error of ΣM/I"))
    summary = {leg: r.summary() for leg, r in ident.items()}
    if truth:
        rec = recovery(ident, truth)
        md.append(markdown_table(recovery_rows(rec), "Recovery of the simulator's truth"))
        for leg in summary:
            summary[leg]["recovery"] = rec[leg]

    leg2 = _pick("TN-right", ident)
    t2 = cohort.get(leg2, trial)
    mi = equivalent_acceleration(ident[leg2].models["model1"], t2.angle_deg, t2.velocity_deg_s, t2.acceleration_deg_s2)
    save_figure(plot_signals(t2, np.asarray(mi)), out / "figures" / "fig2_signals.png")

    save_figure(plot_twitch_dependence(ident[_pick("TN-left", ident)]), out / "figures" / "fig3_4_twitch_dependence.png")
    save_figure(plot_delay_scan(ident), out / "figures" / "delay_scan.png")
    atomic_write_text(out / "report.md", "\n".join(md))
    write_json(out / "summary.json", summary)
    return summary


def recovery(ident: dict[str, LegIdentification], truth: dict) -> dict:
    """Identified vs true parameters per leg, with the tolerance check of :data:`TOLERANCES`."""
    out = {}
    for leg, r in ident.items():
        t = truth["legs"][leg]
        m3 = r.models["model3"].flat_params()
        pairs = {
            "damping": (r.passive["damping"], t["passive"]["damping"]),
            "gravity": (r.passive["gravity"], t["passive"]["gravity"]),
            "k1": (r.passive["k1"], t["passive"]["k1"]),
            "k2": (r.passive["k2"], t["passive"]["k2"]),
            "G2": (m3["gain"], t["active"]["G2"]),
            "gamma_angle": (m3["gamma_angle"], t["active"]["gamma_angle"]),
            "gamma_velocity": (m3["gamma_velocity"], t["active"]["gamma_velocity"]),
        }
        leg_out = {}
        for name, (est, true) in pairs.items():
            rel = abs(est - true) / abs(true)
            leg_out[name] = {
                "estimate": est,
                "truth": true,
                "relative_error": rel,
                "tolerance": TOLERANCES[name],
                "ok": bool(rel <= TOLERANCES[name]),
            }
        dtrue = t["active"]["delay_samples"]
        leg_out["delay_samples"] = {
            "estimate": r.delay,
            "truth": dtrue,
            "abs_error": abs(r.delay - dtrue),
            "tolerance": DELAY_TOLERANCE,
            "ok": bool(abs(r.delay - dtrue) <= DELAY_TOLERANCE),
        }
        out[leg] = leg_out
    return out


def recovery_rows(rec: dict) -> list[dict]:
    rows = []
    for leg, params in rec.items():
        for name, v in params.items():
            err = v.get("relative_error", v.get("abs_error"))
            rows.append(
                {
                    "leg": leg,
                    "parameter": name,
                    "estimate": v["estimate"],
                    "truth": v["truth"],
                    "error": err,
                    "tolerance": v["tolerance"],
                    "within": "yes" if v["ok"] else "NO",
                }
            )
    return rows


def models_from_summary(summary: dict) -> dict[str, dict[str, Model]]:
    """Rebuild the identified models of each leg from an identify ``summary.json``."""
    models = {}
    for leg, s in summary.items():
        passive = passive_effects(**s["passive"])
        d = int(s["delay_samples"])
        m2 = s["model2"]
        models[leg] = {
            "model1": paper_model(1, passive, delay=d).with_params(gain=s["model1"]["gain"]),
            "model2": paper_model(2, passive, delay=d).with_params(
                a=np.array([m2["a1"], m2["a2"]]), b=np.array([m2["b1"], m2["b2"]])
            ),
            "model3": paper_model(3, passive, delay=d).with_params(
                gain=s["model3"]["gain"],
                gamma_angle=s["model3"]["gamma_angle"],
                gamma_velocity=s["model3"]["gamma_velocity"],
            ),
        }
    return models


def load_identification(folder: str | Path) -> dict[str, dict[str, Model]]:
    """Models from the ``summary.json`` of a ``quadshank identify`` output folder."""
    path = Path(folder) / "summary.json"
    if not path.exists():
        raise FileNotFoundError(f"{path}: no identification here (run `quadshank identify DATA --out {folder}`)")
    return models_from_summary(read_json(path))


# ============================================================================ evaluate


def run_evaluate(
    cohort: Cohort, models: dict[str, dict[str, Model]], out: str | Path, *, progress: bool = False
) -> dict:
    """J_φ,p for every leg, trial and model; Table V, sign tests, Figs. 5–6, summary.json."""

    out = Path(out)
    missing = [leg for leg in cohort.legs if leg not in models]
    if missing:
        raise KeyError(f"no identified models for leg(s) {', '.join(missing)}")
    t0 = time.perf_counter()
    J = evaluate_cohort(cohort, models, progress=progress)
    elapsed = time.perf_counter() - t0
    T = table_v(J)
    tests = sign_tests(J)
    md = ["# Evaluation: k-step-ahead angle prediction (eq. 12)", ""]
    md.append(write_table(table_v_rows(T), out / "tables", "table5", "Table V: mean (s.d.) of J_φ,p over legs [deg]"))
    md.append(write_table(sign_test_rows(tests), out / "tables", "sign_tests", "Sign tests between models (trials 2 and 3)"))
    per_leg = [
        {"model": m, "leg": leg, "trial": tr, **{f"J {h} ms": v for h, v in hv.items()}}
        for m, legs in J.items()
        for leg, trials in legs.items()
        for tr, hv in sorted(trials.items())
    ]
    md.append(write_table(per_leg, out / "tables", "j_per_leg", "J_φ,p per leg and trial [deg]"))

    save_figure(plot_j_vs_horizon(T), out / "figures" / "table5_j_vs_horizon.png")
    leg = _pick("JM-left", cohort.legs)
    trial_numbers = [t.trial for t in cohort.trials_of(leg)]
    trial = cohort.get(leg, 2 if 2 in trial_numbers else trial_numbers[0])
    preds = {name: predictions(m, trial) for name, m in models[leg].items()}
    save_figure(plot_predictions(trial, preds, 10), out / "figures" / "fig5_predictions_100ms.png")
    save_figure(plot_predictions(trial, preds, 100), out / "figures" / "fig6_predictions_1s.png")

    summary = {
        "J": {m: {tr: {str(h): v[0] for h, v in hv.items()} for tr, hv in _by_model(T, m).items()} for m in J},
        "J_sd": {m: {tr: {str(h): v[1] for h, v in hv.items()} for tr, hv in _by_model(T, m).items()} for m in J},
        "J_per_leg": {m: {leg: {tr: {str(h): v for h, v in hv.items()} for tr, hv in trials.items()}
                          for leg, trials in legs.items()} for m, legs in J.items()},
        "sign_tests": tests,
        "legs": list(cohort.legs),
        "horizons_samples": list(HORIZONS),
        "evaluation_seconds": elapsed,
    }
    atomic_write_text(out / "report.md", "\n".join(md))
    write_json(out / "summary.json", summary)
    return summary


def _by_model(T: dict, model: str) -> dict:
    return {trial: T[trial][model] for trial in sorted(T) if model in T[trial]}


# ============================================================================ reproduce


def run_reproduce(
    out: str | Path,
    *,
    minutes: float = 5.0,
    seed: int = 0,
    effects=(),
    legs=None,
    progress: bool = False,
    command: str = "",
) -> dict:
    """Simulate the cohort, identify, evaluate; tables, figures and summary.json in ``out``."""
    from ..data._interchange import write_interchange
    from ..data._paper import LEGS
    from ..data._simulate import simulate_cohort, write_truth

    out = Path(out)
    legs = tuple(legs or LEGS)
    t0 = time.perf_counter()
    cohort, truth = simulate_cohort(legs=legs, minutes=minutes, seed=seed, effects=tuple(effects), progress=progress)
    write_interchange(cohort, out / "data")
    write_truth(truth, out / "data" / "truth.json")
    t_sim = time.perf_counter() - t0
    ident = run_identify(cohort, out / "identify", truth=truth, progress=progress)
    t_id = time.perf_counter() - t0 - t_sim
    models = models_from_summary(ident)
    ev = run_evaluate(cohort, models, out / "evaluate", progress=progress)
    t_ev = time.perf_counter() - t0 - t_sim - t_id

    rec_ok = all(v["ok"] for leg in ident.values() for v in leg.get("recovery", {}).values())
    rms = {
        str(t): float(np.mean([truth["legs"][leg]["trials"][str(t)]["rms_angle_deg"] for leg in legs]))
        for t in sorted({tr.trial for tr in cohort})
    }
    summary = {
        "command": command,
        "minutes": minutes,
        "seed": seed,
        "effects": list(effects),
        "legs": list(legs),
        "rms_angle_deg": rms,
        "identification": ident,
        "recovery_ok": rec_ok,
        "J": ev["J"],
        "J_sd": ev["J_sd"],
        "sign_tests": ev["sign_tests"],
        "seconds": {"simulate": t_sim, "identify": t_id, "evaluate": t_ev},
    }
    report = [
        "# Reproduction of Franken et al. (1995) on the simulated cohort",
        "",
        f"Made by: `{command}`" if command else "",
        "",
        f"Legs: {', '.join(legs)}; {minutes:g} min per trial; seed {seed}; hidden effects: {', '.join(effects) or 'none'}.",
        "",
        "Mean RMS knee angle per trial [deg]: "
        + ", ".join(f"trial {t}: {v:.1f}" for t, v in rms.items())
        + " (paper: 23.6, 24.1, 19.3).",
        "",
        f"All identified parameters within the stated tolerances: {'yes' if rec_ok else 'NO'}.",
        "",
        (out / "identify" / "report.md").read_text(),
        (out / "evaluate" / "report.md").read_text(),
        "## Figures",
        "",
        *[f"![{p.stem}]({p.relative_to(out).as_posix()})" for p in sorted(out.glob("*/figures/*.png"))],
        "",
    ]
    atomic_write_text(out / "report.md", "\n".join(report))
    write_json(out / "summary.json", summary)
    return summary


# ============================================================================ hierarchical fit


def run_fit(
    cohort: Cohort,
    out: str | Path,
    model: str = "model3",
    add_effects=(),
    settings=None,
    legs=None,
    *,
    delay_from: str | Path | None = None,
    progress: bool = False,
    data_source: str | None = None,
) -> dict:
    """Hierarchical NUTS fit of one model; writes DIR/fit.nc and DIR/summary.json, returns the summary.

    ``data_source``: where the data came from, recorded as the summary's ``data`` (for
    ``quadshank diagnose`` and ``compare``).

    ``delay_from``: a fit folder whose delay posterior becomes this fit's delay prior
    (see :func:`quadshank.inference._fit.delay_prior_from`).
    """
    from ..inference._fit import FitSettings, build_model, delay_prior_from, delay_start, fit, fit_screen
    from ..inference._fitio import begin_fit, read_summary, save_fit, to_inference_data

    settings = settings or FitSettings()
    out = Path(out)
    m = build_model(model, add_effects)
    log_prior = None
    if delay_from is not None:
        chosen = tuple(legs) if legs is not None else cohort.legs  # the legs fit() will use
        log_prior = delay_prior_from(read_summary(delay_from), chosen)
    out.mkdir(parents=True, exist_ok=True)
    begin_fit(out)
    t0 = time.perf_counter()
    screen = fit_screen(cohort, m, settings, legs=legs, progress=progress)
    extra, evidence = {}, None
    if screen is not None and settings.delay_evidence:
        if progress:
            print("fit: each leg's delays weighed by a Laplace approximation per delay", file=sys.stderr, flush=True)
        t1 = time.perf_counter()
        screen, evidence, moved = delay_start(cohort, settings, screen, log_prior, progress=progress)
        extra["delay_evidence_seconds"] = time.perf_counter() - t1
        extra["screen_restarted"] = {leg: {"from_delay": a, "to_delay": b} for leg, (a, b) in moved.items()}
    mcmc, data = fit(cohort, m, settings, legs=legs, progress=progress, log_delay_prior=log_prior, screen=screen)
    # JAX dispatches asynchronously: the draws may still be computing when fit() returns
    jax.block_until_ready(mcmc.get_samples(group_by_chain=True))
    extra["sampling_seconds"] = time.perf_counter() - t0 - extra.get("delay_evidence_seconds", 0.0)
    idata = to_inference_data(
        mcmc, m, data, settings, delay_source=None if delay_from is None else str(delay_from), log_delay_prior=log_prior,
        delay_evidence=evidence,
    )
    if data_source is not None:
        extra["data"] = str(data_source)
    return save_fit(idata, out, extra=extra)
