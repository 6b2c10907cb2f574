"""``quadshank recovery`` and ``likelihood-check``: calibration on matching truths, written to a folder."""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from ..common._io import atomic_write_text, read_json, write_json
from ..common._provenance import code_fingerprint
from ..data._paper import LEGS
from ..evaluation._recovery import (
    DELAY_SEEN,
    MATCHING_NOISE,
    LegMaximumLikelihood,
    _binomial_band,
    add_pulls,
    coverage_rows,
    likelihood_calibration,
    simulate_matching,
)
from ..inference._fitio import FitResult, from_json, read_summary, to_json
from ..inference._nuts import FitSettings
from ..inference._priors import build_model
from ..model._likelihood import max_shift
from ..outputs._recovery import coverage_markdown, likelihood_markdown
from .fit import run_fit


def _finished_fit(fit_dir: Path, truth: dict, settings) -> FitResult | None:
    """The summary of a complete earlier fit of the same truth with the same settings by the
    same code (its source fingerprint, :func:`quadshank.common._provenance.code_fingerprint`), else None.

    A recovery run that was interrupted, or whose table is rebuilt, reuses such fits; after
    any change to the package the fits are made again.
    """

    try:
        summary = read_summary(fit_dir)
        same_truth = read_json(fit_dir / "truth.json") == json.loads(json.dumps(truth))
    except (FileNotFoundError, ValueError, KeyError):
        return None
    same_code = summary.code.get("fingerprint") == code_fingerprint()
    return summary if same_truth and same_code and summary.settings == _settings_json(settings) else None


def _settings_json(settings) -> dict:
    """FitSettings as a fit's summary.json holds them (through the fit description's JSON)."""

    return from_json(to_json(dataclasses.asdict(settings)))


def run_recovery(
    out: str | Path,
    models: Iterable[str] = ("model1", "model2", "model3"),
    seeds: Iterable[int] = (0, 1, 2),
    legs: Sequence[str] | None = None,
    minutes: float = 1.0,
    settings=None,
    progress: bool = False,
    command: str = "",
    add_effects: Sequence[str] = (),
    truth_effects: Sequence[str] | None = None,
) -> dict:
    """Simulate a matching truth, fit it, and count coverage, for each model and seed.

    ``add_effects`` extend every fitted model; the truth holds ``truth_effects``
    (default: the same effects, so the truth matches; ``()`` asks whether a fit with
    an effect claims it on data without it).  Writes ``out/{name}-seed{S}/``
    (truth.json, fit.nc, summary.json; a complete fit already there of the same truth
    with the same settings by the same code is reused), then ``out/coverage.json`` (every row, and per
    model the covered fraction of the 90 % intervals with the band expected of a
    calibrated posterior, whether the posterior mode of d — and of an angle delay's
    shift — was right for every leg, and an angle delay's change probability per leg)
    and ``out/coverage.md``.
    """

    out = Path(out)
    legs = tuple(legs) if legs else LEGS
    add_effects = tuple(add_effects)
    truth_effects = add_effects if truth_effects is None else tuple(truth_effects)
    settings = settings or FitSettings(chains=2, warmup=500, draws=500)
    models, seeds = list(models), [int(s) for s in seeds]
    per_model: dict[str, dict] = {}
    all_rows = []
    for model in models:
        fitted = build_model(model, add_effects)
        name = fitted.name
        # the posterior against each leg's own likelihood (needs the truth's parameters in the fitted model)
        ml = LegMaximumLikelihood(fitted, MATCHING_NOISE) if not max_shift(fitted) and truth_effects == add_effects else None
        rows, diags = [], []
        for seed in seeds:
            cohort, truth = simulate_matching(model, legs, minutes, seed, add_effects=truth_effects)
            fit_dir = out / f"{name}-seed{seed}"
            fs = dataclasses.replace(settings, seed=seed)
            summary = _finished_fit(fit_dir, truth, fs)
            reused = summary is not None
            if summary is None:
                fit_dir.mkdir(parents=True, exist_ok=True)
                write_json(fit_dir / "truth.json", truth)
                summary = run_fit(cohort, fit_dir, model, add_effects, fs, progress=progress)
            diag = summary.diagnostics
            info = {"seed": seed, "reused": reused, **{k: diag[k] for k in ("rhat_max", "ess_bulk_min", "divergences", "ok")},
                    "sampling_seconds": summary.sampling_seconds, "delay_splits": diag.get("delay_splits", {}),
                    "delay_missed": diag.get("delay_missed", {})}  # fmt: skip
            changes = {leg: s["delay_angle"]["change_probability"] for leg, s in summary.legs.items() if "delay_angle" in s}
            if changes:
                info["change_probability"] = changes
                info["threshold_deg"] = {leg: s["delay_angle"]["threshold_deg"] for leg, s in summary.legs.items()
                                         if "delay_angle" in s}  # fmt: skip
            diags.append(info)
            seed_rows = coverage_rows(summary.legs, truth)
            if ml is not None:
                add_pulls(seed_rows, ml, cohort, truth)
            for r in seed_rows:
                rows.append({"model": name, "seed": seed, **r})
        params = [r for r in rows if r["param"] not in ("delay", "shift")]
        n_cov = sum(r["covered"] for r in params)
        by_param: dict[str, list[bool]] = {}
        for r in params:
            by_param.setdefault(r["param"], []).append(r["covered"])
        per_model[name] = {
            "truth_effects": list(truth_effects),
            "n_intervals": len(params),
            "covered": n_cov,
            "coverage": n_cov / len(params) if params else math.nan,
            "expected_band_95": list(_binomial_band(len(params))),
            "by_param": {k: {"covered": int(sum(v)), "n": len(v)} for k, v in by_param.items()},
            "fits": diags,
        }
        for discrete in ("delay", "shift"):
            hits = [r["covered"] for r in rows if r["param"] == discrete]
            if hits:
                per_model[name][f"{discrete}_mode_right"] = int(sum(hits))
                per_model[name][f"{discrete}_legs"] = len(hits)
        right = {(r["seed"], r["leg"]) for r in rows if r["param"] == "delay" and r["covered"]}
        pulls: dict[tuple[str, str], list[float]] = {}
        for r in params:
            if "pull" in r and (r["seed"], r["leg"]) in right:
                pulls.setdefault((r["param"], r["leg"]), []).append(r["pull"])
        if pulls:
            order = list(dict.fromkeys(r["param"] for r in params))
            per_model[name]["pull"] = [
                {"param": k, "leg": leg, "fits": len(v), "median_abs": float(np.median(np.abs(v))),
                 "max_abs": float(np.max(np.abs(v))), "mean": float(np.mean(v))}
                for (k, leg), v in sorted(pulls.items(), key=lambda kv: (order.index(kv[0][0]), legs.index(kv[0][1])))
            ]  # fmt: skip
        # a mode of a flat P(d) means nothing: count the legs whose data chose a delay at all
        per_model[name]["delay_seen_legs"] = sum(r.get("p_mode", 0.0) >= DELAY_SEEN for r in rows if r["param"] == "delay")
        all_rows.extend(rows)
    result = {
        "command": command,
        "interval": 0.9,
        "legs": list(legs),
        "minutes": minutes,
        "seeds": seeds,
        "settings": _settings_json(settings),
        "noise": MATCHING_NOISE,
        "models": per_model,
        "rows": all_rows,
    }
    write_json(out / "coverage.json", result)
    atomic_write_text(out / "coverage.md", coverage_markdown(result))
    return result


def run_likelihood_calibration(
    out: str | Path,
    models: Iterable[str] = ("model1", "model2", "model3"),
    seeds: Iterable[int] = (0,),
    legs: Sequence[str] | None = None,
    minutes: float = 1.0,
    replicates: int = 100,
    progress: bool = False,
    command: str = "",
) -> dict:
    """:func:`likelihood_calibration` for each model and seed; writes ``out/likelihood.json``
    and ``out/likelihood.md`` and returns what the JSON holds."""

    out = Path(out)
    legs = tuple(legs) if legs else LEGS
    runs = [likelihood_calibration(m, legs, minutes, int(s), replicates, progress=progress) for m in models for s in seeds]
    result = {"command": command, "interval": 0.9, "legs": list(legs), "minutes": minutes, "replicates": replicates, "runs": runs}
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "likelihood.json", result)
    atomic_write_text(out / "likelihood.md", likelihood_markdown(result))
    return result
