"""Recordings at other rates and with irregular time stamps, brought onto the models' grid by
``convert --resample``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from quadshank.cli import main
from quadshank.data import Cohort, InterchangeError, Trial, load_cohort, read_interchange, write_interchange
from quadshank.data._resample import resample_trial


def _irregular(seed: int = 0, n: int = 3000, dt: float = 0.005, jitter: float = 0.3) -> Trial:
    """A swinging shank at about 200 Hz with time stamps jittered by ±jitter of a step, three pulses."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(np.r_[0.0, dt * (1 + rng.uniform(-jitter, jitter, n - 1))])
    angle = 30 * np.sin(2 * np.pi * 0.7 * t) + rng.normal(0, 0.05, n)
    u = np.zeros(n)
    u[[400, 1200, 2500]] = [1.0, 0.5, 1.0]
    return Trial.from_signals("IR", "left", 1, dt, angle, None, u, time_s=t)


def test_irregular_time_stamps_are_refused_unless_resampled(tmp_path):
    trial = _irregular()
    folder = tmp_path / "data"
    # written on a uniform grid (the writer refuses irregular stamps), then stamped as a logger does
    write_interchange(Cohort((trial.replace(time_s=np.arange(trial.n_samples) * 0.005),)), folder)
    path = folder / "IR-left-trial1.csv"
    lines = path.read_text().splitlines()
    j = lines[0].split(",").index("time_s")
    rows = [lines[0]]
    for line, t in zip(lines[1:], trial.time_s):
        cells = line.split(",")
        cells[j] = repr(float(t))
        rows.append(",".join(cells))
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(InterchangeError, match="non-uniform sampling"):
        read_interchange(folder)
    got = read_interchange(folder, resample_s=0.01).trials[0]
    assert got.sampling_period_s == 0.01 and np.allclose(np.diff(got.time_s), 0.01)
    truth = 30 * np.sin(2 * np.pi * 0.7 * got.time_s)
    assert np.sqrt(np.mean((got.angle_deg - truth) ** 2)) < 0.1  # the swing kept, the noise smoothed
    # each pulse at the nearest new sample, with its level
    k = np.flatnonzero(got.stimulation > 0)
    np.testing.assert_allclose(got.time_s[k], trial.time_s[[400, 1200, 2500]], atol=0.005 + 1e-12)
    np.testing.assert_array_equal(got.stimulation[k], [1.0, 0.5, 1.0])


def test_resampling_filters_what_the_new_grid_cannot_hold():
    n, dt = 4000, 0.001
    t = np.arange(n) * dt
    slow, fast = 10 * np.sin(2 * np.pi * 2 * t), 5 * np.sin(2 * np.pi * 120 * t)  # 120 Hz folds to 20 Hz at 100 Hz
    trial = Trial.from_signals("AA", "left", 1, dt, slow + fast, None, np.zeros(n), time_s=t)
    got = resample_trial(trial, 0.01)
    err = got.angle_deg - 10 * np.sin(2 * np.pi * 2 * got.time_s)
    assert np.sqrt(np.mean(err[20:-20] ** 2)) < 0.1  # plain decimation would leave a 5° alias


def test_resampling_refuses_a_gap_and_a_train_too_fast_and_keeps_exclusions():
    trial = _irregular(jitter=0.0)
    t = trial.time_s.copy()
    t[1000:] += 0.05  # ten samples missing
    with pytest.raises(ValueError, match="a gap of 0.055 s .* samples are missing"):
        resample_trial(trial.replace(time_s=t), 0.01)
    u = trial.stimulation.copy()
    u[401] = 1.0  # 5 ms after the pulse at sample 400
    with pytest.raises(ValueError, match="fall on one sample of the new period 0.01 s"):
        resample_trial(trial.replace(stimulation=u), 0.01)
    exclude = np.zeros(trial.n_samples, bool)
    exclude[1000:1010] = True
    got = resample_trial(trial.replace(exclude=exclude), 0.01)
    assert 5 <= got.exclude.sum() <= 7 and got.exclude[500:505].all()


def test_a_recording_at_1_ms_is_resampled_and_identified(tmp_path, capsys):
    fine, coarse = tmp_path / "1ms", tmp_path / "10ms"
    for folder, ms in ((fine, "1"), (coarse, "10")):
        assert main(["-q", "simulate", "--out", str(folder), "--legs", "JM-left", "--minutes", "1",
                     "--trials", "1", "--sampling-period-ms", ms]) == 0
    # at 1 ms the delays considered (10 samples) are too short for a muscle: refused, with what to do
    capsys.readouterr()
    for argv in (["identify", str(fine), "--out", str(tmp_path / "id1")],
                 ["fit", str(fine), "--out", str(tmp_path / "f1"), "--chains", "1", "--warmup", "5", "--draws", "5"],
                 ["discover", str(fine), "--out", str(tmp_path / "d1"), "--effects", "fatigue", "--max-rounds", "1"]):
        assert main(["-q", *argv]) == 2, argv
        err = capsys.readouterr().err
        assert "delays considered reach 10 samples = 10 ms" in err and "--resample 0.01" in err, err
        assert not Path(argv[argv.index("--out") + 1]).exists()
    assert main(["-q", "convert", str(fine), str(tmp_path / "c.nc"), "--resample", "0.01"]) == 0
    assert load_cohort(tmp_path / "c.nc").sampling_period_s == 0.01
    found = {}
    for name, data in (("resampled", tmp_path / "c.nc"), ("at 10 ms", coarse)):
        assert main(["-q", "identify", str(data), "--out", str(tmp_path / name)]) == 0
        found[name] = json.loads((tmp_path / name / "summary.json").read_text())["legs"]["JM-left"]
    a, b = found["resampled"], found["at 10 ms"]
    assert a["delay_samples"] == b["delay_samples"]
    assert a["model1"]["gain"] == pytest.approx(b["model1"]["gain"], rel=0.05)
    assert a["passive"]["damping"] == pytest.approx(b["passive"]["damping"], rel=0.05)


def test_a_new_period_that_no_command_would_read_is_refused():
    """A period longer than the longest the readers accept (0.1 s), or not a number of seconds at
    all, is refused before anything is written; the message says why."""
    trial = _irregular()
    for period in (0.5, float("inf"), 0.0, -0.01):
        with pytest.raises(ValueError, match=r"the new sampling period"):
            resample_trial(trial, period)
    assert resample_trial(trial, 0.1).sampling_period_s == pytest.approx(0.1)


def test_a_missing_trial_is_named_with_the_trials_the_leg_has():
    cohort = Cohort((_irregular(),))
    leg = cohort.legs[0]
    with pytest.raises(KeyError, match=rf"no trial 3 for leg {leg}; its trials: 1"):
        cohort.get(leg, 3)
    with pytest.raises(KeyError, match="legs present"):
        cohort.get("XX-left", 1)


def test_a_pendulum_test_at_1_ms_is_identified_at_its_own_period():
    """Without pulses there is no delay to reach: a pendulum test at 1 ms is identified as it is
    (with the warning on the delays), while the same test with a pulse in it is refused."""
    import warnings

    from quadshank.data._simulate import simulate_pendulum_test
    from quadshank.inference import identify_cohort
    from quadshank.inference._identify import DelayRangeError

    truth = {"damping": 1.3, "gravity": 1950.0, "k1": 30.0, "k2": 0.05}
    pendulum = simulate_pendulum_test(truth, sampling_period_s=0.001)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the delays considered at 1 ms, which do not matter here
        found = identify_cohort(Cohort((pendulum,)))["PT-left"].passive
    assert found["gravity"] == pytest.approx(truth["gravity"], rel=0.05)
    u = pendulum.stimulation.copy()
    u[4000] = 1.0
    with pytest.raises(DelayRangeError, match="reach 10 samples = 10 ms, short of a stimulated muscle's delay"):
        identify_cohort(Cohort((pendulum.replace(stimulation=u),)))
