"""The scale benchmark's cohort: replicas of the simulated legs that are legs of their own, and its section."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_scale  # noqa: E402

from quadshank.data import LEGS  # noqa: E402


def test_replicas_are_new_legs_with_their_own_realisations(tmp_path):
    cohort = bench_scale.replicated_cohort(2, 0.05)
    assert len(cohort.legs) == 2 * len(LEGS)
    assert cohort.legs[: len(LEGS)] == tuple(LEGS)
    assert cohort.legs[len(LEGS)] == "TN2-left"
    first, second = (next(t for t in cohort if t.key == k) for k in ("TN-left", "TN2-left"))
    assert first.n_samples == second.n_samples
    assert not np.array_equal(first.stimulation, second.stimulation)  # another seed: another sequence
    from quadshank.data import read_interchange, write_interchange

    back = read_interchange(write_interchange(cohort, tmp_path / "data"))
    assert back.legs == cohort.legs


def test_the_section_states_the_growth():
    def row(legs, seconds):
        return {"legs": legs, "samples": legs * 6000, "seconds": seconds, "ok": True, "rhat_max": 1.005,
                "ess_bulk_min": 900.0, "ess_tail_min": 700.0, "draws_per_chain": 300,
                "target": {"stopped": "target met"}}

    record = {"command": "python benchmarks/bench_scale.py", "minutes": 1.0, "chains": 4, "target_ess": 400,
              "time_limit_s": 3600.0, "rows": [row(5, 100.0), row(20, 250.0)], "date": "2026-11-27",
              "machine": "x86_64, 2 CPU cores"}
    text = bench_scale.render(record)
    assert "| 20 | 120000 | 250 | 12.5 | yes |" in text
    assert "4× the legs took 2.50× the time" in text
