"""The black-box yardstick: an ARX model of the angle, scored on the physical models' starts."""

import numpy as np
import pytest

from quadshank.data._simulate import simulate_cohort
from quadshank.evaluation._blackbox import ARX, arx_errors, better_than, blackbox_j, fit_arx
from quadshank.evaluation._prediction import horizon_samples, prediction_starts


@pytest.fixture(scope="module")
def cohort():
    return simulate_cohort(legs=["TN-left"], minutes=0.5, seed=3, trials=(1, 2))[0]


def _reference_j(arx: ARX, trial, horizons):
    """J of the ARX recursion written out start by start, on the starts of the physical models."""
    a, b, c = arx.coef[: arx.na], arx.coef[arx.na : arx.na + arx.nb], arx.coef[-1]
    y, u, ex = trial.angle_deg, trial.stimulation, trial.exclude
    starts = prediction_starts(trial, max(horizons), 1)
    sq = np.zeros((len(starts), len(horizons)))
    for s, n in enumerate(starts):
        past = [y[max(n - i, 0)] if not ex[max(n - i, 0)] else y[n] for i in range(arx.na)]  # φ[n], φ[n−1], …
        for step in range(1, max(horizons) + 1):
            m = n + step
            nxt = sum(a[i] * past[i] for i in range(arx.na)) + sum(b[j] * u[max(m - 1 - j, 0)] for j in range(arx.nb)) + c
            past = [nxt] + past[:-1]
            if step in horizons:
                sq[s, horizons.index(step)] = (y[m] - nxt) ** 2
    return np.sqrt(sq.mean(axis=0))


def test_arx_j_is_scored_on_the_starts_and_horizons_of_the_physical_models(cohort):
    arx = fit_arx(cohort.get("TN-left", 1))
    trial = cohort.get("TN-left", 2)
    exclude = np.zeros(trial.n_samples, bool)
    exclude[1000:1100] = True  # an artefact: nonsense in it must not reach any score
    angle = trial.angle_deg.copy()
    angle[exclude] = 1e6
    trial = trial.replace(exclude=exclude, angle_deg=angle)
    horizons = tuple(horizon_samples(trial.sampling_period_s).values())
    got = arx_errors(arx, trial, horizons)
    assert np.all(np.isfinite(got)) and np.all(got < 100)
    np.testing.assert_allclose(got, _reference_j(arx, trial, list(horizons)), rtol=1e-9)


def test_orders_chosen_by_validation_predict_a_known_arx_as_well_as_its_truth():
    rng = np.random.default_rng(0)
    n, period = 6000, 0.01
    u = np.zeros(n)
    u[rng.choice(n, 300, replace=False)] = rng.uniform(0.3, 1.0, 300)
    a, b = np.array([1.6, -0.7]), 2.0 * np.exp(-np.arange(10) / 3.0)
    clean = np.zeros(n)
    for k in range(11, n):
        clean[k] = a @ clean[k - 1 : k - 3 : -1] + b @ u[k - 1 : k - 11 : -1] + rng.normal(0, 0.05)
    from quadshank.data._cohort import Trial

    def trial(y, number):
        return Trial(subject="S", leg="left", trial=number, sampling_period_s=period, time_s=np.arange(n) * period,
                     angle_deg=y, velocity_deg_s=np.gradient(y, period), acceleration_deg_s2=np.zeros(n),
                     stimulation=u)

    arx = fit_arx(trial(clean + rng.normal(0, 0.01, n), 1))
    assert arx.na >= 2 and arx.nb >= 10 and len(arx.validation) == 12
    truth = ARX(2, 10, np.concatenate([a, b, [0.0]]), {})
    fresh = trial(clean, 2)
    hs = (10, 25, 50, 100)
    assert np.all(arx_errors(arx, fresh, hs) < 1.1 * arx_errors(truth, fresh, hs) + 0.005)


def test_blackbox_j_per_leg_and_trial_and_where_it_predicts_better(cohort):
    bb = blackbox_j(cohort, {"TN-left": 1})
    assert set(bb["J_per_leg"]["TN-left"]) == {"1", "2"} and set(bb["J"]["2"]) == {"100", "250", "500", "1000"}
    assert bb["orders"]["TN-left"]["trained_on"] == 1
    worse = {"m": {"2": {h: v + 1.0 for h, v in bb["J"]["2"].items()}}}
    better = {"m": {"2": {h: v - 1.0 for h, v in bb["J"]["2"].items()}}}
    assert better_than(bb, worse) == [{"model": "m", "trial": "2", "horizons_ms": ["100", "250", "500", "1000"]}]
    assert better_than(bb, better) == []


def test_the_diagnosis_says_where_the_black_box_predicts_better(cohort):
    from quadshank.commands.diagnose import blackbox_beside

    from quadshank.loop._diagnose import J_HORIZONS_MS

    horizons = [str(h) for h in J_HORIZONS_MS]  # the diagnosis's horizons: 100, 250, 500 and 1000 ms
    first = blackbox_beside(cohort, ["TN-left"], [1], {h: {"median": 1e3} for h in horizons})
    J = first["J_ms"]
    assert list(J) == horizons and first["better_at_ms"] == horizons
    assert f"predicts better than the baseline at {', '.join(horizons)} ms" in first["sentence"]
    half = {h: {"median": J[h] + (0.1 if h == "500" else -0.1)} for h in horizons}
    second = blackbox_beside(cohort, ["TN-left"], [1], half)
    assert second["better_at_ms"] == ["500"] and "at 500 ms (" in second["sentence"]
    assert "sentence" not in blackbox_beside(cohort, ["TN-left"], [1], {h: {"median": 0.0} for h in J})
