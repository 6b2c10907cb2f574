"""Stimulation artefacts: a signal that jumps at the pulses' own samples is found, named, and
repaired by straight lines; a twitch begun before its logged pulse is told apart from one."""

import warnings

import numpy as np
import pytest

from quadshank.cli import main
from quadshank.commands import run_check
from quadshank.data import (Cohort, DataWarning, Trial, load_cohort, plausibility, repair_stimulation_artefacts,
                            simulate_cohort, stimulation_artefacts, write_interchange)
from quadshank.inference import identify_cohort


@pytest.fixture(scope="module")
def clean():
    cohort, _ = simulate_cohort(legs=["JM-left"], minutes=2.0, seed=3, trials=[1])
    return cohort.trials[0]


def _spiked(trial: Trial, sizes, signal="acceleration_deg_s2") -> Trial:
    """``trial`` with ``sizes[j]`` added to ``signal`` j samples after every pulse."""
    x = np.array(getattr(trial, signal))
    for j, size in enumerate(sizes):
        at = trial.pulse_indices + j
        x[at[at < x.size]] += size
    return trial.replace(**{signal: x})


def _quiet(f, *args):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        return f(*args)


def test_a_spike_on_the_accelerometer_at_each_pulse_is_found_and_repaired(clean):
    """+5000 deg/s² on each pulse's sample reads as a twitch that starts at once: identify's delay
    goes to 0 and its gain up by half.  Found, warned of, and once repaired the delay and the gains
    are the clean recording's."""
    ref = _quiet(identify_cohort, Cohort((clean,)))["JM-left"]
    assert ref.delay >= 3
    spiked = _spiked(clean, [5000.0])
    (found,) = stimulation_artefacts(spiked).values()
    assert found["kind"] == "artefact" and found["lags"] == [0] and found["size"][0] == pytest.approx(5000, rel=0.02)
    (text,) = [t for t in plausibility(spiked) if "jumps at the pulses" in t]
    assert "+5e+03 deg/s² on the pulse's sample" in text and "--repair-artefacts" in text
    with pytest.warns(DataWarning, match=r"JM-left trial 1: the delay comes out at [01] samples? \(\d+ ms\), shorter "
                                         r"than a stimulated muscle's"):
        wrong = identify_cohort(Cohort((spiked,)))["JM-left"]
    assert wrong.models["model3"].flat_params()["gain"] > 1.3 * ref.models["model3"].flat_params()["gain"]
    with pytest.warns(DataWarning, match=r"JM-left trial 1 \(simulated \(seed 3\)\): stimulation artefact repaired by "
                                         r"straight lines: acceleration_deg_s2 on sample 0 after each of \d+ pulses"):
        repaired = repair_stimulation_artefacts(spiked)
    assert stimulation_artefacts(repaired) == {}
    fixed = _quiet(identify_cohort, Cohort((repaired,)))["JM-left"]
    assert fixed.delay == ref.delay
    for name in ("gain", "gamma_angle", "gamma_velocity"):
        got, want = fixed.models["model3"].flat_params()[name], ref.models["model3"].flat_params()[name]
        assert got == pytest.approx(want, rel=0.02, abs=2e-4), name


def test_an_artefact_that_decays_is_repaired_over_its_tail(clean):
    found = stimulation_artefacts(_spiked(clean, [8000.0, 4000.0, 2000.0]))["acceleration_deg_s2"]
    assert found["kind"] == "artefact" and found["lags"] == [0, 1, 2]
    bipolar = stimulation_artefacts(_spiked(clean, [10000.0, -10000.0]))["acceleration_deg_s2"]
    assert bipolar["lags"] == [0, 1] and bipolar["size"][1] == pytest.approx(-10000, rel=0.02)


def test_a_spike_on_the_angle_of_an_angle_only_recording_is_repaired_before_the_derivation(clean):
    """Without an accelerometer a 3° spike on the angle at each pulse becomes thousands of deg/s²
    in the derived acceleration; the angle is repaired and the acceleration derived again."""
    angle_only = Trial.from_signals("JM", "left", 1, clean.sampling_period_s, clean.angle_deg, None, clean.stimulation)
    ref = _quiet(identify_cohort, Cohort((angle_only,)))["JM-left"]
    spiked = Trial.from_signals("JM", "left", 1, clean.sampling_period_s, _spiked(clean, [3.0], "angle_deg").angle_deg,
                                None, clean.stimulation)
    assert list(stimulation_artefacts(spiked)) == ["angle_deg"]
    wrong = _quiet(identify_cohort, Cohort((spiked,)))["JM-left"]
    assert abs(wrong.models["model3"].flat_params()["gain"] / ref.models["model3"].flat_params()["gain"] - 1) > 0.1
    repaired = _quiet(repair_stimulation_artefacts, spiked)
    assert not repaired.acceleration_measured
    assert np.abs(repaired.acceleration_deg_s2 - angle_only.acceleration_deg_s2).max() < \
        0.2 * np.abs(spiked.acceleration_deg_s2 - angle_only.acceleration_deg_s2).max()
    fixed = _quiet(identify_cohort, Cohort((repaired,)))["JM-left"]
    assert fixed.delay == ref.delay
    assert fixed.models["model3"].flat_params()["gain"] == pytest.approx(ref.models["model3"].flat_params()["gain"],
                                                                         rel=0.03)


def test_pulses_logged_late_are_told_apart_and_left(clean):
    """Pulses written 5 samples after they were delivered: the twitch is rising at the logged
    pulse and goes on rising; that is named as a latency, and nothing is repaired."""
    late = np.zeros(clean.n_samples)
    at = clean.pulse_indices + 5
    late[at[at < late.size]] = clean.stimulation[clean.pulse_indices][at < late.size]
    shifted = clean.replace(stimulation=late)
    (found,) = stimulation_artefacts(shifted).values()
    assert found["kind"] == "early"
    assert any("already moving away at the pulses' samples" in t and "logged later than they were delivered" in t
               for t in plausibility(shifted))
    assert repair_stimulation_artefacts(shifted) is shifted


def test_recordings_without_an_artefact_are_left_alone():
    """The simulated cohort (five legs, three trials, twitches varying from pulse to pulse), at 1
    and 5 ms, with equal twitches and with an accelerometer that rings: nothing is found, nothing
    repaired."""
    cohort, _ = simulate_cohort(minutes=1.0, seed=0)
    ringing, _ = simulate_cohort(legs=["TN-left"], minutes=1.0, seed=1, trials=[1], effects=("accel_resonance",))
    equal, _ = simulate_cohort(legs=["TN-left"], minutes=1.0, seed=1, trials=[1], twitch_cv=0.0)
    fine = [simulate_cohort(legs=["JM-left"], minutes=0.5, seed=2, trials=[1], sampling_period_s=dt)[0].trials[0]
            for dt in (0.001, 0.005)]
    for t in (*cohort.trials, *ringing.trials, *equal.trials, *fine):
        assert stimulation_artefacts(t) == {}, (t.key, t.trial, t.sampling_period_s)
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)
        assert repair_stimulation_artefacts(cohort).trials == cohort.trials


def test_convert_repairs_the_artefacts_and_check_qualifies_its_verdict(clean, tmp_path, capsys):
    spiked = _spiked(clean, [5000.0])
    write_interchange(Cohort((spiked,)), tmp_path / "raw")
    with pytest.warns(DataWarning, match="jumps at the pulses"):
        uses = run_check(tmp_path / "raw").legs["JM-left"]["identify"]
    assert "jumps at the pulses' own samples (a stimulation artefact, or pulses logged late)" in uses
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DataWarning)
        assert main(["convert", str(tmp_path / "raw"), str(tmp_path / "repaired.nc"), "--repair-artefacts"]) == 0
    err = capsys.readouterr().err
    assert "stimulation artefact repaired by straight lines: acceleration_deg_s2 on sample 0" in err, err
    repaired = load_cohort(tmp_path / "repaired.nc")
    assert repaired.attrs["artefacts_repaired"].startswith("JM-left trial 1: acceleration_deg_s2 on sample 0")
    assert stimulation_artefacts(repaired.trials[0]) == {}
    assert np.allclose(repaired.trials[0].angle_deg, clean.angle_deg)


def test_excluding_the_pulses_samples_is_named_for_the_twitches_it_leaves_out(clean):
    """Excluding a stimulation artefact's samples, the obvious fix, leaves every twitch out (the
    classical identification drops a twitch with an excluded sample, the fit its windows): named,
    with the repair to use instead."""
    exclude = np.zeros(clean.n_samples, bool)
    exclude[clean.pulse_indices] = True
    said = [t for t in plausibility(_spiked(clean, [5000.0]).replace(exclude=exclude)) if "excluded sample" in t]
    n = clean.pulse_indices.size
    assert len(said) == 1 and said[0].startswith(f"{n} of the {n} pulses have an excluded sample within the 350 ms")
    assert "a stimulation artefact excluded? Repair it instead" in said[0] and "--repair-artefacts" in said[0]
    assert not [t for t in plausibility(clean) if "excluded sample" in t]


def test_a_stimulation_column_held_between_pulses_qualifies_the_fits_verdict(clean):
    """A column that holds the level over the 50 ms after each pulse (a gate): check's verdict on a
    fit says each of those samples is taken for a pulse."""
    held = clean.stimulation.copy()
    for p in clean.pulse_indices:
        held[p:p + 5] = clean.stimulation[p]
    with pytest.warns(DataWarning, match="consecutive samples"):
        uses = run_check(Cohort((clean.replace(stimulation=held),))).legs["JM-left"]
    assert "but the stimulation of trial 1 is nonzero on consecutive samples, each of which a fit takes for a pulse" \
        in uses["fit"], uses
    assert "but the stimulation" not in run_check(Cohort((clean,))).legs["JM-left"]["fit"]
