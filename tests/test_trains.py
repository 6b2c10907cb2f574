"""Stimulation as real stimulators deliver it: trains at 20–50 Hz whose pulse width is modulated,
read from a stimulator's columns and fitted through a recruitment curve."""

from __future__ import annotations

import json

import jax.numpy as jnp
import numpy as np
import pytest

from quadshank.cli import main
from quadshank.data import Cohort, Trial, write_interchange
from quadshank.data._paper import TABLE_III
from quadshank.data._simulate import PASSIVE_TRUTH, simulate_response
from quadshank.model import RecruitmentSigmoid

LEG = "JM-left"
DT = 0.01
WIDTH_US = 400.0  # the stimulator's widest pulse
RECRUITMENT = {"u50": 0.55, "u_width": 0.12}


def train_stimulation(seconds: float, seed: int) -> np.ndarray:
    """Trains of 3–6 pulses at 20, 25, 33 or 50 Hz every 1–2 s, each train at one relative charge
    in [0.2, 1] (the first at 1: the widest pulse)."""
    rng = np.random.default_rng(seed)
    u = np.zeros(int(round(seconds / DT)))
    k, level = 100, 1.0
    while k < u.size - 100:
        period = int(rng.choice([2, 3, 4, 5]))
        for j in range(int(rng.integers(3, 7))):
            u[k + j * period] = level
        k += int(rng.uniform(1.0, 2.0) / DT)
        level = rng.uniform(0.2, 1.0)
    return u


@pytest.fixture(scope="module")
def train_data(tmp_path_factory):
    """90 s of trains: the muscle recruited along the truth's curve from each pulse's relative
    charge, written as a stimulator logs it (pulse width in µs, 0 between pulses), with the
    simulator's sensors and their noise."""
    u = train_stimulation(90.0, seed=4)
    recruited = np.asarray(RecruitmentSigmoid(**RECRUITMENT).recruitment(jnp.asarray(u))) * (u > 0)
    sim = simulate_response(LEG, recruited, noise=True, seed=1)
    trial = Trial.from_signals("JM", "left", 1, DT, sim["angle_deg"], sim["acceleration_deg_s2"], u)
    folder = write_interchange(Cohort((trial,)), tmp_path_factory.mktemp("trains") / "data")
    path = folder / "JM-left-trial1.csv"
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    j = header.index("stimulation")
    header[j] = "pulse_width_us"
    rows = [",".join(header)]
    for line in lines[1:]:
        cells = line.split(",")
        cells[j] = repr(float(cells[j]) * WIDTH_US)
        rows.append(",".join(cells))
    path.write_text("\n".join(rows) + "\n")
    return folder


def test_trains_from_a_stimulators_log_are_fitted_through_a_recruitment_curve(train_data, tmp_path, capsys):
    folder = train_data
    out = tmp_path / "fit"
    rc = main(["-q", "fit", str(folder), "--model", "model3", "--add-effect", "recruitment_sigmoid", "--chains", "2",
               "--warmup", "300", "--draws", "300", "--out", str(out)])
    s = json.loads((out / "summary.json").read_text())
    assert rc in (0, 3) and s["diagnostics"]["rhat_max"] < 1.05 and s["diagnostics"]["divergences"] == 0
    p = {k: v["median"] for k, v in s["legs"][LEG]["params"].items()}
    assert p["u50"] == pytest.approx(RECRUITMENT["u50"], abs=0.03)
    assert p["u_width"] == pytest.approx(RECRUITMENT["u_width"], rel=0.15)
    assert p["gain"] == pytest.approx(TABLE_III[LEG]["G2"], rel=0.08)
    assert p["gamma_angle"] == pytest.approx(TABLE_III[LEG]["gamma_angle"], rel=0.15)
    for k in ("damping", "gravity"):
        assert p[k] == pytest.approx(PASSIVE_TRUTH[LEG][k], rel=0.05), k
    # the classical identification cannot use trains: it says which leg and trial, why, and what can
    capsys.readouterr()
    assert main(["-q", "identify", str(folder), "--out", str(tmp_path / "id")]) == 2
    err = capsys.readouterr().err
    assert "JM-left trial 1" in err and "isolated twitches" in err and "quadshank fit" in err
    _a_plan_in_pulse_widths_is_predicted_through_the_legs_charge(out, tmp_path, capsys)
    # the report gives the recruitment curve in the stimulator's unit too: u50 × 400 µs
    assert main(["-q", "report", str(out), "--out", str(tmp_path / "report"), "--draws", "5"]) == 0
    page = (tmp_path / "report" / "subject-JM.html").read_text()
    u50 = s["legs"][LEG]["params"]["u50"]
    assert f"<code>u50</code> {u50['median'] * WIDTH_US:.4g} µs [{u50['lo'] * WIDTH_US:.4g}," in page, page
    assert "each pulse's pulse width over 400 µs" in page


def _plan(path, column: str, widths: dict[int, float], seconds: float = 3.0):
    rows = [f"time_s,{column}"] + [f"{k * DT:.2f},{widths.get(k, 0.0)!r}" for k in range(int(round(seconds / DT)))]
    path.write_text("\n".join(rows) + "\n")
    return path


def _a_plan_in_pulse_widths_is_predicted_through_the_legs_charge(fit_dir, tmp_path, capsys):
    """The fit keeps the charge its levels are relative to (the widest pulse, 400 µs); a plan in
    pulse widths is that leg's levels, width / 400, rolled out as a plan of levels is; a plan
    in other columns, beyond the widest fitted pulse, or as levels is refused, naming why."""
    import csv

    from quadshank.evaluation._posterior import load_fits, plan_predictions
    from quadshank.inference._fitio import posterior_models
    from quadshank.inference._summaries import interval

    s = json.loads((fit_dir / "summary.json").read_text())
    assert s["charge_scale"] == {LEG: {"largest_charge": WIDTH_US, "columns": ["pulse_width_us"], "unit": "µs"}}
    widths = {50: 200.0, 53: 200.0, 56: 200.0, 150: 400.0, 152: 400.0}
    plan = _plan(tmp_path / "plan.csv", "pulse_width_us", widths)
    out = tmp_path / "predicted"
    assert main(["-q", "predict", str(fit_dir), "--stimulation", str(plan), "--draws", "20", "--out", str(out)]) == 0
    rows = list(csv.DictReader((out / "predictions.csv").open()))
    levels = np.array([float(r[f"{LEG} stimulation"]) for r in rows])
    assert [float(r["pulse_width_us"]) for r in rows] == [widths.get(k, 0.0) for k in range(len(rows))]
    assert np.allclose(levels, [widths.get(k, 0.0) / WIDTH_US for k in range(len(rows))])
    (fit,) = load_fits([fit_dir])
    models, _ = posterior_models(fit.idata, fit.model, LEG, 20, 0)
    expected = np.asarray(interval(plan_predictions(models, levels, 0.0, 0.0), axis=0)["median"])
    got = np.array([float(r[f"{LEG} median [deg]"]) for r in rows])
    assert np.allclose(got, expected, rtol=1e-5, atol=1e-4) and np.ptp(got) > 1.0  # the twitches move the knee
    assert json.loads((out / "summary.json").read_text())["plan_columns"] == ["pulse_width_us"]
    refusals = {
        "other columns": (_plan(tmp_path / "mA.csv", "current_mA", {50: 20.0}), "a charge in mA is not one in µs"),
        "wider": (_plan(tmp_path / "wide.csv", "pulse_width_us", {50: 500.0}), "above the largest in JM-left's"),
        "levels": (_plan(tmp_path / "levels.csv", "stimulation", {50: 0.5}), "give the plan in those columns"),
    }
    for name, (path, message) in refusals.items():
        capsys.readouterr()
        assert main(["-q", "predict", str(fit_dir), "--stimulation", str(path), "--out", str(tmp_path / name)]) == 2
        err = capsys.readouterr().err
        assert message in err and path.name in err, (name, err)
        assert not (tmp_path / name / "summary.json").exists()


def test_the_charge_a_legs_levels_are_relative_to_is_kept_through_netcdf(train_data, tmp_path):
    """Read from a stimulator's columns, a leg keeps its largest charge, the columns and their unit,
    in the folder's cohort and in its NetCDF conversion; levels keep none."""
    from quadshank.data import charge_scales, convert, load_cohort

    expected = {LEG: {"largest_charge": WIDTH_US, "columns": ["pulse_width_us"], "unit": "µs"}}
    assert charge_scales(load_cohort(train_data)) == expected
    convert(train_data, tmp_path / "data.nc")
    assert charge_scales(load_cohort(tmp_path / "data.nc")) == expected
    trial = Trial.from_signals("JM", "left", 1, DT, 20 * np.sin(np.arange(300) * 0.05), None,
                              np.r_[np.zeros(100), 1.0, np.zeros(199)])
    assert charge_scales(load_cohort(write_interchange(Cohort((trial,)), tmp_path / "levels"))) == {}


def test_a_conversion_back_to_a_folder_keeps_the_charge(train_data, tmp_path):
    """NetCDF back to a folder: the levels go to ``stimulation`` and the charge they are relative
    to to ``charge_scale.json``, read back as it was; a cohort without one written over that folder
    removes the file, so its levels are not given another cohort's charges."""
    from quadshank.data import charge_scales, convert, load_cohort
    from quadshank.data._interchange import CHARGE_SCALE_NAME

    expected = charge_scales(load_cohort(train_data))
    convert(train_data, tmp_path / "data.nc")
    back = convert(tmp_path / "data.nc", tmp_path / "back")
    assert "stimulation" in (back / "JM-left-trial1.csv").read_text().splitlines()[0].split(",")
    assert json.loads((back / CHARGE_SCALE_NAME).read_text(encoding="utf-8")) == expected
    again = load_cohort(back)
    assert charge_scales(again) == expected
    np.testing.assert_array_equal(again.trials[0].stimulation, load_cohort(train_data).trials[0].stimulation)
    levels = Cohort(again.trials)  # the same trials, no scale
    write_interchange(levels, back, overwrite=True)
    assert not (back / CHARGE_SCALE_NAME).exists() and charge_scales(load_cohort(back)) == {}


@pytest.mark.parametrize("content, said", [
    ("{not json", "not JSON text"),
    ("[1, 2]", "must be a JSON object"),
    ('{"TN-left": {"largest_charge": 400, "columns": ["pulse_width_us"], "unit": "µs"}}',
     "names leg 'TN-left', which manifest.csv does not list"),
    ('{"JM-left": {"largest_charge": -4, "columns": ["pulse_width_us"], "unit": "µs"}}',
     "JM-left: largest_charge must be a positive number, not -4"),
    ('{"JM-left": {"largest_charge": 4, "columns": ["width"], "unit": "µs"}}', "JM-left: columns must be"),
    ('{"JM-left": {"largest_charge": 4, "columns": ["current_mA"], "unit": "µs"}}',
     "JM-left: unit must be 'mA' for columns ['current_mA'], not 'µs'"),
    ('{"JM-left": {"largest_charge": 4}}', "JM-left: must be {"),
])
def test_a_bad_charge_scale_file_is_named(tmp_path, content, said):
    """A ``charge_scale.json`` that cannot be the charge of a listed leg's levels is refused,
    named with what is wrong."""
    from quadshank.data import InterchangeError, read_interchange

    trial = Trial.from_signals("JM", "left", 1, DT, 20 * np.sin(np.arange(300) * 0.05), None,
                              np.r_[np.zeros(100), 1.0, np.zeros(199)])
    folder = write_interchange(Cohort((trial,)), tmp_path / "data")
    (folder / "charge_scale.json").write_text(content, encoding="utf-8")
    with pytest.raises(InterchangeError) as err:
        read_interchange(folder)
    assert "charge_scale.json" in str(err.value) and said in str(err.value), str(err.value)


def test_a_charge_scale_file_cannot_overrule_a_stimulators_columns(train_data, tmp_path):
    """A leg read from a stimulator's columns takes its scale from them: an entry for it is refused."""
    import shutil

    from quadshank.data import InterchangeError, read_interchange

    folder = tmp_path / "data"
    shutil.copytree(train_data, folder)
    (folder / "charge_scale.json").write_text(
        '{"JM-left": {"largest_charge": 4, "columns": ["pulse_width_us"], "unit": "µs"}}', encoding="utf-8")
    with pytest.raises(InterchangeError, match="whose trials give a stimulator's columns"):
        read_interchange(folder)


def test_a_pulse_width_typo_and_mixed_encodings_are_named(train_data, tmp_path):
    """One pulse logged 100 times too wide scales every other pulse's level down by as much: named
    with its file and time; so is a leg whose trials give the stimulation in two ways. The file as
    logged draws neither."""
    import shutil
    import warnings

    from quadshank.data import DataWarning, read_interchange

    def said(folder):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            read_interchange(folder)
        return [str(w.message) for w in caught if issubclass(w.category, DataWarning)]

    assert not [w for w in said(train_data) if "charge" in w or "same way" in w]
    typo = tmp_path / "typo"
    shutil.copytree(train_data, typo)
    path = typo / "JM-left-trial1.csv"
    lines = path.read_text().splitlines()
    j = lines[0].split(",").index("pulse_width_us")
    row = next(r for r in range(1, len(lines)) if float(lines[r].split(",")[j]) > 0)
    cells = lines[row].split(",")
    cells[j] = repr(float(cells[j]) * 100)
    lines[row] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    (found,) = [w for w in said(typo) if "largest pulse charge" in w]
    assert found.startswith(f"JM-left-trial1.csv (JM-left): its largest pulse charge at time_s = {cells[0]}")
    assert "a typo in pulse_width_us" in found
    mixed = tmp_path / "mixed"
    shutil.copytree(train_data, mixed)
    levels = Trial.from_signals("JM", "left", 1, DT, 20 * np.sin(np.arange(500) * 0.05), None,
                                np.r_[np.zeros(250), 1.0, np.zeros(249)])
    write_interchange(Cohort((levels,)), tmp_path / "two")
    shutil.copy(tmp_path / "two" / "JM-left-trial1.csv", mixed / "JM-left-trial2.csv")
    with open(mixed / "manifest.csv", "a") as f:
        manifest = (mixed / "manifest.csv").read_text().splitlines()
        f.write(manifest[1].replace(",1,", ",2,", 1).replace("trial1", "trial2") + "\n")
    assert any("give every trial of a leg the same way" in w for w in said(mixed)), said(mixed)
