"""`quadshank report`: per-subject HTML pages, cohort index, credible parameters as CSV and JSON.

One tiny fit (model 3, two subjects' legs, 30 s of trial 1, one chain) is far
too short to pass its checks, which is what the warning needs.  A copy of it
whose summary says it passed, with a delay–angle summary put into it, is
reported with a hand-made evaluation and diagnosis, so every section of the
page is drawn.  The pages are opened in headless Chromium (Debian's package,
installed by ``make test``): every figure must decode.
"""

import csv
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

import quadshank.commands.report as report_command
import quadshank.outputs._report as report
from quadshank.cli import main
from quadshank.evaluation import PosteriorEvaluation
from quadshank.loop import Diagnosis, Discovery
from quadshank.inference._summaries import INTERVAL
from quadshank.inference._fitio import load_fit

LEGS = ("TN-left", "JM-left")
CHROMIUM = Path("/usr/bin/chromium")
SNEAKY = "<script>alert('x')</script> & more"


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    root = tmp_path_factory.mktemp("report")
    data, fit = root / "data", root / "fit"
    assert main(["-q", "simulate", "--out", str(data), "--minutes", "0.5", "--legs", ",".join(LEGS),
                 "--trials", "1"]) == 0
    assert main(["-q", "fit", str(data), "--model", "model3", "--chains", "1", "--warmup", "40", "--draws", "40",
                 "--out", str(fit)]) == 3  # one chain: the fit fails its checks
    out = root / "report"
    assert main(["-q", "report", str(fit), "--out", str(out), "--draws", "10", "--start-stride", "20"]) == 0
    return {"root": root, "data": data, "fit": fit, "out": out}


@pytest.fixture(scope="module")
def passing(made):
    """A copy of the fit whose summary passes its checks and has an angle-dependent delay, reported with an
    evaluation's J and a diagnosis ranking given by hand."""
    root = made["root"]
    fit = root / "fit-ok"
    shutil.copytree(made["fit"], fit)
    s = json.loads((fit / "summary.json").read_text())
    s["diagnostics"].update(ok=True, problems=[], advice=[])
    s["banner"] = None
    grid = list(range(-40, 61))
    for k, leg in enumerate(LEGS):
        curve = [4.0 - (a < -20) for a in grid]
        s["legs"][leg]["delay_angle"] = {
            "change_probability": 0.9, "shift_posterior": [0.1, 0.8, 0.1], "pulse_angle_range_deg": [-35.0, 40.0],
            "threshold_deg": {"median": -20.0, "lo": -22.0, "hi": -18.0}, "angle_deg": grid,
            "median": curve, "lo": [c - 0.5 for c in curve], "hi": curve,
        }
    s["delay_angle_population"] = {"angle_deg": grid, "median": [4.0] * len(grid), "lo": [3.0] * len(grid),
                                   "hi": [4.0] * len(grid)}
    (fit / "summary.json").write_text(json.dumps(s))

    evaluation = root / "eval"
    evaluation.mkdir()
    band = lambda m: {"median": m, "lo": m - 0.25, "hi": m + 0.5}  # noqa: E731
    j_legs = {leg: {"1": {h: band(1.0 + k + int(h) / 1000) for h in ("100", "250", "500", "1000")}}
              for k, leg in enumerate(LEGS)}
    PosteriorEvaluation(
        method="posterior", J={"model3": {"1": {h: band(2.0) for h in ("100", "250", "500", "1000")}}},
        J_legs={"model3": j_legs}, sign_tests=[], loo={"fits": {}, "compare": [], "not_compared": []},
        fits={"model3": {"folder": str(fit), "draws_used": 7}}, legs=list(LEGS), horizons_samples=[10, 25, 50, 100],
        interval=[0.05, 0.95], n_draws=7, start_stride=3, seed=0, evaluation_seconds=0.0,
    ).write(evaluation)
    diagnosis = root / "diag"
    diagnosis.mkdir()
    row = lambda effect, d, clears: {  # noqa: E731
        "effect": effect, "delta_elpd": d, "delta_elpd_se": 2.0, "clears_bar": clears,
        "J_500ms": {"before": band(5.0), "after": band(4.0)}, "J_1000ms": {"before": band(7.0), "after": band(6.0)},
    }
    Diagnosis(
        model="model3", legs=list(LEGS), elpd={"value": 0.0, "se": 1.0}, J_ms={}, verdict="potentiation", bar={},
        sentence=SNEAKY, trials=[1], ranking=[row("potentiation", 41.5, True), row("fatigue_of_sorts", 1.5, False)],
    ).write(diagnosis)
    out = root / "report-ok"
    out.mkdir()
    # an earlier report's summary: removed first, written anew last
    (out / "summary.json").write_text('{"schema": "quadshank/report", "schema_version": 1}')
    assert main(["-q", "report", str(fit), "--out", str(out), "--evaluation", str(evaluation),
                 "--diagnosis", str(diagnosis), "--draws", "5"]) == 0
    return {"fit": fit, "out": out, "j_legs": j_legs}


def _pages(out: Path) -> list[Path]:
    s = json.loads((out / "summary.json").read_text())
    return [out / p for p in s["pages"].values()]


def _leg_sections(page: str) -> dict[str, str]:
    """HTML of each leg's section of a subject page (up to the next h2)."""
    parts = re.split(r'(?=<h2 id=")', page)
    return {m.group(1): part for part in parts if (m := re.match(r'<h2 id="leg-([^"]+)">', part))}


def test_every_leg_page_lists_every_parameter_with_units(made):
    out = made["out"]
    summary = json.loads((out / "summary.json").read_text())
    _, _, desc = load_fit(made["fit"])
    expected = {name: info["units"] for name, info in {**desc["params"], **desc["noise"]}.items()}
    assert len(expected) == 9  # model 3: 7 parameters, sigma and nu
    assert set(summary["legs"]) == set(LEGS)
    seen = set()
    for leg, info in summary["legs"].items():
        page = (out / info["page"]).read_text()
        section = _leg_sections(page)[leg]
        for name, units in expected.items():
            row = re.search(rf"<tr><td><code>{re.escape(name)}</code></td><td>([^<]*)</td>(.*?)</tr>", section)
            assert row, (leg, name)
            assert row.group(1) == units, (leg, name)
            cells = re.findall(r'<td class="num">(.*?)</td>', row.group(2))
            assert len(cells) == 3 and re.match(r"-?[0-9]", cells[0]), (leg, name, cells)  # leg, subject, population
            hierarchical = name in desc["params"]
            assert all(c != "–" for c in cells) == hierarchical, (leg, name, cells)
        seen.add(leg)
    assert seen == set(LEGS)
    assert summary["pages"] == {"index": "index.html", "subject TN": "subject-TN.html", "subject JM": "subject-JM.html"}
    for f in summary["files"]:
        assert (out / f).is_file(), f
    index = (out / "index.html").read_text()
    for leg, info in summary["legs"].items():
        assert f'href="{info["page"]}#leg-{leg}"' in index


def test_csv_and_json_hold_the_fit_summary_numbers_and_the_levels(made):
    out = made["out"]
    fs = json.loads((made["fit"] / "summary.json").read_text())
    idata, _, desc = load_fit(made["fit"])
    post = idata.posterior
    for i, leg in enumerate(LEGS):
        rows = {r["parameter"]: r for r in csv.DictReader((out / "legs" / f"{leg}.csv").open())}
        doc = json.loads((out / "legs" / f"{leg}.json").read_text())
        assert set(rows) == set(fs["legs"][leg]["params"]) == set(doc["params"])
        assert doc["delay_posterior"] == fs["legs"][leg]["delay_posterior"]
        assert doc["subject"] == leg.split("-")[0] and doc["diagnostics_ok"] is False
        subject = desc["subjects"].index(doc["subject"])
        for name, q in fs["legs"][leg]["params"].items():
            for k in ("median", "lo", "hi"):
                assert float(rows[name][f"leg_{k}"]) == q[k] == doc["params"][name]["leg"][k], (leg, name, k)
            assert rows[name]["units"] == q["units"] == doc["params"][name]["units"]
            if name in ("sigma", "nu"):
                assert rows[name]["subject_median"] == rows[name]["population_median"] == ""
                assert doc["params"][name]["subject"] is None and doc["params"][name]["population"] is None
                continue
            # the subject and population levels, summarised from fit.nc another way
            for level, draws in (("subject", post[f"{name}_subject"].values[..., subject]),
                                 ("population", post[f"{name}_mu"].values)):
                lo, hi = np.quantile(draws.ravel(), INTERVAL)
                want = {"median": np.median(draws), "lo": lo, "hi": hi}
                for k in ("median", "lo", "hi"):
                    assert float(rows[name][f"{level}_{k}"]) == pytest.approx(want[k], rel=1e-9), (leg, name, level)
                    assert doc["params"][name][level][k] == float(rows[name][f"{level}_{k}"])
                assert doc["params"][name][level]["lo"] <= doc["params"][name][level]["median"] <= doc["params"][name][level]["hi"]
        # J computed here, per trial and horizon, with a band
        assert set(doc["J"]["1"]) == {"100", "250", "500", "1000"}
        assert all(v["lo"] <= v["median"] <= v["hi"] for v in doc["J"]["1"].values())


def test_a_failing_fit_is_flagged_on_every_page_and_a_passing_one_is_not(made, passing):
    problems = json.loads((made["fit"] / "summary.json").read_text())["diagnostics"]["problems"]
    assert problems
    for page in _pages(made["out"]):
        text = page.read_text()
        assert 'class="warning" id="fit-warning"' in text, page.name
        assert text.index('id="fit-warning"') < text.index("<h2"), page.name  # at the top
        for p in problems:
            assert report._e(p) in text, (page.name, p)
        assert "FAIL" in text
    for page in _pages(passing["out"]):
        text = page.read_text()
        assert 'id="fit-warning"' not in text, page.name
        assert "the fit passed its checks" in text


def test_evaluation_diagnosis_and_delay_angle_are_shown(passing):
    out = passing["out"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["J_source"] == "evaluation" and summary["diagnostics_ok"] is True
    for leg in LEGS:
        doc = json.loads((out / "legs" / f"{leg}.json").read_text())
        assert doc["J"] == passing["j_legs"][leg]
        assert doc["delay_angle"]["change_probability"] == 0.9
    for page in _pages(out):
        text = page.read_text()
        assert "7 posterior draws" in text
        assert "Verdict: potentiation." in text and "fatigue_of_sorts" in text
        assert "41.5 ± 2" in text
        assert "&lt;script&gt;alert(&#x27;x&#x27;)&lt;/script&gt; &amp; more" in text
        assert "<script>alert" not in text
        assert "&lt;span" not in text  # the page's own markup is not escaped twice
    tn = (out / "subject-TN.html").read_text()
    assert "P(the delay changes with angle) = 0.90" in tn and 'id="delay-angle"' in tn
    assert summary["figures"]["subject-TN.html"] == 5  # shrinkage, P(d), delay-angle, J, predictions
    assert summary["figures"]["index.html"] == 2  # Table V, pooled delay-angle
    assert "1.1 <span" in tn  # J of TN-left at 100 ms from the evaluation: 1.0 + 0.1


def _strict_json(path: Path):
    return json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"{path}: {c} is not JSON"))


def test_numbers_that_are_not_finite_are_null_and_the_report_reads_them(made, passing):
    """JSON has no NaN: the one-chain fit's R-hat is null in its summary, and an evaluation
    whose band came out not finite (an unstable draw) is written with null and reported
    with "–" in its place, in strict JSON throughout."""
    fit = _strict_json(made["fit"] / "summary.json")
    assert fit["diagnostics"]["rhat_max"] is None and fit["diagnostics"]["chains"] == 1
    root = made["root"]
    evaluation = root / "eval-nan"
    shutil.copytree(passing["out"].parent / "eval", evaluation)
    doc = _strict_json(evaluation / "summary.json")
    leg = LEGS[0]
    band = doc["J_legs"]["model3"][leg]["1"]["100"]
    band.update(median=float("nan"), hi=float("inf"))
    PosteriorEvaluation.from_json(doc).write(evaluation)
    written = _strict_json(evaluation / "summary.json")["J_legs"]["model3"][leg]["1"]["100"]
    assert written["median"] is None and written["hi"] is None and written["lo"] == band["lo"]
    out = root / "report-nan"
    assert main(["-q", "report", str(passing["fit"]), "--out", str(out), "--evaluation", str(evaluation),
                 "--draws", "5"]) == 0
    legs_json = _strict_json(out / "legs" / f"{leg}.json")
    assert legs_json["J"]["1"]["100"]["median"] is None
    assert legs_json["J"]["1"]["250"] == passing["j_legs"][leg]["1"]["250"]
    _strict_json(out / "summary.json")
    assert "– <span" in (out / "subject-TN.html").read_text()


def test_missing_folders_and_unusable_inputs_are_plain_errors(made, capsys):
    root = made["root"]
    assert main(["report", str(root / "no-such-fit"), "--out", str(root / "r1")]) == 2
    assert "no complete fit" in capsys.readouterr().err
    bad = root / "bad-eval"
    bad.mkdir()
    PosteriorEvaluation(method="posterior", J={}, J_legs={"model1": {}}, sign_tests=[], loo={}, fits={}, legs=[],
                        horizons_samples=[], interval=[0.05, 0.95], n_draws=1, start_stride=1, seed=0,
                        evaluation_seconds=0.0).write(bad)
    assert main(["report", str(made["fit"]), "--out", str(root / "r2"), "--evaluation", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("quadshank: error:") and "no fit of 'model3'" in err
    assert main(["report", str(made["fit"]), "--out", str(root / "r3"), "--diagnosis", str(root / "nothing")]) == 2
    assert "summary.json: file not found" in capsys.readouterr().err


def test_an_interrupted_report_leaves_no_summary(made, passing, monkeypatch):
    out = made["root"] / "interrupted"
    out.mkdir()
    (out / "summary.json").write_text("{}")

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(report, "plot_shrinkage", boom)
    with pytest.raises(KeyboardInterrupt):
        report_command.run_report(passing["fit"], out, evaluation=passing["out"].parent / "eval")
    assert not (out / "summary.json").exists()


def _chromium(*args: str, profile: Path) -> subprocess.CompletedProcess:
    if not CHROMIUM.exists():
        pytest.fail(f"{CHROMIUM} is missing: the report test opens the pages in headless Chromium; "
                    "`make test` installs it (Debian package `chromium`)")
    cmd = [str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           f"--user-data-dir={profile}", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


def test_every_page_renders_in_a_headless_browser_with_every_figure(made, passing, tmp_path):
    for out in (made["out"], passing["out"]):
        summary = json.loads((out / "summary.json").read_text())
        for name, page in summary["pages"].items():
            path = out / page
            html_text = path.read_text()
            # self-contained: nothing fetched
            assert not re.search(r'<link|src="(?!data:image/png;base64,)', html_text), page
            r = _chromium("--virtual-time-budget=10000", "--dump-dom", path.as_uri(), profile=tmp_path / "profile")
            body = re.search(r"<body([^>]*)>", r.stdout)
            assert body, (page, r.stderr[-2000:])
            total = re.search(r'data-figures="(\d+)"', body.group(1))
            loaded = re.search(r'data-figures-loaded="(\d+)"', body.group(1))
            assert total and loaded, (page, body.group(0))
            assert int(loaded.group(1)) == int(total.group(1)) >= summary["figures"][page] >= 1, (page, body.group(0))
            shot = tmp_path / f"{out.name}-{path.stem}.png"
            _chromium(f"--screenshot={shot}", "--window-size=1200,1600", "--hide-scrollbars", path.as_uri(),
                      profile=tmp_path / "profile")
            assert shot.exists() and shot.stat().st_size > 40_000, (page, shot.stat().st_size if shot.exists() else None)
        expected = {"index.html": 1, "subject-TN.html": 4, "subject-JM.html": 4}
        for page, n in expected.items():
            assert summary["figures"][page] >= n


def test_a_discover_folder_shows_the_ranking_of_each_round(tmp_path):
    rank = lambda effect: {"effect": effect, "delta_elpd": 30.0, "delta_elpd_se": 3.0, "clears_bar": True}  # noqa: E731
    rounds = [{"model": "model3s", "verdict": "fatigue", "sentence": "add fatigue"},
              {"model": "model3s+fatigue", "verdict": "none", "sentence": "nothing more"}]
    Discovery(model="model3s", final_model="model3s+fatigue", rounds=rounds, added=["fatigue"]).write(tmp_path)
    for k, (r, effect) in enumerate(zip(rounds, ("fatigue", "hill_velocity")), 1):
        (tmp_path / f"round-{k}").mkdir()
        Diagnosis(**r, legs=["TN-left"], elpd={}, J_ms={}, bar={}, trials=[1], ranking=[rank(effect)]).write(tmp_path / f"round-{k}")
    section = report._diagnosis_section(report_command._read_diagnosis(tmp_path, "model3"))
    assert "<h3>round 1</h3>" in section and "<h3>round 2</h3>" in section
    assert "fatigue" in section and "hill_velocity" in section and "model3s+fatigue" in section
    assert "this fit is of model3" in section  # the loop screened another model than this fit's
    (tmp_path / "summary.json").write_text(json.dumps({"something": "else"}))
    with pytest.raises(ValueError, match="not an output of `quadshank diagnose`"):
        report_command._read_diagnosis(tmp_path, "model3")


def test_the_diagnostics_table_shows_the_delay_checks_and_omits_them_for_older_fits():
    """Split chains (FAIL) and delays the evidence weighs but no chain visited (a warning) are rows of
    the checks table, naming the legs and delays; the warnings follow the table; a fit saved before
    these checks existed shows no such rows."""
    base = {"rhat_max": 1.0, "ess_bulk_min": 900.0, "ess_tail_min": 900.0, "divergences": 0, "bfmi_min": 0.9,
            "ok": True, "chains": 2, "draws": 500, "thresholds": {"rhat_max": 1.01, "ess_min": 200, "bfmi_min": 0.3}}
    failing = report._diagnostics_section({
        **base, "ok": False, "delay_splits": {"TN-left": [4, 5]}, "delay_missed": {"JM-left": {"4": [0.25, 0.0]}},
        "warnings": ["JM-left & d = 4 never visited"]})
    row_split = failing[failing.index("settled at different delays"):]
    row_split = row_split[: row_split.index("</tr>")]
    assert "TN-left" in row_split and "FAIL" in row_split
    row_missed = failing[failing.index("no chain visited"):]
    row_missed = row_missed[: row_missed.index("</tr>")]
    assert "JM-left: d = 4" in row_missed and "look" in row_missed and "FAIL" not in row_missed  # a warning
    assert "Warning: JM-left &amp; d = 4 never visited" in failing
    worst = report._diagnostics_section({**base, "ok": False, "rhat_max": 1.2, "worst": {
        "rhat": {"variable": "gain", "at": "TN-left", "value": 1.2}, "ess_bulk": None, "ess_tail": None}})
    row_rhat = worst[worst.index("R-hat, largest"):]
    assert "1.2 (gain, TN-left)" in row_rhat[: row_rhat.index("</tr>")]
    passing = report._diagnostics_section({**base, "delay_splits": {}, "delay_missed": {}})
    assert "no chain visited" in passing and "FAIL" not in passing
    older = report._diagnostics_section(base)
    assert "settled at different delays" not in older and "no chain visited" not in older and "(gain" not in older


def test_a_report_refuses_mixed_fit_files_other_data_and_another_fits_evaluation(made, passing, capsys):
    root = made["root"]
    mixed = root / "mixed"
    shutil.copytree(made["fit"], mixed)
    s = json.loads((mixed / "summary.json").read_text())
    s["fit_id"] = "0" * 16  # a summary.json from another fit beside this fit.nc
    (mixed / "summary.json").write_text(json.dumps(s))
    capsys.readouterr()
    assert main(["-q", "report", str(mixed), "--out", str(root / "r-mixed")]) == 2
    assert "different fits" in capsys.readouterr().err
    assert not (root / "r-mixed" / "summary.json").exists()

    renamed = root / "renamed"  # a summary.json whose legs were edited
    shutil.copytree(made["fit"], renamed)
    s = json.loads((renamed / "summary.json").read_text())
    first = next(iter(s["legs"]))
    s["legs"] = {("P01" if leg == first else leg): v for leg, v in s["legs"].items()}
    (renamed / "summary.json").write_text(json.dumps(s))
    assert main(["-q", "report", str(renamed), "--out", str(root / "r-renamed")]) == 2
    err = capsys.readouterr().err
    assert "summary.json and fit.nc name different legs" in err and "P01" in err and first in err

    other = root / "other-data"  # the same legs, other recordings
    assert main(["-q", "simulate", "--out", str(other), "--minutes", "0.5", "--legs", ",".join(LEGS),
                 "--trials", "1", "--seed", "1"]) == 0
    capsys.readouterr()
    assert main(["-q", "report", str(made["fit"]), "--data", str(other), "--out", str(root / "r-other")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("quadshank: error:") and "not the data the fit" in err.splitlines()[0]

    evaluation = root / "eval-other"
    shutil.copytree(passing["out"].parent / "eval", evaluation)
    e = json.loads((evaluation / "summary.json").read_text())
    e["fits"]["model3"]["fit_id"] = "f" * 16
    (evaluation / "summary.json").write_text(json.dumps(e))
    assert main(["-q", "report", str(made["fit"]), "--evaluation", str(evaluation), "--out", str(root / "r-eval")]) == 2
    assert "another fit" in capsys.readouterr().err


def test_predict_rolls_the_posterior_through_a_plan_as_evaluate_does(made, capsys):
    from quadshank.data import load_cohort
    from quadshank.evaluation import plan_predictions, posterior_predictions
    from quadshank.inference import posterior_models

    idata, model, _ = load_fit(made["fit"])
    trial = load_cohort(made["data"]).get("TN-left", 1)
    pulses = np.flatnonzero(trial.stimulation > 0)
    # a start with the muscle at rest: no pulse in the 80 samples before it
    s0 = next(p - 1 for p, q in zip(pulses[1:], pulses[:-1]) if p - q > 81)
    H = 150
    models, _ = posterior_models(idata, model, "TN-left", 8, 0)
    free = plan_predictions(models, trial.stimulation[s0:s0 + H], trial.angle_deg[s0], trial.velocity_deg_s[s0])
    ahead = posterior_predictions(models, trial, np.array([s0]), (1, 50, H - 1))[:, 0, :]
    np.testing.assert_allclose(free[:, [1, 50, H - 1]], ahead, rtol=1e-4, atol=1e-3)

    plan = made["root"] / "plan.csv"
    t = np.arange(300) * trial.sampling_period_s
    u = np.where(np.arange(300) % 50 == 10, 0.8, 0.0)
    plan.write_text("time_s,stimulation\n" + "".join(f"{float(a)!r},{float(b)!r}\n" for a, b in zip(t, u)))
    out = made["root"] / "predict"
    capsys.readouterr()
    assert main(["predict", str(made["fit"]), "--stimulation", str(plan), "--angle0", "-5", "--draws", "8",
                 "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "TN-left: from -5° the angle ranges over" in err
    assert f"quadshank: warning: {made['fit']}: FIT FAILED ITS CHECKS" in err  # one chain: its bands are not to be trusted
    rows = list(csv.reader((out / "predictions.csv").open()))
    assert rows[0][:2] == ["time_s", "stimulation"] and "JM-left median [deg]" in rows[0]
    assert len(rows) == 301 and float(rows[1][rows[0].index("TN-left median [deg]")]) == pytest.approx(-5.0, abs=1e-3)
    s = json.loads((out / "summary.json").read_text())
    assert s["schema"] == "quadshank/prediction" and s["legs"] == list(LEGS) and s["samples"] == 300
    assert s["banner"].startswith("FIT FAILED ITS CHECKS")
    assert (out / "predictions.png").stat().st_size > 10_000
    lo = np.array([float(r[rows[0].index("TN-left lo [deg]")]) for r in rows[1:]])
    hi = np.array([float(r[rows[0].index("TN-left hi [deg]")]) for r in rows[1:]])
    assert np.all(lo <= hi) and np.ptp(hi) > 1.0  # the pulses move the shank
    seen = s["fitted_angle_range_deg"]["TN-left"]
    # the fitted trial 1, none of its samples excluded
    assert seen == pytest.approx([trial.angle_deg.min(), trial.angle_deg.max()], abs=1e-3)
    assert s["beyond_fitted_range"] == {}

    far = seen[1] + 60.0  # a start far beyond the fitted swings: warned of, not refused
    assert main(["predict", str(made["fit"]), "--stimulation", str(plan), "--angle0", str(far), "--draws", "8",
                 "--legs", "TN-left", "--out", str(made["root"] / "predict-far")]) == 0
    err = capsys.readouterr().err
    assert f"TN-left: the start at {far:.1f}°" in err and "beyond the angles the fit saw" in err
    s = json.loads((made["root"] / "predict-far" / "summary.json").read_text())
    assert s["beyond_fitted_range"]["TN-left"]["start"] == pytest.approx(far)

    bad = made["root"] / "bad-plan.csv"
    bad.write_text("time_s,stimulation\n0.0,0\n0.01,1.5\n0.02,0\n")
    assert main(["-q", "predict", str(made["fit"]), "--stimulation", str(bad), "--out", str(made["root"] / "p2")]) == 2
    err = capsys.readouterr().err
    assert "bad-plan.csv, column 'stimulation', row 3" in err.splitlines()[0]


def test_names_that_meet_as_file_names_keep_files_of_their_own():
    """Subjects whose names differ only in letters a file name cannot hold (Müller, Möller) or in
    case must not overwrite each other's page and leg files."""
    from quadshank.common._io import FILE_STEM_MAX, file_stems

    long = "S" * 300
    stems = file_stems(["Müller-left", "Möller-left", "MULLER-left", "患者-left", "患者-right", "A B-left",
                        "x/../../escaped-left", f"{long}-left", f"{long}-right"])
    assert stems["Müller-left"] == "Muller-left" and stems["Möller-left"] == "Moller-left"
    assert stems["MULLER-left"] == "MULLER-left-2"  # meets Muller-left on a case-insensitive file system
    assert stems["患者-left"] == "__-left" and stems["患者-right"] == "__-right" and stems["A B-left"] == "A_B-left"
    assert stems["x/../../escaped-left"] == "x_.._.._escaped-left"  # no path leaves the output folder
    assert len(stems[f"{long}-left"]) == FILE_STEM_MAX and stems[f"{long}-right"] == stems[f"{long}-left"] + "-2"
    assert len({v.lower() for v in stems.values()}) == len(stems)


def test_parameters_the_data_barely_inform_are_a_row_of_the_checks_and_marked_in_the_leg_table():
    """The fit's ``weakly_informed`` is a warning row naming legs and parameters (none: it passes; a
    fit saved before the check: no row), and a leg's table marks those parameters, a vector's
    component alone where only it is named; "prior only" (no pulses) takes precedence."""
    base = {"rhat_max": 1.0, "ess_bulk_min": 900.0, "ess_tail_min": 900.0, "divergences": 0, "bfmi_min": 0.9,
            "ok": True, "chains": 2, "draws": 500, "thresholds": {"rhat_max": 1.01, "ess_min": 200, "bfmi_min": 0.3}}
    weak = report._diagnostics_section({**base, "weakly_informed": {"AA-left": {"k1": 1.8, "a[2]": 0.7}}})
    row = weak[weak.index("barely inform"):]
    row = row[: row.index("</tr>")]
    assert "AA-left: k1, a[2]" in row and "look" in row and "FAIL" not in row
    assert "pass" in report._diagnostics_section({**base, "weakly_informed": {}}).split("barely inform")[1].split("</tr>")[0]
    assert "barely inform" not in report._diagnostics_section(base)

    unit = {"units": "", "leg": {"median": 1.0, "lo": 0.5, "hi": 2.0}, "subject": None, "population": None}
    rows = {"k1": unit, "k2": unit, "a[1]": unit, "a[2]": unit, "gain": unit}
    marked = {r[0]: r[2] for r in report._param_rows(rows, prior_only=("gain",), barely={"k1": 1.8, "a[2]": 0.7})}
    assert [k for k, v in marked.items() if "barely informed" in v] == ["<code>k1</code>", "<code>a[2]</code>"]
    assert "prior only" in marked["<code>gain</code>"] and "barely" not in marked["<code>gain</code>"]


def test_a_band_beyond_the_fitted_angles_is_named_where_its_median_is_not():
    """The extrapolation warning names the start, else the median prediction, else its band, each
    by the angle furthest out; within the range (and its 10° margin) nothing is named."""
    from quadshank.commands.predict import _beyond

    band = {"median": np.array([0.0, 5.0]), "lo": np.array([-1.0, 2.0]), "hi": np.array([1.0, 40.0])}
    assert _beyond(0.0, band, (-20.0, 20.0)) == {"band": 40.0}
    assert _beyond(50.0, {**band, "median": np.array([0.0, 35.0])}, (-20.0, 20.0)) == {"start": 50.0, "prediction": 35.0}
    assert _beyond(0.0, {**band, "hi": np.array([1.0, 29.0])}, (-20.0, 20.0)) is None


def test_draws_that_run_off_and_a_shank_over_the_top_are_named_not_averaged_into_nan(made, monkeypatch, capsys):
    """A plan that drives some draws' runs to overflow leaves those draws out of the band from where
    they overflow (the band is of the draws still finite, none where none is), and a median beyond
    ±180° (the shank over the top) is named: both warned of, kept in summary.json, and the figure's
    axis is cut at ±200° so that the rest stays readable."""
    import quadshank.commands.predict as predict
    from quadshank.commands.predict import _band

    runs = np.tile(np.linspace(0.0, 10.0, 6), (10, 1))
    runs[2, 3:] = np.nan
    runs[5, 4:] = np.inf
    band, gone = _band(runs)
    assert list(np.flatnonzero(gone)) == [2, 5]
    assert np.allclose(band["median"], np.linspace(0.0, 10.0, 6)) and np.all(np.isfinite(band["lo"]))
    band, _ = _band(np.full((4, 3), np.nan))
    assert np.all(np.isnan(band["median"]))

    def rollouts(models, levels, angle0, velocity0):  # half the draws climb past the top, two overflow
        n, t = 20, np.arange(len(levels), dtype=float)  # --draws 20
        out = np.tile((angle0 or 0.0) + t, (n, 1)) + np.arange(n)[:, None] * 1e-3  # None: at rest, here 0
        out[::2] += 2.0 * t  # the median's draws climb too
        out[:2, 250:] = np.nan
        return out

    monkeypatch.setattr(predict, "plan_predictions", rollouts)
    plan = made["root"] / "plan-over.csv"
    plan.write_text("time_s,stimulation\n" + "".join(f"{i * 0.01!r},{1.0 if i % 5 == 0 else 0.0}\n" for i in range(300)))
    out = made["root"] / "predict-over"
    capsys.readouterr()
    assert main(["predict", str(made["fit"]), "--stimulation", str(plan), "--draws", "20", "--legs", "TN-left",
                 "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "TN-left: 2 of 20 draws ran off to no finite angle under the plan, the first at 2.50 s" in err
    assert "TN-left: the median prediction passes ±180° at" in err and "over the top" in err
    s = json.loads((out / "summary.json").read_text())
    assert s["diverged_draws"] == {"TN-left": {"draws": 2, "first_s": 2.5}}
    assert s["beyond_reach"]["TN-left"]["angle_deg"] >= 180.0 and s["beyond_reach"]["TN-left"]["what"] == "prediction"
    assert "ranges over [0.0°, beyond +180°]" in err
    assert all(v is None or np.isfinite(v) for v in (s["extremes"]["TN-left"]["max_deg"], s["extremes"]["TN-left"]["min_deg"]))
    rows = list(csv.reader((out / "predictions.csv").open()))
    assert all(r[rows[0].index("TN-left median [deg]")] != "nan" for r in rows[1:])


def test_a_long_plans_figure_adds_a_view_of_its_first_pulses():
    """A plan over a minute gets a second view of 20 s from its first pulse, its pulses alone; a short
    plan keeps one view."""
    import matplotlib.pyplot as plt

    from quadshank.outputs import plot_plan_predictions

    t = np.arange(0, 120, 0.01)
    u = np.where(np.arange(t.size) % 300 == 250, 0.8, 0.0)
    m = 10 * np.sin(t)
    fig = plot_plan_predictions(t, u, {"TN-left": {"median": m, "lo": m - 2, "hi": m + 2}})
    assert len(fig.axes) == 4
    drawn = np.concatenate([np.asarray(c.get_segments())[:, 0, 0] for c in fig.axes[3].collections])
    assert drawn.min() == pytest.approx(2.5) and drawn.max() <= 22.5 and drawn.size == 7
    plt.close(fig)
    fig = plot_plan_predictions(t[:3000], u[:3000], {"TN-left": {"median": m[:3000], "lo": m[:3000], "hi": m[:3000]}})
    assert len(fig.axes) == 2
    plt.close(fig)


def test_the_divergent_transitions_row_says_where_they_lie():
    """A fit whose divergent transitions the checks located (``divergences_at``) says in its row of
    the checks where they lie; one without (or saved before the check) shows the count alone."""
    base = {"rhat_max": 1.0, "ess_bulk_min": 900.0, "ess_tail_min": 900.0, "divergences": 5, "bfmi_min": 0.9,
            "ok": False, "chains": 2, "draws": 500, "thresholds": {"rhat_max": 1.01, "ess_min": 200, "bfmi_min": 0.3}}

    def row(d):
        html = report._diagnostics_section(d)
        r = html[html.index("divergent transitions"):]
        return r[: r.index("</tr>")]

    located = row({**base, "divergences_at": {"JM-left": {"k1": 0.97, "k2": 0.04}}})
    assert "5 (all where JM-left&#x27;s k1 is high (0.97) and k2 low (0.04))" in located, located  # HTML-escaped
    assert "FAIL" in located
    assert "all where" not in row({**base, "divergences_at": {}}) and "all where" not in row(base)
