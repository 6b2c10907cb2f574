"""Bad inputs against the command line: every case ends in exit 2 with one ``quadshank: error:``
line naming file, column and row where they exist, no traceback, no summary.json from the run,
and every input file as it was.

The corpus covers CSV folders and NetCDF files (structure, numbers, time, units, listing, links,
unreadable files) and output paths (a file, a path under a file, the data folder itself or a
folder inside it, a folder that holds something else).
"""

from __future__ import annotations

import gzip
import hashlib
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from quadshank.cli import main
from quadshank.data import Cohort, DataWarning, Trial, read_interchange, write_interchange

N = 400
DT = 0.01
T1 = "TN-left-trial1.csv"
T2 = "TN-left-trial2.csv"
J1 = "JM-right-trial1.csv"
MAN = "manifest.csv"


def _trial(subject: str, leg: str, trial: int, phase: float) -> Trial:
    t = np.arange(N) * DT
    w = 2 * np.pi * 0.7
    stim = np.zeros(N)
    stim[[30, 120, 210, 300]] = [1.0, 0.5, 0.8, 0.6]
    return Trial.from_signals(subject, leg, trial, DT, 25 * np.sin(w * t + phase),
                              -25 * w**2 * np.sin(w * t + phase), stim, time_s=t)


def _cohort() -> Cohort:
    return Cohort((_trial("TN", "left", 1, 0.0), _trial("TN", "left", 2, 0.5), _trial("JM", "right", 1, 1.0)))


# ----------------------------------------------------------------------------- CSV cells and rows
def _rows(path: Path) -> list[list[str]]:
    return [line.split(",") for line in path.read_text().splitlines()]


def _write_rows(path: Path, rows) -> None:
    path.write_text("\n".join(",".join(r) for r in rows) + "\n")


def _set_cell(path: Path, row: int, column: str, text: str) -> None:
    rows = _rows(path)
    rows[row - 1][rows[0].index(column)] = text
    _write_rows(path, rows)


def _map_column(path: Path, column: str, f) -> None:
    rows = _rows(path)
    j = rows[0].index(column)
    for r in rows[1:]:
        r[j] = repr(float(f(float(r[j]))))
    _write_rows(path, rows)


def cell(file, column, row, text):
    def mutate(folder: Path):
        _set_cell(folder / file, row, column, text)
        return [file, f"'{column}'", f"row {row}"]
    return mutate


def column_map(file, column, f, expect):
    def mutate(folder: Path):
        _map_column(folder / file, column, f)
        return [file, f"'{column}'", *expect]
    return mutate


def _with_column(path: Path, name: str, value: str | None, first: bool = False) -> list[str]:
    """A column ``name`` added (first, or last) holding ``value`` on every row (None: the row's index)."""
    rows = _rows(path)
    new = [[name] + [str(i) if value is None else value for i in range(len(rows) - 1)]][0]
    _write_rows(path, [[c, *r] if first else [*r, c] for c, r in zip(new, rows)])
    return []


def _blank_between(path: Path, column: str, stride: int) -> list[str]:
    """The column's cells left empty except on every ``stride``-th row."""
    rows = _rows(path)
    j = rows[0].index(column)
    for i, r in enumerate(rows[1:]):
        if i % stride:
            r[j] = ""
    _write_rows(path, rows)
    return []


def _rename_column(path: Path, old: str, new: str) -> list[str]:
    rows = _rows(path)
    rows[0] = [new if c == old else c for c in rows[0]]
    _write_rows(path, rows)
    return []


def _above_header(path: Path, lines: list[str]) -> list[str]:
    path.write_text("\n".join(lines) + "\n" + path.read_text())
    return []


def radians_passive(folder: Path):
    _map_column(folder / J1, "angle_deg", np.deg2rad)
    _map_column(folder / J1, "acceleration_deg_s2", np.deg2rad)
    _map_column(folder / J1, "stimulation", lambda v: 0.0)
    return [J1, "'angle_deg'", "radians"]


def radians_glitch(folder: Path):
    _map_column(folder / J1, "angle_deg", np.deg2rad)
    _set_cell(folder / J1, 9, "angle_deg", "57.0")
    return [J1, "'angle_deg'", "radians"]


def truncated_row(folder: Path):
    rows = _rows(folder / T1)
    rows[40] = rows[40][:2]
    _write_rows(folder / T1, rows)
    return [T1, "row 41", "fields"]


def decimal_comma(folder: Path):
    text = (folder / T1).read_text().splitlines()
    text[10] = text[10].replace(".", ",", 1)
    (folder / T1).write_text("\n".join(text) + "\n")
    return [T1, "row 11"]


def semicolons(folder: Path):
    (folder / T1).write_text((folder / T1).read_text().replace(",", ";"))
    return [T1, "row 1", "separated by semicolons"]


def drop_column(file, column):
    def mutate(folder: Path):
        rows = _rows(folder / file)
        j = rows[0].index(column)
        _write_rows(folder / file, [r[:j] + r[j + 1:] for r in rows])
        return [file, f"'{column}'", "missing column"]
    return mutate


def extra_column(folder: Path):
    rows = _rows(folder / T1)
    _write_rows(folder / T1, [r + (["torque"] if i == 0 else ["1.0"]) for i, r in enumerate(rows)])
    return [T1, "'torque'", "row 1"]


def time_step(row: int, value: str, expect: str):
    def mutate(folder: Path):
        _set_cell(folder / T2, row, "time_s", value)
        return [T2, "'time_s'", f"row {row}", expect]
    return mutate


def time_gap(folder: Path):
    rows = _rows(folder / T2)
    j = rows[0].index("time_s")
    for r in rows[60:]:  # from row 61 on, 50 ms later: a gap in the recording
        r[j] = repr(float(r[j]) + 0.05)
    _write_rows(folder / T2, rows)
    return [T2, "'time_s'", "row 61", "non-uniform"]


def replace_file(file, data: bytes):
    def mutate(folder: Path):
        (folder / file).write_bytes(data)
        return [file]
    return mutate


def gzipped(folder: Path):
    (folder / T1).write_bytes(gzip.compress((folder / T1).read_bytes()))
    return [T1]


def header_only(folder: Path):
    (folder / T1).write_text((folder / T1).read_text().splitlines()[0] + "\n")
    return [T1, "no data rows"]


def manifest_cell(row, column, text, expect=""):
    def mutate(folder: Path):
        _set_cell(folder / MAN, row, column, text)
        return [MAN, f"'{column}'", f"row {row}", expect]
    return mutate


def period_disagrees(folder: Path):
    _set_cell(folder / MAN, 2, "sampling_period_s", "0.02")
    return [T1, "'time_s'", "row 2", "disagrees", "manifest.csv row 2"]


def manifest_duplicate(folder: Path):
    rows = _rows(folder / MAN)
    rows[2][2] = "1"  # TN-left trial 2 listed as trial 1 again
    _write_rows(folder / MAN, rows)
    return [MAN, "row 3", "listed twice"]


def link_outside(folder: Path):
    outside = folder.parent / "elsewhere.csv"
    outside.write_text("secret first line\n1,2,3\n")
    (folder / T1).unlink()
    os.symlink(outside, folder / T1)
    return [MAN, "'file'", "outside the folder"]


def link_to_a_listed_file(folder: Path):
    (folder / T2).unlink()
    os.symlink(folder / T1, folder / T2)
    return [MAN, "'file'", "row 3", "is a link to 'TN-left-trial1.csv' (row 2)"]


def no_header(folder: Path):
    lines = (folder / T1).read_text().splitlines()
    (folder / T1).write_text("\n".join(lines[1:]) + "\n")  # a MATLAB writematrix export: numbers only
    return [T1, "row 1", "the line of column names is missing"]


def acceleration_not_recorded(folder: Path):
    rows = _rows(folder / T1)
    k = rows[0].index("acceleration_deg_s2")
    _write_rows(folder / T1, [rows[0]] + [r[:k] + [""] + r[k + 1:] for r in rows[1:]])
    return [T1, "'acceleration_deg_s2'", "Leave the column out"]


def unlisted(folder: Path):
    shutil.copy(folder / T1, folder / "extra.csv")
    return ["extra.csv", "not listed"]


def no_manifest(folder: Path):
    (folder / MAN).unlink()
    return [MAN, "missing"]


def empty_manifest(folder: Path):
    (folder / MAN).write_text("")
    return [MAN, "empty"]


def stray_quote(folder: Path):
    lines = (folder / T1).read_text().splitlines()
    lines[50] = '"' + lines[50]  # line 51 opens a quote nothing closes
    (folder / T1).write_text("\n".join(lines) + "\n")
    return [T1, "row 51", "quote"]


def quoted_line_break(folder: Path):
    text = (folder / MAN).read_text().splitlines()
    text[1] = '"T\nN"' + text[1][len("TN"):]  # row 2's subject holds a line break
    (folder / MAN).write_text("\n".join(text) + "\n")
    return [MAN, "row 2", "line break"]


def latin1_cell(folder: Path):
    """A degree sign saved by a spreadsheet in Windows-1252, far beyond the first kilobytes of the file."""
    rows = _rows(folder / T1)
    rows[299][rows[0].index("angle_deg")] += "\u00b0"
    (folder / T1).write_bytes(("\n".join(",".join(r) for r in rows) + "\n").encode("latin-1"))
    return [T1, "'angle_deg'", "row 300", "not UTF-8 text: byte 0xb0", "°'"]


def manifest_a_folder(folder: Path):
    (folder / MAN).unlink()
    (folder / MAN).mkdir()
    return [MAN, "not a regular file"]


CSV_CASES = {
    "text in a cell": cell(T1, "angle_deg", 17, "abc"),
    "digit separators": cell(T1, "acceleration_deg_s2", 5, "1_000"),
    "non-ASCII digits": cell(T1, "angle_deg", 6, "١٢"),
    "full-width digits": cell(J1, "angle_deg", 8, "１２"),
    "nan": cell(T1, "stimulation", 20, "nan"),
    "infinity": cell(T2, "angle_deg", 30, "inf"),
    "empty cell": cell(T1, "angle_deg", 12, ""),
    "hex number": cell(T1, "acceleration_deg_s2", 14, "0x1A"),
    "stimulation above 1": cell(T1, "stimulation", 32, "1.5"),
    "stimulation negative": cell(J1, "stimulation", 50, "-0.2"),
    "stimulation in percent": column_map(T2, "stimulation", lambda v: 100 * v, ["outside [0, 1]", "levels in percent"]),
    "stimulation in mA": column_map(T2, "stimulation", lambda v: 150 * v, ["outside [0, 1]", "as the column current_mA"]),
    "a trigger in volts": column_map(T2, "stimulation", lambda v: 5.0 * (v > 0), ["every pulse is 5, outside [0, 1]: a trigger channel"]),
    "a trigger recorded as an analog signal": column_map(T2, "stimulation", lambda v: 5.0 if v > 0 else 0.004,
                                                         ["small nonzero", "a trigger channel recorded as an analog"]),
    "an analog trigger with edges, its baseline mostly 0": lambda folder: _map_column_indexed(
        folder / T2, "stimulation", lambda i: 5.0 if i in (30, 120, 210, 300) else 2.5 if i in (31, 121) else
        0.003 if i % 7 == 0 else 0.0) or [T2, "a trigger channel recorded as an analog"],
    "radians": column_map(J1, "angle_deg", np.deg2rad, ["radians"]),
    "radians with a glitch": radians_glitch,
    "radians without pulses": radians_passive,
    "truncated row": truncated_row,
    "decimal comma": decimal_comma,
    "semicolons": semicolons,
    "missing column": drop_column(T1, "angle_deg"),
    "another joint's angle": lambda folder: _with_column(folder / T1, "hip_angle_deg", "3.0")
    + [T1, "'hip_angle_deg'", "a channel quadshank does not read"],
    "a row index": lambda folder: _with_column(folder / T1, "", None, first=True) + [T1, "a row index"],
    "time in milliseconds": column_map(T2, "time_s", lambda v: 1000 * v, ["is time_s in milliseconds"]),
    "time_ms for time_s": lambda folder: _rename_column(folder / T1, "time_s", "time_ms")
    + [T1, "did you mean 'time_s'? (in seconds: the values divided by 1000)"],
    "a rate for the period": manifest_cell(2, "sampling_period_s", "100", "or a rate in Hz"),
    "a file name in another case": manifest_cell(2, "file", T1.lower(), "differs from it only in case"),
    "a logger's settings above the header": lambda folder: _above_header(folder / J1, ["Logger,DataQ 4108",
                                                                                       "Date,2026-11-30", ""])
    + [J1, "are on line 4", "remove the 3 lines above them"],
    "the angle on every 4th row only": lambda folder: _blank_between(folder / T1, "angle_deg", 4)
    + [T1, "'angle_deg'", "a value on every 4th row only"],
    "a title with a semicolon above the header": lambda folder: _above_header(folder / J1, ["Knee pendulum; JM right"])
    + [J1, "are on line 2", "remove the 1 line above them"],
    "a logger's closing line": lambda folder: (folder / T1).write_text((folder / T1).read_text() + "END\n") and []
    + [T1, "a logger's closing line or a note"],
    "a rate as the period's column": lambda folder: _rename_column(folder / MAN, "sampling_period_s",
                                                                    "sampling_rate_hz") + [MAN, "1 over a rate in Hz"],
    "a manifest's notes": lambda folder: _with_column(folder / MAN, "notes", "ok") + [MAN, "notes or bookkeeping"],
    "a stimulation left empty where no pulse": lambda folder: cell(T1, "stimulation", 3, "")(folder)
    + ["write 0 where no pulse was delivered"],
    "the stimulation column under another name": lambda folder: _rename_column(folder / T1, "stimulation", "stim")
    + [T1, "'stim'", "did you mean 'stimulation'?"],
    "a spreadsheet's #N/A": lambda folder: cell(T1, "angle_deg", 5, "#N/A")(folder) + ["'#N/A'"],
    "a spreadsheet's #N/A first in its row": lambda folder: cell(T1, "time_s", 5, "#N/A")(folder) + ["'#N/A'"],
    "a word for false": lambda folder: cell(T1, "stimulation", 7, "FALSE")(folder) + ["write 1 or 0"],
    "a clock time": lambda folder: cell(T2, "time_s", 9, "14:22:01.00")(folder) + ["a clock time"],
    "angle in tenths of a degree": column_map(J1, "angle_deg", lambda v: round(10 * v),
                                              ["the angle spans", "tenths or hundredths of a degree"]),
    "unknown column": extra_column,
    "time repeated": time_step(21, "0.18", "not strictly increasing"),
    "time decreasing": time_step(40, "0.01", "not strictly increasing"),
    "time gap": time_gap,
    "binary file": replace_file(T1, bytes(range(256)) * 8),
    "gzip file": gzipped,
    "header only": header_only,
    "leg capitalised": manifest_cell(2, "leg", "Left", "'left' or 'right'"),
    "leg with a Cyrillic e": manifest_cell(2, "leg", "l\u0435ft", "'l\\u0435ft' is not 'left' or 'right', which holds characters outside ASCII"),
    "trial gap": manifest_cell(3, "trial", "3", "missing"),
    "trial number a time stamp": manifest_cell(2, "trial", "20230515143000", "a date or a time stamp"),
    "a file linked to another listed": link_to_a_listed_file,
    "a workbook named .csv": lambda folder: replace_file(T1, b"PK\x03\x04" + bytes(range(256)) * 4)(folder)
    + ["a zip archive (an Excel .xlsx", "export the data as CSV"],
    "no header line": no_header,
    "acceleration column empty": acceleration_not_recorded,
    "trial number with separator": manifest_cell(2, "trial", "1_0"),
    "trial number not ASCII": manifest_cell(2, "trial", "١"),
    "trial number overflowing": manifest_cell(2, "trial", "1e400"),
    "value overflowing": cell(T1, "angle_deg", 9, "1e400"),
    "file missing": manifest_cell(2, "file", "nothere.csv", "does not exist"),
    "path traversal": manifest_cell(2, "file", "../x.csv", "inside it"),
    "period disagrees": period_disagrees,
    "period not a number": manifest_cell(2, "sampling_period_s", "ten ms"),
    "trial listed twice": manifest_duplicate,
    "link outside the folder": link_outside,
    "unlisted CSV": unlisted,
    "no manifest": no_manifest,
    "empty manifest": empty_manifest,
    "stray quote": stray_quote,
    "line break in a quoted subject": quoted_line_break,
    "period in milliseconds": manifest_cell(2, "sampling_period_s", "10", "milliseconds"),
    "subject with a control character": manifest_cell(2, "subject", "T\tN", "control character"),
    "a cell in Latin-1": latin1_cell,
    "the manifest a folder": manifest_a_folder,
}


# ----------------------------------------------------------------------------- NetCDF files
def nc_bytes(data: bytes):
    def mutate(nc: Path):
        nc.write_bytes(data)
        return [nc.name, "not a readable"]
    return mutate


def nc_truncated(nc: Path):
    nc.write_bytes(nc.read_bytes()[: nc.stat().st_size // 2])
    return [nc.name]


def nc_edit(edit, expect):
    def mutate(nc: Path):
        with xr.open_dataset(nc, engine="h5netcdf") as ds:
            ds = ds.load()
        ds = edit(ds)
        nc.unlink()
        ds.to_netcdf(nc, engine="h5netcdf")
        return [nc.name, *expect]
    return mutate


def _scaled(name, factor):
    def edit(ds):
        ds[name] = ds[name] * factor
        return ds
    return edit


def _coord(name, index, value):
    def edit(ds):
        values = ds[name].values.copy()
        values[index] = value
        return ds.assign_coords({name: ("trial", values)})
    return edit


def _sample(name, trial, sample, value):
    def edit(ds):
        values = ds[name].values.copy()
        values[trial, sample] = value
        ds[name] = (("trial", "sample"), values)
        return ds
    return edit


def _attrs(ds):
    ds.attrs["format"] = "something-else"
    return ds


NC_CASES = {
    "random bytes": nc_bytes(os.urandom(4096)),
    "empty file": nc_bytes(b""),
    "CSV text": nc_bytes(b"time_s,angle_deg\n0,1\n"),
    "truncated": nc_truncated,
    "radians": nc_edit(_scaled("angle_deg", np.pi / 180), ["[TN-left trial 1]", "'angle_deg'", "radians"]),
    "stimulation in percent": nc_edit(_scaled("stimulation", 100.0), ["'stimulation'", "outside [0, 1]", "levels in percent"]),
    "leg capitalised": nc_edit(_coord("leg", 0, "Left"), ["'leg'", "entry 1"]),
    "trial gap": nc_edit(_coord("trial_number", 1, 3), ["'trial'", "missing"]),
    "time repeated": nc_edit(_sample("time_s", 1, 10, 0.09), ["[TN-left trial 2]", "'time_s'", "sample 11"]),
    "nan angle": nc_edit(_sample("angle_deg", 2, 5, np.nan), ["[JM-right trial 1]", "'angle_deg'", "sample 6"]),
    "another format": nc_edit(_attrs, ["not a quadshank cohort"]),
    "period disagrees": nc_edit(_coord("sampling_period_s", 0, 0.02), ["[TN-left trial 1]", "'time_s'", "disagrees"]),
    "variable missing": nc_edit(lambda ds: ds.drop_vars("acceleration_deg_s2"), ["not a readable"]),
}


# ----------------------------------------------------------------------------- running
def _hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and not p.is_symlink()}


def _run(argv, capsys) -> tuple[int, list[str]]:
    rc = main(["--quiet", *argv])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return rc, err.splitlines()


def _assert_refused(rc, lines, expect, out: Path | None) -> None:
    assert rc == 2, lines
    errors = [line for line in lines if line.startswith("quadshank: error:")]
    assert len(errors) == 1 and lines[0] == errors[0], lines  # the error first, in one line
    for text in filter(None, expect):
        assert text in errors[0], f"{text!r} not in {errors[0]!r}"
    if out is not None:
        assert not (out / "summary.json").exists()


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("base")
    write_interchange(_cohort(), root / "data")
    _cohort().save_netcdf(root / "cohort.nc")
    return root


COMMANDS = {
    "identify": lambda data, out: ["identify", str(data), "--out", str(out)],
    "fit": lambda data, out: ["fit", str(data), "--out", str(out), "--chains", "1", "--warmup", "5", "--draws", "5"],
    "evaluate": lambda data, out: ["evaluate", str(data), "--out", str(out)],
}


@pytest.mark.parametrize("command", [*COMMANDS, "convert"])
@pytest.mark.parametrize("case", CSV_CASES)
def test_a_bad_folder_is_refused(base, tmp_path, capsys, case, command):
    data = tmp_path / "data"
    shutil.copytree(base / "data", data)
    expect = CSV_CASES[case](data)
    before = _hashes(tmp_path)
    out = tmp_path / "out"
    argv = ["convert", str(data), str(tmp_path / "c.nc")] if command == "convert" else COMMANDS[command](data, out)
    rc, lines = _run(argv, capsys)
    _assert_refused(rc, lines, expect, out)
    assert not (tmp_path / "c.nc").exists()
    assert _hashes(tmp_path / "data") == {k.removeprefix("data/"): v for k, v in before.items() if k.startswith("data/")}


@pytest.mark.parametrize("command", [*COMMANDS, "convert"])
@pytest.mark.parametrize("case", NC_CASES)
def test_a_bad_netcdf_file_is_refused(base, tmp_path, capsys, case, command):
    nc = tmp_path / "cohort.nc"
    shutil.copy(base / "cohort.nc", nc)
    expect = NC_CASES[case](nc)
    before = _hashes(tmp_path)
    out = tmp_path / "out"
    argv = ["convert", str(nc), str(out)] if command == "convert" else COMMANDS[command](nc, out)
    rc, lines = _run(argv, capsys)
    _assert_refused(rc, lines, expect, out)
    assert not (out / MAN).exists()
    assert {k: v for k, v in _hashes(tmp_path).items() if not k.startswith("out")} == before


# ----------------------------------------------------------------------------- output paths
def _bad_out(kind: str, tmp: Path, data: Path) -> tuple[Path, str]:
    if kind == "a file":
        (tmp / "f").write_text("mine")
        return tmp / "f", "not a folder"
    if kind == "under a file":
        (tmp / "f").write_text("mine")
        return tmp / "f" / "out", "not a folder"
    if kind == "the data folder":
        return data, "input"
    if kind == "inside the data folder":
        return data / "results", "inside the data folder"
    (tmp / "mine").mkdir()
    (tmp / "mine" / "notes.md").write_text("mine")
    return tmp / "mine", "not empty"


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("kind", ["a file", "under a file", "the data folder", "inside the data folder", "another folder"])
def test_a_bad_output_path_is_refused_before_any_work(base, tmp_path, capsys, command, kind):
    data = tmp_path / "data"
    shutil.copytree(base / "data", data)
    out, expect = _bad_out(kind, tmp_path, data)
    before = _hashes(tmp_path)
    rc, lines = _run(COMMANDS[command](data, out), capsys)
    _assert_refused(rc, lines, [str(out), expect], None)
    assert _hashes(tmp_path) == before  # nothing written, nothing deleted


def test_converting_into_a_data_folder_deletes_nothing(base, tmp_path, capsys):
    """Converting a NetCDF file into a folder that holds recordings is refused and loses nothing."""
    data = tmp_path / "data"
    shutil.copytree(base / "data", data)
    (data / "notes.txt").write_text("mine")
    nc = tmp_path / "other.nc"
    Cohort((_trial("AB", "left", 1, 0.2),)).save_netcdf(nc)
    before = _hashes(tmp_path)
    rc, lines = _run(["convert", str(nc), str(data)], capsys)
    _assert_refused(rc, lines, [str(data), "not empty"], None)
    assert _hashes(tmp_path) == before
    # even when told to overwrite, the files of the earlier recordings stay (the folder would not read)
    rc, lines = _run(["convert", str(nc), str(data), "--overwrite"], capsys)
    _assert_refused(rc, lines, [str(data), T1], None)
    assert _hashes(tmp_path) == before


def test_converting_onto_an_existing_netcdf_file_needs_overwrite(base, tmp_path, capsys):
    nc = tmp_path / "c.nc"
    nc.write_bytes(b"mine")
    rc, lines = _run(["convert", str(base / "data"), str(nc)], capsys)
    _assert_refused(rc, lines, [str(nc), "exists"], None)
    assert nc.read_bytes() == b"mine"
    assert main(["--quiet", "convert", str(base / "data"), str(nc), "--overwrite"]) == 0
    assert nc.read_bytes() != b"mine"


def test_a_failed_rerun_leaves_no_summary(base, tmp_path, capsys):
    """An earlier run's summary.json goes when a rerun starts: a rerun that fails leaves a folder
    that says it is incomplete."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "summary.json").write_text('{"schema": "quadshank/identification", "schema_version": 1}')
    (out / "report.md").write_text("the earlier run's report")
    data = tmp_path / "data"
    shutil.copytree(base / "data", data)
    _set_cell(data / T1, 17, "angle_deg", "abc")
    rc, lines = _run(COMMANDS["identify"](data, out), capsys)
    _assert_refused(rc, lines, [T1], out)
    assert not (out / "summary.json").exists()


def test_continuous_stimulation_names_the_leg_and_trial(base, tmp_path, capsys):
    data = tmp_path / "data"
    shutil.copytree(base / "data", data)
    for f in (T1, T2, J1):
        _map_column(data / f, "stimulation", lambda v: 0.4)  # a pulse at every sample
    rc, lines = _run(COMMANDS["identify"](data, tmp_path / "out"), capsys)
    # reading warns that a pulse on every sample looks like a logged setting, then identify refuses
    warned = [line for line in lines if line.startswith("quadshank: warning:")]
    assert len(warned) == 3 and all("nonzero on every one of its 400 samples" in w for w in warned), lines
    _assert_refused(rc, [line for line in lines if line not in warned], ["TN-left trial 1", "quiet samples"],
                    tmp_path / "out")


def test_a_refused_command_leaves_no_folder_behind(base, tmp_path, capsys):
    rc, lines = _run(["simulate", "--out", str(tmp_path / "new"), "--minutes", "0.1", "--sampling-period-ms", "7.5"],
                     capsys)
    assert rc == 2 and not (tmp_path / "new").exists()
    data = tmp_path / "data"
    shutil.copytree(base / "data", data)
    _set_cell(data / T1, 17, "angle_deg", "abc")
    rc, lines = _run(COMMANDS["fit"](data, tmp_path / "fit"), capsys)
    assert rc == 2 and not (tmp_path / "fit").exists()


def test_a_command_that_fails_removes_the_folder_it_made_empty(base, tmp_path, capsys, monkeypatch):
    """A fit that fails after its folder was made (no finite density, say) is one error line, and
    the folder it made and left empty is gone; a folder it wrote into keeps what it holds."""
    import quadshank.cli as cli

    def fails(cohort, out, *a, **k):
        (Path(out) / "round-1" / "confirm").mkdir(parents=True, exist_ok=True)  # begun, and nothing in it
        raise FloatingPointError("TN-left: the screen of model3 found no finite posterior density")

    monkeypatch.setattr(cli, "run_fit", fails)
    rc, lines = _run(COMMANDS["fit"](base / "data", tmp_path / "fit"), capsys)
    assert rc == 2 and lines == ["quadshank: error: TN-left: the screen of model3 found no finite posterior density"]
    assert not (tmp_path / "fit").exists()
    (tmp_path / "kept").mkdir()
    (tmp_path / "kept" / "notes.txt").write_text("mine")
    rc, lines = _run(COMMANDS["fit"](base / "data", tmp_path / "kept") + ["--overwrite"], capsys)
    assert rc == 2 and (tmp_path / "kept" / "notes.txt").read_text() == "mine"

    def half(cohort, out, *a, **k):
        (Path(out) / "figures").mkdir(parents=True, exist_ok=True)
        (Path(out) / "figures" / "a.png").write_bytes(b"png")
        (Path(out) / "empty").mkdir()
        raise FloatingPointError("late")

    monkeypatch.setattr(cli, "run_fit", half)
    rc, lines = _run(COMMANDS["fit"](base / "data", tmp_path / "half"), capsys)
    assert rc == 2 and (tmp_path / "half" / "figures" / "a.png").exists()  # what was written is kept
    assert not (tmp_path / "half" / "empty").exists() and not (tmp_path / "half" / "summary.json").exists()


def test_values_no_knee_produces_are_refused_where_not_excluded(base, tmp_path, capsys):
    """A missing-data marker, another unit or an overflow in a signal is refused with its file,
    column and row, unless the sample is excluded; a run of a marker in a measured signal within
    the bounds is named in a warning with its time."""
    data = tmp_path / "data"
    shutil.copytree(base / "data", data)
    _set_cell(data / T1, 40, "angle_deg", "-9999")
    _set_cell(data / T1, 41, "acceleration_deg_s2", "1e300")
    rc, lines = _run(["convert", str(data), str(tmp_path / "x.nc")], capsys)
    assert rc == 2 and not (tmp_path / "x.nc").exists()
    said = "\n".join(lines)
    assert f"{T1}, column 'angle_deg', row 40: value -9999.0 beyond ±720" in said
    assert f"{T1}, column 'acceleration_deg_s2', row 41: value 1e+300 beyond ±500000" in said
    assert "RuntimeWarning" not in said
    rows = _rows(data / T1)
    rows[0].append("exclude")
    for i, row in enumerate(rows[1:], start=2):
        row.append("1" if i in (40, 41) else "0")
    for i in range(60, 66):
        rows[i - 1][rows[0].index("acceleration_deg_s2")] = "-9999"
    _write_rows(data / T1, rows)
    with pytest.warns(DataWarning, match=r"acceleration_deg_s2 holds -9999 on 6 samples in 1 run, the first from time_s"):
        cohort = read_interchange(data)
    assert cohort.trials[0].exclude[38:40].all()


def test_an_excluded_artefact_does_not_reach_the_derived_signals_beside_it():
    """The velocity and acceleration derived from the angle run apart on each side of excluded
    samples that hold no knee's angle (a missing-data marker), so the marker leaves the kept
    samples' derivatives as they were without it; through excluded samples that hold a movement
    (a release) the derivation runs on as before."""
    clean = _trial("TN", "left", 1, 0.3)
    angle = clean.angle_deg.copy()
    angle[100:110] = -9999.0
    exclude = np.zeros(angle.size, bool)
    exclude[100:110] = True
    marked = Trial.from_signals("TN", "left", 1, clean.sampling_period_s, angle, None, clean.stimulation, exclude=exclude)
    smooth = Trial.from_signals("TN", "left", 1, clean.sampling_period_s, clean.angle_deg, None, clean.stimulation)
    kept = ~exclude
    kept[90:120] = False  # the filter's own edge beside the stretch differs a little, not by thousands
    np.testing.assert_allclose(marked.acceleration_deg_s2[kept], smooth.acceleration_deg_s2[kept], rtol=1e-9, atol=1e-6)
    near = slice(93, 100)
    assert np.max(np.abs(marked.acceleration_deg_s2[near] - smooth.acceleration_deg_s2[near])) < 1e3
    assert np.max(np.abs(marked.velocity_deg_s[near] - smooth.velocity_deg_s[near])) < 1e2
    moving = Trial.from_signals("TN", "left", 1, clean.sampling_period_s, clean.angle_deg, None, clean.stimulation,
                                exclude=exclude)
    np.testing.assert_array_equal(moving.acceleration_deg_s2, smooth.acceleration_deg_s2)


def test_an_earlier_output_of_the_same_command_is_written_over(base, tmp_path, capsys):
    out = tmp_path / "c"
    for _ in range(2):  # the second run finds the first's mark
        rc, lines = _run(["convert", str(base / "cohort.nc"), str(out)], capsys)
        assert rc == 0, lines
    assert (out / ".quadshank-output").read_text().splitlines()[0] == "convert"
    rc, lines = _run(COMMANDS["identify"](base / "data", out), capsys)  # a folder of recordings
    _assert_refused(rc, lines, [str(out), "holds recordings"], None)
    other = tmp_path / "other"
    other.mkdir()
    (other / ".quadshank-output").write_text("fit\n")  # another command's output
    rc, lines = _run(COMMANDS["identify"](base / "data", other), capsys)
    _assert_refused(rc, lines, [str(other), "no earlier output of `quadshank identify`"], None)


def test_overwrite_never_replaces_another_commands_summary(base, tmp_path, capsys):
    """--overwrite into a fit's folder would swap its summary.json for identify's and leave a folder
    that is neither: refused before any work, the fit's summary kept."""
    fitdir = tmp_path / "fit"
    fitdir.mkdir()
    summary = '{"schema": "quadshank/fit", "model": "model3"}'
    (fitdir / "summary.json").write_text(summary)
    rc, lines = _run(COMMANDS["identify"](base / "data", fitdir) + ["--overwrite"], capsys)
    _assert_refused(rc, lines, [str(fitdir), "holds the output of `quadshank fit`"], None)
    assert (fitdir / "summary.json").read_text() == summary and sorted(p.name for p in fitdir.iterdir()) == ["summary.json"]


def test_a_rerun_removes_what_its_earlier_run_wrote_and_keeps_the_users_files(base, tmp_path, capsys):
    """A rerun into its own earlier output leaves no figure of a leg the new data lack; a file the
    user put there stays, and a mark edited to name a file outside the folder removes nothing there."""
    out = tmp_path / "check"
    rc, lines = _run(["check", str(base / "data"), "--out", str(out)], capsys)
    assert rc == 0, lines
    before = {p.name for p in out.rglob("*.png")}
    assert any("JM-right" in name for name in before), before
    (out / "notes.txt").write_text("mine")
    outside = tmp_path / "outside.txt"
    outside.write_text("not the command's")
    mark = out / ".quadshank-output"
    mark.write_text(mark.read_text() + "../outside.txt\n")
    data = _copy(base, tmp_path, "renamed")
    _set_cell(data / MAN, 4, "subject", "KB")  # JM-right is KB-right now
    rc, lines = _run(["check", str(data), "--out", str(out)], capsys)
    assert rc == 0, lines
    after = {p.name for p in out.rglob("*.png")}
    assert not any("JM-right" in name for name in after) and any("KB-right" in name for name in after), after
    assert (out / "notes.txt").read_text() == "mine" and outside.read_text() == "not the command's"
    assert "notes.txt" not in mark.read_text().splitlines()  # the user's file is not listed as written


FIT_COMMANDS = {
    "report": lambda fit, data, out: ["report", str(fit), "--data", str(data), "--out", str(out)],
    "diagnose": lambda fit, data, out: ["diagnose", str(fit), "--data", str(data), "--out", str(out)],
    "evaluate": lambda fit, data, out: ["evaluate", str(data), "--fit", str(fit), "--out", str(out)],
    "compare": lambda fit, data, out: ["compare", str(fit), str(fit), "--data", str(data), "--out", str(out)],
    "predict": lambda fit, data, out: ["predict", str(fit), "--stimulation", str(data / T1), "--out", str(out)],
}


@pytest.mark.parametrize("damage", ["truncated", "another file", "no summary"])
@pytest.mark.parametrize("command", FIT_COMMANDS)
def test_a_damaged_fit_folder_is_refused(base, tmp_path, capsys, command, damage):
    from quadshank.inference import FitResult

    fit = tmp_path / "fit"
    fit.mkdir()
    FitResult(model="model1", effects=[], trials=[1], legs={}, diagnostics={"ok": True}, banner=None, settings={},
              chain_method="vectorized", sampling_period_s=DT, interval=[0.05, 0.95], code={}).write(fit)
    (fit / "fit.nc").write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(500) if damage == "truncated" else b"time_s,angle\n1,2\n")
    if damage == "no summary":
        (fit / "summary.json").unlink()
    before = _hashes(tmp_path)
    rc, lines = _run(FIT_COMMANDS[command](fit, base / "data", tmp_path / "out"), capsys)
    _assert_refused(rc, lines, [str(fit)], tmp_path / "out")
    assert _hashes(tmp_path) == before


def test_an_empty_output_name_is_refused(base, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for argv in (["identify", str(base / "data"), "--out", ""], ["convert", str(base / "cohort.nc"), " "]):
        rc, lines = _run(argv, capsys)
        _assert_refused(rc, lines, ["give"], None)
    assert list(tmp_path.iterdir()) == []


def test_a_start_that_cuts_a_twitch_from_its_pulse_is_named(base, tmp_path):
    """start_s just after a pulse keeps the pulse's twitch without the pulse: named with the file,
    the manifest row and the pulse's time; a start well clear of the pulses draws nothing."""
    import warnings

    def said(start):
        data = tmp_path / f"start{start}"
        shutil.copytree(base / "data", data)
        rows = _rows(data / MAN)
        rows[0].append("start_s")
        for i, row in enumerate(rows[1:]):
            row.append(str(start) if i == 0 else "")
        _write_rows(data / MAN, rows)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            read_interchange(data)
        return [str(w.message) for w in caught if "without its pulse" in str(w.message)]

    (found,) = said(1.25)  # a pulse at 1.2 s
    assert found.startswith(f"{T1}: start_s = 1.25 ({MAN} row 2) falls 0.05 s after a pulse at time_s = 1.2:")
    assert said(1.7) == []


# ----------------------------------------------------------------------------- what other labs' files look like
def _read(folder: Path) -> tuple[Cohort | None, str, list[str]]:
    """``read_interchange(folder)``: the cohort (None where refused), the error's text and the warnings."""
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            cohort, error = read_interchange(folder), ""
        except ValueError as err:
            cohort, error = None, str(err)
    return cohort, error, [str(w.message) for w in caught if issubclass(w.category, DataWarning)]


def _copy(base: Path, tmp_path: Path, name: str) -> Path:
    data = tmp_path / name
    shutil.copytree(base / "data", data)
    return data


@pytest.mark.parametrize("separator, said", [(";", "semicolons (';')"), ("\t", "tabs")])
def test_a_file_separated_otherwise_is_named_once_with_its_separator(base, tmp_path, separator, said):
    """A spreadsheet in another locale writes ';' (or a tab): one problem says so, not one per
    column that then looks unknown or missing."""
    data = _copy(base, tmp_path, "sep")
    (data / T1).write_text((data / T1).read_text().replace(",", separator))
    _, error, _ = _read(data)
    problems = [line for line in error.splitlines() if T1 in line]
    assert len(problems) == 1 and f"{T1}, row 1: the header is one field" in problems[0], error
    assert f"separated by {said}" in problems[0]


def test_decimal_commas_and_upper_case_names_get_a_hint(base, tmp_path):
    data = _copy(base, tmp_path, "locale")
    rows = _rows(data / T1)
    rows[0] = [c.upper() for c in rows[0]]
    _write_rows(data / T1, rows)
    text = (data / T2).read_text().splitlines()
    (data / T2).write_text("\n".join(text[:1] + [line.replace(".", ",") for line in text[1:]]) + "\n")
    _, error, _ = _read(data)
    assert f"{T1}, column 'TIME_S', row 1: unknown column" in error and "did you mean 'time_s'?" in error
    assert f"{T2}, row 2: " in error and "decimal commas (0,25 for 0.25)?" in error


def test_a_dropout_left_out_may_be_empty_or_nan(base, tmp_path):
    """A sensor's dropout on rows with exclude = 1 may be left empty or NaN: read, filled in
    linearly between its neighbours (the model and the derivatives run through it), and the
    trial otherwise as before; without exclude the cell is refused, with the way out."""
    data = _copy(base, tmp_path, "dropout")
    rows = _rows(data / T1)
    if "exclude" not in rows[0]:
        rows = [rows[0] + ["exclude"]] + [r + ["0"] for r in rows[1:]]
    a, x = rows[0].index("angle_deg"), rows[0].index("exclude")
    before = [float(r[a]) for r in rows[1:]]
    for k, text in zip(range(50, 56), ["", "NaN", "nan", " ", "NAN", ""]):
        rows[k][a], rows[k][x] = text, "1"
    _write_rows(data / T1, rows)
    cohort, error, _ = _read(data)
    assert error == "", error
    t = next(t for t in cohort.trials if t.source == T1)
    got = t.angle_deg
    line = np.interp(np.arange(49, 55), [48, 55], [before[48], before[55]])  # samples 49–54 are rows 51–56
    np.testing.assert_allclose(got[49:55], line)
    np.testing.assert_array_equal(np.delete(got, range(49, 55)), np.delete(before, range(49, 55)))
    assert t.exclude[49:55].all() and np.isfinite(t.velocity_deg_s).all()
    rows[60][a] = "NaN"  # not excluded
    _write_rows(data / T1, rows)
    _, error, _ = _read(data)
    assert (f"{T1}, column 'angle_deg', row 61: non-finite value 'NaN' (NaN and infinity are not allowed; a sample "
            "to leave out may be empty or NaN where its exclude is 1)") in error, error


def test_a_row_of_units_under_the_header_is_one_problem(base, tmp_path):
    """A spreadsheet's units row (``s, deg, deg/s2, ...``) is named once, with its row, as units,
    not cell by cell as non-numeric values; a row with one text cell among numbers is not units."""
    data = _copy(base, tmp_path, "units")
    rows = _rows(data / T1)
    units = {"time_s": "s", "angle_deg": "deg", "acceleration_deg_s2": "deg/s2", "velocity_deg_s": "deg/s"}
    rows.insert(1, [units.get(c, "") for c in rows[0]])
    _write_rows(data / T1, rows)
    _, error, _ = _read(data)
    assert f"{T1}, row 2: holds no number ('s', 'deg', 'deg/s2'" in error and "a row of units" in error, error
    assert "non-numeric" not in error, error
    one = _copy(base, tmp_path, "one-cell")
    rows = _rows(one / T1)
    rows[1][rows[0].index("angle_deg")] = "deg"
    _write_rows(one / T1, rows)
    _, error, _ = _read(one)
    assert f"{T1}, column 'angle_deg', row 2: non-numeric value 'deg'" in error and "a row of units" not in error, error


def test_names_that_look_the_same_are_one_name_or_refused(base, tmp_path):
    """A subject typed 'Zoë' in one row and stored decomposed ('e' + '¨') in another is one subject,
    a file listed composed and stored decomposed (as some file systems write names) is found, and
    a name with an invisible character is refused naming its row."""
    import unicodedata

    nfc, nfd = "Zo\u00eb", unicodedata.normalize("NFD", "Zo\u00eb")
    assert nfc != nfd
    data = _copy(base, tmp_path, "names")
    rows = _rows(data / MAN)
    col = rows[0].index("subject")
    rows[1][col], rows[2][col] = nfc, nfd  # TN-left trials 1 and 2
    (data / T2).rename(data / unicodedata.normalize("NFD", f"{nfc}-left-trial2.csv"))
    rows[2][rows[0].index("file")] = f"{nfc}-left-trial2.csv"
    _write_rows(data / MAN, rows)
    cohort, error, _ = _read(data)
    assert error == "" and f"{nfc}-left" in cohort.legs and len(cohort.trials_of(f"{nfc}-left")) == 2

    hidden = _copy(base, tmp_path, "hidden")
    rows = _rows(hidden / MAN)
    rows[3][rows[0].index("subject")] = "JM\u200b"
    _write_rows(hidden / MAN, rows)
    _, error, _ = _read(hidden)
    assert f"{MAN}, column 'subject', row 4: subject 'JM\\u200b' holds an invisible character" in error
    assert "U+200B" in error


def test_a_pulse_without_charge_is_named(base, tmp_path):
    """Pulse width and current given, one of them 0 at a pulse: no charge, no pulse; said with the
    file, column and first row."""
    data = _copy(base, tmp_path, "charge")
    rows = _rows(data / T1)
    j = rows[0].index("stimulation")
    rows[0][j:j + 1] = ["pulse_width_us", "current_mA"]
    pulses = []
    for i, r in enumerate(rows[1:], start=2):
        level = float(r[j])
        if level > 0:
            pulses.append(i)
        r[j:j + 1] = [repr(300.0 * level), repr(40.0 if level > 0 and len(pulses) > 1 else 0.0)]
    rows[pulses[0] - 1][j] = "300.0"
    _write_rows(data / T1, rows)
    cohort, error, warned = _read(data)
    assert error == ""
    said = [w for w in warned if "current_mA" in w]
    assert len(said) == 1 and said[0].startswith(f"{T1}, column 'current_mA', row {pulses[0]}: 0 where pulse_width_us "
                                                 "is 300.0")
    trial = next(t for t in cohort.trials if t.source == T1)
    assert np.count_nonzero(trial.stimulation) == len(pulses) - 1


def test_a_gate_or_a_logged_setting_is_not_taken_silently_for_pulses(base, tmp_path):
    """Stimulation nonzero on consecutive samples at 100 Hz (a gate) or on every sample (a setting):
    a warning; a 50 Hz train (every other sample) is a train and draws none."""
    def stimulated(name, level):
        data = _copy(base, tmp_path, name)
        _map_column_indexed(data / J1, "stimulation", level)
        return _read(data)

    _, error, warned = stimulated("gate", lambda i: 0.5 if 100 <= i < 140 else 0.0)
    assert error == "" and any("longest 40 samples from time_s = 1.0 (pulses at 100 Hz)" in w for w in warned), warned
    _, _, warned = stimulated("setting", lambda i: 0.3)
    assert any(f"nonzero on every one of its {N} samples" in w for w in warned), warned
    _, _, warned = stimulated("train", lambda i: 0.5 if 100 <= i < 200 and i % 2 == 0 else 0.0)
    assert not [w for w in warned if "consecutive" in w or "every one" in w], warned
    # a trigger high over two samples a pulse: each run read as two pulses at 100 Hz
    _, error, warned = stimulated("trigger", lambda i: 1.0 if i % 60 in (10, 11) else 0.0)
    assert error == "" and any("runs of 2 consecutive samples" in w and "keep each run's first sample" in w
                               for w in warned), warned
    # identify, finding no isolated twitch among the runs, says why rather than pointing to fit
    from quadshank.inference import IdentificationError, identify_cohort

    cohort, _, _ = stimulated("trigger for identify", lambda i: 1.0 if i % 100 in (10, 11) else 0.0)
    with pytest.raises(IdentificationError, match=r"JM-right trial 1: only 0 isolated twitches .*runs of 2 consecutive "
                                                  r"samples.*keep each run's first sample.*`quadshank fit` would take"):
        identify_cohort(cohort.select(["JM-right"]), trial=1)
    _, _, warned = stimulated("a trigger, two pulses touching", lambda i: 1.0 if i % 60 in (10, 11) or 100 <= i < 106
                              else 0.0)
    assert any("runs of 2 consecutive samples" in w for w in warned), warned
    _, _, warned = stimulated("a pulse beside another", lambda i: 1.0 if i in (10, 11, 70, 130, 190) else 0.0)
    assert not [w for w in warned if "consecutive" in w], warned


def _map_column_indexed(path: Path, column: str, f) -> None:
    rows = _rows(path)
    j = rows[0].index(column)
    for i, r in enumerate(rows[1:]):
        r[j] = repr(float(f(i)))
    _write_rows(path, rows)


def test_a_bound_outside_the_recording_is_named(base, tmp_path):
    """start_s/end_s beyond the recording cut nothing (end_s in ms, say): a warning names the
    manifest's column and row; bounds inside it draw none."""
    def bounded(name, start, end):
        data = _copy(base, tmp_path, name)
        rows = _rows(data / MAN)
        rows[0] += ["start_s", "end_s"]
        for i, row in enumerate(rows[1:]):
            row += [start, end] if i == 2 else ["", ""]
        _write_rows(data / MAN, rows)
        return _read(data)

    cohort, error, warned = bounded("ms", "", "3500")
    said = [w for w in warned if "outside" in w]
    assert error == "" and len(said) == 1, warned
    assert said[0].startswith(f"{MAN}, column 'end_s', row 4: 3500.0 s lies outside {J1}'s recording (0 to 3.99 s)")
    assert next(t for t in cohort.trials if t.source == J1).n_samples == N
    _, _, warned = bounded("inside", "0.5", "3.5")
    assert not [w for w in warned if "outside" in w]


def test_irregular_time_stamps_point_to_resampling(base, tmp_path):
    data = _copy(base, tmp_path, "irregular")
    _set_cell(data / T1, 30, "time_s", "0.2805")
    _, error, _ = _read(data)
    assert f"{T1}, column 'time_s', row 30: non-uniform sampling" in error and "--resample" in error


def test_an_irregular_plan_is_told_to_be_written_on_the_fits_grid(tmp_path):
    """A stimulation plan is written, not recorded: its irregular time stamps point to the fit's
    grid, not to `convert --resample`, which reads recordings."""
    from quadshank.data import read_plan

    plan = tmp_path / "plan.csv"
    plan.write_text("time_s,stimulation\n" + "".join(f"{t!r},0\n" for t in (0.0, 0.01, 0.02, 0.0305, 0.04, 0.05)))
    with pytest.raises(ValueError) as err:
        read_plan(plan, 0.01)
    assert "non-uniform sampling" in str(err.value) and "time_s every 0.01 s" in str(err.value)
    assert "--resample" not in str(err.value)


def test_a_stimulated_trial_resting_far_from_zero_is_named(base, tmp_path):
    """Between its twitches a stimulated knee hangs near 0: a flexion angle (90° at rest) is named
    with the file, the trial and the median; the same trial zeroed at rest draws nothing."""
    data = _copy(base, tmp_path, "flexion")
    _map_column(data / T1, "angle_deg", lambda v: v + 90.0)
    _, error, warned = _read(data)
    said = [w for w in warned if "where no twitch acts" in w]
    assert error == "" and len(said) == 1 and T1 in said[0] and "(TN-left trial 1)" in said[0], warned
    median = float(said[0].split("the angle's median is ")[1].split("°")[0])
    assert 80.0 < median < 100.0, said[0]  # a sine about 90°, its quiet samples
    _, _, warned = _read(_copy(base, tmp_path, "zeroed"))
    assert not [w for w in warned if "where no twitch acts" in w]


def test_a_stimulated_trial_offset_from_zero_is_named(tmp_path):
    """A goniometer zeroed 20° into extension is named with the effects that model it; the same
    recording zeroed at rest draws nothing."""
    from quadshank.data import simulate_cohort

    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.5, seed=2, trials=(1,))
    data = write_interchange(cohort, tmp_path / "data")
    _, _, warned = _read(data)
    assert not [w for w in warned if "where no twitch acts" in w], warned
    _map_column(data / T1, "angle_deg", lambda v: v + 20.0)
    _, error, warned = _read(data)
    said = [w for w in warned if "where no twitch acts" in w]
    assert error == "" and len(said) == 1 and "is the goniometer's zero offset?" in said[0], warned
    assert "goniometer_offset" in said[0] and "flexion angle" not in said[0]
    assert 15.0 < float(said[0].split("the angle's median is ")[1].split("°")[0]) < 25.0


def test_trials_at_different_periods_are_named_with_their_files(tmp_path):
    """One model runs at one period: the refusal names each trial's file and period, and the
    command that resamples them."""
    t = np.arange(2 * N) * DT / 2
    half = Trial.from_signals("JM", "right", 1, DT / 2, 25 * np.sin(4.4 * t), -25 * 4.4**2 * np.sin(4.4 * t),
                              np.zeros(2 * N), time_s=t)
    write_interchange(Cohort((_trial("TN", "left", 1, 0.0), half)), tmp_path / "data")
    cohort = read_interchange(tmp_path / "data")
    with pytest.raises(ValueError) as err:
        cohort.sampling_period_s
    assert f"TN-left trial 1 ({T1}): 10 ms, JM-right trial 1 ({J1}): 5 ms" in str(err.value)
    assert "--resample" in str(err.value)


def test_a_short_manifest_row_is_one_problem_not_also_an_unlisted_file(base, tmp_path):
    data = _copy(base, tmp_path, "short")
    rows = _rows(data / MAN)
    rows[2] = rows[2][:3] + rows[2][3:4]  # subject, leg, trial, file: the other cells lost
    rows[0] += ["start_s"]
    for row in rows[1:]:
        row += [""] if row is not rows[2] else []
    _write_rows(data / MAN, rows)
    _, error, _ = _read(data)
    assert f"{MAN}, row 3: 4 fields, expected 6 as in the header" in error
    assert "not listed" not in error, error


def test_a_spreadsheets_separator_line_is_read_past_and_a_comment_is_named(base, tmp_path):
    """``sep=,`` above the header (a spreadsheet's note) is read past, the rows keep their line
    numbers; a comment line above the header is one problem that says so."""
    data = _copy(base, tmp_path, "sep_line")
    (data / T1).write_text("sep=,\n" + (data / T1).read_text())
    cohort, error, _ = _read(data)
    assert error == "" and len(cohort.trials) == 3
    text = (data / T1).read_text().splitlines()
    text[11] = "abc" + text[11][text[11].index(","):]  # line 12: its first cell, time_s
    (data / T1).write_text("\n".join(text) + "\n")
    _, error, _ = _read(data)
    assert error.endswith(f"{T1}, column 'time_s', row 12: non-numeric value 'abc'"), error

    commented = _copy(base, tmp_path, "comment")
    (commented / T1).write_text("# recorded with logger 2\n" + (commented / T1).read_text())
    _, error, _ = _read(commented)
    problems = [line for line in error.splitlines() if T1 in line]
    assert len(problems) == 1 and f"{T1}, row 1: the first line, '# recorded with logger 2', is a comment?" in error


def _same_trials(a: Cohort, b: Cohort) -> None:
    assert [(t.key, t.trial, t.source) for t in a.trials] == [(t.key, t.trial, t.source) for t in b.trials]
    for x, y in zip(a.trials, b.trials):
        for name in ("time_s", "angle_deg", "acceleration_deg_s2", "stimulation", "velocity_deg_s", "exclude"):
            np.testing.assert_array_equal(getattr(x, name), getattr(y, name), err_msg=f"{x.key} {x.trial} {name}")


def test_empty_cells_and_trailing_separators_are_read_past(base, tmp_path):
    """A separator after the last field of every line (a logger's), or only after the data's; a
    spreadsheet's empty columns after the last (``,,``) and its rows of empty cells (``,,,``), in
    the middle or at the end: nothing is lost or invented; a trailing column that holds a value
    without a name is still refused."""
    data = _copy(base, tmp_path, "trailing")
    text = (data / T1).read_text().splitlines()
    (data / T1).write_text("".join(f"{line},\n" for line in text))  # header too
    text = (data / T2).read_text().splitlines()
    (data / T2).write_text("\n".join(text[:1] + [f"{line},," for line in text[1:]]) + "\n")
    text = (data / J1).read_text().splitlines()
    (data / J1).write_text("\n".join(text[:100] + [",,,"] + text[100:] + [",,,", ",,,"]) + "\n")
    text = (data / MAN).read_text().splitlines()
    (data / MAN).write_text("".join(f"{line},\n" for line in text) + ",,,,,\n")
    cohort, error, _ = _read(data)
    assert error == "", error
    _same_trials(cohort, read_interchange(base / "data"))

    named = _copy(base, tmp_path, "a value without a name")
    rows = _rows(named / T1)
    _write_rows(named / T1, [rows[0] + [""]] + [r + (["7"] if i == 10 else [""]) for i, r in enumerate(rows[1:])])
    _, error, _ = _read(named)
    assert f"{T1}, column '', row 1: unnamed column (position 5)" in error, error


def test_a_file_not_in_utf8_names_its_row_and_column(base, tmp_path):
    """A spreadsheet's Windows-1252 (Latin-1) export: the first byte that is not UTF-8 is named
    with its row (counted in the whole file, not in a block read), the column the header names
    there and what the cell reads as in Windows-1252; in the header, the row alone."""
    data = _copy(base, tmp_path, "latin1")
    latin1_cell(data)
    text = (data / MAN).read_text().replace("JM,", "Jo\u00eb,")
    (data / MAN).write_bytes(text.encode("latin-1"))
    _, error, _ = _read(data)
    assert f"{MAN}, column 'subject', row 4: not UTF-8 text: byte 0xeb (invalid continuation byte); in Windows-1252 " \
           "(Latin-1) it reads 'Joë': save the file as UTF-8" in error, error

    header = _copy(base, tmp_path, "latin1 header")
    text = (header / T2).read_text().replace("angle_deg", "angle [\u00b0]", 1)
    (header / T2).write_bytes(text.replace("\n", "\r\n").encode("latin-1"))
    _, error, _ = _read(header)
    assert f"{T2}, row 1: not UTF-8 text: byte 0xb0 (invalid start byte); in Windows-1252 (Latin-1) it reads " \
           "'angle [°]'" in error, error


def test_utf16_with_its_byte_order_mark_is_read(base, tmp_path):
    """A spreadsheet's Unicode export (UTF-16, its byte-order mark first) reads as the UTF-8 file;
    one cut short is named as not UTF-16."""
    data = _copy(base, tmp_path, "utf16")
    for name in (T1, MAN):
        (data / name).write_bytes((data / name).read_text().encode("utf-16"))
    cohort, error, _ = _read(data)
    assert error == "", error
    _same_trials(cohort, read_interchange(base / "data"))
    (data / T1).write_bytes((data / T1).read_bytes()[:-1])
    _, error, _ = _read(data)
    assert f"{T1}: not UTF-16 text, as its byte-order mark says" in error, error


@pytest.mark.parametrize("encoding", ["utf-16-le", "utf-16-be"])
def test_utf16_without_its_byte_order_mark_is_read(base, tmp_path, encoding):
    """Some loggers write UTF-16 without a byte-order mark: the zero bytes of its ASCII header say so."""
    data = _copy(base, tmp_path, "utf16")
    for name in (T1, MAN):
        (data / name).write_bytes((data / name).read_text().encode(encoding))
    cohort, error, _ = _read(data)
    assert error == "", error
    _same_trials(cohort, read_interchange(base / "data"))


def test_a_comma_or_a_character_outside_ascii_in_a_number_gets_a_hint(base, tmp_path):
    """A quoted decimal comma ("0,25") keeps the row's fields and is one cell that is no number: it
    says what it looks like and what the format writes; a typographic minus, which looks like '-',
    is shown escaped."""
    data = _copy(base, tmp_path, "hints")
    _set_cell(data / T1, 11, "angle_deg", '"9,25"')
    _set_cell(data / T1, 12, "acceleration_deg_s2", '"1,234.5"')
    _set_cell(data / T1, 30, "angle_deg", "\u22121.5")
    _set_cell(data / MAN, 2, "sampling_period_s", '"0,01"')
    _, error, _ = _read(data)
    assert f"{T1}, column 'angle_deg', row 11: non-numeric value '9,25' (a decimal comma, 0,25 for 0.25, or digits " \
           "grouped, 1,234.5? A number is written with '.' as its decimal mark and without grouping)" in error, error
    assert f"{T1}, column 'acceleration_deg_s2', row 12: non-numeric value '1,234.5' (a decimal comma" in error, error
    assert f"{T1}, column 'angle_deg', row 30: non-numeric value '\u22121.5' (written '\\u22121.5': a number is " \
           "ASCII digits" in error, error
    assert f"{MAN}, column 'sampling_period_s', row 2: non-numeric value '0,01' (a decimal comma" in error, error


def test_a_recording_copied_as_a_second_trial_is_named(base, tmp_path):
    """Two files that hold the same angles, sample for sample: read, with a warning naming both."""
    data = _copy(base, tmp_path, "copied")
    (data / T2).write_bytes((data / T1).read_bytes())
    with pytest.warns(DataWarning, match=r"TN-left trial 2\): angle_deg is the same on every sample as in .*"
                                         r"TN-left-trial1\.csv \(TN-left trial 1\)"):
        read_interchange(data)


@pytest.mark.parametrize(("argv", "said"), [
    (["simulate", "--minutes", "inf"], "minutes must be positive and at most 1440"),
    (["fit", "DATA", "--chains", "1000000"], "chains (--chains) must be at least 1 and at most 64"),
    (["fit", "DATA", "--draws", "1000000000"], "draws (--draws) must be at least 1 and at most 100000"),
    (["fit", "DATA", "--seed", "99999999999999999999999"], "seed (--seed) must be a whole number from 0 to 4294967295"),
    (["convert", "DATA", "NC", "--resample", "1e-9"], "more than 10 times shorter than the recording's"),
])
def test_option_values_that_would_fill_the_memory_are_refused_before_any_work(base, tmp_path, capsys, argv, said):
    argv = [str(base / "data") if a == "DATA" else str(tmp_path / "c.nc") if a == "NC" else a for a in argv]
    if argv[0] != "convert":
        argv += ["--out", str(tmp_path / "out")]
    rc, lines = _run(argv, capsys)
    _assert_refused(rc, lines, [said], tmp_path / "out")
    assert not (tmp_path / "out").exists() and not (tmp_path / "c.nc").exists()


def _fit_summary_at(folder: Path, period_s: float) -> Path:
    from quadshank.inference import FitResult

    folder.mkdir()
    FitResult(model="model1", effects=[], trials=[1], legs={}, diagnostics={"ok": True}, banner=None, settings={},
              chain_method="vectorized", sampling_period_s=period_s, interval=[0.05, 0.95], code={}).write(folder)
    (folder / "fit.nc").write_bytes(b"")  # the delay prior is read from the summary alone
    return folder


@pytest.mark.parametrize(("argv", "said"), [
    (["fit", "DATA", "--legs", "TN-left,JM-right,TN-left"], "--legs: 'TN-left' given twice"),
    (["fit", "DATA", "--legs", ","], "--legs: ',' names nothing"),
    (["fit", "DATA", "--legs", ""], "--legs: '' names nothing"),
    (["predict", "FIT", "--stimulation", "DATA", "--legs", ""], "--legs: '' names nothing"),
    (["predict", "FIT", "--stimulation", "DATA", "--seed", "-1"], "--seed must be a whole number from 0"),
    (["fit", "DATA", "--trials", "1,1"], "--trials: '1' given twice"),
    (["discover", "DATA", "--effects", " , "], "--effects: ' , ' names nothing"),
    (["discover", "DATA", "--max-rounds", "0"], "--max-rounds must be at least 1, not 0"),
    (["predict", "FIT", "--stimulation", "DATA", "--angle0", "nan"], "--angle0 must be a knee angle in degrees"),
    (["predict", "FIT", "--stimulation", "DATA", "--angle0", "0", "--velocity0", "1e9"],
     "--velocity0 must be an angular velocity"),
    (["fit", "DATA", "--delay-from", "FIT20"], "that fit ran at 20 ms and these data are at 10 ms"),
    (["simulate", "--trials", "2", "--minutes", "0.1"], "--trials 2: a folder of recordings numbers each leg's trials "
                                                        "from 1, and trial(s) 1 would be missing"),
    (["simulate", "--sampling-period-ms", "nan"], "the simulator records at whole milliseconds from 1 to 32 ms"),
])
def test_lists_and_values_that_make_no_sense_are_refused_before_any_work(base, tmp_path, capsys, argv, said):
    named = {"DATA": str(base / "data"), "FIT": str(tmp_path / "nofit"),
             "FIT20": str(_fit_summary_at(tmp_path / "fit20", 0.02)) if "FIT20" in argv else ""}
    argv = [named.get(a, a) for a in argv] + ["--out", str(tmp_path / "out")]
    rc, lines = _run(argv, capsys)
    _assert_refused(rc, lines, [said], tmp_path / "out")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(("argv", "said"), [
    (["fit", "DATA", "--time-limit", "60"], "--time-limit acts only with --target-ess"),
    (["fit", "DATA", "--time=60"], "--time-limit acts only with --target-ess"),  # argparse's prefix of it
    (["evaluate", "DATA", "--draws", "50"], "--draws acts only with --fit"),
    (["predict", "FIT", "--stimulation", "DATA", "--velocity0", "5"], "--velocity0 acts only with --angle0"),
    (["evaluate", "DATA", "--start-stride", "5"], "--start-stride acts only with --fit"),
    (["evaluate", "DATA", "--fit", "FIT", "--band-mcse", "0.1", "--draws", "50"], "--draws is chosen by --band-mcse"),
    (["discover", "DATA", "--chains", "4"], "--chains acts only with --confirm"),
    (["discover", "DATA", "--target-accept", "0.95"], "--target-accept acts only with --confirm"),
    (["discover", "DATA", "--confirm", "--target-ess", "0", "--time-limit", "60"],
     "--time-limit acts only with --target-ess above 0"),
    (["report", "FIT", "--evaluation", "FIT", "--start-stride", "5"], "--start-stride acts only where report computes J"),
    (["demo", "--target-ess", "0", "--time-limit", "60"], "--time-limit acts only with --target-ess above 0"),
])
def test_an_option_that_would_be_ignored_without_its_partner_is_refused(base, tmp_path, capsys, argv, said):
    """An option that acts only beside another is refused alone, before any work, rather than ignored."""
    named = {"DATA": str(base / "data"), "FIT": str(tmp_path / "nofit")}
    argv = [named.get(a, a) for a in argv] + ["--out", str(tmp_path / "out")]
    rc, lines = _run(argv, capsys)
    _assert_refused(rc, lines, [said], tmp_path / "out")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv", [
    ["fit", "D", "--time-limit", "60", "--target-ess", "100"],
    ["evaluate", "D", "--fit", "F", "--draws", "50", "--start-stride", "5"],
    ["evaluate", "D", "--fit", "F", "--band-mcse", "0.1"],
    ["discover", "D", "--confirm", "--chains", "4", "--time-limit", "60"],
    ["report", "F", "--start-stride", "5"],
    ["demo", "--time-limit", "60"],
])
def test_an_option_beside_its_partner_is_taken(argv):
    from quadshank.cli import build_parser, refuse_lone_options

    parser = build_parser()
    args = parser.parse_args([*argv, "--out", "o"])
    args.argv = [*argv, "--out", "o"]
    refuse_lone_options(parser, args)  # raises where an option would be ignored


@pytest.mark.parametrize(("option", "said"), [(["--hide", "telepathy"], "unknown effect(s) 'telepathy'"),
                                              (["--chains", "0"], "chains (--chains) must be at least 1")])
def test_the_demos_options_are_checked_before_its_first_step(tmp_path, capsys, option, said):
    rc, lines = _run(["demo", "--out", str(tmp_path / "demo"), *option], capsys)
    _assert_refused(rc, lines, [said], tmp_path / "demo")
    assert not (tmp_path / "demo").exists()


def test_a_comment_line_among_the_data_is_read_past(base, tmp_path):
    """A logger's closing line ("# end of file") or a comment between rows is no row of data: the
    trial reads as without it."""
    data = _copy(base, tmp_path, "comment")
    rows = (data / T1).read_text().splitlines()
    rows.insert(50, "# marker: stimulation paused")
    (data / T1).write_text("\n".join(rows + ["# end of file"]) + "\n")
    cohort, error, _ = _read(data)
    clean, _, _ = _read(base / "data")
    assert error == ""
    (got,) = [t for t in cohort.trials if t.source == T1]
    (want,) = [t for t in clean.trials if t.source == T1]
    assert got.n_samples == want.n_samples == N
    np.testing.assert_array_equal(got.angle_deg, want.angle_deg)
