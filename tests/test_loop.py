"""The modelling loop finds a hidden torque–angle maximum, Hill torque–velocity and angle-dependent
delay (see loop_cases.py; fatigue, potentiation and no hidden effect: test_loop_none.py)."""

import math

import pytest
from loop_cases import HIDDEN, LEG, check_hidden_first, rankings, screened

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


def test_a_hidden_gravity_offset_is_found_by_the_rest_offset_candidates():
    """Gravity about 10° (the shank resting off angle 0): the two rest-offset candidates lead and
    clear the bar, and ``gravity_offset`` finds the angle.  On stimulated trials of one minute the
    two explain the data about equally well (they differ only in where the elasticity and the gain
    factors act), so either may be first."""
    from quadshank.data._simulate import EFFECT_PARAMETERS, simulate_cohort

    cohort, _ = simulate_cohort(legs=["JM-left"], minutes=1.0, seed=1, trials=(1,), effects=["gravity_offset"])
    r = screened(cohort, n_starts=0, effects=("gravity_offset", "goniometer_offset", "torque_angle_peak"))
    rows = {x["effect"]: x for x in r.rows}
    assert {x["effect"] for x in r.rows[:2]} == {"gravity_offset", "goniometer_offset"} and r.verdict in rows
    top = rows["gravity_offset"]
    assert top["clears_bar"] and top["delta_elpd"] > 10 * rows["torque_angle_peak"]["delta_elpd_se"]
    assert top["signature"] == "angle"
    angle = top["parameters"]["JM-left"]["gravity_angle"]
    assert angle == pytest.approx(EFFECT_PARAMETERS["gravity_offset"]["angle_deg"], abs=2.0)


def test_a_hidden_end_of_range_in_extension_is_found_and_located():
    """The knee meets the end of its range at 75° (a torque rising by e every 5°): the loop puts
    ``extension_limit`` first, past the bar, with the limit's torque and width the truth's.  With
    the package's default starts: from the prior median alone (a torque too small to matter at
    the angles these data reach) the optimiser does not find it."""
    from quadshank.data._simulate import EFFECT_PARAMETERS, simulate_cohort

    cohort, _ = simulate_cohort(legs=["JM-left"], minutes=1.0, seed=1, trials=(1,), effects=["extension_limit"])
    assert max(t.angle_deg.max() for t in cohort) < 85.0  # no swing far beyond the end of the range
    r = screened(cohort, "model3s", effects=("extension_limit", "torque_angle_peak", "gravity_offset", "hill_velocity"))
    check_hidden_first(r, "extension_limit")
    truth = EFFECT_PARAMETERS["extension_limit"]
    found = r.rows[0]["parameters"]["JM-left"]
    at_full_extension = truth["torque_deg_s2"] * math.exp((90.0 - truth["phi_limit_deg"]) / truth["width_deg"])
    assert found["limit_stiffness"] == pytest.approx(at_full_extension, rel=0.15)
    assert found["limit_width"] == pytest.approx(truth["width_deg"], rel=0.1)


def test_the_knees_range_is_found_where_the_swings_meet_it():
    """With nothing hidden, the simulated knee's own range: the baseline, which has none, lacks it,
    and ``extension_limit`` clears the bar."""
    from quadshank.data._simulate import simulate_cohort

    cohort, _ = simulate_cohort(legs=[LEG], minutes=1.0, seed=1, trials=(1,))
    assert max(t.angle_deg.max() for t in cohort) > 85.0
    r = screened(cohort, effects=("extension_limit",))
    check_hidden_first(r, "extension_limit")
    assert r.rows[0]["parameters"][LEG]["limit_stiffness"] > 100.0  # deg/s² at full extension: a stop


def test_the_knees_range_is_found_before_potentiation_whose_swings_meet_it():
    """Potentiation's larger twitches swing the simulated knee into its range (past 85°), which a
    model without an end of range predicts it passes: with potentiation added J at 1 s rises, though
    the evidence supports it, and ``extension_limit``, which lowers J at every horizon, is the
    verdict.  Where the swings stay short of the range, potentiation is found (loop_cases.py)."""
    from quadshank.data._simulate import simulate_cohort

    cohort, _ = simulate_cohort(legs=["JM-left"], minutes=2.0, seed=1, trials=(1,), effects=["potentiation"])
    assert max(t.angle_deg.max() for t in cohort) > 85.0
    r = screened(cohort, effects=("extension_limit", "potentiation"))
    rows = {x["effect"]: x for x in r.rows}
    check_hidden_first(r, "extension_limit")
    assert rows["extension_limit"]["J_lowered_at_ms"] == [100, 250, 500, 1000]
    pot = rows["potentiation"]
    assert pot["supported"]
    assert 1000 in pot["J_raised_at_ms"] and not pot["clears_bar"]


def test_output_candidates_are_screened_beside_an_accelerometer_response():
    """With ``accel_resonance`` in the model, an output effect is screened like any other: ranked,
    not left out as a candidate that failed."""
    import warnings

    from quadshank.data._simulate import simulate_cohort
    from quadshank.loop._diagnose import rank_effects

    cohort, _ = simulate_cohort(legs=["JM-left"], minutes=0.3, seed=5, trials=(1,), effects=("accel_resonance",))
    model = build_model("model3s", ["accel_resonance"])
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # a failed screen warns
        ranking = rank_effects(cohort, model, effects=["activation_damping"], n_draws=50, n_j_draws=10,
                               start_stride=20, n_starts=0)
    assert ranking.failed == {}
    [row] = ranking.rows
    assert row["effect"] == "activation_damping" and math.isfinite(row["delta_elpd"])
    assert not row["clears_bar"]  # the data hold no such effect
