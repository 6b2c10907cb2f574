"""The recovery and likelihood-check tables as Markdown."""

from __future__ import annotations

import math

from ..evaluation._recovery import DELAY_SEEN
from ._tables import markdown_table


def _number(x, spec: str) -> str:
    """``x`` formatted, or "–" where it could not be computed (R-hat of one chain: NaN in a live
    result, null in a summary read back)."""
    return "–" if x is None or not math.isfinite(x) else format(x, spec)


def _sampling_row(model: str, f: dict) -> dict[str, str]:
    """One fit's row of the sampling table: convergence, where chains split over delays, time."""
    secs = f.get("sampling_seconds")
    splits, missed = f.get("delay_splits"), f.get("delay_missed")
    where = "–" if splits is None else ", ".join(f"{leg} {'/'.join(map(str, d))}" for leg, d in splits.items()) or "none"
    unseen = "–" if missed is None else "; ".join(
        f"{leg} " + ", ".join(f"d = {d} ({e:.2f})" for d, (e, _c) in ds.items()) for leg, ds in missed.items()) or "none"
    return {"model": model, "seed": str(f["seed"]), "R-hat max": _number(f["rhat_max"], ".3f"),
            "bulk ESS min": _number(f["ess_bulk_min"], ".0f"), "divergences": str(f["divergences"]),
            "chains at different delays": where, "delays weighed but not visited": unseen,
            "sampling [s]": "" if secs is None else f"{secs:.0f}"}


def coverage_markdown(result: dict) -> str:
    """The coverage table of :func:`run_recovery` as Markdown."""
    lines = [
        "# Parameter recovery on a matching truth",
        "",
        f"Regenerate: `{result['command']}`" if result.get("command") else "",
        "",
        f"Data simulated from the fitted model itself (see `quadshank.evaluation.simulate_matching` and docs/recovery.md), {len(result['legs'])} legs × "
        f"{result['minutes']:g} min of trial 1, seeds {', '.join(map(str, result['seeds']))}; "
        f"NUTS {result['settings']['chains']} chains × {result['settings']['draws']} draws after "
        f"{result['settings']['warmup']} warm-up.  A calibrated posterior covers 90 % of the true values; "
        "the band is where the covered fraction of a calibrated posterior falls 95 % of the time "
        "(intervals treated as independent, which legs sharing a population are not quite).",
        "",
    ]
    lines += markdown_table([
        {"model": model, "effects in the truth": ", ".join(m["truth_effects"]) or "none",
         "90 % intervals covering the truth": f"{m['covered']}/{m['n_intervals']} = {m['coverage']:.2f}",
         "expected (95 % band)": "{:.2f}–{:.2f}".format(*m["expected_band_95"]),
         "delay mode right": f"{m['delay_mode_right']}/{m['delay_legs']} legs "
                             f"(P(mode) ≥ {DELAY_SEEN} in {m['delay_seen_legs']})",
         "shift mode right": f"{m['shift_mode_right']}/{m['shift_legs']} legs" if "shift_legs" in m else "–",
         "fits ok": f"{sum(bool(f['ok']) for f in m['fits'])}/{len(m['fits'])}"}
        for model, m in result["models"].items()
    ]).splitlines()
    changes = [(model, f) for model, m in result["models"].items() for f in m["fits"] if "change_probability" in f]
    if changes:
        lines += ["", "## Angle delay: P(the delay changes with angle), and where (median, 90 % interval)", ""]
        for model, f in changes:
            cells = []
            for leg, p in f["change_probability"].items():
                thr = f.get("threshold_deg", {}).get(leg)
                where = f", threshold {thr['median']:.1f}° [{thr['lo']:.1f}, {thr['hi']:.1f}]" if thr else ""
                cells.append(f"{leg} {p:.2f}{where}")
            lines.append(f"- {model}, seed {f['seed']}: {'; '.join(cells)}")
    lines += ["", "## By parameter (covered / intervals, over legs and seeds)", ""]
    for model, m in result["models"].items():
        cells = ", ".join(f"{k} {v['covered']}/{v['n']}" for k, v in m["by_param"].items())
        lines.append(f"- **{model}**: {cells}")
    pulled = [(model, m["pull"]) for model, m in result["models"].items() if m.get("pull")]
    if pulled:
        lines += ["", "## The posterior against each leg's own likelihood", "",
                  "pull = (posterior median − the leg's maximum likelihood at the true delay) / its standard error, "
                  "over the legs whose posterior mode of d is right: how far the prior and the pooling of legs "
                  "moved each parameter from what the leg's data say (`likelihood-check` calibrates the "
                  "likelihood itself).", ""]
        lines += markdown_table([
            {"model": model, "parameter": v["param"], "leg": v["leg"], "fits": str(v["fits"]),
             "median abs(pull)": f"{v['median_abs']:.2f}", "max abs(pull)": f"{v['max_abs']:.2f}",
             "mean pull": f"{v['mean']:+.2f}"}
            for model, pull in pulled for v in pull
        ]).splitlines()
    lines += ["", "## Sampling", ""]
    lines += markdown_table([_sampling_row(model, f) for model, m in result["models"].items() for f in m["fits"]]).splitlines()
    # a mode of a flat P(d) (model 1) is no claim: only legs whose data chose a delay
    wrong = [r for r in result.get("rows", []) if r["param"] == "delay" and not r["covered"] and r.get("p_mode", 0) >= DELAY_SEEN]
    if wrong:
        lines += ["", "## Legs whose posterior mode of d is wrong", "",
                  f"Among legs whose P(mode) ≥ {DELAY_SEEN}: P(true d) in the chains and by a Laplace approximation "
                  "per delay (`delay_evidence`).", ""]
        lines += markdown_table([
            {"model": r["model"], "seed": str(r["seed"]), "leg": r["leg"], "true d": f"{r['true']:.0f}",
             "mode": f"{r['median']:.0f}", "P(true d), chains": f"{r.get('p_true', float('nan')):.2f}",
             "P(true d), Laplace per delay": "–" if r.get("p_true_evidence") is None else f"{r['p_true_evidence']:.2f}"}
            for r in wrong
        ]).splitlines()
    return "\n".join(lines) + "\n"


def likelihood_markdown(result: dict) -> str:
    """The tables of :func:`run_likelihood_calibration` as Markdown."""
    lines = [
        "# The likelihood alone: maximum likelihood on noise replicates of a matching truth",
        "",
        f"Regenerate: `{result['command']}`" if result.get("command") else "",
        "",
        f"One trajectory per leg and seed ({result['minutes']:g} min of trial 1, simulated from the model itself), its "
        f"acceleration noise drawn afresh {result['replicates']} times; each replicate fitted by maximum likelihood, "
        "each leg alone, at its true delay, with σ and ν free (`quadshank.evaluation.likelihood_calibration`).  "
        "z = (estimate − truth) / standard error from the Hessian.  A calibrated likelihood gives z a mean of 0 "
        "(± its standard error) and an sd of 1, and its Wald 90 % intervals cover 90 % of the time.  No prior, no "
        "pooling of legs, no delay uncertainty and no sampler enter here, so a shortfall of a recovery run's "
        "posterior coverage that this check does not show lies in one of those.",
        "",
    ]
    lines += markdown_table([
        {"model": r["model"], "seed": str(r["seed"]),
         "90 % intervals covering the truth": f"{r['covered']}/{r['intervals']} = {r['coverage']:.3f}",
         "expected (95 % band)": "{:.3f}–{:.3f}".format(*r["expected_band_95"]),
         "replicates with a maximum, per leg": ", ".join(f"{leg} {v['converged']}" for leg, v in r["legs"].items())}
        for r in result["runs"]
    ]).splitlines()
    for r in result["runs"]:
        lines += ["", f"## {r['model']}, seed {r['seed']}: z mean ± se / z sd / coverage", ""]
        lines += markdown_table([
            {"leg": leg, **{name: f"{p['z_mean']:+.2f} ± {p['z_se']:.2f} / {p['z_sd']:.2f} / {p['coverage']:.2f}"
                            for name, p in v["params"].items()}}
            for leg, v in r["legs"].items()
        ]).splitlines()
    lines += [
        "",
        "σ and ν are shown, not counted in the coverage: on twitch windows (models 1 and 3) the likelihood takes a "
        "window's sum of Student-t samples as a Student-t with the sum's variance and kurtosis, an approximation.",
    ]
    return "\n".join(lines) + "\n"
