"""``quadshank report``: the credible-parameter report of a fit (pages written by :mod:`quadshank.outputs._report`)."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import ClassVar

from ..common._io import nulls_as_nan, read_json
from ..common._results import Result, SchemaError
from ..data._interchange import load_cohort
from ..evaluation._parameters import leg_parameters, population_spreads
from ..evaluation._posterior import (
    PosteriorEvaluation,
    check_fit_legs,
    figure_window,
    load_fits,
    posterior_j,
    summarise_j,
    window_predictions,
)
from ..evaluation._prediction import figure_trial, horizon_samples
from ..inference._fitio import posterior_models
from ..loop._diagnose import Diagnosis, Discovery
from ..outputs._report import PREDICTION_HORIZONS_MS, PREDICTION_WINDOW_S, write_report

__all__ = ["Report", "run_report"]


@dataclasses.dataclass
class Report(Result):
    """What ``quadshank report`` wrote: the pages, figures and per-leg files of a fit's report,
    and where its J came from."""

    KIND: ClassVar[str] = "report"

    fit: str  # the fit folder
    model: str
    pages: dict  # "index" and "subject S" -> HTML file, relative to the report folder
    figures: dict  # page -> its figures
    legs: dict  # leg -> subject, page, csv, json
    files: list
    diagnostics_ok: bool  # the fit passed its sampling checks
    J_source: str  # "evaluation" or "computed"
    J_how: str
    n_draws: int
    start_stride: int
    report_seconds: float
    diagnosis: str | None = None  # the diagnose/discover folder shown, if any


def _j_from_evaluation(folder, label: str, legs, fit_id: str | None = None) -> tuple[dict, dict, str]:
    path = Path(folder) / "summary.json"
    doc = read_json(path)
    if not isinstance(doc, dict) or doc.get("schema") != PosteriorEvaluation.schema():
        raise SchemaError(f"{path}: not an output of `quadshank evaluate --fit` (its schema is {doc.get('schema') if isinstance(doc, dict) else None!r})")
    s = PosteriorEvaluation.from_json(doc, str(path))
    if label not in s.J_legs:
        raise ValueError(f"{folder}: the evaluation has no fit of {label!r} (it has {', '.join(s.J_legs) or 'none'})")
    missing = [leg for leg in legs if leg not in s.J_legs[label]]
    if missing:
        raise ValueError(f"{folder}: the evaluation of {label} lacks leg(s) {', '.join(missing)}")
    fit = s.fits.get(label, {})
    if fit_id and fit.get("fit_id") and fit["fit_id"] != fit_id:
        raise ValueError(f"{folder}: evaluates another fit of {label} ({fit.get('folder', '?')}), not this one")
    how = (f"from the evaluation in {folder} ({fit.get('draws_used', s.n_draws)} posterior draws, one start in every "
           f"{s.start_stride} samples; fit {fit.get('folder', '?')})")
    # a band that came out not finite (an unstable draw) was written as null
    return nulls_as_nan(s.J.get(label, {})), nulls_as_nan(s.J_legs[label]), how


def _leg_predictions(fit, cohort, leg: str, n_draws: int, seed: int) -> tuple:
    """(trial, window, predictions) of one leg's prediction figure: 100 ms and 1 s ahead over
    :data:`quadshank.outputs._report.PREDICTION_WINDOW_S` of trial 2 (or the leg's first)."""
    trial = figure_trial(cohort, leg)
    window = figure_window(trial, PREDICTION_WINDOW_S)
    models, _ = posterior_models(fit.idata, fit.model, leg, n_draws, seed)
    horizons = horizon_samples(trial.sampling_period_s, PREDICTION_HORIZONS_MS).values()
    return trial, window, window_predictions(models, trial, horizons, window)


def _read_diagnosis(folder, label: str) -> dict:
    """A ``quadshank diagnose`` result (one ranking) or a ``discover`` one (a ranking per round):
    ``{"folder", "blocks": [{"title", "summary": Diagnosis}], "final_model"}``."""
    folder = Path(folder)
    path = folder / "summary.json"
    doc = read_json(path)
    schema = doc.get("schema") if isinstance(doc, dict) else None
    final = None
    if schema == Diagnosis.schema():
        d = Diagnosis.from_json(doc, str(path))
        blocks, models = [{"title": None, "summary": d}], [d.model]
    elif schema == Discovery.schema():
        s = Discovery.from_json(doc, str(path))
        blocks = []
        for k, r in enumerate(s.rounds, 1):
            round_dir = folder / f"round-{k}"
            rd = (Diagnosis.read(round_dir) if (round_dir / "summary.json").exists() else
                  Diagnosis(model=r["model"], legs=[], elpd=r.get("elpd", {}), J_ms=r.get("J_ms", {}), ranking=[],
                            verdict=r["verdict"], bar={}, sentence=r["sentence"], trials=[]))
            blocks.append({"title": f"round {k}", "summary": rd})
        models, final = [r["model"] for r in s.rounds], s.final_model
    else:
        raise SchemaError(f"{path}: not an output of `quadshank diagnose` or `discover` (its schema is {schema!r})")
    out = {"folder": str(folder), "blocks": blocks, "final_model": final}
    if label.split("+")[0] not in {str(m).split("+")[0] for m in models}:
        out["mismatch"] = f"The diagnosis screened {', '.join(map(str, models))}; this fit is of {label}."
    return out


def run_report(
    fit_dir,
    out,
    *,
    cohort=None,
    evaluation=None,
    diagnosis=None,
    n_draws: int = 50,
    start_stride: int = 10,
    seed: int = 0,
    progress: bool = False,
) -> Report:
    """Write the report of the fit in ``fit_dir`` into ``out``; returns its summary.

    ``cohort``: the fit's data, for the prediction figures and, without
    ``evaluation``, for J (loaded from the folder the fit records when None).
    ``evaluation``: a ``quadshank evaluate --fit`` folder to take J's bands from;
    otherwise J is computed here over ``n_draws`` posterior draws from every
    ``start_stride``-th start.  ``diagnosis``: a ``quadshank diagnose`` or
    ``discover`` folder whose ranking is shown.
    """

    if n_draws < 1:
        raise ValueError(f"--draws must be at least 1, not {n_draws}")
    if start_stride < 1:
        raise ValueError(f"--start-stride must be at least 1, not {start_stride}")
    t0 = time.perf_counter()
    fit_dir, out = Path(fit_dir), Path(out)
    fit = load_fits([fit_dir])[0]
    fs, desc, label = fit.summary, fit.desc, fit.label
    legs = list(desc["legs"])
    diag_info = _read_diagnosis(diagnosis, label) if diagnosis else None
    if cohort is None:
        if not fs.data:
            raise ValueError(f"{fit_dir}: the fit does not record its data; give the data (--data)")
        cohort = load_cohort(Path(fs.data))
    check_fit_legs([fit], cohort)
    evaluated = _j_from_evaluation(evaluation, label, legs, fs.fit_id) if evaluation else None
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").unlink(missing_ok=True)

    if evaluated:
        J, J_legs, j_how = evaluated
    else:
        draws = posterior_j([fit], cohort, n_draws=n_draws, start_stride=start_stride, seed=seed, progress=progress)
        Jc, Jl = summarise_j(draws)
        J, J_legs = Jc[label], Jl[label]
        used = min(n_draws, fit.idata.posterior.sizes["chain"] * fit.idata.posterior.sizes["draw"])
        j_how = (f"computed for this report over {used} posterior draws, one start in every {start_stride} samples "
                 f"(eq. 12 uses every start; `quadshank evaluate --fit` with --start-stride 1 for the full count)")
    params = leg_parameters(fit.idata, desc, fs.legs)
    spreads = population_spreads(fit.idata, desc)
    predictions = {leg: _leg_predictions(fit, cohort, leg, n_draws, seed) for leg in legs}
    written = write_report(out, fit_dir=fit_dir, fit_summary=fs, desc=desc, label=label, J=J, J_legs=J_legs,
                           j_how=j_how, params=params, spreads=spreads, predictions=predictions,
                           diagnosis=diag_info, progress=progress)
    summary = Report(
        fit=str(fit_dir), model=label, **written, J_source="evaluation" if evaluation else "computed", J_how=j_how,
        n_draws=n_draws, start_stride=start_stride, report_seconds=time.perf_counter() - t0,
        diagnosis=str(diagnosis) if diagnosis else None,
    )
    summary.write(out)
    return summary
