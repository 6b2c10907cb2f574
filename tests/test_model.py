"""The Effect/Model abstraction and the discrete-time models of the paper (eqs. 1-8)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from quadshank.model._effects import Effect, Param, register_effect, registered_effects
from quadshank.model._model import (
    Model,
    active_carries,
    paper_model,
    passive_effects,
    predict_ahead,
    simulate_angles,
)

PASSIVE = dict(damping=1.1, gravity=1800.0, k1=25.0, k2=0.05)


def pulse_train(n=3000, seed=0):
    rng = np.random.default_rng(seed)
    u = np.zeros(n)
    t = 20
    while t < n:
        u[t] = 1.0
        t += int(rng.integers(2, 10) if rng.random() < 0.3 else rng.integers(40, 150))
    return u


def test_paper_models_are_compositions_of_effects():
    names = {m: [e.name for e in paper_model(m).effects] for m in ("model1", "model2", "model3")}
    assert names["model1"][0] == "zero_order"
    assert names["model2"][0] == "darma"
    assert names["model3"][:3] == ["zero_order", "linear_torque_angle", "linear_torque_velocity"]
    for n in names.values():
        assert n[-3:] == ["damping", "gravity", "elasticity"]
    with pytest.raises(ValueError, match="model4"):
        paper_model("model4")


def test_model_structure_is_checked():
    z = paper_model(1)
    with pytest.raises(ValueError, match="exactly one activation"):
        Model(z.effects + (paper_model(2).activation,))
    with pytest.raises(ValueError, match="twice"):
        Model(z.effects + (z.effects[-1],))
    with pytest.raises(KeyError, match="no parameter"):
        z.with_params(gamma_angle=0.1)
    # a delay outside the samples the history holds would be clamped or wrapped by the index
    for delay in (-1, 11, 2.5, "4"):
        with pytest.raises(ValueError, match="delay must be a whole number of samples from 0 to 10"):
            z.with_params(delay=delay)
    assert z.with_params(delay=np.arange(11)).delay.shape == (11,)  # one per draw
    for period in (0.0, -0.01, float("nan"), 1.0):
        with pytest.raises(ValueError, match="sampling_period_s must be a period in seconds"):
            Model(z.effects, sampling_period_s=period)


def test_free_swing_matches_accurate_ode_solution():
    """RK4 per T_s of eq. (8) without stimulation against a tight-tolerance ODE solver."""
    m = paper_model(1, passive_effects(**PASSIVE))
    n = 400
    a, v, _ = simulate_angles(m, jnp.zeros(n), angle0=35.0, velocity0=-50.0)

    def rhs(_, y):
        phi, dphi = y
        acc = -PASSIVE["damping"] * dphi - PASSIVE["gravity"] * np.sin(np.deg2rad(phi))
        acc += PASSIVE["k1"] * (np.exp(-PASSIVE["k2"] * phi) - 1)
        return [dphi, acc]

    t = np.arange(n) * 0.01
    ref = solve_ivp(rhs, (0, t[-1]), [35.0, -50.0], t_eval=t, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(np.asarray(a), ref.y[0], atol=2e-3)
    # and the small-angle natural frequency is sqrt(G' pi/180) / (2 pi)
    a_small, _, _ = simulate_angles(paper_model(1, passive_effects(0.0, 1800.0, 0.0, 0.05)), jnp.zeros(2000), 1.0, 0.0)
    a_small = np.asarray(a_small)
    crossings = np.flatnonzero(np.diff(np.sign(a_small)) != 0)
    period = 2 * np.mean(np.diff(crossings)) * 0.01
    assert period == pytest.approx(2 * np.pi / np.sqrt(1800.0 * np.pi / 180), rel=0.01)


@pytest.mark.parametrize("d", [0, 3, 7])
def test_delay_and_activation_timing(d):
    """A pulse at sample k acts over sample k+d (models 1, 3) and from k+d+1 (model 2, eq. 4)."""
    u = np.zeros(60)
    u[10] = 1.0
    _, _, m1 = simulate_angles(paper_model(1).with_params(gain=1e4, delay=d), jnp.asarray(u))
    m1 = np.asarray(m1)
    assert np.flatnonzero(m1) .tolist() == [10 + d]
    assert m1[10 + d] == pytest.approx(1e4)
    a, b = np.array([-1.4, 0.6]), np.array([500.0, 600.0])
    _, _, m2 = simulate_angles(paper_model(2).with_params(a=a, b=b, delay=d), jnp.asarray(u))
    ref = np.zeros(60)
    for k in range(60):
        ref[k] = -a[0] * (ref[k - 1] if k >= 1 else 0) - a[1] * (ref[k - 2] if k >= 2 else 0)
        ref[k] += b[0] * (u[k - 1 - d] if k - 1 - d >= 0 else 0) + b[1] * (u[k - 2 - d] if k - 2 - d >= 0 else 0)
    np.testing.assert_allclose(np.asarray(m2), ref, rtol=1e-5, atol=1e-3)
    assert np.flatnonzero(np.abs(ref) > 0)[0] == 10 + d + 1


def test_model3_modulation_uses_state_at_the_start_of_the_sample():
    m = paper_model(3, passive_effects(**PASSIVE)).with_params(gain=1e4, gamma_angle=-0.01, gamma_velocity=-0.002, delay=2)
    u = pulse_train(600)
    a, v, mi = simulate_angles(m, jnp.asarray(u))
    a, v, mi = (np.asarray(x, dtype=float) for x in (a, v, mi))
    k = np.flatnonzero(u)[:-1] + 2
    np.testing.assert_allclose(mi[k], 1e4 * (1 - 0.01 * a[k]) * (1 - 0.002 * v[k]), rtol=1e-4)


@pytest.mark.parametrize("name", ["model1", "model2", "model3"])
def test_predictions_of_a_model_on_its_own_simulation_are_exact(name):
    """The active part carried over from the previous run + measured passive state = the simulation itself."""
    m = paper_model(name, passive_effects(**PASSIVE)).with_params(delay=4)
    u = pulse_train(2000)
    a, v, _ = simulate_angles(m, jnp.asarray(u))
    starts = np.arange(0, 1900, 7)
    pred = np.asarray(predict_ahead(m, a, v, u, starts, 100))
    a = np.asarray(a)
    truth = a[starts[:, None] + np.arange(1, 101)[None, :]]
    np.testing.assert_allclose(pred, truth, atol=2e-3)
    # a different model does not reproduce it
    other = m.with_params(delay=6)
    pred_other = np.asarray(predict_ahead(other, a, v, u, starts, 100))
    assert np.sqrt(np.mean((pred_other - truth) ** 2)) > 0.1


def test_active_carries_for_a_stateful_activation_follow_the_data():
    m = paper_model(2).with_params(delay=1)
    u = pulse_train(300)
    a, v, mi = simulate_angles(m, jnp.asarray(u))
    carries = active_carries(m, a, v, jnp.asarray(u))
    # the DARMA state before sample k holds M_{k-1}, M_{k-2}
    np.testing.assert_allclose(np.asarray(carries.activation[0][5:, 0]), np.asarray(mi)[4:-1], rtol=1e-5, atol=1e-3)


def test_jit_vmap_and_gradients():
    base = paper_model(3, passive_effects(**PASSIVE)).with_params(delay=3)
    u = jnp.asarray(pulse_train(400))
    gains = jnp.array([8e3, 1.2e4, 1.6e4])

    def final_angle(g):
        a, _, _ = simulate_angles(base.with_params(gain=g), u)
        return a[-1]

    batched = jax.vmap(final_angle)(gains)
    looped = jnp.stack([final_angle(g) for g in gains])
    np.testing.assert_allclose(np.asarray(batched), np.asarray(looped), rtol=1e-5)

    def loss(g):
        a, _, _ = simulate_angles(base.with_params(gain=g), u)
        return jnp.mean(a**2)

    g0 = 1.2e4
    grad = float(jax.grad(loss)(jnp.float32(g0)))
    fd = (float(loss(g0 * 1.001)) - float(loss(g0 * 0.999))) / (0.002 * g0)
    assert np.isfinite(grad) and grad == pytest.approx(fd, rel=0.05)
    # vmapping over the delay (as a latent) works too
    delays = jnp.arange(0, 6)
    finals = jax.vmap(lambda d: simulate_angles(base.with_params(delay=d), u)[0][-1])(delays)
    assert len(set(np.round(np.asarray(finals), 4))) == 6


def test_user_written_effect_slots_in(scratch_registry):
    @register_effect
    @dataclasses.dataclass(frozen=True)
    class CubicTorqueAngle(Effect):
        kind = "gain"
        name = "test_cubic_torque_angle"
        params = (Param("c3", "1/deg^3", prior=("normal", 0.0, 1e-6)),)
        c3: float = 0.0

        def factor(self, ctx):
            return 1.0 + self.c3 * ctx.angle**3

    assert "test_cubic_torque_angle" in registered_effects()
    base = paper_model(1, passive_effects(**PASSIVE))
    ext = base.add("test_cubic_torque_angle").with_params(c3=-1e-5)
    assert ext.params()["c3"] == -1e-5
    assert ext.name == "model1+test_cubic_torque_angle"  # named as build_model names it: results are keyed by it
    u = jnp.asarray(pulse_train(500))
    a0, _, m0 = simulate_angles(base, u)
    a1, _, m1 = simulate_angles(ext, u)
    k = np.flatnonzero(np.asarray(m0))
    ratio = np.asarray(m1)[k] / np.asarray(m0)[k]
    np.testing.assert_allclose(ratio, 1 - 1e-5 * np.asarray(a1)[k] ** 3, rtol=1e-4)
    desc = ext.describe()
    assert desc["effects"][-1]["params"][0]["units"] == "1/deg^3"


def test_register_effect_rejects_malformed_classes():
    class NotADataclass(Effect):
        kind = "gain"
        name = "x"

    with pytest.raises(TypeError, match="frozen dataclass"):
        register_effect(NotADataclass)

    @dataclasses.dataclass(frozen=True)
    class MissingField(Effect):
        kind = "gain"
        name = "missing_field"
        params = (Param("q", "1"),)

    with pytest.raises(TypeError, match="not dataclass fields"):
        register_effect(MissingField)

    @dataclasses.dataclass  # not frozen
    class Mutable(Effect):
        kind = "gain"
        name = "mutable_gain"
        params = (Param("c", "1/deg"),)
        c: float = 0.0

    with pytest.raises(TypeError, match="must be a frozen dataclass"):
        register_effect(Mutable)

    @dataclasses.dataclass(frozen=True)
    class Twice(Effect):
        kind = "gain"
        name = "twice_gain"
        params = (Param("c", "1/deg"), Param("c", "1/deg"))
        c: float = 0.0

    with pytest.raises(TypeError, match=r"parameter\(s\) \['c'\] declared twice"):
        register_effect(Twice)

    @dataclasses.dataclass(frozen=True)
    class ThreeValues(Effect):  # a factor of shape (3,) for one sample: JAX's scan would say only "carry types"
        kind = "gain"
        name = "three_values_gain"
        params = (Param("c", "1/deg"),)
        c: float = 0.0

        def factor(self, ctx):
            return jnp.ones(3) * (1.0 + self.c * ctx.angle)

    with pytest.raises(TypeError, match=r"ThreeValues.factor\(\) must return one value per sample it is given "
                                        r"\(shape \(\) for inputs of shape \(\)\), not \(3,\)"):
        register_effect(ThreeValues)

    @dataclasses.dataclass(frozen=True)
    class NoPulseFactor(Effect):
        kind = "pulse"
        name = "no_pulse_factor"

    with pytest.raises(TypeError, match=r"NoPulseFactor: pulse effect 'no_pulse_factor' must define pulse_factor\(\)"):
        register_effect(NoPulseFactor)
    assert "three_values_gain" not in registered_effects() and "no_pulse_factor" not in registered_effects()


def test_every_registered_effect_contributes_one_value_per_sample():
    """The shape check a user's effect meets at registration holds for every built-in (and the
    user's effect of conftest.py), on one sample and on many; an effect that returns a constant
    passes, since it broadcasts."""
    from quadshank.model._effects import CONTRIBUTIONS, check_contribution

    checked = [cls for cls in registered_effects().values() if cls.kind in CONTRIBUTIONS]
    assert {cls.kind for cls in checked} == set(CONTRIBUTIONS)
    for cls in checked:
        check_contribution(cls)
