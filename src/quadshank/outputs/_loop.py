"""The modelling loop's outputs: residual and predictive-check figures, the ranking as Markdown."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..common._io import atomic_write_bytes, file_stems, save_figure
from ..data._cohort import Cohort
from ..evaluation import _residuals as R
from ..evaluation._checks import elpd_in_time, loo_pit, worst_seconds_sentence
from ..evaluation._posterior import FIGURE_WINDOW_S, figure_window, window_predictions
from ..evaluation._prediction import horizon_samples
from ..evaluation._residuals import leg_residuals
from ..inference._screen import LaplaceFit, leg_draw_models
from ..loop._diagnose import ELPD_SE_BAR, J_DRAWS, J_HORIZONS_MS, STOPPED_AT_LIMIT, Diagnosis, Discovery
from . import _residual_figures as F
from ._figures import plot_posterior_predictions
from ._tables import markdown_table


def screen_residuals(fit: LaplaceFit) -> dict[str, dict]:
    return {leg: leg_residuals(fit, leg) for leg in fit.legs}


def residual_figures(residuals: dict[str, dict], out, label: str, dt: float) -> tuple[list, dict]:
    """Residual diagnostics per leg (trends, correlations, twitch-triggered average) of
    ``residuals`` (leg -> :func:`point_residuals`).  Returns (figure paths, findings per leg in words)."""

    paths, notes = [], {}
    stems = file_stems(residuals)  # a subject's name may hold '/' or be longer than a file name
    for leg, r in residuals.items():
        feats = R.features(r["angle"], r["velocity"], r["stimulation"], r["sample_mask"], r["trial_start"], dt)
        # a feature the recording does not have (no pulses: no interval or pulse count) is left out
        trends = {k: R.binned_trend(r["residual"], v, r["sample_mask"]) for k, v in feats.items()
                  if np.count_nonzero(np.isfinite(v) & np.asarray(r["sample_mask"], bool)) >= 2}
        ac = R.acf(r["residual"], r["sample_mask"])
        pulses = R.has_pulses(r["stimulation"])
        cc = R.ccf(r["residual"], r["stimulation"], r["sample_mask"]) if pulses else None
        found = R.findings(trends, ac, cc)
        notes[leg] = found
        stem = f"{label}_{stems[leg]}"
        paths.append(F.plot_trends(trends, out / f"residual_trends_{stem}.png", notes=found))
        paths.append(F.plot_correlations(ac, cc, out / f"residual_correlation_{stem}.png", notes=found))
        if pulses:
            groups = np.where(r["angle"] < -20.0, "pulse below -20°", "pulse above -20°")
            tta = R.twitch_triggered_average(r["residual"], r["stimulation"], r["sample_mask"], groups=groups)
            paths.append(F.plot_twitch_average(tta, out / f"twitch_average_{stem}.png", dt, notes=found))
        spec = R.spectrum(r["residual"], r["sample_mask"], dt)
        peak = R.spectrum_finding(spec)
        found.extend(peak)
        paths.append(F.plot_spectrum(spec, out / f"residual_spectrum_{stem}.png", notes=peak))
    return paths, notes


def copy_figures(src, names, label: str, out, new_label: str) -> list:
    """The figures ``names`` in ``src`` drawn with ``label`` (:func:`residual_figures`: the label is
    in the file name, not in the figure), copied to ``out`` under ``new_label``; returns their paths."""
    paths = []
    for name in names:
        if f"_{label}_" not in name:
            continue
        data = (Path(src) / name).read_bytes()
        paths.append(atomic_write_bytes(Path(out) / name.replace(f"_{label}_", f"_{new_label}_", 1), data))
    return paths


def predictive_checks(fit: LaplaceFit, cohort: Cohort, out, label: str) -> tuple[list, dict]:
    """The model's predictive checks from its screen: measured against predicted angle one step
    (10 ms) and 1 s ahead with 90 % bands over posterior draws, LOO-PIT, and the pointwise ELPD in
    time.  Returns (figure paths, JSON-able results with their findings in words)."""

    paths, result = [], {"loo_pit": {}, "worst_seconds": {}, "notes": []}
    shown = "JM-left" if "JM-left" in fit.legs else fit.legs[0]
    trial = [t for t in cohort.trials_of(shown) if t.trial in fit.data.trials][-1]
    window = figure_window(trial, FIGURE_WINDOW_S)
    one_second = horizon_samples(trial.sampling_period_s, (1000,))[1000]
    predicted = window_predictions(leg_draw_models(fit, shown, J_DRAWS), trial, (1, one_second), window)
    for p, name in ((1, "one_step"), (one_second, "1s")):
        fig = plot_posterior_predictions(trial, {fit.model.name: predicted[p]}, p, start_s=window[0], length_s=FIGURE_WINDOW_S[1])
        paths.append(save_figure(fig, out / f"predictions_{name}_{label}_{shown}.png"))
    pits, seconds = {}, {}
    for leg in fit.legs:
        values = loo_pit(fit, leg)
        summ = R.loo_pit_summary(values, int(fit.data.segment_mask[fit.legs.index(leg)].sum()))
        pits[leg] = (values, summ)
        result["loo_pit"][leg] = summ
        result["notes"] += [f"{leg}: {n}" for n in summ["notes"]] or [
            f"{leg}: LOO-PIT is uniform within its band (ECDF distance {summ['distance']:.3f} ≤ {summ['band']:.3f})."
        ]
        seconds[leg] = elpd_in_time(fit, cohort, leg)
        result["worst_seconds"][leg] = sorted(seconds[leg], key=lambda r: r["elpd"])[:3]
        result.setdefault("elpd_total", {})[leg] = float(sum(r["elpd"] for r in seconds[leg]))
    worst = [worst_seconds_sentence(leg, rows) for leg, rows in seconds.items()]
    paths.append(F.plot_loo_pit(pits, out / f"loo_pit_{label}.png", notes=list(result["notes"])))
    paths.append(F.plot_elpd_in_time(seconds, out / f"elpd_in_time_{label}.png", notes=worst))
    result["notes"] += worst
    return paths, result


def _j_cells(row: dict) -> dict[str, str]:
    """J before → after [90 % band after] at every horizon of the bands, as table cells; * marks
    the horizons where the effect is judged (its ``acts_at_ms``)."""
    cells = {}
    judged = row.get("judged_at_ms", [500, 1000])
    for h in J_HORIZONS_MS:
        j = row.get(f"J_{h}ms")
        cells[f"J {h} ms before → after [deg]"] = "—" if j is None else (
            f"{j['before']['median']:.3f} → {j['after']['median']:.3f} [{j['after']['lo']:.3f}, {j['after']['hi']:.3f}]"
            + (" *" if h in judged else ""))
    return cells


def _structure_rows(left: dict) -> list[dict]:
    """The table of what the residuals still carry: each feature's first-pass trend, then the offset."""
    side = {f["feature"]: f"{i}. ({f['side']})" for i, f in enumerate(left["found"], 1)}
    rows = [{"feature": R.FEATURE_WORDS.get(k, (k,))[0], "share of residual variance": f"{100 * v['share']:.2f} %",
             "χ² / d.o.f.": f"{v['chi2']:.0f} / {v['dof']}", "p": f"{v['p_value']:.1e}",
             "legs significant": f"{len(v['legs_significant'])} of {v['n_legs']}", "named": side.get(k, "—")}
            for k, v in left["screened"].items()]
    off = left.get("offset", {})
    if "chi2" in off:
        rows.append({"feature": "constant offset", "share of residual variance": f"{100 * off['share']:.2f} %",
                     "χ² / d.o.f.": f"{off['chi2']:.0f} / {off['dof']}", "p": f"{off['p_value']:.1e}",
                     "legs significant": "—", "named": f"yes ({off['side']})" if off["found"] else "—"})
    return rows


def ranking_markdown(summary: Diagnosis, command: str | None = None) -> str:
    """A diagnosis (its ranking, verdict, NUTS confirmation, checks and findings) as Markdown."""
    rows = summary.ranking
    md = [f"# Which effect is missing from {summary.model}", ""]
    if command:
        md += [f"Regenerate: `{command}`", ""]
    md += [f"**Verdict: {summary.verdict}.** {summary.sentence}", ""]
    md += markdown_table([
        {"rank": str(i), "effect": r["effect"], "ΔELPD ± SE": f"{r['delta_elpd']:.1f} ± {r['delta_elpd_se']:.1f}",
         **_j_cells(r), "clears the bar": "yes" if r["clears_bar"] else "no",
         "Pareto k max": f"{r['pareto_k_max']:.2f}",
         "segments k > 0.7": f"{100 * r['pareto_k_high_share']:.0f} %" if "pareto_k_high_share" in r else "–",
         "importance ESS": f"{r['importance_ess_min']:.0f}"}
        for i, r in enumerate(rows, 1)
    ]).splitlines()
    md += [
        "",
        f"The bar: ΔELPD above {ELPD_SE_BAR:g} standard errors (PSIS-LOO over 1-s segments, paired) and J lowered "
        "beyond the 90 % bands at every horizon where the effect acts (marked *: a delay at 100 and 250 ms, the "
        "others at 500 and 1000 ms).  ELPD and bands come from the screen (per-leg MAP, Laplace draws "
        "importance-weighted towards the posterior); a Pareto k above 0.7 or a small importance ESS says the Gaussian "
        "stands poorly for that posterior, and NUTS is the confirmation (`quadshank diagnose FITDIR --confirm`).",
    ]
    confirmed = [r for r in rows if "nuts" in r]
    if confirmed:
        md += [
            "",
            f"## Confirmed with hierarchical NUTS (against the fit in `{summary.confirmed_from or ''}`)",
            "",
        ]
        md += markdown_table([
            {"effect": r["effect"],
             "ΔELPD ± SE (PSIS-LOO)": f"{r['nuts']['delta_elpd']:.1f} ± {r['nuts']['delta_elpd_se']:.1f}",
             **_j_cells(r["nuts"]), "clears the bar": "yes" if r["nuts"]["clears_bar"] else "no",
             "fit": f"`{r['nuts']['folder']}`" + (" — " + r["nuts"]["banner"] if r["nuts"].get("banner") else "")}
            for r in confirmed
        ]).splitlines()
        md += ["", f"The screen's verdict: {summary.screen_verdict}; under NUTS: {summary.verdict}."]
    failed = summary.failed
    if failed:
        md += ["", "## Candidates that could not be screened", ""]
        md += [f"- **{f['effect']}**: {f['error']}" for f in failed]
    if summary.not_applicable:
        md += ["", "## Candidates that do not apply to these data (not screened)", ""]
        md += [f"- **{f['effect']}**: {f['why']}" for f in summary.not_applicable]
    checks = summary.predictive_checks
    if checks:
        md += ["", "## Predictive checks of the baseline (LOO-PIT, pointwise ELPD in time)", ""]
        md += [f"- {n}" for n in checks["notes"]]
    left = summary.unexplained
    if left and left.get("screened"):
        md += ["", "## What the residuals still carry (trend against each feature, legs combined)", ""]
        md += markdown_table(_structure_rows(left)).splitlines()
        md += ["", f"A feature is named when its combined p-value is below {left['alpha']:g} divided by the number of "
               f"features and its trend carries at least {100 * left['min_share']:g} % of the residual's variance. "
               "The table measures each feature on the residual as it is; each named trend is taken out before the "
               "next is looked for, and the verdict's sentence gives a later one's numbers after that."
               + (" See unexplained_structure.png." if left["found"] else "")]
    if summary.residual_findings:
        md += ["", "## Where the model fails (residuals of the baseline)", "", *findings_markdown(summary.residual_findings)]
    return "\n".join(md) + "\n"


def findings_markdown(findings: dict[str, list[str]]) -> list[str]:
    """One list item per leg: its residual findings (:func:`residual_figures`), each a sentence of
    its own (capitalised, ending in a full stop), or that nothing stands out."""

    def sentence(text: str) -> str:
        text = text.strip()
        return text[:1].upper() + text[1:] + ("" if text.endswith(".") else ".")

    return [f"- {leg}: " + (" ".join(map(sentence, lines)) if lines else "nothing stands out.") for leg, lines in findings.items()]


#: What a loop that ended at its round limit says: its last round still added an effect.
LIMIT_SENTENCE = ("The loop stopped at its round limit while its last round still added an effect: a further round "
                  "(`--max-rounds`) may find more.")


def discovery_markdown(summary: Discovery, command: str | None = None) -> str:
    """The modelling loop's page: each round's model, J, ELPD and verdict, the final model, the NUTS check."""
    md = ["# The modelling loop (`quadshank discover`)", ""]
    if command:
        md += [f"Regenerate: `{command}`", ""]
    for k, r in enumerate(summary.rounds, 1):
        J = r["J_ms"]
        md.append(
            f"{k}. **{r['model']}**: J at 0.5 s {J['500']['median']:.3f}° [{J['500']['lo']:.3f}, {J['500']['hi']:.3f}], "
            f"at 1 s {J['1000']['median']:.3f}°; ELPD {r['elpd']['value']:.0f} ± {r['elpd']['se']:.0f}. "
            f"Verdict: {r['verdict']}. {r['sentence']} (details: [round-{k}/report.md](round-{k}/report.md))"
        )
    md += ["", f"Final model: **{summary.final_model}**." + (f" {LIMIT_SENTENCE}" if summary.stopped == STOPPED_AT_LIMIT else "")]
    if summary.confirm is not None:
        c = summary.confirm
        md += ["", "## Confirmed with hierarchical NUTS", "", c["sentence"], "",
               f"Fits: [{c['start']['folder']}]({c['start']['folder']}), [{c['final']['folder']}]({c['final']['folder']}); "
               f"comparison with residuals before and after: [confirm/compare/report.md](confirm/compare/report.md)."]
    return "\n".join(md) + "\n"
