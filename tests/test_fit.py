"""The hierarchical fit end to end, at a size that keeps the suite fast.

These runs are far too short to pass the convergence checks; what they test
is the machinery: the fit folder, its reload, the summary, the loud failure
and reproducibility.  Recovery and coverage at full size are benchmarks.
"""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quadshank.cli import main
from quadshank.inference._nuts import FitSettings, fit
from quadshank.inference._priors import build_model
from quadshank.inference._fitio import FitFolderError, load_fit, posterior_models
from quadshank.data._interchange import load_cohort
from quadshank.model._likelihood import N_DELAYS
from quadshank.common._provenance import code_provenance
from quadshank.data._simulate import simulate_cohort

TINY = ["--chains", "2", "--warmup", "40", "--draws", "30"]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("fit")
    assert main(["-q", "simulate", "--out", str(root / "data"), "--minutes", "0.5",
                 "--legs", "TN-left,TN-right,JM-left", "--trials", "1,2"]) == 0
    return root


@pytest.fixture(scope="module")
def fitted(data_dir):
    out = data_dir / "fit3"
    code = main(["-q", "fit", str(data_dir / "data"), "--model", "model3", *TINY, "--max-tree-depth", "6", "--out", str(out)])
    return out, code


def test_fit_folder_holds_a_complete_reloadable_fit(fitted):
    out, _ = fitted
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["legs"]) == {"TN-left", "TN-right", "JM-left"}
    for leg, s in summary["legs"].items():
        assert len(s["delay_posterior"]) == N_DELAYS
        assert sum(s["delay_posterior"]) == pytest.approx(1.0, abs=1e-4)
        assert len(s["delay_evidence"]) == N_DELAYS and sum(s["delay_evidence"]) == pytest.approx(1.0)
        for name in ("gain", "gamma_angle", "gamma_velocity", "damping", "gravity", "k1", "k2", "sigma", "nu"):
            q = s["params"][name]
            assert q["lo"] <= q["median"] <= q["hi"], (leg, name)
            assert q["units"]
    for key in ("rhat_max", "ess_bulk_min", "divergences", "ess_tail_min", "bfmi_min", "delay_splits", "delay_missed"):
        assert key in summary["diagnostics"]
    assert summary["delay_evidence_seconds"] > 0
    assert summary["code"] == code_provenance()  # which code made the fit (recovery reuses only its own)
    idata, model, desc = load_fit(out)
    np.testing.assert_allclose(idata.constant_data["delay_evidence"].sel(leg="JM-left"),
                               summary["legs"]["JM-left"]["delay_evidence"])
    assert desc["model"] == "model3" and desc["trials"] == [1]
    assert desc["settings"]["max_tree_depth"] == 6 and desc["settings"]["start"] == "screen"
    assert np.asarray(idata.sample_stats["n_steps"]).max() <= 2**6 - 1
    for group in ("posterior", "log_likelihood", "observed_data", "constant_data", "sample_stats"):
        assert hasattr(idata, group), group
    ll = idata.log_likelihood["acceleration_segment"]
    assert ll.sizes["leg"] == 3 and ll.sizes["segment"] == 30  # 30 s in 1-s segments
    assert np.isfinite(ll.values).all()
    m, delays = posterior_models(idata, model, "JM-left", n_draws=10)
    assert np.shape(m.params()["gain"]) == (10,)
    assert delays.shape == (10,) and ((0 <= delays) & (delays < N_DELAYS)).all()


def test_a_fit_that_fails_its_checks_says_so(fitted, capsys):
    out, code = fitted
    assert code == 3  # 30 draws cannot reach the ESS threshold
    summary = json.loads((out / "summary.json").read_text())
    assert summary["diagnostics"]["ok"] is False
    assert summary["banner"].startswith("FIT FAILED ITS CHECKS")
    assert summary["diagnostics"]["advice"]


def test_interrupted_fit_leaves_no_complete_looking_folder(data_dir, monkeypatch):
    import quadshank.commands.fit as fit_command

    out = data_dir / "interrupted"
    out.mkdir()
    (out / "summary.json").write_text("{}")  # a previous fit's summary

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(fit_command, "run_nuts", boom)  # interrupted while sampling, where Ctrl-C is most likely
    with pytest.raises(KeyboardInterrupt):
        fit_command.run_fit(
            load_cohort(data_dir / "data"),
            out, "model1", settings=FitSettings(chains=1, warmup=5, draws=5),
        )
    assert not (out / "summary.json").exists()
    with pytest.raises(FitFolderError, match="no complete fit"):
        load_fit(out)


def test_same_seed_same_posterior():
    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.3, seed=2, trials=(1,))
    settings = FitSettings(chains=1, warmup=20, draws=10, seed=5)
    a, _ = fit(cohort, build_model("model1"), settings, progress=False)
    b, _ = fit(cohort, build_model("model1"), settings, progress=False)
    np.testing.assert_array_equal(np.asarray(a.get_samples()["gain"]), np.asarray(b.get_samples()["gain"]))


def test_a_ctrl_c_that_jax_swallows_still_stops_the_fit(data_dir, monkeypatch, capsys):
    """A Ctrl-C while XLA samples reaches Python inside a callback of JAX's, which drops the
    exception: the command line's handler records it; the draws, complete when sampling returns,
    are saved, and the command says it was interrupted and exits 130 (it had exited 0 without a
    word); a fit to a target ESS draws no further block."""
    import signal

    from numpyro.infer import MCMC

    run = MCMC.run

    def run_and_swallow_a_ctrl_c(self, *args, **kwargs):
        try:
            signal.raise_signal(signal.SIGINT)  # the handler runs here, as in JAX's garbage-collection hook ...
        except KeyboardInterrupt:
            pass  # ... which reports the exception as ignored and goes on
        return run(self, *args, **kwargs)

    monkeypatch.setattr(MCMC, "run", run_and_swallow_a_ctrl_c)
    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal (a background job ignores it)
    try:
        out = data_dir / "swallowed"
        capsys.readouterr()
        assert main(["-q", "fit", str(data_dir / "data"), "--model", "model1", "--legs", "TN-left", "--chains", "1",
                     "--warmup", "5", "--draws", "5", "--out", str(out)]) == 130
        assert "quadshank: interrupted; the step running then was finished" in capsys.readouterr().err
        assert load_fit(out)[0].posterior.sizes["draw"] == 5  # the complete draws, saved with their summary
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handler before is back
        target = data_dir / "swallowed-target"
        assert main(["-q", "fit", str(data_dir / "data"), "--model", "model1", "--legs", "TN-left", "--chains", "1",
                     "--target-ess", "100000", "--warmup", "5", "--draws", "5", "--out", str(target)]) == 130
        s = json.loads((target / "summary.json").read_text())
        assert s["target"]["stopped"] == "interrupted: no further block was drawn" and s["target"]["blocks"] == 1
    finally:
        signal.signal(signal.SIGINT, before)


def test_unknown_effect_and_missing_trial_are_plain_errors(data_dir, capsys):
    args = ["fit", str(data_dir / "data"), *TINY, "--out", str(data_dir / "bad")]
    assert main([*args, "--add-effect", "no_such_effect"]) == 2
    assert "unknown effect 'no_such_effect'" in capsys.readouterr().err
    assert main([*args, "--trials", "7"]) == 2
    err = capsys.readouterr().err
    assert "has no trial 7" in err and "fit:" not in err  # refused before the first progress line
    assert not (data_dir / "bad").exists()  # and before anything is written


def _spread_mixture_by_hand(s, leg_subject):
    """Σ_g w_g N(s; 0, 11ᵀ + r_s² S + r_l² I) over SPREAD_GRID, with the HalfNormal(1) mass of each
    cell found by quadrature of its density, and the normal density from scipy."""
    from scipy import integrate, stats

    from quadshank.inference._priors import SPREAD_GRID

    r = SPREAD_GRID
    edges = np.concatenate([[0.0], np.sqrt(r[1:] * r[:-1]), [np.inf]])
    mass = np.array([integrate.quad(stats.halfnorm.pdf, a, b)[0] for a, b in zip(edges[:-1], edges[1:])])
    same = (leg_subject[:, None] == leg_subject[None, :]).astype(float)
    terms = np.zeros((r.size, r.size))
    for i, rs in enumerate(r):
        for j, rl in enumerate(r):
            cov = 1.0 + rs**2 * same + rl**2 * np.eye(leg_subject.size)
            terms[i, j] = mass[i] * mass[j] * stats.multivariate_normal(np.zeros(leg_subject.size), cov).pdf(s)
    return terms


def test_spread_mixture_is_the_discretised_halfnormal_prior_summed_out():
    from quadshank.inference._priors import SpreadMixture

    leg_subject = np.array([0, 0, 1, 1, 2])
    prior = SpreadMixture(leg_subject)
    for s in ([0.1, 0.12, -0.3, -0.2, 0.5], [0.0] * 5, [2.0, -1.5, 0.3, 0.2, -0.9]):
        s = np.array(s)
        want = np.log(_spread_mixture_by_hand(s, leg_subject).sum())
        assert float(prior.log_prob(jnp.asarray(s, jnp.float32))) == pytest.approx(want, rel=1e-4, abs=1e-4)
    # its draws have the mixture's covariance: E[s sᵀ] = Σ_g w_g C_g
    draws = np.asarray(prior.sample(jax.random.PRNGKey(0), (40000,)), np.float64)
    from quadshank.inference._priors import spread_grid

    log_w, r_s, r_l, *_ = spread_grid(tuple(leg_subject))
    same = (leg_subject[:, None] == leg_subject[None, :]).astype(float)
    want = np.einsum("g,gij->ij", np.exp(log_w), 1.0 + r_s[:, None, None] ** 2 * same + r_l[:, None, None] ** 2 * np.eye(5))
    np.testing.assert_allclose(draws.T @ draws / draws.shape[0], want, rtol=0.06, atol=0.04)


def test_spreads_are_drawn_from_their_conditional_on_the_grid():
    """spread_draws against P(r_s, r_l | s) computed by hand, for legs that agree and legs that do not."""
    from quadshank.inference._priors import SPREAD_GRID, model_params
    from quadshank.inference._draws import spread_draws

    model = build_model("model1")
    leg_subject = np.array([0, 0, 1, 1, 2])
    n = 30000
    for s in ([0.30, 0.31, 0.29, 0.30, 0.30], [0.3, -0.9, 1.4, 0.1, -1.2]):
        s = np.array(s)
        terms = _spread_mixture_by_hand(s, leg_subject)
        p_l = terms.sum(axis=0) / terms.sum()  # P(r_l | s)
        p_s = terms.sum(axis=1) / terms.sum()
        out = spread_draws(model, {"gain_s_leg": np.broadcast_to(s, (1, n, 5))}, leg_subject, seed=0)
        got_l = np.array([np.mean(out["gain_sd_leg_rel"] == r) for r in SPREAD_GRID])
        got_s = np.array([np.mean(out["gain_sd_subject_rel"] == r) for r in SPREAD_GRID])
        np.testing.assert_allclose(got_l, p_l, atol=0.012)
        np.testing.assert_allclose(got_s, p_s, atol=0.012)
    # legs that agree put the leg spread at the grid's floor, legs that differ well above it
    agree = spread_draws(model, {"gain_s_leg": np.full((1, 2000, 5), 0.3)}, leg_subject, seed=1)["gain_sd_leg_rel"]
    differ = spread_draws(model, {"gain_s_leg": np.broadcast_to([0.3, -0.9, 1.4, 0.1, -1.2], (1, 2000, 5))}, leg_subject, seed=1)
    assert np.median(agree) == SPREAD_GRID[0] and np.median(differ["gain_sd_leg_rel"]) > 0.5
    gain = next(p for p in model_params(model) if p.name == "gain")
    np.testing.assert_allclose(differ["gain_sd_leg"], differ["gain_sd_leg_rel"] * gain.prior[2])


def test_population_and_subject_draws_follow_their_gaussian_conditional():
    """hyper_draws against Gaussian conditioning of the joint (μ, x_legs), computed another way."""
    from quadshank.inference._draws import hyper_draws
    from quadshank.inference._priors import model_params

    model = build_model("model1")
    gain = next(p for p in model_params(model) if p.name == "gain")
    leg_subject = np.array([0, 0, 1])  # two legs of subject 0, one of subject 1
    s_leg = np.array([0.3, 0.5, -0.4])
    r_s, r_l = 0.7, 0.2
    n = 40000
    samples = {
        "gain_s_leg": np.broadcast_to(s_leg, (1, n, 3)),
        "gain_sd_subject_rel": np.full((1, n), r_s),
        "gain_sd_leg_rel": np.full((1, n), r_l),
    }
    out = hyper_draws(model, samples, leg_subject, 2, seed=0)
    _, loc, scale = gain.prior
    mu_std = (np.log(out["gain_mu"][0]) - loc) / scale
    same = (leg_subject[:, None] == leg_subject[None, :]).astype(float)
    cov_x = 1.0 + r_s**2 * same + r_l**2 * np.eye(3)
    w = np.linalg.solve(cov_x, np.ones(3))
    assert mu_std.mean() == pytest.approx(w @ s_leg, abs=0.01)
    assert mu_std.var() == pytest.approx(1.0 - w.sum(), rel=0.03)
    # subject 1 (one leg): joint of (μ + b_1, x) conditioned on x
    subj = (np.log(out["gain_subject"][0, :, 1]) - loc) / scale
    c = 1.0 + r_s**2 * (leg_subject == 1)  # Cov(μ + b_1, x_l)
    assert subj.mean() == pytest.approx(np.linalg.solve(cov_x, c) @ s_leg, abs=0.01)
    assert subj.var() == pytest.approx(1.0 + r_s**2 - c @ np.linalg.solve(cov_x, c), rel=0.03)


def test_delay_prior_from_another_fit(fitted, data_dir):
    """A model-1 fit cannot see the delay, so its P(d | data) is exactly the prior it was given."""
    from quadshank.inference._priors import DELAY_PRIOR_FLOOR, delay_prior_from

    source, _ = fitted
    src = json.loads((source / "summary.json").read_text())
    out = data_dir / "fit1_delay"
    assert main(["-q", "fit", str(data_dir / "data"), "--model", "model1", *TINY,
                 "--delay-from", str(source), "--out", str(out)]) in (0, 3)
    got = json.loads((out / "summary.json").read_text())
    for leg in src["legs"]:
        prior = (1 - DELAY_PRIOR_FLOOR) * np.asarray(src["legs"][leg]["delay_posterior"]) + DELAY_PRIOR_FLOOR / N_DELAYS
        np.testing.assert_allclose(got["legs"][leg]["delay_posterior"], prior / prior.sum(), rtol=2e-3, atol=1e-5)  # float32
        # the per-delay evidence of a model blind to d is the fit's delay prior, not the uniform one
        np.testing.assert_allclose(got["legs"][leg]["delay_evidence"], prior / prior.sum(), rtol=2e-3, atol=1e-5)
    assert got["diagnostics"]["delay_missed"] == {}
    _, _, desc = load_fit(out)
    assert desc["delay_prior"]["source"] == str(source)
    with pytest.raises(KeyError, match="OT-left"):
        delay_prior_from(src["legs"], ["OT-left"])
    assert main(["-q", "fit", str(data_dir / "data"), *TINY, "--delay-from", str(data_dir / "nowhere"),
                 "--out", str(data_dir / "bad2")]) == 2


def test_angle_delay_fit_reports_the_delay_angle_curve(tmp_path):
    from quadshank.inference._fitio import fit_summary, to_inference_data
    from quadshank.data._paper import MAX_DELAY

    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.3, seed=4, effects=["angle_delay"], trials=(1,))
    model = build_model("model1", ["angle_delay"])
    settings = FitSettings(chains=1, warmup=10, draws=10, seed=0)
    mcmc, data = fit(cohort, model, settings, progress=False)
    idata = to_inference_data(mcmc, model, data, settings)
    leg = fit_summary(idata)["legs"]["TN-left"]["delay_angle"]
    assert 0.0 <= leg["change_probability"] <= 1.0
    assert sum(leg["shift_posterior"]) == pytest.approx(1.0, abs=1e-3)  # float32 log-probabilities
    lo, med, hi = (np.asarray(leg[k]) for k in ("lo", "median", "hi"))
    assert len(med) == len(leg["angle_deg"])
    assert np.all(lo <= med) and np.all(med <= hi) and np.all(lo >= 0) and np.all(hi <= MAX_DELAY)
    m, delays = posterior_models(idata, model, "TN-left", n_draws=5)
    shifts = np.asarray(m.delay_effect.shift)
    assert shifts.shape == (5,) and np.all(shifts <= delays)


def test_summed_out_threshold_is_drawn_with_the_delay_from_their_joint_conditional():
    """sample_step_states at a fixed θ against P(d, shift, state | θ, y) computed from the
    likelihood's states: the shift's and the threshold's distribution (its CDF at pulse angles
    and between them, where the truncated prior shapes it), and every drawn threshold splitting
    the pulses as its state does."""
    from scipy import stats

    from quadshank.inference._priors import _with_discrete_axes, log_shift_prior, step_param
    from quadshank.inference._draws import sample_step_states
    from quadshank.model._likelihood import leg_loglik_by_threshold, prepare, step_log_mass

    cohort, truth = simulate_cohort(legs=["JM-left"], minutes=0.3, seed=4, effects=["angle_delay"], trials=(1,))
    model = build_model("model3", ["angle_delay"])
    data = prepare(cohort, model)
    step = step_param(model, data)
    assert step.name == "threshold"
    tr = truth["legs"]["JM-left"]
    values = {**tr["passive"], "gain": tr["active"]["G2"], "gamma_angle": tr["active"]["gamma_angle"],
              "gamma_velocity": tr["active"]["gamma_velocity"]}  # fmt: skip
    n = 3000
    post = {p: np.full((n, 1), values[p], np.float32) for p in ("gain", "gamma_angle", "gamma_velocity", "damping", "gravity", "k1", "k2")}
    post |= {"sigma": np.full((n, 1), 900.0, np.float32), "nu": np.full((n, 1), 4.0, np.float32)}  # noisy: spread states
    d, shift, threshold = sample_step_states(model, data, post, None, seed=3)
    # the exact conditional
    one = _with_discrete_axes(model.with_params({k: v[0, 0] for k, v in post.items() if k not in ("sigma", "nu")}, threshold=0.0), ())
    x = {k: v[0] for k, v in data.leg_arrays().items()}
    ll = np.asarray(leg_loglik_by_threshold(one, {"sigma": 900.0, "nu": 4.0}, x, data.response_length, data.max_shift), np.float64)
    logp = ll + np.asarray(step_log_mass(one, x, 0.0, 25.0))[None, None] + log_shift_prior(data.max_shift)[:, :, None]
    p = np.exp(logp - logp.max())
    p /= p.sum()
    p_shift = p.sum(axis=(0, 2))
    assert 0.1 < p_shift[0] < 0.9  # the test needs a spread
    np.testing.assert_allclose(np.bincount(shift[:, 0], minlength=3) / n, p_shift, atol=0.03)
    np.testing.assert_allclose(np.bincount(d[:, 0], minlength=11) / n, p.sum(axis=(1, 2)), atol=0.03)
    angles = np.sort(data.angle[0][data.pulse_sample[0][data.pulse_u[0] > 0]].astype(np.float64))
    edges = np.concatenate([[-np.inf], angles, [np.inf]])
    p_state = p.sum(axis=(0, 1))[: angles.size + 1]
    for a in (angles[3], 0.5 * (angles[5] + angles[6]), -20.0, angles[-4]):
        # P(threshold < a) = Σ_j P(j) P(threshold < a | j), the prior truncated to state j's interval
        lo, hi = stats.norm.cdf(edges[:-1], 0, 25), stats.norm.cdf(edges[1:], 0, 25)
        within = np.clip((stats.norm.cdf(a, 0, 25) - lo) / np.maximum(hi - lo, 1e-300), 0.0, 1.0)
        assert np.mean(threshold[:, 0] < a) == pytest.approx(p_state @ within, abs=0.03), a
    # a drawn threshold lies in an interval between pulse angles (never on one)
    assert not np.isin(threshold[:, 0], angles.astype(np.float32)).any()


def test_chains_start_at_the_classical_estimate_of_the_leading_delay_mode():
    from functools import partial

    import jax

    from quadshank.inference._starts import INIT_JITTER, _init_near, classical_start
    from quadshank.inference._priors import model_params
    from quadshank.model._likelihood import leg_loglik_by_delay, prepare
    from quadshank.evaluation._recovery import simulate_matching

    cohort, truth = simulate_matching("model2", legs=["TN-left", "JM-left"], minutes=1.0, seed=0)
    model = build_model("model2")
    data = prepare(cohort, model)
    start = classical_start(cohort, model, data, 1)
    assert set(start) == {"a_s_leg", "b_s_leg", "damping_s_leg", "gravity_s_leg", "k1_s_leg", "k2_s_leg"}
    # back to parameter values: the start lies in the true delay's mode of every leg
    x = data.leg_arrays()
    for i, leg in enumerate(data.legs):
        values = {}
        for p in model_params(model):
            loc, scale = np.asarray(p.prior[1]), np.asarray(p.prior[2])
            v = loc + scale * (start[f"{p.name}_s_leg"][..., i])
            values[p.name] = np.exp(v) if p.prior[0] == "lognormal" else v
        m = model.with_params({k: np.float32(v) for k, v in values.items()})
        xi = {k: v[i] for k, v in x.items()}
        ll = np.asarray(leg_loglik_by_delay(m, {"sigma": np.float32(40), "nu": np.float32(5)}, xi, data.response_length))
        assert int(np.argmax(ll[:, 0])) == truth["legs"][leg]["delay"], leg
        np.testing.assert_allclose(values["a"], truth["legs"][leg]["params"]["a"], atol=0.2)  # within a prior scale
    site = {"name": "a_s_leg", "type": "sample", "is_observed": False, "kwargs": {"rng_key": jax.random.PRNGKey(1)}}
    init = partial(_init_near, values=start, fallback=lambda s: 0.0)
    v1 = np.asarray(init(site))
    v2 = np.asarray(init({**site, "kwargs": {"rng_key": jax.random.PRNGKey(2)}}))
    assert 0 < np.abs(v1 - start["a_s_leg"]).max() < 5 * INIT_JITTER and not np.allclose(v1, v2)
    assert init({**site, "name": "sigma"}) == 0.0  # other sites: the fallback


def test_screen_start_puts_each_chain_at_a_laplace_draw_with_the_laplace_metric():
    """screen_start maps each leg's screen vector (z per parameter, log σ, log ν) onto numpyro's
    sites: chain c of leg i starts at the leg's c-th Laplace draw, and the metric's block of the
    leg is the Laplace covariance.  model3s has vector parameters (a, b), whose site is (C, L)."""
    from numpyro.infer.util import constrain_fn

    from quadshank.inference._nuts import fit_screen, screen_start
    from quadshank.inference._density import numpyro_model
    from quadshank.inference._priors import STIFFNESS_SITE, stiffness_jacobian, stiffness_params
    from quadshank.model._likelihood import prepare
    from quadshank.inference._screen import _values_np

    cohort, _ = simulate_cohort(legs=["TN-left", "JM-left"], minutes=0.3, seed=4, trials=(1,))
    model = build_model("model3s")
    settings = FitSettings(chains=3, seed=2)
    data = prepare(cohort, model)
    arrays = data.leg_arrays()

    def conditioned(arrays):
        return numpyro_model(model, data, arrays)

    scr = fit_screen(cohort, model, settings, legs=data.legs)
    init, imm = screen_start(model, data, settings, conditioned, arrays, scr)
    (names, metric), = imm.items()
    metric = np.asarray(metric, np.float64)
    assert list(names) == sorted(init) and np.allclose(metric, metric.T)
    assert np.all(np.linalg.eigvalsh(metric) > 0)
    for c in range(3):
        values = constrain_fn(conditioned, (arrays,), {}, {k: v[c] for k, v in init.items()}, return_deterministic=True)
        for i in range(2):
            want = _values_np(scr.specs, scr.draws[i, c])
            for name, v in want.items():
                np.testing.assert_allclose(np.asarray(values[name][i]), v, rtol=2e-5, atol=1e-6, err_msg=(c, name))
            np.testing.assert_allclose(float(values["sigma"][i]), np.exp(scr.draws[i, c, -2]), rtol=1e-5)
            np.testing.assert_allclose(float(values["nu"][i]), np.exp(scr.draws[i, c, -1]), rtol=1e-5)
    # the metric: a's second component of leg 1 against b's first of leg 0 (no coupling across
    # legs), and the same pair within leg 1 carries its Laplace covariance
    offsets = np.cumsum([0] + [int(np.size(init[k][0])) for k in names])
    at = dict(zip(names, offsets[:-1]))
    j_a1, j_b0 = 1, 2  # positions in a leg's screen vector: a (2 components), then b
    assert [s.name for s in scr.specs][:2] == ["a", "b"]
    a1_leg1, b0_leg1, b0_leg0 = at["a_s_leg"] + 1 * 2 + 1, at["b_s_leg"] + 0 * 2 + 1, at["b_s_leg"] + 0 * 2 + 0
    assert metric[a1_leg1, b0_leg1] == pytest.approx(scr.covariance[1, j_a1, j_b0], rel=1e-5)
    assert metric[a1_leg1, b0_leg0] == 0.0
    # the levels above the legs are summed out: the legs' values and noise are the whole vector,
    # G′ sampled through the stiffness at rest
    assert all(k.endswith("_s_leg") or k in ("sigma", "nu", STIFFNESS_SITE) for k in names)
    assert "gravity_s_leg" not in names
    # whose entry of the metric is the leg's Laplace covariance carried by the Jacobian at its mode
    params = stiffness_params(model)
    start = dict(zip([s.name for s in scr.specs], np.cumsum([0] + [s.size for s in scr.specs])))
    j = [int(start[p.name]) for p in params]  # their entries of the screen's vector
    row = stiffness_jacobian(*scr.mode[1, j], params)
    t1 = at[STIFFNESS_SITE] + 1
    assert metric[t1, t1] == pytest.approx(row @ scr.covariance[1][np.ix_(j, j)] @ row, rel=1e-5)
    assert metric[t1, at["damping_s_leg"] + 1] == pytest.approx(row @ scr.covariance[1][j, j[0] - 1], rel=1e-5)


def _two_chain_fit(p_delay, evidence=None):
    """InferenceData of 2 well-mixed chains × 400 draws on legs A and B, whose P(d | θ, data) per
    chain is ``p_delay`` (chain, leg, D); ``evidence``: (leg, D) per-delay Laplace P(d)."""
    import arviz as az

    rng = np.random.default_rng(0)
    with np.errstate(divide="ignore"):  # a delay a chain never visits: log 0
        logp = np.log(np.broadcast_to(np.asarray(p_delay)[:, None], (2, 400, 2, N_DELAYS)))
    return az.from_dict(
        posterior={"gain": rng.standard_normal((2, 400, 2)), "delay_logp": logp},
        sample_stats={"diverging": np.zeros((2, 400), bool), "energy": rng.standard_normal((2, 400))},
        constant_data={} if evidence is None else {"delay_evidence": np.asarray(evidence, np.float64)},
        coords={"leg": ["A", "B"], "delay_samples": np.arange(N_DELAYS)},
        dims={"gain": ["leg"], "delay_logp": ["leg", "delay_samples"], "delay_evidence": ["leg", "delay_samples"]},
    )


def _peaked(mode, spread=0.05):
    out = np.full(N_DELAYS, spread / (N_DELAYS - 1))
    out[mode] = 1.0 - spread
    return out


def test_chains_at_different_delays_fail_the_checks_and_name_the_leg():
    """Chains that agree on everything continuous but sit at different delays of one leg (as model 3's
    do at short data) fail, and the problem names the leg and each chain's delay."""
    from quadshank.inference._fitio import diagnose_sampling

    p = _peaked
    agree = diagnose_sampling(_two_chain_fit([[p(4), 0.5 * (p(4) + p(5))], [p(4), 0.5 * (p(4) + p(5))]]))
    assert agree["ok"], agree["problems"]
    assert agree["delay_splits"] == {}
    # leg A's chains differ a little (total variation 0.3), leg B's settle at 4 and 5
    split = diagnose_sampling(_two_chain_fit([[0.7 * p(4) + 0.3 * p(6), p(4)], [p(4), p(5)]]))
    assert not split["ok"]
    assert split["delay_splits"] == {"B": [4, 5]}
    assert any("B (chain 0: 4, chain 1: 5)" in x for x in split["problems"]), split["problems"]
    assert any("--delay-from" in a for a in split["advice"])
    assert split["mode_jumps"] is None and any("does not cross" in a for a in split["advice"])
    # chains that jumped between the modes and still disagree are told to draw more, not that they cannot cross
    jumped = _two_chain_fit([[0.7 * p(4) + 0.3 * p(6), p(4)], [p(4), p(5)]])
    jumped.sample_stats["mode_jump"] = (("chain", "draw"), np.ones((2, 400), np.int8))
    told = diagnose_sampling(jumped)
    assert not told["ok"] and told["mode_jumps"] == 800
    assert any("800 jumps" in a for a in told["advice"]) and not any("does not cross" in a for a in told["advice"])


def test_one_chain_is_named_as_a_problem_without_arviz_warnings():
    """One chain has no R-hat: the checks say so in their own words, and arviz logs nothing (its
    logger is its own, outside the logging tree, so it is listened to directly)."""
    import logging

    import arviz as az

    from quadshank.inference._fitio import diagnose_sampling

    class Keep(logging.Handler):
        def __init__(self):
            super().__init__()
            self.messages = []

        def emit(self, record):
            self.messages.append(record.getMessage())

    rng = np.random.default_rng(0)
    idata = az.from_dict(posterior={"a": rng.standard_normal((1, 217))},
                         sample_stats={"diverging": np.zeros((1, 217), bool), "energy": rng.standard_normal((1, 217))})
    keep = Keep()
    az._log.addHandler(keep)
    try:
        diag = diagnose_sampling(idata)
    finally:
        az._log.removeHandler(keep)
    assert keep.messages == []
    assert np.isnan(diag["rhat_max"]) and diag["chains"] == 1
    assert "one chain: R-hat cannot be computed" in diag["problems"]


def test_a_failing_check_names_the_parameter_and_leg_that_hold_the_fit_back():
    """R-hat and ESS are maxima and minima over every parameter of every leg: the problem names
    where the worst is, the parameter's own name rather than its standardised site, and the
    summary keeps it."""
    import arviz as az

    from quadshank.inference._fitio import diagnose_sampling

    rng = np.random.default_rng(1)
    legs = ["A-left", "B-left", "C-right"]

    def diagnosed(**posterior):
        return diagnose_sampling(az.from_dict(
            posterior=posterior, coords={"leg": legs}, dims={k: ["leg"] for k in posterior},
            sample_stats={"diverging": np.zeros((2, 300), bool), "energy": rng.standard_normal((2, 300))}))

    gain = rng.standard_normal((2, 300, 3))
    gain[1, :, 2] += 3.0  # the second chain sits elsewhere on the third leg only
    diag = diagnosed(gain=gain, gain_s_leg=gain * 2.0, k2=rng.standard_normal((2, 300, 3)))
    assert diag["worst"]["rhat"]["variable"] == "gain" and diag["worst"]["rhat"]["at"] == "C-right"
    assert any(p.startswith("R-hat") and "(gain of C-right): chains disagree" in p for p in diag["problems"])
    k2 = rng.standard_normal((2, 300, 3))
    for t in range(1, 300):  # the second leg's k2 mixes slowly (AR(1), 0.97), about the same mean in both chains
        k2[:, t, 1] = 0.97 * k2[:, t - 1, 1] + 0.25 * rng.standard_normal(2)
    diag = diagnosed(gain=rng.standard_normal((2, 300, 3)), k2=k2)
    assert diag["worst"]["ess_bulk"] == {**diag["worst"]["ess_bulk"], "variable": "k2", "at": "B-left"}
    assert any(p.startswith("bulk ESS") and "(k2 of B-left) <" in p for p in diag["problems"])


def test_a_delay_the_evidence_weighs_but_no_chain_visits_is_a_warning():
    """Chains that agree on one delay while the per-delay Laplace evidence gives a neighbour a
    fifth of the mass (model 3 on a minute of data) draw a warning naming the leg, the delay and
    both weights, without failing the fit (the evidence is of the leg alone, the chains' of the
    pooled posterior); a neighbour the chains visit, or one the evidence barely weighs, draws none."""
    from quadshank.inference._fitio import diagnose_sampling

    one = np.zeros(N_DELAYS)
    one[3] = 1.0
    chains = [[one, _peaked(4, 0.2)], [one, _peaked(4, 0.2)]]  # leg B's chains give every other delay 0.02
    ev_ok = np.stack([_peaked(3, 0.05), 0.8 * _peaked(4, 0.0) + 0.2 * _peaked(5, 0.0)])
    ok = diagnose_sampling(_two_chain_fit(chains, ev_ok))
    assert ok["ok"], ok["problems"]
    assert ok["delay_missed"] == {} and ok["warnings"] == []
    ev_bad = ev_ok.copy()
    ev_bad[0] = 0.79 * _peaked(3, 0.0) + 0.21 * _peaked(4, 0.0)
    bad = diagnose_sampling(_two_chain_fit(chains, ev_bad))
    assert bad["ok"] and bad["problems"] == []
    assert bad["delay_missed"] == {"A": {4: [0.21, 0.0]}}
    assert any("A (d = 4: 0.21 by the evidence, 0.00 in the chains)" in x for x in bad["warnings"]), bad["warnings"]
    # without the evidence (fits saved before it, or made with delay_evidence=False) nothing is claimed
    assert diagnose_sampling(_two_chain_fit(chains))["delay_missed"] == {}


def test_delay_evidence_weighs_each_delay_by_its_own_mode():
    """One Laplace approximation per delay.  Model 3 on a minute of TN-left (matching truth, d = 4)
    has a mode at d = 3 and one at d = 4: the screen, near the first, puts all of P(d) on 3; the
    evidence gives 4 about a fifth.  Model 2 pins d (all on the truth), and model 1, whose window
    sums cannot see d, leaves it at the uniform prior."""
    from quadshank.inference._nuts import delay_start
    from quadshank.evaluation._recovery import simulate_matching
    from quadshank.inference._screen import delay_evidence, laplace_fit

    for name, seed, minutes in [("model3", 2, 1.0), ("model2", 0, 0.5), ("model1", 0, 0.5)]:
        cohort, truth = simulate_matching(name, ("TN-left",), minutes, seed)
        assert truth["legs"]["TN-left"]["delay"] == 4
        scr = laplace_fit(cohort, build_model(name), n_starts=1, loo=False)
        ev = delay_evidence(scr)
        assert ev.shape == (1, N_DELAYS) and ev.sum() == pytest.approx(1.0)
        if name == "model3":
            assert scr.delay_posterior[0, 3] > 0.99
            assert 0.6 < ev[0, 3] < 0.95 and 0.05 < ev[0, 4] < 0.4, ev.round(3)
            assert ev[0, 3] + ev[0, 4] > 0.99
        elif name == "model2":
            assert ev[0, 4] > 0.99, ev.round(3)
        else:
            np.testing.assert_allclose(ev[0], 1.0 / N_DELAYS, atol=0.01)
            # delays the data do not tell apart move no screen (whichever d is the argmax)
            assert delay_start(cohort, FitSettings(), scr)[2] == {}


def test_a_screen_stuck_at_a_minor_delay_restarts_at_the_best_one():
    """delay_start: a screen whose mode sits at a delay the per-delay evidence gives little
    (here put there on purpose: the screen restarted at the mode of d = 6) is screened again
    from the mode of the delay the evidence weighs most, which then holds the screen's P(d)
    and a higher log density; where the fit's delay prior favours the delay the screen sits
    at, the screen stays."""
    from quadshank.inference._nuts import delay_start
    from quadshank.evaluation._recovery import simulate_matching
    from quadshank.inference._screen import delay_modes, laplace_fit, restart_screen

    cohort, truth = simulate_matching("model3", ("TN-left",), 1.0, 2)
    settings = FitSettings(chains=2, seed=0)
    scr = laplace_fit(cohort, build_model("model3"), n_starts=1, loo=False)
    dm = delay_modes(scr)
    assert dm.modes.shape == (1, N_DELAYS, scr.mode.shape[1]) and np.all(np.isfinite(dm.log_evidence))
    best = int(dm.probability[0].argmax())
    assert scr.delay_posterior[0, best] > 0.5  # this screen found the best delay itself
    stuck = restart_screen(scr, cohort, {"TN-left": dm.modes[0, 6]})
    assert stuck.delay_posterior[0, 6] > 0.5 and dm.probability[0, 6] < 1e-6
    assert stuck.neg_logpost[0] > scr.neg_logpost[0] + 10.0

    new, evidence, moved, _ = delay_start(cohort, settings, stuck)
    assert moved == {"TN-left": (6, best)}
    assert new.delay_posterior[0, best] > 0.5
    assert new.neg_logpost[0] == pytest.approx(scr.neg_logpost[0], abs=1.0)
    np.testing.assert_allclose(evidence, dm.probability, atol=0.02)

    prior = np.log(np.full((1, N_DELAYS), 1e-12))
    prior[0, 6] = 0.0
    same, evidence6, moved6, _ = delay_start(cohort, settings, stuck, log_delay_prior=prior)
    assert moved6 == {} and same is stuck and evidence6[0].argmax() == 6


def test_a_fit_jumps_between_the_delay_modes_its_evidence_weighs():
    """A minute of TN-left under model 3 has one mode of θ at d = 3 and one at d = 4, which the
    per-delay evidence weighs about 4 : 1 (see above).  The fit's chains jump between them
    (``mode_jump`` counts the jumps taken), and each chain's P(d = 4) is of the evidence's order."""
    from quadshank.evaluation._recovery import simulate_matching
    from quadshank.inference._nuts import run_nuts

    cohort, _ = simulate_matching("model3", ("TN-left",), 1.0, 2)
    settings = FitSettings(chains=2, warmup=150, draws=300, seed=0, chain_method="vectorized")
    run = run_nuts(cohort, build_model("model3"), settings, progress=False)
    assert 0.05 < run.delay_evidence[0, 4] < 0.4
    p = np.exp(np.asarray(run.mcmc.get_samples(group_by_chain=True)["delay_logp"], np.float64))[:, :, 0]
    assert np.all(p[..., 3:5].sum(axis=-1).mean(axis=1) > 0.98)
    p4 = p[..., 4].mean(axis=1)  # each chain's P(d = 4)
    assert np.all((p4 > 0.03) & (p4 < 0.6)), p4
    jumped = np.asarray(run.mcmc.get_extra_fields(group_by_chain=True)["mode_jump"])
    assert np.all(jumped.sum(axis=1) >= 5)
    no_jumps = dataclasses.replace(settings, mode_jumps=False, warmup=5, draws=5)
    assert "mode_jump" not in run_nuts(cohort, build_model("model3"), no_jumps, progress=False).mcmc.get_extra_fields()


def test_vectorized_and_sequential_chains_give_the_same_draws():
    """In double precision the batched and the one-by-one programs round nearly alike, and the
    chains give the same draws: a trajectory, a chaotic map, can carry a last-bit difference to
    about 1e-5 of the gain within ten draws, against 1e-2 between two chains.  (At mixed precision
    their single-precision terms round differently, and the chains part after a few draws: the same
    posterior, other draws.)"""
    # equal twitches: a short, smooth posterior whose chains draw no divergence (the runs, not the data, are tested)
    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.3, seed=2, trials=(1,), twitch_cv=0.0)
    draws = {}
    for method in ("vectorized", "sequential"):
        settings = FitSettings(chains=2, warmup=20, draws=10, seed=5, chain_method=method, start="prior", precision="double")
        mcmc, _ = fit(cohort, build_model("model1"), settings, progress=False)
        draws[method] = np.asarray(mcmc.get_samples(group_by_chain=True)["gain"])
    assert draws["vectorized"].shape[:2] == (2, 10)
    assert not np.allclose(draws["vectorized"][0], draws["vectorized"][1])  # two chains, not one twice
    np.testing.assert_allclose(draws["sequential"], draws["vectorized"], rtol=1e-4)


def test_auto_chain_method_runs_large_data_one_chain_after_another():
    from types import SimpleNamespace

    from quadshank.inference._nuts import SEQUENTIAL_FROM_SAMPLES, chain_method

    small = SimpleNamespace(sample_mask=np.ones((2, 9000), bool))  # the demo's 2 legs x 1.5 min
    large = SimpleNamespace(sample_mask=np.ones((5, 30000), bool))  # 5 legs x 5 min
    assert small.sample_mask.sum() < SEQUENTIAL_FROM_SAMPLES <= large.sample_mask.sum()
    assert chain_method(FitSettings(), small) == "vectorized"
    assert chain_method(FitSettings(), large) == "sequential"
    assert chain_method(FitSettings(chain_method="vectorized"), large) == "vectorized"
    assert chain_method(FitSettings(chain_method="sequential"), small) == "sequential"
    with pytest.raises(ValueError, match="chain_method must be one of"):
        FitSettings(chain_method="threads")


def test_the_fit_takes_single_precision_data_at_mixed_precision_on_the_acceleration_alone():
    """``precision="mixed"`` (the default) gives the fit's density the data's floating arrays in single
    precision on the acceleration, in double otherwise; the index arrays are left as they are."""
    from quadshank.inference._nuts import fit_arrays
    from quadshank.model._likelihood import prepare

    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.2, seed=0, trials=(1,))
    assert FitSettings().precision == "mixed"
    with pytest.raises(ValueError, match="precision must be one of"):
        FitSettings(precision="single")
    with jax.enable_x64(True):
        for objective, precision, want in (("acceleration", "mixed", jnp.float32), ("acceleration", "double", jnp.float64),
                                           ("angle", "mixed", jnp.float64)):
            data = prepare(cohort, build_model("model3"), objective=objective)
            x = fit_arrays(data, FitSettings(precision=precision))
            assert x["angle"].dtype == want and x["acceleration"].dtype == want, (objective, precision)
            assert x["window"].dtype == data.window.dtype


def test_the_noise_starts_at_the_fits_own_density_where_the_screen_held_a_threshold(monkeypatch):
    """The screen optimises a step delay effect's threshold that the fit sums out; a threshold on a
    wrong stair places pulses on the wrong side, which look like outliers to it (ν about 4 with a
    Laplace sd of 0.07 in log ν, where the fit's posterior has ν near 37 and an sd near 0.3).  So
    the chains' start and metric for σ and ν come from the fit's own density (30 s of TN-left,
    model3s + angle_delay)."""
    import quadshank.inference._nuts as nuts

    seen = {}
    moved = nuts._noise_at_the_fits_density

    def spy(conditioned, arrays, names, shapes, offsets, noise, inits, imm, seed):
        seen["before"] = inits[:, noise].copy(), np.sqrt(np.diag(imm)[noise])
        moved(conditioned, arrays, names, shapes, offsets, noise, inits, imm, seed)
        seen["after"] = inits[:, noise].copy(), np.sqrt(np.diag(imm)[noise])
        rest = np.setdiff1d(np.arange(imm.shape[0]), noise)
        assert np.all(imm[np.ix_(noise, rest)] == 0.0)  # uncorrelated with the rest

    class Started(Exception):
        """The chains' start is made: the sampler itself is not needed here."""

    def start_only(*args):
        nuts_screen_start(*args)
        raise Started

    nuts_screen_start = nuts.screen_start
    monkeypatch.setattr(nuts, "_noise_at_the_fits_density", spy)
    monkeypatch.setattr(nuts, "screen_start", start_only)
    # equal twitches: twitches that vary, with no noise term for them in the model, thicken the tails of
    # the fit's density too
    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.5, seed=2, effects=["angle_delay"], trials=(1,), twitch_cv=0.0)
    with pytest.raises(Started):
        fit(cohort, build_model("model3s", ["angle_delay"]), FitSettings(chains=2, seed=2), progress=False)
    (start0, sd0), (start1, sd1) = seen["before"], seen["after"]  # columns: log σ, log ν
    assert start1[:, 1].mean() > 2.3 and 0.2 < sd1[1] < 0.6  # the fit's
    assert abs(start1[:, 0].mean() - start0[:, 0].mean()) < 0.2  # σ moves little

    seen.clear()  # without a summed-out threshold the screen's density is the fit's: nothing moves
    with pytest.raises(Started):
        fit(cohort, build_model("model3s"), FitSettings(chains=1, seed=2), progress=False)
    assert not seen


def test_a_delay_piled_at_the_longest_considered_is_a_warning():
    """A leg whose P(d) holds a fifth or more at the longest delay considered (the muscle's delay
    may be longer, or the model's twitch shorter than the recorded one) is named with that
    probability and the delay in milliseconds, without failing the fit; a small tail draws nothing."""
    from quadshank.inference._fitio import diagnose_sampling

    edge = 0.65 * _peaked(N_DELAYS - 2, 0.0) + 0.35 * _peaked(N_DELAYS - 1, 0.0)
    tail = 0.9 * _peaked(4, 0.0) + 0.1 * _peaked(N_DELAYS - 1, 0.0)
    diag = diagnose_sampling(_two_chain_fit([[tail, edge], [tail, edge]]))
    assert diag["ok"], diag["problems"]
    assert diag["delay_at_edge"] == {"B": 0.35}
    (said,) = [w for w in diag["warnings"] if "longest delay considered" in w]
    assert f"{N_DELAYS - 1} samples ({(N_DELAYS - 1) * 10} ms)" in said and "B 0.35" in said and "A " not in said
    quiet = diagnose_sampling(_two_chain_fit([[tail, tail], [tail, tail]]))
    assert quiet["delay_at_edge"] == {} and quiet["delay_at_zero"] == {} and quiet["warnings"] == []
    onset = 0.7 * _peaked(0, 0.0) + 0.3 * _peaked(1, 0.0)  # a twitch at its pulse: no muscle's
    zero = diagnose_sampling(_two_chain_fit([[onset, tail], [onset, tail]]))
    assert zero["delay_at_zero"] == {"A": 0.7} and zero["delay_at_edge"] == {}
    (said,) = [w for w in zero["warnings"] if "at no delay" in w]
    assert "A 0.70" in said and "B " not in said and "identify" in said


def test_parameters_the_data_barely_inform_are_named_and_so_is_one_that_holds_the_fit_back():
    """A leg's parameter whose posterior is nearly as wide as its prior (the standardised site's sd
    at least WEAK_SD) is named with its leg and sd, a vector's component by its index from 1; where such
    a parameter is the one whose ESS fails, the advice says that it is barely informed."""
    import arviz as az

    from quadshank.inference._fitio import WEAK_SD, diagnose_sampling, weakly_informed

    rng = np.random.default_rng(2)
    n = 400
    slow = np.zeros((2, n))
    for t in range(1, n):  # a chain that crawls: ESS far below the 200 the checks ask
        slow[:, t] = 0.99 * slow[:, t - 1] + rng.normal(size=2) * 0.2
    k1_s = np.stack([0.05 * rng.normal(size=(2, n)), slow], axis=-1)  # legs A-left (informed), B-left (not)
    a_s = 0.02 * rng.normal(size=(2, n, 2, 2))
    a_s[:, :, 1, 0] = 0.8 * rng.normal(size=(2, n))  # a's second component of A-left, a[2]: barely informed
    idata = az.from_dict(
        posterior={"k1_s_leg": k1_s, "k1": 25.0 * np.exp(0.8 * k1_s), "a_s_leg": a_s},
        sample_stats={"diverging": np.zeros((2, n), bool), "energy": rng.standard_normal((2, n))},
        coords={"leg": ["A-left", "B-left"], "a_dim": [0, 1]},
        dims={"k1_s_leg": ["leg"], "k1": ["leg"], "a_s_leg": ["a_dim", "leg"]},
    )
    weak = weakly_informed(idata)
    assert set(weak) == {"A-left", "B-left"} and set(weak["A-left"]) == {"a[2]"} and set(weak["B-left"]) == {"k1"}
    assert weak["A-left"]["a[2]"] == pytest.approx(0.8, abs=0.1) and weak["B-left"]["k1"] >= WEAK_SD
    diag = diagnose_sampling(idata)
    assert not diag["ok"] and diag["weakly_informed"] == weak
    (said,) = [w for w in diag["warnings"] if "barely inform" in w]
    assert said.startswith("the data barely inform A-left's a[2] (0.") and "; B-left's k1 (" in said
    assert diag["advice"][0].startswith("k1 of B-left holds the fit back"), diag["advice"]

    informed = idata.copy()
    informed.posterior["k1_s_leg"] = informed.posterior["k1_s_leg"] * 0.1
    informed.posterior["a_s_leg"] = informed.posterior["a_s_leg"] * 0.1
    assert weakly_informed(informed) == {}
    assert not any("barely inform" in w for w in diagnose_sampling(informed)["warnings"])


def test_divergent_transitions_gathered_at_one_end_of_a_posterior_are_located():
    """Where every divergent draw lies in one outer tail of a leg's parameter (the end of a ridge),
    the fit names the leg and parameter with the divergent draws' mean quantile, and its advice says
    that smaller steps seldom mend that; divergent draws spread over the posterior, or fewer than
    three, name nothing and keep the advice of smaller steps."""
    import arviz as az

    from quadshank.inference._fitio import DIVERGENT_MIN, diagnose_sampling, divergence_location

    rng = np.random.default_rng(4)
    n = 300
    k1_s = rng.normal(size=(2, n, 2))  # legs A-left, B-left
    k2_s = -0.9 * k1_s + 0.2 * rng.normal(size=(2, n, 2))  # a ridge: k2 falls as k1 rises
    a_s = rng.normal(size=(2, n, 2, 2))

    def idata_with(diverging):
        return az.from_dict(
            posterior={"k1_s_leg": k1_s, "k2_s_leg": k2_s, "a_s_leg": a_s},
            sample_stats={"diverging": diverging, "energy": rng.standard_normal((2, n))},
            coords={"leg": ["A-left", "B-left"], "a_dim": [0, 1]},
            dims={"k1_s_leg": ["leg"], "k2_s_leg": ["leg"], "a_s_leg": ["a_dim", "leg"]},
        )

    # the divergent draws: the four with A-left's highest k1 (so, on the ridge, its lowest k2)
    flat = k1_s[..., 0].reshape(-1)
    at_end = np.zeros(2 * n, bool)
    at_end[np.argsort(flat)[-4:]] = True
    where = divergence_location(idata_with(at_end.reshape(2, n)))
    assert set(where) == {"A-left"} and set(where["A-left"]) == {"k1", "k2"}
    assert where["A-left"]["k1"] > 0.98 and where["A-left"]["k2"] < 0.1
    diag = diagnose_sampling(idata_with(at_end.reshape(2, n)))
    assert diag["divergences_at"] == where
    (said,) = [a for a in diag["advice"] if "divergent transitions all lie" in a]
    assert "A-left's k1 is high (" in said and " and k2 low (0.0" in said and "seldom mend" in said
    assert not any(a.startswith("raise the target acceptance") for a in diag["advice"])

    spread = np.zeros(2 * n, bool)
    spread[rng.choice(2 * n, 8, replace=False)] = True  # anywhere in the posterior
    diag = diagnose_sampling(idata_with(spread.reshape(2, n)))
    assert diag["divergences_at"] == {}
    assert any(a.startswith("raise the target acceptance") for a in diag["advice"])

    few = np.zeros(2 * n, bool)
    few[np.argsort(flat)[-(DIVERGENT_MIN - 1):]] = True  # at the end, but too few to say so
    assert divergence_location(idata_with(few.reshape(2, n))) == {}
