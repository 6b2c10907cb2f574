"""Every registered effect, built-in or user-written, through the same checks.

The parametrisation reads the registry when the tests are collected, so an
effect registered by the user (here: the documentation's example, registered
in ``conftest.py``) is tested like the built-in ones: its model runs, its
likelihood agrees with the rollout, gradients are finite, jit and vmap agree,
and parameters drawn from its prior give a finite likelihood.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from quadshank.model import _likelihood as L
from quadshank.model._effects import Effect, register_pytree, registered_effects, sin_deg
from quadshank.model._model import active_output, measured_acceleration, paper_model, simulate_angles
from quadshank.data._simulate import simulate_cohort

CANDIDATES = sorted(name for name, cls in registered_effects().items() if cls.candidate)
NOISE = {"sigma": 40.0, "nu": 8.0}


@pytest.fixture(scope="module")
def cohort():
    cohort, _ = simulate_cohort(legs=["JM-left"], minutes=0.5, seed=5, trials=(1, 3))
    return cohort


def _extended(name):
    base = paper_model("3s")
    if name in [e.name for e in base.effects]:
        base = paper_model(2)
    return base.add(name)


def _off_default(effect):
    """The effect's parameters half a prior scale away from their defaults (a default may be a null, e.g. no offset)."""
    out = {}
    for p in effect.declared_params():
        family, _, scale = p.prior[:3]
        v = np.asarray(getattr(effect, p.name), np.float32)
        step = 0.5 * np.asarray(scale, np.float32)
        out[p.name] = jnp.asarray(v * np.exp(step) if family == "lognormal" else v + step, jnp.float32)
    return out


def _leg_x(cohort, model):
    data = L.prepare(cohort, model, trials=(1, 3), legs=["JM-left"])  # trial 3: u = 0.5
    return data, {k: v[0] for k, v in data.leg_arrays().items()}


def _prior_draw(p, rng):
    family, loc, scale = p.prior[:3]
    z = rng.standard_normal(p.shape)
    x = np.asarray(loc, float) + np.asarray(scale, float) * z
    return np.exp(x) if family == "lognormal" else x


def test_the_loop_offers_the_issue_effects():
    for name in ("torque_angle_peak", "hill_velocity", "angle_delay", "fatigue", "potentiation"):
        assert name in CANDIDATES
    assert "cubic_torque_angle" in CANDIDATES  # the user-written effect of conftest.py


def test_an_added_effect_replaces_what_it_generalises():
    names = [e.name for e in _extended("torque_angle_peak").effects]
    assert "linear_torque_angle" not in names and "torque_angle_peak" in names
    assert "linear_torque_velocity" in names


def test_effects_with_the_same_layout_have_distinct_tree_structures(scratch_registry):
    """jit's cache is keyed by the tree structure: two effects with one parameter each must not
    share one (with register_dataclass they compared equal, and a model with one effect now and
    then ran the program compiled for the other: the flake this suite once had)."""
    from quadshank import Param, register_effect

    made = []
    for k in range(40):
        cls = dataclasses.make_dataclass(f"Gain{k}", [("g", float, dataclasses.field(default=float(k)))], bases=(Effect,), frozen=True)
        cls.kind, cls.name, cls.params = "gain", f"scratch_gain_{k}", (Param("g", "1", prior=("normal", 0.0, 1.0)),)
        cls.factor = lambda self, ctx, k=k: k + 0.0 * self.g
        made.append(register_effect(cls)())
    defs = [jax.tree_util.tree_structure(e) for e in made]
    assert all(a != b for i, a in enumerate(defs) for b in defs[i + 1 :])
    name_of = jax.jit(lambda e: e.factor(None))
    assert [float(name_of(e)) for e in made] == [float(k) for k in range(40)]


@pytest.mark.parametrize("name", CANDIDATES)
def test_likelihood_output_equals_the_rollout(cohort, name):
    """The likelihood's pulse-by-pulse M̂ equals stepping the model on the measured state
    (and reading it through the accelerometer's response, if the model has one)."""
    model = _extended(name)
    model = model.with_params(_off_default(model.effect(name)), delay=4)
    if model.delay_effect is not None:
        model = model.with_delay_shift(1)
    data, x = _leg_x(cohort, model)
    t = cohort.get("JM-left", 1)
    stepped = np.asarray(measured_acceleration(model, active_output(model, t.angle_deg, t.velocity_deg_s, t.stimulation)))
    K = data.max_shift
    shift = 1 if K else 0
    sparse = np.asarray(L.leg_active_output(model, x, 4, data.response_length, K, shift))[: t.n_samples]
    assert np.abs(stepped).max() > 100.0  # twitches are there
    np.testing.assert_allclose(sparse, stepped, atol=2e-3 * np.abs(stepped).max())


def _kind_pairs():
    """Two candidates for every pair of effect kinds, a kind with itself included where it has two:
    the candidates of each kind taken in turn, so that the pairs between them cover every
    candidate; the pair the accelerometer's response once kept apart (an output effect read
    through it) explicitly."""
    by_kind = {}
    in_base = {e.name for e in paper_model("3s").effects}  # candidates of the smaller models only
    for name in (n for n in CANDIDATES if n not in in_base):
        by_kind.setdefault(registered_effects()[name].kind, []).append(name)
    kinds = sorted(by_kind)
    pairs, turn = set(), 0
    for i, a in enumerate(kinds):
        for b in kinds[i:]:
            if a == b and len(by_kind[a]) < 2:
                continue
            first = by_kind[a][turn % len(by_kind[a])]
            second = [n for n in by_kind[b] if n != first][turn % (len(by_kind[b]) - (a == b))]
            pairs.add(tuple(sorted((first, second))))
            turn += 1
    with_response = [n for n in CANDIDATES if registered_effects()[n].acceleration_response is not Effect.acceleration_response]
    pairs |= {tuple(sorted((m, o))) for m in with_response for o in by_kind.get("output", [])}
    return sorted(pairs)


KIND_PAIRS = _kind_pairs()


def test_the_pairs_cover_every_pair_of_kinds():
    in_base = {e.name for e in paper_model("3s").effects}
    kinds = {registered_effects()[n].kind for n in CANDIDATES if n not in in_base}
    covered = {frozenset(registered_effects()[n].kind for n in pair) for pair in KIND_PAIRS}
    assert {frozenset((a, b)) for a in kinds for b in kinds if a != b} <= covered
    assert ("accel_resonance", "activation_damping") in KIND_PAIRS


@pytest.mark.parametrize("pair", KIND_PAIRS, ids="+".join)
def test_every_pair_of_kinds_in_one_likelihood(cohort, pair):
    """Any two candidates the registry lets a model hold together: the likelihood's M̂ equals
    stepping the model (read through the accelerometer's response, if it has one), and its
    gradient in both effects' parameters is finite."""
    base = paper_model("3s")
    try:
        model = base.add(pair[0]).add(pair[1])
    except ValueError as err:  # a rule of the registry (one delay effect, say), stated as such
        assert "twice" in str(err) or "more than one" in str(err) or "declared by two" in str(err), err
        return
    values = {**_off_default(model.effect(pair[0])), **_off_default(model.effect(pair[1]))}
    model = model.with_params(values, delay=4)
    if model.delay_effect is not None:
        model = model.with_delay_shift(1)
    data, x = _leg_x(cohort, model)
    t = cohort.get("JM-left", 1)
    stepped = np.asarray(measured_acceleration(model, active_output(model, t.angle_deg, t.velocity_deg_s, t.stimulation)))
    R, K = data.response_length, data.max_shift
    sparse = np.asarray(L.leg_active_output(model, x, 4, R, K, 1 if K else 0))[: t.n_samples]
    assert np.abs(stepped).max() > 100.0
    np.testing.assert_allclose(sparse, stepped, atol=2e-3 * np.abs(stepped).max())

    def loglik(vals):
        return jax.scipy.special.logsumexp(L.leg_loglik_by_delay(model.with_params(vals), NOISE, x, R, K)[:, : K + 1])

    grads = {k: np.asarray(g) for k, g in jax.grad(loglik)(values).items()}
    assert all(np.all(np.isfinite(g)) for g in grads.values()), (pair, grads)
    for name in pair:  # the data depend on each effect (a step's threshold is summed out, not differentiated)
        eff = model.effect(name)
        free = [p.name for p in eff.declared_params() if p.name != getattr(eff, "step_param", None)]
        assert not free or any(np.any(grads[n] != 0) for n in free), (pair, name)


@pytest.mark.parametrize("name", CANDIDATES)
def test_gradient_finite_and_jit_vmap_agree(cohort, name):
    model = _extended(name)
    data, x = _leg_x(cohort, model)
    R, K = data.response_length, data.max_shift
    eff = model.effect(name)
    values = eff.values()

    def loglik(vals):
        m = model.with_params(vals)
        return jax.scipy.special.logsumexp(L.leg_loglik_by_delay(m, NOISE, x, R, K)[:, : K + 1])

    grads = jax.grad(loglik)({k: jnp.asarray(v, jnp.float32) for k, v in values.items()})
    for k, g in grads.items():
        assert np.all(np.isfinite(np.asarray(g))), (name, k)
    assert any(np.any(np.asarray(g) != 0) for g in grads.values()), f"{name}: the data do not depend on it"

    rng = np.random.default_rng(0)
    draws = [{p.name: _prior_draw(p, rng).astype(np.float32) for p in eff.declared_params()} for _ in range(3)]
    stacked = {k: jnp.stack([jnp.asarray(d[k]) for d in draws]) for k in values}
    batched = np.asarray(jax.vmap(jax.jit(loglik))(stacked))
    single = np.array([float(loglik(d)) for d in draws])
    assert np.all(np.isfinite(single)), f"{name}: a prior draw gives a non-finite likelihood"
    np.testing.assert_allclose(batched, single, rtol=1e-5)


@pytest.mark.parametrize("name", CANDIDATES)
def test_rollout_shapes_and_prior_draws(cohort, name):
    model = _extended(name)
    t = cohort.get("JM-left", 1)
    eff = model.effect(name)
    rng = np.random.default_rng(1)
    for _ in range(3):
        m = model.with_params({p.name: jnp.asarray(_prior_draw(p, rng), jnp.float32) for p in eff.declared_params()})
        angle, velocity, acc = simulate_angles(m, jnp.asarray(t.stimulation[:500]))
        assert angle.shape == velocity.shape == acc.shape == (500,)
        assert np.all(np.isfinite(np.asarray(angle)))


def test_a_broken_effect_fails_the_checks(cohort):
    """The agreement test can fail: a pulse effect whose likelihood and rollout disagree."""

    @dataclasses.dataclass(frozen=True)
    class Inconsistent(Effect):
        kind = "pulse"
        name = "inconsistent"
        params = ()

        def pulse_factor(self, pctx):
            return 1.0 + 0.5 * jnp.sin(pctx.time_s)  # fine in both ...

    register_pytree(Inconsistent, [], [])  # a pytree, not in the registry
    model = paper_model("3s").add(Inconsistent()).with_params(delay=4)
    data, x = _leg_x(cohort, model)
    x = dict(x, pulse_time_s=x["pulse_time_s"] + 1.0)  # ... until the likelihood's clock is off by 1 s
    t = cohort.get("JM-left", 1)
    stepped = np.asarray(active_output(model, t.angle_deg, t.velocity_deg_s, t.stimulation))
    sparse = np.asarray(L.leg_active_output(model, x, 4, data.response_length))[: t.n_samples]
    assert np.abs(sparse - stepped).max() > 0.05 * np.abs(stepped).max()


# ------------------------------------------------------------------ simulate, then recover


def _model_cohort(model, minutes, seed=3):
    """JM-left trials 1 (u = 1) and 3 (u = 0.5) generated by ``model`` itself, read through its sensors.
    A noise effect's random gain per pulse (``twitch_variability``) scales each pulse's recruitment
    level in the simulation, log-normal with mean 1, and the data record the planned level."""
    from quadshank.data._cohort import Cohort, Trial
    from quadshank.model._model import measure
    from quadshank.data._simulate import plan_leg, twitch_variability

    n = int(minutes * 6000)
    plans = plan_leg("JM-left", n, seed, ())
    rng = np.random.default_rng(seed)
    trials = []
    for trial in (1, 3):
        stim = np.zeros(n, np.float32)
        stim[plans[trial]["pulses"]] = plans[trial]["u"]
        delivered = stim.copy()
        for e in model.noises:  # the simulator's own log-normal draw, at the effect's CV
            p = plans[trial]["pulses"]
            delivered[p] *= twitch_variability(rng, p.size, float(np.sqrt(e.pulse_variance()))).astype(np.float32)
        angle, velocity, m = simulate_angles(model, jnp.asarray(delivered))
        seen_angle, seen_acc = (np.asarray(v, np.float64) for v in measure(model, angle, velocity, m))
        acc = seen_acc + NOISE["sigma"] * rng.standard_normal(n)
        trials.append(
            Trial.from_signals("JM", "left", trial, 0.01, seen_angle, acc, stim, velocity_deg_s=np.asarray(velocity, np.float64))
        )
    return Cohort(tuple(trials))


#: Every effect a model can add (not the activation or the passive system), candidate or not.
ADDABLE = sorted(name for name, cls in registered_effects().items() if cls.kind not in ("activation", "passive"))


def _recover_base(name):
    """The model to extend: model3s, but a first-order DARMA twitch under a fractional delay (on
    DARMA(2,2) a fraction of a sample is a re-parametrisation of b: b1·w, b1(1 − w) + b2·w, b2(1 − w))."""
    if name == "fractional_delay":
        from quadshank.model._effects import Darma

        base = paper_model("3s")
        act = Darma(a=jnp.array([-0.77]), b=jnp.array([700.0]))
        return dataclasses.replace(base, effects=(act, *[e for e in base.effects if e.kind != "activation"])).add(name)
    return _extended(name)


#: Truths stronger than half a prior scale where half a scale is invisible in half a minute
#: (fatigue by 1/e in ~1200 pulses is a 4 % change over the ~50 pulses of a trial).
RECOVER_TRUTH = {"fatigue": {"n_fatigue": 100.0}}
RECOVER_MINUTES = {"fatigue": 1.0}


@pytest.mark.parametrize("name", ADDABLE)
def test_simulate_then_recover(name):
    """Data generated by the extended model with the effect's parameters off their defaults: at the
    screen's posterior mode, each lies within 3 Laplace standard deviations (or 0.2 prior scales)
    of the truth, and the data narrowed the prior of at least one of them."""
    from quadshank.inference._screen import laplace_fit

    model = _recover_base(name)
    eff = model.effect(name)
    truth = _off_default(eff) | {k: jnp.float32(v) for k, v in RECOVER_TRUTH.get(name, {}).items()}
    true_model = model.with_params(truth, delay=4)
    if true_model.delay_effect is not None:
        true_model = true_model.with_delay_shift(1)
    cohort = _model_cohort(true_model, minutes=RECOVER_MINUTES.get(name, 0.5))
    fit = laplace_fit(cohort, model, trials=(1, 3), legs=["JM-left"], n_starts=1, n_draws=300, seed=0, loo=False)
    if model.delay_effect is None:
        assert int(np.argmax(fit.delay_posterior[0])) == 4
    j, informative = 0, []
    for spec in fit.specs:
        size = spec.size
        if spec.name in truth:
            t = np.asarray(truth[spec.name], float).reshape(-1)
            z_true = spec.param.to_standard(np.reshape(t, spec.shape)).reshape(-1)
            z_mode = fit.mode[0, j : j + size]
            z_sd = fit.draws[0, :, j : j + size].std(axis=0)  # the Laplace Gaussian, in prior scales
            err = np.abs(z_mode - z_true)
            assert np.all(err <= np.maximum(3 * z_sd, 0.2)), f"{name}.{spec.name}: mode {z_mode} vs truth {z_true} (sd {z_sd}), prior scales"
            informative.append(bool(np.all(z_sd < 0.7)))
        j += size
    assert any(informative), f"{name}: the data taught the screen nothing about the effect"


def test_loo_pit_of_the_screen_is_uniform_on_data_from_the_model():
    """On data generated by model3s itself (Student-t noise, as the likelihood assumes), the
    screen's LOO-PIT is uniform within its band, with 10 % of the windows in the outer 5 % tails;
    the same PIT values read against a predictive three times too narrow are not."""
    from quadshank.evaluation import _residuals as rd
    from quadshank.evaluation._checks import elpd_in_time, loo_pit
    from quadshank.inference._screen import laplace_fit

    model = paper_model("3s")
    cohort = _model_cohort(model.with_params(delay=4), minutes=0.5)
    fit = laplace_fit(cohort, model, trials=(1, 3), legs=["JM-left"], n_starts=0, n_draws=200, seed=0)
    pit = loo_pit(fit, "JM-left")
    assert pit.shape == (int(fit.data.window_mask[0].sum()),)
    summary = rd.loo_pit_summary(pit, int(fit.data.segment_mask[0].sum()))
    assert summary["notes"] == [] and 0.07 < summary["tail_share"] < 0.13 and abs(summary["mean"] - 0.5) < 0.03
    from scipy import stats

    too_narrow = stats.t.cdf(3.0 * stats.t.ppf(np.clip(pit, 1e-9, 1 - 1e-9), NOISE["nu"]), NOISE["nu"])
    assert "too narrow" in rd.loo_pit_summary(too_narrow, int(fit.data.segment_mask[0].sum()))["notes"][0]
    seconds = elpd_in_time(fit, cohort, "JM-left")
    assert [r["trial"] for r in seconds] == [1] * 30 + [3] * 30 and seconds[-1]["start_s"] == 29.0
    np.testing.assert_allclose(sum(r["elpd"] for r in seconds), fit.elpd, rtol=1e-9)


def test_single_precision_sine_is_as_accurate_as_xlas():
    """The rollouts' float32 sine (:func:`sin_deg`) against float64: no worse than
    ``jnp.sin(jnp.deg2rad(·))`` in float32 anywhere on ±1000°, exact signs at the
    multiples of 90°, the cosine as its gradient, and float64 left to ``jnp.sin``."""
    x = np.linspace(-1000.0, 1000.0, 200_001).astype(np.float32)
    ref = np.sin(np.deg2rad(x.astype(np.float64)))
    ours = np.asarray(sin_deg(jnp.asarray(x)), np.float64)
    xla = np.asarray(jnp.sin(jnp.deg2rad(jnp.asarray(x))), np.float64)
    assert np.abs(ours - ref).max() <= np.abs(xla - ref).max()
    assert np.abs(ours - ref).max() < 2.4e-7  # two float32 ulps of 1
    quarter = jnp.asarray([-270.0, -90.0, 90.0, 270.0, 450.0], jnp.float32)
    np.testing.assert_allclose(np.asarray(sin_deg(quarter)), [1, -1, 1, -1, 1], atol=1.2e-7)
    np.testing.assert_array_equal(np.asarray(sin_deg(jnp.asarray([-180.0, 0.0, 180.0, 360.0], jnp.float32))), 0.0)
    grad = jax.vmap(jax.grad(sin_deg))(jnp.asarray(x[::997]))
    np.testing.assert_allclose(np.asarray(grad), np.cos(np.deg2rad(x[::997].astype(np.float64))) * np.pi / 180, atol=1e-8)
    with jax.enable_x64(True):
        a = jnp.asarray(x[::997], jnp.float64)
        np.testing.assert_array_equal(np.asarray(sin_deg(a)), np.asarray(jnp.sin(jnp.deg2rad(a))))
