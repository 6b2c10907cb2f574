"""Classical identification as the paper did it (section III-D, eqs. 8–11).

Per leg, from the identification trial (trial 1 by default):

1. **Passive system** (the paper took it from its ref. [16]; here it is
   identified from the same data).  On *quiet* samples, where no pulse was
   delivered in the preceding 350 ms (35 samples at the paper's 10 ms: the
   longest delay and a twitch, so no twitch can be active) and the knee is
   no further extended than +60° (the top of the paper's operating range,
   beyond which a real knee meets the end of its range), the measured
   acceleration obeys eq. (8) with M = 0:
   ``φ̈ = -D'·φ̇ - G'·sin φ + k1'·(exp(-k2·φ) - 1)``.  This is linear in
   (D', G', k1') for fixed k2: k2 is scanned on a log grid (variable
   projection), then all four are refined by bounded nonlinear least squares.
2. **Equivalent acceleration** M/I by eq. (8) on every sample.
3. **Isolated twitches**: pulses with no other pulse in the 250 ms before
   and the 500 ms after (an epoch of 250 ms, 25 samples at 10 ms, followed by
   250 quiet ms).  The windows are counted in time, so that at any sampling
   period an epoch holds the whole twitch and a quiet sample none.
4. **Model 1** (eq. 9): G'_1 = Σ M/I over all epochs / Σ u.
5. **Model 2** (eq. 10): DARMA(2, 2) with a second-order whitening filter on
   the residual, fitted by generalised (extended) least squares over all epochs
   for every delay d in 0..10; the delay with the smallest residual is the
   delay of all three models, as in the paper.
6. **Model 3** (eq. 11): the integrated twitch responses T_i = Σ_{25} M/I are
   fitted by Levenberg–Marquardt to G'_2·(1 + γ_angle·φ)·(1 + γ_velocity·φ̇)
   with φ, φ̇ taken d samples after each pulse.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import least_squares
from scipy.stats import median_abs_deviation

from ..common._arrays import stretches
from ..common._io import nulls_as_nan
from ..common._progress import progress_bar
from ..common._results import Result
from ..data._cohort import SAME_PERIOD_REL, Cohort, Trial, derivation_settings, quiet_mask
from ..data._interchange import DataWarning, check_cohort, pulse_runs
from ..data._paper import MAX_DELAY, SAMPLING_PERIOD_S, TWITCH_REACH_S, TWITCH_SAMPLES
from ..model._likelihood import TWITCH_S, twitch_window
from ..model._model import Model, equivalent_acceleration, paper_model, passive_effects, simulate_angles

__all__ = [
    "LegIdentification",
    "PassiveIdentification",
    "passive_model",
    "identify_passive",
    "identify_passive_free_run",
    "free_run_segments",
    "PASSIVE_OBJECTIVES",
    "PASSIVE_GRAVITY_REL_SE",
    "passive_separated",
    "isolated_twitches",
    "identify_leg",
    "identify_cohort",
    "fit_darma",
    "IdentificationError",
    "DelayRangeWarning",
    "DelayRangeError",
    "check_delay_range",
    "Identification",
    "models_from_summary",
    "load_identification",
]


def quiet_samples(sampling_period_s: float) -> int:
    """Samples after a pulse during which its twitch may still act: 350 ms, the paper's longest
    delay (100 ms) and twitch (250 ms), and at least the longest delay considered (counted in
    samples) and 250 ms (:func:`quadshank.model._likelihood.twitch_window`); 35 at 10 ms.  A
    muscle's delay is a time: at 2 ms the 10 samples the models consider reach 20 ms, and a
    43-ms delay would put the end of its twitch among the quiet samples."""
    return max(twitch_window(sampling_period_s), int(round(TWITCH_REACH_S / sampling_period_s)))


def twitch_epoch(sampling_period_s: float) -> int:
    """Samples of the classical twitch epoch: 250 ms (the paper's 25 samples of 10 ms)."""
    return max(1, int(round(TWITCH_S / sampling_period_s)))

#: Highest knee angle [deg] of the samples used for the passive system (the paper's operating range ends at +60°).
PASSIVE_MAX_ANGLE_DEG = 60.0
#: Fewest isolated twitches needed for a meaningful identification.
MIN_TWITCHES = 8
#: Fewest samples (quiet, at most :data:`PASSIVE_MAX_ANGLE_DEG` extended, not excluded) the
#: passive system is identified from: 2 s at 10 ms, a swing or two.
MIN_PASSIVE_SAMPLES = 200
#: What the passive identification fits: the measured acceleration (equation error, eq. 8 on
#: each quiet sample) or the angle of a free run (output error), on pendulum tests only.
PASSIVE_OBJECTIVES = ("acceleration", "angle")
#: Shortest stretch of usable samples [s] a free run is compared on.
FREE_RUN_MIN_S = 1.0
#: Largest |gravity angle| [deg] an identified gravity offset is taken at face value: the
#: vertical of a seated knee lies near the angle's zero (the effect's prior: 0 ± 10°).
PLAUSIBLE_GRAVITY_ANGLE_DEG = 45.0
#: A pendulum whose free runs miss the swings by more than this share of the swing's spread (the
#: standard deviation of the angle compared) is named: those trials may not be pendulum tests.
POOR_SWING_SHARE = 0.3
#: Largest relative standard error of G' at which the passive system counts as identified.
#: Over the quiet samples the gravity term -G'·sin φ and the elasticity k1'·(exp(-k2·φ) - 1)
#: are nearly proportional (both about linear in φ within the operating range), and only the
#: swing's larger angles tell them apart: where the data cannot, G', k1' and k2 trade along
#: that valley (G' a tenth of a shank's and k1' a hundred times its elasticity, with the same
#: residual).  A shank's G' is known within a few per cent from its mass and length, so a
#: spread of 10 % already says that the data did not separate the two.  The standard errors
#: come from the least squares' Jacobian and the residuals' correlation time.
PASSIVE_GRAVITY_REL_SE = 0.1


#: An identified delay [s] shorter than this is no muscle's (an electrically stimulated quadriceps'
#: is 20-50 ms): a twitch that seems to begin at its pulse is warned of.
SHORTEST_MUSCLE_DELAY_S = 0.015

#: Shortest longest-delay [s] the delays considered (0 … MAX_DELAY samples) should reach: the
#: paper's delays were 40–50 ms.
SHORTEST_DELAY_RANGE_S = 0.06


#: Longest-delay reach [s] below which a model with a muscle is refused: a stimulated
#: quadriceps' delay is 25–50 ms, and a model whose delays end before it puts the twitch's onset
#: at a wrong sample with no sign of it (at 1 ms delays of 31 and 27 ms, simulated, came out at 6 and 4 ms).
SHORTEST_MUSCLE_DELAY_RANGE_S = 0.03


class DelayRangeWarning(DataWarning):
    """The data's sampling period makes the delays considered (0 … 10 samples) too short."""


class DelayRangeError(ValueError):
    """The data's sampling period makes the delays considered too short for a model with a muscle."""


def check_delay_range(sampling_period_s: float, muscle: bool = False, warn: bool = True) -> None:
    """Warn (``warn``) when MAX_DELAY samples at ``sampling_period_s`` reach less than
    :data:`SHORTEST_DELAY_RANGE_S`: the models count their delay (and the twitch) in samples.
    With ``muscle`` (a model with a muscle, or data with pulses to identify one from), refuse
    (:class:`DelayRangeError`) where they reach less than :data:`SHORTEST_MUSCLE_DELAY_RANGE_S`."""
    reach = MAX_DELAY * sampling_period_s
    if muscle and reach < SHORTEST_MUSCLE_DELAY_RANGE_S - 1e-12:
        raise DelayRangeError(
            f"at a sampling period of {sampling_period_s * 1000:g} ms the delays considered reach {MAX_DELAY} samples "
            f"= {reach * 1000:g} ms, short of a stimulated muscle's delay (25-50 ms): the model would put the twitch's "
            "onset at a wrong sample. Resample the recordings first, e.g. `quadshank convert DATA data.nc --resample "
            "0.01`; pendulum tests (no pulses, `--model passive`) are modelled at any period")
    if warn and reach < SHORTEST_DELAY_RANGE_S:
        warnings.warn(
            f"at a sampling period of {sampling_period_s * 1000:g} ms the delays considered reach {MAX_DELAY} samples "
            f"= {reach * 1000:g} ms, shorter than a muscle's delay may be (the paper's: 40-50 ms); resample the "
            "recordings, e.g. `quadshank convert DATA data.nc --resample 0.01`", DelayRangeWarning, stacklevel=2)


class IdentificationError(ValueError):
    """The data do not allow the identification (too few twitches or quiet samples)."""


@dataclasses.dataclass(frozen=True)
class LegIdentification:
    """Everything the classical identification found for one leg."""

    leg: str
    trial: int
    passive: dict
    passive_rms_residual: float
    n_quiet: int
    delay: int
    delay_residuals: np.ndarray  # residual mean square of model 2 per d = 0..MAX_DELAY
    models: dict  # "model1"/"model2"/"model3" -> Model
    whitening: dict  # c1, c2 of eq. (10)
    pulses: np.ndarray  # isolated twitch pulse indices
    integrated: np.ndarray  # T_i = Σ M/I over each epoch, per unit u
    angle_at_d: np.ndarray
    velocity_at_d: np.ndarray
    g1_std: float  # std of the per-twitch integrated response (Table I)
    rms_error_pct: dict  # Table IV: model1 / model3 RMS error of T as % of G'_1
    passive_trials: tuple = ()  # trials without pulses the passive system came from (empty: the quiet samples of `trial`)
    passive_objective: str = "acceleration"  # what the passive system was fitted to (PASSIVE_OBJECTIVES)
    passive_se: dict = dataclasses.field(default_factory=dict)  # standard errors of `passive` (none: not estimated)

    def summary(self) -> dict:
        return {
            "delay_samples": int(self.delay),
            "identification_trial": int(self.trial),
            "passive_trials": [int(t) for t in self.passive_trials],
            "passive_objective": self.passive_objective,
            "n_isolated_twitches": int(len(self.pulses)),
            "passive": {k: float(v) for k, v in self.passive.items()},
            "passive_se": {k: float(v) for k, v in self.passive_se.items()},
            **{name: m.flat_params() for name, m in self.models.items() if name != "passive"},
            "model2_whitening": {k: float(v) for k, v in self.whitening.items()},
            "G1_std": float(self.g1_std),
            "rms_error_pct": {k: float(v) for k, v in self.rms_error_pct.items()},
        }


@dataclasses.dataclass(frozen=True)
class PassiveIdentification:
    """A leg whose identification trial holds no pulse (a pendulum test): the passive system
    alone, identified from the leg's trials without pulses.  Its one model, ``"passive"``, is
    the pendulum of eq. (8) without a muscle."""

    leg: str
    trial: int
    passive: dict
    passive_rms_residual: float
    n_quiet: int
    passive_trials: tuple
    sampling_period_s: float
    passive_objective: str = "acceleration"  # what the passive system was fitted to (PASSIVE_OBJECTIVES)
    passive_se: dict = dataclasses.field(default_factory=dict)  # standard errors of `passive` (none: not estimated)

    @property
    def models(self) -> dict:
        return {"passive": passive_model(self.passive, self.sampling_period_s)}

    def summary(self) -> dict:
        return {
            "identification_trial": int(self.trial),
            "passive_only": True,
            "passive_trials": [int(t) for t in self.passive_trials],
            "passive_objective": self.passive_objective,
            "passive": {k: float(v) for k, v in self.passive.items()},
            "passive_se": {k: float(v) for k, v in self.passive_se.items()},
            "n_quiet_samples": int(self.n_quiet),
        }


def passive_model(passive: dict, sampling_period_s: float) -> Model:
    """The passive pendulum of eq. (8) as a model: model 1 with no muscle (gain 0), named ``passive``."""
    model = paper_model(1, passive_effects(**passive), sampling_period_s=sampling_period_s).with_params(gain=0.0)
    return dataclasses.replace(model, name="passive")


# ============================================================================ passive


def _passive_columns(angle, velocity, k2, gravity_offset: bool = False):
    # acc = D*(-v) + G*(-sin) + k1*(exp(-k2 phi) - 1); about a gravity angle g,
    # -G sin(phi - g) = -(G cos g) sin(phi) + (G sin g) cos(phi): one more column
    cols = [-velocity, -np.sin(np.deg2rad(angle)), np.expm1(-k2 * angle)]
    if gravity_offset:
        cols.append(np.cos(np.deg2rad(angle)))
    return np.column_stack(cols)


def _with_gravity_angle(d: float, gc: float, k1: float, k2: float, gs: float) -> dict:
    """Passive parameters from the coefficients of the columns with a gravity offset."""
    return {"damping": d, "gravity": float(np.hypot(gc, gs)), "k1": k1, "k2": k2,
            "gravity_angle": float(np.degrees(np.arctan2(gs, gc)))}


def _correlation_time(resid: np.ndarray, max_lag: int = 200) -> float:
    """Integrated autocorrelation time 1 + 2·Σρ_k of a residual series, summed over Geyer's initial
    positive sequence (pairs of lags while their sum stays positive); 1 for white noise."""
    r = resid - resid.mean()
    var = float(np.dot(r, r))
    if r.size < 4 or var == 0:
        return 1.0
    lags = min(max_lag, r.size // 4)
    rho = np.array([np.dot(r[:-k], r[k:]) / var for k in range(1, 2 * (lags // 2) + 1)])
    tau = 1.0
    for a, b in zip(rho[0::2], rho[1::2]):
        if a + b <= 0:
            break
        tau += 2 * (a + b)
    return tau


def _standard_errors(jac: np.ndarray, resid: np.ndarray, n: int | None = None) -> np.ndarray:
    """Standard errors of least-squares parameters: the square roots of the diagonal of
    τ·s²·(JᵀJ)⁻¹, s² the residual variance over ``n`` residuals (default: every row of ``jac``;
    fewer where some rows are weighted out) and τ the residuals' correlation time
    (:func:`_correlation_time`, in the order given): successive residuals of a filtered
    acceleration or of a free run are far from independent, and the regressors (angle,
    velocity) vary slowly beside them, so correlated residuals carry about 1/τ of the
    information independent ones would."""
    p = jac.shape[1]
    n = jac.shape[0] if n is None else n
    s2 = float(np.sum(resid**2)) / max(n - p, 1)
    # (JᵀJ)⁻¹ by the SVD of J with its columns equilibrated; singular values are floored, not cut
    # (as a pseudo-inverse would): the direction the data leave undetermined is the one whose
    # spread matters, and cutting it would report it as known.
    norms = np.linalg.norm(jac, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    _, sv, vt = np.linalg.svd(jac / norms, full_matrices=False)
    sv = np.maximum(sv, np.finfo(float).eps * max(float(sv[0]), np.finfo(float).tiny))
    var = np.sum((vt / sv[:, None]) ** 2, axis=0) / norms**2
    return np.sqrt(_correlation_time(resid) * s2 * var)


def passive_mask(trial: Trial) -> np.ndarray:
    """The samples of ``trial`` the passive system is fitted to: quiet (no twitch can act), at
    most :data:`PASSIVE_MAX_ANGLE_DEG` extended, not excluded, and, where the acceleration is
    derived from the angle, not within half its window of the recording's end (there the
    Savitzky-Golay filter extrapolates its cubic, and its noise is many times the rest's)."""
    quiet = quiet_mask(trial.stimulation, quiet_samples(trial.sampling_period_s))
    mask = quiet & (trial.angle_deg <= PASSIVE_MAX_ANGLE_DEG) & ~trial.exclude
    if not trial.acceleration_measured:
        half = derivation_settings(trial.sampling_period_s)["acceleration"]["window_samples"] // 2
        mask[:half] = mask[mask.size - half:] = False
    return mask


def _passive_samples(trials) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Angle, velocity and acceleration of the samples of ``trials`` the passive system is fitted
    to (:func:`passive_mask`)."""
    ang, vel, acc = [], [], []
    for t in trials:
        m = passive_mask(t)
        ang.append(t.angle_deg[m])
        vel.append(t.velocity_deg_s[m])
        acc.append(t.acceleration_deg_s2[m])
    return tuple(np.concatenate(x) for x in (ang, vel, acc))


def identify_passive(trials: list[Trial] | tuple[Trial, ...], gravity_offset: bool = False) -> tuple[dict, float, int]:
    """Passive parameters (D', G', k1', k2) from the quiet samples of ``trials`` by equation
    error; returns the parameters, the RMS residual acceleration [deg/s²] and the number of
    quiet samples used (:func:`_passive_equation_error` documents the method)."""
    if not len(trials):
        raise ValueError("trials: give at least one trial")
    return _passive_equation_error(trials, gravity_offset)[:3]


#: A quiet sample whose acceleration lies more than this many robust standard deviations (1.4826
#: times the residuals' median absolute deviation) from eq. (8)'s is left out of the passive fit:
#: a knee meeting the end of its range, a heel touching the chair or a sensor's spike can
#: accelerate the shank by thousands of deg/s², and on plain least squares three such samples among 17 000
#: take a simulated leg's k1' from 21 to 3.  Gaussian noise reaches 8 SDs once in 10^15 samples.
PASSIVE_OUTLIER_SD = 8.0
#: At most this share of the samples is left out as outliers: more than that far from eq. (8) is
#: the equation's misfit, not a few samples' artefact, and all samples are then kept.
PASSIVE_OUTLIER_MAX_SHARE = 0.01


#: k2 [1/deg] of the grid the passive fits start from (D', G' and k1' are linear at a fixed k2).
PASSIVE_K2_GRID = np.geomspace(1e-3, 0.3, 61)


def _passive_fit_once(angle, velocity, accel, gravity_offset: bool, robust_scale: float | None = None, x0=None):
    """Bounded least squares of eq. (8) on the given samples, from ``x0`` or else the best k2 of
    :data:`PASSIVE_K2_GRID`.  With ``robust_scale`` [deg/s²], scipy's Cauchy loss at that scale,
    from the best k2 by that loss (its linear coefficients by iteratively reweighted least squares),
    so that a few samples far off neither pull the fit nor choose its start."""
    if x0 is None:
        best = None
        for k2 in PASSIVE_K2_GRID:
            X = _passive_columns(angle, velocity, k2, gravity_offset)
            coef, *_ = np.linalg.lstsq(X, accel, rcond=None)
            if robust_scale is None:
                loss = float(np.sum((accel - X @ coef) ** 2))
            else:  # Huber's weights, then Cauchy's (a redescending loss needs a start near the bulk's fit)
                for weights in [_huber_weights] * 4 + [_cauchy_weights] * 4:
                    w = np.sqrt(weights((X @ coef - accel) / robust_scale))
                    coef, *_ = np.linalg.lstsq(X * w[:, None], accel * w, rcond=None)
                loss = float(np.sum(np.log1p(((X @ coef - accel) / robust_scale) ** 2)))
            if best is None or loss < best[0]:
                best = (loss, k2, coef)
        _, k2, coef = best
        d0, g0, k10 = coef[:3]
        x0 = np.array([max(d0, 1e-3), max(g0, 1.0), max(k10, 1e-3), k2, *coef[3:]])
    extra = len(x0) - 4

    def resid(p):
        return _passive_residuals(p, angle, velocity, accel, gravity_offset)

    robust = {} if robust_scale is None else {"loss": "cauchy", "f_scale": robust_scale}
    return least_squares(resid, x0, bounds=([0, 0, 0, 1e-4] + [-np.inf] * extra, [np.inf, np.inf, np.inf, 1.0]
                                            + [np.inf] * extra), x_scale="jac", **robust)


def _huber_weights(z: np.ndarray) -> np.ndarray:
    return np.minimum(1.0, 1.345 / np.maximum(np.abs(z), 1e-12))


def _cauchy_weights(z: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + z**2)


def _passive_residuals(x, angle, velocity, accel, gravity_offset: bool) -> np.ndarray:
    return _passive_columns(angle, velocity, x[3], gravity_offset) @ np.concatenate([x[:3], x[4:]]) - accel


def _passive_least_squares(angle, velocity, accel, gravity_offset: bool, rounds: int = 5):
    """Eq. (8) fitted to the samples by least squares, leaving out those whose residual lies more
    than :data:`PASSIVE_OUTLIER_SD` robust standard deviations from the median residual (refitted
    until no further sample goes, at most ``rounds`` times, and no more than
    :data:`PASSIVE_OUTLIER_MAX_SHARE` of them); returns the fit on the kept samples and the mask of
    kept samples.  A trimmed least squares rather than scipy's robust losses: a sample left out is
    one the user can be told of (and mark in ``exclude``), and the fit on the rest is the plain
    least squares whose standard errors the identification reports."""
    keep = np.ones(angle.size, bool)
    fit = _passive_fit_once(angle, velocity, accel, gravity_offset)
    r = fit.fun
    sd = _robust_sd(r)
    if not sd > 0:
        return fit, keep
    # which samples lie far off is judged from a fit they cannot pull: on least squares a cluster of
    # them bends the fit towards itself, and the samples beside them look the farther off
    robust = _passive_fit_once(angle, velocity, accel, gravity_offset, robust_scale=sd)
    r = _passive_residuals(robust.x, angle, velocity, accel, gravity_offset)
    for _ in range(rounds):
        centre = float(np.median(r[keep]))
        sd = _robust_sd(r[keep])
        kept = np.abs(r - centre) <= PASSIVE_OUTLIER_SD * sd
        if np.count_nonzero(~kept) > PASSIVE_OUTLIER_MAX_SHARE * angle.size or np.array_equal(kept, keep):
            break
        keep = kept
        fit = _passive_fit_once(angle[keep], velocity[keep], accel[keep], gravity_offset, x0=fit.x)
        r = _passive_residuals(fit.x, angle, velocity, accel, gravity_offset)
    return fit, keep


def _robust_sd(r: np.ndarray) -> float:
    """The median absolute deviation scaled to a normal sample's SD (scipy's), unmoved by a few far values."""
    return float(median_abs_deviation(r, scale="normal"))


def _passive_sample_places(trials) -> tuple[np.ndarray, np.ndarray]:
    """Trial number and time [s] of each sample :func:`_passive_samples` returns, in its order."""
    number, time = [], []
    for t in trials:
        m = passive_mask(t)
        number.append(np.full(np.count_nonzero(m), t.trial))
        time.append(t.time_s[m])
    return np.concatenate(number), np.concatenate(time)


def _warn_passive_left_out(where: str, trials, keep, fit, angle, velocity, accel, gravity_offset: bool) -> None:
    """Say which quiet samples the passive fit left out as outliers (:func:`_passive_least_squares`)."""
    r = _passive_residuals(fit.x, angle, velocity, accel, gravity_offset)
    out = np.flatnonzero(~keep)
    number, time = _passive_sample_places(trials)
    worst = out[np.argsort(-np.abs(r[out]))][:3]
    places = ", ".join((f"trial {number[i]} " if len(trials) > 1 else "") + f"t = {time[i]:.2f} s ({angle[i]:.1f}°)"
                       for i in worst)
    sd = _robust_sd(r[keep])
    warnings.warn(
        f"{where}: {out.size} of the {angle.size} quiet samples left out of the passive fit: their acceleration "
        f"lies more than {PASSIVE_OUTLIER_SD:g} robust SDs ({PASSIVE_OUTLIER_SD * sd:.3g} deg/s²) from eq. (8)'s, "
        f"up to {float(np.max(np.abs(r[out]))):.3g} deg/s² off (the largest at {places}), at angles "
        f"{float(np.min(angle[out])):.1f}° to {float(np.max(angle[out])):.1f}°. A knee meeting the end of its range, "
        "an impact or a sensor's spike?"
        + (" Or the twitch of a pulse missing from the stimulation column?" if any(np.any(t.stimulation > 0)
                                                                                  for t in trials) else "")
        + " Mark them in the exclude column to leave them out knowingly",
        DataWarning, stacklevel=4)


def _passive_equation_error(trials, gravity_offset: bool = False, warn: bool = True) -> tuple[dict, float, int, dict]:
    """Passive parameters (D', G', k1', k2) from the quiet samples of ``trials`` (excluded ones left out);
    with ``gravity_offset``, also the angle gravity acts about (``gravity_angle``, see the
    ``gravity_offset`` effect).

    Only samples at or below :data:`PASSIVE_MAX_ANGLE_DEG` (+60°, the top of
    the paper's operating range) are used: eq. (8) describes the shank within
    that range, and further into extension a real knee meets the end of its
    range (capsule, and hamstrings stretched in the seated position), which
    the exponential flexion term cannot represent and would be distorted by.
    Samples far off eq. (8) (an end of range, an impact, a spike) are left out
    and, with ``warn``, named (:func:`_passive_least_squares`).
    Returns the parameters, the RMS residual acceleration [deg/s²], the
    number of quiet samples used (those left out not counted) and the parameters' standard errors
    (:func:`_standard_errors`; G' by the delta method where a gravity angle is fitted).
    """
    angle, velocity, accel = _passive_samples(trials)
    where = ", ".join(f"{t.key} trial {t.trial}" + (f" ({t.source})" if t.source else "") for t in trials)
    _refuse_non_finite(where, angle=angle, velocity=velocity, acceleration=accel)
    if angle.size < MIN_PASSIVE_SAMPLES:
        quiet = np.concatenate([t.angle_deg[quiet_mask(t.stimulation, quiet_samples(t.sampling_period_s)) & ~t.exclude]
                                for t in trials])
        high = quiet.size >= MIN_PASSIVE_SAMPLES and np.count_nonzero(quiet > PASSIVE_MAX_ANGLE_DEG) > quiet.size / 2
        raise IdentificationError(
            f"{where}: only {angle.size} quiet samples (no pulse in the preceding "
            f"{quiet_samples(trials[0].sampling_period_s)} samples, knee at "
            f"most {PASSIVE_MAX_ANGLE_DEG:g}° extended); the passive system needs at least {MIN_PASSIVE_SAMPLES}, "
            "stretches without "
            "stimulation"
            + (f". Most quiet samples lie above {PASSIVE_MAX_ANGLE_DEG:g}° (median {float(np.median(quiet)):.1f}°): "
               "is angle_deg zero with the shank hanging at rest, positive in extension?" if high else "")
        )
    if np.ptp(angle) == 0:
        raise IdentificationError(f"{where}: the angle does not move in the {angle.size} quiet samples "
                                  f"({float(angle[0])!r}° throughout): no swing to identify the passive system from")

    fit, keep = _passive_least_squares(angle, velocity, accel, gravity_offset)
    if warn and not keep.all():
        _warn_passive_left_out(where, trials, keep, fit, angle, velocity, accel, gravity_offset)
    rms = float(np.sqrt(np.mean(fit.fun**2)))
    se = _standard_errors(fit.jac, fit.fun)
    if gravity_offset:
        d, gc, k1, k2, gs = map(float, fit.x)
        g = float(np.hypot(gc, gs))
        # G' = |(gc, gs)|: its standard error by the delta method, gc and gs taken as independent
        se_g = float(np.hypot(gc * se[1], gs * se[4]) / g) if g > 0 else float(np.hypot(se[1], se[4]))
        ses = {"damping": float(se[0]), "gravity": se_g, "k1": float(se[2]), "k2": float(se[3])}
        return _with_gravity_angle(d, gc, k1, k2, gs), rms, int(keep.sum()), ses
    D, G, k1, k2 = fit.x
    return {"damping": D, "gravity": G, "k1": k1, "k2": k2}, rms, int(keep.sum()), dict(zip(_PASSIVE_NAMES, map(float, se)))


#: k2 [1/deg] of the further starts of the free-run fit (:func:`_valley_starts`): from stiff to
#: nearly linear elasticity, across the valley along which G', k1' and k2 trade.
FREE_RUN_START_K2 = (0.01, 0.02, 0.05, 0.1, 0.2)


def _valley_starts(trials, gravity_offset: bool = False) -> list[dict]:
    """Starts for the free-run fit along the valley of G', k1' and k2: for each k2 of
    :data:`FREE_RUN_START_K2`, D', G' and k1' of the equation-error least squares at that k2
    (linear in them) on the quiet samples of ``trials``."""
    angle, velocity, accel = _passive_samples(trials)
    starts = []
    for k2 in FREE_RUN_START_K2:
        coef, *_ = np.linalg.lstsq(_passive_columns(angle, velocity, k2, gravity_offset), accel, rcond=None)
        if gravity_offset:
            start = _with_gravity_angle(float(coef[0]), float(coef[1]), float(coef[2]), k2, float(coef[3]))
        else:
            start = {"damping": float(coef[0]), "gravity": float(coef[1]), "k1": float(coef[2]), "k2": k2}
        starts.append(start)
    return starts


def free_run_segments(trial: Trial) -> list[tuple[int, int]]:
    """The stretches ``[start, stop)`` of ``trial`` a free run is compared on: runs of quiet samples
    (:func:`quiet_mask`: the release and the samples after a pulse left out) that are not
    excluded, at least :data:`FREE_RUN_MIN_S` long.  Each starts a free run afresh from its
    first sample's measured state (an excluded spasm may have moved the shank)."""
    shortest = max(2, int(round(FREE_RUN_MIN_S / trial.sampling_period_s)))
    quiet = quiet_mask(trial.stimulation, quiet_samples(trial.sampling_period_s))
    return [(a, b) for a, b in stretches(quiet & ~trial.exclude) if b - a >= shortest]


_PASSIVE_NAMES = ("damping", "gravity", "k1", "k2")


def _free_run_residuals(params, segments, dt: float):
    """Free-run angle minus measured angle on every segment (concatenated), eq. (8) without a
    muscle with parameters exp(params[:4]) (and the gravity angle params[4] where given);
    ``segments``: (angle0, velocity0, measured, weight) per segment (weight 0 where the angle
    is beyond :data:`PASSIVE_MAX_ANGLE_DEG`)."""
    values = dict(zip(_PASSIVE_NAMES, jnp.exp(params[:4])))
    if params.shape[0] > 4:
        values["gravity_angle"] = params[4]
    model = paper_model("passive", passive_effects(**values), sampling_period_s=dt)
    out = []
    for angle0, velocity0, measured, weight in segments:
        angle, _, _ = simulate_angles(model, jnp.zeros(measured.shape[0], measured.dtype), angle0, velocity0)
        out.append((angle - measured) * weight)
    return jnp.concatenate(out)


#: Bounds of the free-run fit's D', G', k1' (below) and k2 (both sides), as the equation error's:
#: where the swing holds no elasticity, k1'·(exp(-k2·φ) - 1) vanishes as k2 → 0 and k1' is then free,
#: so unbounded logarithms would wander off to values no knee has.
FREE_RUN_LOWER = {"damping": 1e-6, "gravity": 1e-6, "k1": 1e-6, "k2": 1e-4}
FREE_RUN_UPPER_K2 = 1.0


def _free_run_bounds(gravity_offset: bool) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of the free-run fit's parameter vector (:func:`_free_run_start`)."""
    lower = np.log([FREE_RUN_LOWER[k] for k in _PASSIVE_NAMES])
    upper = np.array([np.inf, np.inf, np.inf, np.log(FREE_RUN_UPPER_K2)])
    if gravity_offset:
        lower, upper = np.append(lower, -np.inf), np.append(upper, np.inf)
    return lower, upper


def _free_run_start(start: dict, gravity_offset: bool) -> np.ndarray:
    """The free-run fit's parameter vector (logarithms of D', G', k1', k2, then the gravity angle)
    at the passive parameters ``start``, moved inside :func:`_free_run_bounds`."""
    lower, upper = _free_run_bounds(False)
    x0 = np.clip(np.log([max(float(start[k]), 1e-300) for k in _PASSIVE_NAMES]), lower, upper)
    return np.append(x0, float(start.get("gravity_angle", 0.0))) if gravity_offset else x0


def identify_passive_free_run(trials: list[Trial] | tuple[Trial, ...], start: dict | None = None,
                              gravity_offset: bool = False) -> tuple[dict, float, int]:
    """Passive parameters (D', G', k1', k2) of trials without pulses (pendulum tests) by output
    error on the free swing; returns the parameters, the RMS angle error [deg] of the free runs
    and the number of samples compared (:func:`_passive_free_run` documents the method)."""
    if not len(trials):
        raise ValueError("trials: give at least one trial")
    return _passive_free_run(trials, start, gravity_offset)[:3]


def _passive_free_run(trials, start: dict | None = None, gravity_offset: bool = False) -> tuple[dict, float, int, dict]:
    """Passive parameters (D', G', k1', k2) of trials without pulses (pendulum tests) that make
    the free run of eq. (8) follow the measured angle: output-error least squares.

    Each usable stretch (:func:`free_run_segments`) is simulated from its first sample's
    measured angle and velocity, as J and the free-run error judge a model, and compared
    with the measured angle wherever the knee is at most :data:`PASSIVE_MAX_ANGLE_DEG`
    extended.  The parameters start from ``start``, or by default from the equation-error
    estimate of :func:`identify_passive` and from points along the valley where G', k1' and
    k2 trade (:func:`_valley_starts`): the free run's error has local minima along it, and an
    equation-error start that sits in the valley's wrong part stays there.  From each start
    trust-region least squares with the exact Jacobian (JAX, double precision) refine them,
    and the lowest error is kept.  With ``gravity_offset`` the angle gravity
    acts about is fitted too (``gravity_angle``).  Returns the parameters, the RMS angle error
    [deg] of the free runs, the number of samples compared and the parameters' standard errors
    (:func:`_standard_errors`, of the logarithms: relative ones).
    """
    if start is None:
        # a start only: the samples its equation error leaves out are not named as left out of this fit
        starts = [_passive_equation_error(trials, gravity_offset=gravity_offset, warn=False)[0],
                  *_valley_starts(trials, gravity_offset)]
    else:
        starts = [start]
    dt = trials[0].sampling_period_s
    where = ", ".join(f"{t.key} trial {t.trial}" + (f" ({t.source})" if t.source else "") for t in trials)
    with jax.enable_x64(True):
        pieces = [(t, a, b) for t in trials for a, b in free_run_segments(t)]
        if not pieces:
            raise IdentificationError(f"{where}: no stretch of {FREE_RUN_MIN_S:g} s without pulses and excluded "
                                      "samples to compare a free run with")
        kept = np.concatenate([t.angle_deg[a:b] <= PASSIVE_MAX_ANGLE_DEG for t, a, b in pieces])

        def fitting(kept):
            """The residual function and its Jacobian on the samples ``kept`` (concatenated)."""
            segments, i = [], 0
            for t, a, b in pieces:
                weight = jnp.asarray(kept[i:i + b - a], jnp.float64)
                segments.append((jnp.float64(t.angle_deg[a]), jnp.float64(t.velocity_deg_s[a]),
                                 jnp.asarray(t.angle_deg[a:b], jnp.float64), weight))
                i += b - a
            resid = jax.jit(lambda p: _free_run_residuals(p, segments, dt))
            jac = jax.jit(jax.jacfwd(lambda p: _free_run_residuals(p, segments, dt)))

            def jacobian(p):
                # a run that grows past what a float holds (a stiff start on a swing beyond the fitted
                # range) has no slope there: zero, so that the trust region turns back instead of failing
                J = np.asarray(jac(jnp.asarray(p)))
                return np.where(np.isfinite(J), J, 0.0)

            return resid, jacobian

        resid, jacobian = fitting(kept)
        bounds = _free_run_bounds(gravity_offset)
        fit, failed = None, []
        for s0 in starts:  # the lowest of the local minima along the valley
            x0 = _free_run_start(s0, gravity_offset)
            if not np.all(np.isfinite(np.asarray(resid(jnp.asarray(x0))))):
                failed.append("its free run diverges from the start")
                continue
            with np.errstate(over="ignore", invalid="ignore"):
                try:
                    this = least_squares(lambda p: np.asarray(resid(jnp.asarray(p))), x0, jac=jacobian,
                                         method="trf", x_scale="jac", bounds=bounds)
                except (ValueError, np.linalg.LinAlgError) as exc:
                    failed.append(str(exc))
                    continue
            if np.isfinite(this.cost) and (fit is None or this.cost < fit.cost):
                fit = this
        if fit is None:
            raise IdentificationError(
                f"{where}: the free run of the passive system diverged from every start "
                f"({failed[0] if failed else 'no finite error'}); fit the "
                "acceleration instead (`identify --passive-objective acceleration`), or leave out the swings beyond "
                "the knee's range (start_s, end_s or exclude)")
        # samples far off the free run (a spike) are left out and the fit refined without them, as
        # the equation error leaves out those far off eq. (8): least squares would bend to them
        r = np.asarray(fit.fun)
        sd = _robust_sd(r[kept])
        far = kept & (np.abs(r - np.median(r[kept])) > PASSIVE_OUTLIER_SD * sd)
        if sd > 0 and 0 < np.count_nonzero(far) <= PASSIVE_OUTLIER_MAX_SHARE * np.count_nonzero(kept):
            resid, jacobian = fitting(kept & ~far)
            again = None
            for x0 in (fit.x, *[_free_run_start(s0, gravity_offset) for s0 in starts]):
                with np.errstate(over="ignore", invalid="ignore"):
                    try:  # from every start again: the samples left out may have held the fit in the valley
                        this = least_squares(lambda p: np.asarray(resid(jnp.asarray(p))), x0, jac=jacobian,
                                             method="trf", x_scale="jac", bounds=bounds)
                    except (ValueError, np.linalg.LinAlgError):
                        continue
                if np.isfinite(this.cost) and (again is None or this.cost < again.cost):
                    again = this
            if again is not None:
                time = np.concatenate([t.time_s[a:b] for t, a, b in pieces])
                number = np.concatenate([np.full(b - a, t.trial) for t, a, b in pieces])
                worst = np.flatnonzero(far)[np.argsort(-np.abs(r[far]))][:3]
                places = ", ".join((f"trial {number[i]} " if len(trials) > 1 else "") + f"t = {time[i]:.2f} s"
                                   for i in worst)
                warnings.warn(
                    f"{where}: {np.count_nonzero(far)} of the {np.count_nonzero(kept)} samples of the free swing left "
                    f"out of the passive fit: their angle lies more than {PASSIVE_OUTLIER_SD:g} robust SDs "
                    f"({PASSIVE_OUTLIER_SD * sd:.2g}°) from the free run's, up to {float(np.max(np.abs(r[far]))):.3g}° "
                    f"off (the largest at {places}). A sensor's spike? Mark them in the exclude column to leave them "
                    "out knowingly", DataWarning, stacklevel=3)
                fit, kept = again, kept & ~far
        n = int(np.count_nonzero(kept))
    params = dict(zip(_PASSIVE_NAMES, map(float, np.exp(fit.x[:4]))))
    if gravity_offset:
        params["gravity_angle"] = float(fit.x[4])
    rel = _standard_errors(fit.jac, fit.fun, n)[:4]  # of the logarithms: relative errors
    ses = {k: float(params[k] * r) for k, r in zip(_PASSIVE_NAMES, rel)}
    return params, float(np.sqrt(np.sum(fit.fun**2) / max(n, 1))), n, ses


# ============================================================================ twitches


def isolated_twitches(stimulation: np.ndarray, epoch: int = TWITCH_SAMPLES, exclude=None) -> np.ndarray:
    """Indices of pulses with ``epoch`` quiet samples before and ``2*epoch`` after, none of
    those samples excluded (``exclude``: True on excluded samples; None: none)."""
    stim = np.asarray(stimulation)
    pulses = np.flatnonzero(stim > 0)
    n = len(stim)
    if pulses.size == 0:
        return pulses
    prev_gap = np.diff(pulses, prepend=-(10**9))
    next_gap = np.diff(pulses, append=10**9)
    ok = (prev_gap > epoch) & (next_gap > 2 * epoch) & (pulses >= epoch) & (pulses + 2 * epoch <= n)
    if exclude is not None and np.any(exclude):
        before = np.concatenate([[0], np.cumsum(np.asarray(exclude, dtype=int))])  # excluded samples before k
        lo, hi = np.clip(pulses - epoch, 0, n), np.clip(pulses + 2 * epoch, 0, n)
        ok &= before[hi] == before[lo]
    return pulses[ok]


def _epoch_rows(y, u, pulses, d, order=2, epoch=TWITCH_SAMPLES):
    """Regression data of eq. (10) over all epochs of ``epoch`` samples for delay d (no whitening terms)."""
    idx = (pulses[:, None] + np.arange(epoch)[None, :]).ravel()
    cols = [-y[idx - i] for i in range(1, order + 1)]
    cols += [u[idx - i - d] for i in range(1, order + 1)]  # pulses start after MAX_DELAY + 2
    return np.column_stack(cols), y[idx], idx


def fit_darma(y: np.ndarray, u: np.ndarray, pulses: np.ndarray, d: int, order: int = 2, iterations: int = 10,
              epoch: int = TWITCH_SAMPLES):
    """Generalised least squares of eq. (10) on the epochs for one delay.

    Extended least squares: an equation-error fit, then repeatedly the lagged
    residuals e_{k-1}, e_{k-2} are added as regressors (the whitening filter
    c_1, c_2) and the fit repeated.  Returns (a, b, c, residual mean square).
    """
    X, target, idx = _epoch_rows(y, u, pulses, d, order, epoch)
    e_full = np.zeros_like(y)
    coef, *_ = np.linalg.lstsq(X, target, rcond=None)
    e_full[idx] = target - X @ coef
    c = np.zeros(order)
    for _ in range(iterations):
        E = np.column_stack([e_full[idx - i] for i in range(1, order + 1)])
        Xe = np.hstack([X, E])
        coef_full, *_ = np.linalg.lstsq(Xe, target, rcond=None)
        e_new = np.zeros_like(y)
        e_new[idx] = target - Xe @ coef_full
        e_full = e_new
        coef, c = coef_full[: 2 * order], coef_full[2 * order :]
    resid = e_full[idx]
    return coef[:order], coef[order:], c, float(np.mean(resid**2))


# ============================================================================ leg


def identify_leg(trial: Trial, passive: dict | None = None) -> LegIdentification:
    """Identify the passive system and models 1–3 from one trial of one leg."""
    if not isinstance(trial, Trial):
        raise TypeError(f"trial: give one Trial (cohort.get(leg, 1), say), not {type(trial).__name__}")
    check_cohort(Cohort((trial,)))  # a trial built in Python meets the rules a file's does
    where = f"{trial.key} trial {trial.trial}"
    if passive is not None and not set(_PASSIVE_NAMES) <= set(passive) <= {*_PASSIVE_NAMES, "gravity_angle"}:
        raise ValueError(f"passive: give {', '.join(_PASSIVE_NAMES)} (and gravity_angle where gravity acts about "
                         f"another angle), not {', '.join(map(str, passive))}")
    if passive is None:
        passive, p_rms, n_quiet, p_se = _passive_equation_error([trial])
    else:
        p_rms, n_quiet, p_se = float("nan"), 0, {}
    peff = passive_effects(**passive)
    dt = trial.sampling_period_s
    base = paper_model(1, peff, sampling_period_s=dt)
    mi = np.asarray(
        equivalent_acceleration(base, trial.angle_deg, trial.velocity_deg_s, trial.acceleration_deg_s2),
        dtype=float,
    )
    _refuse_non_finite(where, **{"equivalent acceleration": mi[~trial.exclude]})
    u = trial.stimulation
    epoch = twitch_epoch(dt)
    pulses = isolated_twitches(u, epoch, exclude=trial.exclude)
    if pulses.size < MIN_TWITCHES:
        runs = pulse_runs(trial)  # a trigger over the pulse's width, a gate: pulses never delivered
        raise IdentificationError(
            f"{where}: only {pulses.size} isolated twitches (a pulse with {epoch} quiet samples "
            f"before and {2 * epoch} after, none of them excluded); the classical identification needs at least {MIN_TWITCHES} "
            + (f"({runs[0]}; `quadshank fit` would take each such sample for a pulse too)" if runs else
               "(`quadshank fit` does not: it fits every sample, trains of pulses too)")
        )
    pulses = pulses[pulses > MAX_DELAY + 2]

    # model 2 over all delays -> the delay of all models
    fits = [fit_darma(mi, u, pulses, d, epoch=epoch) for d in range(MAX_DELAY + 1)]
    residuals = np.array([f[3] for f in fits])
    d = int(np.argmin(residuals))
    if d == MAX_DELAY:  # the scan's edge: the residual may fall further beyond it
        warnings.warn(
            f"{where}: the delay comes out at {MAX_DELAY} samples ({MAX_DELAY * dt * 1000:g} ms), the longest considered: "
            "model 2's residual is lowest at the edge of the scan, and the muscle's delay may be longer"
            + (" (resampled to 10 ms, `quadshank convert DATA data.nc --resample 0.01`, the delays considered reach "
               "100 ms)" if dt < SAMPLING_PERIOD_S * (1 - 1e-6) else "")
            + ("; or the noise of an acceleration derived from the angle (no accelerometer) hides the twitch's onset"
               if not trial.acceleration_measured else ""), DataWarning, stacklevel=3)
    elif d * dt < SHORTEST_MUSCLE_DELAY_S:
        warnings.warn(
            f"{where}: the delay comes out at {d} sample{'s' if d != 1 else ''} ({d * dt * 1000:g} ms), shorter than a "
            "stimulated muscle's (20-50 ms; the paper's 40-50 ms): the twitch seems to begin at its pulse. A stimulation "
            "artefact on the pulses' samples (the reader names one where it finds it: `quadshank check`), or pulses "
            "logged later than they were delivered? The gains come out wrong with such a delay", DataWarning,
            stacklevel=3)
    a, b, c, _ = fits[d]

    # integrated twitch responses (per unit recruitment)
    epochs = pulses[:, None] + np.arange(epoch)[None, :]
    integrated = mi[epochs].sum(axis=1) / u[pulses]
    g1 = float(mi[epochs].sum() / u[pulses].sum())
    if not g1 > 0:  # also NaN
        raise IdentificationError(
            f"{where}: after the {pulses.size} isolated pulses the knee's equivalent acceleration sums to "
            f"{g1:.3g} deg/s² per unit stimulation, not a positive twitch: the quadriceps extends the knee. Is the "
            "sign of angle_deg flipped (positive must be extension), is a glitch in the angle in the way, or are the "
            "pulses at other samples than the movement they cause?"
        )
    phi = trial.angle_deg[pulses + d]
    dphi = trial.velocity_deg_s[pulses + d]

    def resid3(p):
        return p[0] * (1 + p[1] * phi) * (1 + p[2] * dphi) - integrated

    fit3 = least_squares(resid3, np.array([g1, 0.0, 0.0]), method="lm", x_scale=np.array([g1, 1e-2, 1e-3]))
    g2, ga, gv = fit3.x

    models = {
        "model1": paper_model(1, peff, delay=d, sampling_period_s=dt).with_params(gain=g1),
        "model2": paper_model(2, peff, delay=d, sampling_period_s=dt).with_params(a=np.asarray(a), b=np.asarray(b)),
        "model3": paper_model(3, peff, delay=d, sampling_period_s=dt).with_params(gain=g2, gamma_angle=ga, gamma_velocity=gv),
    }
    rms1 = float(np.sqrt(np.mean((integrated - g1) ** 2)) / g1 * 100)
    rms3 = float(np.sqrt(np.mean(fit3.fun**2)) / g1 * 100)
    return LegIdentification(
        leg=trial.key,
        trial=trial.trial,
        passive={k: float(v) for k, v in passive.items()},
        passive_rms_residual=p_rms,
        n_quiet=n_quiet,
        passive_se=p_se,
        delay=d,
        delay_residuals=residuals,
        models=models,
        whitening={"c1": float(c[0]), "c2": float(c[1])},
        pulses=pulses,
        integrated=integrated,
        angle_at_d=phi,
        velocity_at_d=dphi,
        g1_std=float(np.std(integrated, ddof=1)),
        rms_error_pct={"model1": rms1, "model3": rms3},
    )


def _refuse_non_finite(where: str, **signals) -> None:
    """Refuse signals that are not finite where the least squares would meet them (LAPACK does
    not return on some of them)."""
    for name, x in signals.items():
        bad = np.flatnonzero(~np.isfinite(x))
        if bad.size:
            raise IdentificationError(f"{where}: the {name} is not finite on {bad.size} of the samples used "
                                      "(a value beyond what a float holds?); correct the recording, or exclude those samples")


def _warn_poor_swing(leg: str, trials, rms: float) -> bool:
    """Warn where the free runs of the identified pendulum miss the swings of ``trials`` by more
    than :data:`POOR_SWING_SHARE` of the swing's spread (``rms``: their RMS angle error [deg]);
    returns whether it warned."""
    kept = [t.angle_deg[a:b][t.angle_deg[a:b] <= PASSIVE_MAX_ANGLE_DEG] for t in trials for a, b in free_run_segments(t)]
    spread = float(np.std(np.concatenate(kept))) if kept else 0.0
    if spread > 0 and rms > POOR_SWING_SHARE * spread:
        numbers = ", ".join(str(t.trial) for t in trials)
        warnings.warn(
            f"{leg}: the pendulum of eq. (8) identified from trial(s) {numbers} (no pulses: pendulum tests) misses "
            f"their free swings by {rms:.3g}° RMS, {rms / spread:.0%} of the swing's spread ({spread:.3g}°): are they "
            "pendulum tests (not a stimulated trial whose pulses are missing)? A rest off the vertical is fitted "
            "with --gravity-offset; a release left in, with start_s or exclude", DataWarning, stacklevel=3)
        return True
    return False


def identify_cohort(
    cohort: Cohort, trial: int = 1, progress: bool = False, passive_objective: str = "auto",
    gravity_offset: bool = False,
) -> dict[str, LegIdentification | PassiveIdentification]:
    """Identify every leg of the cohort from its trial number ``trial``.

    A leg with trials without pulses (pendulum tests) takes its passive system from those
    trials, as the paper took it from pendulum tests; otherwise from the quiet samples of
    ``trial``.  A leg whose trial ``trial`` holds no pulse gets its passive system alone
    (:class:`PassiveIdentification`).

    ``passive_objective``: ``"acceleration"`` (equation error, :func:`identify_passive`),
    ``"angle"`` (output error on the free swing, :func:`identify_passive_free_run`; pendulum
    tests only) or ``"auto"``: the angle where a leg has pendulum tests, which predicts their
    swing best, the acceleration on the quiet samples between pulses, where a free run
    cannot go.  ``gravity_offset``: also fit the angle gravity acts about (from the pendulum tests,
    or the quiet samples of ``trial``, where no twitch acts).
    """
    if passive_objective not in PASSIVE_OBJECTIVES + ("auto",):
        raise ValueError(f"unknown passive objective {passive_objective!r}; use auto, acceleration or angle")
    check_cohort(cohort)  # a cohort built in Python meets the rules a file's does
    muscle = any(np.any(t.stimulation > 0) for t in cohort)  # pendulum tests alone are modelled at any period
    check_delay_range(cohort.sampling_period_s, muscle=muscle, warn=muscle)
    out: dict = {}
    for leg in progress_bar(cohort.legs, desc="identify", enabled=progress):
        chosen = cohort.get(leg, trial)
        passive_trials = [t for t in cohort.trials_of(leg) if not np.any(t.stimulation > 0)]
        if not passive_trials:
            if passive_objective == "angle":
                raise IdentificationError(
                    f"{leg}: the passive objective 'angle' fits free swings, and the leg has no trial without "
                    "pulses (a pendulum test); use the objective 'auto' or 'acceleration'")
            if gravity_offset:  # the quiet samples between twitches, with gravity about a free angle
                passive, p_rms, n_quiet, p_se = _passive_equation_error([chosen], gravity_offset=True)
                out[leg] = dataclasses.replace(identify_leg(chosen, passive=passive), passive_rms_residual=p_rms,
                                               n_quiet=n_quiet, passive_se=p_se)
                _warn_passive_unseparated(leg, passive, p_se, f"the quiet samples of trial {trial}",
                                          angle_span((chosen,)))
                continue
            out[leg] = identify_leg(chosen)
            if not _warn_rest_offset(leg, chosen, out[leg].passive, out[leg].passive_rms_residual):
                _warn_passive_unseparated(leg, out[leg].passive, out[leg].passive_se,
                                          f"the quiet samples of trial {trial}", angle_span((chosen,)))
            continue
        objective = "acceleration" if passive_objective == "acceleration" else "angle"
        numbers = tuple(t.trial for t in passive_trials)
        try:
            if objective == "angle":
                passive, p_rms, n_quiet, p_se = _passive_free_run(passive_trials, gravity_offset=gravity_offset)
            else:
                passive, p_rms, n_quiet, p_se = _passive_equation_error(passive_trials, gravity_offset=gravity_offset)
        except IdentificationError as err:  # say why these trials were asked
            which = (f"trials {', '.join(map(str, numbers))} hold no pulse and so are taken as pendulum tests"
                     if len(numbers) > 1 else f"trial {numbers[0]} holds no pulse and so is taken as a pendulum test")
            raise IdentificationError(f"{err}. {leg}: its {which}, the source of its passive system; leave out a "
                                      "trial that is not one") from err
        # a pendulum that misses the swings says so; its standard errors then measure the misfit
        poor = objective == "angle" and _warn_poor_swing(leg, passive_trials, p_rms)
        if gravity_offset and abs(passive["gravity_angle"]) > PLAUSIBLE_GRAVITY_ANGLE_DEG:
            warnings.warn(
                f"{leg}: the identified pendulum has gravity acting about {passive['gravity_angle']:.0f}°, where a "
                f"seated knee's vertical lies within ±{PLAUSIBLE_GRAVITY_ANGLE_DEG:g}° of the angle's zero: its gravity and "
                "elasticity trade against each other to hold the swing's rest, and their values are not the leg's. "
                "A gravity offset describes a vertical away from the angle's zero (a tilted seat, a goniometer "
                "zeroed elsewhere); a rest that the tissues hold away from the vertical has no built-in effect",
                DataWarning, stacklevel=2)
        if not np.any(chosen.stimulation > 0):
            out[leg] = PassiveIdentification(leg, trial, {k: float(v) for k, v in passive.items()}, p_rms, n_quiet,
                                             numbers, chosen.sampling_period_s, objective, p_se)
        else:
            out[leg] = dataclasses.replace(identify_leg(chosen, passive=passive), passive_rms_residual=p_rms,
                                           n_quiet=n_quiet, passive_trials=numbers, passive_objective=objective,
                                           passive_se=p_se)
        if not poor:
            _warn_passive_unseparated(leg, passive, p_se, f"the swings of trial{'s' if len(numbers) > 1 else ''} "
                                      f"{', '.join(map(str, numbers))} (no pulses)", angle_span(passive_trials))
    return out


#: G' [deg/s²] below which an identified pendulum has next to no gravity: a shank's is m·g·l/I,
#: about 1500–2500, and no leg's is a tenth of it.
GRAVITY_NEAR_ZERO = 150.0


def passive_separated(passive: dict, se: dict) -> bool:
    """Whether the data told the passive system's gravity from its elasticity: G' is positive and
    carries a relative standard error of at most :data:`PASSIVE_GRAVITY_REL_SE` (True where no
    standard error was estimated)."""
    if "gravity" not in se:
        return True
    return bool(passive["gravity"] > 0 and se["gravity"] <= PASSIVE_GRAVITY_REL_SE * passive["gravity"])


#: The quiet samples' passive fit with gravity about another angle (``gravity_offset``) whose RMS
#: residual is this much smaller than eq. (8)'s about angle 0 ...
REST_OFFSET_RMS_RATIO = 1.05
#: ... at an angle at least this far from 0 [deg] says the angle's zero is off the hanging shank: on
#: the simulated cohort (rest at 0) the ratio is 1.000 and the angle within 0.05° of 0, and an
#: offset of 1° raises eq. (8)'s RMS by 10-17 %, while it takes G' to about half and k1' 40-100 fold.
REST_OFFSET_MIN_DEG = 0.5
#: The ratio for an acceleration derived from the angle, whose noise (a second derivative's) fills the
#: residual: without an offset 1.0000-1.0004 on the simulated cohort and the other simulator's
#: recordings, with 3° 1.03-1.05 and with 5° 1.13-1.15 (the angle found within 0.1°).
REST_OFFSET_RMS_RATIO_DERIVED = 1.01
#: Where that fit's RMS residual is more than this share of the quiet samples' spread, eq. (8) does not
#: describe them either way (on the simulated cohort the share is 0.06-0.08; 0.45-0.49 with 90 % of
#: the pulses missing from the stimulation column), and the warning leads with activity between the
#: twitches, which can move the angle gravity seems to act about as well ...
REST_OFFSET_POOR_FIT = 0.25
#: ... and this share where the acceleration is derived from the angle (0.29-0.37 on the simulated
#: cohort from its noise alone, 0.50-0.53 with 90 % of the pulses missing).
REST_OFFSET_POOR_FIT_DERIVED = 0.45


def rest_offset(trial: Trial, about_zero: tuple[dict, float] | None = None) -> tuple[str, bool] | None:
    """Where the quiet samples of a stimulated ``trial`` are fitted much better with gravity about an
    angle away from 0 (:data:`REST_OFFSET_RMS_RATIO`, :data:`REST_OFFSET_MIN_DEG`, at most
    :data:`PLAUSIBLE_GRAVITY_ANGLE_DEG`): what that says, in words, and whether eq. (8) describes
    the quiet samples poorly either way (:data:`REST_OFFSET_POOR_FIT`); else None.  Such an angle is
    zeroed off the shank hanging at rest, which biases every passive and active value identified
    about angle 0 (a few degrees halve G'2); between small swings a constant offset of a measured
    acceleration looks the same.  ``about_zero``: the passive system identified about angle 0 and
    its RMS residual, where already found."""
    if angle_span((trial,)) < RADIAN_SPAN_DEG:
        return None  # a span of a few units: radians, which the warning of next to no gravity names
    try:
        passive, rms = about_zero or _passive_equation_error([trial], warn=False)[:2]
        free, rms_free, _, _ = _passive_equation_error([trial], gravity_offset=True, warn=False)
    except IdentificationError:
        return None
    angle = float(free["gravity_angle"])
    measured = trial.acceleration_measured
    ratio = REST_OFFSET_RMS_RATIO if measured else REST_OFFSET_RMS_RATIO_DERIVED
    if rms <= ratio * rms_free or not REST_OFFSET_MIN_DEG <= abs(angle) <= PLAUSIBLE_GRAVITY_ANGLE_DEG:
        return None  # beyond ±45° the fit is degenerate (gravity at its bound), not a measured angle
    spread = float(np.std(_passive_samples([trial])[2]))
    sensor = (f" Or does the accelerometer read a constant offset? About {abs(free['gravity'] * np.sin(np.radians(angle))):.2g} "
              "deg/s² looks the same between small swings." if trial.acceleration_measured else "")
    if rms_free > (REST_OFFSET_POOR_FIT if measured else REST_OFFSET_POOR_FIT_DERIVED) * spread:
        # eq. (8) does not describe them either way: say that first
        return (f"eq. (8) describes the quiet samples of trial {trial.trial} poorly (RMS {rms_free:.3g} deg/s² at best, "
                f"against their spread of {spread:.3g}), and better with gravity about {angle:+.1f}° than about 0 "
                f"({rms_free:.3g} against {rms:.3g}). Activity between the twitches does this: pulses missing from the "
                "stimulation column (a trigger recorded at another rate, say), a spasm, tone. An angle zeroed away "
                f"from the hanging shank does it too.{sensor} As recorded, the passive values identified from them "
                f"(G' {passive['gravity']:.3g}, k1' {passive['k1']:.3g} deg/s²) and the gains with them are not the "
                "leg's"), True
    return (f"the quiet samples of trial {trial.trial} swing about {angle:+.1f}° rather than about the angle's zero: "
            f"eq. (8) with gravity about {angle:+.1f}° fits them with {rms_free:.3g} deg/s² RMS against {rms:.3g} "
            f"about 0. Is angle_deg zeroed away from the shank hanging at rest (a goniometer's zero)?{sensor} "
            f"As recorded, the identified values are biased (G' {passive['gravity']:.3g} and k1' {passive['k1']:.3g} "
            f"deg/s² against {free['gravity']:.3g} and {free['k1']:.3g} with the offset, and the gains with them): "
            "zero angle_deg with the shank hanging, or identify the offset (`quadshank identify --gravity-offset`) "
            "or fit it (`quadshank fit --add-effect goniometer_offset`, or `gravity_offset` for a rest the tissues "
            "hold)", False)


def _warn_rest_offset(leg: str, trial: Trial, passive: dict, rms: float) -> bool:
    """Warn (and return True) where :func:`rest_offset` finds the quiet samples' angle zeroed elsewhere."""
    found = rest_offset(trial, (passive, rms))
    if found:
        warnings.warn(f"{leg}: {found[0]}", DataWarning, stacklevel=3)
    return bool(found)


#: A range [deg] of the angle (the central 98 % of the samples kept) narrower than this, with next to
#: no gravity identified, reads as radians: a shank's swings span tens of degrees, 2π rad is 6.3.
RADIAN_SPAN_DEG = 2 * np.pi


def angle_span(trials) -> float:
    """The range of the angle over the samples of ``trials`` not excluded, its central 98 %."""
    a = np.concatenate([t.angle_deg[~t.exclude] for t in trials])
    lo, hi = np.quantile(a, [0.01, 0.99]) if a.size else (0.0, 0.0)
    return float(hi - lo)


def _warn_passive_unseparated(leg: str, passive: dict, se: dict, source: str, span: float | None = None) -> None:
    """Warn where the identified G' is next to 0 (an angle zeroed away from the rest) or where
    the data did not tell gravity from elasticity (:func:`passive_separated`), in one warning
    where both hold: a G' near 0 from small swings can be either."""
    near_zero = passive["gravity"] < GRAVITY_NEAR_ZERO
    separated = passive_separated(passive, se)
    if separated and not near_zero:
        return

    def pm(v, e):
        return f"{float(f'{v:.3g}'):g} ± {float(f'{e:.2g}'):g}"

    trade = "" if separated else (
        f"{source} do not tell the pendulum's gravity from the knee's elasticity (G' = "
        f"{pm(passive['gravity'], se['gravity'])} deg/s², k1' = {pm(passive['k1'], se['k1'])} deg/s², "
        f"k2 = {pm(passive['k2'], se['k2'])} /deg): the two terms of eq. (8) are nearly proportional over these "
        "angles, so G', k1' and k2 trade against each other with the same residual, and their values are not the "
        "leg's. A pendulum test (a trial without pulses) with larger swings, the accelerometer's acceleration (one "
        "derived from the angle is noisier) or a longer recording separates them; `quadshank fit` weighs them with "
        "its priors")
    if near_zero:
        text = (f"the identified pendulum has next to no gravity (G' = {passive['gravity']:.3g} deg/s², where a "
                "shank's is about 1500-2500): eq. (8) could not hold the swings with gravity about angle 0. Is angle_deg "
                "zero with the shank at rest? A constant added to every angle does this; the other passive and active "
                "values then come out wrong too")
        if span is not None and span < RADIAN_SPAN_DEG:
            text += (f". Or angle_deg (and the acceleration with it) in radians: the angle spans only "
                     f"{span:.3g} over its samples, where a knee's swings span tens of degrees; convert to degrees")
        if source.startswith("the quiet samples"):
            text += (". Or twitches among the quiet samples: pulses missing from the stimulation column (dropouts, "
                     "a trigger logged at another rate), or an accelerometer that senses gravity's projection")
        text += f". Or: {trade}" if trade else ""
    else:
        text = trade
    warnings.warn(f"{leg}: {text}", DataWarning, stacklevel=3)


def models_from_summary(summary: dict, sampling_period_s: float = SAMPLING_PERIOD_S) -> dict[str, dict[str, Model]]:
    """Rebuild the identified models of each leg from an identify ``summary.json``, at the
    sampling period of the data they were identified from."""
    models = {}
    dt = sampling_period_s
    for leg, s in summary.items():
        # a value that came out not finite was written as null
        s = {**s, **{k: nulls_as_nan(s[k]) for k in ("passive", "model1", "model2", "model3") if k in s}}
        if s.get("passive_only"):
            models[leg] = {"passive": passive_model(s["passive"], dt)}
            continue
        passive = passive_effects(**s["passive"])
        d = int(s["delay_samples"])
        m2 = s["model2"]
        models[leg] = {
            "model1": paper_model(1, passive, delay=d, sampling_period_s=dt).with_params(gain=s["model1"]["gain"]),
            "model2": paper_model(2, passive, delay=d, sampling_period_s=dt).with_params(
                a=np.array([m2["a1"], m2["a2"]]), b=np.array([m2["b1"], m2["b2"]])
            ),
            "model3": paper_model(3, passive, delay=d, sampling_period_s=dt).with_params(
                gain=s["model3"]["gain"],
                gamma_angle=s["model3"]["gamma_angle"],
                gamma_velocity=s["model3"]["gamma_velocity"],
            ),
        }
    return models


@dataclasses.dataclass
class Identification(Result):
    """What ``quadshank identify`` found: each leg's classical estimates (passive system, delay,
    models 1–3, Table IV errors and, given the simulator's truth, their recovery)."""

    KIND: ClassVar[str] = "identification"

    trial: int  # the identification trial
    sampling_period_s: float  # of the data identified; the models run at it
    legs: dict  # leg -> LegIdentification.summary() (and "recovery" where a truth was given)
    warnings: list | None = None  # what the identification warned of, as printed

    def models(self) -> dict[str, dict[str, Model]]:
        """The identified models 1–3 of every leg (see :func:`models_from_summary`)."""
        return models_from_summary(self.legs, self.sampling_period_s)


def load_identification(folder: str | Path, sampling_period_s: float | None = None) -> dict[str, dict[str, Model]]:
    """Models from a ``quadshank identify`` output folder; with ``sampling_period_s``, the
    period of the data to predict, which must be the identified data's."""
    path = Path(folder) / "summary.json"
    if not path.exists():
        raise FileNotFoundError(f"{path}: no identification here (run `quadshank identify DATA --out {folder}`)")
    ident = Identification.read(folder)
    if sampling_period_s is not None and abs(sampling_period_s - ident.sampling_period_s) > SAME_PERIOD_REL * sampling_period_s:
        raise ValueError(f"{path}: identified at a sampling period of {ident.sampling_period_s * 1e3:g} ms; "
                         f"these data are sampled every {sampling_period_s * 1e3:g} ms")
    return ident.models()
