"""Interchange folders: round trips, conversion, every validation rule, atomic writes."""

from __future__ import annotations

import csv
import pickle
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from quadshank.data import _interchange as ix
from quadshank.data._cohort import Cohort, Trial, derive_acceleration, derive_velocity
from quadshank.data._interchange import (
    DataWarning,
    InterchangeError,
    Problem,
    convert,
    load_cohort,
    read_interchange,
    write_interchange,
)

N = 300
DT = 0.01
PULSES = {20: 1.0, 90: 0.5, 160: 1.0, 230: 0.5}
SIGNALS = ("time_s", "angle_deg", "velocity_deg_s", "acceleration_deg_s2", "stimulation")


def make_trial(subject: str, leg: str, trial: int, phase: float, measured: bool = False) -> Trial:
    k = np.arange(N)
    t = k * DT
    w = 2 * np.pi * 0.8
    angle = 30.0 * np.sin(w * t + phase)
    acceleration = -30.0 * w**2 * np.sin(w * t + phase)
    stimulation = np.zeros(N)
    for i, u in PULSES.items():
        stimulation[i] = u
    velocity = 30.0 * w * np.cos(w * t + phase) if measured else None
    return Trial.from_signals(
        subject, leg, trial, DT, angle, acceleration, stimulation, velocity_deg_s=velocity, time_s=t
    )


def make_cohort(measured: bool = False) -> Cohort:
    return Cohort(
        (
            make_trial("TN", "left", 1, 0.0, measured),
            make_trial("TN", "left", 2, 0.7, measured),
            make_trial("JM", "right", 1, 1.3, measured),
        )
    )


@pytest.fixture
def cohort() -> Cohort:
    return make_cohort()


@pytest.fixture
def folder(tmp_path, cohort) -> Path:
    """A valid interchange folder: TN-left trials 1-2, JM-right trial 1, velocity derived."""
    return write_interchange(cohort, tmp_path / "cohort")


@pytest.fixture
def measured_folder(tmp_path) -> Path:
    """The same cohort with a measured velocity column."""
    return write_interchange(make_cohort(measured=True), tmp_path / "measured")


# --------------------------------------------------------------------------- helpers
def read_rows(path: Path) -> list[list[str]]:
    with open(path, newline="") as fh:
        return list(csv.reader(fh))


def write_rows(path: Path, rows: list[list[str]]) -> None:
    with open(path, "w", newline="") as fh:
        csv.writer(fh, lineterminator="\n").writerows(rows)


def set_cell(path: Path, line: int, column: str, value: str) -> None:
    """Set the cell at editor line ``line`` (header = 1) of ``column``."""
    rows = read_rows(path)
    rows[line - 1][rows[0].index(column)] = value
    write_rows(path, rows)


def drop_column(path: Path, column: str) -> None:
    rows = read_rows(path)
    j = rows[0].index(column)
    write_rows(path, [r[:j] + r[j + 1 :] for r in rows])


def add_column(path: Path, column: str, value: str) -> None:
    rows = read_rows(path)
    write_rows(path, [rows[0] + [column]] + [r + [value] for r in rows[1:]])


def column(path: Path, name: str) -> np.ndarray:
    rows = read_rows(path)
    j = rows[0].index(name)
    return np.array([float(r[j]) for r in rows[1:]])


def set_column(path: Path, name: str, values) -> None:
    rows = read_rows(path)
    j = rows[0].index(name)
    for r, v in zip(rows[1:], values):
        r[j] = repr(float(v))
    write_rows(path, rows)


def problems_of(folder: Path) -> InterchangeError:
    with pytest.raises(InterchangeError) as info:
        read_interchange(folder)
    return info.value


def assert_problem(err: InterchangeError, file: str, column: str | None, row: int | None, text: str = "") -> Problem:
    """``err`` has a problem at exactly (file, column, row) whose message contains ``text``."""
    hits = [p for p in err.problems if (p.file, p.column, p.row) == (file, column, row) and text in p.message]
    assert hits, f"no problem at {(file, column, row)} containing {text!r}; got:\n{err}"
    message = str(err)
    assert file in message
    if column is not None:
        assert f"column {column!r}" in message
    if row is not None:
        assert f"row {row}" in message
    return hits[0]


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def assert_same_trials(a: Cohort, b: Cohort) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert (x.subject, x.leg, x.trial, x.velocity_measured) == (y.subject, y.leg, y.trial, y.velocity_measured)
        assert x.sampling_period_s == y.sampling_period_s
        for name in SIGNALS:
            assert same_bits(getattr(x, name), getattr(y, name)), name


TN1 = "TN-left-trial1.csv"
TN2 = "TN-left-trial2.csv"
JM1 = "JM-right-trial1.csv"
MAN = "manifest.csv"


# --------------------------------------------------------------------------- round trips
def test_folder_layout(folder):
    assert sorted(p.name for p in folder.iterdir()) == sorted([MAN, TN1, TN2, JM1])
    assert read_rows(folder / MAN) == [
        ["subject", "leg", "trial", "file", "sampling_period_s"],
        ["TN", "left", "1", TN1, "0.01"],
        ["TN", "left", "2", TN2, "0.01"],
        ["JM", "right", "1", JM1, "0.01"],
    ]


def test_written_files_are_readable_by_others(folder, cohort, tmp_path):
    """Atomic writes go through a private temporary file; the result gets the usual permissions (0644 under umask 022)."""
    import os

    umask = os.umask(0)
    os.umask(umask)
    nc = cohort.save_netcdf(tmp_path / "c.nc")
    for path in [*folder.iterdir(), nc]:
        assert os.stat(path).st_mode & 0o777 == 0o666 & ~umask, path


def test_read_gives_bit_identical_arrays(folder, cohort):
    loaded = read_interchange(folder)
    assert_same_trials(loaded, cohort)
    assert [t.source for t in loaded] == [TN1, TN2, JM1]
    assert loaded.attrs == {"source": str(folder), "source_format": "interchange"}


def test_write_read_write_is_identical(folder, tmp_path):
    first = read_interchange(folder)
    again = write_interchange(first, tmp_path / "again")
    assert_same_trials(read_interchange(again), first)
    for name in (MAN, TN1, TN2, JM1):
        assert (again / name).read_bytes() == (folder / name).read_bytes()


def test_velocity_written_only_when_measured(folder, measured_folder):
    assert "velocity_deg_s" not in read_rows(folder / TN1)[0]
    assert "velocity_deg_s" in read_rows(measured_folder / TN1)[0]
    derived = read_interchange(folder)
    measured = read_interchange(measured_folder)
    assert not any(t.velocity_measured for t in derived)
    assert all(t.velocity_measured for t in measured)
    for t, original in zip(measured, make_cohort(measured=True)):
        assert same_bits(t.velocity_deg_s, original.velocity_deg_s)


def test_derived_velocity_is_derive_velocity(folder):
    for t in read_interchange(folder):
        np.testing.assert_array_equal(t.velocity_deg_s, derive_velocity(t.angle_deg, DT))


def test_interchange_to_netcdf_to_interchange(measured_folder, tmp_path):
    nc = convert(measured_folder, tmp_path / "cohort.nc")
    assert nc == tmp_path / "cohort.nc" and nc.is_file()
    back = convert(nc, tmp_path / "back")
    assert read_rows(back / MAN) == read_rows(measured_folder / MAN)
    assert_same_trials(read_interchange(back), read_interchange(measured_folder))
    assert_same_trials(load_cohort(nc), read_interchange(measured_folder))
    assert load_cohort(nc).attrs["source_format"] == "interchange"


def test_netcdf_to_interchange_to_netcdf(tmp_path):
    original = Cohort(make_cohort().trials[:2] + make_cohort(measured=True).trials[2:])
    nc = original.save_netcdf(tmp_path / "a.nc")
    folder = convert(nc, tmp_path / "folder")
    nc2 = convert(folder, tmp_path / "b.nc")
    assert_same_trials(Cohort.load_netcdf(nc2), original)
    assert [t.velocity_measured for t in load_cohort(nc2)] == [False, False, True]


def test_a_netcdf_file_whose_values_changed_after_writing_is_refused(tmp_path):
    """NetCDF keeps no checksum: a value changed after writing (a damaged copy, another program's
    edit) reads back as another number.  The recordings' fingerprint written with the file
    tells: such a file is refused, naming it; without the attribute (a file written before it,
    or an edit the user keeps) it is read as it is."""
    import xarray as xr

    from quadshank.data._cohort import FINGERPRINT_ATTR

    original = make_cohort()
    nc = original.save_netcdf(tmp_path / "a.nc")
    with xr.open_dataset(nc, engine="h5netcdf") as ds:
        assert ds.attrs[FINGERPRINT_ATTR] == original.fingerprint()
        edited = ds.load()
    assert FINGERPRINT_ATTR not in Cohort.load_netcdf(nc).attrs  # not carried into the cohort, nor written twice
    edited["velocity_deg_s"][0, 40] = edited["velocity_deg_s"][0, 40] + 0.06
    edited.to_netcdf(tmp_path / "edited.nc", engine="h5netcdf")
    with pytest.raises(InterchangeError) as err:
        load_cohort(tmp_path / "edited.nc")
    assert "edited.nc: the recordings read differ from those the file was written with" in str(err.value)
    assert FINGERPRINT_ATTR in str(err.value)
    with pytest.raises(ValueError, match="damaged, or was edited"):
        Cohort.load_netcdf(tmp_path / "edited.nc")
    read, stored = Cohort.read_netcdf_unchecked(tmp_path / "edited.nc")
    assert stored == original.fingerprint() and read.trials[0].velocity_deg_s[40] != original.trials[0].velocity_deg_s[40]
    del edited.attrs[FINGERPRINT_ATTR]
    edited.to_netcdf(tmp_path / "kept.nc", engine="h5netcdf")
    kept = load_cohort(tmp_path / "kept.nc")
    assert kept.trials[0].velocity_deg_s[40] == pytest.approx(original.trials[0].velocity_deg_s[40] + 0.06)


def test_source_with_subfolder_is_kept(folder, tmp_path):
    (folder / "trials").mkdir()
    rows = read_rows(folder / MAN)
    for r in rows[1:]:
        shutil.move(folder / r[3], folder / "trials" / r[3])
        r[3] = f"trials/{r[3]}"
    write_rows(folder / MAN, rows)
    loaded = read_interchange(folder)
    assert loaded.trials[0].source == f"trials/{TN1}"
    out = write_interchange(loaded, tmp_path / "out")
    assert (out / "trials" / TN1).is_file()
    assert read_rows(out / MAN) == rows


def test_manifest_without_sampling_period_defaults(folder):
    drop_column(folder / MAN, "sampling_period_s")
    assert [t.sampling_period_s for t in read_interchange(folder)] == [0.01] * 3


def test_column_order_is_free_and_hidden_csv_ignored(folder):
    rows = read_rows(folder / TN1)
    write_rows(folder / TN1, [r[::-1] for r in rows])
    (folder / ".ipynb_checkpoints").mkdir()
    shutil.copy(folder / TN2, folder / ".ipynb_checkpoints" / "copy.csv")
    assert_same_trials(read_interchange(folder), make_cohort())


def test_load_cohort_dispatch(folder, tmp_path):
    assert len(load_cohort(folder)) == 3
    assert len(load_cohort(folder / MAN)) == 3
    nc = read_interchange(folder).save_netcdf(tmp_path / "c.nc")
    assert len(load_cohort(nc)) == 3
    other = tmp_path / "data.txt"
    other.write_text("x")
    with pytest.raises(ValueError, match="data.txt"):
        load_cohort(other)
    with pytest.raises(FileNotFoundError, match="nowhere"):
        load_cohort(tmp_path / "nowhere")


def test_convert_rejects_wrong_targets(folder, tmp_path):
    with pytest.raises(ValueError, match=r"\.nc"):
        convert(folder, tmp_path / "out.h5")
    nc = convert(folder, tmp_path / "c.nc")
    with pytest.raises(ValueError, match=r"\.nc"):
        convert(nc, tmp_path / "d.nc")
    other = tmp_path / "x.csv"
    other.write_text("a")
    with pytest.raises(ValueError, match="x.csv"):
        convert(other, tmp_path / "y.nc")
    with pytest.raises(NotADirectoryError, match="x.csv is a file, not a folder"):
        convert(folder, other / "sub" / "y.nc")  # a path under a file
    # a folder named by its manifest, as every other command takes it
    assert_same_trials(load_cohort(convert(folder / "manifest.csv", tmp_path / "m.nc")), load_cohort(folder))


# --------------------------------------------------------------------------- error objects
def test_problem_and_error_text():
    p = Problem("trials/TN-left-1.csv", "angle_deg", 17, "non-numeric value 'abc'")
    assert str(p) == "trials/TN-left-1.csv, column 'angle_deg', row 17: non-numeric value 'abc'"
    assert str(Problem(MAN, None, None, "missing")) == "manifest.csv: missing"
    err = InterchangeError([Problem("f.csv", "time_s", i + 2, "bad") for i in range(60)], "ctx")
    lines = str(err).splitlines()
    # the first problem on the first line, naming file, column and row; the others below
    assert lines[0] == "ctx: f.csv, column 'time_s', row 2: bad (and 59 more problems, listed below)"
    assert len(lines) == 1 + 49 + 1 and lines[-1].strip() == "... and 10 more"
    assert str(InterchangeError([p], "ctx")) == f"ctx: {p}"
    assert isinstance(err, ValueError)
    # a summary of further rows counts them: the header's count is of rows, not of lines
    summary = Problem("f.csv", "angle_deg", None, "25 more rows like this (rows 107 to 131)", count=25)
    assert str(InterchangeError([p, p, summary], "ctx")).splitlines()[0].endswith("(and 26 more problems, listed below)")
    copy = pickle.loads(pickle.dumps(err))
    assert copy.problems == err.problems and str(copy) == str(err)


# --------------------------------------------------------------------------- rule 1: manifest
def test_missing_manifest(folder):
    (folder / MAN).unlink()
    err = problems_of(folder)
    assert_problem(err, MAN, None, None, "missing")


def test_manifest_missing_column(folder):
    drop_column(folder / MAN, "leg")
    assert_problem(problems_of(folder), MAN, "leg", 1, "missing column")


def test_manifest_unknown_column(folder):
    add_column(folder / MAN, "notes", "ok")
    assert_problem(problems_of(folder), MAN, "notes", 1, "unknown column")


@pytest.mark.parametrize(
    "line, col, value, text",
    [
        (3, "trial", "two", "non-numeric value 'two'"),
        (3, "trial", "0", "non-positive"),
        (4, "trial", "-1", "non-positive"),
        (3, "trial", "1.5", "not an integer"),
        (2, "leg", "up", "not 'left' or 'right'"),
        (4, "leg", "Right", "not 'left' or 'right'"),
        (2, "subject", "", "empty subject"),
        (3, "sampling_period_s", "abc", "non-numeric"),
        (3, "sampling_period_s", "0", "positive"),
        (4, "sampling_period_s", "-0.01", "positive"),
        (2, "sampling_period_s", "nan", "positive finite"),
    ],
)
def test_manifest_bad_values(folder, line, col, value, text):
    set_cell(folder / MAN, line, col, value)
    assert_problem(problems_of(folder), MAN, col, line, text)


# --------------------------------------------------------------------------- rule 2: listing
def test_duplicated_trial(folder):
    set_cell(folder / MAN, 3, "trial", "1")  # TN-left trial 2 -> 1, as row 2
    p = assert_problem(problems_of(folder), MAN, None, 3, "listed twice")
    assert "rows 2 and 3" in p.message and "TN-left trial 1" in p.message


def test_file_listed_twice(folder):
    set_cell(folder / MAN, 3, "file", TN1)
    err = problems_of(folder)
    p = assert_problem(err, MAN, "file", 3, "listed twice")
    assert "rows 2 and 3" in p.message
    assert_problem(err, TN2, None, None, "not listed")  # now an orphan


def test_listed_file_missing(folder):
    (folder / TN2).unlink()
    assert_problem(problems_of(folder), MAN, "file", 3, "does not exist")


@pytest.mark.parametrize("path", ["/etc/passwd", "../elsewhere.csv"])
def test_listed_file_outside_folder(folder, path):
    set_cell(folder / MAN, 4, "file", path)
    assert_problem(problems_of(folder), MAN, "file", 4, "relative to the folder")


def test_missing_trial_numbers(folder):
    set_cell(folder / MAN, 3, "trial", "3")  # TN-left now has trials 1 and 3
    p = assert_problem(problems_of(folder), MAN, "trial", 3, "trial 2 missing")
    assert "TN-left" in p.message and "rows of TN-left: 2, 3" in p.message


def test_unlisted_csv(folder):
    (folder / "extra").mkdir()
    shutil.copy(folder / TN1, folder / "extra" / "TN-left-trial3.csv")
    assert_problem(problems_of(folder), "extra/TN-left-trial3.csv", None, None, "not listed in manifest.csv")


# --------------------------------------------------------------------------- rule 3: trial CSV structure
def test_trial_missing_column(folder):
    drop_column(folder / TN2, "angle_deg")
    assert_problem(problems_of(folder), TN2, "angle_deg", 1, "missing column")


def test_a_trial_without_a_stimulation_column_is_read_as_a_pendulum_test(folder):
    drop_column(folder / TN2, "stimulation")
    with pytest.warns(DataWarning, match=rf"{TN2} has no column stimulation .*read as a pendulum test without pulses"):
        read = read_interchange(folder)
    assert not np.any(read.get("TN-left", 2).stimulation)
    # the other trials keep their pulses, and the leg's angle is read as written
    assert np.count_nonzero(read.get("TN-left", 1).stimulation) == len(PULSES)
    np.testing.assert_allclose(read.get("TN-left", 2).angle_deg, make_trial("TN", "left", 2, 0.7).angle_deg, atol=1e-9)


def test_a_pendulum_test_beside_a_stimulators_log_is_not_a_mixed_scale(folder):
    """A leg logged as pulse widths, with a pendulum test that has no stimulation column: no
    warning of levels and charges mixed (a trial without pulses has no scale)."""
    rows = read_rows(folder / TN1)
    j = rows[0].index("stimulation")
    rows[0][j] = "pulse_width_us"
    write_rows(folder / TN1, [rows[0]] + [r[:j] + [str(300 * float(r[j]))] + r[j + 1:] for r in rows[1:]])
    drop_column(folder / TN2, "stimulation")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read = read_interchange(folder)
    said = [str(w.message) for w in caught]
    assert any("read as a pendulum test" in m for m in said)
    assert not any("give every trial of a leg the same way" in m for m in said), said
    assert np.max(read.get("TN-left", 1).stimulation) == pytest.approx(1.0)
    # a pendulum test given as levels of 0 is not mixed up either, but pulses given as levels are
    add_column(folder / TN2, "stimulation", "0")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read_interchange(folder)
    assert not any("give every trial of a leg the same way" in str(w.message) for w in caught)
    set_cell(folder / TN2, 10, "stimulation", "0.5")
    with pytest.warns(DataWarning, match="give every trial of a leg the same way"):
        read_interchange(folder)


def test_a_loggers_column_names_are_matched_to_the_formats_by_their_first_word(folder):
    rows = read_rows(folder / TN2)
    names = {"time_s": "Time (s)", "angle_deg": "Angle (deg)", "stimulation": "Stim", "acceleration_deg_s2": "Accel"}
    rows[0] = [names.get(c, c) for c in rows[0]]
    write_rows(folder / TN2, rows)
    err = problems_of(folder)
    for ours, theirs in names.items():
        if theirs in rows[0]:
            assert_problem(err, TN2, theirs, 1, f"did you mean {ours!r}?")


def test_without_an_accelerometer_the_acceleration_is_derived_and_not_written_back(folder, tmp_path):
    drop_column(folder / TN2, "acceleration_deg_s2")
    cohort = read_interchange(folder)
    t = cohort.get("TN-left", 2)
    assert not t.acceleration_measured and cohort.get("TN-left", 1).acceleration_measured
    np.testing.assert_array_equal(t.acceleration_deg_s2, derive_acceleration(t.angle_deg, DT))
    # the derivative of a sinusoid: the derived acceleration is the true one away from the ends
    w = 2 * np.pi * 0.8
    true = -30.0 * w**2 * np.sin(w * t.time_s + 0.7)
    assert np.max(np.abs(t.acceleration_deg_s2 - true)[10:-10]) < 0.01 * np.max(np.abs(true))
    out = write_interchange(cohort, tmp_path / "out")
    assert "acceleration_deg_s2" not in (out / TN2).read_text().splitlines()[0]
    assert "acceleration_deg_s2" in (out / TN1).read_text().splitlines()[0]
    nc = cohort.save_netcdf(tmp_path / "c.nc")
    assert not load_cohort(nc).get("TN-left", 2).acceleration_measured


def test_trial_unknown_column(folder):
    add_column(folder / JM1, "force_N", "1.0")
    assert_problem(problems_of(folder), JM1, "force_N", 1, "unknown column")


def test_trial_misspelt_column_gets_a_hint(folder):
    rows = read_rows(folder / TN1)
    rows[0][rows[0].index("angle_deg")] = "angle_degs"
    write_rows(folder / TN1, rows)
    err = problems_of(folder)
    assert_problem(err, TN1, "angle_degs", 1, "did you mean 'angle_deg'")
    assert_problem(err, TN1, "angle_deg", 1, "missing column")


def test_trial_empty_file(folder):
    (folder / TN1).write_text("")
    assert_problem(problems_of(folder), TN1, None, None, "empty file")


def test_trial_header_only(folder):
    (folder / TN1).write_text(",".join(read_rows(folder / TN1)[0]) + "\n")
    assert_problem(problems_of(folder), TN1, None, None, "no data rows")


def test_trial_wrong_number_of_fields(folder):
    rows = read_rows(folder / TN1)
    rows[9] = rows[9][:-1]  # line 10
    write_rows(folder / TN1, rows)
    assert_problem(problems_of(folder), TN1, None, 10, "3 fields, expected 4")


@pytest.mark.parametrize("value", ["abc", "", "1,5"])
def test_trial_non_numeric(folder, value):
    set_cell(folder / TN1, 17, "angle_deg", value)
    assert_problem(problems_of(folder), TN1, "angle_deg", 17, f"non-numeric value {value!r}")


@pytest.mark.parametrize("value", ["nan", "NaN", "inf", "-inf", "Infinity"])
@pytest.mark.parametrize("col", ["acceleration_deg_s2", "time_s"])
def test_trial_non_finite(folder, value, col):
    set_cell(folder / JM1, 42, col, value)
    assert_problem(problems_of(folder), JM1, col, 42, f"non-finite value {value!r}")


def test_non_finite_measured_velocity(measured_folder):
    set_cell(measured_folder / TN2, 5, "velocity_deg_s", "nan")
    assert_problem(problems_of(measured_folder), TN2, "velocity_deg_s", 5, "non-finite")


def test_many_bad_cells_are_summarised(folder):
    rows = read_rows(folder / TN1)
    j = rows[0].index("angle_deg")
    for r in rows[1:]:
        r[j] = "x"
    write_rows(folder / TN1, rows)
    err = problems_of(folder)
    assert len([p for p in err.problems if p.file == TN1]) == 6
    assert_problem(err, TN1, "angle_deg", 2, "non-numeric value 'x'")
    assert_problem(err, TN1, "angle_deg", None, f"{N - 5} more rows")


# --------------------------------------------------------------------------- rule 4: time
def test_time_not_increasing(folder):
    t = column(folder / TN1, "time_s")
    set_cell(folder / TN1, 50, "time_s", repr(float(t[47])))  # line 50 holds sample 48; equal to line 49
    assert_problem(problems_of(folder), TN1, "time_s", 50, "not strictly increasing")


def test_time_non_uniform(folder):
    t = column(folder / TN1, "time_s")
    set_cell(folder / TN1, 50, "time_s", repr(float(t[48]) + 0.002))
    p = assert_problem(problems_of(folder), TN1, "time_s", 50, "non-uniform sampling")
    assert "0.012" in p.message and "0.01" in p.message


def test_sampling_period_disagrees_with_csv(folder):
    set_column(folder / JM1, "time_s", np.arange(N) * 0.02)
    p = assert_problem(problems_of(folder), JM1, "time_s", 2, "disagrees")
    assert "0.02" in p.message and "0.01" in p.message and "manifest.csv row 4" in p.message


def test_sampling_period_disagrees_with_manifest(folder):
    set_cell(folder / MAN, 2, "sampling_period_s", "0.001")
    p = assert_problem(problems_of(folder), TN1, "time_s", 2, "disagrees")
    assert "0.001" in p.message


def test_sampling_period_within_tolerance(folder):
    set_cell(folder / MAN, 2, "sampling_period_s", "0.010005")  # 5e-4 relative
    assert read_interchange(folder).trials[0].sampling_period_s == 0.010005


# --------------------------------------------------------------------------- rules 5 and 6
@pytest.mark.parametrize("value", ["1.5", "-0.1", "100"])
def test_stimulation_out_of_range(folder, value):
    set_cell(folder / TN2, 30, "stimulation", value)
    assert_problem(problems_of(folder), TN2, "stimulation", 30, "outside [0, 1]")


def test_angle_in_radians(folder):
    angle = np.deg2rad(column(folder / JM1, "angle_deg"))
    set_column(folder / JM1, "angle_deg", angle)
    err = problems_of(folder)
    (p,) = [p for p in err.problems if p.file == JM1 and p.column == "angle_deg"]
    assert "look like radians" in p.message and 2 <= p.row < N + 2


def test_radians_without_stimulation_are_found(folder):
    set_column(folder / JM1, "angle_deg", np.deg2rad(column(folder / JM1, "angle_deg")))
    set_column(folder / JM1, "stimulation", np.zeros(N))
    err = problems_of(folder)
    assert any(p.file == JM1 and p.column == "angle_deg" and "radians" in p.message for p in err.problems)


def test_radians_with_a_glitch_are_found(folder):
    angle = np.deg2rad(column(folder / JM1, "angle_deg"))
    angle[7] = 40.0  # one sample in degrees, or a spike
    set_column(folder / JM1, "angle_deg", angle)
    err = problems_of(folder)
    assert any(p.file == JM1 and p.column == "angle_deg" and "radians" in p.message for p in err.problems)


def test_a_resting_trial_without_pulses_is_not_taken_for_radians(folder):
    set_column(folder / JM1, "angle_deg", 0.2 * np.sin(np.arange(N) / 7.0))  # tiny sway, in degrees
    set_column(folder / JM1, "stimulation", np.zeros(N))
    with pytest.warns(DataWarning, match=f"{JM1} \\(JM-right trial 1\\): acceleration_deg_s2 hardly follows"):
        read_interchange(folder)  # read, with a warning: this acceleration is not the sway's


# --------------------------------------------------------------------------- all problems at once
def test_two_errors_in_two_files(folder):
    set_cell(folder / TN1, 17, "angle_deg", "abc")
    set_cell(folder / JM1, 30, "stimulation", "2")
    result = None
    with pytest.raises(InterchangeError) as info:
        result = read_interchange(folder)
    assert result is None
    err = info.value
    assert_problem(err, TN1, "angle_deg", 17, "non-numeric")
    assert_problem(err, JM1, "stimulation", 30, "outside")
    assert len(err.problems) == 2
    first = str(err).splitlines()[0]
    assert TN1 in first and "'angle_deg'" in first and "row 17" in first and first.endswith("1 more problem, listed below)")


# --------------------------------------------------------------------------- writing
def test_write_refuses_a_cohort_that_would_not_read_back(tmp_path, cohort):
    gap = cohort.select(trials=[2])  # TN-left trial 2 without trial 1
    with pytest.raises(InterchangeError) as info:
        write_interchange(gap, tmp_path / "out")
    assert_problem(info.value, MAN, "trial", 2, "trial 1 missing")
    bad = make_trial("TN", "left", 1, 0.0)
    stim = bad.stimulation.copy()
    stim[10] = 2.0
    with pytest.raises(InterchangeError) as info:
        write_interchange(Cohort((bad.replace(stimulation=stim),)), tmp_path / "out")
    assert_problem(info.value, TN1, "stimulation", 12, "outside")
    assert not (tmp_path / "out").exists()


def test_write_uses_default_names_for_unusable_sources(tmp_path):
    trials = [
        make_trial("TN", "left", 1, 0.0).replace(source="/raw/TN_L1.mat"),
        make_trial("TN", "left", 2, 0.0).replace(source="../x.csv"),
        make_trial("JM", "right", 1, 0.0).replace(source="JM/r1.csv"),
    ]
    out = write_interchange(Cohort(trials), tmp_path / "out")
    assert [r[3] for r in read_rows(out / MAN)[1:]] == [TN1, TN2, "JM/r1.csv"]


def test_default_file_names_spell_subjects_as_the_report_does(tmp_path):
    """Accents are dropped (Müller → Muller) and other characters become ``_``, as in the report's file
    names; the subject itself is kept whole in the manifest."""
    trials = [make_trial("Müller", "left", 1, 0.0), make_trial("患者 1", "left", 1, 0.0)]
    out = write_interchange(Cohort(trials), tmp_path / "out")
    rows = read_rows(out / MAN)[1:]
    assert [r[3] for r in rows] == ["Muller-left-trial1.csv", "___1-left-trial1.csv"]
    assert [t.subject for t in read_interchange(out)] == ["Müller", "患者 1"]


def test_writing_into_a_folder_with_data_needs_overwrite_and_deletes_nothing(folder, cohort):
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    with pytest.raises(FileExistsError, match="not empty"):
        write_interchange(cohort.select(legs=["TN-left"]), folder)
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before  # nothing written, nothing deleted
    # with overwrite, a CSV the new manifest would not list is refused (the folder would not read back) ...
    with pytest.raises(FileExistsError, match=JM1):
        write_interchange(cohort.select(legs=["TN-left"]), folder, overwrite=True)
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
    # ... and the same trials are replaced in place, other files kept
    (folder / "notes.txt").write_text("keep me")
    write_interchange(cohort, folder, overwrite=True)
    assert (folder / "notes.txt").read_text() == "keep me"
    assert len(read_interchange(folder)) == 3


def _fail_after_first(monkeypatch):
    original = ix._write_trial_csv
    calls = []

    def flaky(trial, path):
        calls.append(path)
        if len(calls) > 1:
            Path(path).write_text("time_s,angle")  # half written
            raise OSError("disk full")
        original(trial, path)

    monkeypatch.setattr(ix, "_write_trial_csv", flaky)
    return calls


def test_failed_write_leaves_no_folder(tmp_path, cohort, monkeypatch):
    calls = _fail_after_first(monkeypatch)
    target = tmp_path / "new" / "cohort"
    with pytest.raises(OSError, match="disk full"):
        write_interchange(cohort, target)
    assert len(calls) == 2
    assert not (target / MAN).exists()
    assert not (tmp_path / "new").exists()


def test_failed_write_keeps_previous_folder(folder, monkeypatch):
    before = {p.name: p.read_bytes() for p in folder.iterdir()}
    changed = make_cohort(measured=True)
    _fail_after_first(monkeypatch)
    with pytest.raises(OSError, match="disk full"):
        write_interchange(changed, folder, overwrite=True)
    assert {p.name: p.read_bytes() for p in folder.iterdir()} == before
    assert_same_trials(read_interchange(folder), make_cohort())


def test_spreadsheet_export_bom_and_crlf(folder):
    for name in (MAN, TN1):
        text = (folder / name).read_text()
        (folder / name).write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    assert_same_trials(read_interchange(folder), make_cohort())
    set_cell(folder / TN1, 17, "angle_deg", "abc")
    assert_problem(problems_of(folder), TN1, "angle_deg", 17, "non-numeric")


def test_write_refuses_an_empty_cohort(tmp_path):
    with pytest.raises(InterchangeError, match="no trials"):
        write_interchange(Cohort(()), tmp_path / "empty")


# --------------------------------------------------------------------------- start_s / end_s
def _add_manifest_columns(folder: Path, **columns: list[str]) -> None:
    rows = read_rows(folder / MAN)
    for name, values in columns.items():
        rows[0].append(name)
        for r, v in zip(rows[1:], values):
            r.append(v)
    write_rows(folder / MAN, rows)


def test_start_and_end_cut_a_trial_and_keep_its_times(folder, cohort):
    _add_manifest_columns(folder, start_s=["0.35", "", "1.0"], end_s=["", "2.5", "2.0"])
    got = read_interchange(folder)
    whole = {(t.key, t.trial): t for t in cohort}
    for t, (start, end) in zip(got, [(0.35, None), (None, 2.5), (1.0, 2.0)]):
        w = whole[(t.key, t.trial)]
        keep = (w.time_s >= (start if start is not None else -np.inf)) & (w.time_s <= (end if end is not None else np.inf))
        np.testing.assert_array_equal(t.time_s, w.time_s[keep])
        np.testing.assert_array_equal(t.angle_deg, w.angle_deg[keep])
        np.testing.assert_array_equal(t.velocity_deg_s, w.velocity_deg_s[keep])  # derived from the whole trial
        assert t.velocity_measured is False
    # written back, the cut trials are the data: they read back without the columns (a derived
    # velocity is then derived from the cut recording)
    again = read_interchange(write_interchange(got, folder.parent / "again"))
    for a, b in zip(again, got):
        for name in ("time_s", "angle_deg", "acceleration_deg_s2", "stimulation"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


@pytest.mark.parametrize(
    ("start", "end", "column", "text"),
    [("abc", "", "start_s", "not a time"), ("2.0", "1.0", "end_s", "not after"), ("5.0", "", "start_s", "keep 0"),
     ("", "nan", "end_s", "not a time")],
)
def test_a_bad_start_or_end_is_named(folder, start, end, column, text):
    _add_manifest_columns(folder, start_s=[start, "", ""], end_s=[end, "", ""])
    assert_problem(problems_of(folder), MAN, column, 2, text)


# --------------------------------------------------------------------------- exclude
def test_exclude_column_is_read_kept_in_netcdf_and_written_back(folder, tmp_path):
    flags = np.zeros(N, int)
    flags[:35] = 1  # a release
    flags[200:210] = 1  # an artefact
    add_column(folder / TN1, "exclude", "0")
    rows = read_rows(folder / TN1)
    j = rows[0].index("exclude")
    for r, f in zip(rows[1:], flags):
        r[j] = str(f)
    write_rows(folder / TN1, rows)
    got = read_interchange(folder)
    np.testing.assert_array_equal(got.get("TN-left", 1).exclude, flags.astype(bool))
    assert not got.get("TN-left", 2).exclude.any() and got.get("TN-left", 2).exclude.shape == (N,)
    # NetCDF keeps it; an interchange folder written back has the column only where something is excluded
    nc = tmp_path / "c.nc"
    got.save_netcdf(nc)
    np.testing.assert_array_equal(ix.read_netcdf(nc).get("TN-left", 1).exclude, flags.astype(bool))
    back = write_interchange(got, tmp_path / "back")
    assert "exclude" in read_rows(back / TN1)[0] and "exclude" not in read_rows(back / TN2)[0]
    np.testing.assert_array_equal(read_interchange(back).get("TN-left", 1).exclude, flags.astype(bool))
    # start_s cuts the flags with the samples; the fingerprint sees the flags
    _add_manifest_columns(folder, start_s=["0.2", "", ""])
    cut = read_interchange(folder).get("TN-left", 1)
    np.testing.assert_array_equal(cut.exclude, flags[20:].astype(bool))
    plain = make_cohort()
    assert got.fingerprint(trials=[2]) == plain.fingerprint(trials=[2])
    assert got.fingerprint(trials=[1]) != plain.fingerprint(trials=[1])


@pytest.mark.parametrize(("values", "row", "text"), [({5: "2"}, 6, "not 0 or 1"), ({9: "0.5"}, 10, "not 0 or 1"),
                                                     ({3: "yes"}, 4, "non-numeric")])
def test_a_bad_exclude_flag_is_named(folder, values, row, text):
    add_column(folder / TN1, "exclude", "0")
    for i, v in values.items():
        set_cell(folder / TN1, i + 1, "exclude", v)
    assert_problem(problems_of(folder), TN1, "exclude", row, text)


def test_a_trial_with_every_sample_excluded_is_refused(folder):
    add_column(folder / TN2, "exclude", "1")
    assert_problem(problems_of(folder), TN2, "exclude", None, "at least 2")


def test_excluded_samples_leave_the_prediction_starts():
    from quadshank.evaluation import prediction_starts

    t = make_trial("TN", "left", 1, 0.0)
    flags = np.zeros(N, bool)
    flags[100:105] = True
    starts = prediction_starts(t.replace(exclude=flags), 20)
    runs = starts[:, None] + np.arange(21)[None, :]
    assert not flags[runs].any()
    assert set(prediction_starts(t, 20)) - set(starts) == set(range(80, 105))
    with pytest.raises(ValueError, match="no stretch of 21 samples"):
        prediction_starts(t.replace(exclude=np.arange(N) % 10 == 0), 20)


# --------------------------------------------------------------------------- a stimulator's columns
def _as_stimulator(path: Path, width_per_u: float = 400.0, current: float | None = None) -> np.ndarray:
    """Replace ``stimulation`` by ``pulse_width_us`` (u × width_per_u) and, given, a constant
    ``current_mA`` on the pulses; returns the old stimulation."""
    rows = read_rows(path)
    j = rows[0].index("stimulation")
    u = np.array([float(r[j]) for r in rows[1:]])
    rows[0][j] = "pulse_width_us"
    for r, x in zip(rows[1:], u):
        r[j] = repr(float(x * width_per_u))
    if current is not None:
        rows[0].append("current_mA")
        for r, x in zip(rows[1:], u):
            r.append(repr(float(current if x > 0 else 0.0)))
    write_rows(path, rows)
    return u


def test_a_stimulators_pulse_width_and_current_give_the_relative_charge(folder):
    u1 = _as_stimulator(folder / TN1, 300.0, current=40.0)
    u2 = _as_stimulator(folder / TN2, 150.0, current=40.0)  # half the widths of trial 1
    got = read_interchange(folder)
    top = max(u1.max() * 300.0, u2.max() * 150.0)
    np.testing.assert_allclose(got.get("TN-left", 1).stimulation, u1 * 300.0 / top)
    np.testing.assert_allclose(got.get("TN-left", 2).stimulation, u2 * 150.0 / top)
    assert got.get("TN-left", 1).stimulation.max() == 1.0
    np.testing.assert_array_equal(got.get("JM-right", 1).stimulation, make_cohort().get("JM-right", 1).stimulation)


@pytest.mark.parametrize(("change", "column", "row", "text"), [
    (lambda f: add_column(f, "pulse_width_us", "0"), "pulse_width_us", 1, "either stimulation or pulse_width_us"),
    (lambda f: (_as_stimulator(f), set_cell(f, 22, "pulse_width_us", "-300")), "pulse_width_us", 22, "negative"),
])
def test_a_stimulators_columns_are_checked(folder, change, column, row, text):
    change(folder / TN1)
    assert_problem(problems_of(folder), TN1, column, row, text)


def test_a_small_swing_in_degrees_is_not_taken_for_radians_where_the_accelerometer_agrees(tmp_path):
    """Weak twitches of a knee at rest may keep the angle within ±pi degrees. Where the measured
    acceleration follows the angle's second derivative at its size, both are in degrees; without
    an accelerometer nothing tells the units apart, and the radian rule stands."""
    t = make_trial("TN", "left", 1, 0.0)
    small = t.replace(angle_deg=t.angle_deg / 15.0, acceleration_deg_s2=t.acceleration_deg_s2 / 15.0)  # ±2°
    write_interchange(Cohort((small,)), tmp_path / "small")
    read_interchange(tmp_path / "small")
    (tmp_path / "radians").mkdir()
    shutil.copytree(tmp_path / "small", tmp_path / "radians", dirs_exist_ok=True)
    set_column(tmp_path / "radians" / "TN-left-trial1.csv", "acceleration_deg_s2",
               column(tmp_path / "radians" / "TN-left-trial1.csv", "acceleration_deg_s2") * 180 / np.pi)
    with pytest.raises(InterchangeError, match="radians"):  # an angle in radians beside an acceleration in deg/s²
        read_interchange(tmp_path / "radians")
    drop_column(tmp_path / "small" / "TN-left-trial1.csv", "acceleration_deg_s2")
    with pytest.raises(InterchangeError, match="radians"):
        read_interchange(tmp_path / "small")


def test_subjects_alike_but_for_case_are_named_in_a_warning(tmp_path):
    """``TN`` and ``tn`` are two subjects to the reader, which says so once, with each one's first row."""
    twins = Cohort((make_trial("TN", "left", 1, 0.0), make_trial("tn", "right", 1, 0.7),
                    make_trial("tn", "right", 2, 1.3), make_trial("JM", "right", 1, 0.3)))
    folder = write_interchange(twins, tmp_path / "twins")
    with pytest.warns(DataWarning) as caught:
        back = read_interchange(folder)
    said = [str(w.message) for w in caught if "differ only in case" in str(w.message)]
    assert said == ["manifest.csv: subjects 'TN' (row 2) and 'tn' (row 3) differ only in case and are read as 2 "
                    "subjects; spell them alike if they are one"]
    assert sorted({t.subject for t in back.trials}) == ["JM", "TN", "tn"]


def test_a_subject_with_a_comma_is_read_and_named_in_a_warning(tmp_path):
    """A comma in a subject's name is valid data, but ``--legs`` (comma-separated) cannot name its
    legs: the reader says so once, with the manifest's row, and reads the trials as they are."""
    renamed = Cohort(tuple(make_trial("Smith, J" if t.subject == "TN" else t.subject, t.leg, t.trial, 0.3 * t.trial)
                           for t in make_cohort().trials))
    folder = write_interchange(renamed, tmp_path / "comma")
    with pytest.warns(DataWarning, match=r"row 2: subject 'Smith, J' holds a comma") as caught:
        back = read_interchange(folder)
    assert sum("holds a comma" in str(w.message) for w in caught) == 1
    assert sorted({t.subject for t in back.trials}) == ["JM", "Smith, J"]
    with warnings.catch_warnings():
        warnings.simplefilter("error", DataWarning)
        read_interchange(write_interchange(make_cohort(), tmp_path / "plain"))
