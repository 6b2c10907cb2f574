"""``quadshank fit``: a hierarchical NUTS fit of one model, written as ``fit.nc`` and ``summary.json``."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np

from ..data._cohort import Cohort, derived_signals
from ..data._interchange import DataWarning, charge_scales
from ..inference._fitio import (
    FitResult,
    begin_fit,
    from_json,
    read_summary,
    save_fit,
    to_inference_data,
)
from ..inference._identify import check_delay_range
from ..inference._nuts import FitSettings, run_nuts
from ..inference._priors import build_model, delay_prior_from
from ..model._effects import reads_sensor_only
from ..model._likelihood import chosen_legs, resolve_objective, twitch_window

#: A leg with fewer pulses than this in its fitted trials has active parameters its own data hardly
#: inform (the classical identification asks for 8 isolated twitches; one twitch pins nothing down).
FEW_PULSES = 8


def uninformed_legs(model, cohort: Cohort) -> dict:
    """Legs with fewer than :data:`FEW_PULSES` pulses whose twitch is compared (some sample of its
    window not excluded): per leg the pulses and the parameters of
    the muscle and the delay, whose values there come from the prior and the other legs (none for
    the ``passive`` model, which has no muscle)."""
    active = [p.name for e in model.effects if e.kind in ("activation", "gain", "pulse", "delay")
              for p in e.declared_params()]
    if model.activation.name == "no_muscle":
        return {}  # the pendulum alone: nothing active to inform
    out = {}
    for leg in cohort.legs:
        pulses, hidden = 0, 0
        for t in cohort.trials_of(leg):
            kept, window = ~t.exclude, twitch_window(t.sampling_period_s)
            seen = [bool(kept[k : k + window].any()) for k in np.flatnonzero(t.stimulation > 0)]
            pulses, hidden = pulses + sum(seen), hidden + len(seen) - sum(seen)
        if pulses < FEW_PULSES:
            why = "no pulses" if pulses == 0 else f"only {pulses} pulse{'s' if pulses > 1 else ''}"
            if hidden:  # pulses whose whole twitch is excluded inform nothing
                why += f" whose twitch is compared ({hidden} with their twitch excluded)"
            out[leg] = {"pulses": pulses, "params": active, "delay": True, "why": why}
    return out


def _warn_sensor_effects_without_sensor(model, cohort: Cohort, legs, trials) -> None:
    """Warn where ``model`` has an effect on what the accelerometer reads alone and no fitted trial
    (of ``legs``, numbered ``trials``) has one: its acceleration is derived from the angle, and the
    effect would fit the derivation's smoothing, not a sensor's response."""
    sensor = [e.name for e in model.effects if reads_sensor_only(e)]
    trials = [t for t in cohort.trials if (legs is None or t.key in legs) and t.trial in trials]
    if sensor and trials and not any(t.acceleration_measured for t in trials):
        warnings.warn(f"{', '.join(sensor)} changes only what an accelerometer reads, and these recordings have none "
                      "(their acceleration is derived from the angle): its parameters will describe the smoothing of "
                      "that derivation, not a sensor", DataWarning, stacklevel=3)


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
) -> FitResult:
    """Hierarchical NUTS fit of one model; writes DIR/fit.nc and DIR/summary.json, returns the
    :class:`~quadshank.inference.FitResult` that summary.json holds.

    ``data_source``: where the data came from, recorded as the summary's ``data`` (for
    ``quadshank diagnose`` and ``compare``).

    ``delay_from``: a fit folder whose delay posterior becomes this fit's delay prior
    (see :func:`quadshank.inference._priors.delay_prior_from`).
    """
    settings = settings or FitSettings()
    out = Path(out)
    m = build_model(model, add_effects, sampling_period_s=cohort.sampling_period_s)
    check_delay_range(cohort.sampling_period_s, muscle=m.activation.name != "no_muscle",
                      warn=m.activation.name != "no_muscle")  # the pendulum alone is modelled at any period
    objective = resolve_objective(m, settings.likelihood)  # refuse the angle for a muscle before anything is written
    chosen_legs(cohort, legs, settings.trials)  # and legs or trials the data lack
    if progress and objective == "angle" and m.activation.name != "no_muscle":
        print("fit: the likelihood on the angle runs a free run per delay through every sample for each gradient, "
              "about 15 times the acceleration's cost (docs/fit.md); bound the wait with --target-ess and --time-limit",
              file=sys.stderr, flush=True)
    _warn_sensor_effects_without_sensor(m, cohort, legs, settings.trials)
    log_prior = None
    if delay_from is not None:
        chosen = tuple(legs) if legs is not None else cohort.legs  # the legs fit() will use
        source = read_summary(delay_from)
        if abs(float(source.sampling_period_s) - cohort.sampling_period_s) > 1e-9 * cohort.sampling_period_s:
            raise ValueError(f"--delay-from {delay_from}: that fit ran at {source.sampling_period_s * 1000:g} ms and "
                             f"these data are at {cohort.sampling_period_s * 1000:g} ms; its delays are counted in "
                             "its samples, not these")
        log_prior = delay_prior_from(source.legs, chosen)
    out.mkdir(parents=True, exist_ok=True)
    begin_fit(out)
    run = run_nuts(cohort, m, settings, legs=legs, progress=progress, log_delay_prior=log_prior)
    extra = {}
    if run.delay_evidence_seconds is not None:
        extra["delay_evidence_seconds"] = run.delay_evidence_seconds
        extra["screen_restarted"] = {leg: {"from_delay": a, "to_delay": b} for leg, (a, b) in run.screen_restarted.items()}
    extra["sampling_seconds"] = run.sampling_seconds
    if run.target is not None:
        extra["target"] = run.target
    idata = to_inference_data(
        run.mcmc, m, run.data, settings, delay_source=None if delay_from is None else str(delay_from),
        log_delay_prior=log_prior, delay_evidence=run.delay_evidence,
    )
    if data_source is not None:
        extra["data"] = str(data_source)
    desc = from_json(idata.posterior.attrs["quadshank_model"])
    extra["data_fingerprint"] = cohort.fingerprint(desc["legs"], desc["trials"])
    fitted = cohort.select(desc["legs"], desc["trials"])
    derived = derived_signals(fitted)
    if derived:
        extra["derived_signals"] = derived
    scales = {leg: v for leg, v in charge_scales(cohort).items() if leg in desc["legs"]}
    if scales:
        extra["charge_scale"] = scales  # what a plan in the same columns needs (predict)
    uninformed = uninformed_legs(m, fitted)
    if uninformed:
        extra["uninformed"] = uninformed
    return save_fit(idata, out, extra=extra, overwrite=True)  # the command line's output rules chose the folder
