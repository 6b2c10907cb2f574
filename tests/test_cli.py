"""The command line end to end on a small simulated cohort, and its error handling."""

import json

import numpy as np
import pytest

from quadshank.cli import main
from quadshank.data._interchange import load_cohort


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    assert main(["--quiet", "simulate", "--out", str(out), "--minutes", "2", "--legs", "TN-left,JM-right"]) == 0
    return out


def test_simulate_identify_evaluate(data, tmp_path):
    truth = json.loads((data / "truth.json").read_text())
    assert set(truth["legs"]) == {"TN-left", "JM-right"}
    assert main(["--quiet", "identify", str(data), "--out", str(tmp_path / "id")]) == 0
    doc = json.loads((tmp_path / "id" / "summary.json").read_text())
    assert doc["schema"] == "quadshank/identification" and doc["sampling_period_s"] == pytest.approx(0.01)
    s = doc["legs"]
    assert set(s) == {"TN-left", "JM-right"}
    for leg in s:
        assert abs(s[leg]["delay_samples"] - truth["legs"][leg]["active"]["delay_samples"]) <= 1
        assert set(s[leg]["model3"]) >= {"gain", "gamma_angle", "gamma_velocity"}
    for name in ("table1", "table2", "table3", "table4", "passive"):
        assert (tmp_path / "id" / "tables" / f"{name}.csv").exists()
        assert (tmp_path / "id" / "tables" / f"{name}.md").exists()
    assert (tmp_path / "id" / "figures" / "fig2_signals.png").stat().st_size > 10_000

    assert main(["--quiet", "evaluate", str(data), "--out", str(tmp_path / "ev"), "--identified", str(tmp_path / "id")]) == 0
    ev = json.loads((tmp_path / "ev" / "summary.json").read_text())
    assert set(ev["J"]) == {"model1", "model2", "model3"}
    for model in ev["J"]:
        assert set(ev["J"][model]) == {"1", "2", "3"}
        hs = ev["J"][model]["2"]
        assert set(hs) == {"100", "250", "500", "1000"}
        assert hs["100"] < hs["1000"]  # errors grow with horizon
    assert (tmp_path / "ev" / "figures" / "fig6_predictions_1s.png").exists()
    # the black-box yardstick beside them, trained on trial 1, on every trial and horizon
    bb = ev["blackbox"]
    assert set(bb["J"]) == {"1", "2", "3"} and set(bb["J"]["2"]) == {"100", "250", "500", "1000"}
    assert {o["trained_on"] for o in bb["orders"].values()} == {1}
    for row in bb["better_than"]:
        assert all(bb["J"][row["trial"]][h] < ev["J"][row["model"]][row["trial"]][h] for h in row["horizons_ms"])
    assert "A black-box yardstick" in (tmp_path / "ev" / "report.md").read_text()


def test_convert_round_trip(data, tmp_path):
    nc = tmp_path / "cohort.nc"
    assert main(["--quiet", "convert", str(data), str(nc)]) == 0
    assert main(["--quiet", "convert", str(nc), str(tmp_path / "back")]) == 0
    a, b = load_cohort(data), load_cohort(tmp_path / "back")
    for ta, tb in zip(a, b):
        assert np.array_equal(ta.angle_deg, tb.angle_deg) and np.array_equal(ta.stimulation, tb.stimulation)


def test_expected_errors_are_one_line_with_exit_code_2(data, tmp_path, capsys):
    bad = tmp_path / "bad"
    main(["--quiet", "convert", str(data), str(tmp_path / "c.nc")])
    main(["--quiet", "convert", str(tmp_path / "c.nc"), str(bad)])
    f = next(bad.glob("*TN-left*trial1.csv"))
    lines = f.read_text().splitlines()
    cells = lines[5].split(",")
    cells[1] = "oops"
    lines[5] = ",".join(cells)
    f.write_text("\n".join(lines) + "\n")
    capsys.readouterr()
    assert main(["--quiet", "identify", str(bad), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("quadshank: error:") and "Traceback" not in err
    assert f.name in err and "row 6" in err
    assert not (tmp_path / "x" / "summary.json").exists()  # nothing half-written
    assert main(["--quiet", "evaluate", str(data), "--out", str(tmp_path / "y"), "--identified", str(tmp_path / "nope")]) == 2
    assert "no identification here" in capsys.readouterr().err
    assert main(["--quiet", "simulate", "--out", str(tmp_path / "z"), "--effects", "telepathy"]) == 2
    assert "telepathy" in capsys.readouterr().err


@pytest.mark.slow
def test_demo_small(tmp_path, monkeypatch, capsys):
    """`quadshank demo` at a small size: the reproduction, a fit, its evaluation, a diagnosis and the
    report, each in its folder, and the command says where the report is."""
    from quadshank.commands import demo as _demo
    monkeypatch.setattr(_demo, "DEMO_EFFECTS", ("torque_angle_peak",))  # one candidate keeps the test short
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--minutes", "1", "--legs", "TN-left,OT-left",
                 "--chains", "1", "--warmup", "20", "--draws", "20", "--time-limit", "1"]) == 0
    err = capsys.readouterr().err
    assert f"open the report: {out / 'report' / 'index.html'}" in err
    assert "did not pass its checks" in err  # 20 draws cannot pass; the demo says so and goes on
    s = json.loads((out / "summary.json").read_text())
    assert s["fit_legs"] == ["TN-left", "OT-left"] and s["fit_ok"] is False
    assert list(s["seconds"]) == ["reproduce", "fit", "evaluate", "diagnose", "report"]
    fit = json.loads((out / "fit" / "summary.json").read_text())
    assert fit["settings"]["max_tree_depth"] == 5 == s["fit_settings"]["max_tree_depth"]  # the demo's shallow trees
    # drawn to the demo's target ESS, stopped short after one block (the time limit, or divergences first), and said so
    t = fit["target"]
    assert t["target_ess"] == 200 and t["blocks"] == 1 and not t["met"] and t["stopped"] != "target met"
    assert t["stopped"] in (out / "README.md").read_text()
    rep = json.loads((out / "reproduce" / "summary.json").read_text())
    assert set(rep["J"]) == {"model1", "model2", "model3"}
    ev = json.loads((out / "evaluate" / "summary.json").read_text())
    diag = json.loads((out / "diagnose" / "summary.json").read_text())
    # the loop's baseline on twitches that vary: model3s with its noise term, fitted and diagnosed
    assert s["fit_settings"]["model"] == "model3s+twitch_variability" == fit["model"]
    assert set(ev["J_legs"]["model3s+twitch_variability"]) == {"TN-left", "OT-left"}
    assert diag["model"] == "model3s+twitch_variability"
    assert [r["effect"] for r in diag["ranking"]] == ["torque_angle_peak"] and diag["verdict"] == s["verdict"]
    # the loop is shown on legs simulated again with torque_angle_peak hidden; the reproduction stays the paper's
    assert s["hidden"] == ["torque_angle_peak"] and s["found"] == (s["verdict"] == "torque_angle_peak")
    assert json.loads((out / "loop-data" / "truth.json").read_text())["effects"] == ["torque_angle_peak"]
    assert json.loads((out / "reproduce" / "data" / "truth.json").read_text())["effects"] == []
    assert fit["data"] == str((out / "loop-data").resolve())
    assert "torque_angle_peak hidden in the legs fitted" in (out / "README.md").read_text()
    index = (out / "report" / "index.html").read_text()
    assert "TN-left" in index and "OT-left" in index and "torque_angle_peak" in index
    assert 'id="fit-warning"' in index  # the failed checks at the top of the page
    assert "report/index.html" in (out / "README.md").read_text()


def test_identify_a_cohort_with_subjects_beyond_the_paper(data, tmp_path, capsys):
    """Legs the paper's tables and the truth do not describe get empty cells, not a crash."""
    from quadshank.data import Cohort, write_interchange

    cohort = load_cohort(data)
    other = tuple(t.replace(subject="AB", source="") for t in cohort.trials_of("TN-left"))
    mixed = tmp_path / "mixed"
    write_interchange(Cohort(cohort.trials + other), mixed)
    (mixed / "truth.json").write_text((data / "truth.json").read_text())  # the truth lacks AB-left
    assert main(["--quiet", "identify", str(mixed), "--out", str(tmp_path / "id")]) == 0
    s = json.loads((tmp_path / "id" / "summary.json").read_text())["legs"]
    assert set(s) == {"TN-left", "JM-right", "AB-left"}
    assert "recovery" in s["TN-left"] and "recovery" not in s["AB-left"]
    table = (tmp_path / "id" / "tables" / "table1.csv").read_text().splitlines()
    assert "paper d [ms]" in table[0] and any(row.startswith("AB-left,") for row in table[1:])


def test_a_character_the_figures_font_lacks_is_named_once(data, tmp_path, capsys):
    """Subjects named in a script the figures' font lacks: matplotlib warns at every figure; the
    command says it once per character, in one line."""
    from quadshank.data import Cohort, write_interchange

    cohort = load_cohort(data)
    named = tuple(t.replace(subject="患者", source="") for t in cohort.trials_of("TN-left"))
    write_interchange(Cohort(named), tmp_path / "cjk")
    capsys.readouterr()
    assert main(["--quiet", "identify", str(tmp_path / "cjk"), "--out", str(tmp_path / "id")]) == 0
    err = capsys.readouterr().err
    assert "Glyph" not in err
    warned = [line for line in err.splitlines() if "font has no" in line]
    assert len(warned) == 2 and "'患'" in warned[0] and "'者'" in warned[1], warned


def test_implausible_units_are_warned_about_in_one_line(data, tmp_path, capsys):
    from quadshank.data import Cohort, write_interchange

    cohort = load_cohort(data)
    tn = cohort.trials_of("TN-left")
    scaled = tuple(t.replace(acceleration_deg_s2=np.deg2rad(t.acceleration_deg_s2)) if t.trial == 2 else t for t in tn)
    write_interchange(Cohort(scaled), tmp_path / "rad")
    capsys.readouterr()
    assert main(["--quiet", "identify", str(tmp_path / "rad"), "--out", str(tmp_path / "id")]) == 0
    warned = [line for line in capsys.readouterr().err.splitlines() if line.startswith("quadshank: warning:")]
    assert len(warned) == 1, warned
    assert "trial2.csv" in warned[0] and "TN-left trial 2" in warned[0] and "pi/180" in warned[0]


def test_a_truth_json_of_another_kind_is_left_aside(data, tmp_path, capsys):
    import shutil

    mine = tmp_path / "mine"
    shutil.copytree(data, mine)
    (mine / "truth.json").write_text("[1, 2]")  # the user's own file of that name
    capsys.readouterr()
    assert main(["--quiet", "identify", str(mine), "--out", str(tmp_path / "id")]) == 0
    assert "truth.json: not the simulator's truth" in capsys.readouterr().err
    s = json.loads((tmp_path / "id" / "summary.json").read_text())["legs"]
    assert all("recovery" not in v for v in s.values())


def test_the_command_line_keeps_compiled_programs_in_a_cache_on_disk(tmp_path):
    """``QUADSHANK_XLA_CACHE`` names the cache's folder and ``off`` turns it off; without it the
    cache is under ``$XDG_CACHE_HOME``; a cache the caller chose for JAX is kept.  A program that
    compiles in milliseconds is kept too."""
    import os
    import subprocess
    import sys

    code = ("import jax; from quadshank.common import _xla_cache as c; "
            "f = c.use_compilation_cache(); jax.jit(lambda x: jax.numpy.sin(x) * 2.0)(1.0).block_until_ready(); "
            "print(f)")
    base = {k: v for k, v in os.environ.items()
            if not k.startswith(("JAX_COMPILATION_CACHE", "JAX_PERSISTENT_CACHE", "QUADSHANK_XLA_CACHE"))}

    def run(**env) -> str:
        proc = subprocess.run([sys.executable, "-c", code], env={**base, **env}, capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr[-2000:]
        return proc.stdout.strip()

    def kept(folder) -> bool:  # a program's file (JAX names it ...-cache), not only the cache's lock file
        return any(p.name.endswith("-cache") for p in folder.iterdir())

    folder = tmp_path / "cache"
    assert run(QUADSHANK_XLA_CACHE=str(folder)) == str(folder) and kept(folder)
    assert run(QUADSHANK_XLA_CACHE="off") == "None"
    xdg = tmp_path / "xdg"
    assert run(XDG_CACHE_HOME=str(xdg)) == str(xdg / "quadshank" / "xla") and kept(xdg / "quadshank" / "xla")
    mine = tmp_path / "mine"
    assert run(QUADSHANK_XLA_CACHE=str(folder), JAX_COMPILATION_CACHE_DIR=str(mine)) == str(mine)


def test_a_warning_under_a_progress_bar_gets_a_line_of_its_own():
    """A warning raised while a progress bar is drawn prints as its own line above the bar, which
    is drawn again below it; printed plainly it would share the bar's line and be overwritten."""
    import io

    from tqdm import tqdm

    from quadshank.common._progress import write_above_bars

    out = io.StringIO()
    bar = tqdm(range(3), file=out, desc="identify", mininterval=0)
    for k in bar:
        if k == 1:
            write_above_bars("quadshank: warning: TN-left: something", file=out)
    bar.close()
    lines = [line.strip() for line in out.getvalue().replace("\r", "\n").split("\n")]
    assert "quadshank: warning: TN-left: something" in lines


def test_a_bar_that_names_its_step_in_a_log_shows_the_steps_done(monkeypatch):
    """In a log file (frames half a minute apart) a bar that names each step as it starts shows how
    many steps are done beside the name, not the count of its last timed frame (0/5 throughout)."""
    import io
    import re

    from quadshank.common._progress import progress_bar

    out = io.StringIO()  # not a terminal: the log file's interval between timed frames
    monkeypatch.setattr("sys.stderr", out)
    seen = []
    bar = progress_bar(["a", "b", "c", "d", "e"], desc="screening effects")
    for name in bar:
        bar.set_postfix_str(f"model + {name}")
        seen.append(name)
    assert seen == ["a", "b", "c", "d", "e"]
    frames = out.getvalue().replace("\r", "\n")
    assert re.search(r"\b4/5 \[[^\]]*model \+ e\]", frames), frames
    assert re.search(r"\b2/5 \[[^\]]*model \+ c\]", frames), frames
    assert list(progress_bar(range(3), desc="x", enabled=False)) == [0, 1, 2]


def test_an_interrupt_dropped_in_a_callback_is_recorded_without_a_traceback(capsys):
    """Python reports an exception raised where it cannot propagate (a finaliser, JAX's
    garbage-collection hook) as "Exception ignored" and drops it: a Ctrl-C that lands there is
    recorded for the command to act on, and no traceback is printed for it."""
    import signal

    from quadshank.common._interrupt import check_interrupt, handling_interrupts, interrupt_requested

    class Finalised:
        def __del__(self):
            signal.raise_signal(signal.SIGINT)

    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal
    try:
        with handling_interrupts():
            thing = Finalised()
            del thing  # the handler raises inside __del__, where Python drops it
            assert interrupt_requested()
            with pytest.raises(KeyboardInterrupt):
                check_interrupt()
        assert not interrupt_requested() and signal.getsignal(signal.SIGINT) is signal.default_int_handler
        assert "Exception ignored" not in capsys.readouterr().err
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a background job's: ignored it stays
        with handling_interrupts():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, before)
