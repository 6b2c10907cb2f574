"""Interchange folders: a cohort as plain CSV files, read with full validation.

The interchange format is what a laboratory exports by hand or from any tool;
the NetCDF file of :class:`~quadshank.data._cohort.Cohort` is the native form.
:func:`read_interchange` checks a folder completely and reports *every* problem
it finds, each with file, column and line, before anything is loaded;
:func:`write_interchange` writes a folder that reads back bit-identically;
:func:`load_cohort` and :func:`convert` accept either form.

Interchange folder format
=========================

A folder holding ``manifest.csv`` and one CSV file per trial (UTF-8, or UTF-16
with its byte-order mark; comma separated, first line a header; a UTF-8
byte-order mark, blank lines, rows of empty cells and a separator after the
last field of a line are tolerated; the row numbers quoted in error messages
are line numbers as an editor shows them, the header being line 1).

``manifest.csv`` — one row per trial:

| column              | content                                                     |
|---------------------|-------------------------------------------------------------|
| `subject`           | subject identifier, non-empty (e.g. `TN`)                   |
| `leg`               | `left` or `right`                                           |
| `trial`             | trial number, a positive integer; per leg numbered 1..n     |
| `file`              | path of the trial's CSV, relative to the folder (`/`-separated) |
| `sampling_period_s` | optional column; sampling period in s, > 0, ≤ 0.1 (default 0.01) |
| `start_s`, `end_s`  | optional columns; keep only the samples with start_s <= time_s <= end_s (an empty cell: no bound), to leave out a release, a spasm or an artefact at either end |

Trial CSV — one row per sample, columns in any order, names exact:

| column                | content                                                    |
|-----------------------|------------------------------------------------------------|
| `time_s`              | time [s], uniformly sampled, strictly increasing           |
| `angle_deg`           | knee angle [deg]; 0 = shank at rest, positive = extension  |
| `acceleration_deg_s2` | optional: angular acceleration [deg/s²] (from an accelerometer) |
| `stimulation`         | recruitment level u in [0, 1] of the pulse delivered at that sample, 0 when none |
| `velocity_deg_s`      | optional: measured angular velocity [deg/s]                |
| `exclude`             | optional: 1 where the sample is left out of every comparison with the model (a release, a spasm, a sensor artefact), else 0 |
| `pulse_width_us`, `current_mA` | instead of `stimulation`, a stimulator's log: the pulse width [µs] and/or current [mA] of the pulse delivered at that sample, 0 when none |

A trial given as `pulse_width_us` and/or `current_mA` gets as its ``stimulation``
each pulse's charge (their product; one alone stands for itself) over the largest
charge of the leg across its trials so given: the relative charge in (0, 1], which
a recruitment curve (the ``recruitment_sigmoid`` effect) maps to the share of the
muscle recruited.  Written back, the relative charge is the ``stimulation`` column.

When `velocity_deg_s` is absent the velocity is derived from the angle
(:func:`~quadshank.data._cohort.derive_velocity`) and the trial is marked
``velocity_measured = False``; when `acceleration_deg_s2` is absent (no
accelerometer) the acceleration is derived from the angle
(:func:`~quadshank.data._cohort.derive_acceleration`) and the trial is marked
``acceleration_measured = False``.  A derived signal is not written back.

Validation rules
----------------

All files are checked and all problems are collected; if there is any, an
:class:`InterchangeError` listing them is raised and nothing is loaded.

1. **Manifest**: `manifest.csv` exists; required columns present, no unknown
   column; `trial` a positive integer; `leg` is `left` or `right`; `subject`
   non-empty, without control characters (a line break in a name would break
   every table it is written to); `sampling_period_s` a finite number > 0 and at
   most 0.1 s.
2. **Listing**: no (subject, leg, trial) twice; no file listed twice; every
   listed file exists (inside the folder); per leg the trials are numbered
   1..n without gaps; every CSV file in the folder (recursively; hidden files
   and folders excepted) is listed in the manifest.
3. **Trial CSV structure**: UTF-8 text (the first byte that is not is named
   with its row); required columns present, no unknown or duplicated column;
   at least two data rows; every row has as many fields as the header; every
   cell a finite number (`nan`, `inf` are rejected).
4. **Time**: strictly increasing; uniform (each step within 1 % of the median
   step); the median step equals the manifest's `sampling_period_s` within a
   relative 1e-3.
5. **Stimulation** within [0, 1], or a stimulator's `pulse_width_us` /
   `current_mA` (not both kinds), not negative; **exclude** 0 or 1, and at
   least two samples of a trial not excluded.
6. **Units**: an angle whose samples lie within ±pi (3.2), the 1 % at each end
   left out (glitches), while the angle moves (by more than 0.05 in a trial
   with pulses, 0.5 in one without) is taken to be in radians and rejected
   (trials of at least 100 samples: a few samples say nothing of the units),
   unless, in a trial with pulses, a measured acceleration follows the angle's
   second derivative at about its size (then both are in degrees: weak
   twitches).
7. **Numbers** are ASCII decimals with an optional sign, decimal point and
   exponent (``1_000``, other digits, ``nan`` and ``inf`` are rejected).
8. **Links**: a listed file (or the manifest) that resolves to a place outside
   the folder is rejected.

A NetCDF file goes through the same rules (:func:`read_netcdf`): its problems
name the trial (``cohort.nc [TN-left trial 2]``), the signal and the sample.

Writing uses ``repr`` of every float (shortest exact form), so a cohort read,
written and read again is bit-identical.  Cohort attributes other than the
trials' own fields are not stored in an interchange folder.
"""

from __future__ import annotations

import codecs
import contextlib
import csv
import dataclasses
import difflib
import hashlib
import json
import math
import os
import re
import unicodedata
import warnings
from collections.abc import Iterable, Sequence
from pathlib import Path, PurePosixPath

import numpy as np
from scipy.signal import medfilt, savgol_filter

from ..common._arrays import is_whole_number, stretches
from ..common._io import file_stem, temp_sibling
from ._cohort import (ANGLE_LIMIT_DEG, MAX_SAMPLING_PERIOD_S, MISSING_MARKERS, Cohort, DataWarning, Trial,
                      derive_acceleration, fingerprint_problem, is_checked, leg_key, mark_checked, quiet_mask,
                      seconds_text)
from ._artefacts import artefact_texts, repair_stimulation_artefacts, stimulation_artefacts
from ._paper import TWITCH_REACH_S
from ._resample import resample_cohort, resample_trial

__all__ = [
    "trim",
    "read_stimulation_plan",
    "read_plan",
    "StimulationPlan",
    "charge_scales",
    "DataWarning",
    "plausibility",
    "Problem",
    "InterchangeError",
    "read_interchange",
    "write_interchange",
    "load_cohort",
    "read_netcdf",
    "parse_number",
    "convert",
    "MANIFEST_NAME",
    "DEFAULT_SAMPLING_PERIOD_S",
]

#: File name of the manifest inside an interchange folder.
MANIFEST_NAME = "manifest.csv"
#: Sampling period assumed when the manifest has no ``sampling_period_s`` column.
DEFAULT_SAMPLING_PERIOD_S = 0.01

_MANIFEST_REQUIRED = ("subject", "leg", "trial", "file")
_MANIFEST_OPTIONAL = ("sampling_period_s", "start_s", "end_s")
_TRIAL_REQUIRED = ("time_s", "angle_deg")
#: A trial without ``stimulation`` (nor a stimulator's columns) is a pendulum test: no pulses.
_TRIAL_OPTIONAL = ("stimulation", "acceleration_deg_s2", "velocity_deg_s", "exclude", "pulse_width_us", "current_mA")
#: Columns of a stimulator's log that may stand in for `stimulation`: the charge of each pulse.
_STIMULATOR = ("pulse_width_us", "current_mA")
#: Column order used when writing a trial file.
_TRIAL_WRITE_ORDER = ("time_s", "angle_deg", "velocity_deg_s", "acceleration_deg_s2", "stimulation", "exclude")
_LEGS = ("left", "right")

#: A step may differ from the median step by this fraction before the grid counts as non-uniform.
UNIFORM_TOLERANCE = 0.01
#: Relative tolerance between the median time step and the manifest's sampling period.
PERIOD_TOLERANCE = 1e-3
#: An angle whose magnitude never exceeds this (pi, rounded up) is suspected to be in radians.
RADIAN_LIMIT = 3.2
#: ... provided it moves by more than this (between the quantiles below) in a stimulated trial,
RADIAN_MIN_RANGE = 0.05
#: ... or by more than this in a trial without pulses (a pendulum test in degrees swings far beyond pi).
RADIAN_MIN_RANGE_PASSIVE = 0.5
#: The fraction of samples left out at each end before the radian test (glitches).
RADIAN_QUANTILE = 0.01
#: The radian test needs this many samples: a few samples of a trial say nothing of its units.
RADIAN_MIN_SAMPLES = 100

#: Largest magnitude a sample not excluded may hold, per column: a knee turns less than twice
#: round, swings at up to a few thousand deg/s and accelerates at up to a few 10⁴ deg/s².
#: Beyond these a value is no measurement of a knee in degrees: a logger's missing-data marker
#: (-9999), another unit (millidegrees), an overflow.
MAGNITUDE_LIMITS = {"angle_deg": ANGLE_LIMIT_DEG, "velocity_deg_s": 1.0e5, "acceleration_deg_s2": 5.0e5}

#: Individual problems reported per file, column and kind before they are summarised.
_MAX_PER_KIND = 5
#: Problems listed by ``str(InterchangeError)``.
_MAX_LISTED = 50


# --------------------------------------------------------------------------- errors
@dataclasses.dataclass(frozen=True)
class Problem:
    """One problem found in an interchange folder.

    ``file`` is the path relative to the folder, ``column`` the column name
    (``None`` for a whole-row or whole-file problem), ``row`` the 1-based line
    number as an editor shows it (the header is line 1; ``None`` for a
    whole-file problem).
    """

    file: str
    column: str | None
    row: int | None
    message: str
    row_label: str = "row"  # "sample" in a NetCDF file
    count: int = 1  # the problems this one stands for ("25 more rows like this": 25)

    def __str__(self) -> str:
        where = [self.file]
        if self.column is not None:
            where.append(f"column {self.column!r}")
        if self.row is not None:
            where.append(f"{self.row_label} {self.row}")
        return f"{', '.join(where)}: {self.message}"


class InterchangeError(ValueError):
    """An interchange folder (or a cohort to be written as one) is invalid.

    ``problems`` lists every problem found.  ``str()`` puts the first on the first line
    (file, column and row, then the message) and the others one per line below it.
    """

    def __init__(self, problems: Iterable[Problem], context: str = "invalid interchange folder") -> None:
        self.problems: list[Problem] = list(problems)
        self.context = context
        super().__init__(self.problems, context)

    def __str__(self) -> str:
        n = len(self.problems)
        if n == 0:
            return self.context
        first = f"{self.context}: {self.problems[0]}"
        if n == 1:
            return first
        more = sum(p.count for p in self.problems[1:])
        lines = [f"{first} (and {more} more problem{'s' if more > 1 else ''}, listed below)"]
        lines += [f"  {p}" for p in self.problems[1:_MAX_LISTED]]
        if n > _MAX_LISTED:
            lines.append(f"  ... and {sum(p.count for p in self.problems[_MAX_LISTED:])} more")
        return "\n".join(lines)


def _report_cells(
    problems: list[Problem], file: str, column: str, hits: Sequence[tuple[int, str]], what: str
) -> None:
    """Report offending cells individually, then summarise the rest of the same kind."""
    for line, text in hits[:_MAX_PER_KIND]:
        problems.append(Problem(file, column, line, what.format(text)))
    rest = hits[_MAX_PER_KIND:]
    if rest:
        problems.append(
            Problem(file, column, None, f"{len(rest)} more rows like this (rows {rest[0][0]} to {rest[-1][0]})",
                    count=len(rest))
        )


# --------------------------------------------------------------------------- plausibility
@contextlib.contextmanager
def kept_warnings():
    """Record the warnings issued inside (every :class:`DataWarning`, even one said before) and issue
    them again on leaving, failure or not; yields the list the DataWarnings' texts are put in, for
    a command's report and summary."""
    said: list[str] = []
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", DataWarning)
            yield said
    finally:
        for w in caught:
            if issubclass(w.category, DataWarning):
                said.append(str(w.message))
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


#: Length [s] of the Savitzky–Golay window that smooths the derivatives compared below.
PLAUSIBILITY_WINDOW_S = 0.1
#: A measured derivative whose ratio to the angle's own lies outside this range gets a warning.
PLAUSIBLE_RATIO = (0.5, 2.0)
#: Correlations (measured derivative against the angle's) below which a warning says they disagree.
PLAUSIBLE_CORRELATION = 0.5
#: A measured derivative whose size ratio to the angle's own lies outside this range, though
#: within :data:`PLAUSIBLE_RATIO`, gets a warning of a scale off (an accelerometer's distance from
#: the knee or its gain): the ratio is 0.99-1.03 on the simulated cohort at 1-20 ms (an
#: accelerometer that rings included), its pendulum tests and the other simulator's, and a scale off
#: by 20 % scales D', G' and G'2 with it.
SCALE_RATIO = (0.9, 1.1)
#: A measured derivative that lags (or leads) the angle's own by more than this [s] gets a warning:
#: within 0.5 ms on the simulated cohort at 1-20 ms, its pendulum tests and the other simulator's
#: recordings; an accelerometer's amplifier filtering at 15 Hz lags by 10-12 ms and makes D' 35-44 %
#: too small, and an angle sensor filtering at 10 Hz leads it by 14-16 ms.
PLAUSIBLE_LAG_S = 0.005
#: A measured acceleration of a trial with pulses holding more than this [deg/s²] times sin φ
#: besides the angle's second derivative senses gravity's projection (about g/r, 1900 deg/s² at
#: 30 cm from the knee, which doubles G' or takes it to 0); within ±160 on the simulated cohort at
#: 1-20 ms (an accelerometer that rings included), ±190 on the other simulator's.  A pendulum
#: test's acceleration is itself nearly G'·sin φ, and is not judged so.
GRAVITY_SHARE_DEG_S2 = 500.0
#: A trial without pulses whose last second moves less than this [deg] has come to rest ...
STILL_RANGE_DEG = 2.0
#: ... and one resting further than this [deg] from angle 0 (the shank at rest) gets a warning.
REST_TOLERANCE_DEG = 5.0
#: A trial without pulses that starts this far [deg] into flexion gets a warning about the sign.
RELEASE_FLEXION_DEG = 20.0
#: A trial without pulses whose shank stays within this share of its largest swing (and at least
#: :data:`RELEASE_HOLD_MIN_DEG`) of its extreme angle for :data:`RELEASE_HOLD_S` or more before
#: leaving it was held there by hand: a pendulum test recorded from before its release ...
RELEASE_HOLD_SHARE = 0.03
RELEASE_HOLD_MIN_DEG = 1.0
#: ... (a free swing turns at its extreme far faster: a 60° swing at 0.9 Hz stays within 3 % of it
#: for 0.1 s, and a 10° swing stays within 2° for 0.5 s only below 0.4 Hz, where a shank swings at
#: 0.6-1.2 Hz) ...
RELEASE_HOLD_S = 0.5
#: ... whose largest swing is at least this [deg] from where it comes to rest.
RELEASE_SWING_DEG = 10.0


#: An angle that jumps away and back within one sample faster than this [deg/s] is taken for a
#: sensor glitch.  A knee swings at a few hundred and kicks at about 1500, but it does not turn back
#: within a sample: away and back at 1000 deg/s each is an acceleration of over 10^5 deg/s² at
#: 10 ms, a hundred times a twitch's (a 25° spike at 10 ms, 2500 deg/s, took a pendulum's G' to 0).
GLITCH_SPEED_DEG_S = 1000.0


def plausibility(trial: Trial) -> list[str]:
    """What looks implausible in a trial that passed the rules, in words (empty when nothing does).

    The measured acceleration (and a measured velocity) should follow the angle's own second
    (first) derivative, both smoothed alike: the same sign and about the same size.  A ratio
    near 57 or 1/57 says radians somewhere, a negative correlation a flipped sign, a ratio of
    0.01 or 100 another unit or scale.
    """
    dt = trial.sampling_period_s
    if trial.n_samples > 1 and np.ptp(trial.angle_deg) == 0:
        return [f"angle_deg is constant ({float(trial.angle_deg[0])!r}° throughout): no movement was recorded"]
    glitches = _glitches(trial)
    window = _smoothing_window(dt)
    if trial.n_samples < 3 * window:
        return glitches
    stimulated = bool(np.any(trial.stimulation > 0))
    artefacts = stimulation_artefacts(trial) if stimulated else {}
    found = glitches + _markers(trial) + _faint_pulses(trial) + pulse_runs(trial) \
        + (_rest_plausibility(trial) + twitch_direction(trial) + _unmoved_pulses(trial)
           + artefact_texts(trial, artefacts) + _excluded_twitches(trial) if stimulated
           else _pendulum_plausibility(trial))
    kept = ~trial.exclude  # an excluded artefact is not evidence of a wrong unit or sign
    if np.count_nonzero(kept) < 3 * window:
        return found
    return found + _rails(trial, kept) + signal_doubts(trial, artefacts)


def signal_doubts(trial: Trial, artefacts: dict | None = None) -> list[str]:
    """What :func:`plausibility` says of ``trial``'s measured acceleration and velocity against the
    angle's own derivatives (a placeholder, a sign, a unit, another signal), in words; empty where
    they agree or were derived.  ``check`` qualifies what identify can do with such a trial by them.
    ``artefacts``: the trial's :func:`~quadshank.data._artefacts.stimulation_artefacts`, where already
    found (a signal one holds is not compared)."""
    dt = trial.sampling_period_s
    window = _smoothing_window(dt)
    kept = ~trial.exclude  # an excluded artefact is not evidence of a wrong unit or sign
    if trial.n_samples < 3 * window or np.count_nonzero(kept) < 3 * window or np.ptp(trial.angle_deg) == 0:
        return []
    checks = [("acceleration_deg_s2", 2, "deg/s²")] if trial.acceleration_measured else []
    if trial.velocity_measured:
        checks.append(("velocity_deg_s", 1, "deg/s"))
    found = []
    # a logger's placeholder for a signal it did not record: named, and not compared with the angle
    constant = [c for c in checks if np.ptp(getattr(trial, c[0])[kept]) == 0]
    for column, _, _ in constant:
        found.append(f"{column} is constant ({float(getattr(trial, column)[kept][0])!r} throughout) while the angle "
                     "moves: a placeholder for a signal that was not recorded? Leave the column out and the reader "
                     "derives it from the angle")
    checks = [c for c in checks if c not in constant]
    if artefacts is None:
        artefacts = stimulation_artefacts(trial) if np.any(trial.stimulation > 0) else {}
    for column, order, unit in checks:
        if column in artefacts or "angle_deg" in artefacts:  # named as an artefact: says nothing of units or signs
            continue
        agreement = _agreement(trial.angle_deg, getattr(trial, column), order, dt, kept)
        if agreement is None:
            continue
        corr, ratio = agreement
        what = "second derivative" if order == 2 else "derivative"
        if order == 2 and corr > 0 and np.any(trial.stimulation > 0) \
                and abs(share := _gravity_share(trial, kept) or 0.0) > GRAVITY_SHARE_DEG_S2:
            found.append(f"{column} holds about {share:+.3g}·sin(angle) deg/s² besides the angle's {what}: an "
                         "accelerometer that senses gravity's projection as well as the shank's turning (a single "
                         "accelerometer on the shank does)? Subtract it (or record as the paper did, with two "
                         "accelerometers); left in, it adds to or cancels G'")
            continue
        if corr > PLAUSIBLE_CORRELATION and PLAUSIBLE_RATIO[0] <= ratio <= PLAUSIBLE_RATIO[1]:
            lag = _lag_s(trial.angle_deg, getattr(trial, column), order, dt, kept)
            if lag is not None and abs(lag) > PLAUSIBLE_LAG_S:
                found.append(
                    f"{column} {'lags' if lag > 0 else 'leads'} the angle's {what} by {abs(lag) * 1000:.3g} ms: "
                    + ("a filter in its amplifier, or the channels logged at different instants? " if lag > 0 else
                       "a filtered or slow angle sensor, or the channels logged at different instants? ")
                    + "Left so, the damping and the velocity's effects come out wrong")
            elif not SCALE_RATIO[0] <= ratio <= SCALE_RATIO[1]:
                found.append(f"{column} is {ratio:.3g} times the size of the angle's {what}: is its scale off (an "
                             "accelerometer's distance from the knee, a gain)? The passive and active values come "
                             "out scaled with it" if order == 2 else
                             f"{column} is {ratio:.3g} times the size of the angle's {what}: is its scale off?")
            continue
        if corr < -PLAUSIBLE_CORRELATION:
            found.append(f"{column} runs against the angle's {what} (correlation {corr:.2f}): is the sign of one "
                         "of them flipped? (positive angle = extension)")
        elif corr > PLAUSIBLE_CORRELATION and not PLAUSIBLE_RATIO[0] <= ratio <= PLAUSIBLE_RATIO[1]:
            hint = (" (about 180/pi: radians somewhere?)" if 40 <= ratio <= 80 else
                    " (about pi/180: radians somewhere?)" if 1 / 80 <= ratio <= 1 / 40 else "")
            found.append(f"{column} is {ratio:.3g} times the size of the angle's {what}{hint}; in {unit} and deg "
                         "they agree: check the units")
        elif abs(corr) < PLAUSIBLE_CORRELATION:
            found.append(f"{column} hardly follows the angle's {what} (correlation {corr:.2f}): is it the "
                         "signal of this trial, in this column?")
    return found


#: Consecutive samples of one marker that make a run (a single one may be a measurement).
MARKER_RUN = 3

#: Share of a trial's samples at exactly its largest (or smallest) angle, in runs of at least
#: :data:`MARKER_RUN` samples and further than :data:`REST_TOLERANCE_DEG` from the median angle,
#: from which that angle is taken for a sensor's or amplifier's rail:
#: a swing passes its extreme in a sample or two, and a noisy or finely quantised angle seldom
#: repeats it.
RAIL_SHARE = 0.02


def _rails(trial: Trial, kept: np.ndarray) -> list[str]:
    """Angles held at the trial's extreme value, as a saturated sensor clips them, in words."""
    angle = trial.angle_deg
    rest = float(np.median(angle[kept]))
    found = []
    for side, extreme in (("largest", float(np.max(angle[kept]))), ("smallest", float(np.min(angle[kept])))):
        if abs(extreme - rest) <= REST_TOLERANCE_DEG:  # a knee at rest between twitches, not a rail
            continue
        runs = [(a, b) for a, b in stretches((angle == extreme) & kept) if b - a >= MARKER_RUN]
        n = sum(b - a for a, b in runs)
        if len(runs) >= 2 and n >= RAIL_SHARE * np.count_nonzero(kept):
            found.append(f"angle_deg sits at its {side} value, {extreme!r}°, on {n} samples in {len(runs)} runs "
                         f"(the first from time_s = {seconds_text(trial.time_s[runs[0][0]])}): a saturated sensor or "
                         "amplifier? The model takes a clipped angle for the knee's; set exclude = 1 there")
    return found


def _markers(trial: Trial) -> list[str]:
    """Runs of :data:`~quadshank.data._cohort.MISSING_MARKERS` in the measured signals (samples not excluded), in words."""
    columns = [("angle_deg", trial.angle_deg)]
    columns += [("velocity_deg_s", trial.velocity_deg_s)] if trial.velocity_measured else []
    columns += [("acceleration_deg_s2", trial.acceleration_deg_s2)] if trial.acceleration_measured else []
    found = []
    for column, values in columns:
        for marker in MISSING_MARKERS:
            runs = [(a, b) for a, b in stretches((values == marker) & ~trial.exclude) if b - a >= MARKER_RUN]
            if runs:
                n = sum(b - a for a, b in runs)
                found.append(f"{column} holds {marker:g} on {n} samples in {len(runs)} run{'s' if len(runs) > 1 else ''}, "
                             f"the first from time_s = {seconds_text(trial.time_s[runs[0][0]])}: a logger's missing-data "
                             "marker? Set exclude = 1 there (the fit then leaves those samples out)")
    return found


#: The bulk of a trial's angles (:data:`RADIAN_QUANTILE` to 1 − it) spanning more than this [deg] is
#: no knee's in degrees, whose range of motion is under 180°: the column is in another unit.
ANGLE_SPAN_LIMIT_DEG = 360.0

#: A pulse level below this is no recruitment a stimulator delivers: float noise where it delivered none.
FAINT_PULSE = 1e-6

#: Pulses on this many consecutive samples or more ...
PULSE_RUN = 5
#: ... at this rate [Hz] or faster (FES trains run at 20–50 Hz, rarely above 100 Hz) make a run
#: that reads as a gate or a setting logged on every sample rather than the pulses delivered.
PULSE_RUN_RATE_HZ = 100.0


def _faint_pulses(trial: Trial) -> list[str]:
    """Pulses whose level is below :data:`FAINT_PULSE`, in words (each nonzero level is a pulse)."""
    faint = np.flatnonzero((trial.stimulation > 0) & (trial.stimulation < FAINT_PULSE))
    if not faint.size:
        return []
    return [f"stimulation holds {faint.size} level{'s' if faint.size > 1 else ''} above 0 and below {FAINT_PULSE:g}, "
            f"the first at time_s = {seconds_text(trial.time_s[faint[0]])}: each nonzero level is a pulse; float noise "
            "where no pulse was delivered? Write 0 there"]


def pulse_runs(trial: Trial) -> list[str]:
    """Pulses on consecutive samples at :data:`PULSE_RUN_RATE_HZ` or faster, or on every sample of the
    trial, in words: each nonzero level is one pulse delivered at that sample, so a stimulation
    column that is nonzero over a pulse's width (a trigger), throughout a train (a gate) or on
    every row (a setting) says pulses that were never delivered.  Empty where none are found;
    identify names them where they leave too few isolated twitches."""
    on = trial.stimulation > 0
    if on.size < PULSE_RUN:
        return []
    together = [(a, b) for a, b in stretches(on) if b - a >= 2]
    runs = [(a, b) for a, b in together if b - a >= PULSE_RUN]
    rate = 1.0 / trial.sampling_period_s
    short = [(a, b) for a, b in together if b - a < PULSE_RUN]
    in_short = sum(b - a for a, b in short)
    if not on.all() and rate >= PULSE_RUN_RATE_HZ and len(short) >= 3 and len(short) > 2 * len(runs) \
            and in_short >= 0.5 * np.count_nonzero(on):  # a longer run or two: pulses that touched
        widths = sorted({b - a for a, b in short})
        a = short[0][0]
        return [f"stimulation is nonzero on {len(short)} runs of {' or '.join(map(str, widths))} consecutive samples "
                f"({in_short} of its {np.count_nonzero(on)} pulses), the first from time_s = {seconds_text(trial.time_s[a])}: "
                f"each nonzero sample is one pulse delivered at that sample, so each run reads as pulses at "
                f"{rate:g} Hz. Is it a trigger recorded over the pulse's width? Then keep each run's first sample (the "
                "rising edge) and write 0 on the others. Pulses delivered that close (doublets) are told apart only "
                "at a shorter sampling period"]
    if on.all():
        what = f"every one of its {on.size} samples"
    elif runs and rate >= PULSE_RUN_RATE_HZ:
        a, b = max(runs, key=lambda r: r[1] - r[0])
        what = (f"{len(runs)} run{'s' if len(runs) > 1 else ''} of consecutive samples, the longest {b - a} samples "
                f"from time_s = {seconds_text(trial.time_s[a])} (pulses at {rate:g} Hz)")
    else:
        return []
    return [f"stimulation is nonzero on {what}: each nonzero sample is one pulse delivered at that sample. Is the "
            "column a gate (on while a train runs) or a stimulator setting logged on every row? Give a level only at "
            "the samples where a pulse was delivered, 0 elsewhere"]


#: A trial where at least this share of its pulses (and 10 or more) has an excluded sample among the
#: samples its twitch may reach is named: each of those twitches is left out.
EXCLUDED_TWITCH_SHARE = 0.5


def _excluded_twitches(trial: Trial) -> list[str]:
    """Pulses whose twitch reaches an excluded sample (within :data:`~quadshank.data._paper.TWITCH_REACH_S`),
    in words, where they are most of them (:data:`EXCLUDED_TWITCH_SHARE`): the classical
    identification drops such a twitch and the fit its windows, so that excluding a stimulation
    artefact at every pulse leaves no twitch at all."""
    pulses = trial.pulse_indices
    if pulses.size < 10 or not trial.exclude.any():
        return []
    reach = max(1, int(round(TWITCH_REACH_S / trial.sampling_period_s)))
    before = np.concatenate([[0], np.cumsum(trial.exclude, dtype=np.int64)])
    hit = before[np.minimum(pulses + reach, trial.n_samples)] - before[pulses] > 0
    if np.count_nonzero(hit) < EXCLUDED_TWITCH_SHARE * pulses.size:
        return []
    at_pulse = np.count_nonzero(trial.exclude[pulses] | trial.exclude[np.minimum(pulses + 1, trial.n_samples - 1)])
    return [f"{np.count_nonzero(hit)} of the {pulses.size} pulses have an excluded sample within the "
            f"{TWITCH_REACH_S * 1000:g} ms their twitch may reach, and each such twitch is left out (of the classical "
            "identification and of the fit's windows)"
            + (f"; {at_pulse} have it on their own sample or the next: a stimulation artefact excluded? Repair it "
               "instead (`quadshank convert DATA repaired.nc --repair-artefacts`, after setting exclude back to 0 "
               "there)" if at_pulse >= EXCLUDED_TWITCH_SHARE * pulses.size else "")]


def _glitch_indices(trial: Trial) -> np.ndarray:
    """Samples not excluded where the angle jumps away and back within one sample, faster than
    :data:`GLITCH_SPEED_DEG_S` both ways: a sensor glitch."""
    a = trial.angle_deg
    if a.size < 3:
        return np.zeros(0, int)
    jump = GLITCH_SPEED_DEG_S * trial.sampling_period_s
    out, back = a[1:-1] - a[:-2], a[2:] - a[1:-1]
    spike = (np.abs(out) > jump) & (np.abs(back) > jump) & (np.sign(out) != np.sign(back)) \
        & (np.abs(a[2:] - a[:-2]) < 0.5 * np.minimum(np.abs(out), np.abs(back)))
    at = np.flatnonzero(spike) + 1
    return at[~trial.exclude[at]]


def _exclude_glitches(trial: Trial, label: str) -> Trial:
    """``trial`` with its glitches (:func:`_glitch_indices`) excluded, and the velocity and
    acceleration derived from the angle derived again (across them by a straight line), with a
    warning that says so; a trial without one as it is."""
    at = _glitch_indices(trial)
    # on a pulse's sample or the next one a stimulation artefact's: repaired rather than excluded, since
    # an excluded sample in a twitch's window leaves the twitch out (repair_stimulation_artefacts)
    at = at[~np.isin(at, np.concatenate([trial.pulse_indices, trial.pulse_indices + 1]))]
    if not at.size:
        return trial
    exclude = trial.exclude.copy()
    exclude[at] = True
    i = int(at[0])
    more = f" and {at.size - 1} more such sample{'s' if at.size > 2 else ''}" if at.size > 1 else ""
    warnings.warn(f"{label} ({trial.key} trial {trial.trial}): angle_deg jumps by "
                  f"{float(trial.angle_deg[i] - trial.angle_deg[i - 1]):+.4g}° and back at time_s = "
                  f"{seconds_text(trial.time_s[i])}{more}, faster than a knee moves (over {GLITCH_SPEED_DEG_S:g} "
                  "deg/s): a sensor glitch, excluded (a velocity or acceleration derived from the angle is derived "
                  "across it by a straight line). Correct it in the file to keep the sample", DataWarning,
                  stacklevel=4)
    return Trial.from_signals(
        trial.subject, trial.leg, trial.trial, trial.sampling_period_s, angle_deg=trial.angle_deg,
        acceleration_deg_s2=trial.acceleration_deg_s2 if trial.acceleration_measured else None,
        stimulation=trial.stimulation, velocity_deg_s=trial.velocity_deg_s if trial.velocity_measured else None,
        time_s=trial.time_s, source=trial.source, exclude=exclude)


def _glitches(trial: Trial) -> list[str]:
    """:func:`_glitch_indices` in words: the first, and how many."""
    a = trial.angle_deg
    at = _glitch_indices(trial)
    if not at.size:
        return []
    i = int(at[0])
    more = f" and {at.size - 1} more such sample{'s' if at.size > 2 else ''}" if at.size > 1 else ""
    return [f"angle_deg jumps by {float(a[i] - a[i - 1]):+.4g}° and back at time_s = {seconds_text(trial.time_s[i])}{more}, "
            f"faster than a knee moves (over {GLITCH_SPEED_DEG_S:g} deg/s): a sensor glitch? Correct it, or set "
            "exclude = 1 there (the fit then leaves the sample out)"]


def _pendulum_plausibility(trial: Trial, release: bool = True) -> list[str]:
    """A trial without pulses (a pendulum test) should swing about angle 0, the shank at rest,
    after a release from extension: a swing that comes to rest elsewhere, or that starts deep in
    flexion, says that the zero or the sign of the angle may be off; with ``release``, a shank held
    before its swing (:func:`pendulum_release`), that the lift and the hold are in the recording."""
    kept = ~trial.exclude
    angle = trial.angle_deg[kept]
    if angle.size < 2:  # nothing left to judge (the rules refuse such a trial)
        return []
    tail = angle[-max(2, int(round(1.0 / trial.sampling_period_s))):]
    found = []
    if np.ptp(tail) < STILL_RANGE_DEG and abs(rest := float(np.median(tail))) > REST_TOLERANCE_DEG:
        found.append(f"the shank comes to rest at {rest:.1f}° (its last second), not at 0, the shank at rest: "
                     + ("is angle_deg a flexion angle (90° with the shank hanging)? Write 90 − angle_deg, positive "
                        "in extension" if abs(rest) > REST_MEDIAN_DEG else
                        "is angle_deg zeroed elsewhere? (the effects gravity_offset and goniometer_offset model such "
                        "an offset)"))
    lifts = pendulum_lifts(trial) if release else []
    if lifts:
        found.append(f"the shank is {_lifts_in_words(trial, lifts)} and then swings: a pendulum test recorded from "
                     "before its release, whose lift and hold no pendulum model describes; exclude those samples "
                     "(or cut them with start_s)")
    if angle[0] < -RELEASE_FLEXION_DEG and not trial.exclude[0]:  # a release excluded leaves the swing under way
        found.append(f"the swing starts at {float(angle[0]):.1f}°, deep in flexion; a pendulum test is released "
                     "from extension (positive angle_deg): is the sign of angle_deg flipped?")
    median = float(np.median(angle))
    if abs(median) > REST_MEDIAN_DEG and not found:
        found.append(f"the swing's median angle is {median:.1f}°, where a pendulum test swings about 0, the shank "
                     "hanging at rest: is angle_deg zeroed with the shank hanging, positive in extension? (a flexion "
                     "angle reads 90° at rest)")
    return found


def pendulum_lifts(trial: Trial) -> list[tuple[int, int]]:
    """The examiner's lifts in a pendulum test (a trial without pulses) recorded from before its
    release(s), as ``(start, release)`` sample indices: the shank held by hand (within
    :data:`RELEASE_HOLD_SHARE` of its distance from where it comes to rest, at least
    :data:`RELEASE_HOLD_MIN_DEG`, over every :data:`RELEASE_HOLD_S`: a tremor or a slow sag is
    still a hold) at least :data:`RELEASE_SWING_DEG` from rest, and before it the lift back to where
    the shank was near rest; or, where no hold is found, a rise from a still rest straight to the
    swing's largest extreme (released at the top).  Rest is the median of the last second.  Empty
    where the recording starts at the release, has pulses, or no swing.  Excluded samples are not
    judged; single-sample glitches are smoothed away by a running median."""
    if np.any(trial.stimulation > 0):
        return []
    dt = trial.sampling_period_s
    kept = np.flatnonzero(~trial.exclude)
    hold = int(np.ceil(RELEASE_HOLD_S / dt))
    second = max(2, int(round(1.0 / dt)))
    if kept.size < 2 * hold + second:
        return []
    angle = medfilt(trial.angle_deg[kept], 5) if kept.size >= 5 else trial.angle_deg[kept]
    rest = float(np.median(angle[-second:]))
    far = np.abs(angle - rest)
    windows = np.lib.stride_tricks.sliding_window_view(angle, hold)
    level = np.abs(windows.mean(axis=1) - rest)
    still = np.ptp(windows, axis=1) <= 2 * np.maximum(RELEASE_HOLD_MIN_DEG, RELEASE_HOLD_SHARE * level)
    whole = kept[hold - 1:] - kept[: kept.size - hold + 1] == hold - 1  # no excluded sample inside the window
    held_from = np.flatnonzero(still & whole & (level >= RELEASE_SWING_DEG))
    held = np.zeros(angle.size, bool)
    for i in held_from:
        held[i:i + hold] = True
    lifts, after = [], 0
    for h0, h1 in stretches(held):
        if h1 >= angle.size - second // 2:
            continue  # held to the end: the leg caught, not released
        drop = float(np.max(np.abs(angle[h1:h1 + second] - np.median(angle[h0:h1]))))
        if drop < max(RELEASE_SWING_DEG, 0.5 * float(far[h0:h1].mean())):
            continue  # no swing follows: a slow turn, or a rest taken for elsewhere, not a release
        begin = _lift_start(far, kept, h0, after)
        if begin > 0 and far[h0] - far[begin] < 0.5 * far[h0]:
            continue  # no lift before it (and not held from the recording's start): a swing slowing, not a hand
        lifts.append((int(kept[begin]), int(kept[h1 - 1])))
        after = h1
    if not lifts:  # released at the top of a lift: a rise from a still rest to the largest extreme
        top = int(np.argmax(far))
        if far[top] >= RELEASE_SWING_DEG:
            begin = _lift_start(far, kept, top, 0)
            if begin >= hold and top - begin >= hold // 2 and kept[begin] - kept[begin - hold] == hold \
                    and np.ptp(angle[begin - hold:begin]) <= 2 * RELEASE_HOLD_MIN_DEG:
                lifts.append((int(kept[begin]), int(kept[top])))
    return lifts


def _lift_start(far: np.ndarray, kept: np.ndarray, at: int, after: int) -> int:
    """Back from ``at``, the sample where a lift to it began: the distance from rest ``far`` falls
    going back (within :data:`RELEASE_HOLD_MIN_DEG` of noise) until it is within that of rest, until
    ``after``, or until excluded samples (``kept``: the indices of those not) interrupt it."""
    begin = at
    while begin > after and kept[begin] - kept[begin - 1] == 1 and far[begin - 1] > RELEASE_HOLD_MIN_DEG \
            and far[begin - 1] <= far[begin] + RELEASE_HOLD_MIN_DEG:
        begin -= 1
    return begin


def pendulum_release(trial: Trial) -> int:
    """Where the last free swing of a pendulum test recorded from before its release starts, as a
    sample index (the last lift's release, :func:`pendulum_lifts`); 0 where none is found."""
    lifts = pendulum_lifts(trial)
    return lifts[-1][1] if lifts else 0


def _held_angle(trial: Trial, release: int) -> float:
    """The angle [deg] a pendulum test's shank is held at before its ``release``: the median of the
    preceding :data:`RELEASE_HOLD_S`."""
    hold = int(np.ceil(RELEASE_HOLD_S / trial.sampling_period_s))
    return float(np.median(trial.angle_deg[max(0, release - hold):release + 1]))


def angle_doubts(trial: Trial) -> list[str]:
    """What the plausibility warnings say of the zero or the sign of ``trial``'s angle (a rest
    away from 0 between twitches, a pendulum test that rests elsewhere or starts in flexion), in
    words; empty where nothing is in doubt.  ``check`` qualifies what identify can do with such a
    trial by them."""
    if trial.n_samples < 3 * _smoothing_window(trial.sampling_period_s):
        return []
    return _rest_plausibility(trial) if np.any(trial.stimulation > 0) else _pendulum_plausibility(trial, release=False)


#: A stimulated trial whose angle, where no twitch acts, has its median further than this [deg] from
#: 0 (the shank hanging at rest) gets a warning: a flexion angle reads 90° there.
REST_MEDIAN_DEG = 45.0
#: ... and one further than this [deg], a warning of an offset zero: between twitches a shank swings
#: about its rest, and that median lies within 5° of it on simulated legs of two designs ...
REST_OFFSET_DEG = 10.0
#: ... where at least this many seconds [s] are free of twitches: a shorter stretch may hold part
#: of one swing, whose median lies anywhere within the swing.
REST_OFFSET_QUIET_S = 5.0


def _rest_plausibility(trial: Trial) -> list[str]:
    """A trial with pulses should rest near angle 0 between its twitches: the samples no twitch
    reaches (none in the :data:`~quadshank.data._paper.TWITCH_REACH_S` after a pulse), not
    excluded, at least a second of them, whose median lies beyond :data:`REST_MEDIAN_DEG` say that
    the angle's zero or convention is off, and beyond :data:`REST_OFFSET_DEG` (over at least
    :data:`REST_OFFSET_QUIET_S`) that its zero may be offset.  A trial stimulated throughout has
    no such samples and is not judged."""
    reach = max(1, int(round(TWITCH_REACH_S / trial.sampling_period_s)))
    quiet = quiet_mask(trial.stimulation, reach) & ~trial.exclude
    if np.count_nonzero(quiet) * trial.sampling_period_s < 1.0:
        return []
    median = float(np.median(trial.angle_deg[quiet]))
    # a shank that went over the top (a recording unwrapped through a full turn) hangs at 360°
    off = abs(median - 360.0 * round(median / 360.0))
    if off <= REST_OFFSET_DEG or (off <= REST_MEDIAN_DEG and
                                  np.count_nonzero(quiet) * trial.sampling_period_s < REST_OFFSET_QUIET_S):
        return []
    said = f"where no twitch acts ({np.count_nonzero(quiet)} samples) the angle's median is {median:.1f}°, where the shank "
    if off <= REST_MEDIAN_DEG:
        return [said + "hanging at rest is 0: is the goniometer's zero offset? The passive model's gravity acts about "
                "angle 0, and an offset shrinks G' and inflates the gains; zero angle_deg with the shank hanging, or add "
                "the effect goniometer_offset (a sensor's zero) or gravity_offset (a rest the tissues hold)"]
    return [said + "hanging at rest is 0: is angle_deg zeroed with the shank hanging, positive in extension? (a "
            "flexion angle reads 90° at rest)"]


#: Twitches that start after this many seconds without a pulse (the reach of one twitch) ...
#: are compared: the angle's acceleration over :data:`TWITCH_LIFT_S` after the pulse against the
#: :data:`TWITCH_BEFORE_S` before it; the quadriceps lifts the shank, so it rises.
TWITCH_LIFT_S, TWITCH_BEFORE_S = 0.2, 0.1
#: At least this many such pulses are needed ...
TWITCH_ONSETS_MIN = 8
#: ... and a mean fall of this many standard errors is named.
TWITCH_FALL_SE = 3.0


def twitch_direction(trial: Trial) -> list[str]:
    """A stimulated trial whose angle falls after its pulses: the quadriceps extends the knee, so
    after a pulse that starts a twitch (none in the :data:`TWITCH_REACH_S` before it) the angle's
    acceleration (derived from the angle, as the model sees it) should rise.  A fall of
    :data:`TWITCH_FALL_SE` standard errors over :data:`TWITCH_ONSETS_MIN` pulses or more says that
    the angle is positive in flexion, or that the muscle stimulated is a flexor."""
    dt = trial.sampling_period_s
    reach = max(1, int(round(TWITCH_REACH_S / dt)))
    after, before = max(1, int(round(TWITCH_LIFT_S / dt))), max(1, int(round(TWITCH_BEFORE_S / dt)))
    pulses = np.flatnonzero(trial.stimulation > 0)
    gap = np.diff(pulses, prepend=-(reach + 1))
    onsets = pulses[(gap > reach) & (pulses >= before) & (pulses + after <= trial.n_samples)]
    onsets = [k for k in onsets if not trial.exclude[k - before:k + after].any()]
    if len(onsets) < TWITCH_ONSETS_MIN:
        return []
    acc = derive_acceleration(trial.angle_deg, dt)
    rise = np.array([acc[k:k + after].mean() - acc[k - before:k].mean() for k in onsets])
    se = rise.std(ddof=1) / np.sqrt(rise.size)
    if not se > 0 or rise.mean() > -TWITCH_FALL_SE * se:
        return []
    return [f"the angle falls after the pulses that start a twitch: its acceleration over the "
            f"{TWITCH_LIFT_S * 1000:.0f} ms after each of {rise.size} such pulses is {-rise.mean():.3g} deg/s² below the "
            f"{TWITCH_BEFORE_S * 1000:.0f} ms before ({-rise.mean() / se:.1f} standard errors), where the quadriceps "
            "lifts the shank: is angle_deg positive in flexion? (positive angle = extension; the models describe an "
            "extensor)"]


#: A pulse is followed by a twitch: the angle over this many seconds after it should change ...
UNMOVED_S = 0.25
#: ... and where it stays exactly the same after this many pulses or more, and this share of them, that is named.
UNMOVED_MIN, UNMOVED_SHARE = 3, 0.2


def _unmoved_pulses(trial: Trial) -> list[str]:
    """Pulses after which the angle does not change at all: a twitch moves the shank, so an
    angle that reads exactly the same for :data:`UNMOVED_S` after a pulse (none of those samples
    excluded) was not measuring (or the knee was held at a stop), or the pulse recruited nothing or
    was not delivered."""
    n = max(1, int(round(UNMOVED_S / trial.sampling_period_s)))
    pulses = np.flatnonzero(trial.stimulation > 0)
    pulses = pulses[pulses + n < trial.n_samples]
    pulses = [k for k in pulses if not trial.exclude[k:k + n + 1].any()]
    flat = [k for k in pulses if np.ptp(trial.angle_deg[k:k + n + 1]) == 0]
    if len(flat) < UNMOVED_MIN or len(flat) < UNMOVED_SHARE * len(pulses):
        return []
    return [f"{len(flat)} of {len(pulses)} pulses leave angle_deg exactly unchanged for {UNMOVED_S * 1000:.0f} ms after "
            f"them (the first at {float(trial.time_s[flat[0]]):.3f} s), where a twitch moves the shank: was the sensor "
            "stuck or saturated there, the knee held at the end of its range, the pulse too weak to recruit, or not "
            "delivered? Leave such stretches out with exclude = 1"]


def _lifts_in_words(trial: Trial, lifts) -> str:
    """Where and to what the shank was lifted and held before each release, in words."""
    return "; then ".join(f"lifted from time_s = {seconds_text(trial.time_s[a])} and held at "
                          f"{_held_angle(trial, b):.1f}° until time_s = {seconds_text(trial.time_s[b])}"
                          for a, b in lifts)


def _exclude_before_release(trial: Trial, label: str) -> Trial:
    """A pendulum test recorded from before its release(s) (:func:`pendulum_lifts`) with each lift
    and hold excluded, and each release itself (the first
    :data:`~quadshank.data._paper.TWITCH_REACH_S` of the swing, which a recording that starts at
    the release leaves out too), and a warning that says so; any other trial as it is."""
    lifts = pendulum_lifts(trial)
    if not lifts:
        return trial
    exclude = trial.exclude.copy()
    after = int(round(TWITCH_REACH_S / trial.sampling_period_s))  # as at a recording's start: the hand letting go
    for a, b in lifts:
        exclude[a:b + after + 1] = True
    warnings.warn(
        f"{label} ({trial.key} trial {trial.trial}): a pendulum test recorded from before its release: the shank is "
        f"{_lifts_in_words(trial, lifts)}, and the lift{'s' if len(lifts) > 1 else ''}, the "
        f"hold{'s' if len(lifts) > 1 else ''} and {TWITCH_REACH_S * 1000:g} ms after each release (which no "
        "pendulum model describes) are excluded. start_s in the manifest cuts a first one instead", DataWarning,
        stacklevel=4)
    return trial.replace(exclude=exclude)


def _warn_implausible(cohort: Cohort, labels: Sequence[str]) -> None:
    for t, label in zip(cohort.trials, labels):
        for text in plausibility(t):
            warnings.warn(f"{label} ({t.key} trial {t.trial}): {text}", DataWarning, stacklevel=3)
    first: dict[bytes, tuple[Trial, str]] = {}
    for t, label in zip(cohort.trials, labels):  # a recording copied under a second trial's name
        if t.n_samples < 2 or np.ptp(t.angle_deg) == 0:
            continue  # a constant angle is named above; two of them are not one recording
        digest = hashlib.sha256(np.ascontiguousarray(t.angle_deg, dtype=np.float64).tobytes()).digest()
        if digest in first:
            other, where = first[digest]
            warnings.warn(f"{label} ({t.key} trial {t.trial}): angle_deg is the same on every sample as in {where} "
                          f"({other.key} trial {other.trial}): one recording copied as two trials?", DataWarning,
                          stacklevel=3)
        else:
            first[digest] = (t, label)


# --------------------------------------------------------------------------- CSV tables
#: Separators a spreadsheet in another locale writes instead of the comma, and their names.
_OTHER_SEPARATORS = ((";", "semicolons (';')"), ("\t", "tabs"))


@dataclasses.dataclass
class _Table:
    """A CSV file split into header and data rows, with the line number of each row."""

    columns: dict[str, int]  # known column name -> field index (first occurrence)
    header_line: int
    rows: list[list[str]]
    lines: list[int]
    well_formed: bool  # every data row has as many fields as the header
    #: the rows left out for a wrong number of fields (already reported)
    dropped: list[list[str]] = dataclasses.field(default_factory=list)


def _read_table(
    path: Path, file: str, required: Sequence[str], optional: Sequence[str], problems: list[Problem],
    alternatives: dict[str, tuple[str, ...]] | None = None,
    unknown_hint: str = "Remove the column",
) -> _Table | None:
    """Read a CSV file, reporting structural problems; ``None`` when it is unusable.

    ``alternatives``: a column that other (optional) columns may stand in for; a file may hold
    the column or its stand-ins, not both (and one of them where the column is required).
    ``unknown_hint``: what to say of a column the file may not hold."""
    spanning = False
    header: list[str] | None = None
    header_line = 1
    rows: list[list[str]] = []
    lines: list[int] = []
    reader = None
    archive = _archive_kind(path)
    if archive is not None:
        problems.append(Problem(file, None, None, f"{archive}, not CSV text: export the data as CSV (comma-separated, "
                                "UTF-8) and list that file"))
        return None
    encoding = _encoding(path)
    try:
        with open(path, newline="", encoding=encoding) as fh:
            reader = csv.reader(fh)
            end = 0
            for row in reader:
                start, end = end + 1, reader.line_num
                if end > start and any("\n" in c or "\r" in c for c in row):
                    # a quote left open swallows the lines after it into one field
                    problems.append(Problem(file, None, start, f"a quoted field holds a line break (the row runs "
                                            f"on to line {end}): is a quote (\") left open here? A value may not "
                                            "hold a line break"))
                    spanning = True
                    continue
                if not any(c.strip() for c in row):
                    continue  # blank line, or a spreadsheet's row of empty cells (",,,")
                if header is None and [c.strip().lower() for c in row] == ["sep=", ""]:
                    continue  # a spreadsheet's note that the file is comma-separated, before the header
                if header is None:
                    header = [c.strip() for c in row]
                    header_line = reader.line_num
                elif row[0].lstrip().startswith("#") and not any(c.strip() for c in row[1:]):
                    continue  # a comment line among or after the data ("# end of file"); not a spreadsheet's #N/A
                else:
                    rows.append(row)
                    lines.append(reader.line_num)
    except UnicodeDecodeError as exc:
        told = "byte-order mark says" if encoding == "utf-16" else "first bytes say"
        problems.append(_not_utf8(path, file) if encoding == "utf-8-sig" else
                        Problem(file, None, None, f"not UTF-16 text, as its {told} ({exc.reason})"))
        return None
    except csv.Error as exc:
        line = reader.line_num if reader is not None else None
        problems.append(Problem(file, None, line, f"malformed CSV: {exc}"))
        return None
    except OSError as exc:
        problems.append(Problem(file, None, None, f"cannot be read: {exc.strerror or exc}"))
        return None

    if header is None:
        problems.append(Problem(file, None, None, "empty file (expected a header line and data rows)"))
        return None

    # a separator after the last field of every line (some loggers write one), or a spreadsheet's empty
    # columns after the last: no name, no value; read as absent
    named = len(header)
    while named > 1 and not header[named - 1]:
        named -= 1
    if all(not c.strip() for row in rows for c in row[named:]):
        header = header[:named]
    rows = [row[:len(header)] if len(row) > len(header) and not any(c.strip() for c in row[len(header):]) else row
            for row in rows]

    known = tuple(required) + tuple(optional)
    if all(parse_number(c) is not None for c in header):  # numbers where the names should be
        problems.append(Problem(file, None, header_line, f"the first line, {','.join(header)[:60]!r}, holds numbers: the "
                                f"line of column names is missing. Add it above the data ({', '.join(required)} ...)"))
        return None
    if header[0].startswith("#"):
        problems.append(Problem(file, None, header_line, f"the first line, {','.join(header)[:60]!r}, is a comment? The "
                                f"first line holds the column names ({', '.join(required)} ...); remove the lines "
                                "above them"))
        return None
    if not set(header) & set(known):
        # a logger's block of settings (or a title) above the column names: say where the names are
        at = next((line for line, row in zip(lines[:50], rows[:50])
                   if len({c.strip() for c in row} & set(required)) >= 2), None)
        if at is not None:
            problems.append(Problem(file, None, header_line, f"the column names ({', '.join(required)} ...) are on line "
                                    f"{at}, not on the first: remove the {at - 1} line{'s' if at > 2 else ''} above "
                                    "them (a logger's settings or a title)"))
            return None
    separator = next((sep for sep, label in _OTHER_SEPARATORS if len(header) == 1 and sep in header[0]), None)
    if separator is not None:
        label = dict(_OTHER_SEPARATORS)[separator]
        shown = header[0] if len(header[0]) <= 60 else header[0][:57] + "..."
        problems.append(Problem(file, None, header_line, f"the header is one field, {shown!r}: is the file separated "
                                f"by {label} rather than commas? The format is comma-separated, with '.' as the "
                                "decimal mark (a spreadsheet's 'CSV (comma delimited)' export)"))
    # a required column that is absent, and a column that is not the format's: perhaps the same
    absent = [r for r in required if r not in header and not set((alternatives or {}).get(r, ())) & set(header)]
    unknown = [c for c in header if c and c not in known]
    columns: dict[str, int] = {}
    by_case = {name.lower(): name for name in known}
    for i, name in enumerate(header):
        if name in columns:
            problems.append(Problem(file, name, header_line, "duplicated column"))
        elif name not in known:
            hint = _prefixed(name, known) or difflib.get_close_matches(name, known, n=1) or [
                by_case[m] for m in difflib.get_close_matches(name.lower(), list(by_case), n=1)]
            label = "unnamed column" if not name else "unknown column"
            msg = f"{label} (position {i + 1}); expected {', '.join(known)}"
            if hint and hint[0] in header:  # the column it resembles is there: another channel
                hint = []
            if hint:
                msg += f"; did you mean {hint[0]!r}?"
                if name.lower().endswith("_ms") and hint[0].endswith("_s"):
                    msg += " (in seconds: the values divided by 1000)"
                elif ("rate" in name.lower() or "hz" in name.lower()) and hint[0].endswith("period_s"):
                    msg += " (a period in seconds: 1 over a rate in Hz)"
            elif not name and i == 0:
                msg += "; a row index (as pandas' to_csv writes unless index=False)? Remove the column"
            elif absent:
                msg += f"; if it holds {' or '.join(absent)}, name it so; else: {unknown_hint}"
            else:
                msg += f"; {unknown_hint}"
            if separator is None:
                problems.append(Problem(file, name, header_line, msg))
        else:
            columns[name] = i
    for name in dict.fromkeys((*required, *(alternatives or {}))):
        instead = (alternatives or {}).get(name, ())
        given = [c for c in instead if c in columns]
        if separator is not None:
            break  # the one problem above says why every column is missing
        if name not in columns and not given and name in required:
            also = f"; or give {' and/or '.join(instead)}" if instead else ""
            if unknown:
                also += f"; if {' or '.join(repr(c) for c in unknown[:3])} holds it, name that column {name}"
            problems.append(Problem(file, name, header_line, f"missing column (header is: {','.join(header)}){also}"))
        elif name in columns and given:
            problems.append(Problem(file, given[0], header_line, f"give either {name} or {' and/or '.join(instead)}, "
                                    "not both"))

    if separator is not None:
        return None
    if not rows:
        problems.append(Problem(file, None, None, "no data rows (only the header)"))
        return None

    n_fields = len(header)
    well_formed = not spanning
    bad_rows = [(line, row) for line, row in zip(lines, rows) if len(row) != n_fields]
    if bad_rows:
        well_formed = False
        for line, row in bad_rows[:_MAX_PER_KIND]:
            # 0,25 for 0.25 splits each number in two: more fields than the header, each a run of digits
            comma = len(row) > n_fields and all(re.fullmatch(r"\s*-?[0-9]+\s*", c) for c in row)
            hint = "; decimal commas (0,25 for 0.25)? The format's decimal mark is '.'" if comma else (
                "; a logger's closing line or a note? Remove it, or start it with #"
                if len(row) == 1 and parse_number(row[0]) is None else "")
            problems.append(Problem(file, None, line, f"{len(row)} fields, expected {n_fields} as in the header{hint}"))
        if len(bad_rows) > _MAX_PER_KIND:
            rest = bad_rows[_MAX_PER_KIND:]
            problems.append(
                Problem(file, None, None, f"{len(rest)} more rows with a wrong number of fields "
                        f"(rows {rest[0][0]} to {rest[-1][0]})")
            )
        dropped = [row for row in rows if len(row) != n_fields]
        keep = [i for i, row in enumerate(rows) if len(row) == n_fields]
        rows = [rows[i] for i in keep]
        lines = [lines[i] for i in keep]
    if _units_row(rows, columns):
        cells = ", ".join(repr(rows[0][i].strip()) for i in columns.values() if rows[0][i].strip())
        problems.append(Problem(file, None, lines[0], f"holds no number ({cells}): a row of units under the header? "
                                "The columns' names give their units; remove the row"))
        rows, lines = rows[1:], lines[1:]  # its cells are not named again, column by column
    return _Table(columns, header_line, rows, lines, well_formed, dropped if bad_rows else [])


#: The first bytes of files that are often saved under a ``.csv`` name but are not text.
_ARCHIVES = (
    (b"PK\x03\x04", "a zip archive (an Excel .xlsx or OpenDocument .ods workbook?)"),
    (b"\xd0\xcf\x11\xe0\xa1\xb1\x1a\xe1", "an Excel 97-2003 workbook (.xls)"),
    (b"\x1f\x8b", "a gzip-compressed file (decompress it first)"),
    (b"\x89HDF", "an HDF5 file (a MATLAB v7.3 .mat or NetCDF-4 file?)"),
    (b"MATLAB", "a MATLAB .mat file"),
)


def _prefixed(name: str, known: Sequence[str]) -> list[str]:
    """The one known column whose name begins with ``name``'s first word (a logger's abbreviation:
    'Stim' for stimulation, 'Accel (deg/s2)' for acceleration_deg_s2), as a list; else empty.
    difflib's similarity ranks such short names after longer look-alikes ('Stim' nearer 'time_s')."""
    word = re.split(r"[^a-z]+", name.lower().strip())[0] if name.strip() else ""
    found = [k for k in known if len(word) >= 3 and k.lower().startswith(word)]
    return found if len(found) == 1 else []


def _archive_kind(path: Path) -> str | None:
    """What a file that is not text is, from its first bytes, or None."""
    try:
        with open(path, "rb") as fh:
            start = fh.read(8)
    except OSError:
        return None  # reading it again says why it cannot be read
    return next((what for magic, what in _ARCHIVES if start.startswith(magic)), None)


def _encoding(path: Path) -> str:
    """The text encoding of a CSV file: UTF-16 where it starts with that byte-order mark (a
    spreadsheet's Unicode export), else UTF-8 (a byte-order mark read past)."""
    try:
        with open(path, "rb") as fh:
            start = fh.read(2)
    except OSError:
        return "utf-8-sig"  # reading it again says why it cannot be read
    if start in (codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE):
        return "utf-16"
    # UTF-16 without its byte-order mark (some loggers' and MATLAB's exports): the header's first
    # character is ASCII, so one of its two bytes is zero; no UTF-8 text starts with a zero byte
    if len(start) == 2 and start[1] == 0 and 32 < start[0] < 127:
        return "utf-16-le"
    if len(start) == 2 and start[0] == 0 and 32 < start[1] < 127:
        return "utf-16-be"
    return "utf-8-sig"


def _not_utf8(path: Path, file: str) -> Problem:
    """The problem of a file that is not UTF-8: the row of its first byte that is not (and the
    column, where the header names it), and what the cell reads as in Windows-1252 (Latin-1), the
    encoding a spreadsheet saves in where it is not told UTF-8 (a degree sign is one byte there)."""
    data = path.read_bytes()
    skip = len(codecs.BOM_UTF8) if data.startswith(codecs.BOM_UTF8) else 0
    try:
        data[skip:].decode("utf-8")
        return Problem(file, None, None, "not UTF-8 text")
    except UnicodeDecodeError as exc:
        at, reason = skip + exc.start, exc.reason
    lines = re.split(rb"\r\n|\r|\n", data.removeprefix(codecs.BOM_UTF8))
    before = re.split(rb"\r\n|\r|\n", data[skip:at])
    row, line = len(before), lines[len(before) - 1]  # row: 1-based, as an editor counts lines
    # the header: the first line that the reader does not read past (blank, empty cells, "sep=,")
    head = next((i for i, x in enumerate(lines) if x.replace(b",", b"").strip()
                 and x.replace(b" ", b"").lower() != b"sep=,"), 0)
    column, cell = None, line
    if b'"' not in line:  # without quotes, the commas before the byte count the fields
        field = before[-1].count(b",")
        cell = line.split(b",")[field]
        names = lines[head].split(b",")
        if row - 1 > head and field < len(names) and names[field].strip().isascii():
            column = names[field].strip().decode("ascii")
    shown = cell.strip().decode("cp1252", errors="replace")[:60]
    return Problem(file, column, row, f"not UTF-8 text: byte 0x{data[at]:02x} ({reason}); in Windows-1252 (Latin-1) "
                   f"it reads {shown!r}: save the file as UTF-8 (a spreadsheet's 'CSV UTF-8')")


def _units_row(rows: list[list[str]], columns: dict[str, int]) -> bool:
    """Whether the first data row holds text (units, say) and no number in any known column,
    where the next row holds numbers."""
    if len(rows) < 2 or not columns:
        return False
    first = [rows[0][i].strip() for i in columns.values() if i < len(rows[0])]
    second = [rows[1][i].strip() for i in columns.values() if i < len(rows[1])]
    return (any(first) and all(parse_number(c) is None and not _NON_FINITE.fullmatch(c) for c in first)
            and any(parse_number(c) is not None for c in second))


#: A number as the format writes it: ASCII digits, an optional sign, decimal point and exponent.
#: (Python's ``float`` also takes ``1_000``, non-ASCII digits and ``infinity``; the format does not.)
_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
_NON_FINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)


def _number_hint(text: str) -> str:
    """Why a cell that looks like a number is not one as the format writes it (a decimal comma, digits
    grouped, a character outside ASCII such as a typographic minus), or ''."""
    text = text.strip()
    if re.fullmatch(r"[+-]?[0-9]+(?:,[0-9]+)+(?:\.[0-9]*)?(?:[eE][+-]?[0-9]+)?", text):
        return (" (a decimal comma, 0,25 for 0.25, or digits grouped, 1,234.5? A number is written with '.' as its "
                "decimal mark and without grouping)")
    if not text.isascii():
        return f" (written {ascii(text)}: a number is ASCII digits with '-', '+', '.' and 'e'; no other character)"
    if text.lower() in _TRUTH_WORDS:
        return " (a word for true or false: write 1 or 0)"
    if re.fullmatch(r"[0-9]{1,2}:[0-9]{2}(?::[0-9]{2}(?:\.[0-9]*)?)?", text):
        return " (a clock time: write the seconds since the recording's start, or since any fixed time)"
    return ""


#: Words a spreadsheet or a logger writes for true and false, where the format takes 1 and 0.
_TRUTH_WORDS = ("true", "false", "yes", "no", "y", "n", "on", "off", "wahr", "falsch")


def parse_number(text: str) -> float | None:
    """``text`` (surrounding spaces allowed) as a float when it is a number as the format
    writes it, else ``None``."""
    text = text.strip()
    return float(text) if _NUMBER.fullmatch(text) else None


#: Columns whose cells may be empty or NaN on a row with ``exclude`` = 1 (a sensor's dropout): the
#: reader fills them in (:func:`_fill_missing`).
_MAY_BE_MISSING = ("angle_deg", "acceleration_deg_s2", "velocity_deg_s")
#: What a cell left without a value holds: nothing, or NaN.
_MISSING = re.compile(r"(?:nan)?", re.IGNORECASE)


def _sparse_stride(cells: list[str]) -> int | None:
    """The stride k (2 or more) where a column holds a value on every k-th row only and is empty on
    the rows between (a slower channel written into a faster file), else None."""
    filled = np.flatnonzero([bool(c.strip()) for c in cells])
    if filled.size < 3 or filled.size > len(cells) / 2:
        return None
    steps = np.diff(filled)
    k = int(np.median(steps))
    return k if k >= 2 and np.mean(steps == k) >= 0.9 else None


def _parse_float_column(table: _Table, name: str, file: str, problems: list[Problem],
                        excluded: np.ndarray | None = None) -> np.ndarray | None:
    """The column as floats, or ``None`` (after reporting) when a cell is not a finite number.
    ``excluded`` (True on rows with ``exclude`` = 1): those rows' cells may be empty or NaN, read
    as NaN (the caller fills them in)."""
    idx = table.columns[name]
    cells = [row[idx] for row in table.rows]
    if name in ("acceleration_deg_s2", "velocity_deg_s") and all(_MISSING.fullmatch(c.strip()) for c in cells):
        problems.append(Problem(file, name, None, "no value on any row (empty or NaN): a signal that was not "
                                "recorded? Leave the column out and the reader derives it from the angle"))
        return None
    values = [parse_number(c) for c in cells]
    if excluded is not None:
        values = [math.nan if v is None and out and _MISSING.fullmatch(c.strip()) else v
                  for c, v, out in zip(cells, values, excluded)]
    if None not in values:
        arr = np.array(values, dtype=float)
        if (np.isfinite(arr) | (np.isnan(arr) & (excluded if excluded is not None else False))).all():
            return arr  # an exponent can still overflow
    non_numeric: list[tuple[int, str]] = []
    non_finite: list[tuple[int, str]] = []
    for k, (text, line, v) in enumerate(zip(cells, table.lines, values)):
        if excluded is not None and excluded[k] and v is not None and math.isnan(v):
            continue
        if v is None and not _NON_FINITE.fullmatch(text.strip()):
            non_numeric.append((line, f"{text!r}{_number_hint(text)}"))
        elif v is None or not math.isfinite(v):
            non_finite.append((line, text))
    leave_out = ("; a sample to leave out may be empty or NaN where its exclude is 1" if name in _MAY_BE_MISSING
                 else "; write 0 where no pulse was delivered" if name in ("stimulation", *_STIMULATOR) else "")
    stride = _sparse_stride(cells) if name in _MAY_BE_MISSING else None
    if stride:
        problems.append(Problem(file, name, None, (
            f"a value on every {stride}th row only, empty between: a channel recorded {stride} times slower than the "
            "file's rows (the angle at 100 Hz in a file of 1-kHz stimulation, say)? Give every signal at one rate: "
            "keep the rows that hold the values, each pulse moved to the nearest of them, or fill the values in "
            "between (linear interpolation) and resample (`quadshank convert --resample`)")))
    _report_cells(problems, file, name, non_numeric, "non-numeric value {}" + leave_out)
    _report_cells(problems, file, name, non_finite,
                  "non-finite value {!r} (NaN and infinity are not allowed" + leave_out + ")")
    return None


def _fill_missing(values: np.ndarray) -> np.ndarray:
    """NaN samples (cells left empty on excluded rows) filled in linearly between their finite
    neighbours, and with the nearest finite value at either end: excluded, they are not compared
    with the model, but the model and the derivatives run through them."""
    missing = np.isnan(values)
    if not missing.any() or missing.all():
        return values
    k = np.arange(values.size)
    out = values.copy()
    out[missing] = np.interp(k[missing], k[~missing], values[~missing])
    return out


# --------------------------------------------------------------------------- signal checks
def _check_signals(
    file: str,
    lines: Sequence[int],
    signals: dict[str, np.ndarray | None],
    sampling_period_s: float | None,
    period_origin: str,
    problems: list[Problem],
    uniform: bool = True,
) -> None:
    """Rules 4-6 on columns already known to be finite (``None`` = unusable, skipped).

    ``lines`` gives the line number of each sample; ``period_origin`` says
    where the expected sampling period comes from (for the message).  ``uniform=False``
    (data to be resampled) waives the uniform grid and the manifest's period.
    """
    lines = np.asarray(lines)
    time = signals.get("time_s")
    if time is not None:
        if time.size < 2:
            problems.append(Problem(file, None, None, "only one data row; at least two are needed"))
        else:
            step = np.diff(time)
            bad = np.flatnonzero(~(step > 0))
            if bad.size:
                i = int(bad[0])
                problems.append(
                    Problem(file, "time_s", int(lines[i + 1]),
                            f"time not strictly increasing: {float(time[i + 1])!r} s follows {float(time[i])!r} s "
                            f"(row {int(lines[i])})")
                )
            elif uniform:
                median = float(np.median(step))
                off = np.flatnonzero(np.abs(step - median) > UNIFORM_TOLERANCE * median)
                if off.size:
                    i = int(off[0])
                    problems.append(
                        Problem(file, "time_s", int(lines[i + 1]),
                                f"non-uniform sampling: step {step[i]:.6g} s from the previous row differs "
                                f"from the median step {median:.6g} s by more than {UNIFORM_TOLERANCE:.0%} "
                                "(irregular time stamps? `quadshank convert FOLDER OUT.nc --resample PERIOD_S` puts "
                                "them on a uniform grid)")
                    )
                if sampling_period_s is not None and not math.isclose(
                    median, sampling_period_s, rel_tol=PERIOD_TOLERANCE, abs_tol=0.0
                ):
                    problems.append(
                        Problem(file, "time_s", int(lines[0]),
                                f"sampling period {median:.6g} s (median time step) disagrees with "
                                f"sampling_period_s = {float(sampling_period_s)!r} s {period_origin}"
                                + ("; is time_s in milliseconds? (give seconds: the values divided by 1000)"
                                   if math.isclose(median, 1000 * sampling_period_s, rel_tol=PERIOD_TOLERANCE)
                                   or median > MAX_SAMPLING_PERIOD_S else ""))
                    )

    for column in _STIMULATOR:
        values = signals.get(column)
        if values is not None:
            _report_cells(problems, file, column, [(int(lines[i]), repr(float(values[i])))
                                                   for i in np.flatnonzero(values < 0)],
                          "negative value {} (0 where no pulse was delivered)")
    stim = signals.get("stimulation")
    if stim is None and any(signals.get(c) is not None for c in _STIMULATOR):
        stim = _charge(signals)  # for the radian rule below: where pulses were delivered
    elif stim is not None:
        out = np.flatnonzero((stim < 0) | (stim > 1))
        pulses = stim[stim != 0]
        high = stim[stim > 1]
        low = stim[(stim != 0) & (stim <= 1)]
        plateau = high.size >= 3 and np.mean(np.abs(high - np.median(high)) <= 0.1 * np.median(high)) >= 0.6
        if out.size and plateau and low.size and np.median(np.abs(low)) <= 0.05 * np.median(high):
            # pulses of one height over a baseline that is small but not 0: an analog trigger's noise
            problems.append(Problem(file, "stimulation", None, (
                f"{high.size} values near {float(np.median(high)):.3g} over {low.size} small nonzero ones (median "
                f"{float(np.median(np.abs(low))):.2g}): a trigger channel recorded as an analog signal? "
                "Every nonzero sample is a pulse: write 1 (or the level it recruits) at the first sample of each "
                "pulse and 0 everywhere else, the baseline's noise included")))
        # most pulses above 1, three or more: not a typo on a pulse or two
        elif out.size and (pulses > 0).all() and np.mean(pulses > 1) >= 0.5 and np.count_nonzero(pulses > 1) >= 3:
            if np.all(pulses == pulses[0]):  # one value on every pulse, above 1: a trigger's level
                hint = (f"every pulse is {float(pulses[0]):g}, outside [0, 1]: a trigger channel (in volts, say)"
                        + (", or a level in percent" if float(pulses[0]) == 100 else "") + "? Write 1 for a pulse (at its first "
                        "sample where the trigger is high over several), or the level it recruits")
            else:
                hint = ("pulses of several sizes above 1, outside [0, 1]: " + ("levels in percent (divide by 100), or "
                        if pulses.max() <= 100 else "") + "a stimulator's setting (a current in mA, a pulse width in "
                        "µs)? Give a setting as the column current_mA or pulse_width_us instead of stimulation; the "
                        "reader makes each pulse's charge a level")
            problems.append(Problem(file, "stimulation", None, hint))
        _report_cells(
            problems, file, "stimulation", [(int(lines[i]), repr(float(stim[i]))) for i in out],
            "value {} outside [0, 1] (recruitment level of the pulse, 0 when none)",
        )

    exclude = signals.get("exclude")
    if exclude is not None:
        out = np.flatnonzero((exclude != 0) & (exclude != 1))
        _report_cells(
            problems, file, "exclude", [(int(lines[i]), repr(float(exclude[i]))) for i in out],
            "value {} is not 0 or 1 (1: the sample is left out of the comparison with the model)",
        )
        if not out.size and np.count_nonzero(exclude == 0) < 2:
            problems.append(Problem(file, "exclude", None, f"{np.count_nonzero(exclude == 0)} of {exclude.size} "
                                    "samples not excluded; at least 2 are needed"))

    kept = np.ones(lines.size, bool) if exclude is None else exclude != 1
    angle = signals.get("angle_deg")
    if angle is not None and angle.size == kept.size and np.count_nonzero(kept) >= RADIAN_MIN_SAMPLES:
        lo, hi = np.quantile(angle[kept], [RADIAN_QUANTILE, 1 - RADIAN_QUANTILE])  # a glitch or two left aside
        if hi - lo > ANGLE_SPAN_LIMIT_DEG:
            problems.append(Problem(file, "angle_deg", None, (
                f"the angle spans {hi - lo:.4g} (from {lo:.4g} to {hi:.4g} over the bulk of the samples), where a knee "
                f"moves through less than {ANGLE_SPAN_LIMIT_DEG:g}°: the whole column in another unit (tenths or "
                "hundredths of a degree, a sensor's counts)? Convert it to degrees")))
    beyond = False
    for column, limit in MAGNITUDE_LIMITS.items():
        values = signals.get(column)
        if values is None or values.size != kept.size:
            continue
        out = np.flatnonzero(kept & (np.abs(values) > limit))
        beyond |= bool(out.size)
        _report_cells(
            problems, file, column, [(int(lines[i]), repr(float(values[i]))) for i in out],
            "value {} beyond ±" + f"{limit:g}" + " (no knee's, in degrees: a missing-data marker, another unit, an "
            "overflow?); correct it, or set exclude to 1 there",
        )

    angle = signals.get("angle_deg")
    if angle is not None and stim is not None and angle.size >= RADIAN_MIN_SAMPLES and not beyond:
        # the bulk of the samples, so that a glitch or two cannot hide radians
        lo, hi = np.quantile(angle, [RADIAN_QUANTILE, 1 - RADIAN_QUANTILE])
        magnitude = max(abs(float(lo)), abs(float(hi)))
        moves = hi - lo > (RADIAN_MIN_RANGE if np.any(stim > 0) else RADIAN_MIN_RANGE_PASSIVE)
        small_swing = np.any(stim > 0) and _same_units(angle, signals.get("acceleration_deg_s2"), time, kept)
        if magnitude <= RADIAN_LIMIT and moves and not small_swing:
            peak = int(np.argmax(np.where((angle >= lo) & (angle <= hi), np.abs(angle), -1.0)))
            problems.append(
                Problem(file, "angle_deg", int(lines[peak]),
                        f"values look like radians ({1 - 2 * RADIAN_QUANTILE:.0%} of the samples lie within "
                        f"[{lo:.3g}, {hi:.3g}], inside ±pi, and the angle moves); convert to degrees")
            )


def _smoothing_window(dt: float) -> int:
    """Samples of the Savitzky–Golay window of :data:`PLAUSIBILITY_WINDOW_S` (odd, at least 7)."""
    return max(7, int(round(PLAUSIBILITY_WINDOW_S / dt)) | 1)


def _smoothed_pairs(angle: np.ndarray, measured: np.ndarray, order: int, dt: float, kept=None):
    """The angle's ``order``-th derivative, the measured signal and the angle, each smoothed by the
    same Savitzky–Golay filter of :data:`PLAUSIBILITY_WINDOW_S`, stretch by stretch of the samples
    ``kept`` (so that an excluded artefact does not reach the samples beside it through the
    filter's window): a list of ``(derived, measured, angle)`` per stretch."""
    window = _smoothing_window(dt)
    kept = np.ones(angle.size, bool) if kept is None else np.asarray(kept, bool)
    return [(savgol_filter(angle[a:b], window, 3, deriv=order, delta=dt), savgol_filter(measured[a:b], window, 3),
             savgol_filter(angle[a:b], window, 3)) for a, b in stretches(kept) if b - a >= window]


def _agreement(angle: np.ndarray, measured: np.ndarray, order: int, dt: float, kept=None) -> tuple[float, float] | None:
    """The correlation and the size ratio (standard deviations, measured over derived) of a
    measured signal with the angle's ``order``-th derivative, both smoothed alike
    (:func:`_smoothed_pairs`), on the samples ``kept``; None where either is flat."""
    pieces = _smoothed_pairs(angle, measured, order, dt, kept)
    if not pieces:
        return None
    derived, smooth, _ = (np.concatenate(x) for x in zip(*pieces))
    if np.std(derived) == 0 or np.std(smooth) == 0:
        return None
    return float(np.corrcoef(smooth, derived)[0, 1]), float(np.std(smooth) / np.std(derived))


def _lag_s(angle: np.ndarray, measured: np.ndarray, order: int, dt: float, kept=None) -> float | None:
    """How long [s] a measured signal lags the angle's ``order``-th derivative (negative: leads),
    both smoothed alike: a signal late by τ is about ``d(t) − τ·ḋ(t)``, so τ is minus the ratio of
    the coefficients of ḋ and d in the least squares of the measured signal on both (and a
    constant), stretch by stretch, the filter's edges left out.  Unlike the peak of a
    cross-correlation it is not pulled by a swing that decays.  None where no stretch is long
    enough."""
    half = _smoothing_window(dt) // 2
    rows = []
    for d, m, _ in _smoothed_pairs(angle, measured, order, dt, kept):
        if d.size > 4 * half + 2:
            inner = slice(half, d.size - half)
            rows.append((d[inner], np.gradient(d, dt)[inner], m[inner]))
    if not rows:
        return None
    d, rate, m = (np.concatenate(x) for x in zip(*rows))
    coef, *_ = np.linalg.lstsq(np.column_stack([d, rate, np.ones_like(d)]), m, rcond=None)
    return float(-coef[1] / coef[0]) if coef[0] > 0 else None


def _gravity_share(trial: Trial, kept) -> float | None:
    """The coefficient [deg/s²] of sin φ in a measured acceleration besides the angle's second
    derivative (least squares of the smoothed acceleration on the derivative, sin φ and a
    constant): what a single accelerometer that also senses gravity's projection adds."""
    pieces = _smoothed_pairs(trial.angle_deg, trial.acceleration_deg_s2, 2, trial.sampling_period_s, kept)
    if not pieces:
        return None
    derived, smooth, angle = (np.concatenate(x) for x in zip(*pieces))
    X = np.column_stack([derived, np.sin(np.deg2rad(angle)), np.ones_like(derived)])
    coef, *_ = np.linalg.lstsq(X, smooth, rcond=None)
    return float(coef[1])


def _same_units(angle: np.ndarray, acceleration: np.ndarray | None, time: np.ndarray | None, kept=None) -> bool:
    """Whether a measured acceleration [deg/s²] follows the angle's second derivative at about its
    size (as :func:`plausibility` compares them): then, in a trial with pulses, the angle is in
    degrees however small its swing (weak twitches of a knee at rest), and the radian rule does
    not apply.  A pendulum test swings far beyond pi degrees: there the rule stands, since an
    angle and an acceleration both in radians agree with each other too."""
    if acceleration is None or time is None or time.size < 2 or not np.all(np.diff(time) > 0):
        return False
    dt = float(np.median(np.diff(time)))
    if angle.size < 3 * _smoothing_window(dt):
        return False
    agreement = _agreement(angle, acceleration, 2, dt, kept)
    return agreement is not None and agreement[0] > PLAUSIBLE_CORRELATION \
        and PLAUSIBLE_RATIO[0] <= agreement[1] <= PLAUSIBLE_RATIO[1]


# --------------------------------------------------------------------------- manifest
def _leg_problem(leg: str) -> str:
    """Why ``leg`` is not a leg; a name with characters outside ASCII shows them escaped (a Cyrillic
    'е' looks like 'e' but is not)."""
    shown = ascii(leg) if not leg.isascii() else repr(leg)
    hint = ", which holds characters outside ASCII" if not leg.isascii() else ""
    return f"{shown} is not 'left' or 'right'{hint}"


def _subject_problem(subject: str) -> str | None:
    """What is wrong with a subject's name, or None."""
    if not subject or subject.strip() != subject:
        return f"subject {subject!r} is empty or has leading/trailing white space"
    if any(ord(ch) < 32 or ord(ch) == 127 for ch in subject):
        return (f"subject {subject!r} holds a control character (a line break, a tab); the name is written into "
                "tables and file names")
    hidden = [ch for ch in subject if unicodedata.category(ch) == "Cf"]
    if hidden:
        return (f"subject {ascii(subject)} holds an invisible character ({unicodedata.name(hidden[0], 'format')}, "
                f"U+{ord(hidden[0]):04X}): it would be a subject of its own beside one whose name looks the same")
    return None


def _composed(text: str) -> str:
    """``text`` in Unicode's composed form (NFC): a name typed as 'ë' and one stored as 'e' + '¨' (as
    some file systems and editors write it) are one name, compared and written alike."""
    return unicodedata.normalize("NFC", text)


def _on_disk(folder: Path, key: str) -> Path:
    """The file ``key`` (a relative POSIX path) names in ``folder``: as written, or, where no such
    file exists, its composed or decomposed Unicode form that does (a name looks the same either way)."""
    candidate = folder.joinpath(*PurePosixPath(key).parts)
    if candidate.exists() or key.isascii():
        return candidate
    for form in ("NFC", "NFD"):
        other = folder.joinpath(*PurePosixPath(unicodedata.normalize(form, key)).parts)
        if other.exists():
            return other
    return candidate


def _period_problem(text: str, period: float) -> str | None:
    """What is wrong with a sampling period [s] (``text`` as written), or None."""
    if not (math.isfinite(period) and period > 0):
        return f"{text!r} is not a positive finite number of seconds"
    if period > MAX_SAMPLING_PERIOD_S:
        return (f"{text} s is longer than {MAX_SAMPLING_PERIOD_S:g} s: too slow to follow a knee's swing or a "
                "twitch; is it in milliseconds, or a rate in Hz? (give the period in seconds: milliseconds divided "
                "by 1000, or 1 over the rate; and time_s in seconds)")
    return None


@dataclasses.dataclass
class _Entry:
    """One manifest row; a field is ``None`` when it is invalid (already reported)."""

    line: int
    subject: str | None
    leg: str | None
    trial: int | None
    file: str | None  # as written in the manifest (whitespace stripped)
    key: str | None  # normalised relative path, for comparisons
    path: Path | None  # the file, when it exists
    sampling_period_s: float | None
    start_s: float | None = None  # keep samples from this time on (None: from the first)
    end_s: float | None = None  # ... up to this time (None: to the last)
    span_ok: bool = True  # start_s and end_s are valid (or absent)


def _parse_trial_number(text: str) -> int | str:
    """The trial number, or the reason it is not one."""
    f = parse_number(text)
    if f is None:
        return f"non-numeric value {text!r}; expected a positive integer"
    if not math.isfinite(f) or f != int(f):
        return f"{text!r} is not an integer; expected a positive integer"
    value = int(f)
    if value < 1:
        return f"non-positive value {text!r}; trials are numbered from 1"
    return value


def _normalise_relative(text: str) -> str | None:
    """``text`` as a normalised relative POSIX path, or ``None`` when it leaves the folder."""
    p = PurePosixPath(text.replace("\\", "/"))
    if p.is_absolute() or re.match(r"^[A-Za-z]:", str(p)) or ".." in p.parts or not p.parts:
        return None
    return str(p)


def _read_manifest(folder: Path, problems: list[Problem]) -> tuple[list[_Entry], bool, set[str]] | None:
    """Manifest entries, whether the manifest has a ``sampling_period_s`` column, and the files
    named in rows left out for a wrong number of fields (their problem is reported already; the
    file is not also "not listed")."""
    path = folder / MANIFEST_NAME
    if path.exists() and not path.resolve().is_relative_to(folder.resolve()):
        problems.append(Problem(MANIFEST_NAME, None, None, "a link to a file outside the folder; copy the file into it"))
        return None
    if path.exists() and not path.is_file():
        problems.append(Problem(MANIFEST_NAME, None, None, "not a regular file (a folder?); the manifest is a CSV file"))
        return None
    if not path.is_file():
        problems.append(
            Problem(MANIFEST_NAME, None, None,
                    f"missing: {folder} has no {MANIFEST_NAME} (columns {','.join(_MANIFEST_REQUIRED)}"
                    f"[,{','.join(_MANIFEST_OPTIONAL)}])")
        )
        return None
    table = _read_table(path, MANIFEST_NAME, _MANIFEST_REQUIRED, _MANIFEST_OPTIONAL, problems,
                        unknown_hint="notes or bookkeeping? Remove the column (keep them in a file of their own)")
    if table is None or any(name not in table.columns for name in _MANIFEST_REQUIRED):
        return None
    has_period = "sampling_period_s" in table.columns
    col = table.columns
    entries = []
    for row, line in zip(table.rows, table.lines):
        def bad(column: str, message: str) -> None:
            problems.append(Problem(MANIFEST_NAME, column, line, message))

        subject: str | None = _composed(row[col["subject"]].strip())
        if not subject:
            bad("subject", "empty subject")
            subject = None
        elif _subject_problem(subject):
            bad("subject", _subject_problem(subject))
            subject = None

        leg: str | None = row[col["leg"]].strip()
        if leg not in _LEGS:
            bad("leg", _leg_problem(leg))
            leg = None

        trial = _parse_trial_number(row[col["trial"]].strip())
        if isinstance(trial, str):
            bad("trial", trial)
            trial = None

        period: float | None = DEFAULT_SAMPLING_PERIOD_S
        if has_period:
            text = row[col["sampling_period_s"]].strip()
            period = parse_number(text)
            if period is None and _NON_FINITE.fullmatch(text):
                bad("sampling_period_s", f"{text!r} is not a positive finite number of seconds")
            elif period is None:
                bad("sampling_period_s", f"non-numeric value {text!r}{_number_hint(text)}; expected the sampling period "
                    "in s")
            elif _period_problem(text, period):
                bad("sampling_period_s", _period_problem(text, period))
                period = None

        span: dict[str, float | None] = {"start_s": None, "end_s": None}
        span_ok = True
        for name in span:
            text = row[col[name]].strip() if name in col else ""
            if not text:
                continue
            value = parse_number(text)
            if value is None or not math.isfinite(value):
                bad(name, f"{text!r} is not a time in s (leave the cell empty for no bound)")
                span_ok = False
            else:
                span[name] = value
        if span_ok and None not in span.values() and span["start_s"] >= span["end_s"]:
            bad("end_s", f"end_s {span['end_s']!r} s is not after start_s {span['start_s']!r} s")
            span_ok = False

        file: str | None = row[col["file"]].strip()
        key = file_path = None
        if not file:
            bad("file", "empty file name")
            file = None
        else:
            key = _normalise_relative(file)
            if key is None:
                bad("file", f"{file!r} must be a path relative to the folder, inside it")
            elif key == MANIFEST_NAME:
                bad("file", "the manifest cannot list itself")
                key = None
            else:
                candidate = _on_disk(folder, key)
                if candidate.exists() and not candidate.resolve().is_relative_to(folder.resolve()):
                    bad("file", f"{file!r} is a link to a file outside the folder; copy the file into it")
                elif candidate.is_file():
                    file_path = candidate
                elif candidate.exists():
                    bad("file", f"{file!r} is not a regular file")
                else:
                    try:
                        alike = sorted(p.name for p in candidate.parent.iterdir()
                                       if p.name.lower() == candidate.name.lower())
                    except OSError:  # no such folder, or not readable: nothing to compare
                        alike = []
                    listed = str(PurePosixPath(key).parent / alike[0]) if alike else ""
                    bad("file", f"{file!r} does not exist" + (
                        f"; {listed!r} differs from it only in case (names are compared exactly): list that name"
                        if alike else ""))
        entries.append(_Entry(line, subject, leg, trial, file, key, file_path, period, span["start_s"], span["end_s"],
                              span_ok))
    named = {_normalise_relative(c.strip()) for row in table.dropped for c in row if c.strip()}
    return entries, has_period, {n for n in named if n}


def _check_listing(
    entries: Sequence[_Entry], complete: bool, file: str, problems: list[Problem]
) -> None:
    """Rule 2 within the manifest: duplicates and gaps.

    ``complete`` says whether every entry's subject, leg and trial are valid;
    gaps are only checked then (an invalid trial number would look like a gap).
    """
    first_row: dict[tuple[str, str, int], int] = {}
    for e in entries:
        if e.subject is None or e.leg is None or e.trial is None:
            continue
        ident = (e.subject, e.leg, e.trial)
        if ident in first_row:
            problems.append(
                Problem(file, None, e.line,
                        f"{leg_key(e.subject, e.leg)} trial {e.trial} listed twice "
                        f"(rows {first_row[ident]} and {e.line})")
            )
        else:
            first_row[ident] = e.line

    first_file: dict[str, int] = {}
    first_target: dict[tuple[int, int], _Entry] = {}
    for e in entries:
        if e.key is None:
            continue
        if e.key in first_file:
            problems.append(
                Problem(file, "file", e.line, f"{e.file!r} listed twice (rows {first_file[e.key]} and {e.line})")
            )
            continue
        first_file[e.key] = e.line
        if e.path is None:
            continue
        st = e.path.stat()  # a link (or a hard link) to a file listed already: one recording read twice
        target = (st.st_dev, st.st_ino)
        if target in first_target:
            other = first_target[target]
            problems.append(
                Problem(file, "file", e.line, f"{e.file!r} is a link to {other.file!r} (row {other.line}): "
                        "the same recording listed as two trials")
            )
        else:
            first_target[target] = e

    if not complete:
        return
    legs: dict[str, list[_Entry]] = {}
    for e in entries:
        legs.setdefault(leg_key(e.subject, e.leg), []).append(e)
    for key, rows in legs.items():
        numbers = {e.trial for e in rows}
        if max(numbers) > len(numbers) + 1000:  # a date or a time stamp as the trial's number
            high = max(rows, key=lambda e: e.trial)
            problems.append(
                Problem(file, "trial", high.line,
                        f"{key}: trial {high.trial} of {len(numbers)} listed (trials of a leg must be numbered 1..n "
                        "without gaps; a date or a time stamp belongs in the file's name, not in 'trial')")
            )
            continue
        missing = sorted(set(range(1, max(numbers) + 1)) - numbers)
        if not missing:
            continue
        # The row where the numbering jumps: the first trial numbered above the first gap.
        jump = min((e for e in rows if e.trial > missing[0]), key=lambda e: e.trial)
        shown = ", ".join(map(str, missing[:20])) + (", ..." if len(missing) > 20 else "")
        if not key.isascii():  # a Cyrillic 'Т' looks like 'T': two subjects whose names look the same
            shown += f" (the leg's name escaped: {ascii(key)})"
        problems.append(
            Problem(file, "trial", jump.line,
                    f"{key}: trial{'s' if len(missing) > 1 else ''} {shown} missing (trials of a leg must be "
                    f"numbered 1..n without gaps; rows of {key}: {', '.join(str(e.line) for e in rows)})")
        )


def _csv_files(folder: Path) -> list[Path]:
    """CSV files under ``folder`` (recursively), hidden files and folders excepted."""
    found = []
    for root, dirs, files in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        for name in sorted(files):
            if name.lower().endswith(".csv") and not name.startswith("."):
                found.append(Path(root, name))
    return found


def _file_id(path: Path) -> tuple[int, int]:
    st = path.stat()
    return (st.st_dev, st.st_ino)


# --------------------------------------------------------------------------- reading
def read_interchange(folder: str | os.PathLike, *, resample_s: float | None = None) -> Cohort:
    """Validate an interchange folder completely and load it as a :class:`Cohort`.

    Every problem in every file is collected first; if there is any, an
    :class:`InterchangeError` listing all of them is raised.  Trials keep the
    manifest's order; ``Trial.source`` is the manifest's ``file`` value.

    ``resample_s``: put every trial on a uniform grid of that period
    (:func:`~quadshank.data._resample.resample_trial`: anti-aliased, pulses to the nearest
    sample); the recordings' time stamps then need only increase (irregular stamps, another
    period than the manifest's), with no gap beyond 1.5 median steps.
    """
    folder = Path(folder)
    if not folder.exists():
        raise FileNotFoundError(f"{folder}: no such folder")
    if not folder.is_dir():
        raise NotADirectoryError(f"{folder}: not a folder (an interchange folder holds {MANIFEST_NAME})")

    problems: list[Problem] = []
    context = f"{folder}: invalid interchange folder"
    parsed = _read_manifest(folder, problems)
    if parsed is None:
        raise InterchangeError(problems, context)
    entries, has_period, named_in_bad_rows = parsed
    complete = all(e.subject is not None and e.leg is not None and e.trial is not None for e in entries)
    _check_listing(entries, complete, MANIFEST_NAME, problems)

    signals_of: dict[int, dict[str, np.ndarray | None]] = {}
    notes: list[str] = []  # warnings, given once the folder is known to be valid
    seen_files: set[str] = set()
    unstimulated: list[str] = []  # trial files without a stimulation column: pendulum tests
    for i, e in enumerate(entries):
        if e.path is None or e.key in seen_files:
            continue
        seen_files.add(e.key)
        table = _read_table(e.path, e.file, _TRIAL_REQUIRED, _TRIAL_OPTIONAL, problems,
                            alternatives={"stimulation": _STIMULATOR},
                            unknown_hint="a channel quadshank does not read (EMG, a torque, another joint's angle)? "
                                         "Remove the column")
        if table is None:
            continue
        exclude = _parse_float_column(table, "exclude", e.file, problems) if "exclude" in table.columns else None
        excluded = None if exclude is None else exclude == 1
        signals = {
            name: (exclude if name == "exclude" else _parse_float_column(
                table, name, e.file, problems, excluded if name in _MAY_BE_MISSING else None))
            if name in table.columns else None
            for name in _TRIAL_REQUIRED + _TRIAL_OPTIONAL
        }
        signals.update({name: _fill_missing(signals[name]) for name in _MAY_BE_MISSING if signals[name] is not None})
        if not {"stimulation", *_STIMULATOR} & set(table.columns):
            signals["stimulation"] = np.zeros(len(table.rows))
            unstimulated.append(e.file)
        if table.well_formed:
            origin = (
                f"in {MANIFEST_NAME} row {e.line}"
                if has_period
                else f"(the default; {MANIFEST_NAME} has no sampling_period_s column)"
            )
            _check_signals(e.file, table.lines, signals, e.sampling_period_s, origin, problems,
                           uniform=resample_s is None)
            notes += _chargeless_pulses(e.file, table.lines, signals)
            time = signals.get("time_s")
            if e.span_ok and time is not None and time.size and (e.start_s is not None or e.end_s is not None):
                span = _span(time, e.start_s, e.end_s)
                kept = int(np.count_nonzero(span))
                exclude = signals.get("exclude")
                free = kept if exclude is None or exclude.size != span.size else int(np.count_nonzero(span & (exclude != 1)))
                column = "start_s" if e.start_s is not None else "end_s"
                if kept < 2:
                    problems.append(Problem(MANIFEST_NAME, column, e.line,
                                            f"start_s/end_s keep {kept} sample(s) of {e.file} (its time runs from "
                                            f"{seconds_text(time[0])} to {seconds_text(time[-1])} s); at least 2 are needed"))
                elif free < 2:
                    problems.append(Problem(MANIFEST_NAME, column, e.line,
                                            f"start_s/end_s keep {kept} samples of {e.file}, of which {free} not "
                                            "excluded (its column 'exclude'); at least 2 are needed"))
                else:
                    notes += _bounds_outside(e, time)
        signals_of[i] = signals

    listed = {_file_id(e.path) for e in entries if e.path is not None}
    named_in_bad_rows = {_composed(n) for n in named_in_bad_rows}
    for path in _csv_files(folder):
        rel = path.relative_to(folder).as_posix()
        if rel == MANIFEST_NAME:
            continue
        if _file_id(path) not in listed and _composed(rel) not in named_in_bad_rows:
            problems.append(Problem(rel, None, None, f"CSV file not listed in {MANIFEST_NAME}"))

    kept_scales = _read_charge_scale_file(folder, entries, signals_of, problems)
    if problems:
        raise InterchangeError(problems, context)
    if unstimulated:
        notes.insert(0, _unstimulated_note(unstimulated))
    for text in notes:
        warnings.warn(text, DataWarning, stacklevel=2)

    relative = _relative_charges(entries, signals_of)
    scales = {**kept_scales, **_charge_scales(entries, signals_of)}
    trials = []
    for i, e in enumerate(entries):
        s = signals_of[i]
        if i in relative:
            s = {**s, "stimulation": relative[i]}
        whole = Trial.from_signals(  # a derived velocity is derived from the whole recording, then cut
            e.subject,
            e.leg,
            e.trial,
            e.sampling_period_s,
            angle_deg=s["angle_deg"],
            acceleration_deg_s2=s["acceleration_deg_s2"],
            stimulation=s["stimulation"],
            velocity_deg_s=s["velocity_deg_s"],
            time_s=s["time_s"],
            source=e.file,
            exclude=s["exclude"],
        )
        whole = _exclude_glitches(whole, str(folder / e.file))
        trials.append(_exclude_before_release(trim(whole, e.start_s, e.end_s), str(folder / e.file)))
        _warn_cut_twitch(whole, e)
    if resample_s is not None:
        trials = [resample_trial(t, resample_s) for t in trials]
    attrs = {"source": str(folder), "source_format": "interchange"}
    if scales:
        attrs[CHARGE_SCALE_ATTR] = scales
    cohort = mark_checked(Cohort(tuple(trials), attrs))
    _warn_implausible(cohort, [str(folder / e.file) for e in entries])
    _warn_unselectable_subjects(entries)
    _warn_case_twins(entries)
    return cohort


def _unstimulated_note(files: Sequence[str]) -> str:
    """The warning for trial files without a stimulation column, read as pendulum tests."""
    shown = ", ".join(files[:3]) + (f" and {len(files) - 3} more" if len(files) > 3 else "")
    one = len(files) == 1
    return (f"{shown} {'has' if one else 'have'} no column stimulation (nor pulse_width_us or current_mA): read as "
            f"{'a pendulum test' if one else 'pendulum tests'} without pulses, stimulation 0 on every row. Where "
            "pulses were delivered, add the column")


def _chargeless_pulses(file: str, lines: Sequence[int], signals: dict) -> list[str]:
    """Where a trial gives both a stimulator's columns, samples at which one is nonzero and the
    other 0, in words: the charge (width × current) is 0 there, no pulse, which a logger that
    writes the set width on every row or drops a current reading also gives."""
    width, current = (signals.get(c) for c in _STIMULATOR)
    if width is None or current is None or width.size != current.size:
        return []
    found = []
    for column, other, values, others in (("current_mA", "pulse_width_us", current, width),
                                          ("pulse_width_us", "current_mA", width, current)):
        at = np.flatnonzero((values == 0) & (others > 0))
        if at.size:
            i = int(at[0])
            more = f" and at {at.size - 1} more such sample{'s' if at.size > 2 else ''}" if at.size > 1 else ""
            found.append(f"{file}, column {column!r}, row {int(lines[i])}: 0 where {other} is "
                         f"{float(others[i])!r}{more}: a pulse's charge is width × current, so no pulse is read "
                         f"there. Write 0 in both where no pulse was delivered, or the {column} delivered")
    return found


def _bounds_outside(e: _Entry, time: np.ndarray) -> list[str]:
    """A manifest row's ``start_s``/``end_s`` that lie beyond its recording by more than one
    sample, in words: such a bound cuts nothing, and one in other units (ms) or typed for another
    trial looks the same."""
    dt = float(np.median(np.diff(time))) if time.size > 1 else 0.0
    first, last = float(time[0]), float(time[-1])
    found = []
    for name, value, outside in (("start_s", e.start_s, e.start_s is not None and e.start_s < first - dt),
                                 ("end_s", e.end_s, e.end_s is not None and e.end_s > last + dt)):
        if outside:
            found.append(f"{MANIFEST_NAME}, column {name!r}, row {e.line}: {value!r} s lies outside {e.file}'s "
                         f"recording ({first:.6g} to {last:.6g} s) and cuts nothing; a time in other units, or "
                         "for another trial? (leave the cell empty for no bound)")
    return found


def _warn_unselectable_subjects(entries: list[_Entry]) -> None:
    """Warn, once per subject, where a subject's name holds a comma: the commands' ``--legs``
    takes comma-separated leg names, so its legs cannot be named there (the data are read, and
    every leg is used without ``--legs``)."""
    for subject in sorted({e.subject for e in entries if e.subject and "," in e.subject}):
        line = min(e.line for e in entries if e.subject == subject)
        warnings.warn(f"{MANIFEST_NAME} row {line}: subject {subject!r} holds a comma, so its legs cannot be named "
                      "in --legs, which is comma-separated (without --legs every leg is used); rename the subject "
                      "to select its legs", DataWarning, stacklevel=3)


def _warn_case_twins(entries: list[_Entry]) -> None:
    """Warn where two subjects are spelled alike but for case (``TN`` and ``tn``): they are read
    as two, each with its own place in the hierarchy (a leg is ``left`` or ``right``, exactly)."""
    first: dict[str, int] = {}
    for e in entries:
        if e.subject is not None and e.subject not in first:
            first[e.subject] = e.line
    groups: dict[str, list[str]] = {}
    for name in first:
        groups.setdefault(name.casefold(), []).append(name)
    for names in groups.values():
        if len(names) > 1:
            shown = " and ".join(f"{n!r} (row {first[n]})" for n in names)
            warnings.warn(f"{MANIFEST_NAME}: subjects {shown} differ only in case and are read as {len(names)} "
                          "subjects; spell them alike if they are one", DataWarning, stacklevel=3)


def _warn_cut_twitch(whole: Trial, e: _Entry) -> None:
    """Warn where ``start_s`` cuts a trial within :data:`TWITCH_REACH_S` after a pulse: its twitch
    is then in the samples kept, without the pulse that caused it."""
    if e.start_s is None:
        return
    times = whole.time_s[whole.stimulation > 0]
    cut = times[(times < e.start_s) & (times > e.start_s - TWITCH_REACH_S)]
    if cut.size:
        warnings.warn(f"{e.file}: start_s = {e.start_s!r} ({MANIFEST_NAME} row {e.line}) falls "
                      f"{e.start_s - float(cut[-1]):.3g} s after a pulse at time_s = {float(cut[-1]):.6g}: its twitch "
                      "is in the samples kept, without its pulse; start after the twitch, or before the pulse",
                      DataWarning, stacklevel=3)


def _charge(signals: dict[str, np.ndarray | None]) -> np.ndarray:
    """Each sample's pulse charge in µs·mA from a stimulator's columns (a column not given counts as
    1, so pulse width alone or current alone gives a charge in its own unit)."""
    given = [signals[c] for c in _STIMULATOR if signals.get(c) is not None]
    return np.prod(np.abs(given), axis=0) if given else np.zeros(0)


def _relative_charges(entries: Sequence[_Entry], signals_of: dict) -> dict[int, np.ndarray]:
    """``stimulation`` of the trials given as a stimulator's columns: each pulse's charge over the
    largest of its leg (across the leg's trials so given), in (0, 1]."""
    charges = {i: _charge(s) for i, s in signals_of.items() if s.get("stimulation") is None}
    largest: dict[tuple, float] = {}
    for i, q in charges.items():
        key = (entries[i].subject, entries[i].leg)
        largest[key] = max(largest.get(key, 0.0), float(q.max(initial=0.0)))
    _warn_charge_scales(entries, signals_of, charges)
    out = {}
    for i, q in charges.items():
        top = largest[(entries[i].subject, entries[i].leg)]
        out[i] = q / top if top > 0 else np.zeros_like(q)
    return out


#: The cohort attribute that holds, per leg read from a stimulator's columns, the charge that its
#: levels are relative to (:func:`charge_scales`).
CHARGE_SCALE_ATTR = "charge_scale"

#: The unit of a charge made of the stimulator's columns given (one column alone stands for itself).
_CHARGE_UNITS = {("pulse_width_us",): "µs", ("current_mA",): "mA", ("pulse_width_us", "current_mA"): "µs·mA"}


def _charge_scales(entries: Sequence[_Entry], signals_of: dict) -> dict[str, dict]:
    """Per leg whose trials give a stimulator's columns: its largest pulse charge, the columns and
    the charge's unit, what a plan in the same columns needs to become levels (``predict``).  A
    leg whose trials give different columns (pulse width in one, width and current in another)
    has charges in two units and gets no scale."""
    columns: dict[str, set] = {}
    largest: dict[str, float] = {}
    for i, sig in signals_of.items():
        if sig.get("stimulation") is not None:
            continue
        key = leg_key(entries[i].subject, entries[i].leg)
        columns.setdefault(key, set()).add(tuple(c for c in _STIMULATOR if sig.get(c) is not None))
        largest[key] = max(largest.get(key, 0.0), float(_charge(sig).max(initial=0.0)))
    return {key: {"largest_charge": largest[key], "columns": list(cols[0]), "unit": _CHARGE_UNITS[cols[0]]}
            for key, cols in ((k, sorted(v)) for k, v in columns.items())
            if len(cols) == 1 and cols[0] and largest[key] > 0}


def charge_scales(cohort: Cohort) -> dict[str, dict]:
    """Leg -> ``{"largest_charge", "columns", "unit"}`` of the legs read from a stimulator's columns
    (their ``stimulation`` is each pulse's charge over ``largest_charge``), or whose levels a
    folder's :data:`CHARGE_SCALE_NAME` gives it for; empty for levels.  A cohort read back from
    NetCDF holds it as JSON text."""
    value = cohort.attrs.get(CHARGE_SCALE_ATTR)
    if isinstance(value, str):
        value = json.loads(value)
    return dict(value or {})


#: The file beside the manifest that keeps, for legs whose trials give ``stimulation`` levels, the
#: charge those levels are relative to (:func:`charge_scales`): what :func:`write_interchange`
#: writes for a cohort read from a stimulator's columns, so that a conversion loses nothing.
CHARGE_SCALE_NAME = "charge_scale.json"


def _scale_problem(scale) -> str | None:
    """Why ``scale`` is not one leg's ``{"largest_charge", "columns", "unit"}``, or None."""
    if not isinstance(scale, dict) or set(scale) != {"largest_charge", "columns", "unit"}:
        return 'must be {"largest_charge": number, "columns": [...], "unit": text}'
    charge, columns = scale["largest_charge"], scale["columns"]
    if isinstance(charge, bool) or not isinstance(charge, (int, float)) or not math.isfinite(charge) or charge <= 0:
        return f"largest_charge must be a positive number, not {charge!r}"
    if not isinstance(columns, list) or tuple(columns) not in _CHARGE_UNITS:
        return f"columns must be {' or '.join(repr(list(k)) for k in _CHARGE_UNITS)}, not {columns!r}"
    if scale["unit"] != _CHARGE_UNITS[tuple(columns)]:
        return f"unit must be {_CHARGE_UNITS[tuple(columns)]!r} for columns {columns!r}, not {scale['unit']!r}"
    return None


def _read_charge_scale_file(folder: Path, entries: Sequence[_Entry], signals_of: dict,
                            problems: list[Problem]) -> dict[str, dict]:
    """The scales of :data:`CHARGE_SCALE_NAME`, where the folder has one: each for a leg the
    manifest lists whose trials give ``stimulation`` levels (a leg read from a stimulator's
    columns takes its scale from them)."""
    path = folder / CHARGE_SCALE_NAME
    if not path.is_file():
        return {}
    try:
        value = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        problems.append(Problem(CHARGE_SCALE_NAME, None, None, f"not JSON text: {err}"))
        return {}
    if not isinstance(value, dict):
        problems.append(Problem(CHARGE_SCALE_NAME, None, None,
                                "must be a JSON object: leg (subject-leg) -> its largest charge, columns and unit"))
        return {}
    legs = {leg_key(e.subject, e.leg) for e in entries if e.subject is not None and e.leg is not None}
    from_columns = {leg_key(entries[i].subject, entries[i].leg) for i, sig in signals_of.items()
                    if sig.get("stimulation") is None}
    out = {}
    for key, scale in value.items():
        leg = _composed(str(key))
        if leg not in legs:
            why = f"names leg {leg!r}, which {MANIFEST_NAME} does not list"
        elif leg in from_columns:
            why = (f"gives a scale for {leg}, whose trials give a stimulator's columns: their charges set its scale; "
                   "remove the entry")
        else:
            why = _scale_problem(scale)
            why = None if why is None else f"{leg}: {why}"
        if why is None:
            out[leg] = {"largest_charge": float(scale["largest_charge"]), "columns": list(scale["columns"]),
                        "unit": scale["unit"]}
        else:
            problems.append(Problem(CHARGE_SCALE_NAME, None, None, why))
    return out


#: A leg's largest pulse charge this many times its next largest is named: every other pulse's level
#: is its charge over the largest, so one typo (30000 µs for 300) scales them all down.
CHARGE_OUTLIER_RATIO = 5.0


def _warn_charge_scales(entries: Sequence[_Entry], signals_of: dict, charges: dict[int, np.ndarray]) -> None:
    """Warn of a leg whose largest pulse charge stands far above its others (a typo), and of a leg
    whose trials give the stimulation partly as levels and partly as a stimulator's columns (two
    scales that the fit takes for one)."""
    legs: dict[tuple, list[int]] = {}
    for i in signals_of:
        legs.setdefault((entries[i].subject, entries[i].leg), []).append(i)
    for (subject, leg), rows in legs.items():
        name = leg_key(subject, leg)
        given = [i for i in rows if i in charges]
        # a trial without pulses (a pendulum test) has no scale to mix up
        pulsed = [i for i in rows if i not in charges and np.any(signals_of[i]["stimulation"])]
        if given and pulsed:
            levels = ", ".join(entries[i].file for i in pulsed)
            warnings.warn(f"{name}: {', '.join(entries[i].file for i in given)} give the stimulation as a stimulator's "
                          f"columns (levels are charges over the leg's largest), {levels} as levels in [0, 1]: the fit "
                          "takes them for one scale; give every trial of a leg the same way", DataWarning, stacklevel=4)
        pulses = [(float(charges[i][k]), i, int(k)) for i in given for k in np.flatnonzero(charges[i] > 0)]
        if len(pulses) < 2:
            continue
        pulses.sort()
        (second, *_), (top, i, k) = pulses[-2], pulses[-1]
        if top > CHARGE_OUTLIER_RATIO * second:
            time = signals_of[i].get("time_s")
            when = f" at time_s = {seconds_text(time[k])}" if time is not None and time.size > k else ""
            warnings.warn(f"{entries[i].file} ({name}): its largest pulse charge{when} is {top / second:.0f} times the "
                          f"leg's next largest; every pulse's level is its charge over the largest, so all the others "
                          f"fall below {second / top:.2g}: a typo in pulse_width_us or current_mA?", DataWarning,
                          stacklevel=4)


def _span(time: np.ndarray, start_s: float | None, end_s: float | None) -> np.ndarray:
    keep = np.ones(time.size, bool)
    if start_s is not None:
        keep &= time >= start_s
    if end_s is not None:
        keep &= time <= end_s
    return keep


def trim(trial: Trial, start_s: float | None = None, end_s: float | None = None) -> Trial:
    """The samples of ``trial`` with ``start_s <= time_s <= end_s`` (a bound that is None does not
    cut); times keep their values.  What the manifest's ``start_s``/``end_s`` do on reading."""
    if start_s is None and end_s is None:
        return trial
    keep = _span(trial.time_s, start_s, end_s)
    return trial.replace(**{name: getattr(trial, name)[keep] for name in _TRIAL_WRITE_ORDER})


# --------------------------------------------------------------------------- stimulation plans
@dataclasses.dataclass(frozen=True)
class StimulationPlan:
    """A planned stimulation sequence (:func:`read_plan`): per sample either the recruitment level
    (``stimulation``) or a stimulator's settings, the pulse ``charge`` made of ``columns`` as the
    reader makes a trial's (:func:`charge_scales` turns it into a leg's levels)."""

    time_s: np.ndarray
    stimulation: np.ndarray | None
    #: a stimulator's columns as given (``pulse_width_us`` and/or ``current_mA``); empty for levels
    stimulator: dict = dataclasses.field(default_factory=dict)

    @property
    def columns(self) -> tuple[str, ...]:
        return tuple(self.stimulator)

    @property
    def charge(self) -> np.ndarray | None:
        """Each sample's pulse charge (the product of the columns), None for a plan of levels."""
        return _charge(self.stimulator) if self.stimulator else None

    @property
    def unit(self) -> str | None:
        """The charge's unit, None for a plan of levels."""
        return _CHARGE_UNITS[self.columns] if self.stimulator else None

    def levels(self, leg: str, scales: dict[str, dict]) -> np.ndarray:
        """The plan as ``leg``'s recruitment levels: ``stimulation``, or each pulse's charge over the
        largest of the leg's fitted data (``scales``: :func:`charge_scales` of those data)."""
        if not self.stimulator:
            if leg in scales:
                raise ValueError(f"{leg} was fitted on a stimulator's columns ({', '.join(scales[leg]['columns'])}), "
                                 "where a level is a pulse's charge over the leg's largest: give the plan in "
                                 "those columns, not as stimulation")
            return self.stimulation
        scale = scales.get(leg)
        if scale is None:
            raise ValueError(f"the fit holds no charge of {leg} to relate the plan's {', '.join(self.columns)} to: "
                             "its data gave recruitment levels (stimulation), or trials that gave different "
                             "stimulator columns, or the fit was made before fits kept it; give the plan as stimulation")
        if tuple(scale["columns"]) != self.columns:
            raise ValueError(f"the plan gives {', '.join(self.columns)}, {leg}'s data gave "
                             f"{', '.join(scale['columns'])}: a charge in {self.unit} is not one in {scale['unit']}")
        charge = self.charge
        levels = charge / scale["largest_charge"]
        over = np.flatnonzero(levels > 1.0 + 1e-9)
        if over.size:
            i = int(over[0])
            raise ValueError(f"the plan's pulse at {seconds_text(self.time_s[i])} s has a charge of "
                             f"{float(charge[i]):g} {scale['unit']}, above the largest in {leg}'s fitted data "
                             f"({scale['largest_charge']:g} {scale['unit']}), which the fitted recruitment does not "
                             f"reach{f' (and {over.size - 1} more)' if over.size > 1 else ''}")
        return levels


def read_plan(path: str | os.PathLike, sampling_period_s: float) -> StimulationPlan:
    """A planned stimulation sequence, checked like a trial's columns.

    A CSV file with the columns ``time_s`` (uniform, at ``sampling_period_s``, the fitted
    model's period) and either ``stimulation`` (the recruitment level u in [0, 1] of the pulse
    delivered at each sample, 0 when none) or a stimulator's columns, ``pulse_width_us`` and/or
    ``current_mA`` (0 when no pulse), as the trials of the fitted legs gave them.  Every problem
    names file, column and row.
    """
    path = Path(path)
    problems: list[Problem] = []
    context = f"{path}: invalid stimulation plan"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file (a stimulation plan is a CSV with time_s and stimulation, "
                                "or pulse_width_us and/or current_mA)")
    table = _read_table(path, path.name, ("time_s", "stimulation"), _STIMULATOR, problems,
                        alternatives={"stimulation": _STIMULATOR})
    if table is None or "time_s" not in table.columns or not {"stimulation", *_STIMULATOR} & set(table.columns):
        raise InterchangeError(problems, context)
    names = ("time_s", "stimulation", *_STIMULATOR)
    signals = {c: _parse_float_column(table, c, path.name, problems) if c in table.columns else None for c in names}
    if table.well_formed:
        _check_signals(path.name, table.lines, signals, sampling_period_s, "(the fitted model's period)", problems)
    # a plan is written, not recorded: it is put on the fit's grid by whoever writes it, not by convert
    problems = [dataclasses.replace(p, message=p.message.replace(
        "(irregular time stamps? `quadshank convert FOLDER OUT.nc --resample PERIOD_S` puts them on a uniform grid)",
        f"(a plan gives each pulse at a sample of the fit's grid: time_s every {sampling_period_s:g} s)"))
        for p in problems]
    if problems:
        raise InterchangeError(problems, context)
    stimulator = {c: signals[c] for c in _STIMULATOR if signals[c] is not None}
    return StimulationPlan(signals["time_s"], None if stimulator else signals["stimulation"], stimulator)


def read_stimulation_plan(path: str | os.PathLike, sampling_period_s: float) -> tuple[np.ndarray, np.ndarray]:
    """``(time_s, stimulation)`` of a plan of recruitment levels (:func:`read_plan`, which also
    reads a plan in a stimulator's columns)."""
    plan = read_plan(path, sampling_period_s)
    if plan.stimulation is None:
        raise ValueError(f"{path}: the plan gives {', '.join(plan.columns)}, not stimulation levels: read it with "
                         "read_plan, which relates them to a fitted leg's charges")
    return plan.time_s, plan.stimulation


# --------------------------------------------------------------------------- writing
def _usable_source(source: str) -> str | None:
    """``source`` when it is a plain relative ``.csv`` path inside the folder, else ``None``."""
    if not source or "\\" in source:
        return None
    p = PurePosixPath(source)
    if (
        p.is_absolute()
        or str(p) != source
        or any(part in ("..", ".") or part.startswith(".") for part in p.parts)
        or p.suffix.lower() != ".csv"
        or source.lower() == MANIFEST_NAME
    ):
        return None
    return source


def _default_name(t: Trial) -> str:
    return f"{file_stem(t.subject, 'subject')}-{t.leg}-trial{t.trial}.csv"


def _file_names(cohort: Cohort) -> list[str]:
    """The file each trial is written to: its source when usable and unique, else a default name."""
    names: list[str | None] = [None] * len(cohort)
    taken: set[str] = set()  # compared case-insensitively (case-insensitive file systems)
    for i, t in enumerate(cohort.trials):
        src = _usable_source(t.source)
        if src is not None and src.lower() not in taken:
            names[i] = src
            taken.add(src.lower())
    for i, t in enumerate(cohort.trials):
        if names[i] is None:
            base = _default_name(t)
            name, k = base, 2
            while name.lower() in taken:
                name = f"{base[:-4]}-{k}.csv"
                k += 1
            names[i] = name
            taken.add(name.lower())
    return names  # type: ignore[return-value]


def _check_cohort(cohort: Cohort, names: Sequence[str], *, listing: str = MANIFEST_NAME, first_row: int = 2,
                  row_label: str = "row", listing_row_label: str = "row") -> list[Problem]:
    """The validation rules applied to an in-memory cohort, as the written folder would be read.

    ``names`` label each trial's problems and ``listing`` the problems of the trial list
    (the manifest's name and line numbers, or a NetCDF file's trials and samples counted
    from ``first_row``)."""
    problems: list[Problem] = []
    if not cohort.trials:
        problems.append(Problem(listing, None, None, "the cohort has no trials"))
    entries = []
    for i, (t, name) in enumerate(zip(cohort.trials, names)):
        line = i + first_row
        subject = None if _subject_problem(t.subject) else t.subject
        if subject is None:
            problems.append(Problem(listing, "subject", line, _subject_problem(t.subject)))
        leg = t.leg if t.leg in _LEGS else None
        if leg is None:
            problems.append(Problem(listing, "leg", line, _leg_problem(t.leg)))
        trial = t.trial if t.trial >= 1 else None
        if trial is None:
            problems.append(Problem(listing, "trial", line, f"non-positive trial number {t.trial}"))
        said = _period_problem(repr(float(t.sampling_period_s)), float(t.sampling_period_s))
        period = None if said else t.sampling_period_s
        if said:
            problems.append(Problem(listing, "sampling_period_s", line, said))
        entries.append(_Entry(line, subject, leg, trial, name, name, None, period))
    complete = all(e.subject is not None and e.leg is not None and e.trial is not None for e in entries)
    _check_listing(entries, complete, listing, problems)

    for t, e in zip(cohort.trials, entries):
        _check_trial_signals(t, e.file, first_row, e.sampling_period_s, f"of the trial ({row_label} {e.line} of "
                             f"{listing})", problems)
    return [dataclasses.replace(p, row_label=listing_row_label if p.file == listing else row_label) for p in problems]


def _check_trial_signals(t: Trial, file: str, first_row: int, period: float | None, context: str,
                         problems: list[Problem]) -> None:
    """The rules on one trial's signals, its samples counted from ``first_row``."""
    lines = np.arange(first_row, t.n_samples + first_row)
    signals: dict[str, np.ndarray | None] = {}
    for column in _written_columns(t):
        if column == "velocity_deg_s" and not t.velocity_measured:
            continue
        values = getattr(t, column)
        bad = np.flatnonzero(~np.isfinite(values))
        _report_cells(
            problems, file, column, [(int(lines[j]), repr(float(values[j]))) for j in bad],
            "non-finite value {} (NaN and infinity are not allowed)",
        )
        signals[column] = None if bad.size else values
    if t.n_samples == 0:
        problems.append(Problem(file, None, None, "no samples"))
        return
    _check_signals(file, lines, signals, period, context, problems)


def check_cohort(cohort: Cohort) -> Cohort:
    """Refuse a cohort built in Python (``Trial``, ``Trial.from_signals``, ``Trial.replace``,
    ``Cohort``) whose trials break the rules the readers apply to files (data-format.md): a
    non-finite value, a stimulation outside [0, 1], time not increasing at the sampling period,
    a period out of range, a leg other than left or right, a trial number below 1, two
    subjects whose legs share one key, and the rest.  Raises :class:`InterchangeError` listing
    every problem, each naming the leg, the trial, the signal and the sample's index in its
    array (from 0); then warns of what looks implausible (units, signs), as the readers do.

    Identification, evaluation, the screen and the fit call it on the cohort they are given;
    trials read from files or simulated are not checked again.  Returns ``cohort``.
    """
    new = [t for t in cohort.trials if not is_checked(t)]
    if not new:
        return cohort
    problems: list[Problem] = []
    owners: dict[str, tuple[str, str]] = {}
    for t in cohort.trials:  # one key, one (subject, leg): "JM-x" + "left" and "JM" + "x-left" would merge
        other = owners.setdefault(t.key, (t.subject, t.leg))
        if other != (t.subject, t.leg):
            problems.append(Problem(f"{t.key} trial {t.trial}", "subject", None,
                                    f"subject {t.subject!r} with leg {t.leg!r} and subject {other[0]!r} with leg "
                                    f"{other[1]!r} make the same leg {t.key!r}: rename one"))
    for t in new:
        name = f"{t.key} trial {t.trial}"
        said = _subject_problem(t.subject)
        if said:
            problems.append(Problem(name, "subject", None, said))
        if t.leg not in _LEGS:
            problems.append(Problem(name, "leg", None, _leg_problem(str(t.leg))))
        if not is_whole_number(t.trial) or t.trial < 1:
            problems.append(Problem(name, "trial", None, f"trial number {t.trial!r}: trials are numbered 1, 2, ..."))
        period = float(t.sampling_period_s)
        said = _period_problem(repr(period), period)
        if said:
            problems.append(Problem(name, "sampling_period_s", None, said))
        _check_trial_signals(t, name, 0, None if said else period, "of the trial", problems)
    if problems:
        raise InterchangeError([dataclasses.replace(p, row_label="index") for p in problems],
                               "a cohort built in Python breaks the data rules (data-format.md)")
    _warn_implausible(Cohort(tuple(new)), ["built in Python"] * len(new))
    mark_checked(Cohort(tuple(new)))
    return cohort


def _written_columns(trial: Trial) -> list[str]:
    """A trial's columns in a CSV: a derived velocity or acceleration is not written (it is derived again),
    nor an ``exclude`` column that excludes nothing."""
    left_out = {"velocity_deg_s": not trial.velocity_measured, "acceleration_deg_s2": not trial.acceleration_measured,
                "exclude": not trial.exclude.any()}
    return [n for n in _TRIAL_WRITE_ORDER if not left_out.get(n, False)]


def _write_trial_csv(trial: Trial, path: Path) -> None:
    """Write one trial's CSV (velocity only when it was measured); floats as ``repr``, exclude as 0/1."""
    names = _written_columns(trial)
    columns = [list(map(repr, getattr(trial, n).tolist())) if n != "exclude" else
               ["1" if x else "0" for x in trial.exclude] for n in names]
    with open(path, "w", encoding="utf-8", newline="") as fh:
        fh.write(",".join(names) + "\n")
        fh.writelines(",".join(cells) + "\n" for cells in zip(*columns))


def _write_manifest(cohort: Cohort, names: Sequence[str], path: Path) -> None:
    with open(path, "w", encoding="utf-8", newline="") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(_MANIFEST_REQUIRED + ("sampling_period_s",))  # trials are written as cut
        for t, name in zip(cohort.trials, names):
            writer.writerow([t.subject, t.leg, str(int(t.trial)), name, repr(float(t.sampling_period_s))])


def _make_dirs(path: Path, created: list[Path]) -> None:
    """``mkdir -p``, recording the folders that did not exist yet."""
    missing = []
    p = path
    while not p.exists():
        missing.append(p)
        p = p.parent
    for d in reversed(missing):
        d.mkdir()
        created.append(d)


def write_interchange(cohort: Cohort, folder: str | os.PathLike, *, overwrite: bool = False) -> Path:
    """Write ``cohort`` as an interchange folder; returns the folder.

    The cohort is first checked against the same rules as
    :func:`read_interchange` (an :class:`InterchangeError` is raised and
    nothing is written when it would not read back).  Each trial goes to its
    ``source`` name when that is a plain relative ``.csv`` path, otherwise to
    ``{subject}-{leg}-trial{n}.csv``; velocity is written only when it was
    measured.

    A leg read from a stimulator's columns is written as its levels, and the
    charge they are relative to goes to :data:`CHARGE_SCALE_NAME` beside the
    manifest (:func:`charge_scales` of the folder read back is the cohort's).

    ``folder`` must be new or empty unless ``overwrite``; then the manifest,
    the trial files of this cohort and :data:`CHARGE_SCALE_NAME` replace those
    of the same names (one the cohort has no scale for is removed), and nothing
    else in the folder is touched or deleted.  A CSV file already there that the
    new manifest would not list is refused (the folder would not read back):
    nothing is written.

    The write is atomic per file and ordered: every file is first written under
    a temporary hidden name next to its destination and only when all are
    complete are they renamed into place, the manifest last.  A failure
    leaves the folder as it was (a folder created by this call is removed).
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise NotADirectoryError(f"{folder}: exists and is not a folder")
    names = _file_names(cohort)
    problems = _check_cohort(cohort, names)
    scales = {leg: v for leg, v in charge_scales(cohort).items() if leg in cohort.legs}
    problems += [Problem(CHARGE_SCALE_NAME, None, None, f"{leg}: {why}") for leg, v in scales.items()
                 if (why := _scale_problem(v)) is not None]
    if problems:
        raise InterchangeError(problems, f"cannot write {folder} as an interchange folder")
    if folder.is_dir() and any(not p.name.startswith(".") for p in folder.iterdir()):
        if not overwrite:
            raise FileExistsError(
                f"{folder}: the folder is not empty; give a new folder (or --overwrite to replace the manifest "
                "and the trial files of the same names, leaving everything else)")
        written = {PurePosixPath(n).as_posix().lower() for n in names}
        stale = [p.relative_to(folder).as_posix() for p in _csv_files(folder)
                 if p.name != MANIFEST_NAME or p.parent != folder]
        stale = [n for n in stale if n.lower() not in written]
        if stale:
            shown = ", ".join(stale[:5]) + (f" and {len(stale) - 5} more" if len(stale) > 5 else "")
            raise FileExistsError(
                f"{folder}: holds CSV files this cohort does not write ({shown}); the new manifest would not list "
                "them and the folder would not read back: remove them, or give a new folder")

    created: list[Path] = []
    staged: list[tuple[Path, Path]] = []  # (temporary, final)
    try:
        _make_dirs(folder, created)
        for t, name in zip(cohort.trials, names):
            final = folder.joinpath(*PurePosixPath(name).parts)
            _make_dirs(final.parent, created)
            tmp = temp_sibling(final)
            staged.append((tmp, final))
            _write_trial_csv(t, tmp)
        if scales:
            final = folder / CHARGE_SCALE_NAME
            tmp = temp_sibling(final)
            staged.append((tmp, final))
            tmp.write_text(json.dumps(scales, indent=1, ensure_ascii=False) + "\n", encoding="utf-8")
        manifest = folder / MANIFEST_NAME
        tmp = temp_sibling(manifest)
        staged.append((tmp, manifest))
        _write_manifest(cohort, names, tmp)
        for tmp, final in staged:  # the manifest is last
            os.replace(tmp, final)
        if not scales:  # one left by an earlier cohort would give these levels its charges
            (folder / CHARGE_SCALE_NAME).unlink(missing_ok=True)
    except BaseException:
        for tmp, _ in staged:
            tmp.unlink(missing_ok=True)
        for d in reversed(created):
            try:
                d.rmdir()
            except OSError:
                pass
        raise
    return folder


# --------------------------------------------------------------------------- either form
def _is_netcdf_name(path: Path) -> bool:
    return path.suffix.lower() == ".nc"


def read_netcdf(path: str | os.PathLike) -> Cohort:
    """Load a cohort's NetCDF file and check it by the rules of an interchange folder.

    A file that is not a quadshank cohort (another format, truncated, empty) raises an
    :class:`InterchangeError` naming it; so does a cohort that breaks a rule (radians,
    stimulation outside [0, 1], a leg other than left/right, gaps in the trial numbers,
    time not increasing or not uniform, ...), each problem naming the trial, the signal
    and the sample.
    """
    path = Path(path)
    try:
        # the fingerprint is checked after the rules: a file edited elsewhere that breaks one is
        # told which, before it is told that it was edited
        cohort, stored = Cohort.read_netcdf_unchecked(path)
    except Exception as exc:  # noqa: BLE001 - whatever a foreign or damaged file raises, it is not a cohort file
        reason = str(exc).removeprefix(f"{path}: ") or type(exc).__name__
        raise InterchangeError(
            [Problem(path.name, None, None, f"not a readable quadshank cohort file ({reason})")],
            f"{path}: invalid cohort file") from None
    names = [f"{path.name} [{t.key} trial {t.trial}]" for t in cohort.trials]
    problems = _check_cohort(cohort, names, listing=f"{path.name} [trial list]", first_row=1, row_label="sample",
                             listing_row_label="entry")
    if problems:
        raise InterchangeError(problems, f"{path}: invalid cohort file")
    changed = fingerprint_problem(cohort, stored)
    if changed:
        raise InterchangeError([Problem(path.name, None, None, changed)], f"{path}: invalid cohort file")
    _warn_implausible(cohort, [str(path)] * len(cohort))
    return mark_checked(cohort)


def load_cohort(path: str | os.PathLike) -> Cohort:
    """A cohort from an interchange folder or a NetCDF file (``.nc``), validated by the same rules."""
    path = Path(path)
    if path.is_dir():
        return read_interchange(path)
    if path.is_file() and path.name == MANIFEST_NAME:
        return read_interchange(path.parent)
    if path.is_file() and _is_netcdf_name(path):
        return read_netcdf(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or folder")
    raise ValueError(
        f"{path}: not a cohort; expected an interchange folder (with {MANIFEST_NAME}) or a NetCDF file (.nc)"
    )


def convert(src: str | os.PathLike, dst: str | os.PathLike, *, overwrite: bool = False,
            resample_s: float | None = None, repair_artefacts: bool = False) -> Path:
    """Convert between the two forms, losslessly (unless resampled); returns ``dst``.

    An interchange folder becomes a NetCDF file (``dst`` must end in ``.nc``);
    a NetCDF file becomes an interchange folder (``dst`` must not end in
    ``.nc``).  The NetCDF file records the folder as the cohort's source.  An
    existing ``dst`` (a file, or a folder that is not empty) is refused unless
    ``overwrite`` (see :func:`write_interchange` for what that replaces).
    ``resample_s``: every trial resampled to that period on the way
    (:func:`~quadshank.data._resample.resample_trial`).  ``repair_artefacts``: stimulation
    artefacts replaced by a straight line first
    (:func:`~quadshank.data._artefacts.repair_stimulation_artefacts`).
    """
    src, dst = Path(src), Path(dst)
    if src.is_file() and src.name == MANIFEST_NAME:  # the folder named by its manifest, as load_cohort takes it
        src = src.parent
    if src.exists() and dst.exists() and src.resolve() == dst.resolve():
        raise ValueError(f"{dst}: the destination is the source")
    if src.is_dir():
        if not _is_netcdf_name(dst):
            raise ValueError(f"{dst}: an interchange folder converts to a NetCDF file; the name must end in .nc")
        if dst.is_dir():
            raise IsADirectoryError(f"{dst}: is a folder; give the name of the NetCDF file to write")
        if dst.is_relative_to(src) or dst.resolve().is_relative_to(src.resolve()):
            raise ValueError(f"{dst}: inside the data folder {src}; write the NetCDF file elsewhere")
        if dst.exists() and not overwrite:
            raise FileExistsError(f"{dst}: exists; give a new name (or --overwrite to replace it)")
        above = next((p for p in dst.parents if p.exists()), None)
        if above is not None and not above.is_dir():
            raise NotADirectoryError(f"{dst}: {above} is a file, not a folder")
        if not repair_artefacts:
            return read_interchange(src, resample_s=resample_s).save_netcdf(dst)
        cohort = repair_stimulation_artefacts(read_interchange(src))
        return (cohort if resample_s is None else resample_cohort(cohort, resample_s)).save_netcdf(dst)
    if src.is_file() and _is_netcdf_name(src):
        if _is_netcdf_name(dst):
            raise ValueError(f"{dst}: a NetCDF file converts to an interchange folder; give a folder name, not .nc")
        cohort = read_netcdf(src)
        if repair_artefacts:
            cohort = repair_stimulation_artefacts(cohort)
        return write_interchange(cohort if resample_s is None else resample_cohort(cohort, resample_s), dst,
                                 overwrite=overwrite)
    if not src.exists():
        raise FileNotFoundError(f"{src}: no such file or folder")
    raise ValueError(
        f"{src}: cannot convert; expected an interchange folder (with {MANIFEST_NAME}) or a NetCDF file (.nc)"
    )
