"""Posterior predictive evaluation (`quadshank evaluate --fit`) on two tiny fits.

The fits are far too short to converge; what is tested is the machinery: the
per-draw J against the point-estimate function, the summaries and their
structure, PSIS-LOO and its comparison, the files, and the errors.
"""

import json

import jax
import numpy as np
import pytest

import quadshank.evaluation._posterior as pe
from quadshank.cli import main
from quadshank.evaluation._prediction import prediction_errors, prediction_starts, predictions
from quadshank.inference._fitio import load_fit, posterior_models
from quadshank.data._interchange import load_cohort, write_interchange
from quadshank.data._paper import HORIZONS

TINY = ["--chains", "2", "--warmup", "30", "--draws", "20"]
HORIZON_KEYS = {"100", "250", "500", "1000"}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("posterior")
    data = root / "data"
    assert main(["-q", "simulate", "--out", str(data), "--minutes", "0.5",
                 "--legs", "TN-left,JM-left", "--trials", "1,2"]) == 0
    fits = []
    for model in ("model1", "model3"):
        fits.append(root / model)
        assert main(["-q", "fit", str(data), "--model", model, *TINY, "--out", str(fits[-1])]) in (0, 3)
    out = root / "eval"
    code = main(["-q", "evaluate", str(data), "--fit", str(fits[0]), "--fit", str(fits[1]),
                 "--draws", "10", "--start-stride", "10", "--out", str(out)])
    return {"root": root, "data": data, "fits": fits, "out": out, "code": code}


@pytest.fixture(scope="module")
def summary(run):
    assert run["code"] == 0
    return json.loads((run["out"] / "summary.json").read_text())


def _draws(run, n, leg="JM-left", trial=2):
    idata, model, _ = load_fit(run["fits"][1])
    models, _ = posterior_models(idata, model, leg, n_draws=n, seed=3)
    return models, load_cohort(run["data"]).get(leg, trial)


def _draw(models, i):
    return jax.tree_util.tree_map(lambda x: x[i], models)


def test_vmapped_j_equals_the_point_function_draw_by_draw(run):
    models, trial = _draws(run, 3)
    J = pe.posterior_prediction_errors(models, trial, HORIZONS, start_stride=1)
    assert J.shape == (3, len(HORIZONS))
    for i in (0, 2):
        point = prediction_errors(_draw(models, i), trial, HORIZONS)
        np.testing.assert_allclose(J[i], [point[p] for p in HORIZONS], rtol=1e-4)


def test_start_stride_uses_every_kth_start_for_all_horizons(run):
    models, trial = _draws(run, 2)
    J = pe.posterior_prediction_errors(models, trial, HORIZONS, start_stride=7)
    starts, pred = predictions(_draw(models, 1), trial, max(HORIZONS))
    keep = starts % 7 == 0
    for j, p in enumerate(HORIZONS):
        err = trial.angle_deg[starts[keep] + p] - pred[keep, p - 1]
        assert J[1, j] == pytest.approx(np.sqrt(np.mean(err**2)), rel=1e-4)


def test_chunked_draws_give_the_same_j(run, monkeypatch):
    models, trial = _draws(run, 5)
    whole = pe.posterior_prediction_errors(models, trial, HORIZONS, start_stride=10)
    n_starts = len(prediction_starts(trial, max(HORIZONS), 10))
    monkeypatch.setattr(pe, "CHUNK_ELEMENTS", 2 * n_starts * max(HORIZONS))  # chunks of 2, the last padded
    chunked = pe.posterior_prediction_errors(models, trial, HORIZONS, start_stride=10)
    np.testing.assert_allclose(chunked, whole, rtol=1e-6)


def test_summary_holds_medians_and_bands_per_model_leg_trial_horizon(summary):
    assert {"J", "J_legs", "sign_tests", "loo", "fits"} <= set(summary)
    assert set(summary["J"]) == {"model1", "model3"}
    for model, trials in summary["J"].items():
        assert set(trials) == {"1", "2"}
        for hv in trials.values():
            assert set(hv) == HORIZON_KEYS
            for v in hv.values():
                assert set(v) == {"median", "lo", "hi"}
                assert v["lo"] <= v["median"] <= v["hi"]
            assert hv["100"]["median"] < hv["1000"]["median"]  # errors grow with horizon
        widths = [v["hi"] - v["lo"] for hv in trials.values() for v in hv.values()]
        assert max(widths) > 0, model  # draws differ, so J does
        assert set(summary["J_legs"][model]) == {"TN-left", "JM-left"}
        for leg, by_trial in summary["J_legs"][model].items():
            for hv in by_trial.values():
                assert set(hv) == HORIZON_KEYS
                assert all(v["lo"] <= v["median"] <= v["hi"] for v in hv.values()), (model, leg)
        assert summary["fits"][model]["draws_used"] == 10
        assert summary["fits"][model]["trials_fitted"] == [1]


def test_cohort_j_is_the_per_draw_mean_over_legs():
    rng = np.random.default_rng(0)
    a, b = rng.gamma(4.0, size=(50, 4)), rng.gamma(4.0, size=(50, 4))
    cohort, legs = pe.summarise_j({"m": {"A": {"2": a}, "B": {"2": b}}})
    assert cohort["m"]["2"]["1000"] == pytest.approx(pe.interval((a + b)[:, 3] / 2))
    assert legs["m"]["B"]["2"]["100"]["median"] == pytest.approx(np.median(b[:, 0]))


def test_a_diverging_draw_has_an_unbounded_j_that_the_band_orders_last(run):
    models, trial = _draws(run, 5)
    # one draw's elasticity so stiff that its predictions overflow: J +inf, not NaN
    k2 = np.asarray(models.params()["k2"]).copy()
    k2[0] = 50.0
    J = pe.posterior_prediction_errors(models.with_params({"k2": k2}), trial, HORIZONS, start_stride=10)
    assert np.isposinf(J[0]).all() and np.isfinite(J[1:]).all()
    band = pe.interval(J[:, -1])
    assert np.isfinite(band["lo"]) and np.isfinite(band["median"])
    many = np.concatenate([np.full(10, np.inf), np.arange(10.0)])  # half diverge: the upper end is unbounded
    assert pe.interval(many)["hi"] == np.inf and pe.interval(many)["lo"] == 0.0


def test_sign_tests_on_posterior_medians(summary):
    tests = summary["sign_tests"]
    assert {t["horizon_ms"] for t in tests} == {100, 250, 500, 1000}
    for t in tests:
        assert {t["model_a"], t["model_b"]} == {"model1", "model3"}
        assert t["n_pairs"] <= 2  # two legs, validation trial 2 only
        medians = [summary["J_legs"][m][leg]["2"][str(t["horizon_ms"])]["median"]
                   for leg in ("TN-left", "JM-left") for m in (t["model_a"], t["model_b"])]
        a_better = sum(x < y for x, y in zip(medians[::2], medians[1::2]))
        assert t["a_better"] == a_better


def test_psis_loo_and_comparison(summary):
    loo = summary["loo"]
    assert set(loo["fits"]) == {"model1", "model3"}
    for v in loo["fits"].values():
        assert np.isfinite(v["elpd_loo"]) and v["se"] > 0
        assert v["n_observations"] == 2 * 30  # 2 legs × 30 one-second segments of trial 1
        assert 0 <= v["pareto_k_over_0.7"] <= v["n_observations"]
    assert loo["not_compared"] == []
    (group,) = loo["compare"]
    table = group["table"]
    assert set(table) == {"model1", "model3"}
    assert sorted(r["rank"] for r in table.values()) == [0, 1]
    assert sum(r["weight"] for r in table.values()) == pytest.approx(1.0, abs=1e-6)
    best = min(table, key=lambda m: table[m]["rank"])
    assert table[best]["elpd_diff"] == 0.0
    assert max(loo["fits"], key=lambda m: loo["fits"][m]["elpd_loo"]) == best


def test_fits_of_different_data_are_not_compared(run):
    fits = pe.load_fits(run["fits"])
    fits[1] = fits[1]._replace(desc={**fits[1].desc, "trials": [1, 2]})
    loo = pe.loo_report(fits)
    assert loo["compare"] == []
    assert {x["model"] for x in loo["not_compared"]} == {"model1", "model3"}
    assert set(loo["fits"]) == {"model1", "model3"}


def test_tables_and_figures_are_written(run, summary):
    out = run["out"]
    for name in ("table5_posterior", "j_per_leg_posterior", "sign_tests_posterior", "loo", "loo_compare"):
        assert (out / "tables" / f"{name}.csv").exists() and (out / "tables" / f"{name}.md").exists()
    for name in ("table5_posterior_j_vs_horizon", "fig5_posterior_predictions_100ms", "fig6_posterior_predictions_1s"):
        assert (out / "figures" / f"{name}.png").stat().st_size > 10_000
    rows = (out / "tables" / "table5_posterior.csv").read_text().splitlines()
    assert len(rows) == 1 + 2 * 4  # header, 2 trials × 4 horizons
    assert "model3 median" in rows[0] and "paper model3" in rows[0]


def test_one_fit_has_nothing_to_compare(run, tmp_path):
    out = tmp_path / "one"
    assert main(["-q", "evaluate", str(run["data"]), "--fit", str(run["fits"][0]),
                 "--draws", "10", "--start-stride", "10", "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert list(s["J"]) == ["model1"] and s["sign_tests"] == []
    assert s["loo"]["compare"] == [] and s["loo"]["not_compared"] == []
    # tables with no rows are empty tables, not files of no bytes that no CSV reader takes
    import csv
    for name, first in (("loo_compare", "legs"), ("sign_tests_posterior", "horizon [ms]")):
        rows = list(csv.reader((out / "tables" / f"{name}.csv").open()))
        assert len(rows) == 1 and rows[0][0] == first, (name, rows)


def test_two_fits_of_one_model_are_labelled_by_their_folders(run, tmp_path, capsys):
    """Two fits of one model (here one fit copied) are evaluated side by side, each labelled by the
    model and its folder; one folder given twice is refused."""
    import shutil

    copy = tmp_path / "model1-again"
    shutil.copytree(run["fits"][0], copy)
    assert [f.label for f in pe.load_fits([run["fits"][0], copy])] == ["model1@model1", "model1@model1-again"]
    out = tmp_path / "same-model"
    assert main(["-q", "evaluate", str(run["data"]), "--fit", str(run["fits"][0]), "--fit", str(copy),
                 "--draws", "10", "--start-stride", "10", "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert list(s["J"]) == ["model1@model1", "model1@model1-again"]
    assert s["J"]["model1@model1"] == s["J"]["model1@model1-again"]  # one posterior, the same draws
    assert set(s["loo"]["compare"][0]["table"]) == {"model1@model1", "model1@model1-again"}
    capsys.readouterr()
    assert main(["-q", "evaluate", str(run["data"]), "--fit", str(copy), "--fit", str(copy),
                 "--out", str(tmp_path / "twice")]) == 2
    assert "are one folder; give each fit once" in capsys.readouterr().err


def test_more_draws_than_the_fit_holds_are_said_to_be_fewer(run, tmp_path, capsys):
    """--draws beyond a fit's draws: the bands use every draw it holds, and the warning, the
    summary and the report say how many."""
    out = tmp_path / "more"
    capsys.readouterr()
    assert main(["evaluate", str(run["data"]), "--fit", str(run["fits"][0]),
                 "--draws", "1000", "--start-stride", "20", "--out", str(out)]) == 0
    held = 2 * 20  # TINY: 2 chains of 20 draws
    assert f"--draws 1000: model1 holds {held}" in capsys.readouterr().err
    s = json.loads((out / "summary.json").read_text())
    assert s["n_draws"] == held and s["fits"]["model1"]["draws_used"] == held
    assert f"The bands come from {held} posterior draws" in (out / "report.md").read_text()


def test_missing_fit_or_leg_exits_2_naming_it(run, tmp_path, capsys):
    data, fit1 = str(run["data"]), str(run["fits"][0])
    nowhere = tmp_path / "nowhere"
    capsys.readouterr()
    assert main(["-q", "evaluate", data, "--fit", fit1, "--fit", str(nowhere), "--out", str(tmp_path / "a")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("quadshank: error:") and str(nowhere) in err and "Traceback" not in err
    assert not (tmp_path / "a" / "summary.json").exists()

    one_leg = tmp_path / "one_leg"
    write_interchange(load_cohort(run["data"]).select(legs=["TN-left"]), one_leg)
    assert main(["-q", "evaluate", str(one_leg), "--fit", fit1, "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert "JM-left" in err and fit1 in err
    assert not (tmp_path / "b" / "summary.json").exists()

    assert main(["-q", "evaluate", data, "--fit", fit1, "--identified", fit1, "--out", str(tmp_path / "c")]) == 2
    assert "not both" in capsys.readouterr().err


def test_delay_angle_figure_has_a_panel_per_leg_and_the_population():
    from quadshank.outputs._figures import plot_delay_angle

    grid = list(np.arange(-40.0, 61.0, 1.0))
    step = [3.0 if a < -20 else 4.0 for a in grid]
    da = {"angle_deg": grid, "median": step, "lo": step, "hi": step, "change_probability": 0.97,
          "pulse_angle_range_deg": [-30.0, 45.0]}  # fmt: skip
    summary = {"legs": {"TN-left": {"delay_angle": da}, "JM-left": {"delay_angle": {**da, "change_probability": 0.1}},
                        "OT-left": {}},
               "delay_angle_population": {k: da[k] for k in ("angle_deg", "median", "lo", "hi")}}  # fmt: skip
    fig = plot_delay_angle(summary["legs"], "model2+angle_delay", summary["delay_angle_population"])
    visible = [ax for ax in fig.axes if ax.get_visible()]
    assert [ax.get_title() for ax in visible] == [
        "TN-left: P(change) 0.97", "JM-left: P(change) 0.10", "population (legs pooled)"
    ]
    line = visible[0].get_lines()[0]
    np.testing.assert_array_equal(line.get_ydata(), step)


def test_stride_error_is_the_spread_of_j_over_the_stride_offsets(run):
    models, trial = _draws(run, 1)
    k = 7
    got = pe.stride_error(models, trial, HORIZONS, k)
    starts, pred = predictions(_draw(models, 0), trial, max(HORIZONS))
    per_offset = [[np.sqrt(np.mean((trial.angle_deg[starts[starts % k == o] + p]
                                    - pred[starts % k == o, p - 1]) ** 2)) for p in HORIZONS] for o in range(k)]
    np.testing.assert_allclose(got, np.std(per_offset, axis=0, ddof=1), rtol=1e-4)
    assert np.all(got > 0)
    np.testing.assert_array_equal(pe.stride_error(models, trial, HORIZONS, 1), 0.0)  # every start: no error
    # a stride beyond the trial's starts: each start an offset of its own, at once (not 10⁸ empty offsets)
    np.testing.assert_allclose(pe.stride_error(models, trial, HORIZONS, 10**8),
                               pe.stride_error(models, trial, HORIZONS, trial.n_samples), rtol=1e-12)


def test_band_mcse_adds_the_quantile_and_the_stride_errors():
    rng = np.random.default_rng(0)
    n, sigma = 400, 0.3
    draws = {"m": {"A": {"1": 1.0 + sigma * rng.normal(size=(n, 4))}, "B": {"1": 2.0 + sigma * rng.normal(size=(n, 4))}}}
    zero = {"m": {"A": {"1": np.zeros(4)}, "B": {"1": np.zeros(4)}}}
    _, legs = pe.band_mcse(draws, zero)
    # the 5 % quantile of n independent normal draws: sqrt(p(1 - p) / n) / density, arviz's estimate a little above
    theory = sigma * np.sqrt(0.05 * 0.95 / n) / 0.1031
    # each estimate is itself noisy (about ±30 %): their mean over the 16 band ends
    ratio = np.mean([e[end] for leg in ("A", "B") for e in legs["m"][leg]["1"].values() for end in ("lo", "hi")]) / theory
    assert 0.8 < ratio < 1.6, ratio
    stride = {"m": {"A": {"1": np.full(4, 0.2)}, "B": {"1": np.zeros(4)}}}
    cohort_s, legs_s = pe.band_mcse(draws, stride)
    cohort_0, _ = pe.band_mcse(draws, zero)
    for h in ("100", "1000"):
        for end in ("lo", "hi"):
            assert legs_s["m"]["A"]["1"][h][end] == pytest.approx(np.hypot(legs["m"]["A"]["1"][h][end], 0.2))
            assert legs_s["m"]["B"]["1"][h][end] == pytest.approx(legs["m"]["B"]["1"][h][end])
            # the mean over two legs: the stride errors add as errors of a mean, (0.2² + 0²)^½ / 2
            assert cohort_s["m"]["1"][h][end] == pytest.approx(np.hypot(cohort_0["m"]["1"][h][end], 0.1))
    assert pe.largest_mcse(cohort_s) == max(e for hv in cohort_s["m"]["1"].values() for e in hv.values())


def test_the_stride_error_is_the_scale_of_what_the_stride_changes(run):
    """J at one start in k against J at every start, draw by draw: their differences, in units of
    the stride error measured on one draw, have an RMS near 1 (a standard error of the mean over
    the offsets, k^½ times smaller, or none at all would give far more)."""
    fits = pe.load_fits([run["fits"][1]])
    cohort = load_cohort(run["data"])
    every, _ = pe.posterior_j_and_stride_errors(fits, cohort, n_draws=40, start_stride=1)
    strided, sd = pe.posterior_j_and_stride_errors(fits, cohort, n_draws=40, start_stride=9)
    z = [(strided["model3"][leg][tr] - every["model3"][leg][tr]) / sd["model3"][leg][tr]
         for leg in every["model3"] for tr in every["model3"][leg]]
    rms = float(np.sqrt(np.mean(np.square(z))))
    assert 0.3 < rms < 2.0, rms


def test_bands_to_an_accuracy_choose_draws_and_stride_and_say_so(run, tmp_path):
    fits = pe.load_fits([run["fits"][1]])
    cohort = load_cohort(run["data"])
    loose = pe.accurate_j(fits, cohort, 10.0, pilot=(20, 10))
    assert loose.met and len(loose.rounds) == 1 and (loose.n_draws, loose.start_stride) == (20, 10)
    strict_target = 0.5 * loose.rounds[0]["largest_mcse"]
    strict = pe.accurate_j(fits, cohort, strict_target, pilot=(20, 10))
    assert len(strict.rounds) >= 2
    assert strict.n_draws > 20 or strict.start_stride < 10  # the next round bought accuracy
    assert strict.n_draws <= 40  # no more draws than the fit holds
    assert strict.rounds[-1]["largest_mcse"] == pytest.approx(pe.largest_mcse(strict.mcse["cohort"]))
    assert strict.met == (strict.rounds[-1]["largest_mcse"] <= strict_target)

    out = tmp_path / "acc"
    assert main(["-q", "evaluate", str(run["data"]), "--fit", str(run["fits"][1]), "--band-mcse", "10",
                 "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    m = s["band_mcse"]
    assert m["target"] == 10 and m["met"] and m["largest_cohort"] <= 10 and s["n_draws"] == m["rounds"][-1]["draws"]
    assert set(m["cohort"]["model3"]["2"]["1000"]) == {"lo", "hi"}
    assert "largest Monte Carlo standard error of a band end" in (out / "report.md").read_text()


def test_the_black_box_is_scored_beside_the_fits(run, summary):
    bb = summary["blackbox"]
    assert set(bb["J_per_leg"]) == {"TN-left", "JM-left"} and set(bb["J"]) == {"1", "2"}
    assert set(bb["J"]["2"]) == HORIZON_KEYS and {o["trained_on"] for o in bb["orders"].values()} == {1}
    for row in bb["better_than"]:
        assert all(bb["J"][row["trial"]][h] < summary["J"][row["model"]][row["trial"]][h]["median"]
                   for h in row["horizons_ms"])
    assert "A black-box yardstick" in (run["out"] / "report.md").read_text()


def test_every_evaluation_estimates_its_bands_error(summary):
    m = summary["band_mcse"]
    assert "target" not in m and m["largest_legs"] > 0 and m["largest_cohort"] > 0
    for label in ("model1", "model3"):
        assert set(m["legs"][label]) == {"TN-left", "JM-left"}
