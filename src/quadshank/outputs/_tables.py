"""Tables I–V analogues as rows, written as CSV and Markdown.

A table is a list of rows (dicts with the same keys, in column order).  Values
are numbers or strings; numbers are formatted to 3 significant figures in
Markdown and written in full in CSV.
"""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from ..common._io import atomic_write_text
from ..data._paper import (
    SAMPLING_PERIOD_S,
    TABLE_I,
    TABLE_II,
    TABLE_III,
    TABLE_IV,
    TABLE_V,
)

__all__ = [
    "write_table",
    "markdown_table",
    "active_legs",
    "table_passive",
    "table_i",
    "table_ii",
    "table_iii",
    "table_iv",
    "table_v_rows",
    "sign_test_rows",
    "SIGN_TEST_COLUMNS",
    "recordings_sentence",
]


def _fmt(v) -> str:
    if isinstance(v, str):
        return v
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    if isinstance(v, int):
        return str(v)
    return f"{v:.3g}"


def _columns(rows: list[dict]) -> list[str]:
    """Every key of the rows, in the order of first appearance (rows may differ: a leg with the
    paper's values has columns that another leg lacks)."""
    return list(dict.fromkeys(k for r in rows for k in r))


def markdown_table(rows: list[dict], title: str = "") -> str:
    """Rows (dicts; a key a row lacks is an empty cell) as a Markdown table under a ``###`` title; numbers to 3 significant figures."""
    if not rows:
        return f"### {title}\n\n(no rows)\n" if title else "(no rows)\n"
    cols = _columns(rows)
    lines = [f"### {title}", ""] if title else []
    lines.append("| " + " | ".join(cols) + " |")
    lines.append("|" + "|".join("---" for _ in cols) + "|")
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r.get(c)) for c in cols) + " |")
    return "\n".join(lines) + "\n"


def write_table(rows: list[dict], folder: str | Path, stem: str, title: str, columns=None) -> str:
    """Write ``stem.csv`` and ``stem.md`` in ``folder``; returns the Markdown.  ``columns``: the
    header of a table that may have no rows, so that its CSV still reads as an empty table (a
    file of no bytes is no CSV to pandas or a spreadsheet)."""
    folder = Path(folder)
    buf = io.StringIO()
    if rows or columns:
        w = csv.DictWriter(buf, fieldnames=_columns(rows) if rows else list(columns), lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
    atomic_write_text(folder / f"{stem}.csv", buf.getvalue())
    md = markdown_table(rows, title)
    atomic_write_text(folder / f"{stem}.md", md)
    return md


def active_legs(ident: dict) -> dict:
    """The legs identified with their muscle (not those with the passive system alone)."""
    return {leg: r for leg, r in ident.items() if "model1" in r.models}


def _leg_truth(truth: dict | None, leg: str) -> dict | None:
    if not truth:
        return None
    return truth.get("legs", {}).get(leg)


def _samples_ms(samples: int, sampling_period_s: float):
    """A number of samples in milliseconds (a whole number where it is one)."""
    ms = round(samples * sampling_period_s * 1000, 9)
    return int(ms) if float(ms).is_integer() else ms


def table_passive(ident: dict, truth: dict | None = None) -> list[dict]:
    """Identified passive parameters per leg, beside the truth when given."""
    rows = []
    for leg, r in ident.items():
        t = _leg_truth(truth, leg)
        row = {"leg": leg}
        for k, unit in (("damping", "1/s"), ("gravity", "deg/s²"), ("k1", "deg/s²"), ("k2", "1/deg"),
                        ("gravity_angle", "deg")):
            if k not in r.passive:  # gravity_angle: only where it was identified
                continue
            row[f"{k} [{unit}]"] = r.passive[k]
            se = getattr(r, "passive_se", {})
            if k in ("gravity", "k1", "k2") and k in se:  # the three that trade against each other
                row[f"{k} ±"] = se[k]
            if t and k in t["passive"]:
                row[f"{k} true"] = t["passive"][k]
        row["quiet samples"] = r.n_quiet
        if getattr(r, "passive_objective", "acceleration") == "angle":
            row["fitted to"] = "angle (free run)"
            row["rms free-run error [deg]"] = r.passive_rms_residual
        else:
            row["rms residual [deg/s²]"] = r.passive_rms_residual
        trials = getattr(r, "passive_trials", ())
        row["from"] = (f"trial{'s' if len(trials) > 1 else ''} {', '.join(map(str, trials))} (no pulses)" if trials
                       else f"quiet samples of trial {r.trial}")
        rows.append(row)
    return rows


def table_i(ident: dict, truth: dict | None = None) -> list[dict]:
    """Table I analogue: model 1's gain and the delay per leg, beside the paper's and the truth."""
    rows = []
    for leg, r in active_legs(ident).items():
        t = _leg_truth(truth, leg)
        row = {
            "leg": leg,
            "G'1 [deg/s²]": r.models["model1"].flat_params()["gain"],
            "(std)": r.g1_std,
            "d [ms]": _samples_ms(r.delay, r.models["model1"].sampling_period_s),
            "twitches": len(r.pulses),
        }
        if t:
            row["true G'2 (twitch integral at rest)"] = t["active"]["G2"]
            row["true delay [ms]"] = t["active"]["delay_s"] * 1000
        if leg in TABLE_I:
            row["paper G'1"] = TABLE_I[leg]["G1"]
            row["paper d [ms]"] = _samples_ms(TABLE_I[leg]["delay"], SAMPLING_PERIOD_S)
        rows.append(row)
    return rows


def table_ii(ident: dict, truth: dict | None = None) -> list[dict]:
    """Table II analogue: model 2's DARMA coefficients per leg, beside the paper's and the truth."""
    rows = []
    for leg, r in active_legs(ident).items():
        p = r.models["model2"].flat_params()
        t = _leg_truth(truth, leg)
        row = {"leg": leg, "a1": p["a1"], "a2": p["a2"], "b'1 [deg/s²]": p["b1"], "b'2 [deg/s²]": p["b2"]}
        row.update({"c1": r.whitening["c1"], "c2": r.whitening["c2"]})
        if t:
            eq = t["model2_equivalent"]
            row.update({f"true {k}": eq[k] for k in ("a1", "a2", "b1", "b2") if k in eq})
        if leg in TABLE_II:
            row.update({f"paper {k}": v for k, v in TABLE_II[leg].items()})
        rows.append(row)
    return rows


def table_iii(ident: dict, truth: dict | None = None) -> list[dict]:
    """Table III analogue: model 3's gain and torque–angle and torque–velocity factors per leg."""
    rows = []
    for leg, r in active_legs(ident).items():
        p = r.models["model3"].flat_params()
        t = _leg_truth(truth, leg)
        row = {
            "leg": leg,
            "G'2 [deg/s²]": p["gain"],
            "γ_angle [1/deg]": p["gamma_angle"],
            "γ_velocity [s/deg]": p["gamma_velocity"],
        }
        if t:
            row.update(
                {
                    "true G'2": t["active"]["G2"],
                    "true γ_angle": t["active"]["gamma_angle"],
                    "true γ_velocity": t["active"]["gamma_velocity"],
                }
            )
        if leg in TABLE_III:
            row.update({"paper G'2": TABLE_III[leg]["G2"], "paper γ_angle": TABLE_III[leg]["gamma_angle"]})
            row["paper γ_velocity"] = TABLE_III[leg]["gamma_velocity"]
        rows.append(row)
    return rows


def table_iv(ident: dict) -> list[dict]:
    """Table IV analogue: the RMS error of models 1 and 3 on the integrated twitches [% of G'1] per leg, beside the paper's."""
    rows = []
    for leg, r in active_legs(ident).items():
        row = {"leg": leg, "model 1 [%]": r.rms_error_pct["model1"], "model 3 [%]": r.rms_error_pct["model3"]}
        if leg in TABLE_IV:
            row["paper model 1 [%]"], row["paper model 3 [%]"] = TABLE_IV[leg]
        rows.append(row)
    return rows


def table_v_rows(table: dict) -> list[dict]:
    """Rows of the Table V analogue with the paper's values beside."""
    rows = []
    for trial in sorted(table):
        for h in sorted({h for m in table[trial].values() for h in m}):
            row = {"trial": trial, "horizon [ms]": int(h)}
            for model in sorted(table[trial]):
                mean, sd, _ = table[trial][model][h]
                row[f"{model} mean"] = mean
                row[f"{model} sd"] = sd
            for model in sorted(table[trial]):
                paper = TABLE_V.get(trial, {}).get(model, {}).get(int(h))
                row[f"paper {model}"] = f"{paper[0]} ({paper[1]})" if paper else "–"
            rows.append(row)
    return rows


#: The columns of :func:`sign_test_rows`.
SIGN_TEST_COLUMNS = ("horizon [ms]", "pair", "pairs", "A better", "B better", "p", "significant (α=0.05)")


def sign_test_rows(tests: list[dict]) -> list[dict]:
    """Sign tests between models as table rows (columns :data:`SIGN_TEST_COLUMNS`)."""
    return [
        dict(zip(SIGN_TEST_COLUMNS, (t["horizon_ms"], f"{t['model_a']} vs {t['model_b']}", t["n_pairs"], t["a_better"],
                                     t["b_better"], t["p_value"], "yes: " + t["better"] if t["significant"] else "no")))
        for t in sorted(tests, key=lambda t: (t["horizon_ms"], t["model_a"], t["model_b"]))
    ]


def recordings_sentence(sampling_period_s: float, derived: dict | None, muscle: bool = True) -> str:
    """What a page of results should say about the recordings behind it: the sampling period,
    which signals were derived from the angle (``derived``: a fit's ``derived_signals``, signal
    → ``{"method", "window_samples", "trials"}``), and, away from the paper's 10 ms, that gains
    counted per sample are not the paper's (a twitch's sum over its samples scales as 1/T_s)."""
    ms = sampling_period_s * 1000
    text = f"Recordings sampled every {ms:g} ms"
    if derived:
        text += "; " + "; ".join(
            f"{signal} derived from the angle ({d.get('method', 'filtered')}, {d.get('window_samples', '?')} samples) "
            f"in {len(d.get('trials', ()))} trial{'s' if len(d.get('trials', ())) != 1 else ''}"
            for signal, d in derived.items())
    text += "."
    ratio = SAMPLING_PERIOD_S / sampling_period_s
    if muscle and abs(ratio - 1) > 1e-6:
        text += (f" Gains are per sample: at {ms:g} ms a twitch's gain is about {ratio:.3g}× the paper's values at "
                 f"{SAMPLING_PERIOD_S * 1000:g} ms quoted beside them.")
    return text
