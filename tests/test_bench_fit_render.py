"""The fit benchmark's section is written from its JSON record alone, and says when the peer has not converged."""

import json
import sys
from pathlib import Path

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
