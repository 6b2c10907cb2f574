"""Classical identification (eqs. 8-11) against known truths."""

import re
import warnings

import jax.numpy as jnp
import numpy as np
import pytest

from quadshank import Cohort, Trial
from quadshank.inference._identify import (
    IdentificationError,
    fit_darma,
    identify_cohort,
    identify_leg,
    identify_passive,
    isolated_twitches,
)
from quadshank.data._cohort import quiet_mask
from quadshank.model._model import paper_model, passive_effects, simulate_angles
from quadshank.data._paper import LEGS
from quadshank.evaluation._classical_recovery import DELAY_TOLERANCE, TOLERANCES, recovery
from quadshank.data import DataWarning, derive_acceleration, simulate_pendulum_test
from quadshank.data._simulate import simulate_cohort


def test_isolated_twitches_and_quiet_mask():
    u = np.zeros(400)
    pulses = [30, 100, 110, 200, 290, 330]
    u[pulses] = 1.0
    # 30: 70 quiet after -> isolated; 100/110 too close; 200: next at 290 (> 50) and prev 110 (> 25) -> isolated;
    # 290: next at 330 (40 < 50) -> not; 330: 40 after the previous (> 25), 69 left (> 50) -> isolated
    assert isolated_twitches(u).tolist() == [30, 200, 330]
    q = quiet_mask(u, quiet=35)
    assert not q[:35].any()
    assert not q[30:66].any() and q[66:100].all() and not q[100].any()


def test_isolated_twitches_skip_excluded_epochs():
    u = np.zeros(400)
    u[[30, 200, 330]] = 1.0
    exclude = np.zeros(400, bool)
    exclude[240] = True  # within 200's 50 samples after
    assert isolated_twitches(u, exclude=exclude).tolist() == [30, 330]
    exclude[:] = False
    exclude[10] = True  # within 30's 25 samples before
    assert isolated_twitches(u, exclude=exclude).tolist() == [200, 330]


def test_identification_leaves_excluded_samples_out():
    """An artefact over a stretch of twitches and quiet samples, once excluded, moves nothing."""
    cohort, _ = simulate_cohort(legs=("OT-left",), minutes=3.0, seed=5, trials=(1,))
    clean = cohort.get("OT-left", 1)
    exclude = np.zeros(clean.n_samples, bool)
    exclude[3000:6000] = True
    acc = clean.acceleration_deg_s2.copy()
    acc[3000:6000] += 3000.0 * np.sin(np.arange(3000) / 7.0)
    r_clean = identify_leg(clean.replace(exclude=exclude))
    r_dirty = identify_leg(clean.replace(acceleration_deg_s2=acc, exclude=exclude))
    assert r_dirty.pulses.tolist() == r_clean.pulses.tolist() and not ((r_clean.pulses > 2975) & (r_clean.pulses < 6000)).any()
    assert r_dirty.n_quiet == r_clean.n_quiet
    for name in ("model1", "model3"):
        a, b = r_clean.models[name].flat_params(), r_dirty.models[name].flat_params()
        assert all(float(a[k]) == pytest.approx(float(b[k]), rel=1e-4, abs=1e-9) for k in a), name
    # left in, the artefact would have moved the passive estimates
    moved = identify_leg(clean.replace(acceleration_deg_s2=acc))
    assert abs(moved.passive["gravity"] - r_clean.passive["gravity"]) > 0.01 * r_clean.passive["gravity"] or \
        abs(moved.passive["damping"] - r_clean.passive["damping"]) > 0.05 * r_clean.passive["damping"]


def test_fit_darma_recovers_exact_coefficients_and_the_delay():
    rng = np.random.default_rng(3)
    n = 6000
    u = np.zeros(n)
    t = 40
    while t < n - 80:
        u[t] = 1.0
        t += int(rng.integers(80, 140))
    a, b, d = np.array([-1.5, 0.6]), np.array([400.0, 550.0]), 3
    y = np.zeros(n)
    for k in range(2, n):
        y[k] = -a[0] * y[k - 1] - a[1] * y[k - 2] + b[0] * u[k - 1 - d] + b[1] * u[k - 2 - d]
    y += rng.normal(0, 5.0, n)
    pulses = isolated_twitches(u)
    res = [fit_darma(y, u, pulses, dd)[3] for dd in range(11)]
    assert int(np.argmin(res)) == d
    a_hat, b_hat, c_hat, _ = fit_darma(y, u, pulses, d)
    np.testing.assert_allclose(a_hat, a, atol=0.02)
    np.testing.assert_allclose(b_hat, b, rtol=0.03)
    # output noise makes the equation error an MA process (v_k + a1 v_{k-1} + a2 v_{k-2}): the whitening
    # filter picks that colouring up, which is why eq. (10) carries it
    assert c_hat[0] < -0.5


def test_passive_identification_on_free_swings():
    truth = dict(damping=1.2, gravity=1750.0, k1=30.0, k2=0.05)
    m = paper_model(1, passive_effects(**truth))
    rng = np.random.default_rng(0)
    trials = []
    for i, (a0, v0) in enumerate([(50.0, 0.0), (-40.0, 50.0), (20.0, -300.0)]):
        a, v, _ = simulate_angles(m, jnp.zeros(1500), a0, v0)
        a = np.asarray(a, float)
        acc = np.gradient(np.asarray(v, float), 0.01)
        trials.append(Trial.from_signals("X", "left", i + 1, 0.01, a + rng.normal(0, 0.05, a.size),
                                         acc + rng.normal(0, 20, a.size), np.zeros(a.size)))
    est, rms, n = identify_passive(trials)
    assert n == 3 * (1500 - 35)
    for k, tol in (("damping", 0.1), ("gravity", 0.02), ("k1", 0.5), ("k2", 0.3)):
        assert est[k] == pytest.approx(truth[k], rel=tol), k
    assert rms < 60


def test_model1_gain_is_eq9_and_errors_are_explained():
    cohort, truth = simulate_cohort(legs=("OT-left",), minutes=3.0, seed=5, trials=(1,))
    trial = cohort.get("OT-left", 1)
    r = identify_leg(trial)
    mi = trial.acceleration_deg_s2 + r.passive["damping"] * trial.velocity_deg_s
    mi += r.passive["gravity"] * np.sin(np.deg2rad(trial.angle_deg))
    mi -= r.passive["k1"] * np.expm1(-r.passive["k2"] * trial.angle_deg)
    epochs = r.pulses[:, None] + np.arange(25)
    g1 = mi[epochs].sum() / trial.stimulation[r.pulses].sum()
    assert r.models["model1"].flat_params()["gain"] == pytest.approx(g1, rel=1e-6)  # M/I goes through float32 JAX
    # Table IV: model 3 explains the integrated twitches better than model 1
    assert r.rms_error_pct["model3"] < r.rms_error_pct["model1"]


def test_identification_refuses_data_without_isolated_twitches():
    n = 3000
    u = np.zeros(n)
    u[::5] = 1.0  # a fused train: no isolated twitch anywhere
    trial = Trial.from_signals("X", "left", 1, 0.01, np.zeros(n), np.zeros(n), u)
    with pytest.raises(IdentificationError, match="isolated twitches"):
        identify_leg(trial, passive=dict(damping=1.0, gravity=1800.0, k1=20.0, k2=0.05))


def test_recovery_of_the_simulated_cohort():
    """Every leg of the paper's cohort: the delay within one sample, parameters within TOLERANCES."""
    cohort, truth = simulate_cohort(legs=LEGS, minutes=5.0, seed=11, trials=(1,))
    ident = {leg: identify_leg(cohort.get(leg, 1)) for leg in LEGS}
    rec = recovery(ident, truth)
    failures = [
        f"{leg} {name}: {v['estimate']:.4g} vs {v['truth']:.4g}"
        for leg, params in rec.items()
        for name, v in params.items()
        if not v["ok"]
    ]
    assert not failures, failures
    for leg in LEGS:
        assert abs(ident[leg].delay - truth["legs"][leg]["active"]["delay_samples"]) <= DELAY_TOLERANCE
    # and the tolerances are not vacuous: a wrong gain would fail them
    assert TOLERANCES["G2"] < 0.5


def test_twitches_that_flex_the_knee_ask_about_the_sign():
    """An angle (and acceleration) recorded with the opposite sign makes the twitches flex the
    knee; the identification names that instead of failing inside the optimiser."""
    cohort, _ = simulate_cohort(legs=("OT-left",), minutes=1.5, seed=5, trials=(1,))
    t = cohort.get("OT-left", 1)
    flipped = Trial.from_signals("OT", "left", 1, t.sampling_period_s, -t.angle_deg, -t.acceleration_deg_s2,
                                 t.stimulation, time_s=t.time_s)
    identify_leg(t)  # the same data the right way round identify
    with pytest.raises(IdentificationError, match="OT-left trial 1: .*not a positive twitch.*sign of angle_deg"):
        identify_leg(flipped)


def test_an_angle_that_does_not_move_is_named():
    n = 1000
    trial = Trial.from_signals("X", "left", 1, 0.01, np.full(n, 3.0), np.zeros(n), np.zeros(n))
    with pytest.raises(IdentificationError, match="X-left trial 1: the angle does not move .*3.0° throughout"):
        identify_passive([trial])


def test_a_trial_without_pulses_is_named_as_taken_for_a_pendulum_test():
    """A short pulse-free trial beside a stimulated one is a pendulum test to the
    identification; where it cannot serve as one, the message says why it was asked."""
    cohort, _ = simulate_cohort(legs=("OT-left",), minutes=1.5, seed=5, trials=(1,))
    t = cohort.get("OT-left", 1)
    fragment = Trial.from_signals("OT", "left", 2, t.sampling_period_s, t.angle_deg[:5], t.acceleration_deg_s2[:5],
                                  np.zeros(5), time_s=t.time_s[:5])
    with pytest.raises(IdentificationError, match="OT-left: its trial 2 holds no pulse and so is taken as a pendulum test, the source of its passive"):
        identify_cohort(Cohort((t, fragment)))


def test_trials_without_pulses_that_are_no_pendulum_tests_are_named():
    """A stimulated trial with its pulses missing is taken for a pendulum test; the free runs of
    the pendulum identified from it miss its swing by about its whole spread, which is named,
    alone (its standard errors measure that misfit, not the data's information).  A real
    pendulum test (released from extension, noise, the examiner's hand) is not."""
    cohort, _ = simulate_cohort(legs=("OT-left",), minutes=1.0, seed=5, trials=(1,))
    t = cohort.get("OT-left", 1)
    no_pulses = t.replace(stimulation=np.zeros(t.n_samples))
    _, said = _identified_with_warnings(Cohort((no_pulses,)))
    # a burst's rise and plateau may read as a lift and a hold by hand, which the reader names besides
    said = [w for w in said if "recorded from before its release" not in w]
    assert len(said) == 1, said
    assert re.match(r"OT-left: the pendulum .* misses their free swings by .* are they pendulum tests", said[0])
    pendulum = simulate_pendulum_test({"damping": 1.3, "gravity": 1950.0, "k1": 30.0, "k2": 0.05}, subject="PT")
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)
        identify_cohort(Cohort((pendulum,)))


def test_too_few_quiet_samples_from_an_angle_zeroed_elsewhere_say_so():
    cohort, _ = simulate_cohort(legs=("OT-left",), minutes=1.0, seed=5, trials=(1,))
    t = cohort.get("OT-left", 1)
    with pytest.raises(IdentificationError, match=r"only \d+ quiet samples.*Most quiet samples lie above 60°.*zero"):
        identify_leg(t.replace(angle_deg=t.angle_deg + 150.0))


def test_signals_that_are_not_finite_are_refused_not_fed_to_least_squares():
    """A sample beyond what a float holds (an overflow that reached the trial) is refused naming the
    leg, trial, signal and sample, as a file's would be; least squares on it would not return."""
    from quadshank.data import Cohort, InterchangeError, simulate_cohort
    from quadshank.inference._identify import identify_cohort

    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.5, seed=0, trials=[1])
    t = cohort.trials[0]
    acc = t.acceleration_deg_s2.copy()
    at = np.flatnonzero(t.stimulation > 0)[3] + 5
    acc[at] = np.inf
    with pytest.raises(InterchangeError, match=rf"TN-left trial 1, column 'acceleration_deg_s2', index {at}: "
                                               "non-finite value inf"):
        identify_cohort(Cohort((t.replace(acceleration_deg_s2=acc),)))


def test_a_delay_at_the_longest_considered_is_warned_of_and_kept_in_the_report(tmp_path):
    """Pulses logged 7 samples before the stimulator fired put model 2's best delay beyond the scan: the
    delay at its edge is warned of, and identify's summary and report keep what it warned of."""
    import warnings

    from quadshank.commands.identify import run_identify
    from quadshank.data import Cohort, simulate_cohort

    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=1.0, seed=1, trials=[1])
    t = cohort.trials[0]
    for shift, edge in ((7, True), (3, False)):
        early = Cohort((t.replace(stimulation=np.roll(t.stimulation, -shift)),))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = run_identify(early, tmp_path / f"early{shift}")
        said = [w for w in result.warnings if "the delay comes out at 10 samples (100 ms), the longest considered" in w]
        assert (result.legs["TN-left"]["delay_samples"] == 10) == edge and bool(said) == edge, result.warnings
        assert all(f"- {w}" in (tmp_path / f"early{shift}" / "report.md").read_text() for w in result.warnings)


def test_a_free_run_that_diverges_from_its_start_is_named_with_what_to_do():
    """A start whose free run overflows (a stiff knee on 60° swings) is an identification error naming
    the trial and the way out, not scipy's "Residuals are not finite"."""
    from quadshank.inference._identify import IdentificationError, _passive_free_run

    trial = simulate_pendulum_test({"damping": 2.2, "gravity": 1800.0, "k1": 1.0, "k2": 0.01}, angle0=60.0, seed=2)
    with pytest.raises(IdentificationError, match=r"PT-left trial 1 \(simulated pendulum test\): the free run of the passive system diverged "
                                                  r"from every start .*--passive-objective acceleration"):
        _passive_free_run([trial], start={"damping": 50.0, "gravity": 1800.0, "k1": 1e6, "k2": 0.1})


def test_an_angle_zeroed_elsewhere_is_named_by_its_missing_gravity():
    """A constant added to every angle (a goniometer zeroed 30° away from the rest) leaves the
    passive fit no gravity about angle 0: named with the leg, the angle the quiet samples swing about
    and G'; angles in radians, with the span that gives them away; the recording as it is draws nothing."""
    import warnings

    from quadshank.data import Cohort, DataWarning, simulate_cohort
    from quadshank.inference._identify import identify_cohort

    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.5, seed=0, trials=[1])
    t = cohort.trials[0]

    def said(trial):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            identify_cohort(Cohort((trial,)))
        return [str(w.message) for w in caught if issubclass(w.category, DataWarning) and "next to no gravity" in str(w.message)]

    assert said(t) == []
    # 30° off: the quiet samples name the angle they swing about, and G' near 0 with it
    with pytest.warns(DataWarning, match=r"TN-left: the quiet samples of trial 1 swing about \+[34]\d\.\d° .*G' [0-9.]+e-\d\d"):
        identify_cohort(Cohort((t.replace(angle_deg=t.angle_deg + 30.0),)))
    # the angle and the accelerometer both in radians: the small span is named as well, on every leg and length
    for leg, minutes, seed in (("TN-left", 0.5, 0), ("JM-left", 2.0, 1), ("OT-left", 2.0, 2), ("TN-right", 0.5, 3)):
        (r,) = simulate_cohort(legs=[leg], minutes=minutes, seed=seed, trials=[1])[0].trials
        (found,) = said(r.replace(angle_deg=np.deg2rad(r.angle_deg), acceleration_deg_s2=np.deg2rad(r.acceleration_deg_s2),
                                  velocity_deg_s=np.deg2rad(r.velocity_deg_s)))
        assert "in radians: the angle spans only" in found, (leg, found)


def test_an_angle_zeroed_a_degree_or_more_off_the_rest_is_named_by_the_quiet_samples():
    """Between pulses eq. (8) about an angle a degree or more from 0 fits the quiet samples far better
    than about 0 (an angle zeroed off the hanging shank, which biases every value): a warning names
    the leg, the angle and the biased G' and k1'; the recording as it is, and half a degree off, draw none."""
    import warnings

    from quadshank.data import Cohort, DataWarning, simulate_cohort
    from quadshank.inference._identify import identify_cohort

    cohort, _ = simulate_cohort(legs=["JM-left"], minutes=2, seed=3, trials=[1])
    t = cohort.trials[0]

    def said(offset):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            identify_cohort(Cohort((t.replace(angle_deg=t.angle_deg + offset),)))
        return [str(w.message) for w in caught if issubclass(w.category, DataWarning)
                and "rather than about the angle's zero" in str(w.message)]

    assert said(0.0) == [] and said(0.3) == []
    for offset in (-5.0, 1.5):
        (found,) = said(offset)
        about = float(re.match(r"JM-left: the quiet samples of trial 1 swing about ([-+0-9.]+)°", found).group(1))
        assert abs(about - offset) < 0.4, found
        assert "goniometer_offset" in found and "k1'" in found
        assert "does the accelerometer read a constant offset" in found  # measured: a sensor's offset looks alike
    derived = Trial.from_signals("JM", "left", 1, t.sampling_period_s, t.angle_deg + 3.0, None, t.stimulation)
    with warnings.catch_warnings(record=True) as caught:  # no accelerometer to doubt
        warnings.simplefilter("always")
        identify_cohort(Cohort((derived,)))
    (found,) = [str(w.message) for w in caught if "rather than about the angle's zero" in str(w.message)]
    assert "accelerometer" not in found


def test_the_gravity_offset_is_identified_from_the_quiet_samples_of_a_stimulated_trial():
    """`--gravity-offset` on a stimulated leg fits the quiet samples with gravity about a free angle:
    an angle zeroed 4° off the hanging shank gives that angle and the passive system as on the
    recording zeroed right, where about 0 k1' collapses; no warning of the offset is left to give."""
    from quadshank.data import Cohort, DataWarning, simulate_cohort
    from quadshank.data._simulate import PASSIVE_TRUTH
    from quadshank.inference._identify import identify_cohort

    cohort, _ = simulate_cohort(legs=["JM-left"], minutes=2, seed=3, trials=[1])
    shifted = Cohort(tuple(t.replace(angle_deg=t.angle_deg - 4.0) for t in cohort.trials))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        found = identify_cohort(shifted, gravity_offset=True)["JM-left"]
    assert not [w for w in caught if issubclass(w.category, DataWarning) and "rather than about" in str(w.message)]
    truth = PASSIVE_TRUTH["JM-left"]
    assert found.passive["gravity_angle"] == pytest.approx(-4.0, abs=0.3)
    assert found.passive["damping"] == pytest.approx(truth["damping"], rel=0.05)
    assert found.passive["gravity"] == pytest.approx(truth["gravity"], rel=0.03)
    assert found.passive["k1"] == pytest.approx(truth["k1"], rel=0.2)
    with pytest.warns(DataWarning, match="rather than about the angle's zero"):
        about_zero = identify_cohort(shifted)["JM-left"]
    assert about_zero.passive["k1"] < 0.1 * truth["k1"]


def test_a_marker_on_excluded_samples_leaves_the_identification_as_it_was():
    """A logger's missing-data marker set to be excluded, as the warnings advise, changes nothing
    the classical identification finds (its equivalent acceleration there is no number, and is not used)."""
    from quadshank.data import Cohort, simulate_cohort
    from quadshank.inference._identify import identify_cohort

    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.5, seed=0, trials=[1])
    t = cohort.trials[0]
    angle, exclude = t.angle_deg.copy(), np.zeros(t.n_samples, bool)
    angle[1000:1020], exclude[1000:1020] = -9999.0, True
    clean = identify_cohort(cohort)["TN-left"]
    marked = identify_cohort(Cohort((t.replace(angle_deg=angle, exclude=exclude),)))["TN-left"]
    assert marked.delay == clean.delay
    for name in ("damping", "gravity"):
        assert marked.passive[name] == pytest.approx(clean.passive[name], rel=0.02), name


def _identified_with_warnings(cohort, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ident = identify_cohort(cohort, **kw)
    return ident, [str(w.message) for w in caught if issubclass(w.category, DataWarning)]


UNSEPARATED = "do not tell the pendulum's gravity from the knee's elasticity"


def test_gravity_and_elasticity_that_small_swings_cannot_separate_are_named():
    """Within ±8° sin φ and exp(-k2·φ) - 1 are both linear in φ: the equation error of a
    pendulum test that swings no further cannot tell G' from k1'·k2.  Its standard errors say
    so and a warning names the leg; the same knee released from 55° is separated, G' within
    3 standard errors of the truth.  The free run of the small swing settles at the valley's
    lowest point, G' near the truth with an elasticity it cannot see: k1' within its error of 0."""
    from quadshank.inference._identify import PASSIVE_GRAVITY_REL_SE, passive_separated

    truth = dict(damping=1.1, gravity=1800.0, k1=25.0, k2=0.05)
    found = {}
    for angle0, objective in ((8.0, "acceleration"), (55.0, "acceleration"), (8.0, "angle")):
        trial = simulate_pendulum_test(truth, angle0=angle0, hand=False, seconds=10.0, seed=3)
        ident, said = _identified_with_warnings(Cohort((trial,)), passive_objective=objective)
        r = ident["PT-left"]
        assert set(r.passive_se) == {"damping", "gravity", "k1", "k2"}
        assert r.summary()["passive_se"] == pytest.approx(r.passive_se)
        found[angle0, objective] = (r, said)
    small, said_small = found[8.0, "acceleration"]
    assert not passive_separated(small.passive, small.passive_se)
    (message,) = [m for m in said_small if UNSEPARATED in m]
    assert message.startswith("PT-left: ") and "the swings of trial 1 (no pulses) do not tell" in message
    g = small.passive["gravity"]
    assert f"G' = {float(f'{g:.3g}'):g} ± " in message
    large, said_large = found[55.0, "acceleration"]
    assert passive_separated(large.passive, large.passive_se)
    assert not [m for m in said_large if UNSEPARATED in m]
    assert large.passive_se["gravity"] < PASSIVE_GRAVITY_REL_SE / 2 * large.passive["gravity"]
    assert abs(large.passive["gravity"] - truth["gravity"]) < 3 * large.passive_se["gravity"]
    run, _ = found[8.0, "angle"]
    assert run.passive["gravity"] == pytest.approx(truth["gravity"], rel=0.05)
    assert run.passive_se["k1"] > run.passive["k1"]


def test_the_free_run_of_a_pendulum_test_is_not_held_in_the_valley_by_its_start():
    """The equation error of a pendulum test with a noisy accelerometer sits in the valley where
    G', k1' and k2 trade (G' about two thirds of the truth); a free run refined from there alone
    stays in a local minimum.  Started along the valley too, it finds the truth's minimum."""
    from quadshank.inference._identify import identify_passive, identify_passive_free_run

    truth = dict(damping=1.1, gravity=1800.0, k1=25.0, k2=0.05)
    trial = simulate_pendulum_test(truth, angle0=60.0, acceleration_noise_deg_s2=30.0, seconds=8.4, seed=1)
    equation_error = identify_passive([trial])[0]
    assert equation_error["gravity"] < 0.8 * truth["gravity"]
    stuck, stuck_rms, _ = identify_passive_free_run([trial], start=equation_error)
    found, rms, _ = identify_passive_free_run([trial])
    assert rms < stuck_rms
    assert found["gravity"] == pytest.approx(truth["gravity"], rel=0.01)
    assert found["k2"] == pytest.approx(truth["k2"], rel=0.1)


def test_quiet_samples_of_an_angle_only_minute_that_trade_gravity_for_elasticity_are_named(tmp_path):
    """One minute of TN-left without its accelerometer: the derived acceleration's noise leaves
    G' and the elasticity trading (G' about two thirds of the truth, k1' tens of times it), and
    the leg is named, in the warning and in the command's report; with the accelerometer the
    same samples separate them."""
    from quadshank.commands.identify import run_identify
    from quadshank.inference._identify import passive_separated

    # equal twitches: the swings of this minute are those the trade was found on
    cohort, truth = simulate_cohort(legs=["TN-left"], minutes=1.0, seed=0, trials=[1], twitch_cv=0.0)
    t = cohort.trials[0]
    derived = t.replace(acceleration_deg_s2=derive_acceleration(t.angle_deg, t.sampling_period_s),
                        acceleration_measured=False)
    sensor, said_sensor = _identified_with_warnings(Cohort((t,)))
    angle_only, said_angle = _identified_with_warnings(Cohort((derived,)))
    a, b = sensor["TN-left"], angle_only["TN-left"]
    assert passive_separated(a.passive, a.passive_se) and not [m for m in said_sensor if UNSEPARATED in m]
    assert a.passive["gravity"] == pytest.approx(truth["legs"]["TN-left"]["passive"]["gravity"], rel=0.02)
    assert not passive_separated(b.passive, b.passive_se)
    (message,) = [m for m in said_angle if UNSEPARATED in m]
    assert message.startswith("TN-left: the quiet samples of trial 1 do not tell")
    assert b.passive_se["gravity"] > 10 * a.passive_se["gravity"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        run_identify(Cohort((derived,)), tmp_path / "angle-only")
        run_identify(Cohort((t,)), tmp_path / "sensor")
    assert "Not separated: TN-left: their data do not tell gravity" in (tmp_path / "angle-only" / "report.md").read_text()
    assert "Not separated" not in (tmp_path / "sensor" / "report.md").read_text()


def test_quiet_samples_far_off_the_pendulum_are_left_out_and_named():
    """A knee meeting the end of its range in deep flexion (or a heel touching the chair) pushes the
    shank with thousands of deg/s² on a few quiet samples; on plain least squares 3 such samples in
    17 000 took k1' from 21 to 3.  They are left out, named with their times, and the rest fitted."""
    cohort, _ = simulate_cohort(legs=("JM-left",), minutes=5.0, seed=19, trials=(1,))
    clean = cohort.get("JM-left", 1)
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)  # clean data: nothing left out, nothing said
        ref, _, n_ref = identify_passive([clean])
    from quadshank.inference._identify import passive_mask

    used = np.flatnonzero(passive_mask(clean))
    deepest = used[np.argsort(clean.angle_deg[used])[:14]]
    for size in (3000.0, 13000.0):
        acc = clean.acceleration_deg_s2.copy()
        acc[deepest] += size
        with pytest.warns(DataWarning, match=r"JM-left trial 1 .*: 14 of the \d+ quiet samples left out of the passive "
                          r"fit.*t = \d+\.\d\d s \(-\d+\.\d°\).*end of its range.*exclude column") as said:
            est, _, n = identify_passive([clean.replace(acceleration_deg_s2=acc)])
        places = re.findall(r"t = (\d+\.\d\d) s", str(said[0].message))
        assert places and all(np.isclose(clean.time_s[deepest], float(t), atol=0.006).any() for t in places)
        assert n == n_ref - 14
        for name, tol in (("damping", 0.01), ("gravity", 0.01), ("k1", 0.05), ("k2", 0.03)):
            assert est[name] == pytest.approx(ref[name], rel=tol), (size, name)
        # the same samples marked in exclude give the same fit, silently
        exclude = np.zeros(clean.n_samples, bool)
        exclude[deepest] = True
        with warnings.catch_warnings():
            warnings.simplefilter("error", DataWarning)
            marked, _, _ = identify_passive([clean.replace(acceleration_deg_s2=acc, exclude=exclude)])
        assert marked == pytest.approx(est, rel=1e-3)


def test_an_angle_only_recordings_last_samples_are_not_in_the_passive_fit():
    """A derived acceleration's last half window comes from the Savitzky-Golay cubic extrapolated:
    its noise is many times the rest's, and it stays out of the passive fit (and out of its warnings)."""
    from quadshank.inference._identify import passive_mask

    cohort, _ = simulate_cohort(legs=("TN-left",), minutes=1.0, seed=2, trials=(1,))
    t = cohort.get("TN-left", 1)
    angle_only = Trial.from_signals(t.subject, t.leg, 1, t.sampling_period_s, t.angle_deg, None, t.stimulation)
    measured, derived = passive_mask(t), passive_mask(angle_only)
    assert measured[-3:].all() or not measured[-1]  # the measured acceleration's end is used where quiet
    assert not derived[-3:].any() and np.array_equal(derived[:-3], measured[:-3])
