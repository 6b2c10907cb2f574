"""``quadshank evaluate`` and ``compare``: classical and posterior J_φ,p, sign tests, PSIS-LOO, written to a folder.

Every file is written atomically and ``summary.json`` last, so a folder with a summary is complete.
"""

from __future__ import annotations

import time
import warnings
from pathlib import Path

from ..common._io import atomic_write_text, save_figure
from ..data._cohort import Cohort, Trial, derived_signals
from ..data._interchange import DataWarning
from ..data._paper import HORIZONS_MS, TABLE_V
from ..evaluation._blackbox import better_than, blackbox_j
from ..evaluation._posterior import (
    FIGURE_WINDOW_S,
    PARETO_K_BAD,
    LoadedFit,
    PosteriorEvaluation,
    accurate_j,
    band_mcse,
    check_fit_legs,
    figure_window,
    largest_mcse,
    load_fits,
    loo_report,
    posterior_j_and_stride_errors,
    posterior_medians,
    summarise_j,
    window_predictions,
)
from ..evaluation._prediction import (
    Evaluation,
    evaluate_cohort,
    figure_trial,
    free_run_errors,
    horizon_samples,
    predictions,
    sign_tests,
    table_v,
)
from ..evaluation._residuals import fit_residuals
from ..evaluation._structure import nothing_found, residual_structure, structure_sentence
from ..inference._fitio import posterior_models
from ..inference._summaries import INTERVAL
from ..model._likelihood import prepare
from ..model._model import Model
from ..outputs._figures import (
    plot_delay_angle,
    plot_j_vs_horizon,
    plot_posterior_j_vs_horizon,
    plot_posterior_predictions,
    plot_predictions,
)
from ..outputs._loop import residual_figures
from ..outputs._residual_figures import plot_structure
from ..outputs._tables import (
    SIGN_TEST_COLUMNS,
    markdown_table,
    recordings_sentence,
    sign_test_rows,
    table_v_rows,
    write_table,
)
from .identify import _pick


def _table_v_rows(J: dict, labels: list[str]) -> list[dict]:
    """Posterior Table V: median and 90 % band of the mean over legs, the paper's mean (s.d.) beside."""
    rows = []
    for tr in sorted({tr for by_trial in J.values() for tr in by_trial}, key=int):
        for h in map(str, HORIZONS_MS):
            row: dict = {"trial": tr, "horizon [ms]": int(h)}
            for label in labels:
                v = J[label].get(tr, {}).get(h, {})
                row[f"{label} median"] = v.get("median")
                row[f"{label} 5%"] = v.get("lo")
                row[f"{label} 95%"] = v.get("hi")
            for label in labels:
                paper = TABLE_V.get(tr, {}).get(label, {}).get(int(h))
                row[f"paper {label}"] = f"{paper[0]} ({paper[1]})" if paper else "–"
            rows.append(row)
    return rows


def _per_leg_rows(J_legs: dict, fits: list[LoadedFit]) -> list[dict]:
    fitted = {f.label: {str(t) for t in f.desc["trials"]} for f in fits}
    return [
        {
            "model": label,
            "leg": leg,
            "trial": tr,
            "fitted on it": "yes" if tr in fitted[label] else "no",
            "horizon [ms]": int(h),
            "median": v["median"],
            "5%": v["lo"],
            "95%": v["hi"],
        }
        for label, by_leg in J_legs.items()
        for leg, trials in by_leg.items()
        for tr, hv in sorted(trials.items(), key=lambda kv: int(kv[0]))
        for h, v in hv.items()
    ]


#: The columns of the PSIS-LOO comparison table.
LOO_COMPARE_COLUMNS = ("legs", "trials", "model", "rank", "elpd_diff", "dse", "weight")


def _loo_rows(loo: dict) -> tuple[list[dict], list[dict]]:
    key = f"pareto_k_over_{PARETO_K_BAD}"
    fits = [
        {"model": label, "elpd_loo": v["elpd_loo"], "se": v["se"], "p_loo": v["p_loo"],
         "observations": v["n_observations"], f"k > {PARETO_K_BAD}": v[key], "k max": v["pareto_k_max"]}
        for label, v in loo["fits"].items()
    ]
    compare = [
        dict(zip(LOO_COMPARE_COLUMNS, (", ".join(group["legs"]), ", ".join(map(str, group["trials"])), label,
                                       row["rank"], row["elpd_diff"], row["dse"], row["weight"])))
        for group in loo["compare"]
        for label, row in sorted(group["table"].items(), key=lambda kv: kv[1]["rank"])
    ]
    return fits, compare


def _figure_case(fits: list[LoadedFit], cohort: Cohort) -> tuple[str, Trial]:
    """The leg and trial of the prediction figures: JM-left, trial 2, as the paper, when available."""
    common = [leg for leg in cohort.legs if all(leg in f.desc["legs"] for f in fits)]
    candidates = common or list(fits[0].desc["legs"])
    leg = "JM-left" if "JM-left" in candidates else candidates[0]
    return leg, figure_trial(cohort, leg)


def _prediction_figures(fits, cohort, J_legs, out: Path, *, n_draws: int, seed: int) -> list[Path]:
    """Figs. 5-6 with a 90 % band over draws: 100 ms and 1 s ahead over a 20-s window."""
    leg, trial = _figure_case(fits, cohort)
    window = figure_window(trial, FIGURE_WINDOW_S)
    models = {f.label: posterior_models(f.idata, f.model, leg, n_draws, seed)[0] for f in fits if leg in f.desc["legs"]}
    paths = []
    hs = horizon_samples(trial.sampling_period_s, (100, 1000))
    names = {100: "fig5_posterior_predictions_100ms.png", 1000: "fig6_posterior_predictions_1s.png"}
    predicted = {label: window_predictions(m, trial, hs.values(), window) for label, m in models.items()}
    for h, name in names.items():
        p = hs[h]
        j = {label: J_legs[label][leg][str(trial.trial)][str(h)] for label in models}
        fig = plot_posterior_predictions(trial, {label: pr[p] for label, pr in predicted.items()}, p, j=j,
                                         start_s=window[0], length_s=FIGURE_WINDOW_S[1])
        paths.append(save_figure(fig, out / "figures" / name))
    return paths


def _residual_section(fits: list[LoadedFit], cohort: Cohort, out: Path, md: list) -> tuple[dict, dict]:
    """Residual figures of every fit on its identification trials, and the structure its residuals
    still carry (:func:`quadshank.evaluation._structure.residual_structure`); appends a report
    section.  Returns (findings in words, structure) per fit."""

    md += ["## Residuals of each fit (posterior medians, modal delay)", ""]
    findings, structure = {}, {}
    for f in fits:
        data = prepare(cohort, f.model, tuple(f.desc["trials"]), f.desc["legs"], objective="acceleration")
        res = {leg: fit_residuals(f.idata, f.model, data, leg) for leg in f.desc["legs"]}
        stem = f.label.replace("+", "_")
        paths, notes = residual_figures(res, out / "figures", stem, f.model.sampling_period_s)
        findings[f.label] = notes
        left = structure[f.label] = residual_structure(res, f.model.sampling_period_s, data.response_length)
        words = structure_sentence(left, lead="The residuals still carry structure")
        if left["found"]:
            paths.append(plot_structure(left, out / "figures" / f"unexplained_structure_{stem}.png", notes=[words]))
        md.append(f"### {f.label}")
        md.append("")
        for leg, lines in notes.items():
            md.append(f"- {leg}: " + (" ".join(lines) if lines else "nothing stands out."))
        md.append("- " + (words or nothing_found(left)))
        md += ["", *[f"![{p.stem}]({p.relative_to(out).as_posix()})" for p in paths], ""]
    return findings, structure


def _blackbox_section(cohort: Cohort, train: dict, physical: dict, start_stride: int = 1) -> tuple[dict, list[str]]:
    """The ARX yardstick on ``cohort`` (each leg trained on ``train[leg]``) beside ``physical``
    (``{model: {trial: {h_ms: J of the mean over legs}}}``): its summary entry and report lines."""
    try:
        bb = blackbox_j(cohort, train, start_stride=start_stride)
    except ValueError as e:  # a trial too short to validate one: the yardstick is left out, and said so
        return {"skipped": str(e)}, [f"- No black-box yardstick: {e}.", ""]
    bb["better_than"] = better_than(bb, physical)
    rows = [{"model": "ARX (black box)", "trial": tr, **{f"J {h} ms": v for h, v in hv.items()}}
            for tr, hv in bb["J"].items()]
    rows += [{"model": m, "trial": tr, **{f"J {h} ms": v for h, v in hv.items()}}
             for m, trials in physical.items() for tr, hv in trials.items()]
    orders = "; ".join(f"{leg}: {o['output_lags']} output and {o['input_lags']} input lags"
                       for leg, o in bb["orders"].items())
    md = [markdown_table(rows, "A black box beside the physical models: J_φ,p of the mean over legs [deg]"),
          f"The black box is a linear ARX model of the angle fitted to each leg's trial "
          f"{sorted({o['trained_on'] for o in bb['orders'].values()})[0]}, its orders chosen by validation ({orders}).",
          ""]
    if bb["better_than"]:
        md += [f"- The black box predicts better than {r['model']} on trial {r['trial']} at "
               f"{', '.join(r['horizons_ms'])} ms: the physical model misses something the data hold there."
               for r in bb["better_than"]] + [""]
    else:
        md += ["- Every physical model predicts better than the black box at every horizon.", ""]
    return bb, md


def _mcse_sentence(mcse: dict, draws_used: dict[str, int], start_stride: int) -> str:
    """The bands' accuracy in words: the draws (``draws_used``: per fit) and stride, and the largest
    error of a band end."""
    starts = "every start" if start_stride == 1 else f"one start in {start_stride}"
    counts = set(draws_used.values())
    draws = (f"{counts.pop()} posterior draws" if len(counts) == 1 else
             "posterior draws (" + ", ".join(f"{label}: {n}" for label, n in draws_used.items()) + ")")
    text = (f"The bands come from {draws} and {starts}; the largest Monte Carlo "
            f"standard error of a band end is {mcse['largest_cohort']:.3f}° on the mean over legs and "
            f"{mcse['largest_legs']:.3f}° on one leg's band")
    if "target" in mcse:
        text += (f" (asked: {mcse['target']:g}° on the mean over legs, "
                 + ("met" if mcse["met"] else "NOT met: the fits hold too few draws, or the rounds ran out") + ")")
    return text + "."


def run_posterior_evaluate(
    cohort: Cohort,
    folders,
    out: str | Path,
    *,
    n_draws: int = 200,
    start_stride: int = 1,
    seed: int = 0,
    progress: bool = False,
    residuals: bool = False,
    band_accuracy: float | None = None,
) -> PosteriorEvaluation:
    """Posterior J (Table V with bands), sign tests, PSIS-LOO, Figs. 5-6 with bands; summary.json last.

    ``residuals``: also each fit's residual diagnostics at its posterior medians
    (:mod:`quadshank.loop._diagnose`), side by side, what ``quadshank compare`` shows.
    ``band_accuracy`` [deg]: choose the draws and the start stride so that the ends of the
    cohort's bands carry at most this Monte Carlo standard error
    (:func:`quadshank.evaluation.accurate_j`; ``n_draws`` and ``start_stride`` are then unused).
    Every band end's error is estimated either way (``band_mcse`` in the summary).
    """
    if n_draws < 1:
        raise ValueError(f"--draws must be at least 1, not {n_draws}")
    if start_stride < 1:
        raise ValueError(f"--start-stride must be at least 1, not {start_stride}")
    out = Path(out)
    fits = load_fits(folders)
    check_fit_legs(fits, cohort)
    labels = [f.label for f in fits]
    held = {f.label: f.idata.posterior.sizes["chain"] * f.idata.posterior.sizes["draw"] for f in fits}
    short = {label: n for label, n in held.items() if n < n_draws}
    if band_accuracy is None and short:
        warnings.warn(f"--draws {n_draws}: " + ", ".join(f"{label} holds {n}" for label, n in short.items())
                      + "; such a fit's bands come from every draw it holds", DataWarning, stacklevel=2)

    t0 = time.perf_counter()
    accuracy = {}
    if band_accuracy is not None:
        acc = accurate_j(fits, cohort, band_accuracy, seed=seed, progress=progress)
        draws, stride_sd, n_draws, start_stride = acc.draws, acc.stride_sd, acc.n_draws, acc.start_stride
        accuracy = {"target": acc.target, "met": acc.met, "rounds": acc.rounds}
    else:
        draws, stride_sd = posterior_j_and_stride_errors(fits, cohort, n_draws=n_draws, start_stride=start_stride,
                                                         seed=seed, progress=progress)
    elapsed = time.perf_counter() - t0
    J, J_legs = summarise_j(draws)
    mcse_cohort, mcse_legs = band_mcse(draws, stride_sd)
    mcse = {"largest_cohort": largest_mcse(mcse_cohort), "largest_legs": largest_mcse(mcse_legs), **accuracy,
            "cohort": mcse_cohort, "legs": mcse_legs}
    tests = sign_tests(posterior_medians(J_legs)) if len(fits) >= 2 else []
    loo = loo_report(fits)

    md = ["# Posterior evaluation: k-step-ahead angle prediction (eq. 12) and PSIS-LOO", "",
          _recordings_line(cohort, muscle=any("no_muscle" not in f.summary.effects for f in fits)), ""]
    for f in fits:
        banner = f.summary.banner
        md.append(f"- {f.label}: fit {f.folder}, fitted on trial(s) {', '.join(map(str, f.desc['trials']))}"
                  + (f" — **{banner}**" if banner else ""))
    md.append("")
    md.append(write_table(_table_v_rows(J, labels), out / "tables", "table5_posterior",
                          "Table V (posterior): J_φ,p of the mean over legs, median and 90 % band [deg]"))
    md += [_mcse_sentence(mcse, {label: min(n_draws, n) for label, n in held.items()}, start_stride), ""]
    md.append(write_table(_per_leg_rows(J_legs, fits), out / "tables", "j_per_leg_posterior",
                          "J_φ,p per leg and trial, median and 90 % band over draws [deg]"))
    md.append(write_table(sign_test_rows(tests), out / "tables", "sign_tests_posterior",
                          "Sign tests on the posterior-median J (trials 2 and 3)", SIGN_TEST_COLUMNS))
    loo_fits, loo_compare = _loo_rows(loo)
    md.append(write_table(loo_fits, out / "tables", "loo", "PSIS-LOO per fit (1-s segments)"))
    md.append(write_table(loo_compare, out / "tables", "loo_compare", "PSIS-LOO comparison (same data)",
                          LOO_COMPARE_COLUMNS))
    if loo["not_compared"]:
        md.append(markdown_table(loo["not_compared"], "Fits not compared by LOO"))

    figures = [save_figure(plot_posterior_j_vs_horizon(J), out / "figures" / "table5_posterior_j_vs_horizon.png")]
    figures += _prediction_figures(fits, cohort, J_legs, out, n_draws=n_draws, seed=seed)
    for f in fits:
        if any("delay_angle" in s for s in f.summary.legs.values()):
            fig = plot_delay_angle(f.summary.legs, f.label, f.summary.delay_angle_population)
            figures.append(save_figure(fig, out / "figures" / f"delay_angle_{f.label.replace('+', '_')}.png"))
    md += ["## Figures", "", *[f"![{p.stem}]({p.relative_to(out).as_posix()})" for p in figures], ""]
    findings, structure = _residual_section(fits, cohort, out, md) if residuals else (None, None)
    fitted = cohort.select(legs=list(dict.fromkeys(leg for f in fits for leg in f.desc["legs"])))
    medians = {label: {tr: {h: v["median"] for h, v in hv.items()} for tr, hv in trials.items()}
               for label, trials in J.items()}
    blackbox, bb_md = _blackbox_section(fitted, {leg: int(fits[0].desc["trials"][0]) for leg in fitted.legs},
                                        medians, start_stride)
    md[md.index("## Figures"):md.index("## Figures")] = ["## A black-box yardstick", "", *bb_md]

    result = PosteriorEvaluation(
        method="posterior",
        J=J,
        J_legs=J_legs,
        sign_tests=tests,
        loo=loo,
        fits={
            f.label: {
                "folder": str(f.folder),
                "legs": list(f.desc["legs"]),
                "trials_fitted": list(f.desc["trials"]),
                "draws_used": min(n_draws, held[f.label]),
                "banner": f.summary.banner,
                "fit_id": f.summary.fit_id,
            }
            for f in fits
        },
        legs=list(dict.fromkeys(leg for f in fits for leg in f.desc["legs"])),
        horizons_samples=list(horizon_samples(cohort.sampling_period_s).values()),
        interval=list(INTERVAL),
        n_draws=min(n_draws, max(held.values())),
        start_stride=start_stride,
        seed=seed,
        evaluation_seconds=elapsed,
    )
    result.residual_findings = findings
    result.unexplained = structure
    result.band_mcse = mcse
    result.blackbox = blackbox
    atomic_write_text(out / "report.md", "\n".join(md))
    result.write(out)
    return result


def _recordings_line(cohort: Cohort, muscle: bool = True) -> str:
    """The sampling period and the signals derived from the angle, said at the top of a report."""
    return recordings_sentence(cohort.sampling_period_s, derived_signals(cohort), muscle)


def run_evaluate(
    cohort: Cohort, models: dict[str, dict[str, Model]], out: str | Path, *, progress: bool = False
) -> Evaluation:
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
    md = ["# Evaluation: k-step-ahead angle prediction (eq. 12)", "", _recordings_line(cohort), ""]
    md.append(write_table(table_v_rows(T), out / "tables", "table5", "Table V: mean (s.d.) of J_φ,p over legs [deg]"))
    md.append(write_table(sign_test_rows(tests), out / "tables", "sign_tests", "Sign tests between models (trials 2 and 3)",
                          SIGN_TEST_COLUMNS))
    per_leg = [
        {"model": m, "leg": leg, "trial": tr, **{f"J {h} ms": v for h, v in hv.items()}}
        for m, legs in J.items()
        for leg, trials in legs.items()
        for tr, hv in sorted(trials.items())
    ]
    md.append(write_table(per_leg, out / "tables", "j_per_leg", "J_φ,p per leg and trial [deg]"))
    free = free_run_errors(cohort, models)
    if free:
        rows = [{"model": m, "leg": leg, "trial": tr, "free run [deg]": v}
                for m, legs in free.items() for leg, trials in legs.items() for tr, v in sorted(trials.items())]
        md.append(write_table(rows, out / "tables", "free_run", "Pendulum tests: RMS error of the free swing from "
                              "its first measured state [deg]"))

    means = {m: {tr: {str(h): v[0] for h, v in hv.items()} for tr, hv in _by_model(T, m).items()} for m in J}
    train = {leg: (1 if 1 in [t.trial for t in cohort.trials_of(leg)] else cohort.trials_of(leg)[0].trial)
             for leg in cohort.legs}
    blackbox, bb_md = _blackbox_section(cohort, train, means)
    md += ["## A black-box yardstick", "", *bb_md]
    save_figure(plot_j_vs_horizon(T), out / "figures" / "table5_j_vs_horizon.png")
    leg = _pick("JM-left", cohort.legs)
    trial = figure_trial(cohort, leg)
    preds = {name: predictions(m, trial) for name, m in models[leg].items()}
    hs = horizon_samples(trial.sampling_period_s, (100, 1000))
    save_figure(plot_predictions(trial, preds, hs[100]), out / "figures" / "fig5_predictions_100ms.png")
    save_figure(plot_predictions(trial, preds, hs[1000]), out / "figures" / "fig6_predictions_1s.png")

    result = Evaluation(
        J={m: {tr: {str(h): v[0] for h, v in hv.items()} for tr, hv in _by_model(T, m).items()} for m in J},
        J_sd={m: {tr: {str(h): v[1] for h, v in hv.items()} for tr, hv in _by_model(T, m).items()} for m in J},
        J_per_leg={m: {leg: {tr: {str(h): v for h, v in hv.items()} for tr, hv in trials.items()}
                       for leg, trials in legs.items()} for m, legs in J.items()},
        sign_tests=tests,
        legs=list(cohort.legs),
        horizons_samples=list(horizon_samples(cohort.sampling_period_s).values()),
        evaluation_seconds=elapsed,
        free_run=free,
        blackbox=blackbox,
    )
    atomic_write_text(out / "report.md", "\n".join(md))
    result.write(out)
    return result


def _by_model(T: dict, model: str) -> dict:
    return {trial: T[trial][model] for trial in sorted(T) if model in T[trial]}
