"""Cohorts built in Python meet the rules a file's trials meet: identification, evaluation, the
likelihood and ``run_check`` refuse what the readers would, naming the leg, trial, signal and
sample index, and warn of what looks implausible."""

import warnings

import numpy as np
import pytest

from quadshank.commands import run_check
from quadshank.data import Cohort, DataWarning, InterchangeError, Trial, check_cohort, simulate_cohort
from quadshank.evaluation import prediction_errors
from quadshank.inference import identify_cohort
from quadshank.model import paper_model
from quadshank.model._likelihood import prepare


@pytest.fixture(scope="module")
def trial():
    cohort, _ = simulate_cohort(legs=["JM-left"], minutes=1.0, seed=3, trials=(1,))
    t = cohort.trials[0]
    # a trial as a lab would build it from its own arrays: angle and stimulation, the rest derived
    return Trial.from_signals("JM", "left", 1, t.sampling_period_s, t.angle_deg, None, t.stimulation)


def _with(base, **changes) -> Cohort:
    return Cohort((base.replace(**changes),))


def _nan_at(trial, i):
    angle = trial.angle_deg.copy()
    angle[i] = np.nan
    return angle


@pytest.mark.parametrize(("changes", "said"), [
    (lambda t: {"stimulation": t.stimulation * 5}, "JM-left trial 1, column 'stimulation': every pulse is 5, outside [0, 1]"),
    (lambda t: {"angle_deg": _nan_at(t, 17)}, "JM-left trial 1, column 'angle_deg', index 17: non-finite value nan"),
    (lambda t: {"time_s": t.time_s[::-1].copy()}, "JM-left trial 1, column 'time_s', index 1"),
    (lambda t: {"sampling_period_s": 0.2}, "column 'sampling_period_s': 0.2 s is longer than"),
    (lambda t: {"leg": "Left"}, "JM-Left trial 1, column 'leg': 'Left' is not 'left' or 'right'"),
    (lambda t: {"trial": 0}, "JM-left trial 0, column 'trial': trial number 0"),
    (lambda t: {"subject": ""}, "column 'subject': subject '' is empty"),
    (lambda t: {"angle_deg": np.radians(t.angle_deg)}, "column 'angle_deg', index 404: values look like radians"),
])
def test_a_trial_built_in_python_that_breaks_a_rule_is_refused_everywhere(trial, changes, said):
    cohort = _with(trial, **changes(trial))
    for use in (check_cohort,
                lambda c: identify_cohort(c),
                lambda c: prepare(c, paper_model(3)),
                lambda c: prediction_errors(paper_model(3), c.trials[0]),
                lambda c: run_check(c)):
        with pytest.raises(InterchangeError) as err:
            use(cohort)
        assert said in str(err.value), str(err.value)
        assert str(err.value).startswith("a cohort built in Python breaks the data rules")


def test_two_subjects_whose_legs_make_one_key_are_refused(trial):
    a = trial.replace(subject="JM-x", leg="left")
    b = trial.replace(subject="JM", leg="x-left", trial=2)
    with pytest.raises(InterchangeError, match="subject 'JM' with leg 'x-left' and subject 'JM-x' with leg 'left' "
                                               "make the same leg 'JM-x-left'"):
        check_cohort(Cohort((a, b)))


def test_a_valid_trial_is_checked_once_and_warned_of_as_read_from_a_file(trial):
    good = _with(trial)
    assert check_cohort(good) is good
    assert run_check(good).legs["JM-left"]["identify"].startswith("models 1-3")
    # an accelerometer mounted the other way round: its acceleration against the angle's
    flipped = _with(trial, acceleration_deg_s2=-trial.acceleration_deg_s2, acceleration_measured=True)
    with pytest.warns(DataWarning, match="built in Python \\(JM-left trial 1\\): acceleration_deg_s2 .*sign"):
        check_cohort(flipped)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_cohort(flipped)  # checked already: no second warning
        check_cohort(simulate_cohort(legs=["TN-left"], minutes=0.2, seed=1, trials=(1,))[0])  # made within the rules


def test_arguments_a_wrong_index_would_clamp_or_wrap_are_refused(trial):
    """Starts outside the recording, horizons below one sample, a leg given twice, a passive system
    missing a parameter, integer trial numbers and an alpha outside (0, 1): each is named, not
    silently clamped, wrapped, doubled or matched to nothing."""
    from quadshank.evaluation import horizon_samples, sign_tests
    from quadshank.inference import identify_leg
    from quadshank.model._model import predict_ahead

    model = paper_model(3)
    signals = (trial.angle_deg, trial.velocity_deg_s, trial.stimulation)
    for starts in ([trial.n_samples], [-1], [2.5]):
        with pytest.raises(ValueError, match=rf"starts: .* lie outside the recording's samples 0\.\.{trial.n_samples - 1}"):
            predict_ahead(model, *signals, np.array(starts), 5)
    assert predict_ahead(model, *signals, np.array([0, trial.n_samples - 1]), 5).shape == (2, 5)
    for horizons in ([-1, 10], [0], []):
        with pytest.raises(ValueError, match="a horizon is a whole number of samples, at least 1"):
            prediction_errors(model, trial, horizons)
    with pytest.raises(ValueError, match="a horizon is a positive number of milliseconds"):
        horizon_samples(0.01, (-100, 100))
    cohort = Cohort((trial,))
    with pytest.raises(ValueError, match="legs: JM-left given twice"):
        prepare(cohort, model, legs=["JM-left", "JM-left"])
    assert prepare(cohort, model, legs="JM-left").legs == ("JM-left",)  # one name, not its letters
    with pytest.raises(ValueError, match="passive: give damping, gravity, k1, k2"):
        identify_leg(trial, passive={"damping": 0.9})
    J = {"a": {"L": {"2": {100: 1.0}}}, "b": {"L": {"2": {100: 2.0}}}}
    assert sign_tests(J, trials=(2, 3)) == sign_tests(J, trials=("2", "3")) and len(sign_tests(J)) == 1
    with pytest.raises(ValueError, match="alpha must lie between 0 and 1"):
        sign_tests(J, alpha=2)


def test_a_derived_signal_is_derived_again_when_the_angle_or_the_period_changes(trial):
    """``Trial.replace`` of the angle or the period re-derives what was derived from the angle,
    as ``from_signals`` would; a measured signal, or one given, is kept."""
    doubled = trial.replace(angle_deg=2 * trial.angle_deg)
    fresh = Trial.from_signals("JM", "left", 1, trial.sampling_period_s, 2 * trial.angle_deg, None, trial.stimulation)
    np.testing.assert_allclose(doubled.velocity_deg_s, fresh.velocity_deg_s, atol=1e-9)
    np.testing.assert_allclose(doubled.acceleration_deg_s2, fresh.acceleration_deg_s2, atol=1e-6)
    slower = trial.replace(sampling_period_s=2 * trial.sampling_period_s, time_s=2 * trial.time_s)
    assert np.std(slower.velocity_deg_s) == pytest.approx(np.std(trial.velocity_deg_s) / 2, rel=0.05)
    given = trial.replace(angle_deg=2 * trial.angle_deg, velocity_deg_s=trial.velocity_deg_s)
    np.testing.assert_array_equal(given.velocity_deg_s, trial.velocity_deg_s)
    measured = trial.replace(acceleration_measured=True).replace(angle_deg=2 * trial.angle_deg)
    np.testing.assert_array_equal(measured.acceleration_deg_s2, trial.acceleration_deg_s2)


def test_settings_and_declarations_of_the_wrong_type_are_refused_where_they_are_made():
    """FitSettings and Param refuse what numpyro, numpy or a fit would trip over later: a
    fractional or text count, a truthy string for a flag, a bare trial number, a prior that does
    not fit the parameter's shape or support (register_effect's refusals: test_model.py)."""
    from quadshank import Param
    from quadshank.inference import FitSettings

    for kw, said in (({"chains": 2.7}, "chains (--chains) must be a whole number, not 2.7"),
                     ({"draws": "100"}, "draws (--draws) must be a whole number, not '100'"),
                     ({"centred": "no"}, "centred must be True or False"),
                     ({"trials": 1}, "trials: give the trial numbers to fit"), ({"trials": (0,)}, "trials: give")):
        with pytest.raises(ValueError, match=said.replace("(", r"\(").replace(")", r"\)")):
            FitSettings(**kw)
    assert FitSettings(trials=[1, 2]).trials == (1, 2)
    for kw, said in ((dict(name=5, units="x"), "must be a Python identifier"),
                     (dict(name="x", units=None), "units must be a string"),
                     (dict(name="x", units="1", support="negative", prior=("lognormal", 0.0, 1.0)), "lognormal prior"),
                     (dict(name="v", units="", prior=("normal", (0, 0, 0), (1, 1, 1)), shape=(2,)), "3 components"),
                     (dict(name="w", units="", shape=(-1,)), "sizes of at least 1")):
        with pytest.raises(ValueError, match=said):
            Param(**kw)


def test_a_trial_is_refused_at_construction_where_no_rule_could_read_it(trial):
    """Types and shapes the data rules cannot even look at are refused when the Trial is made,
    naming the field; a trial number given as text is read as the number."""
    signals = (trial.sampling_period_s, trial.angle_deg, None, trial.stimulation)
    for args, kwargs, error, said in (
            (("JM", 3, 1, *signals), {}, TypeError, "leg must be a string, not 3"),
            ((None, "left", 1, *signals), {}, TypeError, "subject must be a string, not None"),
            (("JM", "left", 1.7, *signals), {}, TypeError, r"trial must be a whole number \(1, 2, ...\), not 1.7"),
            (("JM", "left", 1, 0.0, *signals[1:]), {}, ValueError, "sampling_period_s must be a positive number of seconds, not 0.0"),
            (("JM", "left", 1, "0.01", *signals[1:]), {}, ValueError, "sampling_period_s must be a positive number"),
            (("JM", "left", 1, trial.sampling_period_s, trial.angle_deg[:, None], None, trial.stimulation), {},
             ValueError, r"angle_deg has shape \(6000, 1\); give one value per sample"),
            (("JM", "left", 1, *signals), {"exclude": np.zeros(10)}, ValueError, r"exclude has shape \(10,\), expected \(6000,\)"),
            (("JM", "left", 1, *signals), {"exclude": np.full(trial.n_samples, 2)}, ValueError,
             "exclude must be 0 or 1 .* index 0 holds 2")):
        with pytest.raises(error, match=said):
            Trial.from_signals(*args, **kwargs)
    with pytest.raises(ValueError, match=r"JM-left trial 1: stimulation has shape \(5,\), expected \(6000,\)"):
        trial.replace(stimulation=trial.stimulation[:5])
    assert trial.replace(trial="2").trial == 2
    pendulum = Trial.from_signals("JM", "left", 2, trial.sampling_period_s, trial.angle_deg, None, None)
    assert pendulum.stimulation.shape == trial.angle_deg.shape and not pendulum.stimulation.any()
    composed, decomposed = trial.replace(subject="Zo\u00eb"), trial.replace(subject="Zoe\u0308", trial=2)
    assert Cohort((composed, decomposed)).legs == ("Zo\u00eb-left",)  # one subject, as the reader reads it
    assert Cohort((trial.replace(trial="1"),)).get("JM-left", 1).trial == 1
    with pytest.raises(TypeError, match=r"Cohort takes a sequence of trials; one trial is Cohort\(\(trial,\)\)"):
        Cohort(trial)
    with pytest.raises(TypeError, match="Cohort takes a sequence of Trial, not str"):
        Cohort(("a", "b"))
    assert Cohort((trial,)).select(legs="JM-left", trials=1).trials == (trial,)


def test_a_trials_signals_are_its_own_and_read_only(trial):
    """Writing into a trial's signal is refused, and changing the array it was built from leaves
    it as it was: a cohort built from it, and the fingerprint a fit recorded, cannot change."""
    angle = trial.angle_deg.copy()
    built = Trial.from_signals("JM", "left", 1, trial.sampling_period_s, angle, None, trial.stimulation)
    cohort = Cohort((built,))
    before = cohort.fingerprint()
    angle[:] = 0.0
    assert built.angle_deg[100] == trial.angle_deg[100] != 0.0
    for name in ("angle_deg", "stimulation", "velocity_deg_s", "exclude"):
        with pytest.raises(ValueError, match="read-only"):
            getattr(built, name)[0] = 1
    assert cohort.select(legs=["JM-left"]).fingerprint() == before


def test_empty_and_misplaced_arguments_are_named():
    """What had failed deep in numpy, scipy or a dict lookup names the argument instead."""
    from quadshank.evaluation import evaluate_cohort
    from quadshank.inference import FitSettings, fit, identify_passive

    for kwargs, said in (({"legs": []}, "legs: give at least one leg; known legs"),
                         ({"trials": []}, "trials: give at least one trial"),
                         ({"seed": -1}, "seed must be a whole number from 0"),
                         ({"seed": 1.5}, "seed must be a whole number"),
                         ({"trials": [1.0]}, r"unknown trial\(s\) \[1.0\]"),
                         ({"minutes": "1"}, "minutes must be positive")):
        with pytest.raises(ValueError, match=said):
            simulate_cohort(**{"legs": ["JM-left"], "minutes": 0.1, **kwargs})
    cohort, _ = simulate_cohort(legs=["JM-left", "TN-left"], minutes=0.2, seed=1, trials=(1,))
    model = paper_model(3)
    with pytest.raises(KeyError, match="models has no entry for leg\\(s\\) TN-left \\(it has JM-left\\)"):
        evaluate_cohort(cohort, {"JM-left": {"model3": model}})
    with pytest.raises(TypeError, match=r"models: give models\[leg\]\[model_name\]"):
        evaluate_cohort(cohort, {"model3": model})
    with pytest.raises(ValueError, match="legs: give at least one leg \\(the data has JM-left, TN-left\\)"):
        prepare(cohort, model, legs=[])
    with pytest.raises(ValueError, match="legs: give at least one leg \\(the data hold no trials\\)"):
        prepare(Cohort(()), model)
    with pytest.raises(ValueError, match="trials: give at least one trial"):
        identify_passive([])
    with pytest.raises(TypeError, match=r"model: give a Model \(quadshank.build_model\('model3s'\) builds one"):
        fit(cohort, "model3s", FitSettings(chains=1, warmup=10, draws=10), progress=False)
    from quadshank.inference import identify_leg
    with pytest.raises(TypeError, match="trial: give one Trial .*, not Cohort"):
        identify_leg(cohort)


def test_save_fit_refuses_a_folder_that_holds_files(tmp_path):
    """``save_fit`` writes into a new or empty folder; another fit, or a data folder, is refused
    unless ``overwrite=True``, and what is not a fit is refused before anything is written."""
    from quadshank.inference import save_fit

    class Posterior:  # the least save_fit reads before it writes: a folder refusal comes first
        posterior = None

    other = tmp_path / "other-fit"
    other.mkdir()
    (other / "summary.json").write_text("{}")
    with pytest.raises(FileExistsError, match="other-fit: the folder already holds a fit; give a new folder, or "
                                              "overwrite=True"):
        save_fit(Posterior(), other)
    data = tmp_path / "data"
    data.mkdir()
    (data / "manifest.csv").write_text("subject\n")
    with pytest.raises(FileExistsError, match="already holds files"):
        save_fit(Posterior(), data)
    assert (other / "summary.json").read_text() == "{}" and sorted(p.name for p in data.iterdir()) == ["manifest.csv"]
    with pytest.raises(TypeError, match="idata: give the fit's InferenceData"):
        save_fit(None, tmp_path / "new")
    assert not (tmp_path / "new").exists()
