"""The modelling loop on the simulator with hidden effects: the diagnosis finds what is missing.

One leg, one minute (two for fatigue), the baseline model3s (model 3's gains on model 2's DARMA
twitch).  For each hidden effect the ranking must put it first, with ΔELPD
above twice its standard error and J at 500 and 1000 ms lowered beyond the
bands; on data with no hidden effect the verdict must be ``none``.
"""

import json
import warnings

import numpy as np
import pytest

from quadshank._cli import main
from quadshank._diagnose import candidates, rank_effects
from quadshank._fit import build_model
from quadshank._interchange import write_interchange
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


def test_discover_on_the_command_line_with_a_user_effect(tmp_path, capsys):
    """The whole loop in one command; the user-written effect of conftest.py is screened like the others."""
    cohort = _cohort("potentiation")
    write_interchange(cohort, tmp_path / "data")
    out = tmp_path / "discover"
    rc = main(["--quiet", "discover", str(tmp_path / "data"), "--effects", "potentiation,cubic_torque_angle",
               "--max-rounds", "2", "--out", str(out)])
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["added"] == ["potentiation"]
    assert s["final_model"] == "model3s+potentiation"
    r1 = json.loads((out / "round-1" / "summary.json").read_text())
    cubic = next(r for r in r1["ranking"] if r["effect"] == "cubic_torque_angle")
    assert np.isfinite(cubic["delta_elpd"]) and not cubic["clears_bar"]
    assert "Adding potentiation improves ELPD" in (out / "round-1" / "report.md").read_text()
    assert len(s["rounds"]) == 2 and s["rounds"][1]["verdict"] == "none"
    for name in r1["figures"]:
        assert (out / "round-1" / name).stat().st_size > 5000


@pytest.fixture(scope="module")
def saved_fits(tmp_path_factory):
    """Data with hidden potentiation and two short NUTS fits of it: model3s, and model3s + potentiation."""
    root = tmp_path_factory.mktemp("saved")
    write_interchange(_cohort("potentiation"), root / "data")
    rcs = {}
    for name, extra in (("base", []), ("pot", ["--add-effect", "potentiation"])):
        rcs[name] = main(["--quiet", "fit", str(root / "data"), "--model", "model3s", *extra, "--chains", "1",
                          "--warmup", "30", "--draws", "30", "--out", str(root / name)])
    return root, rcs


def test_diagnose_a_saved_fit(saved_fits, tmp_path):
    """`diagnose FITDIR` reads the fit's model, legs, trials and data, and ranks; a bad effect name is an error."""
    root, rcs = saved_fits
    fitdir = root / "base"
    assert rcs["base"] in (0, 3)  # 30 draws may fail the checks, but the fit is saved
    assert json.loads((fitdir / "summary.json").read_text())["data"] == str((root / "data").resolve())
    out = tmp_path / "diag"
    assert main(["--quiet", "diagnose", str(fitdir), "--effects", "potentiation,fatigue", "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["model"] == "model3s" and s["verdict"] == "potentiation"
    assert [r["effect"] for r in s["ranking"]] == ["potentiation", "fatigue"]
    assert main(["--quiet", "diagnose", str(fitdir), "--effects", "telepathy", "--out", str(tmp_path / "x")]) == 2


def test_compare_before_and_after(saved_fits, tmp_path):
    """`compare A B`: J bands side by side, ΔELPD in B's favour, and each fit's residual figures;
    the baseline's residual trend over the preceding interpulse interval is what potentiation removes."""
    root, rcs = saved_fits
    assert rcs["pot"] in (0, 3)
    out = tmp_path / "cmp"
    assert main(["--quiet", "compare", str(root / "base"), str(root / "pot"), "--draws", "20",
                 "--start-stride", "20", "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert set(s["J"]) == {"model3s", "model3s+potentiation"}
    (group,) = s["loo"]["compare"]
    assert group["table"]["model3s+potentiation"]["rank"] == 0
    before, after = s["residual_findings"]["model3s"][LEG], s["residual_findings"]["model3s+potentiation"][LEG]
    assert any("interpulse" in line for line in before), before
    assert not any("interpulse" in line for line in after), after
    report = (out / "report.md").read_text()
    for label in ("model3s", "model3s_potentiation"):
        for kind in ("residual_trends", "residual_correlation", "twitch_average"):
            png = out / "figures" / f"{kind}_{label}_{LEG}.png"
            assert png.stat().st_size > 5000 and png.name in report
