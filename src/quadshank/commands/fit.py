"""``quadshank fit``: a hierarchical NUTS fit of one model, written as ``fit.nc`` and ``summary.json``."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import jax

from ..data._cohort import Cohort
from ..inference._fitio import begin_fit, read_summary, save_fit, to_inference_data
from ..inference._nuts import FitSettings, delay_start, fit, fit_screen
from ..inference._priors import build_model, delay_prior_from


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
    (see :func:`quadshank.inference._priors.delay_prior_from`).
    """

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
