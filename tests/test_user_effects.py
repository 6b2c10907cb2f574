"""A user's own effect from a file on the command line: fitted, recorded with the fit, reloaded in
a fresh process, and refused when its source changed or went away."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

from quadshank.cli import main

EFFECT = textwrap.dedent('''
    import dataclasses

    from quadshank import Effect, Param, register_effect


    @register_effect
    @dataclasses.dataclass(frozen=True)
    class SquaredTorqueAngle(Effect):
        """A twitch that grows with the squared knee angle."""

        kind = "gain"
        name = "squared_torque_angle"
        params = (Param("c2", "1/deg^2", prior=("normal", 0.0, 1e-4)),)
        c2: float = 0.0

        def factor(self, ctx):
            return 1.0 + self.c2 * ctx.angle**2
''')


def quadshank(*args: str) -> subprocess.CompletedProcess:
    """The command line in a fresh Python process, as a user runs it."""
    code = "import sys; from quadshank.cli import main; raise SystemExit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_a_fit_with_an_effect_from_a_file_reloads_in_a_fresh_process(tmp_path):
    data, fit, effects = tmp_path / "data", tmp_path / "fit", tmp_path / "my_effects.py"
    assert main(["-q", "simulate", "--out", str(data), "--legs", "JM-left", "--minutes", "0.3", "--trials", "1"]) == 0
    effects.write_text(EFFECT)
    run = quadshank("fit", str(data), "--effects-file", str(effects), "--model", "model1", "--add-effect",
                    "squared_torque_angle", "--chains", "1", "--warmup", "20", "--draws", "20", "--out", str(fit))
    assert run.returncode in (0, 3), run.stderr
    assert "effects from" in run.stderr and "squared_torque_angle" in run.stderr
    s = json.loads((fit / "summary.json").read_text())
    assert "c2" in s["legs"]["JM-left"]["params"]
    origin = s["effect_origins"]["squared_torque_angle"]
    assert origin["file"] == str(effects.resolve()) and len(origin["source_sha256"]) == 16
    assert "gravity" not in s["effect_origins"]  # built-ins are not listed

    # a fresh process without --effects-file finds the effect again from the fit's record
    run = quadshank("-q", "report", str(fit), "--out", str(tmp_path / "report"), "--draws", "5",
                    "--start-stride", "50")
    assert run.returncode == 0, run.stderr
    assert "c2" in (tmp_path / "report" / "index.html").read_text() + "".join(
        p.read_text() for p in (tmp_path / "report").glob("*.html"))

    # the source changed: refused, naming the effect and the file
    effects.write_text(EFFECT.replace("1e-4", "2e-4"))
    run = quadshank("-q", "report", str(fit), "--out", str(tmp_path / "report2"))
    assert run.returncode == 2
    assert "effect 'squared_torque_angle' has changed since the fit was made" in run.stderr
    assert str(effects.resolve()) in run.stderr
    # ... or went away
    effects.unlink()
    run = quadshank("-q", "report", str(fit), "--out", str(tmp_path / "report3"))
    assert run.returncode == 2 and "which is not there any more" in run.stderr


def test_an_effects_file_that_defines_nothing_or_fails_is_named(tmp_path, capsys):
    data = tmp_path / "data"
    assert main(["-q", "simulate", "--out", str(data), "--legs", "JM-left", "--minutes", "0.1", "--trials", "1"]) == 0
    empty, broken = tmp_path / "empty.py", tmp_path / "broken.py"
    empty.write_text("x = 1\n")
    broken.write_text("import no_such_module_here\n")
    script, clash, prior = tmp_path / "script.py", tmp_path / "clash.py", tmp_path / "prior.py"
    script.write_text("import sys\nsys.exit(0)\n")
    clash.write_text(EFFECT.replace('"squared_torque_angle"', '"fatigue"'))
    prior.write_text(EFFECT.replace('prior=("normal", 0.0, 1e-4)', 'prior=("normal", 0.0)'))
    for path, text in ((empty, "defines no effect"), (broken, "failed to import: ModuleNotFoundError"),
                       (tmp_path / "missing.py", "no such effects file"), (script, "failed to import: SystemExit"),
                       (clash, "the name 'fatigue' is a built-in effect's"),
                       (prior, "must be ('normal', location, scale)")):
        capsys.readouterr()
        assert main(["-q", "fit", str(data), "--effects-file", str(path), "--out", str(tmp_path / "fit")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("quadshank: error:") and str(path) in err and text in err
        assert not (tmp_path / "fit").exists() or not any((tmp_path / "fit").iterdir())
    from quadshank.model import registered_effects
    assert registered_effects()["fatigue"].__module__ == "quadshank.model._effects"  # the built-in kept


def test_effects_offered_by_an_installed_package_are_loaded(tmp_path, monkeypatch, scratch_registry):
    """An entry point of the group quadshank.effects, as an installed package declares one: here a
    module on the path, found through a stand-in for the installed metadata."""
    import importlib.metadata

    from quadshank.model import _plugins
    from quadshank.model._effects import registered_effects

    (tmp_path / "lab_effects.py").write_text(EFFECT.replace("squared_torque_angle", "lab_squared_angle"))
    monkeypatch.syspath_prepend(str(tmp_path))
    ep = importlib.metadata.EntryPoint(name="lab", value="lab_effects", group=_plugins.ENTRY_POINT_GROUP)
    monkeypatch.setattr(_plugins.importlib.metadata, "entry_points",
                        lambda group=None: [ep] if group == _plugins.ENTRY_POINT_GROUP else [])
    assert _plugins.load_entry_point_effects() == ["lab_squared_angle"]
    assert "lab_squared_angle" in registered_effects()
    assert _plugins.effect_origin("lab_squared_angle")["module"] == "lab_effects"
    assert _plugins.effect_origin("gravity") is None


def test_an_effect_that_returns_nan_is_named_by_the_fit(scratch_registry):
    """A user's effect whose factor is NaN everywhere leaves the screen no finite density: the
    error names the effect beside the model, not only the model."""
    import dataclasses

    import jax.numpy as jnp

    from quadshank import Effect, FitSettings, Param, build_model, fit, register_effect, simulate_cohort

    @register_effect
    @dataclasses.dataclass(frozen=True)
    class NotANumber(Effect):
        kind = "gain"
        name = "test_not_a_number"
        params = (Param("c0", "1", prior=("normal", 0.0, 1.0)),)
        c0: float = 0.0

        def factor(self, ctx):
            return jnp.nan * (1.0 + self.c0 * ctx.angle)

    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.2, seed=1, trials=(1,))
    with pytest.raises(FloatingPointError, match=r"TN-left: the screen of model3s\+test_not_a_number found no finite "
                                                 r"posterior density .*or an effect \(test_not_a_number\) returns"):
        fit(cohort, build_model("model3s", ["test_not_a_number"]), FitSettings(chains=1, warmup=10, draws=10),
            progress=False)
