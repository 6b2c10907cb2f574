"""J_φ,p (eq. 12), the sign test and the Table V analogue."""

import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from quadshank import Trial
from quadshank.evaluation._prediction import prediction_errors, sign_tests, table_v
from quadshank.model._model import paper_model, passive_effects, simulate_angles

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from reference_jphi import j_phi_loop  # noqa: E402

PASSIVE = dict(damping=1.0, gravity=1750.0, k1=30.0, k2=0.05)
PARAMS = {
    "model1": {"gain": 1.1e4},
    "model2": {"a1": -1.45, "a2": 0.6, "b1": 500.0, "b2": 600.0},
    "model3": {"gain": 1.3e4, "gamma_angle": -8e-3, "gamma_velocity": -1.8e-3},
}


def _noisy_trial(n=700, seed=1):
    """Angle data from a *different* model than the ones evaluated, plus noise."""
    rng = np.random.default_rng(seed)
    u = np.zeros(n)
    t = 15
    while t < n:
        u[t] = 1.0
        t += int(rng.integers(3, 9) if rng.random() < 0.3 else rng.integers(40, 120))
    truth = paper_model(3, passive_effects(1.2, 1800.0, 25.0, 0.05)).with_params(
        gain=1.5e4, gamma_angle=-1e-2, gamma_velocity=-2e-3, delay=5
    )
    a, v, _ = simulate_angles(truth, jnp.asarray(u))
    a = np.asarray(a, float) + rng.normal(0, 0.2, n)
    return Trial.from_signals("TN", "left", 2, 0.01, a, np.zeros(n), u)


@pytest.mark.parametrize("name", ["model1", "model2", "model3"])
def test_j_matches_a_plain_per_window_loop(name):
    trial = _noisy_trial()
    p = PARAMS[name]
    if name == "model2":
        model = paper_model(2, passive_effects(**PASSIVE), delay=4).with_params(
            a=np.array([p["a1"], p["a2"]]), b=np.array([p["b1"], p["b2"]])
        )
    else:
        model = paper_model(name, passive_effects(**PASSIVE), delay=4).with_params(**p)
    ours = prediction_errors(model, trial)
    ref = j_phi_loop(name, {**p, **PASSIVE}, 4, trial.angle_deg, trial.velocity_deg_s, trial.stimulation)
    assert set(ours) == {10, 25, 50, 100}
    for h in ours:
        assert ours[h] == pytest.approx(ref[h], rel=2e-3), h
    # errors grow with horizon on data from another model
    vals = [ours[h] for h in (10, 25, 50, 100)]
    assert vals[0] < vals[-1]


def test_sign_test_counts_and_p_values():
    legs = [f"L{i}" for i in range(5)]
    J = {"model1": {}, "model3": {}, "model2": {}}
    for i, leg in enumerate(legs):
        for t in ("2", "3"):
            J["model1"][leg] = J["model1"].get(leg, {})
            J["model3"][leg] = J["model3"].get(leg, {})
            J["model2"][leg] = J["model2"].get(leg, {})
            J["model1"][leg][t] = {100: 2.0, 1000: 10.0}
            J["model3"][leg][t] = {100: 2.0 + (0.1 if i % 2 else -0.1), 1000: 7.0}
            # model2 beats model1 at 1 s in 9 of 10 pairs
            J["model2"][leg][t] = {100: 2.0, 1000: 9.0 if (i, t) != (0, "2") else 11.0}
    tests = {(r["model_a"], r["model_b"], r["horizon_ms"]): r for r in sign_tests(J)}
    r = tests[("model1", "model3", 1000)]
    assert (r["n_pairs"], r["a_better"], r["b_better"]) == (10, 0, 10)
    assert r["p_value"] == pytest.approx(2 * 0.5**10)
    assert r["significant"] and r["better"] == "model3"
    r = tests[("model1", "model2", 1000)]
    assert (r["a_better"], r["b_better"]) == (1, 9)
    assert r["p_value"] == pytest.approx(2 * 11 * 0.5**10)  # P(X<=1) two-sided, n = 10
    assert r["significant"]
    r = tests[("model1", "model3", 100)]
    assert not r["significant"] and r["better"] is None
    r = tests[("model1", "model2", 100)]  # ties are dropped, as in a sign test
    assert r["n_pairs"] == 0 and r["p_value"] == 1.0


def test_table_v_is_mean_and_sd_over_legs():
    J = {"model1": {"A": {"1": {100: 2.0}}, "B": {"1": {100: 4.0}}, "C": {"1": {100: 6.0}}}}
    T = table_v(J)
    mean, sd, n = T["1"]["model1"][100]
    assert (mean, n) == (4.0, 3)
    assert sd == pytest.approx(2.0)


def test_a_model_whose_predictions_diverge_is_named():
    """An unstable identified filter (model 2 with a pole outside the unit circle) gives J that is
    not finite; evaluate_cohort names the model, leg, trial and horizons instead of leaving a bare
    NaN, and a stable model on the same trial draws no warning."""
    import warnings

    from quadshank.data._cohort import Cohort
    from quadshank.evaluation._prediction import DivergedPredictionWarning, evaluate_cohort

    trial = _noisy_trial()
    cohort = Cohort([trial])
    passive = passive_effects(**PASSIVE)
    stable = paper_model(2, passive, delay=4).with_params(a=np.array([-1.45, 0.6]), b=np.array([500.0, 600.0]))
    unstable = paper_model(2, passive, delay=4).with_params(a=np.array([-2.5, 1.6]), b=np.array([500.0, 600.0]))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        J = evaluate_cohort(cohort, {trial.key: {"model2": unstable, "model3": paper_model(3, passive, delay=4)
                                                  .with_params(**PARAMS["model3"])}})
    said = [str(w.message) for w in caught if issubclass(w.category, DivergedPredictionWarning)]
    assert not np.isfinite(J["model2"][trial.key]["2"][1000])
    assert len(said) == 1 and said[0].startswith(f"model2 on {trial.key} trial 2: its predictions are not finite")
    assert "1000 ms" in said[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error", DivergedPredictionWarning)
        assert np.isfinite(evaluate_cohort(cohort, {trial.key: {"model2": stable}})["model2"][trial.key]["2"][1000])


def test_a_user_effect_that_returns_nan_is_named():
    """A user's effect whose factor is not finite gives J that is not finite; the warning names the
    model, the trial, the first start that fails and the user's effects, not only a bare NaN."""
    from quadshank import build_model
    from quadshank.evaluation import prediction_errors
    from quadshank.evaluation._prediction import DivergedPredictionWarning

    trial = _noisy_trial()
    model = build_model("model3", "cubic_torque_angle")  # one name, not a list: conftest.py registers it
    assert model.name == "model3+cubic_torque_angle"
    model = model.with_params(**PARAMS["model3"], c3=float("nan"))
    first = int(trial.pulse_indices[0])
    with pytest.warns(DivergedPredictionWarning) as caught:
        J = prediction_errors(model, trial, (10, 25))
    said = [str(w.message) for w in caught if issubclass(w.category, DivergedPredictionWarning)]
    assert not np.isfinite(J[10]) and len(said) == 1
    said = said[0]
    assert said.startswith(f"model3+cubic_torque_angle on {trial.key} trial 2: its predictions are not finite "
                           "(J at 100 ms, 250 ms), first from sample ")
    assert "or an effect (cubic_torque_angle) returns a value that is not finite" in said
    assert int(said.split("first from sample ")[1].split(":")[0]) <= first


def test_figures_leave_a_gap_where_a_prediction_meets_an_excluded_sample():
    """The predictions a figure draws are those J scores: where the run from a start meets an
    excluded sample the band is NaN (a gap), and every other start is predicted."""
    import jax

    from quadshank.evaluation._posterior import figure_window, window_predictions
    from quadshank.evaluation._prediction import scored

    trial = _noisy_trial()
    exclude = np.zeros(trial.n_samples, bool)
    exclude[3200:3400] = True
    trial = trial.replace(exclude=exclude)
    model = paper_model(3, passive_effects(**PASSIVE), delay=4).with_params(**PARAMS["model3"])
    draws = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), model)  # two draws of one model
    window = figure_window(trial, (30.0, 10.0))
    out = window_predictions(draws, trial, (10, 100), window)
    for p, (starts, pred) in out.items():
        gap = (starts + p >= 3200) & (starts <= 3399)
        assert np.isnan(pred[:, gap]).all() and np.isfinite(pred[:, ~gap]).all(), p
        np.testing.assert_array_equal(~gap, scored(trial, starts, p))
