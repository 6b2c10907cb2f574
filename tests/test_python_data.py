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
    (lambda t: {"sampling_period_s": -0.01}, "column 'sampling_period_s': '-0.01' is not a positive finite number"),
    (lambda t: {"leg": "Left"}, "JM-Left trial 1, column 'leg': 'Left' is not 'left' or 'right'"),
    (lambda t: {"trial": 0}, "JM-left trial 0, column 'trial': trial number 0"),
    (lambda t: {"subject": ""}, "column 'subject': subject '' is empty"),
    (lambda t: {"angle_deg": np.radians(t.angle_deg)}, "column 'angle_deg', index 402: values look like radians"),
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
