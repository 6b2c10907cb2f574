"""The modelling loop on twitches that vary from pulse to pulse (the simulator's default: a
log-normal gain per pulse, coefficient of variation 0.2, the paper's Table IV).  From the
loop's baseline model3s the noise term for it (``twitch_variability``) is the verdict; with
it in the model the variation is noise: hidden effects among varying twitches, and nothing
else called missing where nothing is hidden, are loop_cases.py's."""

import re
import warnings

import pytest
from loop_cases import SEED

from quadshank.loop._diagnose import rank_effects, verdict_sentence
from quadshank.data._simulate import TWITCH_CV, simulate_cohort

LEG = "JM-left"
SCREEN = dict(n_draws=150, n_j_draws=30, n_starts=0)


@pytest.fixture(scope="module")
def varying():
    cohort, _ = simulate_cohort(legs=[LEG], minutes=1.0, seed=SEED, trials=(1,))
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
    assert abs(cv - TWITCH_CV) < 0.08, cv
    said = verdict_sentence(r)
    assert "scatter about the model, not its dynamics, so J does not judge it (at 1 s " in said
    assert re.search(r"at 1 s \d+\.\d\d° without it, \d+\.\d\d° with it\)", said), said
