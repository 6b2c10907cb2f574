"""Residual diagnostics of a fitted model: where does the model fail?

Every function takes per-sample arrays of one leg over one or more
concatenated trials: the one-step-ahead ``residual`` (measured minus predicted
equivalent acceleration, deg/s²), ``angle`` (deg), ``velocity`` (deg/s),
``stimulation`` (recruitment level u in [0, 1] at pulse samples, 0 elsewhere),
``sample_mask`` (False for padding and gaps, ignored everywhere; a non-finite
residual counts as masked out too) and ``trial_start`` (index of the first
sample of each sample's trial).  The numerics (:func:`features`,
:func:`binned_trend`, :func:`acf`, :func:`ccf`,
:func:`twitch_triggered_average`, :func:`spectrum`, :func:`findings`) never
plot or print; the ``plot_*`` functions draw on a fresh
:class:`matplotlib.figure.Figure` (no pyplot state), save a PNG and return
its path.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from scipy import signal, stats

from ..inference._screen import LaplaceFit
from ..inference._summaries import pooled_draws
from ..model._likelihood import leg_active_output
from ..model._model import Model, equivalent_acceleration

__all__ = [
    "FEATURE_LABELS", "features", "binned_trend", "acf", "ccf", "twitch_triggered_average", "spectrum",
    "findings", "spectrum_finding", "loo_pit_summary", "point_residuals", "fit_residuals", "leg_residuals",
    "has_pulses",
]  # fmt: skip

FEATURE_LABELS = {
    "angle": "knee angle [deg]",
    "velocity": "angular velocity [deg/s]",
    "time": "time in trial [s]",
    "ipi": "preceding interpulse interval [s]",
    "pulse_count": "pulses so far in trial [-]",
    "u": "recruitment level u of last pulse [-]",
}
# (words, unit) of each feature for the sentences of :func:`findings`
FEATURE_WORDS = {
    "angle": ("knee angle", "deg"),
    "velocity": ("angular velocity", "deg/s"),
    "time": ("time in trial", "s"),
    "ipi": ("preceding interpulse interval", "s"),
    "pulse_count": ("pulse count in the trial", "pulses"),
    "u": ("recruitment level u", ""),
}
_BAND_Z = 1.96  # two-sided 95 % normal quantile


# ----------------------------------------------------------------------------- helpers


def _valid(residual, sample_mask) -> np.ndarray:
    return np.asarray(sample_mask, bool) & np.isfinite(np.asarray(residual, float))


def _centred(x, mask) -> np.ndarray:
    """``x`` minus its mean over ``mask``, zero outside the mask (so products vanish there)."""
    x = np.asarray(x, float)
    return np.where(mask, x - x[mask].mean(), 0.0)


def _lagged_products(x, y, max_lag: int) -> np.ndarray:
    """Σ_k x_k y_{k+j} for j = 0..max_lag (biased: no division by the number of pairs)."""
    n = len(x)
    return np.array([x[: n - j] @ y[j:] if j < n else 0.0 for j in range(max_lag + 1)])


def _with_band(value: np.ndarray, n: int) -> dict:
    band = _BAND_Z / math.sqrt(n)
    lags = np.arange(len(value))
    return {"lags": lags, "value": value, "band": band, "n_outside": int(np.sum(np.abs(value[1:]) > band)), "n": n}


def _lag1(residual, mask) -> float:
    x = _centred(residual, mask)
    return float(_lagged_products(x, x, 1)[1] / (x @ x))


def format_p(p: float) -> str:
    return "p < 0.001" if p < 0.001 else f"p = {p:.3f}"


def _fmt_num(v: float) -> str:
    return f"{v:+.0f}".replace("-", "−") if abs(v) >= 10 else f"{v:+.2g}".replace("-", "−")


def _fmt_centre(v: float) -> str:
    return f"{v:.3g}".replace("-", "−")


def _fmt_lags(lags) -> str:
    """[3, 4, 5, 8] -> '3–5, 8'."""
    runs, start = [], None
    for i, lag in enumerate(lags):
        start = lag if start is None else start
        if i + 1 == len(lags) or lags[i + 1] != lag + 1:
            runs.append(f"{start}" if start == lag else f"{start}–{lag}")
            start = None
    return ", ".join(runs)


def _significant_lags(result: dict, alpha: float) -> tuple[bool, np.ndarray]:
    """Whether the lags ≥ 1 stand out beyond chance, and which lags to name.

    Under a white residual each lag falls outside the 95 % band with
    probability 0.05, so a few lags out mean nothing (flagging any count above
    5 % would flag white noise about half the time with 50 lags).  The lags
    stand out when either their number outside the band has a binomial
    probability below ``alpha``, or one lag exceeds the Bonferroni band
    z_{1 − alpha/(2 n_lags)}/√N (a single strong lag).  Named are the lags
    beyond the Bonferroni band if any, else those beyond the 95 % band.
    """
    lags, value, band = result["lags"], result["value"], result["band"]
    pos = lags >= 1
    out = lags[pos & (np.abs(value) > band)]
    n_lags = int(pos.sum())
    strong = lags[pos & (np.abs(value) > band / _BAND_Z * stats.norm.isf(alpha / (2 * n_lags)))]
    p_count = stats.binom.sf(len(out) - 1, n_lags, 0.05) if len(out) else 1.0
    return bool(p_count < alpha or len(strong)), (strong if len(strong) else out)


# ----------------------------------------------------------------------------- numerics


def has_pulses(stimulation) -> bool:
    """Whether a residual's stimulation holds a pulse; without one (a pendulum test) there is nothing
    to correlate the residual with or to average it over."""
    return bool(np.any(np.nan_to_num(np.asarray(stimulation, float)) > 0))


def features(angle, velocity, stimulation, sample_mask, trial_start, dt: float = 0.01) -> dict[str, np.ndarray]:
    """Per-sample features against which to look at the residual.

    Returns a dict of (N,) float arrays, NaN outside ``sample_mask``:

    - ``"angle"`` [deg], ``"velocity"`` [deg/s]: as given;
    - ``"time"`` [s]: time in trial, ``(k - trial_start[k]) * dt``;
    - ``"ipi"`` [s]: interval between the most recent pulse at or before k and
      the pulse before it in the same trial; NaN before the trial's second pulse;
    - ``"pulse_count"``: pulses delivered in the trial at or before k;
    - ``"u"``: recruitment level of the most recent pulse in the trial at or
      before k; NaN before the trial's first pulse.

    A pulse is any sample with ``stimulation > 0``, masked or not (a pulse in a
    gap inside a trial was still delivered).
    """
    mask = np.asarray(sample_mask, bool)
    start = np.asarray(trial_start, int)
    u = np.nan_to_num(np.asarray(stimulation, float))
    n = len(u)
    k = np.arange(n)
    pulse = u > 0
    # index of the most recent pulse at or before k (−1: none yet)
    last = np.maximum.accumulate(np.where(pulse, k, -1))
    # index of the pulse before each pulse (−1: none)
    prev = np.concatenate(([-1], last[:-1]))
    cum = np.cumsum(pulse)
    count = cum - np.concatenate(([0], cum))[start]
    has_last = last >= start
    safe_last = np.where(has_last, last, 0)
    has_pair = has_last & (prev[safe_last] >= start)
    ipi = np.where(has_pair, (safe_last - prev[safe_last]) * dt, np.nan)
    out = {
        "angle": np.asarray(angle, float).copy(),
        "velocity": np.asarray(velocity, float).copy(),
        "time": (k - start) * float(dt),
        "ipi": ipi,
        "pulse_count": count.astype(float),
        "u": np.where(has_last, u[safe_last], np.nan),
    }
    for v in out.values():
        v[~mask] = np.nan
    return out


def binned_trend(residual, feature, sample_mask, n_bins: int = 10, weights=None) -> dict:
    """Mean residual in quantile bins of a feature, and a test that all bin means are zero.

    The standard error of a bin mean uses an effective sample size that
    accounts for the residual's autocorrelation: with ρ the lag-1
    autocorrelation of the whole masked residual (see :func:`acf`),
    ``n_eff = n (1 − ρ) / (1 + ρ)`` clipped to [1, n] (the AR(1) variance
    inflation of a mean over a contiguous run).  With ``weights`` the bin mean
    is weighted and n is Kish's ``(Σw)² / Σw²``.

    The trend test is χ² = Σ_b (mean_b / se_b)² against the χ² distribution
    with as many degrees of freedom as bins.  Bins are quantiles of the feature
    over masked-in samples with a finite feature; for a discrete feature tied
    quantiles merge, so there may be fewer than ``n_bins`` bins (the degrees
    of freedom follow).  Note ρ includes any trend itself, so a strong trend
    makes the test conservative, never liberal.

    Returns ``centre`` (median feature), ``mean``, ``se``, ``count`` per bin and
    floats ``chi2``, ``p_value``, ``max_z`` (largest |mean/se|), ``rho``.
    """
    r = np.asarray(residual, float)
    f = np.asarray(feature, float)
    valid = _valid(r, sample_mask)
    rho = _lag1(r, valid)
    use = valid & np.isfinite(f)
    w_all = np.ones_like(r) if weights is None else np.asarray(weights, float)
    use &= np.isfinite(w_all) & (w_all > 0)
    edges = np.unique(np.quantile(f[use], np.linspace(0.0, 1.0, n_bins + 1)))
    idx = np.searchsorted(edges[1:-1], f[use], side="right")
    rs, fs, ws = r[use], f[use], w_all[use]
    centre, mean, se, count = [], [], [], []
    for b in range(max(len(edges) - 1, 1)):
        sel = idx == b
        x, w = rs[sel], ws[sel]
        n_w = np.sum(w) ** 2 / np.sum(w**2) if sel.any() else 0.0
        if n_w < 1.5:  # no spread to estimate from
            continue
        m = np.sum(w * x) / np.sum(w)
        var = np.sum(w * (x - m) ** 2) / np.sum(w) * n_w / (n_w - 1.0)
        n_eff = np.clip(n_w * (1.0 - rho) / (1.0 + rho), 1.0, n_w)
        centre.append(np.median(fs[sel]))
        mean.append(m)
        se.append(math.sqrt(var / n_eff))
        count.append(int(sel.sum()))
    if not mean:
        raise ValueError("no bin with at least two masked-in samples of finite feature")
    mean, se = np.array(mean), np.array(se)
    z = mean / se
    chi2 = float(np.sum(z**2))
    return {
        "centre": np.array(centre), "mean": mean, "se": se, "count": np.array(count, int),
        "chi2": chi2, "p_value": float(stats.chi2.sf(chi2, len(z))), "max_z": float(np.max(np.abs(z))),
        "rho": rho,
    }  # fmt: skip


def acf(residual, sample_mask, max_lag: int = 50) -> dict:
    """Autocorrelation of the masked residual at lags 0..max_lag with its 95 % band.

    ``value[j] = Σ x_k x_{k+j} / Σ x_k²`` with x the residual minus its mean
    over masked-in samples, the products taken only where both samples are
    masked in (biased estimator).  The band is ±1.96/√N with N the number of
    masked-in samples: the standard deviation of the sample autocorrelation of
    white noise of length N.  (Using the length of the full correlation
    sequence, 2N − 1, as SysIdentPy does, gives a band √2 too narrow and flags
    a white residual.)

    Returns ``lags``, ``value``, ``band``, ``n_outside`` (lags ≥ 1 with
    |value| > band) and ``n``.
    """
    mask = _valid(residual, sample_mask)
    x = _centred(residual, mask)
    value = _lagged_products(x, x, max_lag) / (x @ x)
    return _with_band(value, int(mask.sum()))


def ccf(residual, stimulation, sample_mask, max_lag: int = 50) -> dict:
    """Cross-correlation of the stimulation at k with the residual at k + j, j = 0..max_lag.

    ``value[j] = Σ s_k r_{k+j} / √(Σ s² Σ r²)`` with both series demeaned over
    masked-in samples and products only where both samples are masked in.  A
    residual that follows the pulses at some lag means the twitch's timing or
    shape is wrong.  The band is ±1.96/√N as in :func:`acf`; it assumes at
    least one of the two series is white, so an autocorrelated residual
    against a periodic pulse train crosses it more often than 5 %.

    Returns ``lags``, ``value``, ``band``, ``n_outside`` (lags ≥ 1), ``n``.
    """
    mask = _valid(residual, sample_mask)
    s = _centred(np.nan_to_num(np.asarray(stimulation, float)), mask)
    r = _centred(residual, mask)
    value = _lagged_products(s, r, max_lag) / math.sqrt((s @ s) * (r @ r))
    return _with_band(value, int(mask.sum()))


def twitch_triggered_average(residual, stimulation, sample_mask, window: int = 30, groups=None) -> dict:
    """Mean residual at p + j, j = 0..window−1, over pulses p whose whole window is masked in.

    With ``groups`` ((N,) labels read at the pulse samples; NaN labels are
    skipped) there is one average per label, else one labelled ``"all"``.
    Each has ``mean`` and ``se`` (pulse-to-pulse standard deviation / √count)
    of shape (window,) and ``count`` pulses.  Twitches of neighbouring pulses
    that fall inside the window are not deconvolved: at a fixed interpulse
    interval their mean shows as a bump one interval later.
    """
    r = np.asarray(residual, float)
    mask = _valid(r, sample_mask)
    u = np.nan_to_num(np.asarray(stimulation, float))
    n = len(r)
    pulses = np.flatnonzero((u > 0) & mask)
    pulses = pulses[pulses + window <= n]
    lags = np.arange(window)
    pulses = pulses[mask[pulses[:, None] + lags[None, :]].all(axis=1)]
    segments = r[pulses[:, None] + lags[None, :]]
    if groups is None:
        labels = np.full(len(pulses), "all", dtype=object)
    else:
        labels = np.asarray(groups)[pulses]
    out = {}
    keep = np.array([g == g for g in labels], bool)  # drops NaN labels
    for label in np.unique(labels[keep]):
        seg = segments[labels == label]
        c = len(seg)
        se = seg.std(axis=0, ddof=1) / math.sqrt(c) if c > 1 else np.full(window, np.nan)
        key = label.item() if isinstance(label, np.generic) else label
        out[key] = {"mean": seg.mean(axis=0), "se": se, "count": c}
    return {"lags": lags, "groups": out}


def spectrum(residual, sample_mask, dt: float = 0.01, nperseg: int = 256) -> dict:
    """Welch power spectral density of the masked residual.

    Welch's estimate is taken on each contiguous masked-in run at least
    ``nperseg`` long (no spectrum across a gap) and the runs are averaged,
    weighted by their number of segments; if no run is that long, ``nperseg``
    shrinks to the longest run.  Returns ``freq_hz``, ``psd`` [(deg/s²)²/Hz]
    and ``peak_hz``, the frequency of the largest PSD above 1 Hz (NaN if none).
    """
    r = np.asarray(residual, float)
    mask = _valid(r, sample_mask)
    padded = np.concatenate(([False], mask, [False])).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    runs = list(zip(edges[::2], edges[1::2]))
    if not runs:
        raise ValueError("no masked-in samples")
    nperseg = min(nperseg, max(b - a for a, b in runs))
    step = nperseg - nperseg // 2
    freq, total, weight = None, 0.0, 0
    for a, b in runs:
        if b - a < nperseg:
            continue
        freq, p = signal.welch(r[a:b], fs=1.0 / dt, nperseg=nperseg, detrend="constant")
        n_seg = (b - a - nperseg // 2) // step
        total, weight = total + n_seg * p, weight + n_seg
    psd = total / weight
    above = freq > 1.0
    peak = float(freq[above][np.argmax(psd[above])]) if above.any() else float("nan")
    return {"freq_hz": freq, "psd": psd, "peak_hz": peak}


#: A spectral peak above 1 Hz stands out when it exceeds the median PSD over 1-20 Hz this many times.
PEAK_RATIO = 5.0
#: Lowest frequency [Hz] of a residual peak taken for the accelerometer's skin-motion resonance (its
#: prior: 18 Hz, within a factor 1.35 at 1 sd); below it the peak is as slow as the shank's own swing
#: (about 1 Hz for G' = 1800 deg/s²).
RESONANCE_FROM_HZ = 5.0


def spectrum_finding(spec: dict) -> list[str]:
    """A sentence if the residual's spectrum has a peak above 1 Hz that stands out (:data:`PEAK_RATIO`)."""
    f, psd = spec["freq_hz"], spec["psd"]
    band = (f > 1.0) & (f <= 20.0)
    if not np.isfinite(spec["peak_hz"]) or not band.any():
        return []
    ratio = float(psd[np.argmin(np.abs(f - spec["peak_hz"]))] / np.median(psd[band]))
    if ratio < PEAK_RATIO:
        return []
    like = ("the accelerometer's skin-motion resonance rings like this" if spec["peak_hz"] >= RESONANCE_FROM_HZ else
            "as slow as the shank's own swing: its passive stiffness, damping or a friction the model lacks")
    return [f"The residual's spectrum peaks at {spec['peak_hz']:.1f} Hz, {ratio:.0f}× its median over 1-20 Hz: "
            f"an oscillation the model lacks ({like})."]


def loo_pit_summary(pit, n_independent: int) -> dict:
    """Calibration of LOO-PIT values ``pit`` (uniform for a calibrated predictive).

    ``n_independent``: how many of them are close to independent (the 1-s
    segments; the windows within one are not), which sets the 95 % band of the
    ECDF's distance from uniform (Kolmogorov: 1.36/√n).  Returns the ECDF
    distance, the band, the share in the outer 5 % tails (10 % expected), the
    mean (0.5 expected) and ``notes``: what stands out, in words.
    """
    pit = np.sort(np.asarray(pit, float)[np.isfinite(pit)])
    n = pit.size
    if n == 0:
        raise ValueError("no LOO-PIT values")
    ecdf_hi = np.arange(1, n + 1) / n
    distance = float(max(np.max(ecdf_hi - pit), np.max(pit - (ecdf_hi - 1.0 / n))))
    band = 1.36 / math.sqrt(max(1, min(n, n_independent)))
    tails = float(np.mean((pit < 0.05) | (pit > 0.95)))
    mean = float(pit.mean())
    notes = []
    if distance > band:
        shape = []
        if abs(mean - 0.5) > band / 2:
            shape.append(f"the mean PIT is {mean:.2f} (0.5 expected): the model {'under' if mean > 0.5 else 'over'}-predicts")
        if tails > 0.15:
            shape.append(f"{100 * tails:.0f} % of the windows lie in the outer 5 % tails (10 % expected): the predictive "
                         "distribution is too narrow, or misses a systematic error")
        elif tails < 0.05:
            shape.append(f"only {100 * tails:.0f} % lie in the outer 5 % tails (10 % expected): the predictive is too wide")
        notes.append(f"LOO-PIT departs from uniform (ECDF distance {distance:.3f} > band {band:.3f}); " + "; ".join(shape or ["its shape is irregular"]) + ".")
    return {"distance": distance, "band": band, "tail_share": tails, "mean": mean, "n": n, "notes": notes}


def findings(trends: dict[str, dict], acf_result: dict, ccf_result: dict | None, alpha: float = 0.01) -> list[str]:
    """Plain sentences for what stands out; ``[]`` when nothing does.

    One sentence per feature whose trend has ``p_value < alpha`` (naming the
    bins with the most negative and most positive mean), one if the acf lags
    stand out beyond chance and one if the ccf lags do, naming them.  A lag
    set stands out when more lags leave the 95 % band than chance allows
    (binomial probability below ``alpha`` at 5 % per lag: ≥ 9 of 50 at
    alpha = 0.01) or one lag leaves the Bonferroni band at ``alpha``; the
    literal "any lag outside the 95 % band" would flag most white residuals.
    ``ccf_result`` is ``None`` where the trials hold no pulse.
    """
    out = []
    for key, t in trends.items():
        if not t["p_value"] < alpha or len(t["mean"]) < 2:  # one bin (a single recruitment level): an offset, not a change
            continue
        words, unit = FEATURE_WORDS.get(key, (key, ""))
        unit = f" {unit}" if unit else ""
        lo, hi = (
            f"{_fmt_num(t['mean'][b])} deg/s² near {_fmt_centre(t['centre'][b])}{unit}"
            for b in (np.argmin(t["mean"]), np.argmax(t["mean"]))
        )
        out.append(
            f"the residual changes with {words} (χ² = {t['chi2']:.0f} on {len(t['mean'])} bins, "
            f"{format_p(t['p_value'])}): mean {lo}, {hi}"
        )
    if _significant_lags(acf_result, alpha)[0]:
        n_lags = int(np.sum(acf_result["lags"] >= 1))
        out.append(
            f"the residual is autocorrelated beyond the 95 % band at {acf_result['n_outside']} of {n_lags} lags: "
            "the model misses dynamics"
        )
    flagged, lags = _significant_lags(ccf_result, alpha) if ccf_result is not None else (False, ())
    if flagged:
        out.append(
            f"the residual is correlated with the stimulation at lag{'s' if len(lags) > 1 else ''} "
            f"{_fmt_lags(list(lags))} samples: "
            "the twitch's timing or shape is off"
        )
    return out


def leg_residuals(fit: LaplaceFit, leg: str) -> dict[str, np.ndarray]:
    """One-step residual of the equivalent acceleration at the screen's mode of ``leg`` (its modal d).

    Returns per-sample arrays over the identification trials (with the likelihood's
    gaps, masked): residual, angle, velocity, stimulation, sample_mask, trial_start.
    """
    i = fit.legs.index(leg)
    values = {k: v for k, v in fit.values(leg).items() if k not in ("sigma", "nu")}
    d = int(np.argmax(fit.delay_posterior[i]))
    K = fit.data.max_shift
    shift = int(np.bincount(fit.shifts[i], minlength=K + 1).argmax()) if K else 0
    return point_residuals(fit.model, fit.data, i, values, d, shift)


def fit_residuals(idata, model: Model, data, leg: str) -> dict[str, np.ndarray]:
    """:func:`leg_residuals` for a saved (NUTS) fit: at the posterior medians of ``leg`` and its modal d and shift."""
    post = idata.posterior
    i = list(post["leg"].values).index(leg)
    flat = lambda name: pooled_draws(post, name)[:, i]  # noqa: E731
    values = {p.name: np.median(flat(p.name), axis=0) for e in model.effects for p in e.declared_params()}
    d = int(np.bincount(flat("delay").astype(int)).argmax())
    shift = int(np.bincount(flat("delay_shift").astype(int)).argmax()) if "delay_shift" in post else 0
    return point_residuals(model, data, data.legs.index(leg), values, d, shift)


def point_residuals(model: Model, data, i: int, values: dict, d: int, shift: int) -> dict[str, np.ndarray]:
    """One-step residual of leg ``i`` of ``data`` (a LikelihoodData) for one parameter point."""
    x = {k: jnp.asarray(v[i]) for k, v in data.leg_arrays().items()}
    K = data.max_shift
    model = model.with_params({k: jnp.asarray(v, jnp.float32) for k, v in values.items()}, delay=d)
    if K:
        model = model.with_delay_shift(shift)
    M = np.asarray(leg_active_output(model, x, d, data.response_length, K, shift))
    e = np.asarray(equivalent_acceleration(model, x["angle"], x["velocity"], x["acceleration"], mask=x["sample_mask"]))
    mask = np.asarray(data.sample_mask[i])
    trial_start = np.asarray(data.trial_start[i], int)  # not the mask's: it starts again after an excluded stretch
    return {
        "residual": np.where(mask, e - M, np.nan),
        "angle": np.asarray(data.angle[i], float),
        "velocity": np.asarray(data.velocity[i], float),
        "stimulation": np.asarray(data.stimulation[i], float),
        "sample_mask": mask,
        "trial_start": trial_start,
    }
