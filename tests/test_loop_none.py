"""The modelling loop finds hidden fatigue and potentiation, and says `none` when nothing is
hidden (see loop_cases.py; the other hidden effects: test_loop.py)."""

import pytest
from loop_cases import LEG, baseline, check_hidden_first, rankings

from quadshank.loop._diagnose import candidates

HERE = ("fatigue", "potentiation")


@pytest.fixture(scope="module")
def ranked():
    return rankings((*HERE, "none"))


@pytest.mark.parametrize("effect", HERE)
def test_the_hidden_effect_is_ranked_first_and_clears_the_bar(ranked, effect):
    check_hidden_first(ranked[effect], effect)


def test_no_hidden_effect_gives_the_verdict_none(ranked):
    r = ranked["none"]
    assert {x["effect"] for x in r.rows} == set(candidates(baseline()))
    assert r.verdict == "none", [(x["effect"], round(x["delta_elpd"], 1), x["clears_bar"]) for x in r.rows]
    assert not any(x["clears_bar"] for x in r.rows)


def test_the_ranking_reports_the_recovered_effect(ranked):
    """The leader's parameters give the simulator's potentiation (1 + P·exp(−(IPI − T_s)/τ_p), P = 0.8,
    τ_p = 60 ms) within 10 % over the short intervals, where P and τ_p trade against each other."""
    import numpy as np

    from quadshank.data._simulate import EFFECT_PARAMETERS

    p = ranked["potentiation"].rows[0]["parameters"][LEG]
    truth = EFFECT_PARAMETERS["potentiation"]
    ipi = np.arange(0.02, 0.13, 0.01)
    found = 1 + p["potentiation"] * np.exp(-(ipi - 0.01) / p["tau_p"])
    true = 1 + truth["P"] * np.exp(-(ipi - 0.01) / truth["tau_p_s"])
    assert np.all(np.abs(found / true - 1) < 0.1), (p, found / true)
