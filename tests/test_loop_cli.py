"""The modelling loop on the command line: `discover --confirm`, `diagnose` of a saved fit, `compare`.

Data with hidden potentiation (JM-left, 1 min of trial 1); the two short NUTS fits
made by `discover --confirm` (the start model, and round 1's leader confirmed
against it) serve `diagnose` and `compare`.
"""

import contextlib
import io
import json

import numpy as np
import pytest

from quadshank.cli import main
from quadshank.data._interchange import write_interchange
from quadshank.data._simulate import simulate_cohort

LEG = "JM-left"


def _cohort(effect):
    # the loop tests' seed (loop_cases.py): the swings stay short of the simulated knee's range; equal
    # twitches, so that the loop's first round is the hidden effect (twitches that vary add the noise
    # term first: test_loop_variability.py)
    cohort, _ = simulate_cohort(legs=[LEG], minutes=1.0, seed=4, trials=(1,), effects=[effect], twitch_cv=0.0)
    return cohort


@pytest.fixture(scope="module")
def discovered(tmp_path_factory):
    """`discover --confirm` on data with hidden potentiation, screening it and the user-written
    effect of conftest.py; round 1's leader confirmed by NUTS against a NUTS fit of the start model."""
    root = tmp_path_factory.mktemp("discover")
    write_interchange(_cohort("potentiation"), root / "data")
    out = root / "discover"
    with contextlib.redirect_stderr(io.StringIO()) as err:  # the progress bars, to check what they say
        rc = main(["discover", str(root / "data"), "--effects", "potentiation,cubic_torque_angle",
                   "--max-rounds", "2", "--confirm", "--target-ess", "0", "--chains", "1", "--warmup", "30", "--draws", "30",
                   "--out", str(out)])
    return root, out, rc, err.getvalue()


def test_discover_confirms_with_fits_drawn_to_a_target_ess():
    """`discover --confirm` draws each NUTS fit in blocks to an ESS target (R-hat and ESS checked) by
    default; `--target-ess 0` gives the fixed lengths, and the user's lengths are kept either way."""
    from quadshank.cli import CONFIRM_FIXED_LENGTHS, CONFIRM_TARGET_ESS, TARGET_LENGTHS, build_parser, confirm_settings
    from quadshank.inference import FitSettings

    def settings(*extra):
        return confirm_settings(build_parser().parse_args(["discover", "data", "--out", "o", *extra]), (1,))

    assert settings() is None  # without --confirm, no NUTS fit
    s = settings("--confirm")
    assert (s.target_ess, s.warmup, s.draws, s.time_limit_s) == (CONFIRM_TARGET_ESS, *TARGET_LENGTHS, 1800.0)
    assert s.target_accept == FitSettings.target_accept
    assert settings("--confirm", "--target-accept", "0.97").target_accept == 0.97
    with pytest.raises(ValueError, match="target_accept .*must lie between 0 and 1"):
        settings("--confirm", "--target-accept", "1.5")
    s = settings("--confirm", "--target-ess", "0")
    assert s.target_ess is None and (s.warmup, s.draws) == CONFIRM_FIXED_LENGTHS
    s = settings("--confirm", "--target-ess", "250", "--time-limit", "60", "--warmup", "50", "--draws", "40", "--chains", "3")
    assert (s.target_ess, s.time_limit_s, s.warmup, s.draws, s.chains) == (250, 60.0, 50, 40, 3)
    with pytest.raises(ValueError, match="--target-ess must be at least 0"):
        settings("--confirm", "--target-ess", "-1")


def test_discover_on_the_command_line_with_a_user_effect(discovered):
    """The whole loop in one command; the user-written effect is screened like the others; NUTS confirms."""
    root, out, rc, progress = discovered
    s = json.loads((out / "summary.json").read_text())
    assert rc == (0 if s["nuts_fits_ok"] else 3)  # the fixture's NUTS fits are short: they may fail their checks
    # the progress line says which round and which candidate the loop is on
    assert "round 1 of at most 2: screening effects" in progress and "model3s + cubic_torque_angle" in progress
    assert "round 2 of at most 2: screening effects" in progress
    s = json.loads((out / "summary.json").read_text())
    assert s["added"] == ["potentiation"]
    assert s["final_model"] == "model3s+potentiation"
    r1 = json.loads((out / "round-1" / "summary.json").read_text())
    cubic = next(r for r in r1["ranking"] if r["effect"] == "cubic_torque_angle")
    assert np.isfinite(cubic["delta_elpd"]) and not cubic["clears_bar"]
    assert "Adding potentiation improves ELPD" in (out / "round-1" / "report.md").read_text()
    assert len(s["rounds"]) == 2 and s["rounds"][1]["verdict"] == "none"
    assert s["stopped"] == "no candidate cleared the bar" and "round limit" not in (out / "report.md").read_text()
    for name in r1["figures"]:
        assert (out / "round-1" / name).stat().st_size > 5000
    for name in ("predictions_one_step_baseline_JM-left.png", "predictions_1s_baseline_JM-left.png", "loo_pit_baseline.png",
                 "elpd_in_time_baseline.png", "residual_spectrum_baseline_JM-left.png"):
        assert name in r1["figures"]
    checks = r1["predictive_checks"]
    assert checks["loo_pit"][LEG]["n"] > 1000  # one PIT per likelihood window
    np.testing.assert_allclose(checks["elpd_total"][LEG], r1["elpd"]["value"], rtol=1e-9)
    worst = checks["worst_seconds"][LEG]
    assert [r["elpd"] for r in worst] == sorted(r["elpd"] for r in worst) and all(0 <= r["start_s"] < 60 for r in worst)
    assert "Predictive checks of the baseline" in (out / "round-1" / "report.md").read_text()
    # round 1's leader is refitted with NUTS against the start model's fit before it is added
    assert r1["screen_verdict"] == r1["verdict"] == "potentiation"
    nuts = next(r for r in r1["ranking"] if r["effect"] == "potentiation")["nuts"]
    assert nuts["clears_bar"] and nuts["delta_elpd"] > 2 * nuts["delta_elpd_se"] > 0
    assert nuts["J_1000ms"]["after"]["hi"] < nuts["J_1000ms"]["before"]["lo"]
    assert "nuts" not in cubic  # only leaders that clear the screen's bar are refitted
    confirms = "NUTS confirms potentiation" if r1["nuts_fits_ok"] else "NUTS would confirm potentiation"
    assert confirms in r1["sentence"] and s["nuts_fits_ok"] == (r1["nuts_fits_ok"] and s["confirm"]["start"]["diagnostics"]["ok"])
    assert "Confirmed with hierarchical NUTS" in (out / "round-1" / "report.md").read_text()
    c = s["confirm"]
    assert c["start"]["model"] == "model3s" and c["final"]["model"] == "model3s+potentiation"
    assert c["final"]["folder"] == "round-1/confirm/fit-potentiation"
    assert s["rounds"][0]["screen_verdict"] == "potentiation"
    assert c["elpd_diff"] > 0  # the final model ranks first under NUTS too
    assert "NUTS: model3s+potentiation against model3s" in (out / "report.md").read_text()
    assert (out / "confirm" / "compare" / "summary.json").exists()


def test_diagnose_a_saved_fit(discovered, tmp_path, scratch_registry):
    """`diagnose FITDIR` reads the fit's model, legs, trials and data, and ranks; a candidate whose
    screen fails (a user's effect with a bug) is reported and left out, and the others are ranked;
    with `--confirm` the leader is refitted with NUTS with the saved fit's settings and judged there
    (the same data, settings and seed give what discover's round 1 found); a bad effect name or
    number of leaders is an error."""
    import dataclasses

    import jax.numpy as jnp

    from quadshank import Effect, Param, register_effect

    @register_effect
    @dataclasses.dataclass(frozen=True)
    class BrokenGain(Effect):
        kind = "gain"
        name = "broken_gain"
        params = (Param("g", "1", prior=("normal", 0.0, 1.0)),)
        g: float = 0.0

        def factor(self, ctx):
            return jnp.log(-1.0 - self.g**2) * ctx.angle  # NaN everywhere: no finite density

    root, out, _, _ = discovered
    fitdir = out / "confirm" / "fit-start"
    assert json.loads((fitdir / "summary.json").read_text())["data"] == str((root / "data").resolve())
    diag = tmp_path / "diag"
    with pytest.warns(RuntimeWarning, match="broken_gain failed"):
        rc = main(["--quiet", "diagnose", str(fitdir), "--effects", "broken_gain,potentiation", "--confirm",
                   "--out", str(diag)])
    s = json.loads((diag / "summary.json").read_text())
    assert rc == (0 if s["nuts_fits_ok"] else 3)
    assert s["model"] == "model3s" and s["verdict"] == s["screen_verdict"] == "potentiation"
    assert [r["effect"] for r in s["ranking"]] == ["potentiation"]
    assert [f["effect"] for f in s["failed"]] == ["broken_gain"] and "finite" in s["failed"][0]["error"]
    assert "Candidates that could not be screened" in (diag / "report.md").read_text()
    bb = s["blackbox"]  # the yardstick beside the baseline, on its legs, trials and horizons
    assert set(bb["J_ms"]) == {"100", "250", "500", "1000"} and set(bb["orders"]) == set(s["legs"])
    assert bb["better_at_ms"] == [h for h, v in bb["J_ms"].items() if v < s["J_ms"][h]["median"]]
    assert ("A black box" in s["sentence"]) == bool(bb["better_at_ms"])

    nuts = s["ranking"][0]["nuts"]
    fit = json.loads((diag / "confirm" / "fit-potentiation" / "summary.json").read_text())
    start = json.loads((fitdir / "summary.json").read_text())
    assert fit["model"] == "model3s+potentiation" and fit["settings"] == start["settings"]
    assert fit["data"] == start["data"]
    r1 = json.loads((out / "round-1" / "summary.json").read_text())
    in_discover = next(r for r in r1["ranking"] if r["effect"] == "potentiation")["nuts"]
    np.testing.assert_allclose(nuts["delta_elpd"], in_discover["delta_elpd"], rtol=1e-6)
    assert nuts["clears_bar"] and s["nuts_fits_ok"] == nuts["diagnostics"]["ok"]
    assert ("NUTS confirms potentiation" if nuts["diagnostics"]["ok"] else "NUTS would confirm potentiation") in s["sentence"]

    assert main(["--quiet", "diagnose", str(fitdir), "--effects", "telepathy", "--out", str(tmp_path / "x")]) == 2
    assert main(["--quiet", "diagnose", str(fitdir), "--confirm", "-1", "--out", str(tmp_path / "y")]) == 2


def test_compare_before_and_after(discovered, tmp_path):
    """`compare A B`: J bands side by side, ΔELPD in B's favour, and each fit's residual figures and
    findings; the baseline's residual trends over the preceding interpulse interval."""
    _, out, _, _ = discovered
    cmp = tmp_path / "cmp"
    final = out / json.loads((out / "summary.json").read_text())["confirm"]["final"]["folder"]
    assert main(["--quiet", "compare", str(out / "confirm" / "fit-start"), str(final),
                 "--draws", "20", "--start-stride", "20", "--out", str(cmp)]) == 0
    s = json.loads((cmp / "summary.json").read_text())
    assert set(s["J"]) == {"model3s", "model3s+potentiation"}
    (group,) = s["loo"]["compare"]
    assert group["table"]["model3s+potentiation"]["rank"] == 0
    before = s["residual_findings"]["model3s"][LEG]
    assert any("interpulse" in line for line in before), before  # the signature of the missing effect
    assert set(s["residual_findings"]["model3s+potentiation"]) == {LEG}
    left = s["unexplained"]  # the trend over the interpulse interval falls once potentiation is in
    assert set(left["model3s"]["screened"]) == set(left["model3s+potentiation"]["screened"]) >= {"ipi", "angle"}
    assert left["model3s+potentiation"]["screened"]["ipi"]["chi2"] < left["model3s"]["screened"]["ipi"]["chi2"]
    report = (cmp / "report.md").read_text()
    for label in ("model3s", "model3s_potentiation"):
        for kind in ("residual_trends", "residual_correlation", "twitch_average"):
            png = cmp / "figures" / f"{kind}_{label}_{LEG}.png"
            assert png.stat().st_size > 5000 and png.name in report


def test_the_screens_starts_are_an_option_of_discover(tmp_path, monkeypatch, capsys):
    """``--starts N`` reaches the loop (default: one prior draw besides the median); a negative
    number is refused before any work."""
    import quadshank.cli as cli
    from quadshank.loop._diagnose import SCREEN_STARTS

    seen = []

    def run_discover(*args, **kwargs):
        seen.append(kwargs["n_starts"])
        raise ValueError("stopped before the loop")

    monkeypatch.setattr(cli, "run_discover", run_discover)
    cohort, _ = simulate_cohort(legs=[LEG], minutes=0.1, seed=1, trials=(1,))
    write_interchange(cohort, tmp_path / "data")
    args = ["discover", str(tmp_path / "data"), "--out", str(tmp_path / "out")]
    assert main(args) != 0 and main([*args, "--starts", "3"]) != 0
    assert seen == [SCREEN_STARTS, 3] and SCREEN_STARTS == 1
    assert main([*args, "--starts", "-1"]) != 0 and len(seen) == 2
    assert "--starts must be at least 0" in capsys.readouterr().err
