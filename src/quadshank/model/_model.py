"""Model: a flat tuple of effects plus the delay, and the pure functions that run it.

One sample of the discrete-time model (T_s, default 10 ms):

1. the pulse delivered at sample k, scaled by the pulse effects (fatigue,
   potentiation, ...), enters the input history;
2. the delay selects the input reaching the muscle, u_{k-d} (eq. 1);
3. gain effects scale it, evaluated at the state at the start of the sample,
   f_i(φ_k, φ̇_k) (eqs. 2, 5): a twitch is scaled as a whole by the state at
   its onset;
4. the activation effect turns it into an equivalent acceleration M_k/I
   (for the zero-order activation of models 1 and 3, M_k/I =
   G'·u_{k-d}·Π f_i(φ_k, φ̇_k), eq. 5 exactly), which output effects
   modulate by the state at this sample;
5. the passive system (eq. 8) is integrated over T_s by one RK4 step with
   M_k/I held constant, as in the paper.

The dynamics run on the true angle.  Measurement effects say how the sensors
see it (:func:`true_angle`, :func:`measured_angle`,
:func:`measured_acceleration`); the functions that take measured signals
(:func:`equivalent_acceleration`, :func:`active_output`,
:func:`predict_ahead`) convert at their entry and exit, and without
measurement effects the conversions are the identity.

Everything is pure and jit-able; a :class:`Model` is a pytree whose leaves are
the effects' parameter values and the delay, so it can be vmapped over draws.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..data._cohort import MAX_SAMPLING_PERIOD_S, SAME_PERIOD_REL
from ..data._paper import MAX_DELAY, SAMPLING_PERIOD_S
from ._effects import (
    FIRST_IPI_S,
    Damping,
    Darma,
    Effect,
    ExponentialElasticity,
    Gravity,
    GravityOffset,
    LinearTorqueAngle,
    LinearTorqueVelocity,
    NoMuscle,
    PulseContext,
    StepContext,
    ZeroOrderActivation,
    get_effect,
    register_pytree,
)

__all__ = [
    "Model",
    "ActiveCarry",
    "paper_model",
    "PAPER_MODELS",
    "MODELS",
    "FIT_MODELS",
    "passive_effects",
    "equivalent_acceleration",
    "simulate_angles",
    "active_carries",
    "active_output",
    "predict_ahead",
    "true_angle",
    "measured_angle",
    "acceleration_response",
    "measured_acceleration",
    "measure",
]

#: Length of the input and angle history kept by the model (d ≤ MAX_DELAY, +2 spare).
HISTORY = MAX_DELAY + 3


def _check_delay(delay, name: str) -> None:
    """Refuse a delay that is not a whole number of samples from 0 to MAX_DELAY (one per draw where
    it is an array; a traced delay, inside a compiled function, is the program's to keep in range)."""
    if isinstance(delay, jax.core.Tracer):
        return
    try:
        d = np.asarray(delay)
        bad = d.dtype.kind not in "iuf" or not np.all(np.isfinite(d)) or np.any(d != np.round(d)) \
            or np.any(d < 0) or np.any(d > MAX_DELAY)
    except (TypeError, ValueError):
        bad = True
    if bad:
        raise ValueError(f"model {name!r}: delay must be a whole number of samples from 0 to {MAX_DELAY}, not {delay!r}")


@dataclasses.dataclass(frozen=True)
class Model:
    """A flat composition of effects with a delay of ``delay`` samples."""

    effects: tuple[Effect, ...]
    delay: Any = 4
    name: str = ""
    sampling_period_s: float = SAMPLING_PERIOD_S

    def __post_init__(self) -> None:
        object.__setattr__(self, "effects", tuple(self.effects))
        kinds = [e.kind for e in self.effects]
        if kinds.count("activation") != 1:
            raise ValueError(f"model {self.name!r} needs exactly one activation effect, has {kinds.count('activation')}")
        if kinds.count("delay") > 1:
            raise ValueError(f"model {self.name!r} has more than one delay effect")
        names = [e.name for e in self.effects]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"model {self.name!r} lists effect(s) {sorted(dup)} twice")
        pnames = [p.name for e in self.effects for p in e.declared_params()]
        clash = {n for n in pnames if pnames.count(n) > 1}
        if clash:
            raise ValueError(f"model {self.name!r}: parameter name(s) {sorted(clash)} declared by two effects")
        _check_delay(self.delay, self.name)
        period = self.sampling_period_s
        if not isinstance(period, jax.core.Tracer) and not (np.isfinite(period) and 0 < period <= MAX_SAMPLING_PERIOD_S):
            raise ValueError(f"model {self.name!r}: sampling_period_s must be a period in seconds, above 0 and at most "
                             f"{MAX_SAMPLING_PERIOD_S:g}, not {period!r}")

    # ------------------------------------------------------------------ structure
    @property
    def activation(self) -> Effect:
        return next(e for e in self.effects if e.kind == "activation")

    @property
    def gains(self) -> tuple[Effect, ...]:
        return tuple(e for e in self.effects if e.kind == "gain")

    @property
    def pulses(self) -> tuple[Effect, ...]:
        return tuple(e for e in self.effects if e.kind == "pulse")

    @property
    def passives(self) -> tuple[Effect, ...]:
        return tuple(e for e in self.effects if e.kind == "passive")

    @property
    def outputs(self) -> tuple[Effect, ...]:
        return tuple(e for e in self.effects if e.kind == "output")

    @property
    def measurements(self) -> tuple[Effect, ...]:
        return tuple(e for e in self.effects if e.kind == "measurement")

    @property
    def noises(self) -> tuple[Effect, ...]:
        return tuple(e for e in self.effects if e.kind == "noise")

    @property
    def delay_effect(self) -> Effect | None:
        return next((e for e in self.effects if e.kind == "delay"), None)

    def effect(self, name: str) -> Effect:
        for e in self.effects:
            if e.name == name:
                return e
        raise KeyError(f"model {self.name!r} has no effect {name!r}; it has {[e.name for e in self.effects]}")

    # ------------------------------------------------------------------ parameters
    def params(self) -> dict[str, Any]:
        """All parameter values by (model-unique) name."""
        out: dict[str, Any] = {}
        for e in self.effects:
            out.update(e.values())
        return out

    def with_params(self, values: Mapping[str, Any] | None = None, *, delay=None, **kw) -> Model:
        """A copy with some parameters (by name) and/or the delay replaced."""
        values = dict(values or {}, **kw)
        remaining = dict(values)
        effects = []
        for e in self.effects:
            mine = {p.name: remaining.pop(p.name) for p in e.declared_params() if p.name in remaining}
            effects.append(e.with_values(**mine) if mine else e)
        if remaining:
            raise KeyError(f"model {self.name!r} has no parameter(s) {sorted(remaining)}; it has {sorted(self.params())}")
        return dataclasses.replace(self, effects=tuple(effects), delay=self.delay if delay is None else delay)

    def with_delay_shift(self, shift) -> Model:
        """A copy whose delay effect shortens the delay by ``shift`` samples where it applies."""
        eff = self.delay_effect
        if eff is None:
            raise ValueError(f"model {self.name!r} has no delay effect to shift")
        effects = tuple(dataclasses.replace(e, shift=shift) if e is eff else e for e in self.effects)
        return dataclasses.replace(self, effects=effects)

    def at_period(self, sampling_period_s: float) -> Model:
        """A copy that runs at ``sampling_period_s`` [s]: the data's, which the model must match."""
        return dataclasses.replace(self, sampling_period_s=float(sampling_period_s))

    def check_period(self, sampling_period_s: float, where: str) -> None:
        """A ``ValueError`` when data sampled at ``sampling_period_s`` (``where``: which data) do
        not match the model's period: its delays, horizons and dynamics are in samples."""
        if abs(sampling_period_s - self.sampling_period_s) > SAME_PERIOD_REL * self.sampling_period_s:
            raise ValueError(
                f"{where} is sampled every {sampling_period_s * 1000:g} ms, but model {self.name!r} runs at "
                f"{self.sampling_period_s * 1000:g} ms: build the model at the data's period (Model.at_period)"
            )

    def add(self, *effects: Effect | str, name: str | None = None) -> Model:
        """A copy with further effects (instances, or registered names with default values).

        An added effect takes the place of the effects it ``replaces`` (a
        torque–angle relation with a maximum replaces the linear one).  The copy is named
        ``name``, by default this model's name and the added effects' (``model3+fatigue``), as
        :func:`build_model` names it: results are keyed by model name.
        """
        new = tuple(get_effect(e)() if isinstance(e, str) else e for e in effects)
        gone = {r for e in new for r in e.replaces}
        kept = tuple(e for e in self.effects if e.name not in gone)
        name = name or "+".join((self.name, *(e.name for e in new)))
        return dataclasses.replace(self, effects=kept + new, name=name)

    def describe(self) -> dict:
        """A JSON-able description of the structure (effects, parameters, units, priors, levels)."""
        return {
            "name": self.name,
            "delay_samples": _to_py(self.delay),
            "sampling_period_s": self.sampling_period_s,
            "effects": [
                {
                    "name": e.name,
                    "kind": e.kind,
                    "class": type(e).__name__,
                    "params": [
                        {
                            "name": p.name,
                            "units": p.units,
                            "support": p.support,
                            "prior": list(p.prior),
                            "level": p.level,
                            "shape": list(p.shape),
                            "value": _to_py(getattr(e, p.name)),
                        }
                        for p in e.declared_params()
                    ],
                }
                for e in self.effects
            ],
        }

    def flat_params(self) -> dict[str, float]:
        """Parameters as plain floats, vectors spread as a1, a2, ... (for tables and JSON)."""
        out = {}
        for name, v in self.params().items():
            arr = np.asarray(v, dtype=float)
            if arr.ndim == 0:
                out[name] = float(arr)
            else:
                for i, x in enumerate(arr.ravel(), start=1):
                    out[f"{name}{i}"] = float(x)
        return out


def _to_py(v):
    arr = np.asarray(v)
    return arr.item() if arr.ndim == 0 else arr.tolist()


register_pytree(Model, ["effects", "delay"], ["name", "sampling_period_s"])


# ====================================================================== the paper's models


def passive_effects(damping=1.0, gravity=1800.0, k1=25.0, k2=0.05, gravity_angle=None) -> tuple[Effect, ...]:
    """The passive system of eqs. (6)–(8) as three effects; with ``gravity_angle`` [deg], gravity
    acts about that angle (``gravity_offset`` in place of ``gravity``)."""
    g = Gravity(gravity) if gravity_angle is None else GravityOffset(gravity, gravity_angle)
    return (Damping(damping), g, ExponentialElasticity(k1, k2))


def paper_model(
    number: int | str, passive: tuple[Effect, ...] | None = None, delay=4, sampling_period_s: float = SAMPLING_PERIOD_S
) -> Model:
    """Model 1, 2 or 3 of the paper (eqs. 3–5) as a composition of effects, or ``model3s``
    (model 3's gain factors scaling model 2's DARMA twitch at its onset), running at
    ``sampling_period_s`` (the paper's 10 ms by default; the data's in every command)."""
    key = str(number).removeprefix("model")
    passive = passive_effects() if passive is None else tuple(passive)
    if key == "1":
        active = (ZeroOrderActivation(),)
    elif key == "2":
        active = (Darma(a=jnp.array([-1.46, 0.59]), b=jnp.array([480.0, 510.0])),)
    elif key == "3":
        active = (ZeroOrderActivation(), LinearTorqueAngle(), LinearTorqueVelocity())
    elif key == "3s":
        active = (Darma(a=jnp.array([-1.46, 0.59]), b=jnp.array([480.0, 510.0])), LinearTorqueAngle(), LinearTorqueVelocity())
    elif key == "passive":
        return Model((NoMuscle(),) + passive, delay=0, name="passive", sampling_period_s=float(sampling_period_s))
    else:
        raise ValueError(f"unknown model {number!r}; the models are model1, model2, model3 (the paper's), model3s "
                         "and passive (the pendulum alone)")
    return Model(active + passive, delay=delay, name=f"model{key}", sampling_period_s=float(sampling_period_s))


PAPER_MODELS = ("model1", "model2", "model3")
#: The paper's models and model3s: model 3's gain factors on model 2's shaped (DARMA) twitch,
#: the baseline of the modelling loop, whose likelihood sees a twitch's timing and its size.
MODELS = PAPER_MODELS + ("model3s",)
#: The models ``quadshank fit`` takes: those above and ``passive``, the pendulum alone (pendulum tests).
FIT_MODELS = MODELS + ("passive",)


# ====================================================================== one sample


class ActiveCarry(NamedTuple):
    """Everything but the passive state: input/angle history, pulse counters, effect states."""

    u_hist: Any  # (HISTORY,) u_hist[i] = u_{k-1-i} before sample k is processed (pulse effects applied)
    angle_hist: Any  # (HISTORY,) angles at the same samples
    activation: Any
    gains: tuple
    since_pulse_s: Any = 0.0  # time since the last pulse delivered [s]
    n_pulses: Any = 0.0  # pulses delivered so far in the trial
    time_s: Any = 0.0  # time in the trial at sample k [s]


def init_active(model: Model, dtype=jnp.float32) -> ActiveCarry:
    z = jnp.zeros(HISTORY, dtype)
    return ActiveCarry(
        z,
        z,
        model.activation.init_state(),
        tuple(g.init_state() for g in model.gains),
        jnp.asarray(FIRST_IPI_S, dtype),
        jnp.asarray(0.0, dtype),
        jnp.asarray(0.0, dtype),
    )


def pulse_factors(model: Model, pctx: PulseContext):
    """Π of the pulse effects' factors (1 without pulse effects)."""
    q = 1.0
    for e in model.pulses:
        q = q * e.pulse_factor(pctx)
    return q


def passive_acceleration(model: Model, angle, velocity):
    """The passive effects' angular acceleration [deg/s²] at ``angle`` and ``velocity``."""
    acc = 0.0
    for e in model.passives:
        acc = acc + e.acceleration(angle, velocity)
    return acc


def _active_step(model: Model, carry: ActiveCarry, u_now, angle, velocity):
    """Advance the active part by one sample; returns (carry, M_k/I)."""
    dt = model.sampling_period_s
    pulse = u_now > 0
    since = carry.since_pulse_s
    if model.pulses:
        pctx = PulseContext(u=u_now, ipi_s=since, count=carry.n_pulses, time_s=carry.time_s, angle=angle, velocity=velocity)
        u_now = jnp.where(pulse, u_now * pulse_factors(model, pctx), 0.0)
    since = jnp.where(pulse, dt, since + dt)
    counters = dict(since_pulse_s=since, n_pulses=carry.n_pulses + pulse, time_s=carry.time_s + dt)
    u_hist = jnp.concatenate([jnp.reshape(u_now, (1,)).astype(carry.u_hist.dtype), carry.u_hist[:-1]])
    angle_hist = jnp.concatenate([jnp.reshape(angle, (1,)).astype(carry.angle_hist.dtype), carry.angle_hist[:-1]])
    d = jnp.asarray(model.delay)
    delay_effect = model.delay_effect
    if delay_effect is None:
        u_del = u_hist[d]
    else:
        u_del = delay_effect.select(d, u_hist, angle_hist)
    ctx = StepContext(angle=angle, velocity=velocity, u=u_del, u_now=u_now)
    gain_states = []
    for g, s in zip(model.gains, carry.gains):
        s, f = g.gain(s, ctx)
        gain_states.append(s)
        u_del = u_del * f
    act_state, m = model.activation.step(carry.activation, u_del)
    for o in model.outputs:
        m = m * o.output_factor(ctx)
    carry = ActiveCarry(u_hist, angle_hist, act_state, tuple(gain_states), **counters)
    return carry, m


def _rk4(model: Model, angle, velocity, m, dt):
    def f(a, v):
        return v, m + passive_acceleration(model, a, v)

    k1a, k1v = f(angle, velocity)
    k2a, k2v = f(angle + 0.5 * dt * k1a, velocity + 0.5 * dt * k1v)
    k3a, k3v = f(angle + 0.5 * dt * k2a, velocity + 0.5 * dt * k2v)
    k4a, k4v = f(angle + dt * k3a, velocity + dt * k3v)
    angle = angle + dt / 6.0 * (k1a + 2 * k2a + 2 * k3a + k4a)
    velocity = velocity + dt / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
    return angle, velocity


# ====================================================================== whole-trial functions


def true_angle(model: Model, measured):
    """The shank's angle from the goniometer's reading (identity without measurement effects)."""
    for e in model.measurements:
        measured = e.true_angle(measured)
    return measured


def measured_angle(model: Model, true):
    """What the goniometer reads at the true angle ``true``."""
    for e in reversed(model.measurements):
        true = e.measured_angle(true)
    return true


def acceleration_response(model: Model):
    """Impulse response (unit sum) of the accelerometer chain, or None for a perfect one."""
    g = None
    for e in model.measurements:
        h = e.acceleration_response(model.sampling_period_s)
        if h is not None:
            g = h if g is None else causal_fir(jnp.concatenate([g, jnp.zeros(h.shape[0] - 1, g.dtype)]), h)
    return g


def measured_acceleration(model: Model, acceleration, axis: int = -1):
    """The accelerometer's reading of the angular acceleration ``acceleration`` (causal filter along ``axis``)."""
    g = acceleration_response(model)
    if g is None:
        return acceleration
    return jnp.moveaxis(causal_fir(jnp.moveaxis(jnp.asarray(acceleration), axis, -1), g), -1, axis)


def causal_fir(x, g):
    """y_k = Σ_j g_j x_{k−j} along the last axis (x_{<0} = 0), as a sum of shifted copies:
    a short filter this way is cheaper to compile and differentiate than a convolution."""
    n, L = x.shape[-1], g.shape[0]
    xp = jnp.concatenate([jnp.zeros((*x.shape[:-1], L - 1), x.dtype), x], axis=-1)
    g = g.astype(x.dtype)
    return sum(g[j] * xp[..., L - 1 - j : L - 1 - j + n] for j in range(L))


def measure(model: Model, angle, velocity, m):
    """The sensors' view of a simulated trial (:func:`simulate_angles`'s true state and M/I):
    (measured angle, measured angular acceleration), both noise-free."""
    acc = m + passive_acceleration(model, angle, velocity)
    return measured_angle(model, angle), measured_acceleration(model, acc)


def equivalent_acceleration(model: Model, angle, velocity, acceleration, mask=None):
    """M/I by eq. (8): measured acceleration minus the passive system's contribution.

    ``angle`` is the goniometer's reading; with an accelerometer response the
    passive contribution is passed through it (the active output is compared
    through the same response), and ``mask`` (samples to keep) stops it from
    leaking out of padding.
    """
    passive = passive_acceleration(model, true_angle(model, angle), velocity)
    if acceleration_response(model) is not None:
        if mask is not None:
            passive = jnp.where(mask, passive, 0.0)
        passive = measured_acceleration(model, passive)
    return acceleration - passive


@jax.jit
def simulate_angles(model: Model, stimulation, angle0=0.0, velocity0=0.0):
    """Free-run simulation of the model driven by ``stimulation``; returns (angle, velocity, M/I).

    Outputs are at samples 0..N-1 (state at the start of each sample; M/I applied over it),
    the true state: :func:`measure` gives what the sensors read.
    """
    stimulation = jnp.asarray(stimulation)
    dt = model.sampling_period_s
    carry0 = init_active(model, stimulation.dtype)

    def body(c, u):
        active, a, v = c
        active, m = _active_step(model, active, u, a, v)
        a2, v2 = _rk4(model, a, v, m, dt)
        return (active, a2, v2), (a, v, m)

    a0 = jnp.asarray(angle0, stimulation.dtype)
    v0 = jnp.asarray(velocity0, stimulation.dtype)
    _, (angle, velocity, m) = jax.lax.scan(body, (carry0, a0, v0), stimulation)
    return angle, velocity, m


@jax.jit
def active_carries(model: Model, angle, velocity, stimulation) -> ActiveCarry:
    """The active part's carry before each sample, driven by the *measured* state.

    This is the paper's initialisation of the active part "on the basis of the
    previous simulation run": the run started one sample earlier from the
    measured state passes its active state on.  Returns an ActiveCarry whose
    leaves have a leading axis of length N (one carry per start sample).
    """
    return _carries(model, true_angle(model, jnp.asarray(angle)), velocity, stimulation)


def _carries(model: Model, angle, velocity, stimulation, begin=None, bound=None) -> ActiveCarry:
    """:func:`active_carries` on the true angle.  ``begin`` (bool per sample, optional): where the
    active part starts again from rest (a trial's first sample, where samples of several trials
    follow one another); ``bound``: applied to the carry after each step (e.g. to keep a filter
    made unstable by a trial step of an optimiser finite)."""
    stimulation = jnp.asarray(stimulation)
    rest = init_active(model, stimulation.dtype)

    def body(c, x):
        start, u, a, v = x
        if start is not None:
            c = jax.tree_util.tree_map(lambda r, ci: jnp.where(start, r, ci), rest, c)
        new, _ = _active_step(model, c, u, a, v)
        return (new if bound is None else bound(new)), c

    inputs = (None if begin is None else jnp.asarray(begin), stimulation, jnp.asarray(angle), jnp.asarray(velocity))
    _, carries = jax.lax.scan(body, rest, inputs)
    return carries


@jax.jit
def active_output(model: Model, angle, velocity, stimulation):
    """M_k/I at every sample with the active part driven by the *measured* state (one step ahead).

    The shank's own M/I, before any accelerometer response."""
    stimulation = jnp.asarray(stimulation)
    angle = true_angle(model, jnp.asarray(angle))

    def body(c, x):
        u, a, v = x
        return _active_step(model, c, u, a, v)

    _, m = jax.lax.scan(body, init_active(model, stimulation.dtype), (stimulation, jnp.asarray(angle), jnp.asarray(velocity)))
    return m


def predict_ahead(model: Model, angle, velocity, stimulation, starts, horizon: int = 100):
    """k-step-ahead angle predictions from each start, one rollout of ``horizon`` samples each.

    The passive part starts from the measured (angle, velocity) at the start
    sample; the active part from :func:`active_carries`; the actual stimulation
    drives the rollout.  Returns an array (len(starts), horizon) whose column
    j-1 is the predicted angle j samples after the start.  Vectorised over starts.
    """
    if not isinstance(starts, jax.core.Tracer):  # an index beyond the recording would be clamped to its end
        n, at = np.shape(stimulation)[0], np.asarray(starts)
        outside = at[(at < 0) | (at >= n)] if at.dtype.kind in "iu" else at
        if outside.size:
            raise ValueError(f"starts: {', '.join(map(str, outside[:5].tolist()))} lie outside the recording's "
                             f"samples 0..{n - 1} (or are not whole numbers)")
    return _predict_ahead(model, angle, velocity, stimulation, jnp.asarray(starts), horizon)


@functools.partial(jax.jit, static_argnames=("horizon",))
def _predict_ahead(model, angle, velocity, stimulation, starts, horizon):
    angle = true_angle(model, jnp.asarray(angle))
    velocity = jnp.asarray(velocity)
    stimulation = jnp.asarray(stimulation)
    carries = _carries(model, angle, velocity, stimulation)
    dt = model.sampling_period_s
    n = stimulation.shape[0]
    padded = jnp.concatenate([stimulation, jnp.zeros(horizon, stimulation.dtype)])
    windows = padded[starts[:, None] + jnp.arange(horizon)[None, :]]  # (S, horizon)
    carry0 = jax.tree_util.tree_map(lambda x: x[jnp.clip(starts, 0, n - 1)], carries)

    def one(active, a, v, us):
        def body(c, u):
            active, a, v = c
            active, m = _active_step(model, active, u, a, v)
            a, v = _rk4(model, a, v, m, dt)
            return (active, a, v), a

        _, pred = jax.lax.scan(body, (active, a, v), us)
        return pred

    return measured_angle(model, jax.vmap(one)(carry0, angle[starts], velocity[starts], windows))
