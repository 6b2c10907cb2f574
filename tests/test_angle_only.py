"""Recordings without an accelerometer: the acceleration derived from the angle gives the
classical estimates within stated tolerances of those from the accelerometer."""

from __future__ import annotations

import numpy as np
import pytest

from quadshank.data import read_interchange, simulate_cohort, write_interchange
from quadshank.inference import identify_cohort

#: Relative tolerance of each estimate from a derived acceleration against the accelerometer's.
TOLERANCE = {"damping": 0.03, "gravity": 0.03, "k2": 0.10, "k1": 0.25, "G2": 0.05, "G1": 0.05}


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    cohort, _ = simulate_cohort(legs=["TN-left", "JM-left", "OT-left"], minutes=2.0, seed=0, trials=[1])
    folder = write_interchange(cohort, tmp_path_factory.mktemp("angle-only") / "data")
    for f in folder.glob("*-trial1.csv"):  # drop the accelerometer's column
        rows = [line.split(",") for line in f.read_text().splitlines()]
        j = rows[0].index("acceleration_deg_s2")
        f.write_text("\n".join(",".join(r[:j] + r[j + 1:]) for r in rows) + "\n")
    angle_only = read_interchange(folder)
    assert not any(t.acceleration_measured for t in angle_only)
    return identify_cohort(cohort), identify_cohort(angle_only)


def test_classical_estimates_from_the_angle_alone(both):
    sensor, derived = both
    for leg in sensor:
        a, b = sensor[leg], derived[leg]
        for name in ("damping", "gravity", "k1", "k2"):
            assert b.passive[name] == pytest.approx(a.passive[name], rel=TOLERANCE[name]), (leg, name)
        g2a, g2b = (x.models["model3"].flat_params()["gain"] for x in (a, b))
        assert g2b == pytest.approx(g2a, rel=TOLERANCE["G2"]), leg
        g1a, g1b = (x.models["model1"].flat_params()["gain"] for x in (a, b))
        assert g1b == pytest.approx(g1a, rel=TOLERANCE["G1"]), leg
        assert abs(b.delay - a.delay) <= 1, leg


def test_the_derived_acceleration_is_not_the_accelerometers(both):
    """The comparison above is not of one signal with itself."""
    sensor, derived = both
    assert any(sensor[leg].passive["k1"] != derived[leg].passive["k1"] for leg in sensor)
    assert not np.allclose([s.passive["damping"] for s in sensor.values()],
                           [d.passive["damping"] for d in derived.values()], rtol=1e-9, atol=0)


def test_a_page_of_results_says_which_signals_were_derived():
    """The sentence at the top of every report names the period and each signal derived from the
    angle (method, window, how many trials), and at another period than the paper's says how the
    per-sample gains compare with its values."""
    from quadshank.data import Trial
    from quadshank.data._cohort import Cohort, derived_signals
    from quadshank.outputs._tables import recordings_sentence

    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.2, seed=0, trials=[1, 2])
    t1, t2 = cohort.trials
    angle_only = Trial.from_signals("TN", "left", 1, t1.sampling_period_s, t1.angle_deg, None, t1.stimulation,
                                    velocity_deg_s=t1.velocity_deg_s)
    derived = derived_signals(Cohort((angle_only, t2)))
    assert derived["acceleration"]["trials"] == ["TN-left trial 1"]  # trial 2 holds the accelerometer's
    assert "acceleration" not in derived_signals(cohort)
    said = recordings_sentence(0.01, {"acceleration": derived["acceleration"]})
    assert said == ("Recordings sampled every 10 ms; acceleration derived from the angle (Savitzky-Golay, zero-phase, "
                    "7 samples) in 1 trial.")
    assert recordings_sentence(0.005, None) == ("Recordings sampled every 5 ms. Gains are per sample: at 5 ms a twitch's "
                                                "gain is about 2× the paper's values at 10 ms quoted beside them.")
    assert recordings_sentence(0.005, None, muscle=False) == "Recordings sampled every 5 ms."
