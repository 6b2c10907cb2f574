"""The modelling loop finds a hidden torque–angle maximum, Hill torque–velocity and angle-dependent
delay (see loop_cases.py; fatigue, potentiation and no hidden effect: test_loop_none.py)."""

import pytest
from loop_cases import HIDDEN, check_hidden_first, rankings

from quadshank.loop._diagnose import candidates
from quadshank.inference._priors import build_model

HERE = ("torque_angle_peak", "hill_velocity", "angle_delay")


@pytest.fixture(scope="module")
def ranked():
    return rankings(HERE)


@pytest.mark.parametrize("effect", HERE)
def test_the_hidden_effect_is_ranked_first_and_clears_the_bar(ranked, effect):
    check_hidden_first(ranked[effect], effect)


def test_candidates_follow_the_registry():
    model = build_model("model3s")
    names = candidates(model)
    assert "linear_torque_angle" not in names and "darma" not in names  # in the model / not a candidate
    assert set(HIDDEN) <= set(names) and "cubic_torque_angle" in names  # conftest's user-written effect
    assert "angle_delay" not in candidates(build_model("model3s", ["angle_delay"]))
    assert "linear_torque_angle" not in candidates(build_model("model3s", ["torque_angle_peak"]))
    assert "fractional_delay" not in names  # on a DARMA(2,2) twitch it re-parametrises b
