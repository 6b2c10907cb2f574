"""The sampling period comes from the data: the pipeline at 5 ms and at 20 ms, and a model
at another period than its data refused."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from quadshank import build_model, simulate_cohort
from quadshank.cli import main
from quadshank.evaluation import horizon_samples, prediction_errors
from quadshank.model import prepare


@pytest.mark.slow
@pytest.mark.parametrize("period_ms", [5, 20])
def test_simulate_fit_evaluate_report_at_another_period(tmp_path, period_ms, capsys):
    dt = period_ms / 1000.0
    data, fit, ev, rep = (tmp_path / k for k in ("data", "fit", "eval", "report"))
    assert main(["-q", "simulate", "--out", str(data), "--legs", "TN-left,JM-left", "--minutes", "0.3",
                 "--trials", "1,2", "--sampling-period-ms", str(period_ms)]) == 0
    manifest = (data / "manifest.csv").read_text().splitlines()
    first = (data / manifest[1].split(",")[3]).read_text().splitlines()
    t0, t1 = (float(line.split(",")[0]) for line in first[1:3])
    assert t1 - t0 == pytest.approx(dt)

    # a fit that fails its checks exits 3 and is still written
    assert main(["-q", "fit", str(data), "--out", str(fit), "--model", "model2", "--chains", "1",
                 "--warmup", "15", "--draws", "15"]) in (0, 3)
    summary = json.loads((fit / "summary.json").read_text())
    assert summary["sampling_period_s"] == pytest.approx(dt)

    assert main(["-q", "evaluate", str(data), "--fit", str(fit), "--out", str(ev), "--draws", "5",
                 "--start-stride", "25"]) == 0
    evaluation = json.loads((ev / "summary.json").read_text())
    assert evaluation["horizons_samples"] == [round(h / period_ms) for h in (100, 250, 500, 1000)]
    assert set(evaluation["J"]["model2"]["2"]) == {"100", "250", "500", "1000"}
    assert f"Recordings sampled every {period_ms} ms; velocity derived from the angle" in (ev / "report.md").read_text()

    assert main(["-q", "report", str(fit), "--out", str(rep), "--evaluation", str(ev)]) == 0
    page = (rep / "index.html").read_text()
    assert f"Recordings sampled every {period_ms} ms; velocity derived from the angle" in page
    assert f"Gains are per sample: at {period_ms} ms a twitch&#x27;s gain is about {10 / period_ms:g}× the paper&#x27;s " \
           "values at 10 ms" in page
    delays = re.findall(r"mode d = (\d+) samples \(([\d.]+) ms\)", page)
    assert delays
    for samples, ms in delays:
        assert float(ms) == pytest.approx(int(samples) * period_ms)
    capsys.readouterr()


def test_a_model_at_another_period_than_its_data_is_refused():
    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.1, trials=(1,), sampling_period_s=0.005)
    at_10ms = build_model("model1")
    with pytest.raises(ValueError, match=r"TN-left trial 1 is sampled every 5 ms, but model 'model1' runs at 10 ms"):
        prepare(cohort, at_10ms)
    with pytest.raises(ValueError, match="sampled every 5 ms"):
        prediction_errors(at_10ms, cohort.trials[0])
    at_5ms = build_model("model1", sampling_period_s=cohort.sampling_period_s)
    assert prepare(cohort, at_5ms).n_legs == 1
    assert prepare(cohort, at_10ms.at_period(0.005)).n_legs == 1


def test_horizons_are_milliseconds_in_whole_samples():
    assert horizon_samples(0.01) == {100: 10, 250: 25, 500: 50, 1000: 100}
    assert horizon_samples(0.005) == {100: 20, 250: 50, 500: 100, 1000: 200}
    assert horizon_samples(0.02) == {100: 5, 250: 12, 500: 25, 1000: 50}  # 250 ms: the nearest, 240 ms
    assert horizon_samples(0.2, (100,)) == {100: 1}  # at least one sample


def test_trials_at_different_periods_have_no_common_period():
    a, _ = simulate_cohort(legs=["TN-left"], minutes=0.05, trials=(1,), sampling_period_s=0.005)
    b, _ = simulate_cohort(legs=["JM-left"], minutes=0.05, trials=(1,))
    mixed = type(a)(a.trials + b.trials)
    with pytest.raises(ValueError, match="TN-left trial 1: 5 ms, JM-left trial 1: 10 ms"):
        mixed.sampling_period_s
    assert np.isclose(a.sampling_period_s, 0.005)


def test_the_simulator_refuses_a_period_off_its_millisecond_grid():
    assert main(["-q", "simulate", "--out", "unused", "--minutes", "0.1", "--sampling-period-ms", "7.5"]) == 2


@pytest.mark.parametrize("period_ms", [5, 20])
def test_the_zero_order_model_finds_the_delay_at_another_period(period_ms):
    """Model 3 compares whole twitches (windows of 250 ms besides the longest delay). Counted in
    samples, a window at 5 ms held half a twitch, and the screen put a 43-ms delay at 5 ms."""
    from quadshank.inference._screen import laplace_fit

    dt = period_ms / 1000.0
    # equal twitches: model 3's delay shows only through the state its gain factors are taken at, which
    # a minute of twitches that vary from pulse to pulse does not pin (the period is what is tested)
    cohort, truth = simulate_cohort(legs=["TN-left"], minutes=1.0, trials=(1,), seed=1, sampling_period_s=dt,
                                    twitch_cv=0.0)
    active = truth["legs"]["TN-left"]["active"]
    fit = laplace_fit(cohort, build_model("model3", sampling_period_s=dt), loo=False)
    assert abs(int(np.argmax(fit.delay_posterior[0])) - active["delay_s"] / dt) < 1.0
    # the twitch's sum over its samples grows as the samples shorten: 10 ms / T_s times the paper's
    assert float(fit.values("TN-left")["gain"]) == pytest.approx(active["sampled_twitch_sum"] * 0.01 / dt, rel=0.1)


def test_the_classical_passive_system_is_the_same_at_any_period():
    """The quiet samples the passive system is identified on are counted in time (350 ms after a
    pulse): counted in samples, at 5 ms and 2 ms they held the ends of twitches, and gravity came
    out at half its value (921 and 0 deg/s² against 1936 at 10 ms)."""
    import warnings

    from quadshank.inference._identify import identify_passive

    found = {}
    for period_ms in (10, 5, 2):
        cohort, _ = simulate_cohort(legs=["TN-left"], minutes=1.0, trials=(1,), sampling_period_s=period_ms / 1000, seed=0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the delay range at 2 ms, which this test is not about
            found[period_ms] = identify_passive([cohort.trials[0]])[0]
    for period_ms in (5, 2):
        assert found[period_ms]["gravity"] == pytest.approx(found[10]["gravity"], rel=0.02), period_ms
        assert found[period_ms]["damping"] == pytest.approx(found[10]["damping"], rel=0.05), period_ms
