"""The modelling loop on the simulator with hidden effects: the diagnosis finds what is missing.

One leg, one minute (two for fatigue), the baseline model3s (model 3's gains on model 2's DARMA
twitch).  For each hidden effect the ranking must put it first, with ΔELPD
above twice its standard error and J at 500 and 1000 ms lowered beyond the
bands; on data with no hidden effect the verdict must be ``none``.
"""

import warnings

import pytest

from quadshank._diagnose import candidates, rank_effects
from quadshank._fit import build_model
from quadshank._simulate import simulate_cohort

HIDDEN = ("torque_angle_peak", "hill_velocity", "angle_delay", "fatigue", "potentiation")
LEG = "JM-left"
#: One minute of trial 1 per dataset; fatigue shows over more pulses (its gain falls by 1/e in 800).
MINUTES = {"fatigue": 2.0}


def _cohort(effect):
    hidden = [] if effect == "none" else [effect]
    cohort, _ = simulate_cohort(legs=[LEG], minutes=MINUTES.get(effect, 1.0), seed=1, trials=(1,), effects=hidden)
    return cohort


@pytest.fixture(scope="module")
def rankings():
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for effect in HIDDEN:
            out[effect] = rank_effects(_cohort(effect), "model3s", effects=HIDDEN, n_draws=150, n_j_draws=30)
        # no hidden effect: every registered candidate is screened, built-in and user-written
        out["none"] = rank_effects(_cohort("none"), "model3s", n_draws=150, n_j_draws=30)
    return out


@pytest.mark.parametrize("effect", HIDDEN)
def test_the_hidden_effect_is_ranked_first_and_clears_the_bar(rankings, effect):
    r = rankings[effect]
    top = r.rows[0]
    assert top["effect"] == effect, [(x["effect"], round(x["delta_elpd"], 1)) for x in r.rows]
    assert top["delta_elpd"] > 2 * top["delta_elpd_se"]
    for h in ("J_500ms", "J_1000ms"):
        assert top[h]["after"]["hi"] < top[h]["before"]["lo"], (h, top[h])
    assert r.verdict == effect


def test_no_hidden_effect_gives_the_verdict_none(rankings):
    r = rankings["none"]
    assert {x["effect"] for x in r.rows} == set(candidates(build_model("model3s")))
    assert r.verdict == "none", [(x["effect"], round(x["delta_elpd"], 1), x["clears_bar"]) for x in r.rows]
    assert not any(x["clears_bar"] for x in r.rows)


def test_the_ranking_reports_the_recovered_effect(rankings):
    """The leader's parameters come out near the simulator's (potentiation: P = 0.8, τ = 60 ms)."""
    row = rankings["potentiation"].rows[0]
    p = row["parameters"][LEG]
    assert abs(p["potentiation"] - 0.8) < 0.2 and abs(p["tau_p"] - 0.06) < 0.02


def test_candidates_follow_the_registry():
    model = build_model("model3s")
    names = candidates(model)
    assert "linear_torque_angle" not in names and "darma" not in names  # in the model / not a candidate
    assert set(HIDDEN) <= set(names) and "cubic_torque_angle" in names  # conftest's user-written effect
    assert "angle_delay" not in candidates(build_model("model3s", ["angle_delay"]))
    assert "linear_torque_angle" not in candidates(build_model("model3s", ["torque_angle_peak"]))
