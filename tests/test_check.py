"""`quadshank check`: what the reader makes of a folder of recordings, before any fit."""

import contextlib
import csv
import io
import json

import numpy as np
import pytest

from quadshank.cli import main
from quadshank.commands import Check, run_check
from quadshank.data._cohort import Cohort
from quadshank.data._interchange import DataWarning, convert, write_interchange
from quadshank.data._simulate import simulate_cohort

N = 3000  # samples of a trial: 0.5 min at 10 ms
EXCLUDED = 50  # the release of the pendulum test, left out


def _rows(path):
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    return rows[0], rows[1:]


def _write(path, head, body):
    with open(path, "w", newline="") as f:
        csv.writer(f).writerows([head, *body])


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    """Three legs, two trials each, as a lab's folder might hold them: TN-left's trial 2 a pendulum
    test (no pulses) whose release is excluded, JM-left's trial 1 without an accelerometer, and
    OT-left's trial 1 trains of 4 pulses 30 ms apart (no isolated twitch)."""
    root = tmp_path_factory.mktemp("check") / "data"
    cohort, _ = simulate_cohort(legs=["TN-left", "JM-left", "OT-left"], minutes=N / 6000, seed=1, trials=(1, 2))
    write_interchange(cohort, root)

    head, body = _rows(root / "TN-left-trial2.csv")
    si = head.index("stimulation")
    head.append("exclude")
    for i, r in enumerate(body):
        r[si] = "0"
        r.append("1" if i < EXCLUDED else "0")
    _write(root / "TN-left-trial2.csv", head, body)

    head, body = _rows(root / "JM-left-trial1.csv")
    ai = head.index("acceleration_deg_s2")
    _write(root / "JM-left-trial1.csv", [c for j, c in enumerate(head) if j != ai],
           [[c for j, c in enumerate(r) if j != ai] for r in body])

    head, body = _rows(root / "OT-left-trial1.csv")
    si = head.index("stimulation")
    for i, r in enumerate(body):
        r[si] = "0.6" if i >= 100 and i % 100 in (0, 3, 6, 9) else "0"
    _write(root / "OT-left-trial1.csv", head, body)
    return root


def test_each_trial_is_summarised_from_its_file(folder, tmp_path):
    result = run_check(folder, tmp_path / "out")
    rows = {(r["leg"], r["trial"]): r for r in result.trials}
    assert list(rows) == [(leg, t) for leg in ("TN-left", "JM-left", "OT-left") for t in (1, 2)]
    for (leg, t), r in rows.items():
        head, body = _rows(folder / f"{leg}-trial{t}.csv")
        values = np.array([[float(c) for c in row] for row in body])
        col = {name: values[:, j] for j, name in enumerate(head)}
        keep = col["exclude"] == 0 if "exclude" in col else np.ones(len(body), bool)
        assert r["samples"] == N and r["seconds"] == pytest.approx(30.0) and r["sampling_period_ms"] == pytest.approx(10.0)
        assert r["pulses"] == int(np.count_nonzero(col["stimulation"]))
        assert r["excluded_share"] == pytest.approx(np.mean(~keep))
        assert r["angle_min_deg"] == pytest.approx(col["angle_deg"][keep].min(), abs=1e-3)
        assert r["angle_max_deg"] == pytest.approx(col["angle_deg"][keep].max(), abs=1e-3)
        assert r["acceleration"] == ("measured" if "acceleration_deg_s2" in col else "derived from the angle")
        assert r["velocity"] == "derived from the angle" and r["stimulation"] == "levels"
        assert r["source"] == f"{leg}-trial{t}.csv"

    pendulum, trains = rows[("TN-left", 2)], rows[("OT-left", 1)]
    assert pendulum["pulses"] == 0 and pendulum["pulse_kind"] == "no pulses (a pendulum test)"
    assert pendulum["excluded_share"] == pytest.approx(EXCLUDED / N) and pendulum["shortest_interval_ms"] is None
    assert trains["pulse_kind"] == "trains" and trains["isolated_twitches"] == 0
    assert trains["shortest_interval_ms"] == pytest.approx(30.0)
    # the simulator's random pulses leave isolated twitches in every other trial
    assert all(r["pulse_kind"] == "isolated twitches" and r["isolated_twitches"] >= 8 for k, r in rows.items()
               if k not in {("TN-left", 2), ("OT-left", 1)})


def test_what_identify_and_fit_can_do_with_each_leg(folder):
    first = run_check(folder).legs
    assert first["TN-left"]["identify"].startswith("models 1-3 (")
    assert "passive system from trial(s) 2 (no pulses)" in first["TN-left"]["identify"]
    assert first["OT-left"]["identify"].startswith("no: 0 isolated twitches of the 8 needed")
    assert first["OT-left"]["fit"] == "any model"
    second = run_check(folder, identification_trial=2).legs
    assert second["TN-left"]["identify"].startswith("the passive system only")
    assert second["TN-left"]["fit"].startswith("--model passive")
    third = run_check(folder, identification_trial=3).legs
    assert third["JM-left"]["identify"].startswith("no trial 3")


def test_the_output_folder_holds_the_table_a_figure_per_trial_and_the_summary(folder, tmp_path):
    out = tmp_path / "out"
    result = run_check(folder, out)
    head, body = _rows(out / "recordings.csv")
    assert len(body) == 6 and head[:3] == ["leg", "trial", "source"]
    assert [r[:2] for r in body] == [[r["leg"], str(r["trial"])] for r in result.trials]
    assert [int(r[head.index("pulses")]) for r in body] == [r["pulses"] for r in result.trials]
    assert "| TN-left | 2 |" in (out / "recordings.md").read_text()
    figures = [f for f in result.files if f.endswith(".png")]
    assert len(figures) == 6 and "recording_TN-left_trial2.png" in figures
    assert [r[head.index("figure")] for r in body] == [r["figure"] for r in result.trials] == figures
    assert all((out / f).stat().st_size > 10_000 for f in figures)
    back = Check.read(out)
    assert back.to_json() == json.loads(json.dumps(result.to_json()))


def test_the_readers_warnings_are_kept_and_said_again(folder, tmp_path):
    """Two subjects that differ only in case draw the reader's warning; check keeps it."""
    data = _copy(folder, tmp_path)
    manifest = (data / "manifest.csv").read_text().replace("\nJM,", "\ntn,")
    (data / "manifest.csv").write_text(manifest)
    with pytest.warns(DataWarning, match="differ only in case"):
        result = run_check(data)
    assert any("differ only in case" in w for w in result.warnings)
    assert "tn-left" in result.legs


def test_on_the_command_line(folder, tmp_path, capsys):
    assert main(["check", str(folder)]) == 0
    said = capsys.readouterr().out
    for leg in ("TN-left", "JM-left", "OT-left"):
        assert f"{leg}: identify (trial 1):" in said
    assert not (tmp_path / "out").exists()
    assert main(["--quiet", "check", str(folder), "--out", str(tmp_path / "out")]) == 0
    assert (tmp_path / "out" / "summary.json").is_file()

    bad = tmp_path / "bad"
    bad.mkdir()
    for p in folder.iterdir():
        (bad / p.name).write_bytes(p.read_bytes())
    head, body = _rows(bad / "JM-left-trial2.csv")
    body[3][head.index("angle_deg")] = "abc"
    _write(bad / "JM-left-trial2.csv", head, body)
    with contextlib.redirect_stderr(io.StringIO()) as err:
        assert main(["check", str(bad)]) == 2
    assert "JM-left-trial2.csv, column 'angle_deg', row 5" in err.getvalue()


def test_a_leg_read_from_a_stimulators_columns_says_its_scale(folder, tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    for p in folder.iterdir():
        (data / p.name).write_bytes(p.read_bytes())
    for t in (1, 2):
        head, body = _rows(data / f"JM-left-trial{t}.csv")
        si = head.index("stimulation")
        head[si] = "pulse_width_us"
        for r in body:
            r[si] = repr(400.0 * float(r[si]))
        _write(data / f"JM-left-trial{t}.csv", head, body)
    result = run_check(data)
    rows = {(r["leg"], r["trial"]): r for r in result.trials}
    assert rows[("JM-left", 1)]["stimulation"] == "charge over the leg's largest (400 µs)"
    assert rows[("TN-left", 1)]["stimulation"] == "levels"
    assert "--add-effect recruitment_sigmoid" in result.legs["JM-left"]["fit"]
    assert "recruitment" not in result.legs["TN-left"]["fit"]


def test_a_cohort_file_reads_as_its_folder(folder, tmp_path):
    nc = convert(folder, tmp_path / "cohort.nc")
    from_file, from_folder = run_check(nc), run_check(folder)
    assert from_file.trials == from_folder.trials and from_file.legs == from_folder.legs


def test_a_period_too_short_for_the_delays_considered_is_said():
    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.1, seed=1, trials=(1,), sampling_period_s=0.005)
    with pytest.warns(DataWarning, match="delays considered reach 10 samples = 50 ms"):
        result = run_check(cohort)
    assert result.data == "a cohort in memory" and result.sampling_period_s == pytest.approx(0.005)
    assert any("resample" in w for w in result.warnings)
    assert result.trials[0]["sampling_period_ms"] == pytest.approx(5.0)


def test_pendulum_tests_at_a_short_period_are_not_told_to_be_resampled():
    """Pendulum tests alone are modelled at any period: no word of the delays considered."""
    import warnings

    from quadshank.data import simulate_pendulum_test
    from quadshank.data._simulate import PASSIVE_TRUTH
    from quadshank.inference import identify_cohort

    pendulum = Cohort((simulate_pendulum_test(PASSIVE_TRUTH["TN-left"], subject="TN", sampling_period_s=0.005),))
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        run_check(pendulum)
        identify_cohort(pendulum)
    assert not [w for w in said if "delays considered" in str(w.message)], [str(w.message) for w in said]


def test_a_period_too_short_for_a_muscles_delays_is_each_legs_verdict():
    """Below 3 ms identify and a muscle's fit refuse stimulated data: check says so per leg, not "models 1-3"."""
    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.5, seed=1, trials=(1,), sampling_period_s=0.002)
    with pytest.warns(DataWarning):
        uses = run_check(cohort).legs["TN-left"]
    assert uses["identify"].startswith("no: at 2 ms the delays considered reach 20 ms") and "--resample" in uses["identify"]
    assert uses["fit"] == "--model passive only, until resampled"


def test_twitches_that_flex_the_knee_are_each_legs_verdict():
    """A flipped angle: check warns, and its verdict says identify will refuse the twitches."""
    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=1.0, seed=1, trials=(1,))
    t = cohort.trials[0]
    flipped = Cohort((t.replace(angle_deg=-t.angle_deg, velocity_deg_s=-t.velocity_deg_s,
                                acceleration_deg_s2=-t.acceleration_deg_s2),))
    with pytest.warns(DataWarning, match="positive in flexion"):
        uses = run_check(flipped).legs["TN-left"]
    assert uses["identify"].startswith("no: its twitches flex the knee"), uses
    assert run_check(cohort).legs["TN-left"]["identify"].startswith("models 1-3")


def _copy(folder, tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    for p in folder.iterdir():
        (data / p.name).write_bytes(p.read_bytes())
    return data


def _set_manifest(data, subject, trial, column, value):
    """Set one trial's cell of the manifest, adding the column (empty elsewhere) where it is new."""
    head, body = _rows(data / "manifest.csv")
    if column not in head:
        head.append(column)
        body = [r + [""] for r in body]
    for r in body:
        if r[0] == subject and r[2] == str(trial):
            r[head.index(column)] = value
    _write(data / "manifest.csv", head, body)


def test_a_leg_without_enough_samples_for_the_passive_system_is_told_what_identify_would_say(folder, tmp_path):
    """check gives identify's verdict: a pendulum test cut to 1.5 s, its first 0.5 s excluded,
    cannot give the passive system."""
    from quadshank.inference import IdentificationError, identify_cohort
    from quadshank.data import load_cohort

    data = _copy(folder, tmp_path)
    _set_manifest(data, "TN", 2, "end_s", "1.5")
    result = run_check(data, identification_trial=2)
    row = next(r for r in result.trials if r["leg"] == "TN-left" and r["trial"] == 2)
    assert row["passive_samples"] < 200
    assert result.legs["TN-left"]["identify"].startswith(f"no: {row['passive_samples']} samples for the passive system")
    assert result.legs["TN-left"]["identify"].endswith("in trial 2, of the 200 needed")
    with pytest.raises(IdentificationError, match=f"only {row['passive_samples']} quiet samples"):
        identify_cohort(load_cohort(data).select(["TN-left"]), trial=2)
    # a leg with enough: its count is what identify uses
    full = next(r for r in run_check(folder).trials if r["leg"] == "TN-left" and r["trial"] == 2)
    assert full["passive_samples"] == identify_cohort(load_cohort(folder).select(["TN-left"]), trial=2)["TN-left"].n_quiet


def test_trials_at_different_periods_are_shown_and_each_leg_told_why_the_other_commands_refuse(folder, tmp_path):
    data = _copy(folder, tmp_path)
    head, body = _rows(data / "OT-left-trial2.csv")
    _write(data / "OT-left-trial2.csv", head, body[::2])  # every other sample: 20 ms
    _set_manifest(data, "OT", 2, "sampling_period_s", "0.02")
    with pytest.warns(DataWarning, match="sampled at different periods"):
        result = run_check(data, tmp_path / "out")
    assert result.sampling_period_s is None
    assert {r["sampling_period_ms"] for r in result.trials} == {10.0, 20.0}
    assert all(u["identify"].startswith("no: the trials are sampled at different periods") for u in result.legs.values())
    assert Check.read(tmp_path / "out").sampling_period_s is None


def test_a_subject_named_like_a_path_keeps_its_figures_in_the_output_folder(folder, tmp_path):
    data = _copy(folder, tmp_path)
    manifest = (data / "manifest.csv").read_text().replace("\nJM,", "\nx/../../escaped,")
    (data / "manifest.csv").write_text(manifest)
    out = tmp_path / "deep" / "out"
    result = run_check(data, out)
    assert "recording_x_.._.._escaped-left_trial1.png" in result.files
    assert all((out / f).is_file() for f in result.files)
    assert not list(tmp_path.glob("*.png")) and not list((tmp_path / "deep").glob("*.png"))


def test_a_long_trials_figure_adds_a_view_of_its_first_pulses():
    """Minutes of pulses merge into a band: a trial over a minute gets a second view of 20 s from
    its first pulse, holding only that span's pulses; a short trial keeps one view."""
    import matplotlib.pyplot as plt

    from quadshank.outputs import plot_recording

    cohort, _ = simulate_cohort(legs=["JM-left"], minutes=1.5, seed=2, trials=(1,))
    trial = cohort.trials[0]
    first = trial.pulse_indices[0]
    fig = plot_recording(trial, isolated=trial.pulse_indices)
    assert len(fig.axes) == 4
    zoom = fig.axes[3]
    drawn = np.concatenate([np.asarray(c.get_segments())[:, 0, 0] for c in zoom.collections])
    assert drawn.min() == pytest.approx(trial.time_s[first])
    assert drawn.max() <= trial.time_s[first] + 20.0
    assert drawn.size < 2 * trial.pulse_indices.size / 3  # pulses and isolated ones of 20 s of 90
    plt.close(fig)
    short, _ = simulate_cohort(legs=["JM-left"], minutes=0.5, seed=2, trials=(1,))
    fig = plot_recording(short.trials[0])
    assert len(fig.axes) == 2
    plt.close(fig)


def test_an_angle_zeroed_elsewhere_qualifies_what_identify_can_do(tmp_path):
    """An angle zeroed away from the shank hanging at rest is warned of by the reader; the verdict on
    the leg says so too, rather than "models 1-3" alone.  A pendulum test zeroed at the flexion
    angle (90° hanging) is doubted by its median."""
    from quadshank.data import simulate_pendulum_test
    from quadshank.data._interchange import angle_doubts
    from quadshank.data._simulate import PASSIVE_TRUTH

    cohort, _ = simulate_cohort(legs=["JM-left"], minutes=0.5, seed=1, trials=(1,))
    stimulated = cohort.trials[0]
    clean = run_check(cohort).legs["JM-left"]["identify"]
    assert "looks zeroed" not in clean and "does not match" not in clean
    with pytest.warns(DataWarning, match="is the goniometer's zero offset"):
        uses = run_check(Cohort((stimulated.replace(angle_deg=stimulated.angle_deg + 30.0),))).legs["JM-left"]
    assert uses["identify"].startswith("models 1-3 (")
    assert "but the angle of trial 1 looks zeroed elsewhere" in uses["identify"]

    # two degrees off: below the reader's rest warning, found by the quiet samples' fit as identify finds it
    with pytest.warns(DataWarning, match=r"JM-left: the quiet samples of trial 1 swing about \+[12]\.\d°"):
        uses = run_check(Cohort((stimulated.replace(angle_deg=stimulated.angle_deg + 2.0),))).legs["JM-left"]
    assert "but the angle of trial 1 looks zeroed elsewhere" in uses["identify"]

    # the angle and the accelerometer in radians agree with each other: check names the span
    in_radians = stimulated.replace(angle_deg=np.deg2rad(stimulated.angle_deg),
                                    acceleration_deg_s2=np.deg2rad(stimulated.acceleration_deg_s2),
                                    velocity_deg_s=np.deg2rad(stimulated.velocity_deg_s))
    with pytest.warns(DataWarning, match="JM-left: the angle of trial 1 spans only .* in radians"):
        uses = run_check(Cohort((in_radians,))).legs["JM-left"]
    assert "but the angle of trial 1 looks like radians" in uses["identify"]

    # an accelerometer in rad/s² (or wired the other way round) beside an angle in degrees: the reader
    # warns of it, and the verdict says the values would come out wrong
    for acc, said in ((np.deg2rad(stimulated.acceleration_deg_s2), "about pi/180"),
                      (-stimulated.acceleration_deg_s2, "runs against")):
        with pytest.warns(DataWarning, match=said):
            uses = run_check(Cohort((stimulated.replace(acceleration_deg_s2=acc),))).legs["JM-left"]
        assert "but the measured acceleration or velocity of trial 1 does not match the angle's derivatives" \
            in uses["identify"], uses

    pendulum = simulate_pendulum_test(PASSIVE_TRUTH["TN-left"], subject="TN", seed=0, seconds=3.0)  # still swinging
    assert angle_doubts(pendulum) == []
    (doubt,) = angle_doubts(pendulum.replace(angle_deg=pendulum.angle_deg + 90.0))
    assert doubt.startswith("the swing's median angle is") and "a flexion angle reads 90° at rest" in doubt
