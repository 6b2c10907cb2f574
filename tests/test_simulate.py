"""Tests of the simulated cohort (quadshank.data._simulate)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from quadshank.data._paper import LEGS, RMS_ANGLE, SAMPLING_PERIOD_S, TABLE_I, TABLE_III
from quadshank.data._simulate import (
    EFFECT_PARAMETERS,
    EFFECTS,
    PASSIVE_TRUTH,
    SENSOR,
    STIMULATION_DENSITY,
    _sampled_twitch,
    default_truth,
    isolated_pulses,
    simulate_cohort,
    simulate_response,
    stimulation_sequence,
    write_truth,
)

TS = SAMPLING_PERIOD_S


# ----------------------------------------------------------------------------- helpers
def equivalent_acceleration(trial, leg_truth):
    """Eq. (8) on recorded data: M/I = φ̈ + D'φ̇ + G' sin φ − k1'(exp(−k2 φ) − 1)."""
    p = leg_truth["passive"]
    a, v = trial.angle_deg, trial.velocity_deg_s
    return (
        trial.acceleration_deg_s2
        + p["damping"] * v
        + p["gravity"] * np.sin(np.deg2rad(a))
        - p["k1"] * (np.exp(-p["k2"] * a) - 1.0)
    )


def isolated_twitches(trial, leg_truth, epoch=25):
    """Integrated twitch responses of isolated pulses, with φ and φ̇ at d samples after the pulse."""
    eq = equivalent_acceleration(trial, leg_truth)
    pulses = trial.pulse_indices
    ks = pulses[isolated_pulses(pulses, trial.n_samples)]
    d = leg_truth["active"]["delay_paper_samples"]
    total = np.array([eq[k : k + epoch].sum() for k in ks])
    return ks, total, trial.angle_deg[ks + d], trial.velocity_deg_s[ks + d]


def model3_factor(leg_truth, angle, velocity):
    act = leg_truth["active"]
    return np.maximum(0.0, 1 + act["gamma_angle"] * angle) * np.maximum(0.0, 1 + act["gamma_velocity"] * velocity)


_RUNS: dict = {}


def run(legs=("JM-left",), minutes=0.5, seed=0, effects=(), trials=(1, 2, 3), twitch_cv=0.2):
    """Cached simulate_cohort (runs are deterministic)."""
    key = (tuple(legs), minutes, seed, tuple(effects), tuple(trials), twitch_cv)
    if key not in _RUNS:
        _RUNS[key] = simulate_cohort(legs=legs, minutes=minutes, seed=seed, effects=effects, trials=trials,
                                     twitch_cv=twitch_cv)
    return _RUNS[key]


EFFECT_LEG = "JM-left"
EFFECT_MINUTES = 3.0


def effect_run(*effects):
    return run(legs=(EFFECT_LEG,), minutes=EFFECT_MINUTES, seed=0, effects=effects, trials=(1,))


# ----------------------------------------------------------------------------- truth
def test_unknown_names_raise():
    with pytest.raises(ValueError, match="known effects: " + ", ".join(EFFECTS)):
        simulate_cohort(legs=("JM-left",), minutes=0.1, effects=("fatigue", "cramp"))
    with pytest.raises(ValueError, match="cramp"):
        default_truth(effects=("cramp",))
    with pytest.raises(ValueError, match="known legs"):
        default_truth(legs=("XX-left",))
    with pytest.raises(ValueError, match="trial"):
        simulate_cohort(legs=("JM-left",), minutes=0.1, trials=(4,))


def test_default_truth_is_plausible_and_json():
    truth = default_truth(effects=EFFECTS)
    assert json.loads(json.dumps(truth)) == truth
    assert truth["effects"] == list(EFFECTS)
    assert set(truth["legs"]) == set(LEGS)
    for leg, lt in truth["legs"].items():
        p, act = lt["passive"], lt["active"]
        assert {k: p[k] for k in PASSIVE_TRUTH[leg]} == PASSIVE_TRUTH[leg]
        assert 0.8 <= p["natural_frequency_hz"] <= 1.0
        assert 0.07 <= p["damping_ratio"] <= 0.13
        assert 0.10 <= p["elastic_fraction_of_gravity_at_-40deg"] <= 0.20
        at60 = p["k1"] * (1 - math.exp(-60 * p["k2"])) / (p["gravity"] * math.sin(math.radians(60)))
        assert at60 < 0.03
        assert act["G2"] == TABLE_III[leg]["G2"]
        # fractional delay whose nearest whole sample is the paper's
        assert act["delay_samples"] != round(act["delay_samples"])
        assert round(act["delay_samples"]) == TABLE_I[leg]["delay"]
        assert act["delay_s"] == pytest.approx(act["delay_samples"] * TS)
        assert 0.030 < act["twitch_tc_s"] < 0.045
        assert set(lt["effects"]) == set(EFFECTS)
        assert lt["model1_equivalent"]["G1"] == act["G2"]
    assert default_truth(legs=("OT-left",))["legs"]["OT-left"]["effects"] == {}


def test_model2_equivalent_reproduces_sampled_twitch():
    truth = default_truth()
    for leg, lt in truth["legs"].items():
        act, m2 = lt["active"], lt["model2_equivalent"]
        y = _sampled_twitch(act["G2"], act["twitch_tc_s"], act["delay_samples"], n=80)
        d = m2["delay"]
        assert d == math.floor(act["delay_samples"])
        u = np.zeros(80)
        u[0] = 1.0
        sim = np.zeros(80)
        for k in range(80):
            val = 0.0
            if k >= 1:
                val -= m2["a1"] * sim[k - 1]
            if k >= 2:
                val -= m2["a2"] * sim[k - 2]
            if k - 1 - d >= 0:
                val += m2["b1"] * u[k - 1 - d]
            if k - 2 - d >= 0:
                val += m2["b2"] * u[k - 2 - d]
            sim[k] = val
        np.testing.assert_allclose(sim, y, atol=1e-6 * act["G2"])
        # a double pole at exp(−T_s/tc): a2 is Table II's
        assert m2["a2"] == pytest.approx(math.exp(-2 * TS / act["twitch_tc_s"]), rel=1e-6)


def test_write_truth_roundtrip(tmp_path):
    _, truth = run()
    path = write_truth(truth, tmp_path / "sub" / "truth.json")
    assert json.loads(path.read_text()) == json.loads(json.dumps(truth))
    assert path.read_text().startswith("{\n  ")
    assert [p.name for p in path.parent.iterdir()] == ["truth.json"]


# ----------------------------------------------------------------------------- determinism
def test_same_seed_identical_different_seed_differs():
    c1, t1 = run(seed=3)
    c2, t2 = simulate_cohort(legs=("JM-left",), minutes=0.5, seed=3)
    c3, _ = run(seed=4)
    assert t1 == t2
    for a, b, c in zip(c1, c2, c3):
        np.testing.assert_array_equal(a.angle_deg, b.angle_deg)
        np.testing.assert_array_equal(a.acceleration_deg_s2, b.acceleration_deg_s2)
        np.testing.assert_array_equal(a.stimulation, b.stimulation)
        assert not np.array_equal(a.stimulation, c.stimulation)
        assert not np.array_equal(a.angle_deg, c.angle_deg)
    assert c1.attrs == {"simulated": 1, "seed": 3, "minutes": 0.5, "effects": [], "twitch_cv": 0.2,
                        "truth_format": "quadshank-truth/1"}


def test_subset_of_legs_and_trials_reproduces_full_run():
    full, _ = run(legs=("TN-left", "JM-left"), seed=5)
    part, _ = run(legs=("JM-left",), seed=5)
    only2, _ = run(legs=("JM-left",), seed=5, trials=(2,))
    for trial in (1, 2, 3):
        a, b = full.get("JM-left", trial), part.get("JM-left", trial)
        np.testing.assert_array_equal(a.angle_deg, b.angle_deg)
        np.testing.assert_array_equal(a.acceleration_deg_s2, b.acceleration_deg_s2)
        np.testing.assert_array_equal(a.stimulation, b.stimulation)
    np.testing.assert_array_equal(only2.get("JM-left", 2).angle_deg, part.get("JM-left", 2).angle_deg)
    assert len(only2) == 1


def test_longer_sequence_starts_with_shorter():
    dens = STIMULATION_DENSITY["TN-left"]["1.0"]
    short = stimulation_sequence(np.random.default_rng(1), 3000, dens)
    long = stimulation_sequence(np.random.default_rng(1), 60000, dens)
    np.testing.assert_array_equal(long[: short.size], short)
    assert long[short.size] >= 3000


# ----------------------------------------------------------------------------- protocol
def test_stimulation_protocol():
    cohort, truth = run(legs=("TN-left", "JM-left"), seed=5)
    assert len(cohort) == 6
    for trial in cohort:
        assert trial.n_samples == 3000
        assert trial.sampling_period_s == TS
        np.testing.assert_allclose(trial.time_s, np.arange(3000) * TS)
        assert not trial.velocity_measured
        values = set(np.unique(trial.stimulation[trial.stimulation > 0]))
        assert values == ({0.5} if trial.trial == 3 else {1.0})
        pulses = trial.pulse_indices
        ipi = np.diff(pulses) * TS
        assert ipi.min() >= 0.02 - 1e-9
        assert (ipi <= 0.12 + 1e-9).sum() > 10  # short IPIs: summation
        assert (ipi >= 0.5 - 1e-9).sum() > 10  # long IPIs
        facts = truth["legs"][trial.key]["trials"][str(trial.trial)]
        assert facts["n_pulses"] == pulses.size
        assert facts["n_isolated"] == isolated_pulses(pulses, trial.n_samples).sum()
        if trial.trial == 1:  # the identification trial has isolated twitches
            assert facts["n_isolated"] > 5
        assert facts["rms_angle_deg"] == pytest.approx(np.sqrt(np.mean(trial.angle_deg**2)))
        # goniometer quantisation
        steps = trial.angle_deg / SENSOR["angle_resolution_deg"]
        np.testing.assert_allclose(steps, np.round(steps), atol=1e-6)


def test_isolated_pulse_rule():
    pulses = np.array([10, 40, 100, 102, 200, 260, 400])
    mask = isolated_pulses(pulses, 440)
    # 10: too close to the start; 100/102: a doublet; 400: the recording ends within 500 ms
    assert mask.tolist() == [False, True, False, False, True, True, False]


# ----------------------------------------------------------------------------- twitch
@pytest.mark.parametrize("leg", ["TN-right", "OT-left"])
def test_unmodulated_twitch_sums_to_G2_with_fractional_delay(leg):
    truth = default_truth(legs=(leg,))["legs"][leg]["active"]
    stim = np.zeros(200)
    stim[20] = 1.0
    out = simulate_response(leg, stim)
    act = out["twitch_activation"]
    assert act.sum() == pytest.approx(truth["G2"], rel=0.05)
    onset = np.flatnonzero(act > 0)[0] - 20
    assert onset == math.ceil(truth["delay_samples"])
    assert np.all(act[: 20 + math.floor(truth["delay_samples"]) + 1] == 0)
    expected = _sampled_twitch(truth["G2"], truth["twitch_tc_s"], truth["delay_samples"], n=180)
    np.testing.assert_allclose(act[20:], expected, rtol=1e-6, atol=1e-6 * truth["G2"])


def test_a_hidden_recruitment_curve_shrinks_a_half_level_pulse_to_its_power():
    stim = np.zeros(200)
    stim[20] = 0.5
    linear = simulate_response("JM-left", stim)["twitch_activation"].sum()
    curved = simulate_response("JM-left", stim, effects=("recruitment_power",))["twitch_activation"].sum()
    kappa = EFFECT_PARAMETERS["recruitment_power"]["kappa"]
    assert curved / linear == pytest.approx(0.5 ** (kappa - 1.0), rel=1e-9)
    stim[20] = 1.0  # a full-level pulse recruits the whole muscle either way
    assert simulate_response("JM-left", stim, effects=("recruitment_power",))["twitch_activation"].sum() == \
        pytest.approx(simulate_response("JM-left", stim)["twitch_activation"].sum(), rel=1e-12)


def test_equivalent_acceleration_of_twitch_from_rest():
    leg = "JM-left"
    lt = default_truth(legs=(leg,))["legs"][leg]
    stim = np.zeros(300)
    stim[100] = 1.0
    stim[200] = 1.0
    out = simulate_response(leg, stim, noise=True, seed=2)
    m = out["equivalent_acceleration"]
    G2 = lt["active"]["G2"]
    # from rest (f = g = 1 at the onset) the twitch is the unmodulated one, summing to ~G2
    true_sum = m[100:140].sum()
    assert 0.95 * G2 < true_sum < 1.0 * G2
    # a twitch is scaled by f·g of the state at its onset (t_j + tau), not modulated afterwards
    onset = 200 + int(math.ceil(lt["active"]["delay_samples"]))
    fg = model3_factor(lt, out["true_angle_deg"][onset - 1 : onset], out["true_velocity_deg_s"][onset - 1 : onset])[0]
    assert abs(fg - 1.0) > 0.05  # the shank is moving, so the check below has teeth
    tail = m[100:200]  # the first twitch has died out before the second
    assert abs(tail[-10:]).max() < 1.0
    assert m[200:260].sum() == pytest.approx(fg * m[100:160].sum(), rel=0.03)
    # eq. (8) on the noisy recording recovers it within the accelerometer noise
    from quadshank.data._cohort import Trial

    trial = Trial.from_signals("JM", "left", 1, TS, out["angle_deg"], out["acceleration_deg_s2"], stim)
    eq = equivalent_acceleration(trial, lt)
    noise = SENSOR["acceleration_noise_deg_s2"] * math.sqrt(40)
    assert abs(eq[100:140].sum() - true_sum) < 4 * noise + 0.02 * true_sum
    assert abs(eq[20:95].mean()) < 4 * SENSOR["acceleration_noise_deg_s2"] / math.sqrt(75) + 1.0


# ----------------------------------------------------------------------------- hidden effects
def test_fatigue_lowers_late_twitches_and_carries_over():
    ratios = {}
    for effects in ((), ("fatigue",)):
        cohort, truth = effect_run(*effects)
        lt = truth["legs"][EFFECT_LEG]
        ks, total, a, v = isolated_twitches(cohort.get(EFFECT_LEG, 1), lt)
        fg = model3_factor(lt, a, v)
        ok = fg > 0.3  # twitches the torque-angle/velocity factors have not all but switched off
        norm = total[ok] / fg[ok]
        ks = ks[ok]
        ratios[effects] = norm[ks >= (EFFECT_MINUTES - 1) * 6000].mean() / norm[ks < 6000].mean()
    assert ratios[("fatigue",)] < 0.9
    assert ratios[("fatigue",)] < ratios[()] - 0.08
    assert ratios[()] > 0.9
    _, truth = run(seed=0, effects=("fatigue",), trials=(2,))
    facts = truth["legs"]["JM-left"]["trials"]["2"]
    assert 0 < facts["fatigue_pulses_at_start"] < 0.5 * 250


def test_torque_angle_peak_weakens_flexed_twitches():
    ratio = {}
    for effects in ((), ("torque_angle_peak",)):
        cohort, truth = effect_run(*effects)
        ks, total, a, v = isolated_twitches(cohort.get(EFFECT_LEG, 1), truth["legs"][EFFECT_LEG])
        ratio[effects] = total[a < -20].mean() / total[(a > 0) & (a < 30)].mean()
    assert ratio[()] > 1.1  # model 3: γ_angle < 0
    assert ratio[("torque_angle_peak",)] < 0.5  # a maximum near 15°, small at −20° and below


def test_hill_velocity_weakens_shortening_twitches():
    ratio = {}
    for effects in ((), ("hill_velocity",)):
        cohort, truth = effect_run(*effects)
        lt = truth["legs"][EFFECT_LEG]
        ks, total, a, v = isolated_twitches(cohort.get(EFFECT_LEG, 1), lt)
        f = np.maximum(0.0, 1 + lt["active"]["gamma_angle"] * a)
        ok = f > 0.3
        norm, v = total[ok] / f[ok], v[ok]
        ratio[effects] = norm[v > 50].mean() / norm[v < -50].mean()
    assert ratio[("hill_velocity",)] < 0.8 * ratio[()]


def test_angle_delay_advances_onset_in_flexion():
    early = {}
    for effects in ((), ("angle_delay",)):
        cohort, truth = effect_run(*effects)
        trial = cohort.get(EFFECT_LEG, 1)
        eq = equivalent_acceleration(trial, truth["legs"][EFFECT_LEG])
        pulses = trial.pulse_indices
        quiet = np.diff(np.concatenate([[-1000], pulses])) >= 25
        low = pulses[quiet & (trial.angle_deg[pulses] < -20)]
        high = pulses[quiet & (trial.angle_deg[pulses] > 0)]
        assert low.size > 10 and high.size > 10
        # truth delay 4.3 samples: nothing at k+4 unless the delay is one sample shorter
        early[effects] = (eq[low + 4].mean(), eq[high + 4].mean())
    assert abs(early[()][0]) < 100 and abs(early[()][1]) < 100
    assert early[("angle_delay",)][0] > 250
    assert abs(early[("angle_delay",)][1]) < 100


def test_potentiation_enlarges_responses_after_short_ipi():
    stim = np.zeros(300)
    stim[[100, 102, 104]] = 1.0  # a triplet at 20 ms
    stim_single = np.zeros(300)
    stim_single[100] = 1.0
    sums = {}
    for effects in ((), ("potentiation",)):
        triplet = simulate_response("JM-left", stim, effects=effects)
        single = simulate_response("JM-left", stim_single, effects=effects)
        sums[effects] = {
            "triplet": triplet["equivalent_acceleration"][100:160].sum(),
            "single": single["equivalent_acceleration"][100:160].sum(),
            "activation": triplet["twitch_activation"].sum(),
        }
    on, off = sums[("potentiation",)], sums[()]
    assert on["single"] == pytest.approx(off["single"])  # no preceding IPI
    factor = 1 + 0.8 * math.exp(-(0.02 - TS) / 0.06)
    # exact but for the onset state of twitches 2 and 3, which the first twitch has begun to move
    assert on["activation"] / off["activation"] == pytest.approx((1 + 2 * factor) / 3, rel=0.02)
    assert on["triplet"] > 1.2 * off["triplet"]
    # and in a cohort run the data change
    c0, _ = effect_run()
    c1, _ = effect_run("potentiation")
    assert not np.array_equal(c0.get(EFFECT_LEG, 1).angle_deg, c1.get(EFFECT_LEG, 1).angle_deg)


def test_accel_resonance_adds_high_frequency_ripple():
    power = {}
    trials = {}
    for effects in ((), ("accel_resonance",)):
        cohort, _ = effect_run(*effects)
        trial = cohort.get(EFFECT_LEG, 1)
        trials[effects] = trial
        acc = trial.acceleration_deg_s2 - trial.acceleration_deg_s2.mean()
        spec = np.abs(np.fft.rfft(acc)) ** 2
        freq = np.fft.rfftfreq(acc.size, TS)
        power[effects] = spec[freq > 10].sum()
    assert power[("accel_resonance",)] > 1.5 * power[()]
    # a sensor effect: the movement itself is unchanged
    np.testing.assert_array_equal(trials[()].angle_deg, trials[("accel_resonance",)].angle_deg)


def test_every_effect_changes_the_data():
    base, _ = run(seed=1)
    for name in EFFECTS:
        other, truth = run(seed=1, effects=(name,))
        assert truth["effects"] == [name]
        assert name in truth["legs"]["JM-left"]["effects"]
        changed = any(
            not np.array_equal(a.angle_deg, b.angle_deg)
            or not np.array_equal(a.acceleration_deg_s2, b.acceleration_deg_s2)
            for a, b in zip(base, other)
        )
        assert changed, name
        for a, b in zip(base, other):
            np.testing.assert_array_equal(a.stimulation, b.stimulation)


def test_progress_bar_gives_the_same_data(capsys):
    quiet, _ = run(minutes=0.5, seed=0)
    loud, _ = simulate_cohort(legs=("JM-left",), minutes=0.5, seed=0, progress=True)
    assert "simulating" in capsys.readouterr().err
    for a, b in zip(quiet, loud):
        np.testing.assert_array_equal(a.angle_deg, b.angle_deg)


def test_x64_is_not_switched_on_globally():
    import jax
    import jax.numpy as jnp

    run()
    assert not jax.config.jax_enable_x64
    assert jnp.zeros(1).dtype == jnp.float32


# ----------------------------------------------------------------------------- calibration
def test_rms_angle_calibration():
    cohort, truth = run(legs=LEGS, minutes=2.0, seed=0)
    summary = truth["summary"]
    for trial in ("1", "2", "3"):
        assert abs(summary[trial]["mean_rms_angle_deg"] - RMS_ANGLE[trial]) < 2.0, (trial, summary[trial])
    # the operating range -40..60 deg is covered (1st and 99th percentiles of the angle, trials 1-2)
    angles = np.concatenate([t.angle_deg for t in cohort if t.trial in (1, 2)])
    lo, hi = np.percentile(angles, [1, 99])
    assert -50 < lo < -30 and 50 < hi < 75, (lo, hi)
    for leg in LEGS:
        facts = truth["legs"][leg]["trials"]["1"]
        assert facts["n_isolated"] >= 8  # enough to identify (MIN_TWITCHES); 55-216 per leg in 5 min


def test_twitch_variability_factors_have_mean_one_and_the_stated_spread():
    from quadshank.data._simulate import TWITCH_CV, twitch_variability

    cv = TWITCH_CV
    g = twitch_variability(np.random.default_rng(0), 200_000, cv)
    assert g.min() > 0
    assert g.mean() == pytest.approx(1.0, abs=0.003)
    assert g.std() / g.mean() == pytest.approx(cv, rel=0.02)
    # by default, only the twitch amplitudes differ from equal twitches: same pulses, same sensor noise streams
    base, _ = run(seed=2, twitch_cv=0.0)
    varied, truth = run(seed=2)
    assert truth["twitch_cv"] == cv and varied.attrs["twitch_cv"] == cv
    for a, b in zip(base, varied):
        np.testing.assert_array_equal(a.stimulation, b.stimulation)
    assert not np.array_equal(base.trials[0].angle_deg, varied.trials[0].angle_deg)


# ----------------------------------------------------------------------------- the knee's range
def test_the_knee_range_acts_only_at_the_ends_of_the_range():
    import jax.numpy as jnp

    from quadshank.data._simulate import KNEE_RANGE, _range_torque

    inside = np.asarray(_range_torque(jnp.linspace(-55.0, 77.0, 1001)))
    assert np.abs(inside).max() < 1.0  # deg/s², against gravity's 1650-1950 deg/s² at 90°
    r = KNEE_RANGE
    assert float(_range_torque(r["extension_deg"] + 4 * r["width_deg"])) > 50_000  # stops extension
    assert float(_range_torque(r["flexion_deg"] - 4 * r["width_deg"])) < -50_000  # and flexion


@pytest.mark.parametrize("effects", [(), *((e,) for e in EFFECTS)], ids=lambda e: e[0] if e else "default")
def test_no_simulated_trial_leaves_the_anatomical_range(effects):
    """Seed 1 at full length: without the knee's range its rare large swings had reached 155°
    (the shank over the top with potentiation)."""
    from quadshank.data._simulate import ANATOMICAL_RANGE_DEG

    cohort, truth = simulate_cohort(minutes=5.0, seed=1, effects=effects, trials=(1, 2))
    lo, hi = ANATOMICAL_RANGE_DEG
    for t in cohort:
        assert lo <= t.angle_deg.min() and t.angle_deg.max() <= hi, (t.key, t.trial, t.angle_deg.min(), t.angle_deg.max())
    assert truth["knee_range"]["extension_deg"] == 88.0
