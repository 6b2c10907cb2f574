"""The fit benchmark's section is written from its JSON record alone, and says when the peer has not converged."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_fit  # noqa: E402


def _record(peer_rhat, peer_ess):
    return {
        "command": "python benchmarks/bench_fit.py --out results/benchmarks.md",
        "date": "2026-11-25", "machine": "x86_64, CPU", "model": "model3", "effects": ["angle_delay"],
        "legs": ["TN-left", "TN-right", "JM-left", "JM-right", "OT-left"], "minutes": 5.0, "chains": 4,
        "chain_method": "vectorized", "start": "screen", "warmup": 1000, "draws": 1000,
        "fit_wall_s": 830.0, "fit_compile_s": 34.0, "fit_sampling_s": 784.0, "delay_evidence_s": 7.0,
        "ok": True, "problems": [], "rhat_max": 1.004, "ess_bulk_min": 3597.0, "ess_tail_min": 2386.0,
        "divergences": 0, "ess_bulk_min_per_s": 3597.0 / 784.0, "delay_mode": {"TN-left": 4},
        "j_draws": 200, "j_trials": 15, "j_wall_s": 150.0, "j_compile_s": 1.0,
        "peer": {"pymc": "5", "nutpie": "0.16", "backend": "numba", "density_check": [-1.0, -1.0],
                 "compile_s": 116.0, "sampling_s": 4920.0, "rhat_max": peer_rhat, "ess_bulk_min": peer_ess,
                 "divergences": 0, "ess_bulk_min_per_s": peer_ess / 4920.0},
    }


def test_unconverged_peer_is_called_so_and_small_rates_keep_their_digits():
    text = bench_fit.render(_record(2.877, 4.6), "bench_fit_screen")
    assert "The peer's fit fails the same checks" in text
    assert "bulk ESS ≥ 400" in text
    assert "| 4.59 | 0.000935 |" in text  # 4.6 / 4920 s, not rounded to 0.00
    assert "4907× the peer's" in text
    assert "Neither fit" not in text  # quadshank's fit passed


def test_converged_peer_gets_a_plain_ratio():
    text = bench_fit.render(_record(1.003, 2000.0), "bench_fit_screen")
    assert "fails the same checks" not in text
    assert "11.3× the peer's" in text  # (3597 / 784) / (2000 / 4920)
    # the title tells the sections of several runs apart
    assert text.startswith("## Hierarchical fit and posterior J bands: 5 legs × 5 min, 4 × (1000 + 1000), "
                           "vectorized chains from the screen, the peer with its diagonal mass matrix from its own starts\n")


@pytest.mark.parametrize("failed_ours", [False, True])
def test_from_record_rewrites_only_its_section(tmp_path, failed_ours):
    rec = _record(2.877, 4.6)
    if failed_ours:
        rec.update(ok=False, problems=["R-hat 1.8 ≥ 1.01: chains disagree"])
    (tmp_path / "bench_fit_screen.json").write_text(json.dumps(rec))
    out = tmp_path / "benchmarks.md"
    out.write_text("# Benchmarks\n\n<!-- other:begin -->\nkept\n<!-- other:end -->\n\n"
                   "<!-- bench_fit_screen:begin -->\nold\n<!-- bench_fit_screen:end -->\n")
    assert bench_fit.main(["--from-record", str(tmp_path / "bench_fit_screen.json"), "--out", str(out)]) == 0
    text = out.read_text()
    assert "kept" in text and "\nold\n" not in text
    assert "sampling wall time | 784 s | 4920 s" in text
    assert ("Neither fit has converged." in text) == failed_ours
    assert ("FAILED its checks: R-hat 1.8" in text) == failed_ours


def test_peer_start_and_steps_are_rendered():
    rec = _record(1.003, 2000.0)
    assert "nutpie's own jittered defaults" in bench_fit.render(rec, "s")  # an old record: no start, no steps
    assert "leapfrog steps" not in bench_fit.render(rec, "s")
    rec["peer"].update(start="fit", steps_per_draw=63.25)
    rec["steps_per_draw"] = 11.94
    text = bench_fit.render(rec, "s")
    assert "started at the points the fit's chains started at" in text
    assert "| leapfrog steps per draw (after warm-up) | 11.9 | 63.2 |" in text


def test_peer_metric_is_named():
    """A record from before the metric option ran nutpie's diagonal metric and says so; a record that
    names the metric gets its own words."""
    rec = _record(1.003, 2000.0)
    assert "its diagonal mass matrix (`--peer-metric diag`)" in bench_fit.render(rec, "s")
    rec["peer"]["metric"] = "low_rank"
    text = bench_fit.render(rec, "s")
    assert "its low-rank modified mass matrix (`--peer-metric low_rank`)" in text and "diagonal" not in text


def test_peer_chains_start_where_the_fits_did():
    """The start vector follows nutpie's order of unconstrained values (the constrained ones after
    n_dim are left out), PyMC's ``_log__`` names map to numpyro's sites, and chain k's values go
    to nutpie's k-th request."""
    import dataclasses

    @dataclasses.dataclass(frozen=True)
    class Compiled:  # the fields of nutpie's compiled model that _start_at reads
        shape_info: tuple
        n_dim: int
        initial_point_func: object = None

    names = ["gain_s_leg", "sigma_log__", "sigma"]
    slices = [slice(0, 3), slice(3, 6), slice(6, 9)]
    shapes = [(3,), (3,), (3,)]
    starts = {"gain_s_leg": np.arange(6.0).reshape(2, 3), "sigma": 10 + np.arange(6.0).reshape(2, 3)}
    c = bench_fit._start_at(Compiled((names, slices, shapes), 6), starts, chains=2)
    got = [c.initial_point_func(seed) for seed in (7, 7, 7)]
    np.testing.assert_array_equal(got[0], [0, 1, 2, 10, 11, 12])
    np.testing.assert_array_equal(got[1], [3, 4, 5, 13, 14, 15])
    np.testing.assert_array_equal(got[2], got[0])  # a retried start cycles through the chains
    with pytest.raises(ValueError, match="sigma_log__"):
        bench_fit._start_at(Compiled((names, slices, [(3,), (4,), (3,)]), 7), starts, chains=2)


def test_the_densitys_precision_is_named_where_the_record_holds_it():
    rec = _record(1.003, 2000.0)
    assert "precision" not in bench_fit.render(rec, "s").split("| measure |")[0]
    rec["precision"] = "double"
    assert "the density at double precision" in bench_fit.render(rec, "s")
