"""The angle likelihood of a model with a muscle: shooting segments from the measured state.

Each segment's run must be exactly the rollout J scores (``model.predict_ahead``), the pieces the
fit and PSIS-LOO use must agree, the models it cannot fit are refused with the reason, and the
screen on the angle recovers a model with a twitch shape from simulated data."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quadshank.common._arrays import stretches
from quadshank.data import Cohort, default_truth, derive_acceleration, simulate_cohort
from quadshank.inference import laplace_fit
from quadshank.loop._diagnose import not_applicable
from quadshank.model import paper_model
from quadshank.model._likelihood import (
    LikelihoodError,
    free_run_angles,
    leg_loglik_by_delay,
    leg_pointwise,
    prepare,
    resolve_objective,
    shooting_samples,
)
from quadshank.model._model import predict_ahead


@pytest.fixture(scope="module")
def two_trials():
    """One leg, two short trials; trial 1 has an excluded stretch in its middle."""
    cohort, _ = simulate_cohort(legs=("JM-left",), minutes=0.25, seed=5, trials=(1, 2))
    t1, t2 = cohort.get("JM-left", 1), cohort.get("JM-left", 2)
    exclude = np.zeros(t1.n_samples, bool)
    exclude[700:760] = True
    return Cohort((t1.replace(exclude=exclude), t2))


def _model3s():
    """Model 3 with a twitch shape at JM-left's truth (its DARMA equivalent), delay 5."""
    leg = default_truth(("JM-left",))["legs"]["JM-left"]
    active, darma, passive = leg["active"], leg["model2_equivalent"], leg["passive"]
    return paper_model("3s").with_params(
        a=jnp.array([darma["a1"], darma["a2"]]), b=jnp.array([darma["b1"], darma["b2"]]),
        gamma_angle=active["gamma_angle"], gamma_velocity=active["gamma_velocity"],
        **{k: passive[k] for k in ("damping", "gravity", "k1", "k2")}, delay=5)


def test_each_shooting_run_is_the_rollout_j_scores(two_trials):
    model = _model3s()
    data = prepare(two_trials, model, trials=(1, 2), objective="angle")
    x = {k: v[0] for k, v in data.leg_arrays().items()}
    predicted = np.asarray(free_run_angles(model, x))
    reset, compared = np.asarray(x["reset"]), np.asarray(x["sample_mask"])
    p = shooting_samples(model.sampling_period_s)
    starts = np.flatnonzero(reset)
    assert not compared[reset].any()
    trial2 = int(np.flatnonzero(np.asarray(x["begin"]))[1])  # trial 2's first sample in the leg's arrays
    checked = 0
    for s in starts:
        trial, offset = (two_trials.get("JM-left", 1), 0) if s < trial2 else (two_trials.get("JM-left", 2), trial2)
        stop = np.flatnonzero(reset[s + 1 :] | ~compared[s + 1 :])  # the run ends where the next starts or at a gap
        n = min(p - 1, int(stop[0]) if stop.size else p - 1)
        if n < 1 or s - offset + n >= trial.n_samples:
            continue
        ref = np.asarray(predict_ahead(model, trial.angle_deg, trial.velocity_deg_s, trial.stimulation,
                                       np.array([s - offset]), n))[0]
        np.testing.assert_allclose(predicted[s + 1 : s + 1 + n], ref, atol=2e-3)
        checked += 1
    assert checked >= 10
    # a run starts at each stretch of compared samples (after the excluded one too) and every p samples in it
    spans = stretches(compared | reset)
    assert len(spans) == 3  # trial 1 before and after its excluded samples, trial 2
    assert starts.tolist() == [k for a, b in spans for k in range(a, b, p)]


def test_the_fit_and_psis_loo_see_the_same_angle_likelihood(two_trials):
    model = _model3s()
    data = prepare(two_trials, model, trials=(1, 2), objective="angle")
    x = {k: v[0] for k, v in data.leg_arrays().items()}
    noise = {"sigma": jnp.float32(0.5), "nu": jnp.float32(8.0)}
    by_delay = np.asarray(leg_loglik_by_delay(model, noise, x, data.response_length, data.max_shift))[:, 0]
    for d in (2, 5, 9):
        seg = np.asarray(leg_pointwise(model, noise, x, d, data.response_length, data.n_segments))
        np.testing.assert_allclose(seg.sum(), by_delay[d], rtol=1e-4)
    # the delay matters to the angle: the true delay's runs are far likelier than a wrong one's
    assert by_delay[5] > by_delay[9] + 100 and by_delay[5] > by_delay[1] + 100


def test_a_run_that_diverges_keeps_the_likelihood_and_its_gradient_finite(two_trials):
    """An optimiser's trial step can make the twitch filter unstable: its runs then grow without
    bound, and an overflow would turn the log density and its gradient into NaN."""
    model = _model3s().with_params(a=jnp.array([-2.6, 1.7]))  # poles outside the unit circle
    data = prepare(two_trials, model, trials=(1, 2), objective="angle")
    x = {k: v[0] for k, v in data.leg_arrays().items()}

    def total(values):
        m = model.with_params(values)
        return jnp.sum(leg_loglik_by_delay(m, {"sigma": 0.5, "nu": 8.0}, x, data.response_length, data.max_shift))

    values = {k: jnp.asarray(v, jnp.float32) for k, v in model.params().items()}
    value, grad = jax.value_and_grad(total)(values)
    assert np.isfinite(float(value)) and float(value) < -1e5
    assert all(np.all(np.isfinite(np.asarray(g))) for g in grad.values())


def test_double_precision_parameters_run_on_single_precision_data(two_trials):
    model = _model3s()
    data = prepare(two_trials, model, trials=(1, 2), objective="angle")
    x32 = {k: v[0] for k, v in data.leg_arrays().items()}
    with jax.enable_x64(True):
        m64 = model.with_params({k: jnp.asarray(v, jnp.float64) for k, v in model.params().items()})
        x64 = {k: v.astype(jnp.float64) if jnp.issubdtype(v.dtype, jnp.floating) else v for k, v in x32.items()}
        noise = {"sigma": jnp.float64(0.5), "nu": jnp.float64(8.0)}
        mixed = np.asarray(leg_loglik_by_delay(m64, noise, x32, data.response_length, data.max_shift))
        double = np.asarray(leg_loglik_by_delay(m64, noise, x64, data.response_length, data.max_shift))
    np.testing.assert_allclose(mixed, double, rtol=1e-9)


def test_models_the_angle_cannot_fit_are_refused_with_the_reason():
    assert resolve_objective(paper_model(3), "auto") == "acceleration"
    assert resolve_objective(paper_model(3), "angle") == "angle"
    assert resolve_objective(paper_model("passive"), "auto") == "angle"
    for effect, kind in (("angle_delay", "delay"), ("twitch_variability", "noise")):
        with pytest.raises(LikelihoodError, match=f"'{effect}', a {kind} effect.*--likelihood acceleration"):
            resolve_objective(paper_model(3).add(effect), "angle")


def test_a_fit_on_the_angle_says_what_it_costs_before_it_starts(two_trials, tmp_path, monkeypatch, capsys):
    """A muscle's fit on the angle is about 15 times the acceleration's per gradient: the command
    says so, and how to bound the wait, before any work; a fit on the acceleration does not."""
    import quadshank.commands.fit as fit_command
    from quadshank.inference import FitSettings

    class Started(Exception):
        pass

    def started(*args, **kwargs):
        raise Started

    monkeypatch.setattr(fit_command, "run_nuts", started)
    for likelihood, said in (("angle", True), ("acceleration", False)):
        capsys.readouterr()
        with pytest.raises(Started):
            fit_command.run_fit(two_trials, tmp_path / likelihood, "model3s",
                                settings=FitSettings(likelihood=likelihood, trials=(1,)), progress=True)
        err = capsys.readouterr().err
        assert ("about 15 times the acceleration's cost" in err and "--time-limit" in err) == said, err
    with pytest.raises(KeyError, match="no trial 7"):  # a trial the data lack: refused before the notice
        fit_command.run_fit(two_trials, tmp_path / "missing", "model3s",
                            settings=FitSettings(likelihood="angle", trials=(7,)), progress=True)
    assert capsys.readouterr().err == ""


def test_the_loop_lists_what_the_angle_cannot_screen_with_the_reason(two_trials):
    legs, trials = ("JM-left",), (1,)
    out = not_applicable(paper_model(3), two_trials, ["angle_delay", "twitch_variability", "fatigue"], legs, trials,
                         "angle")
    assert set(out) == {"angle_delay", "twitch_variability"}
    assert "delay effect" in out["angle_delay"] and "noise effect" in out["twitch_variability"]
    assert not not_applicable(paper_model(3), two_trials, ["angle_delay", "twitch_variability"], legs, trials,
                              "acceleration")


def test_the_screen_on_the_angle_recovers_a_model_with_a_twitch_shape():
    """Equal twitches: on 30 s the variation of twitches from pulse to pulse (which the angle's
    likelihood has no term for) moves the gain factors by more than the angle's own error."""
    cohort, truth = simulate_cohort(legs=("TN-left",), minutes=0.5, seed=4, trials=(1,), twitch_cv=0.0)
    fit = laplace_fit(cohort, paper_model("3s"), objective="angle", loo=False, n_starts=1)
    t = truth["legs"]["TN-left"]
    v = fit.values("TN-left")
    assert fit.data.objective == "angle"
    assert int(np.argmax(fit.delay_posterior[0])) in (4, 5)  # the truth: 4.3 samples
    for k in ("damping", "gravity"):
        assert v[k] == pytest.approx(t["passive"][k], rel=0.05), k
    assert v["k1"] == pytest.approx(t["passive"]["k1"], rel=0.4)
    assert v["k2"] == pytest.approx(t["passive"]["k2"], rel=0.2)
    # the twitch's area (its DC gain), which the angle integrates; its shape the angle sees less sharply
    area = float(np.sum(v["b"]) / (1.0 + np.sum(v["a"])))
    assert area == pytest.approx(t["active"]["G2"], rel=0.05)
    assert v["gamma_angle"] == pytest.approx(t["active"]["gamma_angle"], rel=0.2)


def test_the_loop_lists_an_accelerometers_response_as_not_applicable_without_one(two_trials):
    """Where no trial screened has an accelerometer, an effect on what one reads would fit the
    smoothing of the filter that derived the acceleration: listed with the reason, not screened.
    One trial with an accelerometer among those screened makes it applicable again."""
    legs = ("JM-left",)
    derived = Cohort(tuple(t.replace(acceleration_deg_s2=derive_acceleration(t.angle_deg, t.sampling_period_s),
                                     acceleration_measured=False) for t in two_trials.trials))
    out = not_applicable(paper_model(3), derived, ["accel_resonance", "goniometer_offset", "fatigue"], legs, (1, 2))
    assert set(out) == {"accel_resonance"}
    assert out["accel_resonance"].startswith("changes only what an accelerometer reads, and trial(s) 1, 2 have none")
    mixed = Cohort((derived.get("JM-left", 1), two_trials.get("JM-left", 2)))
    assert not not_applicable(paper_model(3), mixed, ["accel_resonance"], legs, (1, 2))
    assert not not_applicable(paper_model(3), two_trials, ["accel_resonance"], legs, (1, 2))


def test_a_fit_with_an_accelerometers_response_on_recordings_without_one_warns(two_trials, tmp_path, monkeypatch):
    """`fit --add-effect accel_resonance` on angle-only recordings says that the effect would
    describe the derivation's smoothing; with an accelerometer it says nothing (the fit itself
    is not run: it stops where the sampler would start)."""
    from quadshank.commands import fit as fit_command
    from quadshank.data import DataWarning

    class Stop(Exception):
        pass

    def stop(*args, **kwargs):
        raise Stop

    monkeypatch.setattr(fit_command, "run_nuts", stop)
    derived = Cohort(tuple(t.replace(acceleration_deg_s2=derive_acceleration(t.angle_deg, t.sampling_period_s),
                                     acceleration_measured=False) for t in two_trials.trials))
    for cohort, warned in ((derived, True), (two_trials, False)):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            with pytest.raises(Stop):
                fit_command.run_fit(cohort, tmp_path / "fit", model="model3", add_effects=("accel_resonance",))
        said = [str(w.message) for w in caught if issubclass(w.category, DataWarning) and "accelerometer" in str(w.message)]
        assert len(said) == int(warned), said
        if warned:
            assert said[0].startswith("accel_resonance changes only what an accelerometer reads, and these recordings")
