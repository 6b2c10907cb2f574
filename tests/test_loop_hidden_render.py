"""The hidden-effects study reads each loop's rounds from its folder and says whether it found the effect."""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import loop_hidden  # noqa: E402


def _loop(tmp_path, name, rounds):
    """A ``discover`` folder with one round per (verdict, leader, ΔELPD, SE)."""
    out = tmp_path / name
    for k, (verdict, leader, d, se) in enumerate(rounds, start=1):
        (out / f"round-{k}").mkdir(parents=True)
        ranking = [{"effect": leader, "delta_elpd": d, "delta_elpd_se": se}] if leader else []
        (out / f"round-{k}" / "summary.json").write_text(json.dumps({"model": f"m{k}", "verdict": verdict,
                                                                      "ranking": ranking}))
    return out


def test_found_means_added_and_none_allows_only_the_noise_term(tmp_path):
    hidden = _loop(tmp_path, "a", [("twitch_variability", "twitch_variability", 865.0, 127.0),
                                   ("fatigue", "fatigue", 102.0, 48.0), ("none", "hill_velocity", 9.0, 20.0)])
    row = loop_hidden.loop_row("fatigue", 2.0, hidden, 300.0)
    assert row["found"] and row["added"] == ["twitch_variability", "fatigue"]
    assert not loop_hidden.loop_row("potentiation", 2.0, hidden, 300.0)["found"]  # a stand-in is not the effect
    clean = _loop(tmp_path, "b", [("twitch_variability", "twitch_variability", 865.0, 127.0),
                                  ("none", "hill_velocity", 23.0, 27.0)])
    assert loop_hidden.loop_row("none", 1.0, clean, 200.0)["found"]
    false_positive = _loop(tmp_path, "c", [("accel_resonance", "accel_resonance", 38.0, 8.0)])
    assert not loop_hidden.loop_row("none", 1.0, false_positive, 200.0)["found"]


def test_the_table_gives_each_round_and_names_the_leader_of_a_none(tmp_path):
    out = _loop(tmp_path, "a", [("twitch_variability", "twitch_variability", 865.4, 126.6),
                                ("none", "hill_velocity", 23.1, 26.9)])
    record = {"command": "python benchmarks/loop_hidden.py", "leg": "JM-left", "seed": 4,
              "rows": [loop_hidden.loop_row("potentiation", 1.0, out, 248.0)]}
    text = loop_hidden.render(record)
    row = next(line for line in text.splitlines() if line.startswith("| potentiation"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells == ["potentiation", "1", "no", "`twitch_variability` (865 ± 127)",
                     "none (leader hill_velocity 23 ± 27)", "", "248"]
    assert "python benchmarks/loop_hidden.py" in text and "seed 4" in text


def test_a_confirmed_round_gives_nuts_beside_the_screen(tmp_path):
    out = _loop(tmp_path, "a", [("twitch_variability", "twitch_variability", 1126.0, 153.0),
                                ("none", "angle_delay", 40.0, 20.0)])
    for k, nuts in ((1, {"delta_elpd": 1089.0, "delta_elpd_se": 150.0, "clears_bar": True, "banner": None}),
                    (2, {"delta_elpd": 38.0, "delta_elpd_se": 21.0, "clears_bar": False, "banner": "R-hat 1.02"})):
        path = out / f"round-{k}" / "summary.json"
        summary = json.loads(path.read_text())
        summary["ranking"][0]["nuts"] = nuts
        summary["screen_verdict"] = summary["verdict"]
        path.write_text(json.dumps(summary))
    row = loop_hidden.loop_row("angle_delay", 1.0, out, 400.0)
    assert row["rounds"][0]["nuts"]["clears_bar"] and not row["rounds"][1]["nuts"]["clears_bar"]
    line = next(x for x in loop_hidden.render({"command": "c", "leg": "JM-left", "seed": 4, "rows": [row]}).splitlines()
                if x.startswith("| angle_delay"))
    cells = [c.strip() for c in line.strip("|").split("|")]
    assert cells[3] == "`twitch_variability` (1126 ± 153; NUTS 1089 ± 150, clears the bar)"
    assert cells[4] == ("none (leader angle_delay 40 ± 20; NUTS 38 ± 21, does not clear it; "
                        "its fit failed its checks)")


def test_a_new_run_replaces_the_rows_it_redoes_and_keeps_the_others():
    def row(effect, minutes, seconds):
        return {"effect": effect, "minutes": minutes, "rounds": [], "added": [], "found": False, "seconds": seconds}

    old = {"command": "a", "leg": "JM-left", "seed": 4,
           "rows": [row("none", 1.0, 1), row("fatigue", 1.0, 2), row("fatigue", 2.0, 3), row("hill_velocity", 1.0, 4)]}
    new = {"command": "b", "leg": "JM-left", "seed": 4, "rows": [row("fatigue", 2.0, 30)]}
    out = loop_hidden.merged(old, new)
    assert [(r["effect"], r["minutes"], r["seconds"]) for r in out["rows"]] == [
        ("none", 1.0, 1), ("fatigue", 1.0, 2), ("fatigue", 2.0, 30), ("hill_velocity", 1.0, 4)]
    assert out["commands"] == ["a", "b"] and "(1) `a`, (2) `b`" in loop_hidden.render(out)
    other = {**new, "seed": 5}
    assert loop_hidden.merged(old, other) is other  # another leg or seed: nothing of the old is kept


def test_each_row_names_the_command_that_made_it():
    """A row keeps its command through merges; in a record whose rows do not yet name theirs, a
    row's is the last of the record's commands that ran its effect at its length."""
    def row(effect, minutes, **extra):
        return {"effect": effect, "minutes": minutes, "rounds": [], "added": [], "found": True, "seconds": 1.0, **extra}

    script = "python benchmarks/loop_hidden.py"
    old = {"leg": "JM-left", "seed": 4, "command": f"{script} --jobs 2",
           "commands": [f"{script} --jobs 2", f"{script} --confirm --minutes 1 --effects none,fatigue",
                        f"{script} --confirm --minutes 2 --effects fatigue,gravity_offset"],
           "rows": [row("none", 1.0), row("fatigue", 1.0), row("fatigue", 2.0), row("gravity_offset", 4.0),
                    row("hill_velocity", 1.0)]}
    last = f"{script} --confirm --target-accept 0.95 --minutes 1 --effects hill_velocity"
    out = loop_hidden.merged(old, {"leg": "JM-left", "seed": 4, "command": last,
                                   "rows": [row("hill_velocity", 1.0, command=last)]})
    made_by = {(r["effect"], r["minutes"]): r["command"] for r in out["rows"]}
    assert made_by == {("none", 1.0): old["commands"][1], ("fatigue", 1.0): old["commands"][1],
                       ("fatigue", 2.0): old["commands"][2], ("gravity_offset", 4.0): old["commands"][0],
                       ("hill_velocity", 1.0): last}
    assert out["commands"] == [*old["commands"], last]
    text = loop_hidden.render(out)
    cells = {line.split("|")[1].strip() + line.split("|")[2].strip(): line.rstrip("|").split("|")[-1].strip()
             for line in text.splitlines() if line.startswith("| ") and not line.startswith("| hidden")}
    assert cells == {"none1": "(2)", "fatigue1": "(2)", "fatigue2": "(3)", "gravity_offset4": "(1)",
                     "hill_velocity1": "(4)"}
    # a command whose rows were all redone since is no longer listed
    redo = f"{script} --minutes 4 --effects gravity_offset"
    again = loop_hidden.merged(out, {"leg": "JM-left", "seed": 4, "command": redo,
                                     "rows": [row("gravity_offset", 4.0, command=redo)]})
    assert again["commands"] == [*old["commands"][1:], last, redo]
