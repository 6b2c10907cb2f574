"""Plausibility of recordings that pass the format's rules: units and signs, and the fingerprint
that ties a fit to its data."""

from __future__ import annotations

import re

import numpy as np
import pytest

from quadshank.data import Cohort, Trial, parse_number, plausibility
from quadshank.evaluation import check_fit_data
from quadshank.inference import FitResult

DT = 0.01


def _trial(n: int = 1000, trial: int = 1) -> Trial:
    rng = np.random.default_rng(3)
    t = np.arange(n) * DT
    w = 2 * np.pi * 0.6
    angle = 30 * np.exp(-0.2 * t) * np.sin(w * t)
    acc = np.gradient(np.gradient(angle, DT), DT) + rng.normal(0, 20, n)  # an accelerometer's noise
    return Trial.from_signals("TN", "left", trial, DT, angle + rng.normal(0, 0.05, n), acc, np.zeros(n),
                              velocity_deg_s=np.gradient(angle, DT), time_s=t)


def test_consistent_signals_are_plausible():
    assert plausibility(_trial()) == []


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (lambda t: t.replace(acceleration_deg_s2=np.deg2rad(t.acceleration_deg_s2)), ["acceleration_deg_s2", "pi/180"]),
        (lambda t: t.replace(acceleration_deg_s2=-t.acceleration_deg_s2), ["acceleration_deg_s2", "flipped"]),
        (lambda t: t.replace(acceleration_deg_s2=0.01 * t.acceleration_deg_s2), ["acceleration_deg_s2", "units"]),
        (lambda t: t.replace(angle_deg=np.deg2rad(t.angle_deg)), ["acceleration_deg_s2", "180/pi"]),
        (lambda t: t.replace(velocity_deg_s=np.deg2rad(t.velocity_deg_s)), ["velocity_deg_s", "pi/180"]),
        (lambda t: t.replace(acceleration_deg_s2=np.random.default_rng(0).normal(0, 500, t.n_samples)),
         ["acceleration_deg_s2", "hardly follows"]),
    ],
)
def test_a_unit_or_sign_that_seems_off_is_named(change, words):
    found = plausibility(change(_trial()))
    assert found and any(all(w in f for w in words) for f in found), found


@pytest.mark.parametrize("text", ["1", "-2.5", "+3.", ".5", "1e-3", "2.5E+04", " 7 "])
def test_numbers_as_the_format_writes_them(text):
    assert parse_number(text) == float(text)


@pytest.mark.parametrize("text", ["1_000", "١٢", "１２", "0x1A", "nan", "inf", "", "1,5", "1.2.3", "e5"])
def test_anything_else_is_not_a_number(text):
    assert parse_number(text) is None


def _fit_of(cohort: Cohort, **kw) -> tuple[FitResult, dict]:
    desc = {"model": "model1", "legs": ["TN-left"], "trials": [1]}
    summary = FitResult(model="model1", effects=[], trials=[1], legs={}, diagnostics={}, banner=None, settings={},
                        chain_method="vectorized", sampling_period_s=DT, interval=[0.05, 0.95], code={},
                        data_fingerprint=cohort.fingerprint(["TN-left"], [1]), data="where/the/data/are", **kw)
    return summary, desc


def test_a_fit_refuses_data_it_was_not_fitted_to():
    cohort = Cohort((_trial(), _trial(trial=2)))
    summary, desc = _fit_of(cohort)
    check_fit_data("fitdir", summary, desc, cohort)  # the same data
    check_fit_data("fitdir", summary, desc, cohort.select(trials=[1]))  # trial 2 was not fitted
    t = cohort.trials[0]
    changed = t.angle_deg.copy()
    changed[500] += 1e-9
    with pytest.raises(ValueError, match="not the data the fit in fitdir was fitted to.*where/the/data/are"):
        check_fit_data("fitdir", summary, desc, Cohort((t.replace(angle_deg=changed), cohort.trials[1])))
    with pytest.raises(ValueError, match="lacks TN-left trial 1"):
        check_fit_data("fitdir", summary, desc, cohort.select(trials=[2]))
    other = Cohort(tuple(x.replace(subject="JM") for x in cohort.trials))
    with pytest.raises(KeyError, match="TN-left"):
        check_fit_data("fitdir", summary, desc, other)


def test_a_constant_angle_is_named():
    t = _trial()
    found = plausibility(t.replace(angle_deg=np.full(t.n_samples, 5.0)))
    assert found == ["angle_deg is constant (5.0° throughout): no movement was recorded"]


def _pendulum(rest: float = 0.0, sign: float = 1.0, seconds: float = 12.0) -> Trial:
    n = int(seconds / DT)
    t = np.arange(n) * DT
    angle = rest + sign * 50 * np.exp(-0.8 * t) * np.cos(2 * np.pi * 0.8 * t)
    acc = np.gradient(np.gradient(angle, DT), DT)
    return Trial.from_signals("PT", "left", 1, DT, angle, acc, np.zeros(n), time_s=t)


def test_a_pendulum_test_about_zero_released_from_extension_is_plausible():
    assert plausibility(_pendulum()) == []


def test_a_pendulum_test_resting_off_zero_is_named():
    found = plausibility(_pendulum(rest=-23.0))
    assert any("comes to rest at -23.0°" in f and "gravity_offset" in f for f in found), found
    # at 90°: a flexion angle, named as one rather than as an offset zero
    found = [f for f in plausibility(_pendulum(rest=90.0)) if "comes to rest at 90.0°" in f]
    assert len(found) == 1 and "a flexion angle" in found[0] and "90 − angle_deg" in found[0], found
    assert "gravity_offset" not in found[0]


def test_a_pendulum_test_released_from_flexion_asks_about_the_sign():
    found = plausibility(_pendulum(sign=-1.0))
    assert any("starts at -50.0°" in f and "flipped" in f for f in found), found
    # a stimulated trial is not a pendulum test
    t = _pendulum(sign=-1.0)
    u = np.zeros(t.n_samples)
    u[300] = 1.0
    assert not any("flipped" in f for f in plausibility(t.replace(stimulation=u)))


def test_a_glitch_in_the_angle_is_named_with_its_time():
    t = _trial()
    angle = t.angle_deg.copy()
    angle[[300, 700]] = [1e6, -400.0]  # two samples far off, each back at the next sample
    found = plausibility(t.replace(angle_deg=angle))
    assert any("jumps by" in f and "time_s = 3.0 and 1 more such sample" in f and "exclude" in f for f in found), found
    # marked in exclude, neither is named again
    exclude = np.zeros(t.n_samples, bool)
    exclude[[300, 700]] = True
    assert not any("jumps by" in f for f in plausibility(t.replace(angle_deg=angle, exclude=exclude)))
    # a fast but continuous swing (2000 deg/s peak) is no glitch
    fast = 400 * np.sin(2 * np.pi * 0.8 * np.arange(t.n_samples) * DT)
    assert not any("jumps by" in f for f in plausibility(t.replace(angle_deg=fast)))


def test_a_glitch_is_named_where_most_of_the_trial_is_excluded():
    """Too few samples kept to compare the signals: what was found before (a glitch in a kept
    sample) is still said."""
    t = _trial()
    angle, exclude = t.angle_deg.copy(), np.ones(t.n_samples, bool)
    exclude[:20] = False
    angle[10] = 1e6
    found = plausibility(t.replace(angle_deg=angle, exclude=exclude))
    assert any("jumps by" in f and "time_s = 0.1" in f for f in found), found


def test_float_noise_in_the_stimulation_is_named():
    """Levels just above 0 where no pulse was delivered (a spreadsheet's float noise) would each
    be a pulse: named with their number and the first one's time; real levels draw nothing."""
    t = _trial()
    assert not any("float noise" in f for f in plausibility(t))
    stim = np.where(t.stimulation > 0, t.stimulation, 1e-12)
    noisy = t.replace(stimulation=stim)
    (said,) = [f for f in plausibility(noisy) if "float noise" in f]
    zeros = int(np.count_nonzero(t.stimulation == 0))
    assert said.startswith(f"stimulation holds {zeros} levels above 0 and below 1e-06, the first at time_s = ")


def test_an_angle_that_falls_after_the_pulses_asks_about_the_sign():
    """The quadriceps lifts the shank: on the simulated cohort (with equal twitches too) no trial
    is named, while every one whose angle and acceleration are both flipped (so that they still
    agree with each other) is, with the number of pulses; a pendulum test has no pulses to judge."""
    from quadshank.data._simulate import simulate_cohort

    for cv in (0.2, 0.0):
        effects = f"twitch CV {cv:g}"
        cohort, _ = simulate_cohort(legs=("TN-left", "JM-right"), minutes=1.0, seed=2, twitch_cv=cv)
        for t in cohort.trials:
            assert not any("falls after the pulses" in f for f in plausibility(t)), (effects, t.key, t.trial)
            flipped = t.replace(angle_deg=-t.angle_deg, acceleration_deg_s2=-t.acceleration_deg_s2)
            found = [f for f in plausibility(flipped) if "falls after the pulses" in f]
            assert len(found) == 1 and "positive in flexion" in found[0], (effects, t.key, t.trial, found)
            n = int(found[0].split("after each of ")[1].split()[0])
            assert n >= 8
    assert not any("falls after the pulses" in f for f in plausibility(_trial().replace(angle_deg=-_trial().angle_deg)))


def test_pulses_that_leave_the_angle_unchanged_are_named():
    """A twitch moves the shank: an angle that reads exactly the same for 250 ms after a pulse
    (a stuck or saturated sensor) is named where 3 pulses or more, and a fifth of them, do so;
    an angle quantised to 0.1° still moves after every pulse, and an excluded stretch is not judged."""
    from quadshank.data._simulate import simulate_cohort

    cohort, _ = simulate_cohort(legs=("TN-left",), minutes=1.0, seed=2, trials=(1,))
    t = cohort.trials[0]
    words = "exactly unchanged"
    assert not any(words in f for f in plausibility(t))
    assert not any(words in f for f in plausibility(t.replace(angle_deg=np.round(t.angle_deg, 1))))
    stuck = t.angle_deg.copy()
    a, b = 2000, 5000  # 20 s to 50 s the sensor holds one reading
    stuck[a:b] = stuck[a]
    pulses = np.flatnonzero(t.stimulation > 0)
    inside = int(np.count_nonzero((pulses >= a) & (pulses + 25 < b)))
    assert inside >= 10
    (said,) = [f for f in plausibility(t.replace(angle_deg=stuck)) if words in f]
    assert said.startswith(f"{inside} of {pulses.size} pulses leave angle_deg exactly unchanged for 250 ms")
    first = pulses[(pulses >= a) & (pulses + 25 < b)][0]
    assert f"(the first at {t.time_s[first]:.3f} s)" in said and "exclude = 1" in said
    excluded = np.zeros(t.n_samples, bool)
    excluded[a:b] = True
    assert not any(words in f for f in plausibility(t.replace(angle_deg=stuck, exclude=excluded)))
    few = t.angle_deg.copy()
    two = pulses[(pulses > 200) & (np.diff(pulses, append=10**9) > 60)][:2]
    for k in two:
        few[k:k + 26] = few[k]
    assert not any(words in f for f in plausibility(t.replace(angle_deg=few)))


@pytest.mark.parametrize("column", ["acceleration_deg_s2", "velocity_deg_s"])
def test_a_measured_signal_held_constant_is_named_as_a_placeholder(column):
    """A logger that writes 0 for a signal it did not record: named, and not compared with the angle."""
    t = _trial()
    found = plausibility(t.replace(**{column: np.zeros(t.n_samples)}))
    assert any(column in f and "constant" in f and "Leave the column out" in f for f in found), found
    assert not any("hardly follows" in f for f in found), found


def test_an_angle_clipped_at_a_rail_is_named_and_a_knee_resting_between_twitches_is_not():
    t = _trial()
    found = plausibility(t.replace(angle_deg=np.minimum(t.angle_deg, 10.0)))  # swings cut flat at 10°
    assert any("angle_deg sits at its largest value, 10.0°" in f and "saturated" in f for f in found), found
    assert not any("sits at its" in f for f in plausibility(t)), plausibility(t)
    # twitches from rest, the knee back at exactly 0 between them: the rest is the smallest angle, not a rail
    n = 1000
    angle = np.zeros(n)
    for k in range(50, n - 60, 100):
        angle[k:k + 40] = 15 * np.sin(np.pi * np.arange(40) / 40)
    resting = Trial.from_signals("TN", "left", 1, DT, angle, np.gradient(np.gradient(angle, DT), DT), np.zeros(n),
                                 time_s=np.arange(n) * DT)
    assert not any("sits at its" in f for f in plausibility(resting)), plausibility(resting)


def test_a_time_in_a_message_is_written_as_the_recording_has_it():
    """115 samples of 10 ms are 1.1500000000000001 s in floating point; the message says 1.15."""
    t = _trial()
    assert repr(float(t.time_s[115])) != "1.15"
    angle = t.angle_deg.copy()
    angle[115] = 1e6
    found = [f for f in plausibility(t.replace(angle_deg=angle)) if "jumps by" in f]
    assert found and "time_s = 1.15," in found[0], found


@pytest.fixture(scope="module")
def stimulated():
    from quadshank.data import simulate_cohort

    cohort, _ = simulate_cohort(legs=["JM-left"], minutes=1.0, seed=3, trials=[1])
    return cohort.trials[0]


def test_an_accelerometer_off_in_scale_lag_or_sensing_gravity_is_named(stimulated):
    """An accelerometer 20 % off in scale, filtered by its amplifier (a causal 15 Hz low-pass), one
    that also senses gravity's projection, and an angle sensor that lags (10 Hz): each shifts the
    identified values by 20-100 % while agreeing with the angle well enough for the units' check.
    Each is named; the recording as simulated draws none of these."""
    from scipy.signal import butter, lfilter

    from quadshank.data._interchange import signal_doubts

    t = stimulated
    assert signal_doubts(t) == []
    acc = t.acceleration_deg_s2
    b, a = butter(2, 15.0, fs=1 / DT)
    cases = {
        "scale": (t.replace(acceleration_deg_s2=1.2 * acc), r"is 1\.2\d? times the size of the angle's second "
                                                            r"derivative: is its scale off"),
        "amplifier": (t.replace(acceleration_deg_s2=lfilter(b, a, acc)), r"lags the angle's second derivative by "
                                                                         r"(\d+\.?\d*) ms: a filter in its amplifier"),
        "gravity": (t.replace(acceleration_deg_s2=acc + 1900 * np.sin(np.deg2rad(t.angle_deg))),
                    r"holds about \+1\.\d+e\+03·sin\(angle\) deg/s² besides the angle's second derivative"),
        "slow angle": (Trial.from_signals("JM", "left", 1, DT, lfilter(*butter(2, 10.0, fs=1 / DT), t.angle_deg), acc,
                                          t.stimulation), r"leads the angle's second derivative by (\d+\.?\d*) ms"),
    }
    for name, (trial, pattern) in cases.items():
        said = [d for d in signal_doubts(trial) if re.search(pattern, d)]
        assert len(said) == 1, (name, signal_doubts(trial))
        if (m := re.search(pattern, said[0])) and m.groups():
            assert 5.0 < float(m.group(1)) < 25.0, (name, said)
        assert said[0] in plausibility(trial)
