"""Shared by test_loop.py and test_loop_none.py (two files, so two test workers share the work).

The modelling loop on the simulator with hidden effects: one leg, one minute
of trial 1 (two for fatigue and for the angle-dependent delay) of the default cohort, whose twitches vary from
pulse to pulse (CV 0.2, the paper's Table IV); the baseline model3s (model 3's
gains on model 2's DARMA twitch) with the likelihood's term for that variation
(``twitch_variability``), which a round of the loop adds first
(test_loop_variability.py).  The seed is one whose swings stay within 80° with
each effect: where they meet the simulated knee's range, which model3s lacks,
the loop finds the range first (test_loop.py).  For each hidden effect the
ranking must put it first, with ΔELPD above twice its standard error and J
lowered beyond the bands at the horizons where it acts; on data with no hidden
effect the verdict must be ``none``.
"""

import warnings

from quadshank.inference._priors import build_model
from quadshank.loop._diagnose import rank_effects
from quadshank.model._effects import registered_effects
from quadshank.data._simulate import simulate_cohort

HIDDEN = ("torque_angle_peak", "hill_velocity", "angle_delay", "fatigue", "potentiation")
LEG = "JM-left"
#: One minute of trial 1 per dataset; fatigue shows over more pulses (its gain falls by 1/e in 800).
#: The delay 10 ms shorter below −20° needs pulses below −20°: in JM-left's first minute it leads
#: the evidence (ΔELPD 220 ± 51) but lowers J at 100 and 250 ms by less than the bands' width (the
#: verdict's sentence says so); from two minutes on it clears the bar.
MINUTES = {"fatigue": 2.0, "angle_delay": 2.0}
#: The simulation's seed: JM-left's swings stay within −53°…84° with each hidden effect.
SEED = 4
#: The loop's baseline: model3s with the noise term for twitches that vary.
BASELINE = ("model3s", ("twitch_variability",))


def baseline():
    return build_model(*BASELINE)


def cohort_with(effect):
    hidden = [] if effect == "none" else [effect]
    cohort, _ = simulate_cohort(legs=[LEG], minutes=MINUTES.get(effect, 1.0), seed=SEED, trials=(1,), effects=hidden)
    return cohort


def screened(cohort, model=None, **kw):
    """The loop's ranking of ``model`` (default :func:`baseline`) on ``cohort``, as these tests
    screen: 150 Laplace draws, J from 30 of them, warnings off; ``kw`` to :func:`rank_effects`."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return rank_effects(cohort, baseline() if model is None else model, n_draws=150, n_j_draws=30, **kw)


def rankings(effects) -> dict:
    """The baseline's ranking per dataset; with a hidden effect the five of HIDDEN are
    screened, with none every registered candidate (built-in and user-written).

    With a hidden effect each extension's mode is sought from one start only (the
    baseline's mode, the new parameters at their prior median; ``n_starts=0``): the
    hidden effect must be found without the prior draws that the default adds, a
    harder test and a quarter of the work.  The ``none`` verdict is tested with the
    package's defaults, where more starts give each candidate its best chance to
    claim the data (a false positive is the failure there)."""
    out = {}
    for effect in effects:
        kw = {"effects": None} if effect == "none" else {"effects": HIDDEN, "n_starts": 0}
        out[effect] = screened(cohort_with(effect), **kw)
    return out


def check_hidden_first(r, effect) -> None:
    top = r.rows[0]
    assert top["effect"] == effect, [(x["effect"], round(x["delta_elpd"], 1)) for x in r.rows]
    assert top["delta_elpd"] > 2 * top["delta_elpd_se"]
    for h in registered_effects()[effect].acts_at_ms:  # lowered beyond the bands where the effect acts
        assert top[f"J_{h}ms"]["after"]["hi"] < top[f"J_{h}ms"]["before"]["lo"], (h, top[f"J_{h}ms"])
    assert r.verdict == effect
