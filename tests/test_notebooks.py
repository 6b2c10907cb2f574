"""The notebooks: each source executes at the small size, says what it should, and its committed
``.ipynb`` is the same notebook with outputs.

The small size (``QUADSHANK_NOTEBOOK_SMALL=1``) shortens data and chains; each notebook's
last cell prints a JSON line of its results, checked here.
"""

import importlib.util
import math
import warnings
from pathlib import Path

import pytest

jupytext = pytest.importorskip("jupytext")
pytest.importorskip("nbclient")

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
_spec = importlib.util.spec_from_file_location("nb_execute", NOTEBOOKS / "execute.py")
nb_execute = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(nb_execute)

NAMES = [p.stem for p in nb_execute.sources()]


def test_the_four_notebooks_of_the_issue_are_there():
    assert NAMES == ["a_reproduce_paper", "b_posterior_analysis", "c_modelling_loop", "d_write_an_effect"]


def _code(nb) -> list[str]:
    return [c.source.strip() for c in nb.cells if c.cell_type == "code"]


@pytest.mark.parametrize("name", NAMES)
def test_the_committed_notebook_is_its_source_executed(name):
    """Same code cells as the source, every one run in order, outputs kept and no error among them."""
    src = jupytext.read(NOTEBOOKS / f"{name}.py")
    ipynb = NOTEBOOKS / f"{name}.ipynb"
    assert ipynb.exists(), f"{ipynb.name} missing: run `make notebooks`"
    nb = jupytext.read(ipynb)
    assert _code(nb) == _code(src), f"{ipynb.name} is out of date with {name}.py: run `make notebooks`"
    cells = [c for c in nb.cells if c.cell_type == "code"]
    counts = [c.get("execution_count") for c in cells]
    assert counts == list(range(1, len(cells) + 1)), f"{ipynb.name}: not executed top to bottom ({counts})"
    outputs = [o for c in cells for o in c.get("outputs", [])]
    assert not [o for o in outputs if o.get("output_type") == "error"]
    assert sum("image/png" in o.get("data", {}) for o in outputs) >= 2, f"{ipynb.name}: its figures are missing"
    result = nb_execute.last_json(nb)
    assert result["notebook"] == name and result["small"] is False


def _run(name, tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        nb = nb_execute.execute(NOTEBOOKS / f"{name}.py", small=True, cwd=tmp_path, timeout=900)
    result = nb_execute.last_json(nb)
    assert result["notebook"] == name and result["small"] is True
    assert (tmp_path / "_work" / name).is_dir(), "the notebook wrote outside its work folder"
    return result


def test_a_reproduce_paper_runs(tmp_path):
    r = _run("a_reproduce_paper", tmp_path)
    J = r["J_trial2_1000ms"]
    # model 3 predicts 1 s ahead better than models 1 and 2 even at the small size
    assert J["model3"] < min(J["model1"], J["model2"]), J
    assert r["paper_J_trial2_1000ms"] == {"model1": 12.4, "model2": 12.5, "model3": 7.5}


def test_b_posterior_analysis_runs(tmp_path):
    r = _run("b_posterior_analysis", tmp_path)
    assert set(r["delay_mode"]) == {"TN-left", "TN-right", "JM-left"}
    assert all(3 <= d <= 5 for d in r["delay_mode"].values()), r["delay_mode"]  # true delays 4.3 and 4.7
    assert all(0.0 <= p <= 1.0 for p in r["change_probability"].values())
    J = r["J_trial1_1000ms"]
    assert 0 < J["lo"] <= J["median"] <= J["hi"] and math.isfinite(J["hi"])


def test_c_modelling_loop_runs(tmp_path):
    r = _run("c_modelling_loop", tmp_path)
    assert r["verdict"] == "potentiation", r
    assert r["J_1000ms_after"] < r["J_1000ms_before"], r


def test_d_write_an_effect_runs(tmp_path):
    r = _run("d_write_an_effect", tmp_path)
    assert r["effect"] == "angle_velocity_coupling"
    rec = r["recovered"]
    # the screen finds c within a third of the prior's s.d. (0.3), and the data narrow the
    # prior's 90 % width (about 1.0) at least five-fold
    assert abs(rec["mode"] - r["truth"]) < 0.1, rec
    assert rec["hi"] - rec["lo"] < 0.2, rec
    assert r["verdict"] == "angle_velocity_coupling"
