"""Cohort: validated trials of one or more legs, held in memory and as NetCDF.

A :class:`Trial` is one recording of one leg: angle, velocity, acceleration and
stimulation on a uniform time grid.  A :class:`Cohort` is an ordered tuple of
trials with provenance.  The native on-disk form is a single NetCDF file
(xarray, h5netcdf engine) with dims ``(trial, sample)``; shorter trials are
padded with NaN and their length is stored, so the round trip is lossless.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import unicodedata
import weakref
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import xarray as xr
from scipy.signal import savgol_filter

from ..common._arrays import is_whole_number, stretches
from ..common._io import atomic_path

__all__ = [
    "Trial", "Cohort", "derive_velocity", "derive_acceleration", "derivation_settings", "VELOCITY_WINDOW",
    "ACCELERATION_WINDOW_S", "leg_key", "derived_signals",
]  # fmt: skip

#: Savitzky–Golay window (samples) used to derive velocity from the angle at T_s = 10 ms and
#: longer periods; at shorter periods the window spans :data:`VELOCITY_WINDOW_S` instead.
VELOCITY_WINDOW = 7
#: The velocity window's length [s] at periods shorter than 10 ms: counted in samples, 7 samples
#: at 1 ms would raise the velocity's noise tenfold (0.38·s/T_s), and a free run started from
#: it misses a pendulum test's swing by five times the angle's noise.
VELOCITY_WINDOW_S = 0.07
#: Polynomial order of the Savitzky–Golay velocity filter.
VELOCITY_POLYORDER = 2

FORMAT_VERSION = "quadshank-cohort/1"
#: The attribute of a cohort's NetCDF file that holds its recordings' fingerprint, checked on reading.
FINGERPRINT_ATTR = "recordings_fingerprint"
#: Relative difference below which two sampling periods are the same period.
SAME_PERIOD_REL = 1e-6
_SIGNALS = ("time_s", "angle_deg", "velocity_deg_s", "acceleration_deg_s2", "stimulation")


class DataWarning(UserWarning):
    """Recordings that pass the rules but look implausible: a unit or a sign that seems off."""


def seconds_text(t: float) -> str:
    """A time [s] for a message: rounded to the nanosecond, so that 1.15 is not 1.1500000000000001."""
    return repr(round(float(t), 9))


def leg_key(subject: str, leg: str) -> str:
    """The key a leg goes by everywhere: ``"TN-left"``."""
    return f"{subject}-{leg}"


def derive_velocity(angle_deg: np.ndarray, dt: float) -> np.ndarray:
    """Knee angular velocity [deg/s] from the sampled angle [deg], off-line.

    A zero-phase Savitzky–Golay differentiator (quadratic fit over
    :data:`VELOCITY_WINDOW` = 7 samples, 70 ms at T_s = 10 ms; at shorter periods
    :data:`VELOCITY_WINDOW_S`, 70 ms, in samples: 71 at 1 ms).  Being
    non-causal it adds no lag, which is what the paper's off-line derivation
    allows.  The trade-off is bandwidth against noise: for white angle noise of
    standard deviation s the velocity noise is about ``0.38 * s / dt`` (a plain
    central difference gives ``0.71 * s / dt``), while a sinusoid at 5 Hz keeps
    95 % of its amplitude; the 10 ms velocity kick of a twitch is smeared over
    the window.  A causal filter of the same length would lag by 30 ms.
    """

    angle = np.asarray(angle_deg, dtype=float)
    window = _velocity_window(dt)
    if angle.size < window:
        return np.gradient(angle, dt) if angle.size > 1 else np.zeros_like(angle)
    return savgol_filter(angle, window, VELOCITY_POLYORDER, deriv=1, delta=dt, mode="interp")


def _velocity_window(dt: float) -> int:
    """The velocity window in samples at ``dt``: :data:`VELOCITY_WINDOW`, or
    :data:`VELOCITY_WINDOW_S` rounded to an odd number of samples where that is longer."""
    return max(VELOCITY_WINDOW, int(round(VELOCITY_WINDOW_S / dt)) | 1)


#: Length [s] of the Savitzky–Golay window that derives the acceleration from the angle
#: (7 samples at T_s = 10 ms, 35 at 2 ms); see :func:`derive_acceleration`.
ACCELERATION_WINDOW_S = 0.07
#: Polynomial order of that window.
ACCELERATION_POLYORDER = 3


def _acceleration_window(dt: float) -> int:
    """:data:`ACCELERATION_WINDOW_S` in samples at ``dt``: odd, at least 5."""
    return max(5, int(round(ACCELERATION_WINDOW_S / dt)) | 1)


def derive_acceleration(angle_deg: np.ndarray, dt: float) -> np.ndarray:
    """Knee angular acceleration [deg/s²] from the sampled angle [deg], off-line, for
    recordings without an accelerometer.

    A zero-phase Savitzky–Golay second derivative: a cubic fitted over
    :data:`ACCELERATION_WINDOW_S` (rounded to an odd number of samples, at least 5).
    Zero-phase, it adds no lag, so the delay of a twitch is not moved; it smooths a
    twitch's onset over the window and amplifies angle noise (for white noise of standard
    deviation s, by about ``1.2 · s / dt²`` at 7 samples), which the noise model of the fit
    absorbs.  On the simulated cohort the classical estimates from a derived acceleration
    lie within a few per cent of those from the accelerometer (``docs/data-format.md``).
    """
    angle = np.asarray(angle_deg, dtype=float)
    window = _acceleration_window(dt)
    if angle.size < window:
        return np.gradient(np.gradient(angle, dt), dt) if angle.size > 2 else np.zeros_like(angle)
    return savgol_filter(angle, window, ACCELERATION_POLYORDER, deriv=2, delta=dt, mode="interp")


#: The longest sampling period [s] accepted: slower than this cannot follow a knee's swing
#: (about one period a second) or a twitch (about 100 ms); a longer one is usually milliseconds
#: written as seconds.
MAX_SAMPLING_PERIOD_S = 0.1
#: Largest |angle| [deg] that can be a knee's: it turns less than twice round.
ANGLE_LIMIT_DEG = 720.0
#: Values loggers write where a sample is missing.
MISSING_MARKERS = (-9999.0, 9999.0, -999.0, 999.0, -99999.0, 99999.0, -32768.0, 32767.0)


def quiet_mask(stimulation: np.ndarray, quiet: int) -> np.ndarray:
    """True where no pulse was delivered in the ``quiet`` samples up to and including k, and not
    among the first ``quiet`` samples (the release, or a twitch from before the recording)."""
    pulses = (np.asarray(stimulation) > 0).astype(int)
    recent = np.convolve(pulses, np.ones(quiet + 1, dtype=int))[: len(pulses)]
    mask = recent == 0
    mask[:quiet] = False
    return mask


#: A run of excluded samples no longer than this [s] (a glitch, a dropout) is bridged by a straight
#: line before a signal is derived from the angle: derived through it, the samples beside it would
#: carry it, and a free run starting there would start from a velocity the glitch made.
BRIDGED_EXCLUSION_S = 0.03


def _derived_by_stretch(derive, angle: np.ndarray, dt: float, exclude) -> np.ndarray:
    """``derive(angle, dt)``, run apart on each side of the excluded samples whose angle is no
    knee's (``exclude``: True on excluded samples, or None) and on those samples themselves; a
    run of excluded samples of at most :data:`BRIDGED_EXCLUSION_S` between kept ones is bridged
    by a straight line first."""
    if exclude is not None and np.any(exclude):
        exclude = np.asarray(exclude, bool)
        short = [(a, b) for a, b in stretches(exclude)
                 if 0 < a and b < angle.size and (b - a) * dt <= BRIDGED_EXCLUSION_S + 1e-12]
        if short:
            angle, exclude = np.array(angle, dtype=float), exclude.copy()
            for a, b in short:
                angle[a:b] = np.interp(np.arange(a, b), [a - 1, b], [angle[a - 1], angle[b]])
                exclude[a:b] = False  # bridged: no longer broken for the derivation
    broken = np.zeros(angle.size, bool) if exclude is None else np.asarray(exclude, bool) & (
        (np.abs(angle) > ANGLE_LIMIT_DEG) | np.isin(angle, MISSING_MARKERS) | ~np.isfinite(angle))
    if not broken.any():
        return derive(angle, dt)
    out = np.empty_like(angle)
    for mask in (~broken, broken):
        for a, b in stretches(mask):
            out[a:b] = derive(angle[a:b], dt)
    return out


def derivation_settings(sampling_period_s: float) -> dict:
    """How :func:`derive_velocity` and :func:`derive_acceleration` work at this period (recorded by a fit)."""
    return {
        "velocity": {"method": "Savitzky-Golay, zero-phase", "window_samples": _velocity_window(sampling_period_s),
                     "polyorder": VELOCITY_POLYORDER},
        "acceleration": {"method": "Savitzky-Golay, zero-phase", "window_samples": _acceleration_window(sampling_period_s),
                         "polyorder": ACCELERATION_POLYORDER},
    }


def derived_signals(cohort: Cohort) -> dict:
    """The signals of ``cohort`` derived from the angle (no sensor): per signal, how
    (:func:`derivation_settings`) and in which trials (``"JM-left trial 1"``); signals measured in
    every trial are left out."""
    out = {}
    for signal, how in derivation_settings(cohort.sampling_period_s).items():
        trials = [f"{t.key} trial {t.trial}" for t in cohort.trials if not getattr(t, f"{signal}_measured")]
        if trials:
            out[signal] = {**how, "trials": trials}
    return out


#: Trials that passed the data rules: read by a reader, made by the simulator, or checked once by
#: :func:`quadshank.data.check_cohort`.  Held weakly: a trial no longer used is forgotten.
_CHECKED: weakref.WeakSet = weakref.WeakSet()


def mark_checked(cohort: Cohort) -> Cohort:
    """Record ``cohort``'s trials as checked against the data rules; returns ``cohort``."""
    _CHECKED.update(cohort.trials)
    return cohort


def is_checked(trial: Trial) -> bool:
    """Whether ``trial`` was checked against the data rules (:func:`mark_checked`)."""
    return trial in _CHECKED


def _trial_number(trial) -> int:
    """A trial number as an int: a whole number, or a string of digits (as read from a file name)."""
    if isinstance(trial, str) and trial.strip().isdigit():
        return int(trial)
    if not is_whole_number(trial):
        raise TypeError(f"trial must be a whole number (1, 2, ...), not {trial!r}")
    return int(trial)


def _check_names(subject, leg) -> None:
    """Refuse a subject or a leg that is not a string (the data rules, :func:`quadshank.data.check_cohort`,
    say which strings)."""
    for field, value in (("subject", subject), ("leg", leg)):
        if not isinstance(value, str):
            raise TypeError(f"{field} must be a string, not {value!r}")


def _period(period, key: str, trial: int) -> float:
    """The sampling period as a float, refused where it is no positive finite number of seconds."""
    if isinstance(period, (bool, np.bool_)) or not isinstance(period, (int, float, np.integer, np.floating)) \
            or not np.isfinite(period) or period <= 0:
        raise ValueError(f"{key} trial {trial}: sampling_period_s must be a positive number of seconds, not {period!r}")
    return float(period)


def _exclude_mask(exclude, n: int, key: str, trial: int) -> np.ndarray:
    """``exclude`` as a boolean array of ``n`` samples, refused where it holds other values than 0 and 1."""
    values = np.array(exclude)
    if values.shape != (n,):
        raise ValueError(f"{key} trial {trial}: exclude has shape {values.shape}, expected ({n},): "
                         "one 0 or 1 per sample")
    if values.dtype != bool:
        try:
            bad = np.flatnonzero((values != 0) & (values != 1))
        except TypeError:
            bad = np.arange(n)
        if bad.size:
            raise ValueError(f"{key} trial {trial}: exclude must be 0 or 1 (True or False) per sample; "
                             f"index {bad[0]} holds {values[bad[0]].item()!r}")
    return values.astype(bool)


@dataclasses.dataclass(frozen=True, eq=False)
class Trial:
    """One recording of one leg on a uniform grid of ``sampling_period_s``.

    Units: angle [deg] (0 = shank at rest, positive = extension), velocity
    [deg/s], acceleration [deg/s²], stimulation = recruitment level u in [0, 1]
    of the pulse delivered at that sample (0 when none).  ``exclude`` marks
    samples left out of every comparison with the model (a release, a spasm, a
    sensor artefact): the likelihood, the classical identification and J skip
    them, while the model still runs through them (None: nothing excluded).
    """

    subject: str
    leg: str
    trial: int
    sampling_period_s: float
    time_s: np.ndarray
    angle_deg: np.ndarray
    velocity_deg_s: np.ndarray
    acceleration_deg_s2: np.ndarray
    stimulation: np.ndarray
    velocity_measured: bool = True
    source: str = ""
    acceleration_measured: bool = True
    exclude: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "trial", _trial_number(self.trial))
        _check_names(self.subject, self.leg)
        # one spelling of a name: 'ë' typed, and 'e' + '¨' as some file systems store it, are one subject
        object.__setattr__(self, "subject", unicodedata.normalize("NFC", self.subject))
        object.__setattr__(self, "sampling_period_s", _period(self.sampling_period_s, self.key, self.trial))
        n = np.shape(self.time_s)[0] if np.ndim(self.time_s) else -1
        for name in _SIGNALS:
            # a copy the trial alone holds, read-only: a frozen trial's signals cannot change under a
            # cohort built from it, or under the fingerprint a fit recorded of them
            arr = np.array(getattr(self, name), dtype=float)
            if arr.shape != (n,):
                raise ValueError(f"{self.key} trial {self.trial}: {name} has shape {arr.shape}, expected ({max(n, 0)},): "
                                 "each signal is one value per sample")
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        exclude = np.zeros(n, bool) if self.exclude is None else _exclude_mask(self.exclude, n, self.key, self.trial)
        exclude.setflags(write=False)
        object.__setattr__(self, "exclude", exclude)

    @property
    def key(self) -> str:
        return leg_key(self.subject, self.leg)

    @property
    def n_samples(self) -> int:
        return len(self.time_s)

    @property
    def pulse_indices(self) -> np.ndarray:
        return np.flatnonzero(self.stimulation > 0)

    @classmethod
    def from_signals(
        cls,
        subject: str,
        leg: str,
        trial: int,
        sampling_period_s: float,
        angle_deg,
        acceleration_deg_s2,
        stimulation,
        velocity_deg_s=None,
        time_s=None,
        source: str = "",
        exclude=None,
    ) -> Trial:
        """Build a trial, deriving the velocity and the acceleration from the angle when they
        are not given (None); ``stimulation`` None is a pendulum test, no pulses.  The
        derivation runs through excluded samples, whose angle is
        usually a real movement (a release, a spasm), except where an excluded angle is no
        knee's (beyond :data:`ANGLE_LIMIT_DEG` or one of :data:`MISSING_MARKERS`): there it
        runs on each side apart, so that the marker does not reach the kept samples beside it
        through the filter's window."""
        trial = _trial_number(trial)
        _check_names(subject, leg)
        sampling_period_s = _period(sampling_period_s, leg_key(subject, leg), trial)
        angle = np.asarray(angle_deg, dtype=float)
        if angle.ndim != 1:
            raise ValueError(f"{leg_key(subject, leg)} trial {trial}: angle_deg has shape {angle.shape}; "
                             "give one value per sample (a 1-D array)")
        if exclude is not None:
            exclude = _exclude_mask(exclude, angle.size, leg_key(subject, leg), trial)
        if time_s is None:
            time_s = np.arange(angle.size) * sampling_period_s
        measured = velocity_deg_s is not None
        if not measured:
            velocity_deg_s = _derived_by_stretch(derive_velocity, angle, sampling_period_s, exclude)
        accelerometer = acceleration_deg_s2 is not None
        if not accelerometer:
            acceleration_deg_s2 = _derived_by_stretch(derive_acceleration, angle, sampling_period_s, exclude)
        return cls(
            subject=subject,
            leg=leg,
            trial=trial,
            sampling_period_s=sampling_period_s,
            time_s=np.asarray(time_s, dtype=float),
            angle_deg=angle,
            velocity_deg_s=np.asarray(velocity_deg_s, dtype=float),
            acceleration_deg_s2=np.asarray(acceleration_deg_s2, dtype=float),
            stimulation=np.zeros(angle.size) if stimulation is None else np.asarray(stimulation, dtype=float),
            velocity_measured=measured,
            source=source,
            acceleration_measured=accelerometer,
            exclude=exclude,
        )

    def replace(self, **changes) -> Trial:
        """A copy with ``changes``.  A velocity or an acceleration derived from the angle (not
        measured) is derived again where the angle, the period or the excluded samples change
        and it is not given: the old one would be the old angle's."""
        if {"angle_deg", "sampling_period_s", "exclude"} & set(changes):
            angle = np.asarray(changes.get("angle_deg", self.angle_deg), dtype=float)
            period = float(changes.get("sampling_period_s", self.sampling_period_s))
            exclude = changes.get("exclude", self.exclude)
            for name, derive, measured in (("velocity_deg_s", derive_velocity, "velocity_measured"),
                                           ("acceleration_deg_s2", derive_acceleration, "acceleration_measured")):
                if name not in changes and not changes.get(measured, getattr(self, measured)):
                    changes[name] = _derived_by_stretch(derive, angle, period, exclude)
        return dataclasses.replace(self, **changes)


@dataclasses.dataclass(frozen=True, eq=False)
class Cohort:
    """An ordered collection of trials with provenance (free-form attributes)."""

    trials: tuple[Trial, ...]
    attrs: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        if isinstance(self.trials, Trial):
            raise TypeError("Cohort takes a sequence of trials; one trial is Cohort((trial,))")
        object.__setattr__(self, "trials", tuple(self.trials))
        odd = [t for t in self.trials if not isinstance(t, Trial)]
        if odd:
            raise TypeError(f"Cohort takes a sequence of Trial, not {type(odd[0]).__name__} ({odd[0]!r:.60})")
        if not isinstance(self.attrs, dict):
            raise TypeError(f"attrs must be a dict, not {type(self.attrs).__name__}")
        seen = set()
        for t in self.trials:
            ident = (t.subject, t.leg, t.trial)
            if ident in seen:
                raise ValueError(f"duplicated trial {t.key} trial {t.trial}")
            seen.add(ident)

    def __iter__(self) -> Iterator[Trial]:
        return iter(self.trials)

    def __len__(self) -> int:
        return len(self.trials)

    @property
    def legs(self) -> tuple[str, ...]:
        """Leg keys in order of first appearance."""
        return tuple(dict.fromkeys(t.key for t in self.trials))

    @property
    def sampling_period_s(self) -> float:
        """The trials' common sampling period [s]; a ``ValueError`` naming the periods when they differ."""
        periods = sorted({t.sampling_period_s for t in self.trials})
        if not periods:
            raise ValueError("the cohort has no trials, so no sampling period")
        if periods[-1] - periods[0] > SAME_PERIOD_REL * periods[0]:
            where = ", ".join(f"{t.key} trial {t.trial}" + (f" ({t.source})" if t.source.lower().endswith(".csv") else "")
                              + f": {t.sampling_period_s * 1000:g} ms" for t in self.trials)
            raise ValueError(f"the trials are sampled at different periods ({where}); one model runs at one period: "
                             "`quadshank convert DATA OUT.nc --resample PERIOD_S` puts every trial on one")
        return periods[0]

    def trials_of(self, leg: str) -> tuple[Trial, ...]:
        return tuple(sorted((t for t in self.trials if t.key == leg), key=lambda t: t.trial))

    def get(self, leg: str, trial: int) -> Trial:
        for t in self.trials:
            if t.key == leg and t.trial == int(trial):
                return t
        if leg in self.legs:
            have = ", ".join(str(t.trial) for t in self.trials_of(leg))
            raise KeyError(f"no trial {trial} for leg {leg}; its trials: {have}")
        raise KeyError(f"no trial {trial} for leg {leg}; legs present: {', '.join(self.legs)}")

    def fingerprint(self, legs: Sequence[str] | None = None, trials: Sequence[int] | None = None) -> str:
        """A hash of the recordings of the given legs and trials (all by default): their keys,
        sampling periods and every signal, bit for bit, in leg and trial order.  A fit records
        it, and the commands that read the fit refuse data with another."""
        h = hashlib.sha256()
        chosen = sorted((t for t in self.select(legs, trials).trials), key=lambda t: (t.key, t.trial))
        for t in chosen:
            h.update(f"{t.key}|{t.trial}|{float(t.sampling_period_s)!r}|{t.velocity_measured}|"
                     f"{t.acceleration_measured}".encode())
            for name in _SIGNALS:
                h.update(np.ascontiguousarray(getattr(t, name), dtype=np.float64).tobytes())
            if t.exclude.any():  # recordings without excluded samples hash as they always did
                h.update(b"exclude" + np.packbits(t.exclude).tobytes())
        return h.hexdigest()[:16]

    def select(self, legs: Sequence[str] | None = None, trials: Sequence[int] | None = None) -> Cohort:
        """A sub-cohort with only the given legs and/or trial numbers (a single leg or number is taken as one)."""
        legs = (legs,) if isinstance(legs, str) else legs
        trials = (trials,) if is_whole_number(trials) else trials
        if legs is not None:
            missing = [leg for leg in legs if leg not in self.legs]
            if missing:
                raise KeyError(f"legs not in cohort: {', '.join(missing)}; present: {', '.join(self.legs)}")
        keep = tuple(
            t
            for t in self.trials
            if (legs is None or t.key in legs) and (trials is None or t.trial in trials)
        )
        return Cohort(keep, dict(self.attrs))

    # ---------------------------------------------------------------- xarray / NetCDF
    def to_dataset(self) -> xr.Dataset:
        n_max = max((t.n_samples for t in self.trials), default=0)
        data = {}
        for name in _SIGNALS:
            arr = np.full((len(self.trials), n_max), np.nan)
            for i, t in enumerate(self.trials):
                arr[i, : t.n_samples] = getattr(t, name)
            data[name] = (("trial", "sample"), arr)
        exclude = np.zeros((len(self.trials), n_max), np.int8)
        for i, t in enumerate(self.trials):
            exclude[i, : t.n_samples] = t.exclude
        data["exclude"] = (("trial", "sample"), exclude)
        coords = {
            "subject": ("trial", np.array([t.subject for t in self.trials], dtype=object)),
            "leg": ("trial", np.array([t.leg for t in self.trials], dtype=object)),
            "trial_number": ("trial", np.array([t.trial for t in self.trials], dtype=np.int64)),
            "sampling_period_s": ("trial", np.array([t.sampling_period_s for t in self.trials], dtype=float)),
            "n_samples": ("trial", np.array([t.n_samples for t in self.trials], dtype=np.int64)),
            "velocity_measured": ("trial", np.array([t.velocity_measured for t in self.trials], dtype=np.int8)),
            "acceleration_measured": ("trial", np.array([t.acceleration_measured for t in self.trials], dtype=np.int8)),
            "source": ("trial", np.array([t.source for t in self.trials], dtype=object)),
        }
        ds = xr.Dataset(data, coords=coords)
        units = {
            "time_s": "s",
            "angle_deg": "deg",
            "velocity_deg_s": "deg/s",
            "acceleration_deg_s2": "deg/s^2",
            "stimulation": "1",
            "exclude": "1",
        }
        for name, unit in units.items():
            ds[name].attrs["units"] = unit
        ds.attrs.update({k: _attr_value(v) for k, v in self.attrs.items()})
        ds.attrs["format"] = FORMAT_VERSION
        return ds

    @classmethod
    def from_dataset(cls, ds: xr.Dataset) -> Cohort:
        trials = []
        for i in range(ds.sizes["trial"]):
            n = int(ds["n_samples"].values[i])
            sig = {name: np.asarray(ds[name].values[i, :n], dtype=float) for name in _SIGNALS}
            trials.append(
                Trial(
                    subject=str(ds["subject"].values[i]),
                    leg=str(ds["leg"].values[i]),
                    trial=int(ds["trial_number"].values[i]),
                    sampling_period_s=float(ds["sampling_period_s"].values[i]),
                    velocity_measured=bool(ds["velocity_measured"].values[i]),
                    # files written before angle-only recordings were read had an accelerometer
                    acceleration_measured=bool(ds["acceleration_measured"].values[i])
                    if "acceleration_measured" in ds else True,
                    source=str(ds["source"].values[i]),
                    # files written before samples could be excluded have no such variable
                    exclude=np.asarray(ds["exclude"].values[i, :n]) != 0 if "exclude" in ds else None,
                    **sig,
                )
            )
        attrs = {k: v for k, v in ds.attrs.items() if k not in ("format", FINGERPRINT_ATTR)}
        return cls(tuple(trials), attrs)

    def save_netcdf(self, path: str | os.PathLike) -> Path:
        """Write the cohort to ``path`` atomically (temporary file, then rename), with the
        recordings' :meth:`fingerprint`, which :meth:`load_netcdf` checks."""
        ds = self.to_dataset()
        ds.attrs[FINGERPRINT_ATTR] = self.fingerprint()
        with atomic_path(path) as tmp:
            ds.to_netcdf(tmp, engine="h5netcdf")
        return Path(path)

    @classmethod
    def load_netcdf(cls, path: str | os.PathLike) -> Cohort:
        """The cohort of ``path``, refused where its recordings differ from those it was written
        with (:meth:`save_netcdf`, :func:`fingerprint_problem`)."""
        cohort, stored = cls.read_netcdf_unchecked(path)
        problem = fingerprint_problem(cohort, stored)
        if problem:
            raise ValueError(f"{path}: {problem}")
        return cohort

    @classmethod
    def read_netcdf_unchecked(cls, path: str | os.PathLike) -> tuple[Cohort, str | None]:
        """The cohort of ``path`` and the recordings' fingerprint it was written with (None: a file
        written without one), not compared: :func:`quadshank.data.read_netcdf` checks the rules first."""
        path = Path(path)
        with xr.open_dataset(path, engine="h5netcdf") as ds:
            if ds.attrs.get("format") != FORMAT_VERSION:
                raise ValueError(
                    f"{path}: not a quadshank cohort file (attribute 'format' is "
                    f"{ds.attrs.get('format')!r}, expected {FORMAT_VERSION!r})"
                )
            stored = ds.attrs.get(FINGERPRINT_ATTR)
            return cls.from_dataset(ds.load()), None if stored is None else str(stored)


def fingerprint_problem(cohort: Cohort, stored) -> str | None:
    """Why ``cohort``, read from a NetCDF file that was written with the fingerprint ``stored``,
    cannot be trusted, or None.  NetCDF keeps no checksum of its values: bytes changed on a disk or
    in a copy read back as other numbers, silently, and the fingerprint written with them tells.
    A file written without one (None) is read as it is."""
    if stored is None or str(stored) == cohort.fingerprint():
        return None
    return (f"the recordings read differ from those the file was written with (fingerprint {cohort.fingerprint()}, "
            f"written {stored}): the file is damaged, or was edited by another program. Convert it again from its "
            f"source; to keep an edit, delete the file's attribute {FINGERPRINT_ATTR!r}")


def _attr_value(v):
    """NetCDF attributes hold numbers and strings; anything else is stored as its JSON text."""
    if isinstance(v, (str, int, float, np.integer, np.floating)):
        return v

    return json.dumps(v)
