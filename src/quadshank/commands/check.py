"""``quadshank check``: what quadshank reads in a folder (or file) of recordings, before any fit.

A folder that does not read fails with every problem at once (the reader's error, naming file,
column and row).  One that reads gets a row per trial (length, period, what is excluded, the
pulses and how many are isolated twitches, the angle's range, which signals were measured and
which derived) and, per leg, what ``identify`` and ``fit`` can do with it; the reader's
plausibility warnings are kept with them.  With an output folder: ``recordings.csv`` and
``recordings.md``, a figure per trial (``recording_LEG_trialN.png``) and, last, ``summary.json``.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..common._io import file_stems, save_figure
from ..common._results import Result
from ..data._artefacts import stimulation_artefacts
from ..data._cohort import Cohort, Trial
from ..data._interchange import (DataWarning, angle_doubts, charge_scales, check_cohort, kept_warnings, load_cohort,
                                 pendulum_release, pulse_runs, signal_doubts, twitch_direction)
from ..data._paper import MAX_DELAY
from ..inference._identify import (
    DelayRangeError,
    MIN_PASSIVE_SAMPLES,
    MIN_TWITCHES,
    PASSIVE_MAX_ANGLE_DEG,
    check_delay_range,
    isolated_twitches,
    RADIAN_SPAN_DEG,
    angle_span,
    passive_mask,
    rest_offset,
    twitch_epoch,
)
from ..outputs._figures import plot_recording
from ..outputs._tables import write_table

__all__ = ["Check", "run_check", "check_table", "trial_row", "leg_uses", "TRIAL_COLUMNS"]

#: The columns of a trial's row (``recordings.csv``, :attr:`Check.trials`).
TRIAL_COLUMNS = (
    "leg", "trial", "source", "seconds", "sampling_period_ms", "samples", "excluded_share", "pulses",
    "isolated_twitches", "shortest_interval_ms", "stimulation", "angle_min_deg", "angle_max_deg",
    "acceleration", "velocity", "passive_samples",
)  # fmt: skip

#: What a trial's pulses are, as :func:`trial_row` names them.
NO_PULSES, ISOLATED, TRAINS, FEW = "no pulses (a pendulum test)", "isolated twitches", "trains", "few"


@dataclasses.dataclass
class Check(Result):
    """What ``quadshank check`` read: a row per trial (:data:`TRIAL_COLUMNS`), per leg what
    ``identify`` and ``fit`` can do with it, and the reader's warnings."""

    KIND: ClassVar[str] = "check"

    data: str  # the folder or file read
    sampling_period_s: float | None  # None: the trials are sampled at different periods
    identification_trial: int  # the trial ``identify`` would use (its --trial)
    trials: list  # rows of TRIAL_COLUMNS
    legs: dict  # leg -> {"identify": ..., "fit": ...}
    warnings: list  # the reader's plausibility warnings, one line each
    files: list = dataclasses.field(default_factory=list)  # written beside summary.json


def _kind(pulses: int, isolated: int) -> str:
    if pulses == 0:
        return NO_PULSES
    if isolated >= MIN_TWITCHES:
        return ISOLATED
    return FEW if isolated == pulses else TRAINS


def _isolated(trial: Trial) -> np.ndarray:
    """The trial's isolated twitches as the classical identification finds them (sample indices)."""
    return isolated_twitches(trial.stimulation, twitch_epoch(trial.sampling_period_s), exclude=trial.exclude)


def trial_row(trial: Trial, scale: dict | None = None, isolated: np.ndarray | None = None) -> dict:
    """One trial's row of :data:`TRIAL_COLUMNS` plus ``pulse_kind`` (:data:`NO_PULSES`,
    :data:`ISOLATED`, :data:`TRAINS` or :data:`FEW`).  ``scale``: the leg's charge scale
    (:func:`~quadshank.data.charge_scales`) where its levels are charges; ``isolated``: the
    trial's isolated twitches where already found."""
    dt = trial.sampling_period_s
    at = np.flatnonzero(trial.stimulation > 0)
    isolated = int((_isolated(trial) if isolated is None else isolated).size)
    kept = trial.angle_deg[~trial.exclude]
    if scale:
        largest = f"{scale.get('largest_charge', float('nan')):g} {scale.get('unit', '')}".strip()
        stim = f"charge over the leg's largest ({largest})"
    else:
        stim = "levels"
    return {
        "leg": trial.key,
        "trial": int(trial.trial),
        "source": Path(trial.source).name if trial.source else "",
        "seconds": round(trial.n_samples * dt, 6),
        "sampling_period_ms": round(dt * 1000.0, 6),
        "samples": int(trial.n_samples),
        "excluded_share": float(np.mean(trial.exclude)),
        "pulses": int(at.size),
        "isolated_twitches": isolated,
        "shortest_interval_ms": round(float(np.min(np.diff(at))) * dt * 1000.0, 6) if at.size > 1 else None,
        "stimulation": stim,
        "angle_min_deg": round(float(np.min(kept)), 3),
        "angle_max_deg": round(float(np.max(kept)), 3),
        "acceleration": "measured" if trial.acceleration_measured else "derived from the angle",
        "velocity": "measured" if trial.velocity_measured else "derived from the angle",
        "passive_samples": int(np.count_nonzero(passive_mask(trial))),
        "pulse_kind": _kind(int(at.size), isolated),
    }


def leg_uses(rows: list[dict], identification_trial: int = 1) -> dict:
    """What ``identify`` (on ``identification_trial``) and ``fit`` (on the same trial) can do with
    one leg, from its trials' rows (:func:`trial_row`): ``{"identify": ..., "fit": ...}``."""
    by_trial = {r["trial"]: r for r in rows}
    passive = [r["trial"] for r in rows if r["pulses"] == 0]
    row = by_trial.get(identification_trial)
    if row is None:
        text = f"no trial {identification_trial} (choose one of {', '.join(map(str, sorted(by_trial)))})"
        return {"identify": text, "fit": text}
    also = (f"; the passive system from trial(s) {', '.join(map(str, passive))} (no pulses)"
            if passive and row["pulses"] else "")
    # identify takes the passive system from the trials without pulses, else from the quiet samples of its trial
    source = [by_trial[k] for k in passive] if passive else [row]
    usable = sum(r["passive_samples"] for r in source)
    short = (f"no: {usable} samples for the passive system (quiet, at most "
             f"{PASSIVE_MAX_ANGLE_DEG:g}° extended, not excluded) in "
             f"trial{'s' if len(source) > 1 else ''} {', '.join(str(r['trial']) for r in source)}, of the "
             f"{MIN_PASSIVE_SAMPLES} needed") if usable < MIN_PASSIVE_SAMPLES else None
    if row["pulses"] == 0:
        identify = short or "the passive system only (no pulses: a pendulum test)"
        fit = "--model passive (no pulses: a model with a muscle would learn its muscle from its prior alone)"
    else:
        if short:
            identify = short
        elif row["isolated_twitches"] >= MIN_TWITCHES:
            identify = f"models 1-3 ({row['isolated_twitches']} isolated twitches){also}"
        else:
            identify = (f"no: {row['isolated_twitches']} isolated twitches of the {MIN_TWITCHES} needed "
                        "(`fit` compares every sample, trains too)")
        fit = "any model"
        if row["stimulation"] != "levels":  # charges, which the muscle does not follow linearly
            fit += "; the levels are charges: add the recruitment curve (--add-effect recruitment_sigmoid)"
    return {"identify": identify, "fit": fit}


def run_check(data, out=None, *, identification_trial: int = 1) -> Check:
    """Read ``data`` (a folder of recordings or a ``.nc`` file; or a :class:`~quadshank.data.Cohort`
    in memory) as every command does and say what was read (:class:`Check`); the reader's warnings
    (and a sampling period too short for the delays considered) are returned and issued again.
    ``out``: where to write ``recordings.csv`` and ``recordings.md``, a figure per trial and
    ``summary.json`` (None: nothing written)."""
    with kept_warnings() as said:
        if isinstance(data, Cohort):
            cohort, data = check_cohort(data), "a cohort in memory"
        else:
            cohort = load_cohort(data)
        try:
            period = cohort.sampling_period_s
        except ValueError as err:  # trials at different periods: shown, then refused by every other command
            period, mixed = None, str(err)
            warnings.warn(f"{mixed}; every other command refuses these data as they are", DataWarning, stacklevel=2)
        else:
            mixed = None
            # what fit and identify would warn of at this period (pendulum tests alone are modelled at any)
            check_delay_range(period, warn=any(np.any(t.stimulation > 0) for t in cohort))
        # (leg, trial) whose quiet samples swing about an angle away from 0, as identify warns where it takes
        # the passive system from them (a leg without pendulum tests, at a period it identifies)
        offset, poor, radians = set(), set(), set()
        doubts = {(t.key, t.trial): angle_doubts(t) for t in cohort}  # the reader's doubts of zero and sign
        pendulum = {t.key for t in cohort if not np.any(t.stimulation > 0)}
        try:
            identifies = period is not None and check_delay_range(period, muscle=True, warn=False) is None
        except DelayRangeError:
            identifies = False
        for t in cohort:
            if identifies and t.trial == identification_trial and t.key not in pendulum \
                    and np.any(t.stimulation > 0) and not doubts[t.key, t.trial]:
                span = angle_span((t,))
                if span < RADIAN_SPAN_DEG:  # both signals in radians agree with each other: the reader lets them by
                    radians.add((t.key, t.trial))
                    warnings.warn(f"{t.key}: the angle of trial {t.trial} spans only {span:.3g} over its samples, "
                                  "where a knee's swings span tens of degrees: are angle_deg (and the acceleration with "
                                  "it) in radians? Convert them to degrees", DataWarning, stacklevel=2)
                    continue
                found = rest_offset(t)
                if found:
                    (poor if found[1] else offset).add((t.key, t.trial))
                    warnings.warn(f"{t.key}: {found[0]}", DataWarning, stacklevel=2)
    scales = charge_scales(cohort)
    isolated = [_isolated(t) for t in cohort]
    rows = [trial_row(t, scales.get(t.key), i) for t, i in zip(cohort, isolated)]
    legs = {leg: leg_uses([r for r in rows if r["leg"] == leg], identification_trial) for leg in cohort.legs}
    for t in cohort:  # an identification trial whose twitches flex the knee: identify refuses it
        uses = legs[t.key]
        if t.trial == identification_trial and uses["identify"].startswith("models") and twitch_direction(t):
            uses["identify"] = uses["identify"].replace(
                "models 1-3", "no: its twitches flex the knee (is angle_deg positive in flexion?), and identify "
                "refuses twitches that do not extend it; with the sign turned, models 1-3", 1)
    for leg, uses in legs.items():  # an angle zeroed elsewhere: identify runs, and its values come out wrong
        trials = [t for t in cohort if t.key == leg]
        passive = [t for t in trials if not np.any(t.stimulation > 0)]
        used = [t for t in trials if t.trial == identification_trial] + [t for t in passive
                                                                           if t.trial != identification_trial]
        gated = [t.trial for t in trials if pulse_runs(t)]
        if gated:  # fit takes every nonzero sample of any trial for a pulse delivered there
            uses["fit"] += (f"; but the stimulation of trial{'s' if len(gated) > 1 else ''} "
                            f"{', '.join(map(str, gated))} is nonzero on consecutive samples, each of which a fit "
                            "takes for a pulse (the warnings say how)")
        if uses["identify"].startswith("no"):
            continue
        zeroed = {(leg, t.trial) for t in used if doubts[leg, t.trial]} | offset
        mismatched = {(leg, t.trial) for t in used if signal_doubts(t)}
        held = {(leg, t.trial) for t in used if pendulum_release(t)}
        jumping = {(leg, t.trial) for t in used if stimulation_artefacts(t)}
        runs = {(leg, t.trial) for t in used if t.trial in gated}
        for signal, what, which in (
                ("angle", "looks zeroed elsewhere or signed otherwise", zeroed), ("angle", "looks like radians", radians),
                ("angle", "has quiet samples the passive model describes poorly (activity between the twitches?)", poor),
                ("angle", "holds the lift and the hold before the pendulum's release", held),
                ("measured acceleration or velocity", "does not match the angle's derivatives", mismatched),
                ("recording", "jumps at the pulses' own samples (a stimulation artefact, or pulses logged late)",
                 jumping),
                ("stimulation", "is nonzero on consecutive samples, each of which is taken for a pulse", runs)):
            named = [t.trial for t in used if (leg, t.trial) in which]
            if named:
                uses["identify"] += (f"; but the {signal} of trial{'s' if len(named) > 1 else ''} "
                                     f"{', '.join(map(str, named))} {what} (the warnings say how): as recorded, its "
                                     "passive and active values come out wrong")
    if period is not None and any(r["pulses"] for r in rows):
        try:  # a period too short for a muscle's delays: identify and a muscle's fit refuse it
            check_delay_range(period, muscle=True, warn=False)
        except DelayRangeError:
            resample = (f"no: at {period * 1000:g} ms the delays considered reach {MAX_DELAY * period * 1000:g} ms, "
                        "short of a muscle's; resample first (`quadshank convert DATA data.nc --resample 0.01`)")
            legs = {leg: {"identify": resample, "fit": "--model passive only, until resampled"} for leg in legs}
    if mixed:
        refused = "no: the trials are sampled at different periods (resample them: `quadshank convert --resample`)"
        legs = {leg: {"identify": refused, "fit": refused} for leg in legs}
    result = Check(data=str(data), sampling_period_s=period,
                   identification_trial=int(identification_trial), trials=rows, legs=legs, warnings=said)
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        stems = file_stems(cohort.legs)  # a subject's name may hold '/' or be longer than a file name
        for t, r in zip(cohort, rows):  # which figure is whose, where two names meet in one file name
            r["figure"] = f"recording_{stems[t.key]}_trial{t.trial}.png"
        write_table(rows, out, "recordings", "The recordings as read")
        files = ["recordings.csv", "recordings.md"]
        for t, r, i in zip(cohort, rows, isolated):
            title = f"{r['pulses']} pulses, {r['isolated_twitches']} isolated twitches" if r["pulses"] else NO_PULSES
            save_figure(plot_recording(t, i, title), out / r["figure"])
            files.append(r["figure"])
        result.files = files
        result.write(out)
    return result


def check_table(result: Check) -> str:
    """The rows as a plain-text table for the console, then each leg's uses."""
    head = ("leg", "trial", "s", "ms", "excluded", "pulses", "isolated", "angle [deg]", "acceleration")
    body = [
        (r["leg"], str(r["trial"]), f"{r['seconds']:.1f}", f"{r['sampling_period_ms']:g}",
         f"{100 * r['excluded_share']:.1f} %", str(r["pulses"]), str(r["isolated_twitches"]),
         f"{r['angle_min_deg']:.1f} to {r['angle_max_deg']:.1f}",
         "measured" if r["acceleration"] == "measured" else "derived")
        for r in result.trials
    ]
    widths = [max(len(x) for x in col) for col in zip(head, *body)]
    lines = ["  ".join(x.ljust(w) for x, w in zip(line, widths)).rstrip() for line in (head, *body)]
    for leg, uses in result.legs.items():
        lines.append(f"{leg}: identify (trial {result.identification_trial}): {uses['identify']}; fit: {uses['fit']}")
    return "\n".join(lines)
