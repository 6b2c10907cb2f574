"""Drawing to a target effective sample size: blocks that continue the chains, the stopping rule."""

import json

import numpy as np
import pytest

from quadshank.cli import main
from quadshank.data._simulate import simulate_cohort
from quadshank.inference import _nuts
from quadshank.inference._nuts import BlockDraws, FitSettings, convergence_status, fit
from quadshank.inference._priors import build_model


def _ar1(rng, phi, shape):
    x = np.zeros(shape)
    x[:, 0] = rng.normal(size=shape[0]) / np.sqrt(1 - phi**2)
    for t in range(1, shape[1]):
        x[:, t] = phi * x[:, t - 1] + rng.normal(size=shape[0])
    return x


def test_convergence_status_passes_independent_chains_and_names_the_variable_that_lags():
    rng = np.random.default_rng(0)
    iid = {"a": rng.normal(size=(4, 500)), "b": rng.normal(size=(4, 500, 3))}
    ok = convergence_status(iid, needed=400)
    assert ok["met"] and ok["ess_bulk_min"] > 1000 and ok["rhat_max"] < 1.01 and ok["draws_per_chain"] == 500

    slow = {**iid, "c": _ar1(rng, 0.98, (4, 500))}  # ESS about 4·500·(1−φ)/(1+φ) ≈ 20
    st = convergence_status(slow, needed=400)
    assert not st["met"] and st["ess_bulk_min"] < 100 and st["lagging"] == "c"

    apart = {**iid, "d": rng.normal(size=(4, 500)) + np.array([0.0, 0.0, 0.0, 1.0])[:, None]}  # one chain elsewhere
    st = convergence_status(apart, needed=100)
    assert not st["met"] and st["rhat_max"] > 1.05 and st["lagging"] == "d"


def test_the_lagging_variable_is_named_with_its_leg_or_subject(monkeypatch):
    """The block's check names the entry that lags, not only its variable: a leg's parameter by
    the leg, a subject's value by the subject; a scalar by nothing more."""
    from types import SimpleNamespace

    rng = np.random.default_rng(3)
    data = SimpleNamespace(legs=("A-left", "B-left", "C-right"), subjects=("A", "B", "C"), leg_subject=np.arange(3))
    monkeypatch.setattr(_nuts, "hyper_draws", lambda *args: {})  # the draws below stand for them
    iid = {"gain": rng.normal(size=(4, 500, 3)), "gain_subject": rng.normal(size=(4, 500, 3)), "nu_pop": rng.normal(size=(4, 500))}

    def lagging(name, entry=None):
        draws = {**iid, name: iid[name].copy()}
        slow = _ar1(rng, 0.98, (4, 500))
        if entry is None:
            draws[name] = slow
        else:
            draws[name][:, :, entry] = slow
        st = _nuts.target_status(draws, None, data, FitSettings(target_ess=400))
        return st["lagging"], st.get("lagging_at")

    assert lagging("gain", 2) == ("gain", "C-right")
    assert lagging("gain_subject", 1) == ("gain_subject", "B")
    assert lagging("nu_pop") == ("nu_pop", None)


def test_blocks_continue_the_chains_exactly_as_one_longer_run(monkeypatch):
    # equal twitches: a short, smooth posterior whose chains draw no divergence (the runs, not the data, are tested)
    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.3, seed=2, trials=(1,), twitch_cv=0.0)
    model = build_model("model1")
    # in double precision: at mixed precision the stepping loop of the blocks and the whole loop of one
    # run round their single-precision terms differently, and the chains part within a few draws
    one, _ = fit(cohort, model, FitSettings(chains=2, warmup=60, draws=30, seed=5, start="prior", precision="double"),
                 progress=False)

    checks = []

    def met_at_third(samples, *args):  # the stopping rule is tested above; here, the blocks themselves
        checks.append(samples["gain_s_leg"].shape[1])
        return {"met": len(checks) == 3, "draws_per_chain": checks[-1], "ess_needed": 200, "rhat_max": 1.0,
                "ess_bulk_min": 0.0, "ess_tail_min": 0.0, "lagging": "gain"}

    monkeypatch.setattr(_nuts, "target_status", met_at_third)
    blocks, _ = fit(cohort, model, FitSettings(chains=2, warmup=60, draws=10, seed=5, start="prior", target_ess=200,
                                               precision="double"),
                    progress=False)
    assert isinstance(blocks, BlockDraws) and checks == [10, 20, 30]
    assert blocks.target["blocks"] == 3 and blocks.target["stopped"] == "target met"
    a, b = one.get_samples(group_by_chain=True), blocks.get_samples(group_by_chain=True)
    assert b["gain"].shape[:2] == (2, 30)
    np.testing.assert_allclose(b["gain"], a["gain"], rtol=1e-4)  # rounding only: two chains differ by 1e-2
    np.testing.assert_array_equal(blocks.get_extra_fields()["num_steps"], np.asarray(one.get_extra_fields()["num_steps"]))
    assert blocks.get_samples()["gain"].shape[0] == 60  # chains pooled, as numpyro's get_samples()


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("target")
    assert main(["-q", "simulate", "--out", str(root / "data"), "--minutes", "0.3", "--legs", "TN-left",
                 "--trials", "1"]) == 0
    return root


def test_a_fit_to_a_target_ess_stops_at_it_and_says_so(data, capsys):
    out = data / "met"
    # model 2 from the screen's start and metric mixes well: the target is met in a few blocks; a
    # target below what the checks ask (100 per chain) is drawn to theirs, and the command says so
    code = main(["fit", str(data / "data"), "--model", "model2", "--chains", "2",
                 "--warmup", "100", "--draws", "100", "--target-ess", "150", "--out", str(out)])
    summary = json.loads((out / "summary.json").read_text())
    t, diag = summary["target"], summary["diagnostics"]
    assert t["stopped"] == "target met" and t["met"], t
    assert t["draws_per_chain"] == 100 * t["blocks"] == diag["draws"]
    assert min(diag["ess_bulk_min"], diag["ess_tail_min"]) >= 200 and diag["rhat_max"] < 1.01
    assert code == (0 if diag["ok"] else 3)
    assert "target ESS 150 (drawn to 200, what the fit's checks ask): target met" in capsys.readouterr().err


def test_a_fit_that_runs_out_of_time_says_the_target_was_not_met(data, capsys):
    out = data / "late"
    code = main(["fit", str(data / "data"), "--model", "model1", "--chains", "2", "--start", "prior",
                 "--warmup", "20", "--draws", "10", "--target-ess", "100000", "--time-limit", "1", "--target-accept", "0.95",
                 "--out", str(out)])
    summary = json.loads((out / "summary.json").read_text())
    assert summary["settings"]["target_accept"] == 0.95  # the sampler's, as the user asked
    t = summary["target"]
    assert not t["met"] and t["blocks"] == 1 and "time limit of 1 s" in t["stopped"]
    assert code == 3 and not summary["diagnostics"]["ok"]
    assert "target ESS 100000: time limit of 1 s" in capsys.readouterr().err
