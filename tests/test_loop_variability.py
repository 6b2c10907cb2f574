"""The modelling loop on twitches that vary from pulse to pulse (the simulator's
``twitch_variability``: a log-normal gain per pulse, coefficient of variation 0.2, the
paper's Table IV).  Without a noise term for it, the variation is taken for an effect
(the accelerometer's resonance clears the bar); with ``twitch_variability`` in the model
it is noise, and nothing else is called missing."""

import re
import warnings

import pytest
from loop_cases import HIDDEN, check_hidden_first

from quadshank.loop._diagnose import rank_effects, verdict_sentence
from quadshank.model._model import paper_model
from quadshank.data._simulate import EFFECT_PARAMETERS, simulate_cohort

LEG = "JM-left"
SCREEN = dict(n_draws=150, n_j_draws=30, n_starts=0)
#: The loop's baseline with the noise term for varying twitches.
NOISY_BASE = paper_model("3s").add("twitch_variability", name="model3s+twitch_variability")


@pytest.fixture(scope="module")
def varying():
    cohort, _ = simulate_cohort(legs=[LEG], minutes=1.0, seed=1, trials=(1,), effects=["twitch_variability"])
    return cohort


def test_varying_twitches_are_found_as_noise(varying):
    """From the loop's baseline, the noise term is the verdict (by the evidence alone: it cannot
    change a prediction), its CV near the simulated 0.2, and the sentence says it is noise."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = rank_effects(varying, "model3s", effects=("twitch_variability", "accel_resonance", "angle_delay"), **SCREEN)
    assert r.verdict == "twitch_variability", [(x["effect"], round(x["delta_elpd"], 1)) for x in r.rows]
    top = r.rows[0]
    assert top["delta_elpd"] > 4 * top["delta_elpd_se"]
    cv = float(r.fits["twitch_variability"].values(LEG)["twitch_cv"])
    assert abs(cv - EFFECT_PARAMETERS["twitch_variability"]["cv"]) < 0.08, cv
    said = verdict_sentence(r)
    assert "scatter about the model, not its dynamics, so J does not judge it (at 1 s " in said
    assert re.search(r"at 1 s \d+\.\d\d° without it, \d+\.\d\d° with it\)", said), said


def test_with_the_noise_term_nothing_else_is_called_missing(varying):
    """With ``twitch_variability`` in the baseline, no candidate clears the bar on data where
    nothing else is hidden; without the term in the likelihood the resonance did."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = rank_effects(varying, NOISY_BASE, effects=("accel_resonance", "angle_delay", "potentiation"), **SCREEN)
    assert r.verdict == "none", [(x["effect"], round(x["delta_elpd"], 1), round(x["delta_elpd_se"], 1)) for x in r.rows]
    resonance = next(x for x in r.rows if x["effect"] == "accel_resonance")
    assert not resonance["supported"], resonance["delta_elpd"]


@pytest.mark.parametrize("hidden", ["torque_angle_peak", "hill_velocity"])
def test_a_hidden_effect_is_found_among_varying_twitches(hidden):
    """With ``twitch_variability`` in the baseline, an effect hidden in twitch-varying data is
    ranked first and clears the bar (ΔELPD > 2 SE, J lowered beyond the bands where it acts)."""
    cohort, _ = simulate_cohort(legs=[LEG], minutes=1.0, seed=1, trials=(1,), effects=["twitch_variability", hidden])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = rank_effects(cohort, NOISY_BASE, effects=HIDDEN, **SCREEN)
    check_hidden_first(r, hidden)
