"""The loop's bar and verdict sentence on J bands and evidence given by hand (no fits)."""

import numpy as np
import pytest

from quadshank.loop._diagnose import J_HORIZONS_MS, Ranking, evidence_bar, verdict_sentence
from quadshank.model._effects import registered_effects

RNG = np.random.default_rng(0)


def _draws(medians, spread=0.05, n=200):
    """J draws (n, horizons) around ``medians`` [deg] per horizon of J_HORIZONS_MS."""
    return np.asarray(medians)[None, :] + spread * RNG.standard_normal((n, len(J_HORIZONS_MS)))


BEFORE = _draws([1.0, 2.0, 4.0, 6.0])
#: a delay change: predictions better over the first 250 ms, no different at 0.5 and 1 s
DELAY_LIKE = _draws([0.6, 1.5, 4.0, 6.0])
#: a change of gain: better at 0.5 and 1 s
GAIN_LIKE = _draws([1.0, 2.0, 3.0, 4.5])


def test_a_delay_is_judged_where_a_delay_acts():
    acts = registered_effects()["angle_delay"].acts_at_ms
    assert tuple(acts) == (100, 250)
    row = evidence_bar(300.0, 50.0, BEFORE, DELAY_LIKE, True, acts)
    assert row["supported"] and row["clears_bar"] and row["J_lowered_at_ms"] == [100, 250]
    # at the horizons of a change of gain the same J bands would not clear it: its 1-s J effect is small
    assert not evidence_bar(300.0, 50.0, BEFORE, DELAY_LIKE, True, (500, 1000))["clears_bar"]
    assert not evidence_bar(60.0, 50.0, BEFORE, DELAY_LIKE, True, acts)["clears_bar"]  # not supported
    assert registered_effects()["fatigue"].acts_at_ms == (500, 1000)


def _ranking(rows, verdict):
    return Ranking(base=None, fits={}, rows=rows, verdict=verdict, J_base={})


def _row(effect, d, se, after, acts):
    return {"effect": effect, **evidence_bar(d, se, BEFORE, after, True, acts)}


def test_the_sentence_names_evidence_that_does_not_lower_j_and_j_that_is_not_the_best_explanation():
    lead = _row("angle_delay", 1490.0, 339.0, _draws([1.0, 2.0, 4.0, 6.0]), (100, 250))  # evidence, no J change
    stand_in = _row("potentiation", 1180.0, 104.0, GAIN_LIKE, (500, 1000))  # lowers J, less evidence
    assert lead["supported"] and not lead["clears_bar"] and stand_in["clears_bar"]
    text = verdict_sentence(_ranking([stand_in, lead], "potentiation"))
    assert text.startswith("Adding potentiation improves ELPD by 1180 ± 104 and lowers J at 500 ms")
    assert "angle_delay has the most evidence (ΔELPD 1490 ± 339) but changes J little where it acts" in text
    note = text.split("angle_delay has the most evidence")[1]
    assert "at 100 ms" in note and "at 250 ms" in note and "at 1000 ms" not in note  # where a delay acts

    found = _row("angle_delay", 1490.0, 339.0, DELAY_LIKE, (100, 250))
    text = verdict_sentence(_ranking([found, stand_in], "angle_delay"))
    assert text.startswith("Adding angle_delay improves ELPD by 1490 ± 339 and lowers J at 100 ms")
    assert "potentiation also lowers J" in text and "is not the best explanation" in text
    assert "has the most evidence" not in text

    alone = verdict_sentence(_ranking([found], "angle_delay"))
    assert "not the best explanation" not in alone and "most evidence" not in alone

    weak = _row("fatigue", 8.6, 13.6, _draws([1.0, 2.0, 4.0, 6.0]), (500, 1000))
    text = verdict_sentence(_ranking([weak], "none"))
    assert text.startswith("Nothing is missing that the candidates describe: the best, fatigue, changes ELPD by 8.6 ± 13.6")
    assert "most evidence" not in text  # not supported: nothing to add


def test_a_candidate_that_lowers_j_without_evidence_is_not_called_an_explanation():
    best = _row("torque_angle_peak", 500.0, 50.0, GAIN_LIKE, (500, 1000))
    lucky = _row("fatigue", 3.0, 5.0, GAIN_LIKE, (500, 1000))  # lowers J, no evidence
    assert lucky["J_lowered_beyond_bands"] and not lucky["supported"]
    assert "fatigue" not in verdict_sentence(_ranking([best, lucky], "torque_angle_peak"))


def test_an_effect_names_horizons_the_bands_are_drawn_at(scratch_registry):
    import dataclasses

    import pytest

    from quadshank import Effect, register_effect

    @dataclasses.dataclass(frozen=True)
    class SlowGain(Effect):
        kind = "gain"
        name = "slow_gain"
        acts_at_ms = (2000,)

        def factor(self, ctx):
            return 1.0

    with pytest.raises(TypeError, match=r"acts_at_ms must name some of the horizons \(100, 250, 500, 1000\)"):
        register_effect(SlowGain)


def test_evidence_that_rests_on_unreliable_segments_is_not_counted():
    """PSIS-LOO's Pareto k: the evidence must hold on the segments the extension's leave-one-out
    estimate is reliable for; evidence carried by a few segments of high k is not support."""
    from quadshank.loop._diagnose import PARETO_K_MAX, k_checked_difference

    rng = np.random.default_rng(1)
    n = 120
    base = rng.normal(-50.0, 1.0, n)
    ext = base + rng.normal(0.05, 0.5, n)  # no real gain on most segments ...
    ext[:4] += 150.0  # ... and a large one on four segments whose k is high
    k_ext = np.full(n, 0.3)
    k_ext[:4] = 1.4
    base[[10, 11]] = np.nan  # a segment not compared in one fit is left out of both
    d, se, share = k_checked_difference(base, ext, k_ext)
    keep = np.ones(n, bool)
    keep[:4] = keep[[10, 11]] = False
    assert d == pytest.approx(np.sum((ext - base)[keep])) and share == pytest.approx(4 / (n - 2))
    assert PARETO_K_MAX == 0.7

    full = np.nansum(ext - base)
    diff = (ext - base)[np.isfinite(base)]
    full_se = float(np.sqrt(diff.size * np.var(diff)))
    row = {"effect": "fatigue", **evidence_bar(full, full_se, BEFORE, GAIN_LIKE, True, (500, 1000), (d, se, share))}
    assert full > 2 * full_se  # supported over every segment ...
    assert not row["supported"] and not row["clears_bar"]  # ... but not on the reliable ones
    text = verdict_sentence(_ranking([row], "none"))
    assert "fatigue's evidence" in text and "Pareto k > 0.7 in 3 %" in text and "NUTS (--confirm)" in text
    # where the reliable segments carry the evidence as well, it stands
    ext2 = base + 5.0
    row2 = evidence_bar(float(np.nansum(ext2 - base)), 1.0, BEFORE, GAIN_LIKE, True, (500, 1000),
                        k_checked_difference(base, ext2, k_ext))
    assert row2["supported"] and row2["clears_bar"]


def test_where_most_segments_are_unreliable_the_approximation_is_named_and_the_rest_must_hold():
    """Most segments' k high says the approximation stands poorly as a whole, not that a few segments
    carry the evidence: the sentence names the approximation and sends the candidate to NUTS, and
    the evidence must still hold on the reliable segments.  A share just above one half decides
    nothing: with the same reliable evidence the row reads the same on either side of it."""
    from quadshank.loop._diagnose import K_SHARE_MAX

    def row(checked):
        return {"effect": "accel_resonance",
                **evidence_bar(6.4, 2.4, BEFORE, BEFORE, False, (500, 1000), checked)}

    weak_above, weak_below = row((2.3, 1.4, K_SHARE_MAX + 0.02)), row((2.3, 1.4, K_SHARE_MAX - 0.02))
    assert not weak_above["supported"] and not weak_above["clears_bar"]
    assert (weak_below["supported"], weak_below["clears_bar"]) == (weak_above["supported"], weak_above["clears_bar"])
    text = verdict_sentence(_ranking([weak_above], "none"))
    assert "stands poorly for the posterior with accel_resonance (Pareto k > 0.7 in 52 % of the segments)" in text
    assert "on the other segments it is 2 ± 1, not counted as supported" in text and "NUTS (--confirm)" in text
    assert "rests on segments" not in text
    # no reliable segment at all: nothing is counted, and the sentence says why
    none_left = {"effect": "angle_delay",
                 **evidence_bar(708.0, 170.0, BEFORE, DELAY_LIKE, True, (100, 250), (0.0, 0.0, 1.0))}
    assert not none_left["supported"] and not none_left["clears_bar"]
    assert "no segment is estimated reliably" in verdict_sentence(_ranking([none_left], "none"))
    # where the reliable segments carry the evidence, the approximation is named and the evidence stands
    strong = {"effect": "angle_delay",
              **evidence_bar(708.0, 170.0, BEFORE, DELAY_LIKE, True, (100, 250), (300.0, 60.0, 0.8))}
    assert strong["supported"] and strong["clears_bar"]
    text = verdict_sentence(_ranking([strong], "angle_delay"))
    assert "(Pareto k > 0.7 in 80 % of the segments)" in text and "not counted" not in text


def test_candidates_that_cannot_change_the_likelihood_are_named_with_the_reason():
    """On the pendulum alone, or on trials without pulses, an effect that acts through the muscle
    has nothing to explain; where the fit compares angles, neither has one on what the
    accelerometer reads alone."""
    from quadshank.data import Cohort, simulate_pendulum_test
    from quadshank.inference._priors import build_model
    from quadshank.loop._diagnose import MUSCLE_KINDS, candidates, not_applicable

    known = registered_effects()
    t = simulate_pendulum_test({"damping": 1.3, "gravity": 1950.0, "k1": 30.0, "k2": 0.05}, subject="PT", trial=1)
    pendulum = Cohort((t,))
    passive = build_model("passive")
    offered = candidates(passive)
    found = not_applicable(passive, pendulum, offered, pendulum.legs, (1,))
    muscle = {e for e in offered if known[e].kind in MUSCLE_KINDS}
    assert muscle and set(found) == muscle | {"accel_resonance"}
    assert {"gravity_offset", "goniometer_offset"} <= set(offered) - set(found)
    assert "passive is the pendulum alone" in found["torque_angle_peak"] and "compares angles" in found["accel_resonance"]

    model3 = build_model("model3")
    offered = candidates(model3)
    found = not_applicable(model3, pendulum, offered, pendulum.legs, (1,))
    assert set(found) == {e for e in offered if known[e].kind in MUSCLE_KINDS}  # judged by the acceleration
    assert "hold no pulse" in found["potentiation"]
    one_pulse = Cohort((t.replace(stimulation=(np.arange(t.n_samples) == 200).astype(float)),))
    assert not_applicable(model3, one_pulse, offered, one_pulse.legs, (1,)) == {}


def test_nothing_found_names_the_features_the_residuals_were_screened_against():
    """A pendulum test has no interpulse interval or pulse count: the sentence does not claim them."""
    from quadshank.evaluation._structure import NOTHING_FOUND, nothing_found

    said = nothing_found({"screened": {"angle": {}, "velocity": {}, "time": {}}})
    assert said == "The residuals change with none of knee angle, angular velocity and time in trial beyond chance."
    assert nothing_found({"screened": {}}) == NOTHING_FOUND


def test_an_effect_on_the_accelerometer_alone_must_not_raise_j():
    """An accelerometer's effect cannot improve an angle prediction, so its bar is the evidence;
    but where J rises beyond the bands with it, it has moved the dynamics to absorb their misfit:
    it does not clear the bar, and the sentence says why.  A noise effect's bar stays the evidence."""
    accel = registered_effects()["accel_resonance"]
    assert not accel.predicts_angle and accel.kind != "noise"
    worse = _draws([1.0, 2.0, 4.5, 6.6])  # J at 500 and 1000 ms beyond the bands
    same = _draws([1.0, 2.0, 4.0, 6.0])
    row = evidence_bar(108.0, 25.0, BEFORE, worse, False, accel.acts_at_ms, None, accel.kind)
    assert row["supported"] and row["J_raised_at_ms"] == [500, 1000] and not row["clears_bar"]
    assert evidence_bar(108.0, 25.0, BEFORE, same, False, accel.acts_at_ms, None, accel.kind)["clears_bar"]
    noise = registered_effects()["twitch_variability"]
    assert evidence_bar(108.0, 25.0, BEFORE, worse, False, noise.acts_at_ms, None, noise.kind)["clears_bar"]

    rows = [{"effect": "accel_resonance", **row}, _row("fatigue", 20.0, 30.0, same, (500, 1000))]
    said = verdict_sentence(_ranking(rows, "none"))
    assert "accel_resonance has evidence (ΔELPD 108 ± 25) but acts on what the accelerometer reads alone, and with it " \
           "J rises beyond the bands (" in said and "° → 4.50° at 500 ms" in said, said
    assert "changes J little" not in said  # the note of a lead whose J does not move is not said of it


def test_a_nuts_fit_that_failed_its_checks_confirms_nothing(capsys):
    """NUTS's word on a leader from a fit that failed its checks is "would confirm", with the
    banner, and the command exits 3 as `fit` does; from fits that passed it is "confirms", exit 0."""
    from quadshank.cli import _nuts_fits_code
    from quadshank.loop._diagnose import nuts_sentence

    band = {"median": 2.0, "lo": 1.8, "hi": 2.2}
    nuts = {"clears_bar": True, "delta_elpd": 40.0, "delta_elpd_se": 8.0,
            "J_1000ms": {"before": {**band, "median": 2.5}, "after": band}}
    passed = nuts_sentence([{"effect": "fatigue", "nuts": {**nuts, "banner": None}}])
    assert passed.startswith("NUTS confirms fatigue: ΔELPD 40 ± 8, J at 1 s 2.50° → 2.00° [1.80, 2.20].")
    failed = nuts_sentence([{"effect": "fatigue", "nuts": {**nuts, "banner": "FIT FAILED ITS CHECKS: R-hat 1.05"}}])
    assert failed.startswith("NUTS would confirm fatigue: ") and \
        failed.endswith("(but its fit failed its checks: FIT FAILED ITS CHECKS: R-hat 1.05).")
    assert _nuts_fits_code(None, "out") == _nuts_fits_code(True, "out") == 0
    capsys.readouterr()
    assert _nuts_fits_code(False, "out") == 3
    assert "a NUTS fit made to confirm failed its checks" in capsys.readouterr().err


def test_a_loop_that_ends_at_its_round_limit_says_more_rounds_may_find_more():
    """Where the last round still added an effect the loop ended at its limit, not because nothing
    cleared the bar: the page says so (and the summary's ``stopped``); where the last verdict was
    none it does not."""
    from quadshank.loop._diagnose import STOPPED_AT_LIMIT, STOPPED_NOTHING, Discovery
    from quadshank.outputs._loop import LIMIT_SENTENCE, discovery_markdown

    band = {"median": 2.0, "lo": 1.8, "hi": 2.2}
    one = {"model": "model3s", "verdict": "twitch_variability", "sentence": "Adding it helps.",
           "J_ms": {"500": band, "1000": band}, "elpd": {"value": -100.0, "se": 5.0}}
    at_limit = Discovery(model="model3s", final_model="model3s+twitch_variability", rounds=[one],
                         added=["twitch_variability"], stopped=STOPPED_AT_LIMIT)
    assert LIMIT_SENTENCE in discovery_markdown(at_limit)
    done = Discovery(model="model3s", final_model="model3s", rounds=[{**one, "verdict": "none"}], added=[],
                     stopped=STOPPED_NOTHING)
    assert LIMIT_SENTENCE not in discovery_markdown(done)
