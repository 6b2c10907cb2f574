"""Resampling a recording onto another uniform grid (``quadshank convert --resample``).

The models count their delay and their twitch in samples (the delay d in 0 … 10 samples,
the paper's 10 ms grid), so a recording at 1 ms, or with irregular time stamps, is best
brought onto a grid of its own choosing first.  :func:`resample_trial` does that:

1. the new grid runs from the trial's first time stamp in steps of the new period, up to
   its last;
2. the angle, and a measured velocity and acceleration, are put on a uniform grid at the
   recording's own median step (linear interpolation, which irregular stamps need), and,
   when the new period is longer, low-passed by a zero-phase Butterworth filter (order 4,
   cut-off at :data:`ANTI_ALIAS_FRACTION` of the new Nyquist frequency, ``filtfilt``) so
   that nothing above the new Nyquist frequency folds back; then interpolated at the new
   grid's times.  A derived velocity or acceleration is derived again on the new grid;
3. each pulse moves to the nearest sample of the new grid with its level; two pulses that
   would land on one sample are refused (the new period is too long for that train);
4. a new sample is excluded when an excluded sample of the recording lies within half a
   new period of it.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import butter, filtfilt

from ._cohort import MAX_SAMPLING_PERIOD_S, Cohort, Trial, seconds_text

__all__ = ["resample_trial", "resample_cohort", "ANTI_ALIAS_FRACTION", "MAX_STEP_RATIO"]

#: Cut-off of the anti-aliasing filter as a fraction of the new grid's Nyquist frequency.
ANTI_ALIAS_FRACTION = 0.8
#: Irregular time stamps are resampled when no step exceeds this multiple of the median step
#: (a longer gap is samples missing, which interpolation would invent).
MAX_STEP_RATIO = 1.5
#: Most a recording's sampling rate may be raised by resampling: a finer grid interpolates
#: samples that hold nothing new, and a period given in the wrong unit would fill the memory.
MAX_UPSAMPLING = 10.0


def _on_grid(time: np.ndarray, values: np.ndarray, fine: np.ndarray, grid: np.ndarray, period_s: float,
             step: float) -> np.ndarray:
    x = np.interp(fine, time, values)
    if period_s > step * (1 + 1e-9) and fine.size > 15:
        b, a = butter(4, ANTI_ALIAS_FRACTION * (0.5 / period_s), fs=1.0 / step)
        x = filtfilt(b, a, x)
    return np.interp(grid, fine, x)


def resample_trial(trial: Trial, period_s: float) -> Trial:
    """``trial`` on a uniform grid of ``period_s`` seconds (see the module's docs)."""
    if not period_s > 0:
        raise ValueError(f"the new sampling period must be positive, not {period_s!r} s")
    if not period_s <= MAX_SAMPLING_PERIOD_S:
        raise ValueError(f"the new sampling period {period_s!r} s is longer than {MAX_SAMPLING_PERIOD_S:g} s, which "
                         "cannot follow a knee's swing or a twitch (and which no command would read)")
    where = f"{trial.key} trial {trial.trial}" + (f" ({trial.source})" if trial.source else "")
    time = trial.time_s
    steps = np.diff(time)
    if time.size < 2 or not np.all(steps > 0):
        raise ValueError(f"{where}: time must increase from sample to sample to be resampled")
    step = float(np.median(steps))
    if period_s < step / MAX_UPSAMPLING:
        raise ValueError(f"{where}: the new sampling period {period_s:g} s is more than {MAX_UPSAMPLING:g} times shorter "
                         f"than the recording's ({step:.6g} s): a finer grid adds samples and no information "
                         "(is the period in seconds?)")
    long = np.flatnonzero(steps > MAX_STEP_RATIO * step)
    if long.size:
        i = int(long[0])
        raise ValueError(f"{where}, column 'time_s': a gap of {steps[i]:.6g} s from {seconds_text(time[i])} s to "
                         f"{float(time[i + 1])!r} s, more than {MAX_STEP_RATIO:g} times the median step {step:.6g} s: "
                         "samples are missing there, and resampling would invent them")
    grid = time[0] + period_s * np.arange(int(np.floor((time[-1] - time[0]) / period_s + 1e-9)) + 1)
    if grid.size < 2:
        raise ValueError(f"{where}: {time[-1] - time[0]:.6g} s long, shorter than one new period of {period_s:g} s")
    fine = time[0] + step * np.arange(int(np.floor((time[-1] - time[0]) / step + 1e-9)) + 1)

    def signal(name):
        return _on_grid(time, getattr(trial, name), fine, grid, period_s, step)

    pulses = trial.pulse_indices
    slots = np.rint((time[pulses] - time[0]) / period_s).astype(int)
    inside = slots < grid.size
    pulses, slots = pulses[inside], slots[inside]
    clash = np.flatnonzero(np.diff(slots) == 0)
    if clash.size:
        i = int(clash[0])
        raise ValueError(f"{where}: the pulses at {seconds_text(time[pulses[i]])} s and "
                         f"{seconds_text(time[pulses[i + 1]])} s fall on one sample of the new period {period_s:g} s; "
                         "resample to a shorter period")
    stimulation = np.zeros(grid.size)
    stimulation[slots] = trial.stimulation[pulses]
    exclude = np.zeros(grid.size, bool)
    for t in time[trial.exclude]:
        exclude[np.abs(grid - t) < 0.5 * period_s] = True
    return Trial.from_signals(
        trial.subject, trial.leg, trial.trial, period_s,
        angle_deg=signal("angle_deg"),
        acceleration_deg_s2=signal("acceleration_deg_s2") if trial.acceleration_measured else None,
        stimulation=stimulation,
        velocity_deg_s=signal("velocity_deg_s") if trial.velocity_measured else None,
        time_s=grid, source=trial.source, exclude=exclude,
    )


def resample_cohort(cohort: Cohort, period_s: float) -> Cohort:
    """Every trial of ``cohort`` resampled to ``period_s`` (:func:`resample_trial`)."""
    return Cohort(tuple(resample_trial(t, period_s) for t in cohort.trials),
                  {**cohort.attrs, "resampled_to_s": float(period_s)})
