"""Credible-parameter reports of a fit: one self-contained HTML page per subject and a cohort index.

``quadshank report FITDIR --out DIR`` writes

- ``DIR/index.html``: the cohort: one row per leg (delay, J at 1 s, the fit's
  checks), the population-level parameters with the spreads between subjects
  and legs, the posterior Table V beside the paper's, the pooled delay–angle
  curve when the fit has ``angle_delay``, the diagnosis ranking when given;
- ``DIR/subject-<S>.html`` per subject: for each leg every parameter's posterior
  median and 90 % interval with units beside its subject's and the population's
  (shrinkage, also as a forest plot in prior scales), P(d), the delay–angle curve
  with its band, J_φ,p against horizon with bands beside the paper's Table V,
  measured and predicted angle with bands at 100 ms and 1 s ahead, the fit's
  diagnostics, the diagnosis ranking;
- ``DIR/legs/<leg>.csv`` and ``DIR/legs/<leg>.json``: the credible parameters of
  each leg at the three levels (the JSON adds P(d), the delay–angle summary and J);
- ``DIR/summary.json``, removed first and written last.

Each page is one file: figures are PNGs inlined as ``data:`` URIs, the style
sheet and the one script are inline, nothing is fetched.  The script writes,
once the page has loaded, the number of ``<img>`` elements and how many of them
decoded as ``data-figures`` and ``data-figures-loaded`` on ``<body>``, so a
headless browser's DOM dump shows whether every figure rendered.  When the fit
failed its checks a red box at the top of every page says so, with the problems
and the advice.

Levels.  A leg's values are the fit summary's (``summary.json`` of the fit); the
subject and population values are the posterior draws ``<name>_subject`` and
``<name>_mu`` (:func:`quadshank.inference._draws.hyper_draws`), summarised the same way
(median, 5 % and 95 % quantiles).  The noise parameters σ and ν are per leg and
have no hierarchy.
"""

from __future__ import annotations

import base64
import csv
import html
import io
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from ..common._io import atomic_write_text, figure_bytes, file_stems, write_json
from ..common._progress import progress_bar
from ..data._paper import SAMPLING_PERIOD_S, TABLE_V
from ..inference._fitio import located_words
from ..inference._summaries import INTERVAL, interval
from ..model._effects import registered_effects, to_standard
from ._figures import horizon_axis, plot_delay_angle
from ._tables import recordings_sentence

__all__ = ["write_report", "plot_shrinkage", "plot_delay_posterior", "plot_leg_predictions", "PREDICTION_WINDOW_S", "PREDICTION_HORIZONS_MS"]

#: Prediction figures: (start, length) [s] of the window; on shorter trials the start moves earlier.
PREDICTION_WINDOW_S = (30.0, 10.0)
#: Horizons [samples] of the prediction figures: 100 ms and 1 s.
PREDICTION_HORIZONS_MS = (100, 1000)
#: The z of the 5 % and 95 % quantiles of a normal: the prior's 90 % interval in prior scales.
_Z90 = 1.6448536269514722
_TRIAL_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")


# ============================================================================ J


# ============================================================================ figures


def _data_uri(fig) -> str:
    return "data:image/png;base64," + base64.b64encode(figure_bytes(fig, "png", dpi=90)).decode("ascii")


def plot_shrinkage(subject: str, legs: list[str], params: dict):
    """Forest plot in prior scales: population, the subject and its legs, per parameter component."""

    labels = [k for k, v in params[legs[0]]["params"].items() if v["prior"] is not None]
    rows = [("population", "population", None), (f"subject {subject}", "subject", None)]
    rows += [(leg, "leg", leg) for leg in legs]
    colours = {"population": "0.35", "subject": "tab:purple", "leg": "tab:blue"}
    n = len(rows)
    fig, ax = plt.subplots(figsize=(7.5, 0.32 * n * len(labels) + 1.2))
    ax.axvspan(-_Z90, _Z90, color="0.92", zorder=0, label="prior 90 %")
    ax.axvline(0.0, color="0.6", lw=0.8)
    ticks = []
    for j, label in enumerate(labels):
        base = j * (n + 1)
        ticks.append(base + (n - 1) / 2)
        for k, (name, level, leg) in enumerate(rows):
            q = params[leg or legs[0]]["params"][label][level]
            if q is None:
                continue
            prior = params[legs[0]]["params"][label]["prior"]
            lo, med, hi = (float(to_standard(q[x], prior)) for x in ("lo", "median", "hi"))
            y = base + k
            ax.plot([lo, hi], [y, y], "-", color=colours[level], lw=2)
            first = j == 0 and (level != "leg" or k == 2)
            ax.plot([med], [y], "o", color=colours[level], ms=4,
                    label=(name if level != "leg" else "legs: " + ", ".join(legs)) if first else None)
    ax.set_yticks(ticks)
    ax.set_yticklabels(labels)
    ax.invert_yaxis()
    ax.set_xlabel("(value − prior centre) / prior scale   (log value for log-normal priors)")
    ax.legend(fontsize=7, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=4, frameon=False)
    fig.tight_layout()
    return fig


def plot_delay_posterior(legs: list[str], fit_legs: dict, sampling_period_s: float = SAMPLING_PERIOD_S):
    """P(d | data) of each leg as bars, from a fit's per-leg summaries (``FitResult.legs``); d in
    samples of ``sampling_period_s``."""
    fig, axes = plt.subplots(1, len(legs), figsize=(3.6 * len(legs), 2.8), squeeze=False, sharey=True)
    for ax, leg in zip(axes[0], legs):
        p = np.asarray(fit_legs[leg]["delay_posterior"])
        ax.bar(np.arange(p.size), p, color="tab:blue")
        ax.set_xticks(np.arange(p.size))
        ax.set_xlabel(f"delay d [samples of {sampling_period_s * 1000:g} ms]")
        ax.set_title(f"{leg}: P(d | data)", fontsize=9)
    axes[0, 0].set_ylabel("posterior probability")
    fig.tight_layout()
    return fig


def _paper_table_v(label: str) -> tuple[str, dict]:
    base = label.split("+")[0]
    return base, {tr: by_model[base] for tr, by_model in TABLE_V.items() if base in by_model}


def _plot_j_legs(legs: list[str], J_legs: dict, label: str):
    """J against horizon per leg: median and 90 % band per trial, the paper's Table V (mean ± s.d.) beside."""

    base, paper = _paper_table_v(label)
    fig, axes = plt.subplots(1, len(legs), figsize=(4.4 * len(legs), 3.6), squeeze=False, sharey=True)
    for ax, leg in zip(axes[0], legs):
        for c, (tr, hv) in enumerate(sorted(J_legs[leg].items(), key=lambda kv: int(kv[0]))):
            colour = _TRIAL_COLOURS[c % len(_TRIAL_COLOURS)]
            items = sorted(hv.items(), key=lambda kv: int(kv[0]))
            hs = [int(h) for h, _ in items]
            ax.plot(hs, [v["median"] for _, v in items], "o-", color=colour, label=f"trial {tr} (median, 90 %)")
            ax.fill_between(hs, [v["lo"] for _, v in items], [v["hi"] for _, v in items], color=colour, alpha=0.25)
            if tr in paper:
                ph = sorted(paper[tr])
                ax.errorbar([h * 1.04 for h in ph], [paper[tr][h][0] for h in ph], yerr=[paper[tr][h][1] for h in ph],
                            fmt=":x", capsize=3, color=colour, label=f"paper {base}, trial {tr} (mean ± s.d.)")
        horizon_axis(ax)
        ax.set_title(leg, fontsize=9)
    axes[0, 0].set_ylabel("J_φ,p [deg]")
    axes[0, -1].legend(fontsize=7)
    fig.tight_layout()
    return fig


def plot_leg_predictions(leg: str, trial, window, predictions: dict, J_legs: dict, fitted_trials=()):
    """Measured angle and the angle predicted 100 ms and 1 s ahead: median and 90 % band over draws.

    ``window`` and ``predictions``: :func:`quadshank.evaluation.figure_window` and
    :func:`quadshank.evaluation.window_predictions` of ``trial``.  Returns (figure, trial number).
    """
    _, i0, i1 = window
    fig, axes = plt.subplots(len(predictions), 1, figsize=(9, 2.5 * len(predictions)), sharex=True)
    for ax, (p, (starts, pred)) in zip(np.atleast_1d(axes), predictions.items()):
        t = trial.time_s[starts + p]
        band = interval(pred, axis=0)
        ax.plot(trial.time_s[i0:i1], trial.angle_deg[i0:i1], "k-", lw=1.1, label="measured")
        ms = int(round(p * trial.sampling_period_s * 1000))
        ax.plot(t, band["median"], "--", color="tab:green", lw=1.1, label=f"predicted {ms} ms ahead (median)")
        ax.fill_between(t, band["lo"], band["hi"], color="tab:green", alpha=0.3, lw=0, label="90 % band over draws")
        ax.set_xlim(trial.time_s[i0], trial.time_s[i1 - 1])
        j = J_legs.get(leg, {}).get(str(trial.trial), {}).get(str(ms))
        title = f"{ms} ms ahead"
        if j:
            title += f": J = {j['median']:.2f}° [{j['lo']:.2f}, {j['hi']:.2f}] over the trial"
        ax.set_title(title, fontsize=9)
        ax.set_ylabel("angle [deg]")
        ax.legend(fontsize=7, loc="upper right")
    np.atleast_1d(axes)[-1].set_xlabel("time [s]")
    fitted = "fitted on it" if trial.trial in fitted_trials else "not fitted on it"
    fig.suptitle(f"{leg}, trial {trial.trial} ({fitted}): measured and predicted knee angle", fontsize=10)
    fig.tight_layout()
    return fig, trial.trial


# ============================================================================ HTML

_STYLE = """
body{font-family:system-ui,sans-serif;margin:1.5em auto;max-width:1100px;padding:0 1em;color:#222}
h1{font-size:1.5em}h2{font-size:1.25em;border-bottom:1px solid #ccc;margin-top:1.6em}h3{font-size:1.05em}
table{border-collapse:collapse;margin:.6em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.2em .5em;text-align:left;vertical-align:top}
th{background:#f2f2f2}td.num{text-align:right;font-variant-numeric:tabular-nums}
.ci{white-space:nowrap;color:#444}.doc{display:inline-block;font-size:.85em;color:#555;max-width:18em}
img{max-width:100%;display:block;margin:.6em 0}
.warning{border:3px solid #c00;background:#fee;color:#600;padding:.6em 1em;margin:1em 0}
.warning strong{color:#c00}.ok{color:#060}.fail{color:#c00;font-weight:bold}
.note{color:#555;font-size:.9em}.prior-only{background:#fde68a;color:#78350f;padding:0 .3em;border-radius:3px;font-size:.85em}nav a{margin-right:1em}
"""

_SCRIPT = """
window.addEventListener('load', function () {
  var imgs = document.getElementsByTagName('img'), ok = 0;
  for (var i = 0; i < imgs.length; i++) { if (imgs[i].complete && imgs[i].naturalWidth > 0) ok++; }
  document.body.setAttribute('data-figures', String(imgs.length));
  document.body.setAttribute('data-figures-loaded', String(ok));
});
"""


def _e(x) -> str:
    return html.escape(str(x), quote=True)


def _num(x) -> str:
    if x is None:
        return "–"
    x = float(x)
    if not np.isfinite(x):
        return "–" if np.isnan(x) else str(x)
    return f"{x:.4g}"


def _q(q: dict | None) -> str:
    if not q:
        return "–"
    return f"{_num(q['median'])} <span class=\"ci\">[{_num(q['lo'])}, {_num(q['hi'])}]</span>"


def _table(header: list[str], rows: list[list[str]], num_cols=()) -> str:
    """Rows of already-escaped cells."""
    head = "".join(f"<th>{_e(h)}</th>" for h in header)
    body = "".join(
        "<tr>" + "".join(f'<td class="num">{c}</td>' if j in num_cols else f"<td>{c}</td>" for j, c in enumerate(r)) + "</tr>"
        for r in rows
    )
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _figure(uri: str, alt: str) -> str:
    return f'<img src="{uri}" alt="{_e(alt)}">'


def _page(title: str, body: list[str]) -> str:
    return (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        f"<title>{_e(title)}</title><style>{_STYLE}</style><script>{_SCRIPT}</script></head>\n"
        "<body>\n" + "\n".join(body) + "\n</body></html>\n"
    )


def _warning_box(diag: dict) -> str:
    if diag.get("ok"):
        return ""
    items = "".join(f"<li>{_e(p)}</li>" for p in diag.get("problems", []))
    advice = "".join(f"<li>{_e(a)}</li>" for a in diag.get("advice", []))
    return (
        '<div class="warning" id="fit-warning"><strong>This fit failed its convergence checks: '
        "do not trust these intervals.</strong> The checks judge the fit as a whole, every leg and subject, so "
        "a problem named here may lie in another subject's leg.<ul>" + items + "</ul>"
        + (f"<p>Advice:</p><ul>{advice}</ul>" if advice else "") + "</div>"
    )


def _diagnostics_section(d: dict) -> str:
    th = d.get("thresholds", {})

    def verdict(good: bool) -> str:
        return '<span class="ok">pass</span>' if good else '<span class="fail">FAIL</span>'

    def finite(x) -> bool:
        return x is not None and np.isfinite(float(x))

    def value(key: str, worst: str) -> str:
        """The check's value and, where the fit records it (fits saved before did not), whose it is."""
        w = (d.get("worst") or {}).get(worst)
        return _num(d.get(key)) + (f" ({_e(w['variable'])}{', ' + _e(w['at']) if w['at'] else ''})" if w else "")

    rows = [
        ["R-hat, largest", value("rhat_max", "rhat"), f"&lt; {_num(th.get('rhat_max'))}",
         verdict(finite(d.get("rhat_max")) and d["rhat_max"] < th.get("rhat_max", 1.01))],
        ["bulk ESS, smallest", value("ess_bulk_min", "ess_bulk"), f"≥ {_num(th.get('ess_min'))}",
         verdict(finite(d.get("ess_bulk_min")) and d["ess_bulk_min"] >= th.get("ess_min", 0))],
        ["tail ESS, smallest", value("ess_tail_min", "ess_tail"), f"≥ {_num(th.get('ess_min'))}",
         verdict(finite(d.get("ess_tail_min")) and d["ess_tail_min"] >= th.get("ess_min", 0))],
        ["divergent transitions", _e(d.get("divergences")) + (f" (all where {_e(located_words(d['divergences_at']))})"
                                                             if d.get("divergences_at") else ""),
         f"≤ {_e(th.get('divergences', 0))}",
         verdict(d.get("divergences", 0) <= th.get("divergences", 0))],
        ["E-BFMI, smallest", _num(d.get("bfmi_min")), f"&gt; {_num(th.get('bfmi_min'))}",
         verdict(finite(d.get("bfmi_min")) and d["bfmi_min"] > th.get("bfmi_min", 0.3))],
    ]
    if "delay_splits" in d:  # fits saved before this check lack it
        splits = d["delay_splits"]
        rows.append(["legs whose chains settled at different delays",
                     _e(", ".join(splits) if splits else "none"), "none", verdict(not splits)])
    if "delay_missed" in d:
        missed = d["delay_missed"]
        cell = "; ".join(f"{leg}: d = {', '.join(map(str, ds))}" for leg, ds in missed.items()) or "none"
        # a warning (the evidence is of each leg alone), not a failed check
        rows.append(["delays weighed by a Laplace approximation per delay, of each leg alone, that no chain visited",
                     _e(cell), "none (a warning)", '<span class="ok">pass</span>' if not missed else "<b>look</b>"])
    if "weakly_informed" in d:
        weak = d["weakly_informed"]
        cell = "; ".join(f"{leg}: {', '.join(ps)}" for leg, ps in weak.items()) or "none"
        rows.append(["parameters the data barely inform (posterior sd ≥ half the prior's)",
                     _e(cell), "none (a warning)", '<span class="ok">pass</span>' if not weak else "<b>look</b>"])
    head = (f"<p>{_e(d.get('chains'))} chain(s) of {_e(d.get('draws'))} draws. Overall: "
            + ('<span class="ok">the fit passed its checks.</span>' if d.get("ok")
               else '<span class="fail">the fit FAILED its checks.</span>') + "</p>")
    notes = "".join(f'<p class="note">Warning: {_e(w)}</p>' for w in d.get("warnings", []))
    return '<h2 id="diagnostics">Sampling diagnostics</h2>' + head + _table(["check", "value", "needed", ""], rows, (1, 2)) + notes


def _diagnosis_section(diagnosis: dict | None) -> str:
    if not diagnosis:
        return ""
    parts = ['<h2 id="diagnosis">Which effect is missing: the diagnosis ranking</h2>',
             f'<p class="note">From {_e(diagnosis["folder"])}.</p>']
    for block in diagnosis["blocks"]:
        s = block["summary"]
        if block.get("title"):
            parts.append(f"<h3>{_e(block['title'])}</h3>")
        parts.append(f"<p>Model screened: {_e(s.model)}. <strong>Verdict: {_e(s.verdict)}.</strong> "
                     f"{_e(s.sentence)}</p>")
        rows = []
        for k, r in enumerate(s.ranking, 1):
            j5, j10 = r.get("J_500ms", {}), r.get("J_1000ms", {})
            rows.append([
                str(k), _e(r.get("effect")), f"{_num(r.get('delta_elpd'))} ± {_num(r.get('delta_elpd_se'))}",
                f"{_q(j5.get('before'))} → {_q(j5.get('after'))}", f"{_q(j10.get('before'))} → {_q(j10.get('after'))}",
                "<strong>yes</strong>" if r.get("clears_bar") else "no",
            ])
        if rows:
            parts.append(_table(["rank", "effect", "ΔELPD ± SE", "J 500 ms before → after [deg]",
                                 "J 1000 ms before → after [deg]", "clears the bar"], rows, (2, 3, 4)))
        for f in s.failed:
            parts.append(f'<p class="warning">Not screened: <strong>{_e(f.get("effect"))}</strong> '
                         f'({_e(f.get("error"))}).</p>')
        if s.not_applicable:
            parts.append('<p class="note">Not screened, as they do not apply to these data: '
                         + "; ".join(f'<strong>{_e(f.get("effect"))}</strong> ({_e(f.get("why"))})'
                                     for f in s.not_applicable) + ".</p>")
    if diagnosis.get("final_model"):
        parts.append(f"<p>Final model of the loop: <strong>{_e(diagnosis['final_model'])}</strong>.</p>")
    if diagnosis.get("mismatch"):
        parts.append(f'<p class="note">{_e(diagnosis["mismatch"])}</p>')
    return "\n".join(parts)


def _param_rows(rows: dict, prior_only=(), barely=()) -> list[list[str]]:
    """Table rows of a leg's parameters; those in ``prior_only`` (the leg's data do not inform
    them) say so beside their interval, and so do those in ``barely`` (a posterior nearly as wide
    as the prior: :func:`quadshank.inference.weakly_informed`; a component as ``a[1]``)."""
    def base(label: str) -> str:
        return label.split("[")[0]

    def mark(name: str) -> str:
        if base(name) in prior_only:
            return ' <span class="prior-only">prior only</span>'
        return ' <span class="prior-only">barely informed</span>' if name in barely or base(name) in barely else ""

    return [
        [f"<code>{_e(name)}</code>", _e(r["units"]),
         _q(r["leg"]) + mark(name),
         _q(r["subject"]), _q(r["population"]), f'<span class="doc">{_e(r.get("doc") or "")}</span>']
        for name, r in rows.items()
    ]


def _in_charge_html(leg: str, rows: dict, scale: dict | None, effects) -> str:
    """The parameters in relative charge (an effect's ``in_charge``) in the stimulator's own unit,
    for a leg read from a stimulator's columns (``scale``: its ``FitResult.charge_scale``)."""
    if not scale:
        return ""
    known = registered_effects()
    names = [p for e in effects if e in known for p in getattr(known[e], "in_charge", ())]
    parts = []
    for name in names:
        q = rows.get(name, {}).get("leg")
        if q:
            top, unit = scale["largest_charge"], scale["unit"]
            parts.append(f"<code>{_e(name)}</code> {_num(q['median'] * top)} {_e(unit)} "
                         f"[{_num(q['lo'] * top)}, {_num(q['hi'] * top)}]")
    if not parts:
        return ""
    what = {"µs": "pulse width", "mA": "current"}.get(scale["unit"], "pulse charge")
    return (f"<p>{_e(leg)}'s stimulation levels are each pulse's {what} over {_num(scale['largest_charge'])} "
            f"{_e(scale['unit'])}, the largest in its data; in {_e(scale['unit'])}: " + "; ".join(parts) + ".</p>")


def _delay_text(s: dict, sampling_period_s: float) -> str:
    p = s["delay_posterior"]
    mode = int(np.argmax(p))
    return f"mode d = {mode} samples ({mode * sampling_period_s * 1000:g} ms), P = {p[mode]:.2f}"


def _j_rows(J_leg: dict, label: str) -> list[list[str]]:
    base, paper = _paper_table_v(label)
    rows = []
    for tr, hv in sorted(J_leg.items(), key=lambda kv: int(kv[0])):
        for h, v in sorted(hv.items(), key=lambda kv: int(kv[0])):
            pv = paper.get(tr, {}).get(int(h))
            rows.append([_e(tr), _e(h), _q(v), f"{pv[0]} ({pv[1]})" if pv else "–"])
    return rows


def _delay_angle_html(da: dict) -> str:
    thr = da.get("threshold_deg")
    return (f"P(the delay changes with angle) = {da['change_probability']:.2f}; shift posterior "
            + ", ".join(f"P({k}) = {p:.2f}" for k, p in enumerate(da.get("shift_posterior", [])))
            + (f"; threshold {_q(thr)} deg" if thr else "; no draw with a change inside the pulses' angle range"))


# ============================================================================ the command


def _leg_csv(rows: dict) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    levels = ("leg", "subject", "population")
    w.writerow(["parameter", "units"] + [f"{lv}_{k}" for lv in levels for k in ("median", "lo", "hi")])
    for name, r in rows.items():
        w.writerow([name, r["units"]] + [
            "" if r[lv] is None else repr(float(r[lv][k])) for lv in levels for k in ("median", "lo", "hi")
        ])
    return buf.getvalue()


def write_report(
    out: Path,
    *,
    fit_dir,
    fit_summary: dict,
    desc: dict,
    label: str,
    J: dict,
    J_legs: dict,
    j_how: str,
    params: dict,
    spreads: dict,
    predictions: dict,
    diagnosis: dict | None,
    progress: bool = False,
) -> dict:
    """Write the pages, per-leg CSV and JSON of a fit's report into ``out`` (each file atomically);
    returns what was written: pages, figures per page, files per leg, whether the fit passed its checks.

    ``params``/``spreads``: :func:`quadshank.evaluation.leg_parameters` and
    :func:`quadshank.evaluation.population_spreads`; ``predictions[leg]``: (trial, window,
    predictions) for :func:`plot_leg_predictions`; ``diagnosis``: a diagnosis or discovery
    summary read for the report, or None.
    """
    fs, legs, diag_info = fit_summary, list(desc["legs"]), diagnosis
    dt = desc.get("sampling_period_s", SAMPLING_PERIOD_S)
    subjects = list(dict.fromkeys(params[leg]["subject"] for leg in legs))
    subject_legs = {s: [leg for leg in legs if params[leg]["subject"] == s] for s in subjects}
    pages = {s: f"subject-{stem}.html" for s, stem in file_stems(subjects).items()}
    leg_stem = file_stems(legs)
    diag_ok = bool(fs.diagnostics.get("ok"))
    fitted_trials = ", ".join(map(str, desc["trials"]))
    base, paper = _paper_table_v(label)
    header = (f'<p class="note">Model <strong>{_e(label)}</strong> ({_e(", ".join(desc["effects"]))}), fit {_e(fit_dir)}, '
              f"fitted on trial(s) {_e(fitted_trials)}; intervals are 90 % (5 % to 95 % quantiles) around the posterior "
              f"median. J_φ,p {_e(j_how)}. {_e(recordings_sentence(dt, fs.derived_signals, 'no_muscle' not in fs.effects))}</p>")
    files: list[str] = []

    # ---------------------------------------------------------------- per leg: CSV and JSON
    for leg in legs:
        s = fs.legs[leg]
        doc = {
            "leg": leg, "subject": params[leg]["subject"], "model": label, "fit": str(fit_dir),
            "interval": list(INTERVAL), "diagnostics_ok": diag_ok,
            "params": {k: {kk: v[kk] for kk in ("units", "leg", "subject", "population")} for k, v in params[leg]["params"].items()},
            "delay_posterior": s["delay_posterior"], "delay_mode_samples": s["delay_mode_samples"],
            "J": J_legs.get(leg, {}),
        }
        if "delay_angle" in s:
            doc["delay_angle"] = s["delay_angle"]
        atomic_write_text(out / "legs" / f"{leg_stem[leg]}.csv", _leg_csv(params[leg]["params"]))
        write_json(out / "legs" / f"{leg_stem[leg]}.json", doc)
        files += [f"legs/{leg_stem[leg]}.csv", f"legs/{leg_stem[leg]}.json"]

    warning = _warning_box(fs.diagnostics)
    diag_html = _diagnostics_section(fs.diagnostics)
    diagnosis_html = _diagnosis_section(diag_info)
    nav = '<nav><a href="index.html">cohort index</a>' + "".join(
        f'<a href="{_e(p)}">subject {_e(s)}</a>' for s, p in pages.items()) + "</nav>"
    figures_per_page: dict[str, int] = {}
    muscle = "no_muscle" not in fs.effects  # the pendulum alone (--model passive) has no delay to show

    # ---------------------------------------------------------------- subject pages
    for subject in progress_bar(subjects, desc="report pages", enabled=progress):
        sl = subject_legs[subject]
        body = [nav, f"<h1>Subject {_e(subject)}: credible parameters of {_e(label)}</h1>", warning, header]
        figs = 0
        body.append('<h2 id="shrinkage">Shrinkage: legs, subject and population</h2>')
        body.append('<p class="note">Each parameter in prior scales from the prior\'s centre (log value for a '
                    "log-normal prior); grey: the prior's 90 % interval. Legs pulled towards their subject and the "
                    "population show how much the hierarchy pools.</p>")
        body.append(_figure(_data_uri(plot_shrinkage(subject, sl, params)), f"shrinkage of subject {subject}"))
        figs += 1
        if muscle:
            body.append('<h2 id="delay">Delay posterior</h2>')
            body.append(_figure(_data_uri(plot_delay_posterior(sl, fs.legs, dt)), f"delay posterior of subject {subject}"))
            figs += 1
        if any("delay_angle" in fs.legs[leg] for leg in sl):
            body.append('<h2 id="delay-angle">Delay against knee angle</h2>')
            sub = {leg: fs.legs[leg] for leg in sl if "delay_angle" in fs.legs[leg]}
            body.append(_figure(_data_uri(plot_delay_angle(sub, label)), f"delay-angle curve of subject {subject}"))
            figs += 1
        body.append('<h2 id="j">Prediction error J_φ,p against horizon</h2>')
        body.append(f'<p class="note">Per leg and trial, median and 90 % band over posterior draws; dotted: the paper\'s '
                    f"Table V for {_e(base)}, mean (s.d.) over its five legs"
                    + ("" if paper else " (the paper reports no such model)") + ".</p>")
        body.append(_figure(_data_uri(_plot_j_legs(sl, J_legs, label)), f"J against horizon, subject {subject}"))
        figs += 1
        for leg in sl:
            s = fs.legs[leg]
            u = (fs.uninformed or {}).get(leg)
            body.append(f'<h2 id="leg-{_e(leg_stem[leg])}">Leg {_e(leg)}</h2>')
            delay = (f"Delay: {_e(_delay_text(s, dt))}{' (prior only)' if u else ''}" if muscle else
                     "No muscle, so no delay: the pendulum alone")
            body.append(f"<p>{delay}. Files: "
                        f'<a href="legs/{_e(leg_stem[leg])}.csv">CSV</a>, <a href="legs/{_e(leg_stem[leg])}.json">JSON</a>.</p>')
            if u:
                body.append(f'<p class="note prior-only-note">{_e(leg)}: {_e(u["why"])} in the fitted trials. Its delay '
                            f"and {_e(', '.join(u['params']))} are not estimates from its data: their values are the "
                            "prior's and what the other legs tell the population (marked <em>prior only</em>).</p>")
            if "delay_angle" in s:
                body.append(f"<p>{_delay_angle_html(s['delay_angle'])}.</p>")
            body.append(f"<h3>Credible parameters of {_e(leg)}</h3>")
            body.append(_table(["parameter", "units", f"leg {leg}", f"subject {subject}", "population", "meaning"],
                               _param_rows(params[leg]["params"], u["params"] if u else (),
                                           ((fs.diagnostics or {}).get("weakly_informed") or {}).get(leg, {})), (2, 3, 4)))
            charge = _in_charge_html(leg, params[leg]["params"], (fs.charge_scale or {}).get(leg), fs.effects)
            if charge:
                body.append(charge)
            body.append(f"<h3>J_φ,p of {_e(leg)} [deg]</h3>")
            body.append(_table(["trial", "horizon [ms]", "median [90 %]", f"paper {base}: mean (s.d.)"],
                               _j_rows(J_legs.get(leg, {}), label), (2, 3)))
            fig, trial_no = plot_leg_predictions(leg, *predictions[leg], J_legs, desc["trials"])
            body.append(f"<h3>Measured and predicted angle, {_e(leg)}, trial {trial_no}</h3>")
            body.append(_figure(_data_uri(fig), f"predictions of {leg}"))
            figs += 1
        body += [diag_html, diagnosis_html]
        atomic_write_text(out / pages[subject], _page(f"quadshank report: subject {subject}", body))
        figures_per_page[pages[subject]] = figs
        files.append(pages[subject])

    # ---------------------------------------------------------------- index
    body = [nav, f"<h1>Credible parameters of {_e(label)}: cohort</h1>", warning, header]
    rows = []
    for leg in legs:
        s = fs.legs[leg]
        subject = params[leg]["subject"]
        j = J_legs.get(leg, {})
        tr = sorted(j, key=int)[-1] if j else None
        rows.append([
            _e(subject), f'<a href="{_e(pages[subject])}#leg-{_e(leg_stem[leg])}">{_e(leg)}</a>', _e(_delay_text(s, dt)) if muscle else "– (no muscle)",
            (f"trial {_e(tr)}: {_q(j[tr].get('1000'))}" if tr else "–"),
            '<span class="ok">passed</span>' if diag_ok else '<span class="fail">FAILED</span>',
        ])
    body.append('<h2 id="legs">Subjects and legs</h2>')
    body.append(_table(["subject", "leg", "delay", "J at 1 s [deg]", "fit checks"], rows, (3,)))
    body.append('<h2 id="population">Population-level parameters</h2>')
    body.append('<p class="note">Population mean, and the spreads between subjects and between the legs of a subject '
                "(standard deviations on the prior's scale: log units for a log-normal prior).</p>")
    any_leg = params[legs[0]]["params"]
    prow = [[f"<code>{_e(k)}</code>", _e(v["units"]), _q(v["population"]), _q(spreads.get(k, {}).get("sd_subject")),
             _q(spreads.get(k, {}).get("sd_leg"))] for k, v in any_leg.items() if v["prior"] is not None]
    body.append(_table(["parameter", "units", "population mean", "between subjects", "between legs"], prow, (2, 3, 4)))
    index_figs = 0
    if J:
        body.append('<h2 id="table-v">Table V (posterior): J_φ,p of the mean over legs</h2>')
        body.append(f'<p class="note">Median and 90 % band over posterior draws of the mean over the fit\'s legs; dotted: '
                    f"the paper's Table V for {_e(base)}, mean (s.d.) over its five legs"
                    + ("" if paper else " (the paper reports no such model)") + ".</p>")
        body.append(_figure(_data_uri(_plot_j_legs(["mean over legs"], {"mean over legs": J}, label)),
                            "posterior Table V against the paper's"))
        index_figs += 1
        trows = []
        for tr, hv in sorted(J.items(), key=lambda kv: int(kv[0])):
            for h, v in sorted(hv.items(), key=lambda kv: int(kv[0])):
                pv = paper.get(tr, {}).get(int(h))
                trows.append([_e(tr), _e(h), _q(v), f"{pv[0]} ({pv[1]})" if pv else "–"])
        body.append(_table(["trial", "horizon [ms]", "median [90 %] [deg]", f"paper {base}: mean (s.d.)"], trows, (2, 3)))
    if fs.delay_angle_population is not None:
        body.append('<h2 id="delay-angle">Delay against knee angle, legs pooled</h2>')
        body.append(_figure(_data_uri(plot_delay_angle({}, label, fs.delay_angle_population)),
                            "population delay-angle curve"))
        index_figs += 1
    body += [diag_html, diagnosis_html]
    atomic_write_text(out / "index.html", _page(f"quadshank report: {label}", body))
    figures_per_page["index.html"] = index_figs
    files.insert(0, "index.html")

    return {
        "pages": {"index": "index.html", **{f"subject {s}": p for s, p in pages.items()}},
        "figures": figures_per_page,
        "legs": {leg: {"subject": params[leg]["subject"], "page": pages[params[leg]["subject"]],
                       "csv": f"legs/{leg_stem[leg]}.csv", "json": f"legs/{leg_stem[leg]}.json"} for leg in legs},
        "files": files,
        "diagnostics_ok": diag_ok,
    }
