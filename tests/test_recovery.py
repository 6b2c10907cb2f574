"""Parameter recovery on a matching truth: the data generator, the coverage count, the command."""

import json

import jax.numpy as jnp
import numpy as np
import pytest

from quadshank.cli import main
from quadshank.inference._priors import build_model
from quadshank.model._likelihood import leg_loglik_by_delay, prepare
from quadshank.model._model import equivalent_acceleration, simulate_angles
from quadshank.evaluation._recovery import MATCHING_NOISE, ANGLE_RANGE, coverage_rows, matching_values, simulate_matching


@pytest.mark.parametrize("model", ["model1", "model2", "model3"])
def test_matching_data_are_the_model_plus_student_t_noise(model):
    cohort, truth = simulate_matching(model, legs=["JM-left", "OT-left"], minutes=0.5, seed=4)
    assert truth["model"] == model and set(truth["legs"]) == {"JM-left", "OT-left"}
    for trial in cohort.trials:
        true = truth["legs"][trial.key]
        m = build_model(model).with_params({k: jnp.asarray(v) for k, v in true["params"].items()}, delay=true["delay"])
        u = truth["recruitment"][trial.key]["1"]
        assert set(np.unique(trial.stimulation)) <= {0.0, u}
        assert ANGLE_RANGE[0] <= trial.angle_deg.min() and trial.angle_deg.max() <= ANGLE_RANGE[1]
        angle, velocity, em = (np.asarray(v) for v in simulate_angles(m, jnp.asarray(trial.stimulation, jnp.float32)))
        np.testing.assert_allclose(trial.angle_deg, angle, atol=1e-4)
        np.testing.assert_allclose(trial.velocity_deg_s, velocity, atol=1e-3)
        resid = np.asarray(equivalent_acceleration(m, trial.angle_deg, trial.velocity_deg_s, trial.acceleration_deg_s2)) - em
        # t(5) scaled by 40: median |x| = 0.727 * 40; a wrong scale or no noise misses this
        assert np.median(np.abs(resid)) == pytest.approx(0.727 * MATCHING_NOISE["sigma"], rel=0.1)
    again, _ = simulate_matching(model, legs=["JM-left", "OT-left"], minutes=0.5, seed=4)
    np.testing.assert_array_equal(again.trials[0].acceleration_deg_s2, cohort.trials[0].acceleration_deg_s2)
    other, _ = simulate_matching(model, legs=["JM-left", "OT-left"], minutes=0.5, seed=5)
    assert not np.array_equal(other.trials[0].stimulation, cohort.trials[0].stimulation)


def test_the_recruitment_is_lowered_only_where_the_model_leaves_the_range():
    _, t1 = simulate_matching("model1", legs=["OT-left"], minutes=1.0, seed=0)
    _, t3 = simulate_matching("model3", legs=["OT-left"], minutes=1.0, seed=0)
    assert t3["recruitment"]["OT-left"]["1"] == 1.0  # model 3's torque-angle factor keeps it in range
    assert t1["recruitment"]["OT-left"]["1"] < 1.0


def test_the_likelihood_peaks_at_the_true_delay_of_matching_data():
    cohort, truth = simulate_matching("model2", legs=["TN-right"], minutes=1.0, seed=1)
    true = truth["legs"]["TN-right"]
    m = build_model("model2").with_params({k: jnp.asarray(v, jnp.float32) for k, v in true["params"].items()})
    data = prepare(cohort, m)
    x = {k: v[0] for k, v in data.leg_arrays().items()}
    noise = {"sigma": jnp.float32(MATCHING_NOISE["sigma"]), "nu": jnp.float32(MATCHING_NOISE["nu"])}
    ll = np.asarray(leg_loglik_by_delay(m, noise, x, data.response_length))[:, 0]
    assert int(np.argmax(ll)) == true["delay"] == 5
    assert ll[5] - np.sort(ll)[-2] > 50.0


def test_coverage_rows_count_each_component_and_the_delay_mode():
    truth = {"legs": {"A-left": {"params": {"gain": 2.0, "a": [-1.5, 0.6]}, "delay": 4}}}
    p = np.full(11, 0.01)
    p[3] = 0.9
    summary = {"legs": {"A-left": {
        "params": {"gain": {"median": 2.1, "lo": 1.9, "hi": 2.3},
                   "a": {"median": [-1.4, 0.6], "lo": [-1.45, 0.5], "hi": [-1.3, 0.7]}},
        "delay_posterior": p.tolist(),
    }}}  # fmt: skip
    rows = {r["param"]: r for r in coverage_rows(summary["legs"], truth)}
    assert set(rows) == {"gain", "a[0]", "a[1]", "delay"}
    assert rows["gain"]["covered"] and rows["a[1]"]["covered"]
    assert not rows["a[0]"]["covered"]  # -1.5 is below the interval [-1.45, -1.3]
    assert not rows["delay"]["covered"] and rows["delay"]["median"] == 3.0
    with pytest.raises(KeyError, match="B-left"):
        coverage_rows(summary["legs"], {"legs": {"B-left": truth["legs"]["A-left"]}})


def test_matching_values_follow_the_paper_tables():
    v = matching_values("model3", "JM-left")
    assert v["params"]["gamma_angle"] == pytest.approx(-2.16e-2) and v["delay"] == 4
    assert matching_values("model2", "TN-left")["params"]["b"] == [541.0, 645.0]
    with pytest.raises(ValueError, match="model4"):
        matching_values("model4", "TN-left")


def test_recovery_command_writes_the_coverage_table(tmp_path, capsys):
    """The coverage table, its exit code 3 and a warning where a fit failed its checks, and a rerun
    into the same folder that takes the finished fit again rather than fitting it anew."""
    out = tmp_path / "rec"
    args = ["recovery", "--models", "model1", "--seeds", "3", "--legs", "TN-left,JM-left", "--minutes", "0.5",
            "--chains", "1", "--warmup", "30", "--draws", "20", "--start", "prior", "--out", str(out)]
    capsys.readouterr()
    code = main(args)
    said = capsys.readouterr()
    result = json.loads((out / "coverage.json").read_text())
    ok = result["models"]["model1"]["fits"][0]["ok"]
    assert code == (0 if ok else 3) and ("fits failed their checks" in said.err) == (not ok)
    assert "90 % intervals cover the truth" in said.err and "expected if calibrated" in said.err
    assert "the delay not estimated (P(d) stayed the prior's on every leg)" in said.err  # model 1 does not see it
    fit_before = (out / "model1-seed3" / "fit.nc").stat().st_mtime_ns
    assert main(["-q", *args]) == code  # again into its own folder: the finished fit is taken again
    again = json.loads((out / "coverage.json").read_text())
    assert again["models"]["model1"]["fits"][0]["reused"] is True
    assert (out / "model1-seed3" / "fit.nc").stat().st_mtime_ns == fit_before
    assert again["models"]["model1"]["covered"] == result["models"]["model1"]["covered"]
    assert result["settings"]["start"] == "prior"
    m = result["models"]["model1"]
    # per leg: gain and four passive parameters, and the delay row
    assert m["n_intervals"] == 2 * 5 and m["delay_legs"] == 2
    assert m["covered"] == sum(r["covered"] for r in result["rows"] if r["param"] != "delay")
    lo, hi = m["expected_band_95"]
    assert lo < 0.9 < hi
    # each parameter row has the leg's own maximum likelihood at the true delay, close to the truth
    # (its data were made by it), and the posterior median's pull from it
    for r in (r for r in result["rows"] if r["param"] != "delay"):
        assert abs(r["ml"] - r["true"]) < 4.0 * r["ml_se"], r
        assert r["pull"] == pytest.approx((r["median"] - r["ml"]) / r["ml_se"])
    assert (out / "model1-seed3" / "fit.nc").exists() and (out / "model1-seed3" / "truth.json").exists()
    md = (out / "coverage.md").read_text()
    assert "quadshank" in md and "| model1 |" in md


@pytest.mark.parametrize("with_step", [True, False])
def test_the_angle_delay_likelihood_finds_the_step_of_matching_data(with_step):
    cohort, truth = simulate_matching("model2", legs=["TN-left"], minutes=2.0, seed=2,
                                      add_effects=["angle_delay"] if with_step else [])  # fmt: skip
    true = truth["legs"]["TN-left"]
    m = build_model("model2", ["angle_delay"])
    params = {k: jnp.asarray(v, jnp.float32) for k, v in true["params"].items() if k != "threshold"}
    data = prepare(cohort, m)
    x = {k: v[0] for k, v in data.leg_arrays().items()}
    noise = {"sigma": jnp.float32(MATCHING_NOISE["sigma"]), "nu": jnp.float32(MATCHING_NOISE["nu"])}
    grid = np.arange(-35.0, 10.5, 1.0)
    ll = np.stack([
        np.asarray(leg_loglik_by_delay(m.with_params(params, threshold=jnp.float32(t)), noise, x,
                                       data.response_length, data.max_shift))[true["delay"]]
        for t in grid
    ])  # (thresholds, shifts)  # fmt: skip
    if with_step:
        best = grid[np.argmax(ll[:, 1])]
        assert abs(best + 20.0) <= 2.0, best
        assert ll[:, 1].max() - ll[0, 0] > 20.0  # the step beats no change clearly
    else:
        # no threshold inside the pulses' angles makes a shorter delay better than none
        assert ll[:, 1].max() - ll[0, 0] < 2.0 and ll[:, 2].max() - ll[0, 0] < 2.0


def test_recovery_reuses_a_finished_fit_of_the_same_truth_settings_and_code(tmp_path, monkeypatch):
    import quadshank.commands.recovery as recovery
    import quadshank.common._provenance as provenance
    from quadshank.inference import FitResult, FitSettings

    calls = []

    def fake_run_fit(cohort, out, model, add_effects, settings, progress=False):
        calls.append(settings.seed)
        truth = json.loads((out / "truth.json").read_text())
        legs = {leg: {"params": {k: {"median": v, "lo": v, "hi": v} for k, v in t["params"].items()},
                      "delay_posterior": [0.0] * 4 + [1.0] + [0.0] * 6} for leg, t in truth["legs"].items()}  # fmt: skip
        summary = FitResult(
            model="model1", effects=[], trials=[1], legs=legs, banner=None, chain_method="vectorized",
            diagnostics={"rhat_max": 1.0, "ess_bulk_min": 500.0, "divergences": 0, "ok": True},
            settings=json.loads(json.dumps({k: list(v) if isinstance(v, tuple) else v for k, v in settings.__dict__.items()})),
            sampling_period_s=0.01, interval=[0.05, 0.95], code=provenance.code_provenance(),
        )
        summary.write(out)
        (out / "fit.nc").write_text("")
        return summary

    monkeypatch.setattr(recovery, "run_fit", fake_run_fit)
    monkeypatch.setattr(recovery, "add_pulls", lambda *a: None)  # the legs' own likelihood: not tested here
    settings = FitSettings(chains=1, warmup=5, draws=5)
    kw = dict(models=["model1"], seeds=[0, 1], legs=["TN-left"], minutes=0.2, settings=settings)
    run_recovery = recovery.run_recovery
    result = run_recovery(tmp_path, **kw)
    assert calls == [0, 1]
    assert [f["reused"] for f in result["models"]["model1"]["fits"]] == [False, False]
    result = run_recovery(tmp_path, **kw)
    assert calls == [0, 1]  # both reused
    assert [f["reused"] for f in result["models"]["model1"]["fits"]] == [True, True]
    with monkeypatch.context() as m:
        m.setattr(recovery, "code_fingerprint", lambda: "another-code")
        run_recovery(tmp_path, **kw)
    assert calls == [0, 1, 0, 1]  # the package changed: refitted
    run_recovery(tmp_path, **{**kw, "minutes": 0.3})
    assert calls == [0, 1] * 3  # another truth: refitted
    run_recovery(tmp_path, **{**kw, "minutes": 0.3, "settings": FitSettings(chains=1, warmup=6, draws=5)})
    assert calls == [0, 1] * 4  # other settings: refitted


def test_coverage_table_names_delays_missed_and_wrong_modes_the_data_chose():
    """The Sampling table names each fit's split chains and missed delays; the wrong-mode table lists
    a leg whose data chose a delay (P(mode) ≥ 0.5) with P(true d) from the chains and the evidence,
    and leaves out a flat P(d) whose argmax is no claim."""
    from quadshank.outputs._recovery import coverage_markdown

    fit = {"seed": 2, "rhat_max": 1.06, "ess_bulk_min": 32, "divergences": 0, "ok": False, "sampling_seconds": 30,
           "delay_splits": {"TN-right": [4, 5]}, "delay_missed": {"JM-left": {"4": [0.25, 0.0]}}}
    rows = [
        {"model": "model3", "seed": 2, "leg": "JM-left", "param": "delay", "true": 4.0, "median": 3.0,
         "covered": False, "p_mode": 1.0, "p_true": 0.0, "p_true_evidence": 0.25},
        {"model": "model3", "seed": 2, "leg": "TN-left", "param": "delay", "true": 4.0, "median": 0.0,
         "covered": False, "p_mode": 0.09, "p_true": 0.09, "p_true_evidence": 0.09},
    ]  # fmt: skip
    result = {"legs": ["JM-left", "TN-left"], "seeds": [2], "minutes": 1, "interval": 0.9,
              "settings": {"chains": 2, "warmup": 300, "draws": 300}, "rows": rows,
              "models": {"model3": {"truth_effects": [], "n_intervals": 0, "covered": 0, "coverage": float("nan"),
                                    "expected_band_95": [0.8, 0.95], "by_param": {}, "fits": [fit],
                                    "delay_mode_right": 0, "delay_legs": 2, "delay_seen_legs": 1,
                                    "pull": [{"param": "k1", "leg": "JM-left", "fits": 4, "median_abs": 0.57,
                                              "max_abs": 0.95, "mean": 0.5}]}}}  # fmt: skip
    md = coverage_markdown(result)
    assert "| model3 | k1 | JM-left | 4 | 0.57 | 0.95 | +0.50 |" in md
    assert "| model3 | 2 | 1.060 | 32 | 0 | TN-right 4/5 | JM-left d = 4 (0.25) | 30 |" in md
    assert "| model3 | 2 | JM-left | 4 | 3 | 0.00 | 0.25 |" in md
    assert "| model3 | 2 | TN-left |" not in md


def test_likelihood_check_command_finds_the_likelihood_calibrated(tmp_path):
    # model 3 on one leg, 1 min: 40 noise replicates of one trajectory, maximum likelihood at the true d
    out = tmp_path / "lc"
    code = main(["-q", "likelihood-check", "--models", "model3", "--seeds", "1", "--legs", "TN-right",
                 "--minutes", "1", "--replicates", "40", "--out", str(out)])  # fmt: skip
    assert code == 0
    (run,) = json.loads((out / "likelihood.json").read_text())["runs"]
    leg = run["legs"]["TN-right"]
    assert leg["converged"] >= 36 and leg["intervals"] == 7 * leg["converged"]
    # a twitch window's noise with the sum's variance and kurtosis (window_noise): the well-determined
    # parameters' z has mean 0 and sd 1 within the spread of 40 replicates (sd of z sd ≈ 0.11), and
    # σ is unbiased; scaled as σ√n·t_ν instead, the gain's z sd was 1.1–1.3 (results/likelihood-check)
    assert 0.80 <= run["coverage"] <= 0.97, run["coverage"]
    for name in ("damping", "gain", "gamma_angle", "gamma_velocity", "sigma"):
        p = leg["params"][name]
        assert abs(p["z_mean"]) < 3.5 * p["z_se"], (name, p)
        assert 0.7 < p["z_sd"] < 1.3, (name, p)
    md = (out / "likelihood.md").read_text()
    assert "Regenerate: `quadshank" in md and "| model3 | 1 |" in md


def test_likelihood_check_sees_a_bias(monkeypatch):
    # the same check told a gain 4 % above the one that made the data: z of the gain far below 0
    import quadshank.evaluation._recovery as rec

    simulate = rec.simulate_matching

    def off_truth(*args, **kwargs):
        cohort, truth = simulate(*args, **kwargs)
        for true in truth["legs"].values():
            true["params"]["gain"] *= 1.04
        return cohort, truth

    monkeypatch.setattr(rec, "simulate_matching", off_truth)
    run = rec.likelihood_calibration("model3", legs=["TN-right"], minutes=1.0, seed=1, replicates=12)
    gain = run["legs"]["TN-right"]["params"]["gain"]
    assert run["legs"]["TN-right"]["converged"] >= 10
    assert gain["z_mean"] < -5.0 and gain["coverage"] < 0.3, gain
    assert run["coverage"] < run["expected_band_95"][0]
