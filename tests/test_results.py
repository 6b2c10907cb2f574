"""Typed results: each command's summary.json is the JSON form of a dataclass with a schema version."""

from __future__ import annotations

import dataclasses
import json

import pytest

from pathlib import Path

from quadshank.commands import Check, Demo, PlanPrediction, Report, Reproduction
from quadshank.common import SCHEMA_VERSION, Result, SchemaError
from quadshank.evaluation import Evaluation, PosteriorEvaluation
from quadshank.inference import FitResult, Identification, load_identification
from quadshank.loop import Diagnosis, Discovery

RESULTS = [FitResult, PosteriorEvaluation, Diagnosis, Discovery, Identification, Evaluation, Reproduction, Report, Demo,
           PlanPrediction, Check]
SCHEMA_DOC = Path(__file__).resolve().parents[1] / "docs" / "results-schema.md"


def _fit(**kw) -> FitResult:
    base = dict(model="model1", effects=["zero_order"], trials=[1], legs={"TN-left": {"delay_posterior": [1.0]}},
                diagnostics={"ok": False}, banner="FIT FAILED ITS CHECKS: one chain", settings={"chains": 1},
                chain_method="vectorized", sampling_period_s=0.01, interval=[0.05, 0.95], code={"version": "x"})
    return FitResult(**{**base, **kw})


def test_a_result_reads_back_as_it_was_written(tmp_path):
    fit = _fit(data="somewhere", sampling_seconds=1.5)
    fit.write(tmp_path)
    doc = json.loads((tmp_path / "summary.json").read_text())
    assert doc["schema"] == "quadshank/fit" and doc["schema_version"] == SCHEMA_VERSION
    assert "screen_restarted" not in doc  # an optional part the run did not make is left out
    assert doc["banner"] == fit.banner and "delay_angle_population" not in doc
    assert FitResult.read(tmp_path) == fit
    assert not FitResult.read(tmp_path).ok


def test_a_number_that_is_not_finite_is_written_as_null(tmp_path):
    """JSON has no NaN or infinity: a strict reader (JavaScript, R's jsonlite) refuses Python's
    ``NaN``.  R-hat of one chain, an unstable model's J and the like are written as null, in
    plain floats, numpy scalars and arrays alike, and the summary reads back."""
    import math

    import numpy as np

    def strict(text):
        return json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in strict JSON"))

    diagnostics = {"ok": False, "rhat_max": float("nan"), "ess_bulk_min": np.float64(5.0),
                   "worst": np.array([1.0, np.inf, -np.inf]), "bfmi": np.float32("nan"), "chains": 1}
    _fit(diagnostics=diagnostics).write(tmp_path)
    doc = strict((tmp_path / "summary.json").read_text())
    assert doc["diagnostics"] == {"ok": False, "rhat_max": None, "ess_bulk_min": 5.0, "worst": [1.0, None, None],
                                  "bfmi": None, "chains": 1}
    back = FitResult.read(tmp_path)
    assert back.diagnostics["rhat_max"] is None and math.isclose(back.diagnostics["ess_bulk_min"], 5.0)


def test_a_required_field_stays_when_it_is_none(tmp_path):
    _fit(banner=None, diagnostics={"ok": True}).write(tmp_path)
    assert json.loads((tmp_path / "summary.json").read_text())["banner"] is None
    assert FitResult.read(tmp_path).ok


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"schema": "quadshank/diagnosis"}, "not a fit summary"),
        ({"schema_version": SCHEMA_VERSION + 1}, "schema version"),
        ({"schema": None}, "without a schema"),
    ],
)
def test_a_summary_of_another_kind_or_version_is_refused_naming_the_file(tmp_path, change, message):
    doc = {**_fit().to_json(), **change}
    if change.get("schema", "") is None:
        del doc["schema"]
    (tmp_path / "summary.json").write_text(json.dumps(doc))
    with pytest.raises(SchemaError, match=message) as err:
        FitResult.read(tmp_path)
    assert str(tmp_path / "summary.json") in str(err.value)


def test_a_missing_field_is_named(tmp_path):
    doc = _fit().to_json()
    del doc["legs"]
    with pytest.raises(SchemaError, match="lacks legs"):
        FitResult.from_json(doc, "x/summary.json")


def test_live_objects_stay_out_of_the_json():
    d = Diagnosis(model="m", legs=["a"], elpd={}, J_ms={}, ranking=[], verdict="none", bar={}, sentence="s",
                  trials=[1], screened=object())
    doc = d.to_json()
    assert "screened" not in doc and doc["schema"] == "quadshank/diagnosis"
    back = Diagnosis.from_json(json.loads(json.dumps(doc)))
    assert back.screened is None and dataclasses.replace(back, screened=d.screened) == d


@pytest.mark.parametrize("kind", RESULTS)
def test_every_result_names_its_kind_and_is_documented(kind):
    assert kind.schema().startswith("quadshank/") and kind.KIND
    assert dataclasses.is_dataclass(kind)
    doc = SCHEMA_DOC.read_text()
    assert f"## `{kind.schema()}`" in doc  # a section of its own
    section = doc.split(f"## `{kind.schema()}`")[1].split("\n## ")[0]
    for field in dataclasses.fields(kind):
        if field.metadata.get("json", True):
            assert f"`{field.name}`" in section, f"{kind.__name__}.{field.name} is not described"


def test_every_result_type_is_listed():
    def subclasses(cls):
        return {c for s in cls.__subclasses__() for c in (s, *subclasses(s))}

    assert subclasses(Result) == set(RESULTS)  # a new result type is added to the documentation and this list


def test_an_identification_refuses_data_of_another_period(tmp_path):
    legs = {"A": {"passive": {"damping": 1.0, "gravity": 1900.0, "k1": 10.0, "k2": 0.05}, "delay_samples": 4,
                  "model1": {"gain": 1.0}, "model2": {"a1": 1.5, "a2": -0.6, "b1": 0.1, "b2": 0.1},
                  "model3": {"gain": 1.0, "gamma_angle": 0.0, "gamma_velocity": 0.0}}}
    Identification(trial=1, sampling_period_s=0.005, legs=legs).write(tmp_path)
    models = load_identification(tmp_path, 0.005)
    assert models["A"]["model2"].sampling_period_s == pytest.approx(0.005)
    with pytest.raises(ValueError, match="5 ms.*10 ms"):
        load_identification(tmp_path, 0.01)
