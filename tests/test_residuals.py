"""Residual diagnostics (:mod:`quadshank.evaluation._residuals`) on residuals built with a known answer."""

import math

import numpy as np
import pytest
from scipy import stats

from quadshank import outputs
from quadshank.evaluation import _residuals as rd
DT = 0.01
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _ar1(rng, n, rho, sigma=1.0):
    """Stationary AR(1) of length n with lag-1 autocorrelation rho and marginal sd sigma."""
    e = rng.normal(0.0, sigma * math.sqrt(1 - rho**2), n)
    x = np.empty(n)
    x[0] = rng.normal(0.0, sigma)
    for k in range(1, n):
        x[k] = rho * x[k - 1] + e[k]
    return x


def _layout(n_trials, trial_len, gap):
    """sample_mask and trial_start of trials of trial_len samples separated by gap padding samples."""
    mask, start = [], []
    for i in range(n_trials):
        s = i * (trial_len + gap)
        mask += [True] * trial_len + [False] * gap
        start += [s] * (trial_len + gap)
    return np.array(mask), np.array(start)


def _leg(seed=0, n_trials=5, trial_len=1000, gap=20):
    """A synthetic leg: slow angle swings, pulses every 3–6 samples with random u."""
    rng = np.random.default_rng(seed)
    mask, start = _layout(n_trials, trial_len, gap)
    n = len(mask)
    t = np.arange(n) * DT
    angle = -40 + 30 * np.sin(2 * np.pi * 0.3 * t + rng.uniform(0, 6))
    velocity = np.gradient(angle, DT)
    stim = np.zeros(n)
    k = 0
    while k < n:
        stim[k] = rng.uniform(0.2, 1.0)
        k += int(rng.integers(3, 7))
    stim[~mask] = 0.0
    return rng, mask, start, angle, velocity, stim


# ----------------------------------------------------------------------------- features


def test_features_exact_values():
    # trial A: samples 0..9, gap 10..11, trial B: 12..19
    mask = np.array([True] * 10 + [False] * 2 + [True] * 8)
    start = np.array([0] * 12 + [12] * 8)
    stim = np.zeros(20)
    stim[[2, 5, 9, 14, 18]] = [0.5, 0.7, 0.3, 0.9, 0.4]
    angle, velocity = np.linspace(-60, 0, 20), np.full(20, 5.0)
    f = rd.features(angle, velocity, stim, mask, start, dt=DT)
    assert set(f) == set(rd.FEATURE_LABELS) == {"angle", "velocity", "time", "ipi", "pulse_count", "u"}
    nan = np.nan
    exp_time = np.r_[np.arange(10) * DT, nan, nan, np.arange(8) * DT]
    exp_count = np.r_[0, 0, 1, 1, 1, 2, 2, 2, 2, 3, nan, nan, 0, 0, 1, 1, 1, 1, 2, 2]
    exp_u = np.r_[nan, nan, 0.5, 0.5, 0.5, 0.7, 0.7, 0.7, 0.7, 0.3, nan, nan, nan, nan, 0.9, 0.9, 0.9, 0.9, 0.4, 0.4]
    # the pulse at 9 belongs to trial A: B's first ipi comes only with its second pulse
    exp_ipi = np.r_[[nan] * 5, [0.03] * 4, 0.04, nan, nan, [nan] * 6, 0.04, 0.04]
    np.testing.assert_allclose(f["time"], exp_time, atol=1e-12)
    np.testing.assert_array_equal(f["pulse_count"], exp_count)
    np.testing.assert_allclose(f["u"], exp_u)
    np.testing.assert_allclose(f["ipi"], exp_ipi, atol=1e-12)
    np.testing.assert_array_equal(np.isnan(f["angle"]), ~mask)
    assert np.isnan(f["velocity"][10:12]).all() and f["velocity"][0] == 5.0


# ----------------------------------------------------------------------------- binned_trend


def test_binned_trend_finds_time_trend():
    rng, mask, start, *_ = _leg(seed=1)
    time = np.where(mask, (np.arange(len(mask)) - start) * DT, np.nan)
    resid = rng.normal(0, 10, len(mask)) + 30 * time / 10.0
    resid[~mask] = 1e6  # padding must be ignored
    t = rd.binned_trend(resid, time, mask, n_bins=10)
    assert t["p_value"] < 1e-6
    assert len(t["mean"]) == 10 and np.all(np.diff(t["mean"]) > 0)
    assert np.all(np.diff(t["centre"]) > 0)
    assert t["count"].sum() == mask.sum() and np.all(np.abs(t["count"] - mask.sum() / 10) < 0.1 * mask.sum() / 10)
    np.testing.assert_allclose(t["mean"][[0, -1]], [1.5, 28.5], atol=2.0)


def test_binned_trend_white_noise_not_flagged():
    rng, mask, start, *_ = _leg(seed=2)
    time = np.where(mask, (np.arange(len(mask)) - start) * DT, np.nan)
    t = rd.binned_trend(rng.normal(0, 10, len(mask)), time, mask)
    assert t["p_value"] > 0.01 and t["max_z"] < 3.5
    assert abs(t["rho"]) < 0.05


def test_binned_trend_ar1_corrected_by_n_eff():
    rng = np.random.default_rng(3)
    mask, start = _layout(5, 2000, 10)
    resid = np.concatenate([np.r_[_ar1(rng, 2000, 0.9, 10.0), np.zeros(10)] for _ in range(5)])
    time = np.where(mask, (np.arange(len(mask)) - start) * DT, np.nan)
    t = rd.binned_trend(resid, time, mask, n_bins=10)
    assert abs(t["rho"] - 0.9) < 0.02
    assert t["p_value"] > 0.01
    # with the naive n = count, the same bins would be flagged
    naive_chi2 = 0.0
    edges = np.quantile(time[mask], np.linspace(0, 1, 11))
    idx = np.clip(np.searchsorted(edges, time[mask], side="right") - 1, 0, 9)
    for b in range(10):
        x = resid[mask][idx == b]
        naive_chi2 += (x.mean() / (x.std(ddof=1) / math.sqrt(len(x)))) ** 2
    assert stats.chi2.sf(naive_chi2, 10) < 0.01
    np.testing.assert_allclose(naive_chi2 / t["chi2"], (1 + t["rho"]) / (1 - t["rho"]), rtol=0.02)


def test_binned_trend_weights():
    rng = np.random.default_rng(4)
    n = 4000
    f = rng.uniform(0, 1, n)
    resid = rng.normal(0, 1, n)
    w = np.where(np.arange(n) % 2 == 0, 1.0, 0.0)
    a = rd.binned_trend(resid, f, np.ones(n, bool), n_bins=4, weights=w)
    b = rd.binned_trend(resid[::2], f[::2], np.ones(n // 2, bool), n_bins=4)
    np.testing.assert_allclose(a["mean"], b["mean"], rtol=1e-10)


# ----------------------------------------------------------------------------- acf / ccf


def test_acf_white_noise_band_and_ar1():
    rng = np.random.default_rng(5)
    resid = rng.normal(0, 1, 5200)
    mask = np.ones(5200, bool)
    mask[1000:1200] = False
    resid[1000:1200] = 1e6
    a = rd.acf(resid, mask, max_lag=50)
    assert a["band"] == pytest.approx(1.96 / math.sqrt(5000), rel=1e-12)
    assert a["value"][0] == pytest.approx(1.0) and len(a["value"]) == 51
    assert a["n_outside"] <= 6 and a["n_outside"] == np.sum(np.abs(a["value"][1:]) > a["band"])
    ar = rd.acf(_ar1(rng, 5000, 0.8), np.ones(5000, bool), max_lag=50)
    assert abs(ar["value"][1] - 0.8) < 0.03 and abs(ar["value"][2] - 0.64) < 0.05
    assert ar["n_outside"] > 10


def test_acf_matches_biased_estimator():
    rng = np.random.default_rng(6)
    x = rng.normal(0, 1, 300)
    a = rd.acf(x, np.ones(300, bool), max_lag=5)
    xc = x - x.mean()
    expected = [np.sum(xc[: 300 - j] * xc[j:]) / np.sum(xc**2) for j in range(6)]
    np.testing.assert_allclose(a["value"], expected, rtol=1e-12)


def test_ccf_peak_at_the_residual_lag():
    rng = np.random.default_rng(7)
    n = 6000
    stim = np.where(rng.uniform(size=n) < 0.2, rng.uniform(0.2, 1.0, n), 0.0)
    resid = rng.normal(0, 20, n)
    resid[4:] += 50 * stim[:-4]  # residual follows the input 4 samples later
    c = rd.ccf(resid, stim, np.ones(n, bool), max_lag=30)
    assert int(np.argmax(np.abs(c["value"]))) == 4
    assert c["value"][4] > 10 * c["band"]
    assert c["band"] == pytest.approx(1.96 / math.sqrt(n))


# ----------------------------------------------------------------------------- twitch-triggered average


def test_twitch_triggered_average_recovers_kernel_and_groups():
    rng = np.random.default_rng(8)
    n, window = 30000, 30
    j = np.arange(window)
    kernel = 40 * np.sin(np.pi * j / 15) * np.exp(-j / 10)
    pulses = np.cumsum(rng.integers(40, 60, 600))
    pulses = pulses[pulses < n - window]
    angle = -40 + 30 * np.sin(2 * np.pi * np.arange(n) / 3000)
    below = angle < -20
    stim = np.zeros(n)
    stim[pulses] = rng.uniform(0.2, 1.0, len(pulses))
    resid = rng.normal(0, 15, n)
    for p in pulses:
        resid[p : p + window] += kernel * (2.0 if below[p] else 1.0)
    mask = np.ones(n, bool)
    mask[5000:5100] = False
    resid[5000:5100] = 1e6
    inside = [p for p in pulses if mask[p : p + window].all()]

    tta = rd.twitch_triggered_average(resid, stim, mask, window=window)
    g = tta["groups"]["all"]
    assert g["count"] == len(inside) and list(tta["groups"]) == ["all"]
    np.testing.assert_array_equal(tta["lags"], j)
    assert g["count"] > 400
    # se from the pulse-to-pulse spread (kernel sizes of both groups mix in, so only a lower bound)
    assert np.all(g["se"] > 0.9 * 15 / math.sqrt(g["count"]))

    labels = np.where(below, "below -20 deg", "above -20 deg")
    split = rd.twitch_triggered_average(resid, stim, mask, window=window, groups=labels)["groups"]
    assert set(split) == {"below -20 deg", "above -20 deg"}
    assert split["below -20 deg"]["count"] + split["above -20 deg"]["count"] == g["count"]
    for label, scale in [("below -20 deg", 2.0), ("above -20 deg", 1.0)]:
        s = split[label]
        assert np.all(np.abs(s["mean"] - scale * kernel) < 3 * s["se"])
        np.testing.assert_allclose(s["se"], 15 / math.sqrt(s["count"]), rtol=0.25)


# ----------------------------------------------------------------------------- spectrum


def test_spectrum_finds_oscillation():
    rng = np.random.default_rng(9)
    mask, _ = _layout(3, 3000, 50)
    t = np.arange(len(mask)) * DT
    resid = rng.normal(0, 5, len(mask)) + 20 * np.sin(2 * np.pi * 7.0 * t)
    resid[~mask] = 1e6
    s = rd.spectrum(resid, mask, dt=DT, nperseg=256)
    assert abs(s["peak_hz"] - 7.0) < 0.4
    assert s["freq_hz"][-1] == pytest.approx(50.0) and s["psd"].shape == s["freq_hz"].shape
    # white-noise floor: 2 σ² dt (one-sided), away from the line
    floor = np.median(s["psd"][(s["freq_hz"] > 15) & (s["freq_hz"] < 45)])
    assert floor == pytest.approx(2 * 25 * DT, rel=0.2)


# ----------------------------------------------------------------------------- findings


def _all_trends(resid, mask, start, angle, velocity, stim):
    f = rd.features(angle, velocity, stim, mask, start, dt=DT)
    return {k: rd.binned_trend(resid, v, mask) for k, v in f.items()}


def test_findings_name_the_trend_and_stay_quiet_on_white_noise(capsys):
    rng, mask, start, angle, velocity, stim = _leg(seed=10)
    time = (np.arange(len(mask)) - start) * DT
    white = rng.normal(0, 10, len(mask))
    trends = _all_trends(white, mask, start, angle, velocity, stim)
    a, c = rd.acf(white, mask), rd.ccf(white, stim, mask)
    assert rd.findings(trends, a, c) == []

    trended = white + 30 * (time / 10.0 - 0.5)
    trends = _all_trends(trended, mask, start, angle, velocity, stim)
    notes = rd.findings({"time": trends["time"]}, rd.acf(white, mask), rd.ccf(white, stim, mask))
    assert len(notes) == 1 and "time in trial" in notes[0] and "p < 0.001" in notes[0]
    # one recruitment level throughout: a single bin is an offset, never a change with the feature
    offset = rd.binned_trend(white + 5.0, np.ones(len(mask)), mask)
    assert len(offset["mean"]) == 1 and offset["p_value"] < 0.01
    assert rd.findings({"recruitment": offset}, rd.acf(white, mask), rd.ccf(white, stim, mask)) == []
    assert capsys.readouterr().out == ""


def test_findings_acf_and_ccf_sentences():
    rng = np.random.default_rng(11)
    n = 6000
    mask = np.ones(n, bool)
    stim = np.where(rng.uniform(size=n) < 0.2, rng.uniform(0.2, 1.0, n), 0.0)
    resid = _ar1(rng, n, 0.8, 10.0)
    resid[4:] += 50 * stim[:-4]
    notes = rd.findings({}, rd.acf(resid, mask), rd.ccf(resid, stim, mask))
    a = rd.acf(resid, mask)
    assert len(notes) == 2
    assert f"at {a['n_outside']} of 50 lags" in notes[0] and "misses dynamics" in notes[0]
    assert "at lag 4 samples" in notes[1] and "twitch" in notes[1]


# ----------------------------------------------------------------------------- plots


def _is_png(path):
    return path.exists() and path.stat().st_size > 5000 and path.read_bytes()[:8] == PNG_MAGIC


def test_plots_write_pngs(tmp_path):
    rng, mask, start, angle, velocity, stim = _leg(seed=12, n_trials=2)
    time = (np.arange(len(mask)) - start) * DT
    resid = rng.normal(0, 10, len(mask)) + 30 * time / 10.0
    trends = _all_trends(resid, mask, start, angle, velocity, stim)
    a, c = rd.acf(resid, mask), rd.ccf(resid, stim, mask)
    notes = rd.findings(trends, a, c)
    groups = np.where(angle < -20, "below", "above")
    tta = rd.twitch_triggered_average(resid, stim, mask, groups=groups)
    spec = rd.spectrum(resid, mask)
    paths = [
        outputs.plot_trends(trends, tmp_path / "trends.png", notes=notes),
        outputs.plot_correlations(a, c, tmp_path / "corr.png", notes=["a note"]),
        outputs.plot_twitch_average(tta, tmp_path / "tta.png", dt=DT),
        outputs.plot_spectrum(spec, tmp_path / "spec.png", notes=None),
    ]
    for p in paths:
        assert _is_png(p), p


def test_spectrum_finding_names_a_resonance_and_stays_quiet_on_white_noise():
    rng = np.random.default_rng(4)
    n, dt = 6000, 0.01
    mask = np.ones(n, bool)
    white = rng.standard_normal(n)
    assert rd.spectrum_finding(rd.spectrum(white, mask, dt)) == []
    ringing = white + 2.0 * np.sin(2 * np.pi * 12.0 * dt * np.arange(n))
    (line,) = rd.spectrum_finding(rd.spectrum(ringing, mask, dt))
    assert "peaks at 12." in line and "skin-motion resonance" in line
    # a peak as slow as the shank's own swing is not the accelerometer's resonance
    swinging = white + 2.0 * np.sin(2 * np.pi * 1.5 * dt * np.arange(n))
    (line,) = rd.spectrum_finding(rd.spectrum(swinging, mask, dt))
    assert "peaks at 1." in line and "shank's own swing" in line and "skin-motion" not in line


def test_loo_pit_summary_reads_the_shape_of_a_miscalibrated_predictive():
    rng = np.random.default_rng(5)
    n = 4000
    calibrated = rd.loo_pit_summary(rng.uniform(size=n), 100)
    assert calibrated["notes"] == [] and calibrated["distance"] < calibrated["band"]
    assert 0.08 < calibrated["tail_share"] < 0.12
    z = rng.standard_normal(n)
    narrow = rd.loo_pit_summary(stats.norm.cdf(2.0 * z), 100)  # the predictive's sd is half the truth's
    assert "too narrow" in narrow["notes"][0] and narrow["tail_share"] > 0.3
    wide = rd.loo_pit_summary(stats.norm.cdf(0.4 * z), 100)
    assert "too wide" in wide["notes"][0]
    high = rd.loo_pit_summary(stats.norm.cdf(z + 0.6), 100)  # the data lie above the predictions
    assert "under-predicts" in high["notes"][0]


def test_findings_are_listed_as_sentences_of_their_own():
    """Each leg's findings in a report read as separate sentences, whatever case and stop each came with."""
    from quadshank.outputs._loop import findings_markdown

    lines = findings_markdown({"A-left": ["the residual changes with knee angle (p < 0.001): mean −3 near 10",
                                          "The residual's spectrum peaks at 1.5 Hz."], "B-left": []})
    assert lines == ["- A-left: The residual changes with knee angle (p < 0.001): mean −3 near 10. "
                     "The residual's spectrum peaks at 1.5 Hz.", "- B-left: nothing stands out."]
