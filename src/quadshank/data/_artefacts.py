"""Stimulation artefacts: a recorded signal that jumps at the pulses' own samples.

A stimulator's pulse reaches the sensors' leads as an electrical artefact: the accelerometer (or
the goniometer) reads a spike on the pulse's sample, or on the one after, that is over within a
few milliseconds.  No muscle responds that fast (an electrically stimulated quadriceps' delay is
20-50 ms), so on the samples within :data:`ARTEFACT_REACH_S` of a pulse the shank's true
acceleration and angle continue as before the pulse.  Left in, a spike on every pulse's sample
looks like a twitch that starts at once: the classical identification takes the delay to 0 and
the gain grows by the spike's share of each twitch's sum, and the Bayesian fit does the same.

:func:`stimulation_artefacts` finds such jumps: for each pulse with no other pulse in the
:data:`ARTEFACT_QUIET_BEFORE_S` before it (so that no earlier twitch is starting), the signal
on each sample within reach of the pulse is compared with the straight line through the two
samples before the pulse; the median over the pulses, against the spread of the same statistic
on samples far from any pulse, tells an artefact from noise.  :func:`repair_stimulation_artefacts`
replaces the samples found by a straight line between the samples either side of them (as
``mne.preprocessing.fix_stim_artifact`` does with ``mode="linear"``), on every pulse, and derives
a derived velocity or acceleration again from a repaired angle.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.stats import median_abs_deviation

from ._cohort import Cohort, DataWarning, Trial

__all__ = ["ARTEFACT_REACH_S", "stimulation_artefacts", "repair_stimulation_artefacts"]

#: Samples within this time [s] after a pulse are judged for an artefact (at 10 ms, the pulse's
#: sample and the next; at 1 ms, the ten after it): before any muscle's twitch can begin.
ARTEFACT_REACH_S = 0.01
#: Pulses judged have no other pulse within this time [s] before them: no earlier twitch starts
#: while they are judged, and a train is judged by its first pulse.
ARTEFACT_QUIET_BEFORE_S = 0.1
#: A lag is an artefact's where the median over the pulses of the signal's departure from the
#: line through the two samples before the pulse exceeds this many robust standard deviations
#: of the same departure on samples far from any pulse (its median over 10 pulses carries about
#: 0.4 of them as noise).
ARTEFACT_SD = 3.0
#: Fewest pulses judged for an artefact to be found.
ARTEFACT_MIN_PULSES = 10
#: A spike's tail: the lags after those found whose departure, smaller than the one before it,
#: still exceeds this many robust SDs are the artefact's too (one that decays over a few samples).
#: A departure that grows past the lags found is a rise (a twitch begun before its logged pulse).
ARTEFACT_TAIL_SD = 2.0
#: Lags beyond the reach judged for the artefact's end.
_EXTRA_LAGS = 3
#: The signals judged: those recorded by a sensor (a derived one follows the angle's).
_SIGNALS = ("angle_deg", "acceleration_deg_s2", "velocity_deg_s")


def _lags(sampling_period_s: float) -> int:
    """The samples after a pulse judged, the pulse's own included: at least two."""
    return max(2, int(np.floor(ARTEFACT_REACH_S / sampling_period_s + 1e-9)) + 1)


def _departures(x: np.ndarray, at: np.ndarray, lags: int) -> np.ndarray:
    """``(len(at), lags)``: x at each lag after each index less the line through the two samples
    before it."""
    line = 2 * x[at - 1] - x[at - 2]
    slope = x[at - 1] - x[at - 2]
    return np.stack([x[at + j] - (line + j * slope) for j in range(lags)], axis=1)


def stimulation_artefacts(trial: Trial) -> dict[str, dict]:
    """The measured signals of ``trial`` that jump at its pulses' own samples, before any twitch
    can begin: per signal name, ``kind``, ``lags`` (samples after the pulse, 0 the pulse's own),
    ``size`` (the median departure at each, in the signal's unit), ``pulses`` (how many were
    judged) and ``noise`` (the robust SD the first was judged against).  ``kind`` is
    ``"artefact"`` where the departure does not grow after the lags found (a spike, or one that
    decays over a few samples, whose lags are then included while it decays,
    :data:`ARTEFACT_TAIL_SD`), else ``"early"``: the signal keeps departing, as a twitch does that
    began before its logged pulse (pulses logged after they were delivered).  Empty where nothing
    is found, or where fewer than :data:`ARTEFACT_MIN_PULSES` pulses stand apart enough to be
    judged."""
    dt = trial.sampling_period_s
    lags = _lags(dt)
    span = lags + _EXTRA_LAGS  # the lags after the reach tell a spike from a rise
    before = max(2, int(np.ceil(ARTEFACT_QUIET_BEFORE_S / dt)))
    n = trial.n_samples
    on = trial.stimulation > 0
    pulses = np.flatnonzero(on)
    if pulses.size < ARTEFACT_MIN_PULSES or n < before + span + 2:
        return {}
    # a pulse judged: none other in `before` samples before it nor within its span, nothing excluded
    recent = np.convolve(on.astype(int), np.ones(before + 1, dtype=int))[:n] - on  # pulses in `before` before k
    ahead = np.convolve(on[::-1].astype(int), np.ones(span, dtype=int))[:n][::-1] - on  # in the span after k
    bad = np.convolve(trial.exclude.astype(int), np.ones(span + 2, dtype=int))
    window_bad = bad[span - 1 + np.arange(n)]  # excluded among k-2 .. k+span-1
    judged = pulses[(pulses >= before) & (pulses + span < n)]
    judged = judged[(recent[judged] == 0) & (ahead[judged] == 0) & (window_bad[judged] == 0)]
    if judged.size < ARTEFACT_MIN_PULSES:
        return {}
    # samples far from any pulse, as the reference for the departures' spread
    near = np.convolve(on.astype(int), np.ones(2 * (before + span) + 1, dtype=int), mode="same") > 0
    ref = np.flatnonzero(~near & (window_bad == 0))
    ref = ref[(ref >= 2) & (ref + span < n)]
    if ref.size < 10 * ARTEFACT_MIN_PULSES:
        return {}
    found = {}
    for name in _SIGNALS:
        if name == "acceleration_deg_s2" and not trial.acceleration_measured or \
                name == "velocity_deg_s" and not trial.velocity_measured:
            continue
        x = getattr(trial, name)
        r = _departures(x, ref, span)  # the line's error grows with the lag: each lag its own noise
        noise = median_abs_deviation(r, axis=0, scale="normal")
        if not np.all(noise > 0):
            continue
        size = np.median(_departures(x, judged, span), axis=0)
        beyond = np.abs(size) > ARTEFACT_SD * noise
        hit = np.flatnonzero(beyond[:lags])
        if not hit.size:
            continue
        last = int(hit[-1])
        while last + 1 < span - 1 and abs(size[last + 1]) > ARTEFACT_TAIL_SD * noise[last + 1] \
                and abs(size[last + 1]) < abs(size[last]):
            last += 1  # an artefact that decays over further samples
        # a departure that grows past the lags found is a rise, not a spike
        back = abs(size[last + 1]) < abs(size[last])
        hit = [int(j) for j in range(int(hit[0]), last + 1)] if back else [int(j) for j in hit]
        found[name] = {"kind": "artefact" if back else "early", "lags": hit, "size": [float(size[j]) for j in hit],
                       "pulses": int(judged.size), "noise": float(noise[hit[0]])}
    return found


def artefact_texts(trial: Trial, found: dict | None = None) -> list[str]:
    """:func:`stimulation_artefacts` (``found``, where already found) in words, one per signal, with
    what to do."""
    dt = trial.sampling_period_s
    texts = []
    for name, a in (stimulation_artefacts(trial) if found is None else found).items():
        unit = {"angle_deg": "°", "acceleration_deg_s2": " deg/s²", "velocity_deg_s": " deg/s"}[name]
        where = ", ".join(f"{s:+.3g}{unit} {_lag_words(j, dt)}" for j, s in zip(a["lags"], a["size"]))
        if a["kind"] == "early":
            texts.append(
                f"{name} is already moving away at the pulses' samples and goes on ({where}; the median over "
                f"{a['pulses']} pulses, against a noise of {a['noise']:.2g}{unit}): a twitch that begins before "
                "its pulse? Are the pulses logged later than they were delivered (a latency between the stimulator's "
                "channel and the sensors')? Shift the stimulation column back by that latency")
            continue
        texts.append(
            f"{name} jumps at the pulses, before any muscle can respond: {where} (the median over {a['pulses']} "
            f"pulses, against a noise of {a['noise']:.2g}{unit}). A stimulation artefact? Left in, it reads as a "
            "twitch that starts at once: the delay comes out too short and the gain too large. `quadshank convert "
            "DATA repaired.nc --repair-artefacts` draws a straight line across those samples of every pulse; "
            "excluding them would leave each twitch out")
    return texts


def _lag_words(j: int, dt: float) -> str:
    return "on the pulse's sample" if j == 0 else f"{j} sample{'s' if j > 1 else ''} ({j * dt * 1000:g} ms) after it"


def repair_stimulation_artefacts(data: Trial | Cohort) -> Trial | Cohort:
    """``data`` with the artefacts :func:`stimulation_artefacts` finds replaced: on every pulse, the
    samples from the first lag found to the last are set on the straight line between the
    samples either side of them (runs of such samples from pulses close together are bridged
    as one).  A derived velocity or acceleration is derived again from a repaired angle.  Each
    trial repaired is named in a :class:`~quadshank.data.DataWarning`, and a cohort's attrs
    record them (``artefacts_repaired``); a trial without an artefact is returned as it is.  A
    rise that begins before the pulses (``kind`` ``"early"``) is no artefact and is left."""
    if isinstance(data, Cohort):
        pairs = [_repaired(t) for t in data.trials]
        done = [f"{t.key} trial {t.trial}: {note}" for t, note in pairs if note]
        return Cohort(tuple(t for t, _ in pairs), {**data.attrs, "artefacts_repaired": "; ".join(done) or "none"})
    return _repaired(data)[0]


def _repaired(trial: Trial) -> tuple[Trial, str]:
    """:func:`repair_stimulation_artefacts` of one trial, and what was repaired in words ('' for nothing)."""
    found = {name: a for name, a in stimulation_artefacts(trial).items() if a["kind"] == "artefact"}
    if not found:
        return trial, ""
    pulses = trial.pulse_indices
    n = trial.n_samples
    signals, notes = {}, []
    for name, a in found.items():
        first, last = min(a["lags"]), max(a["lags"])
        mask = np.zeros(n, bool)
        for j in range(first, last + 1):
            at = pulses + j
            mask[at[at < n]] = True
        x = np.array(getattr(trial, name), dtype=float)
        good = np.flatnonzero(~mask)
        x[mask] = np.interp(np.flatnonzero(mask), good, x[good])
        signals[name] = x
        lags = f"sample {first}" if first == last else f"samples {first}-{last}"
        notes.append(f"{name} on {lags} after each of {pulses.size} pulses")
    note = "; ".join(notes)
    warnings.warn(f"{trial.key} trial {trial.trial}" + (f" ({trial.source})" if trial.source else "")
                  + f": stimulation artefact repaired by straight lines: {note}", DataWarning, stacklevel=3)
    repaired = Trial.from_signals(
        trial.subject, trial.leg, trial.trial, trial.sampling_period_s,
        angle_deg=signals.get("angle_deg", trial.angle_deg),
        acceleration_deg_s2=signals.get("acceleration_deg_s2", trial.acceleration_deg_s2)
        if trial.acceleration_measured else None,
        stimulation=trial.stimulation,
        velocity_deg_s=signals.get("velocity_deg_s", trial.velocity_deg_s) if trial.velocity_measured else None,
        time_s=trial.time_s, source=trial.source, exclude=trial.exclude)
    return repaired, note
