"""Pendulum tests (trials without pulses) as data: the passive system identified from them alone,
or beside stimulated trials, as the paper took it from pendulum tests."""

from __future__ import annotations

import json

import numpy as np
import pytest

from quadshank.cli import main
from quadshank.data import Cohort, DataWarning, Trial, simulate_cohort, simulate_pendulum_test, write_interchange
from quadshank.evaluation import free_run_error, free_runs
from quadshank.inference import (
    IdentificationError,
    LegIdentification,
    PassiveIdentification,
    identify_cohort,
    passive_model,
)

DT = 0.01
PASSIVE = {"damping": 1.3, "gravity": 1950.0, "k1": 30.0, "k2": 0.05}
#: One swing from +60° reaches about -40°: over that range G', k1 and k2 trade off against each other
#: (k1·(exp(-k2·φ) - 1) is nearly linear in φ, as is G'·sin φ), so what a pendulum test pins down is
#: D' and the passive torque curve over the swing, not its three terms one by one.
DAMPING_TOLERANCE = 0.05
CURVE_TOLERANCE = 0.10  # RMS over the swing, relative to the curve's RMS


def _curve(p: dict, phi: np.ndarray) -> np.ndarray:
    return -p["gravity"] * np.sin(np.deg2rad(phi - p.get("gravity_angle", 0.0))) + p["k1"] * np.expm1(-p["k2"] * phi)


def _assert_passive_recovered(found: dict, truth: dict, angle: np.ndarray) -> None:
    assert found["damping"] == pytest.approx(truth["damping"], rel=DAMPING_TOLERANCE)
    phi = np.linspace(angle.min(), min(angle.max(), 60.0), 200)
    err = np.sqrt(np.mean((_curve(found, phi) - _curve(truth, phi)) ** 2)) / np.sqrt(np.mean(_curve(truth, phi) ** 2))
    assert err < CURVE_TOLERANCE, err


def _pendulum_trial(subject: str, trial: int, passive: dict, seed: int = 0) -> Trial:
    """A shank released from 60° at rest, the examiner's hand pushing for 0.3 s, sensor noise of
    0.05° and 30 deg/s² (:func:`quadshank.data.simulate_pendulum_test`)."""
    return simulate_pendulum_test(passive, subject=subject, trial=trial, seed=seed)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_pendulum_test_alone_gives_the_passive_system(seed):
    t = _pendulum_trial("PT", 1, PASSIVE, seed)
    r = identify_cohort(Cohort((t,)))["PT-left"]
    assert isinstance(r, PassiveIdentification) and r.passive_trials == (1,)
    _assert_passive_recovered(r.passive, PASSIVE, t.angle_deg)
    assert set(r.models) == {"passive"} and r.models["passive"].flat_params()["gain"] == 0.0


def test_a_pendulum_test_beside_stimulated_trials_gives_their_passive_system():
    cohort, truth = simulate_cohort(legs=["TN-left"], minutes=2.0, seed=0, trials=[1])
    passive = truth["legs"]["TN-left"]["passive"]
    pendulum = _pendulum_trial("TN", 2, passive)
    both = identify_cohort(Cohort(cohort.trials + (pendulum,)))["TN-left"]
    alone = identify_cohort(cohort)["TN-left"]
    assert isinstance(both, LegIdentification) and both.passive_trials == (2,) and alone.passive_trials == ()
    _assert_passive_recovered(both.passive, passive, pendulum.angle_deg)
    g2 = both.models["model3"].flat_params()["gain"]
    assert g2 == pytest.approx(alone.models["model3"].flat_params()["gain"], rel=0.05)
    assert abs(both.delay - alone.delay) <= 1


def test_identify_and_evaluate_a_cohort_of_pendulum_tests(tmp_path, capsys):
    trials = (_pendulum_trial("PT", 1, PASSIVE, 0), _pendulum_trial("PT", 2, PASSIVE, 1),
              _pendulum_trial("QT", 1, {**PASSIVE, "damping": 0.9}, 2))
    data = write_interchange(Cohort(trials), tmp_path / "data")
    capsys.readouterr()
    assert main(["identify", str(data), "--out", str(tmp_path / "id")]) == 0
    err = capsys.readouterr().err
    assert "PT-left: passive system only, from trial(s) 1, 2" in err
    assert f"tables and summary.json in {tmp_path / 'id'}" in err and not (tmp_path / "id" / "figures").exists()
    s = json.loads((tmp_path / "id" / "summary.json").read_text())["legs"]
    assert s["PT-left"]["passive_only"] and s["QT-left"]["passive_trials"] == [1]
    assert "(no rows)" in (tmp_path / "id" / "tables" / "table1.md").read_text()
    assert "trials 1, 2 (no pulses)" in (tmp_path / "id" / "tables" / "passive.csv").read_text()
    assert "Passive system only" in (tmp_path / "id" / "report.md").read_text()
    assert main(["-q", "evaluate", str(data), "--out", str(tmp_path / "ev"), "--identified", str(tmp_path / "id")]) == 0
    ev = json.loads((tmp_path / "ev" / "summary.json").read_text())
    assert set(ev["J"]) == {"passive"} and ev["sign_tests"] == []
    j = ev["J_per_leg"]["passive"]["PT-left"]["2"]
    assert j["100"] < j["1000"] < 5.0  # the identified pendulum predicts its own swing to within degrees
    # a pendulum test is judged by its free swing too: from the release, whose push no model has,
    # the free run misses by degrees; with the release excluded it follows the swing to the noise
    free = ev["free_run"]["passive"]
    assert set(free) == {"PT-left", "QT-left"} and set(free["PT-left"]) == {"1", "2"}
    assert all(v > 2.0 for trials in free.values() for v in trials.values()), free
    assert "free swing" in (tmp_path / "ev" / "report.md").read_text()
    released = write_interchange(Cohort(tuple(t.replace(exclude=t.time_s < 0.35) for t in trials)),
                                 tmp_path / "released")
    for file in released.glob("*-trial*.csv"):  # as a goniometer's log holds it: no stimulation column
        rows = [line.split(",") for line in file.read_text().splitlines()]
        j = rows[0].index("stimulation")
        file.write_text("".join(",".join(r[:j] + r[j + 1:]) + "\n" for r in rows))
    capsys.readouterr()
    assert main(["-q", "identify", str(released), "--out", str(tmp_path / "id2")]) == 0
    assert "have no column stimulation" in capsys.readouterr().err
    assert main(["-q", "evaluate", str(released), "--out", str(tmp_path / "ev2"), "--identified",
                 str(tmp_path / "id2")]) == 0
    free = json.loads((tmp_path / "ev2" / "summary.json").read_text())["free_run"]["passive"]
    assert all(v < 0.15 for trials in free.values() for v in trials.values()), free


def test_a_fit_marks_what_a_pendulum_leg_cannot_inform(tmp_path, capsys):
    """A leg without pulses: the fit says per leg that its delay and muscle are not estimates from
    its data, and the report marks them "prior only"; a leg with pulses is not marked."""
    stimulated, _ = simulate_cohort(legs=["TN-left"], minutes=0.5, seed=0, trials=[1])
    pendulum = _pendulum_trial("PT", 1, PASSIVE)
    data = write_interchange(Cohort(stimulated.trials + (pendulum,)), tmp_path / "data")
    capsys.readouterr()
    rc = main(["fit", str(data), "--model", "model1", "--chains", "1", "--warmup", "30", "--draws", "30",
               "--out", str(tmp_path / "fit")])
    assert rc in (0, 3)  # so short a fit may fail its checks; what matters here is what it says
    err = capsys.readouterr().err
    assert "PT-left: no pulses in the fitted trials: its delay and gain are the prior's" in err
    assert "TN-left: " not in " ".join(line for line in err.splitlines() if "prior's" in line)
    assert "PT-left: P(d) is the prior's" in err and "PT-left: P(d) mode" not in err and "TN-left: P(d) mode" in err
    s = json.loads((tmp_path / "fit" / "summary.json").read_text())
    assert s["uninformed"] == {"PT-left": {"pulses": 0, "params": ["gain"], "delay": True, "why": "no pulses"}}
    assert main(["-q", "report", str(tmp_path / "fit"), "--out", str(tmp_path / "report"), "--draws", "5",
                 "--start-stride", "50"]) == 0
    pages = {p.name: p.read_text() for p in (tmp_path / "report").glob("*.html")}
    pt = next(text for name, text in pages.items() if "PT" in name)
    tn = next(text for name, text in pages.items() if "TN" in name)
    assert 'class="prior-only"' in pt and "(prior only)" in pt
    assert 'class="prior-only"' not in tn


def test_fit_model_passive_recovers_the_pendulum_with_the_release_excluded(tmp_path, capsys):
    """``fit --model passive``: the pendulum alone, fitted hierarchically to pendulum tests whose
    release (the examiner's hand, 0.3 s) is excluded; no muscle, nothing marked prior only."""
    truths = {"PT": PASSIVE, "QT": {**PASSIVE, "damping": 0.9}}
    trials = []
    for i, (subject, passive) in enumerate(truths.items()):
        t = _pendulum_trial(subject, 1, passive, seed=i)
        trials.append(t.replace(exclude=t.time_s < 0.35))
    data = write_interchange(Cohort(tuple(trials)), tmp_path / "data")
    capsys.readouterr()
    rc = main(["-q", "fit", str(data), "--model", "passive", "--chains", "2", "--warmup", "400", "--draws", "400",
               "--out", str(tmp_path / "fit")])
    s = json.loads((tmp_path / "fit" / "summary.json").read_text())
    # one swing per leg leaves G', k1' and k2 on a ridge (one curve, see _assert_passive_recovered), which
    # 2 × 400 draws do not always explore to the checks' ESS; the curve and D' are what must be right
    assert rc in (0, 3) and s["diagnostics"]["rhat_max"] < 1.05 and s["diagnostics"]["divergences"] <= 5
    assert "uninformed" not in s and s["model"] == "passive"
    assert "delay_evidence_seconds" not in s  # no muscle: no delay to weigh
    assert s["likelihood"] == "angle" and s["legs"]["PT-left"]["params"]["sigma"]["units"] == "deg"
    # the angle's noise: the goniometer's 0.05° (the free runs follow the swing)
    assert all(0.03 < s["legs"][leg]["params"]["sigma"]["median"] < 0.08 for leg in s["legs"])
    # its report shows no delay: there is no muscle for one
    assert main(["-q", "report", str(tmp_path / "fit"), "--out", str(tmp_path / "report"), "--draws", "5",
                 "--start-stride", "50"]) == 0
    page = next((tmp_path / "report").glob("subject-*.html")).read_text()
    assert "No muscle, so no delay" in page and "Delay posterior" not in page
    assert "– (no muscle)" in (tmp_path / "report" / "index.html").read_text()
    for subject, passive in truths.items():
        params = s["legs"][f"{subject}-left"]["params"]
        assert set(params) == {"damping", "gravity", "k1", "k2", "sigma", "nu"}
        found = {k: params[k]["median"] for k in ("damping", "gravity", "k1", "k2")}
        _assert_passive_recovered(found, passive, trials[0].angle_deg)
        assert params["nu"]["median"] > 5  # the release, left in, would make the noise heavy-tailed
    # the angle cannot hold a delay effect: refused with the reason, before anything is written
    rc = main(["-q", "fit", str(data), "--model", "model3", "--add-effect", "angle_delay", "--likelihood", "angle",
               "--out", str(tmp_path / "no")])
    err = capsys.readouterr().err
    assert rc != 0 and "'angle_delay', a delay effect" in err and "--likelihood acceleration" in err
    assert not (tmp_path / "no").exists()


def _realistic(passive: dict, seed: int, gravity_angle: float = 0.0) -> Trial:
    """A pendulum test as a lab records one: angle only (no accelerometer), 0.2° of goniometer
    noise, the hand's push at the release marked excluded."""
    t = simulate_pendulum_test(passive, seed=seed, gravity_angle=gravity_angle, angle_noise_deg=0.2,
                               acceleration_noise_deg_s2=None)
    return t.replace(exclude=t.time_s < 0.35)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_angle_objective_follows_the_swing_as_the_truth_does(seed):
    """Output error on the free swing: its free run from the measured state is as close to the
    measured angle as the truth's, where the acceleration's fit (derived from a noisy angle) misses."""
    t = _realistic(PASSIVE, seed)
    by_angle = identify_cohort(Cohort((t,)), passive_objective="angle")["PT-left"]
    by_acc = identify_cohort(Cohort((t,)), passive_objective="acceleration")["PT-left"]
    assert by_angle.passive_objective == "angle" and by_acc.passive_objective == "acceleration"
    truth = free_run_error(passive_model(PASSIVE, DT), t)
    angle = free_run_error(by_angle.models["passive"], t)
    acc = free_run_error(by_acc.models["passive"], t)
    assert angle <= 1.05 * truth and angle < acc
    assert by_angle.passive_rms_residual == pytest.approx(angle, rel=0.1)  # its own measure, off the release
    _assert_passive_recovered(by_angle.passive, PASSIVE, t.angle_deg)
    # auto picks the angle for pendulum tests
    assert identify_cohort(Cohort((t,)))["PT-left"].passive_objective == "angle"


def test_a_knee_without_elasticity_keeps_its_terms_within_bounds():
    """A swing that holds no elasticity leaves k1'·(exp(-k2·φ) - 1) free to vanish in either factor:
    the free-run fit keeps k1' and k2 within its bounds, with finite standard errors, and the
    damping and gravity are still the swing's."""
    from quadshank.inference._identify import FREE_RUN_LOWER, FREE_RUN_UPPER_K2

    truth = {**PASSIVE, "k1": 1e-9}
    t = _realistic(truth, 4)
    r = identify_cohort(Cohort((t,)))["PT-left"]
    assert r.passive_objective == "angle"
    assert FREE_RUN_LOWER["k2"] * 0.999 <= r.passive["k2"] <= FREE_RUN_UPPER_K2 * 1.001
    assert r.passive["k1"] < 1e6
    assert all(np.isfinite(v) for v in r.passive_se.values()), r.passive_se
    assert r.passive["damping"] == pytest.approx(truth["damping"], rel=DAMPING_TOLERANCE)
    _assert_passive_recovered(r.passive, truth, t.angle_deg)


def test_a_shank_resting_off_the_vertical_is_identified_with_the_gravity_offset(tmp_path):
    t = _realistic(PASSIVE, 3, gravity_angle=15.0)
    data = write_interchange(Cohort((t,)), tmp_path / "data")
    assert main(["-q", "identify", str(data), "--gravity-offset", "--out", str(tmp_path / "id")]) == 0
    s = json.loads((tmp_path / "id" / "summary.json").read_text())["legs"]["PT-left"]
    assert s["passive_objective"] == "angle"
    found = s["passive"]
    # like G', k1 and k2, the gravity angle trades off against the elasticity; the shank's rest,
    # where the passive torques balance, is what the swing pins down
    from scipy.optimize import brentq

    def rest(p):
        return brentq(lambda phi: _curve(p, np.array([phi]))[0], -60.0, 60.0)

    assert 5.0 < found["gravity_angle"] < 25.0
    assert rest(found) == pytest.approx(rest({**PASSIVE, "gravity_angle": 15.0}), abs=0.5)
    _assert_passive_recovered(found, {**PASSIVE, "gravity_angle": 15.0}, t.angle_deg)
    with_offset = free_run_error(passive_model(found, DT), t)
    with pytest.warns(DataWarning, match="PT-left: the pendulum .* misses .* --gravity-offset"):  # and says so
        without = identify_cohort(Cohort((t,)))["PT-left"]
    assert with_offset < 0.3 and free_run_error(without.models["passive"], t) > 2 * with_offset
    # a free swing needs a pendulum test: refused for a stimulated leg, naming it
    stimulated, _ = simulate_cohort(legs=["TN-left"], minutes=0.5, seed=0, trials=[1])
    with pytest.raises(IdentificationError, match="TN-left: the passive objective 'angle'"):
        identify_cohort(stimulated, passive_objective="angle")


def test_free_runs_restart_after_an_excluded_stretch():
    t = simulate_pendulum_test(PASSIVE, hand=False, angle_noise_deg=0.0, acceleration_noise_deg_s2=0.0)
    exclude = np.zeros(t.n_samples, bool)
    exclude[300:320] = True
    spasm = t.angle_deg.copy()
    spasm[300:320] += 20.0  # whatever the excluded stretch holds
    # the velocity as measured: one derived from this angle would carry the spasm into the samples beside it
    spasmed = t.replace(exclude=exclude, angle_deg=spasm, velocity_deg_s=t.velocity_deg_s)
    runs = free_runs(passive_model(PASSIVE, DT), spasmed)
    assert [(a, x.size) for a, x in runs] == [(0, 300), (320, t.n_samples - 320)]
    assert free_run_error(passive_model(PASSIVE, DT), spasmed) < 0.05
    assert free_run_error(passive_model({**PASSIVE, "damping": 2.0}, DT), t) > 1.0


def _numpy_free_runs(p: dict, angle, velocity, starts, dt):
    """Free runs of eq. (8) without a muscle, NumPy RK4, each started at the measured state of one
    of ``starts`` and run until the next start (or the end)."""
    def f(a, v):
        return v, -p["damping"] * v - p["gravity"] * np.sin(np.deg2rad(a)) + p["k1"] * np.expm1(-p["k2"] * a)

    out = np.full(angle.size, np.nan)
    for s, e in zip(starts, list(starts[1:]) + [angle.size]):
        a, v = float(angle[s]), float(velocity[s])
        for k in range(s, e):
            out[k] = a
            k1a, k1v = f(a, v)
            k2a, k2v = f(a + dt / 2 * k1a, v + dt / 2 * k1v)
            k3a, k3v = f(a + dt / 2 * k2a, v + dt / 2 * k2v)
            k4a, k4v = f(a + dt * k3a, v + dt * k3v)
            a, v = a + dt / 6 * (k1a + 2 * k2a + 2 * k3a + k4a), v + dt / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
    return out


def test_the_angle_likelihood_is_student_t_about_free_runs_restarted_after_excluded_samples():
    """The fit's angle objective against a NumPy reference: each stretch between excluded samples
    runs freely from its first sample's measured state, and every later sample's measured angle is
    Student-t about it; its segments sum to the whole, and its gradient (forward sensitivities)
    is reverse mode's."""
    import jax
    import jax.numpy as jnp
    from scipy import stats

    from quadshank.inference._priors import build_model
    from quadshank.model import LikelihoodError, leg_loglik_by_delay, leg_pointwise, prepare
    from quadshank.model._likelihood import _free_run_plain, free_run_angles

    t = _realistic(PASSIVE, 0)
    gap = (t.time_s >= 3.0) & (t.time_s < 3.2)
    t = t.replace(exclude=t.exclude | gap)
    model = build_model("passive").with_params({k: np.float32(v) for k, v in PASSIVE.items()})
    data = prepare(Cohort((t,)), model)
    assert data.objective == "angle"
    x = {k: v[0] for k, v in data.leg_arrays().items()}
    noise = {"sigma": 0.3, "nu": 6.0}
    ll = np.asarray(leg_loglik_by_delay(model, noise, x, data.response_length, 0))
    assert ll.shape[0] == 11 and np.ptp(ll) == 0.0  # no muscle: every delay alike

    kept = ~t.exclude
    starts = [int(k) for k in np.flatnonzero(kept & ~np.concatenate([[False], kept[:-1]]))]
    assert len(starts) == 2  # after the release and after the gap
    runs = _numpy_free_runs(PASSIVE, t.angle_deg, t.velocity_deg_s, starts, DT)
    compared = kept.copy()
    compared[starts] = False  # a run's first sample is its measured start, not compared
    expected = stats.t.logpdf(t.angle_deg - runs, df=noise["nu"], scale=noise["sigma"])[compared].sum()
    assert ll[0, 0] == pytest.approx(expected, rel=2e-4)
    pointwise = np.asarray(leg_pointwise(model, noise, x, 4, data.response_length, data.n_segments))
    assert pointwise.sum() == pytest.approx(ll[0, 0], rel=1e-5)

    # the gradient, with a goniometer offset (a parameter the measured start depends on)
    m2 = build_model("passive", ["goniometer_offset"])
    x2 = {k: v[0] for k, v in prepare(Cohort((t,)), m2).leg_arrays().items()}
    values = {k: jnp.float32(v) for k, v in {**PASSIVE, "angle_offset": 1.5}.items()}

    def loss(v, run):
        pred = run(m2.with_params(v), x2["angle"], x2["velocity"], x2["reset"])
        return jnp.sum(jnp.where(x2["sample_mask"], (pred - x2["angle"]) ** 2, 0.0))

    fast = jax.grad(loss)(values, lambda m, a, v, r: free_run_angles(m, {"angle": a, "velocity": v, "reset": r}))
    slow = jax.grad(loss)(values, _free_run_plain)
    for k in values:
        assert float(fast[k]) == pytest.approx(float(slow[k]), rel=1e-3), k

    # the angle of a muscle holds no delay effect
    with pytest.raises(LikelihoodError, match="--likelihood acceleration"):
        prepare(Cohort((t,)), build_model("model3", ["angle_delay"]), objective="angle")
    assert prepare(Cohort((t,)), model, objective="acceleration").objective == "acceleration"


def test_the_residual_figures_of_a_pendulum_fit_leave_out_what_has_no_pulses(tmp_path):
    """A diagnosis of pendulum tests: the residuals have no interpulse interval or pulse count to
    bin against, and their figures are drawn from the features they have."""
    from quadshank.inference import laplace_fit
    from quadshank.inference._priors import build_model
    from quadshank.outputs import residual_figures
    from quadshank.outputs._loop import screen_residuals

    import warnings

    t = _realistic(PASSIVE, 0, gravity_angle=8.0)
    screen = laplace_fit(Cohort((t,)), build_model("passive"), n_draws=20)
    assert screen.data.objective == "angle"
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no division by a stimulation that is all zero, no empty legend
        paths, notes = residual_figures(screen_residuals(screen), tmp_path, "baseline", DT)
    assert paths and all(p.exists() for p in paths) and "PT-left" in notes
    assert not any(p.name.startswith("twitch_average") for p in paths)  # no pulse to average over


def test_discover_starts_from_the_pendulum_alone_on_the_command_line(tmp_path):
    """`discover --model passive`: the loop on pendulum tests finds the rest off the vertical, and
    names the muscle's candidates as not applicable."""
    data = write_interchange(Cohort((_realistic(PASSIVE, 0, gravity_angle=8.0),)), tmp_path / "data")
    out = tmp_path / "loop"
    assert main(["-q", "discover", str(data), "--model", "passive", "--max-rounds", "1",
                 "--effects", "gravity_offset,goniometer_offset,potentiation", "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["rounds"][0]["model"] == "passive" and s["added"][0] in ("gravity_offset", "goniometer_offset")
    r1 = json.loads((out / "round-1" / "summary.json").read_text())
    assert [x["effect"] for x in r1["not_applicable"]] == ["potentiation"]


def test_the_loop_on_pendulum_tests_lists_the_muscle_candidates_as_not_applicable(tmp_path):
    """Candidates that cannot change a pendulum's likelihood are named in the report, not ranked."""
    from quadshank.loop import rank_effects
    from quadshank.loop._diagnose import Diagnosis, not_applicable, verdict_sentence
    from quadshank.model import paper_model
    from quadshank.outputs._loop import ranking_markdown

    import warnings

    t = _realistic(PASSIVE, 0, gravity_angle=8.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # a screen that fails warns, and is left out
        ranking = rank_effects(Cohort((t,)), "passive", effects=["torque_angle_peak", "accel_resonance", "goniometer_offset"],
                               n_draws=60, n_j_draws=10, start_stride=20, n_starts=0)  # 20 draws: every k > 0.7
    assert [r["effect"] for r in ranking.rows] == ["goniometer_offset"] and ranking.verdict == "goniometer_offset"
    assert set(ranking.not_applicable) == {"torque_angle_peak", "accel_resonance"}
    d = Diagnosis(**ranking.to_json(), sentence=verdict_sentence(ranking), trials=[1])
    md = ranking_markdown(d)
    assert "do not apply to these data" in md and "**torque_angle_peak**: acts through the muscle" in md
    # a diagnosis of a pendulum fit made on the acceleration screens by the acceleration: the
    # accelerometer's response too, where the test was recorded with an accelerometer
    ranking = rank_effects(Cohort((t.replace(acceleration_measured=True),)), "passive",
                           effects=["torque_angle_peak", "accel_resonance"],
                           n_draws=20, n_j_draws=10, start_stride=20, n_starts=0, objective="acceleration")
    assert ranking.base.data.objective == "acceleration" and list(ranking.not_applicable) == ["torque_angle_peak"]
    # and without one (this test is angle only), not: it would fit the derivation's smoothing
    assert "derived from the angle" in not_applicable(paper_model("passive"), Cohort((t,)), ["accel_resonance"],
                                                      [t.key], (1,), "acceleration")["accel_resonance"]


def test_a_gravity_angle_far_from_the_zero_is_named(monkeypatch):
    """A gravity offset identified far from the angle's zero (a rest the tissues hold, traded
    between gravity and the elasticity) draws a warning naming the leg and the angle; one near
    the zero draws none."""
    import warnings

    from quadshank.inference import _identify

    t = _realistic(PASSIVE, 3, gravity_angle=15.0)
    for angle, named in ((121.0, True), (15.0, False)):
        monkeypatch.setattr(_identify, "_passive_free_run",
                            lambda trials, gravity_offset=False, angle=angle: ({**PASSIVE, "gravity_angle": angle}, 0.1, 900, {}))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            identify_cohort(Cohort((t,)), gravity_offset=True)
        said = [str(w.message) for w in caught if "has gravity acting about" in str(w.message)]
        if named:
            assert len(said) == 1 and said[0].startswith(f"PT-left: the identified pendulum has gravity acting about {angle:.0f}°")
        else:
            assert said == []


def test_pulses_whose_twitch_is_excluded_inform_nothing():
    """A leg whose pulses all fall where their twitch is excluded is as uninformed as one without
    pulses, and says why; excluding only the pulses' own samples leaves their twitches compared."""
    from quadshank.commands.fit import uninformed_legs
    from quadshank.inference import build_model
    from quadshank.model._likelihood import twitch_window

    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.5, seed=0, trials=[1])
    t = cohort.trials[0]
    pulses = np.flatnonzero(t.stimulation > 0)
    hidden = np.zeros(t.n_samples, bool)
    for k in pulses:
        hidden[k : k + twitch_window(t.sampling_period_s)] = True
    model = build_model("model1")
    assert uninformed_legs(model, cohort) == {}
    (got,) = uninformed_legs(model, Cohort((t.replace(exclude=hidden),))).values()
    assert got["pulses"] == 0 and got["why"] == f"no pulses whose twitch is compared ({pulses.size} with their twitch excluded)"
    only_pulses = np.zeros(t.n_samples, bool)
    only_pulses[pulses] = True
    assert uninformed_legs(model, Cohort((t.replace(exclude=only_pulses),))) == {}


def _recorded_from_before_the_release(t: Trial, held_s: float = 2.0, seed: int = 5) -> Trial:
    """``t`` (a release from 60° at rest) with what a lab's recording holds before it: a second at
    rest, a second's lift to 60° by hand and ``held_s`` held there (sensor noise as ``t``'s)."""
    rng = np.random.default_rng(seed)
    n_lift, n_hold = int(1.0 / DT), int(held_s / DT)
    lift = 60.0 * (1 - np.cos(np.linspace(0, np.pi, n_lift))) / 2
    pre = np.concatenate([np.zeros(int(1.0 / DT)), lift, np.full(n_hold, 60.0)])
    acc = np.gradient(np.gradient(pre, DT), DT)
    return Trial.from_signals(t.subject, t.leg, t.trial, DT, np.concatenate([pre + rng.normal(0, 0.05, pre.size),
                                                                            t.angle_deg]),
                              np.concatenate([acc + rng.normal(0, 30.0, pre.size), t.acceleration_deg_s2]),
                              np.zeros(pre.size + t.n_samples))


def test_a_pendulum_test_recorded_from_before_its_release_is_read_from_the_release(tmp_path):
    """A lab's pendulum test often starts before the release: the shank at rest, lifted by hand and
    held.  No pendulum model holds the lift and the hold (the free runs start at rest and never
    rise): the reader finds the release, excludes the lift, the hold and the release's 350 ms (as
    at a recording that starts there), and says so; a trial built in Python is warned of, and
    check's verdict says its values would come out wrong."""
    from quadshank.commands import run_check
    from quadshank.data import load_cohort
    from quadshank.data._interchange import pendulum_release

    swing = simulate_pendulum_test(PASSIVE, hand=False, seed=3)
    held = _recorded_from_before_the_release(swing)
    start = held.n_samples - swing.n_samples  # the release
    assert abs(pendulum_release(held) - start) <= 6  # the shank leaves the hold's band within 60 ms
    # as built: warned of, and the free swing is not found
    with pytest.warns(DataWarning, match=r"lifted from time_s = 1\.\d+ and held at 60\.0° until time_s = 4\.0\d and then "
                                         r"swings: a pendulum test recorded from before its release"):
        uses = run_check(Cohort((held,))).legs["PT-left"]["identify"]
    assert "holds the lift and the hold before the pendulum's release" in uses
    with pytest.warns(DataWarning):
        wrong = identify_cohort(Cohort((held,)))["PT-left"].passive
    assert not wrong["gravity"] == pytest.approx(PASSIVE["gravity"], rel=0.5)
    # read from a folder: excluded up to 350 ms after the release, and the pendulum found
    write_interchange(Cohort((held,)), tmp_path / "pt")
    with pytest.warns(DataWarning, match=r"PT-left trial 1\): a pendulum test recorded from before its release: the "
                                         r"shank is lifted from time_s = 1\.\d+ and held at 60\.0° until time_s = 4\.0\d, "
                                         r".* 350 ms after each release"):
        read = load_cohort(tmp_path / "pt")
    t = read.trials[0]
    # the second at rest before the lift is kept (a free run from rest stays there); from the lift on to
    # 350 ms after the release is excluded
    assert not t.exclude[:100].any() and t.exclude[120:start + 35].all() and not t.exclude[start + 45:].any()
    r = identify_cohort(read)["PT-left"]
    _assert_passive_recovered(r.passive, PASSIVE, swing.angle_deg)
    assert run_check(read).legs["PT-left"]["identify"] == "the passive system only (no pulses: a pendulum test)"


def test_a_free_swing_is_not_taken_for_a_hold():
    """Pendulum tests released at the recording's start, from 20-80° or from flexion, with and
    without the hand's push, at 5-20 ms, with and without an accelerometer, and stimulated trials:
    no release is found before their swing."""
    from quadshank.data._interchange import pendulum_release

    for angle0 in (20.0, 60.0, 80.0, -30.0):
        for hand in (True, False):
            for dt, acc in ((0.01, 30.0), (0.005, None), (0.02, 30.0)):
                t = simulate_pendulum_test(PASSIVE, angle0=angle0, hand=hand, sampling_period_s=dt,
                                           acceleration_noise_deg_s2=acc, seed=1)
                assert pendulum_release(t) == 0, (angle0, hand, dt)
    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.5, seed=0, trials=[1])
    assert pendulum_release(cohort.trials[0]) == 0
    # lifted from rest and let go at once (held a tenth of a second): the rise from a still rest is a
    # lift, released at its top
    swing = simulate_pendulum_test(PASSIVE, hand=False, seed=3)
    held = _recorded_from_before_the_release(swing, held_s=0.1)
    assert abs(pendulum_release(held) - (held.n_samples - swing.n_samples)) <= 6


def test_a_glitch_in_a_pendulum_test_does_not_bend_the_swing(tmp_path):
    """A one-sample spike of 25° (2500 deg/s away and back) had taken the free swing's G' to 0.  Read
    from a folder it is excluded as a glitch; built in Python and left in, the free-run fit leaves
    it out and says so; excluded by hand, the velocity a free run starts from is derived across it
    by a straight line (derived through it, D' had come out 65 % too large)."""
    from quadshank.data import load_cohort

    t = simulate_pendulum_test(PASSIVE, seed=0)
    spiked = t.angle_deg.copy()
    spiked[300] += 25.0
    left_in = t.replace(angle_deg=spiked)
    with pytest.warns(DataWarning, match=r"PT-left trial 1 .*: 1 of the \d+ samples of the free swing left out of "
                                         r"the passive fit: .* \(the largest at t = 3\.00 s\)\. A sensor's spike\?"):
        r = identify_cohort(Cohort((left_in,)))["PT-left"]
    _assert_passive_recovered(r.passive, PASSIVE, t.angle_deg)
    exclude = np.zeros(t.n_samples, bool)
    exclude[300] = True
    by_hand = Trial.from_signals("PT", "left", 1, DT, spiked, t.acceleration_deg_s2, t.stimulation, exclude=exclude)
    assert abs(by_hand.velocity_deg_s[301] - t.velocity_deg_s[301]) < 5.0  # derived across the glitch
    _assert_passive_recovered(identify_cohort(Cohort((by_hand,)))["PT-left"].passive, PASSIVE, t.angle_deg)
    write_interchange(Cohort((left_in,)), tmp_path / "pt")
    with pytest.warns(DataWarning, match=r"angle_deg jumps by \+2\d\.\d+° and back at time_s = 3\.0, .*a sensor "
                                         r"glitch, excluded"):
        read = load_cohort(tmp_path / "pt")
    assert read.trials[0].exclude[300] and read.trials[0].exclude.sum() == 1
    _assert_passive_recovered(identify_cohort(read)["PT-left"].passive, PASSIVE, t.angle_deg)


def test_two_drops_and_a_trembling_hold_in_one_recording_are_each_found(tmp_path):
    """Two lifts in one file, the second held with a tremor of ±1° at 5 Hz: each lift and hold is
    found and excluded (the free swing between them kept), and the pendulum comes out right."""
    from quadshank.data import load_cohort
    from quadshank.data._interchange import pendulum_lifts

    first = _recorded_from_before_the_release(simulate_pendulum_test(PASSIVE, hand=False, seed=3, seconds=6.0))
    rng = np.random.default_rng(7)
    lift = 50.0 * (1 - np.cos(np.linspace(0, np.pi, 100))) / 2
    hold = 50.0 + np.sin(2 * np.pi * 5.0 * np.arange(150) * DT)
    second = simulate_pendulum_test(PASSIVE, hand=False, seed=4, seconds=6.0, angle0=50.0)
    pre = np.concatenate([lift, hold])
    acc = np.gradient(np.gradient(pre, DT), DT) + rng.normal(0, 30.0, pre.size)
    angle = np.concatenate([first.angle_deg, pre + rng.normal(0, 0.05, pre.size), second.angle_deg])
    both = Trial.from_signals("PT", "left", 1, DT, angle,
                              np.concatenate([first.acceleration_deg_s2, acc, second.acceleration_deg_s2]),
                              np.zeros(angle.size))
    lifts = pendulum_lifts(both)
    releases = [first.n_samples - 600, first.n_samples + pre.size]  # the true releases
    assert len(lifts) == 2 and all(abs(b - r) <= 8 for (_, b), r in zip(lifts, releases)), lifts
    assert lifts[1][0] >= first.n_samples - 10  # the first drop's free swing before the second lift is kept
    write_interchange(Cohort((both,)), tmp_path / "pt")
    with pytest.warns(DataWarning, match=r"held at 60\.0° until time_s = 4\.0\d; then lifted from .* held at "
                                         r"5\d\.\d° until .* the lifts, the holds and 350 ms after each release"):
        read = load_cohort(tmp_path / "pt")
    _assert_passive_recovered(identify_cohort(read)["PT-left"].passive, PASSIVE, first.angle_deg)


def test_a_plan_starts_by_default_where_each_draw_comes_to_rest():
    """A shank resting off the vertical (gravity about -20°, or about -12° for another draw) starts a
    plan at its own rest, not at angle 0: without pulses its prediction stays there."""
    import jax
    import jax.numpy as jnp

    from quadshank.evaluation import plan_predictions, rest_states

    draws = [passive_model({**PASSIVE, "gravity_angle": g}, DT) for g in (-20.0, -12.0)]
    models = jax.tree.map(lambda *leaves: jnp.stack([jnp.asarray(x) for x in leaves]), *draws)
    angle, velocity = rest_states(models)
    # where gravity balances the elasticity: -G' sin(φ - g) + k1' (exp(-k2 φ) - 1) = 0
    for g, a in zip((-20.0, -12.0), angle):
        assert -PASSIVE["gravity"] * np.sin(np.deg2rad(a - g)) + PASSIVE["k1"] * np.expm1(-PASSIVE["k2"] * a) == (
            pytest.approx(0.0, abs=0.05))
        assert g < a < 0.0
    assert np.all(np.abs(velocity) < 0.01)
    still = plan_predictions(models, np.zeros(200), None)
    np.testing.assert_allclose(still, np.repeat(angle[:, None], 200, axis=1), atol=0.01)
    from_zero = plan_predictions(models, np.zeros(200), 0.0)
    assert np.all(np.abs(from_zero[:, 0]) < 1e-6) and np.all(np.ptp(from_zero, axis=1) > 5.0)
