"""The paper's results (Tables I, IV and V) on the simulated cohort, at full size.

One run of the whole protocol (5 legs, 3 trials of 5 minutes, seed 0: the
seed of ``results/reproduce``), identified and evaluated as the paper did.
"""

import numpy as np
import pytest

from quadshank.evaluation._prediction import evaluate_cohort, sign_tests, table_v
from quadshank.inference._identify import identify_cohort
from quadshank.data._paper import LEGS, TABLE_III
from quadshank.inference._identify import models_from_summary
from quadshank.data._simulate import simulate_cohort

MODELS = ("model1", "model2", "model3")


@pytest.fixture(scope="module")
def reproduction():
    cohort, truth = simulate_cohort(legs=LEGS, minutes=5.0, seed=0)
    ident = identify_cohort(cohort)
    models = models_from_summary({leg: r.summary() for leg, r in ident.items()})
    J = evaluate_cohort(cohort, models)
    return ident, J, table_v(J)


def test_isolated_twitches_span_the_swing(reproduction):
    """G'_1 (eq. 9) near G'_2, as in the paper's Tables I and III (ratios 0.87-0.95).

    Isolated twitches recorded only while the shank falls back into flexion
    (long IPIs shorter than the swing's period) give G'_1/G'_2 of about 1.14.
    """
    ident, _, _ = reproduction
    for leg in LEGS:
        ratio = ident[leg].models["model1"].flat_params()["gain"] / TABLE_III[leg]["G2"]
        assert 0.9 < ratio < 1.1, (leg, ratio)


def test_the_default_cohort_gives_the_papers_table_iv(reproduction):
    """The paper's model 3 leaves 12-29 % RMS error in the integrated twitches (Table IV).

    The default cohort's twitches vary from pulse to pulse (CV 0.2): about 20 %, and model 1's
    error stays above model 3's.  With equal twitches (``twitch_cv=0``) the simulated error is
    sensor noise only (1-4 %).
    """
    ident, _, _ = reproduction
    equal, _ = simulate_cohort(legs=LEGS, minutes=5.0, seed=0, trials=(1,), twitch_cv=0.0)
    equal_ident = identify_cohort(equal)
    for leg in LEGS:
        pct = ident[leg].rms_error_pct
        assert 10 < pct["model3"] < 35, (leg, pct)
        assert pct["model1"] > pct["model3"], (leg, pct)
        assert equal_ident[leg].rms_error_pct["model3"] < 5, (leg, equal_ident[leg].rms_error_pct)


def test_table_v_behaves_as_the_paper(reproduction):
    _, J, T = reproduction
    for trial in ("1", "2", "3"):
        for m in MODELS:
            means = [T[trial][m][h][0] for h in sorted(T[trial][m])]
            assert np.all(np.diff(means) > 0), (trial, m, means)  # errors grow with horizon
            assert 0.5 < means[0] < 4.0, (trial, m, means)  # a few degrees at 100 ms
        at_1s = {m: T[trial][m][1000][0] for m in MODELS}
        assert min(at_1s, key=at_1s.get) == "model3", (trial, at_1s)  # model 3 best at 1 s
    for trial in ("1", "2"):  # u = 1: the paper's 7-12 deg at 1 s (model 3 6.7-7.5, models 1-2 8.2-12.5)
        for m in MODELS:
            assert 5.0 < T[trial][m][1000][0] < 14.0, (trial, m, T[trial][m][1000])
    tests = {(t["model_a"], t["model_b"], t["horizon_ms"]): t for t in sign_tests(J)}
    assert tests[("model1", "model3", 1000)]["better"] == "model3"
    assert tests[("model2", "model3", 1000)]["better"] == "model3"
    assert not tests[("model1", "model2", 1000)]["significant"]  # as in the paper
