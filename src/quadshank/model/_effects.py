"""Effects: one physical mechanism each, declared as data, composed into models.

An effect is a small frozen dataclass whose fields are its parameter values.
It declares each parameter as a :class:`Param` (name, units, support, prior,
hierarchy level) and contributes to the dynamics through one pure method that
depends on its *kind*:

``activation``
    ``init_state()`` and ``step(state, u_delayed) -> (state, m)``: the activation
    dynamics, eq. (1), turning the delayed recruitment level into an equivalent
    acceleration ``m`` [deg/s²].  Exactly one per model.
``gain``
    ``factor(ctx) -> scalar``: a multiplicative modulation (torque–angle,
    torque–velocity, ...), eq. (2), of the input reaching the muscle at this
    sample, evaluated at the state at that instant: the twitch it starts is
    scaled as a whole by the state at its onset (for the zero-order activation
    of models 1 and 3 this is exactly eq. 5).
``pulse``
    ``pulse_factor(pctx) -> scalar``: a modulation of a pulse's twitch by what
    is known when it is delivered (:class:`PulseContext`: its recruitment
    level, the preceding interpulse interval, the pulses delivered before it
    in the trial, the time in the trial): fatigue, potentiation, a
    recruitment nonlinearity.
``passive``
    ``acceleration(angle, velocity) -> deg/s²``: a term of the passive system,
    eq. (8), added to the angular acceleration.
``output``
    ``output_factor(ctx) -> scalar``: a modulation of the active output M_k/I
    at every sample by the state at that sample (not at a twitch's onset):
    e.g. passive damping that grows with activation.
``measurement``
    how the sensors see the shank: ``true_angle(measured)`` and
    ``measured_angle(true)`` (a goniometer offset), and/or
    ``acceleration_response(dt)``, the impulse response (unit sum) through
    which the accelerometer sees the shank's angular acceleration (a
    skin-motion resonance).  The model's dynamics run on the true angle;
    predictions are compared with measurements through these.
``noise``
    no dynamics: a parameter of the likelihood's noise model that the
    hierarchical fit pools like any other (``twitch_variability``: a random
    gain per pulse).  The likelihood reads it (:mod:`quadshank.model._likelihood`);
    predictions do not.
``delay``
    ``select(d, u_hist, angle_hist) -> u``: how the pulses delivered up to ``d``
    samples ago reach the muscle (default: exactly ``d`` samples; at most one
    per model).  ``u_hist[j]`` and ``angle_hist[j]`` are the recruitment level
    and angle ``j`` samples ago.  A delay effect may shorten the delay by up to
    ``max_shift`` samples for some pulses; ``pulse_weight(angle)`` in [0, 1] is
    the share of a pulse delivered at ``angle`` that takes the shorter delay,
    and its integer field ``shift`` (a discrete leaf, listed in the class
    attribute ``discrete``) is summed out by the hierarchical fit like d.

Two class attributes serve the modelling loop (:mod:`quadshank.loop._diagnose`):
``replaces`` names effects this one generalises (a torque–angle relation with
a maximum replaces the linear one when it is added to a model), and
``signature`` names the residual feature where its absence shows (``angle``,
``velocity``, ``ipi``, ``pulse_count``, ``time``, ``onset``, ``u``,
``frequency``).  ``predicts_angle = False`` marks an effect that changes only
what the accelerometer reads, or only the noise, so it cannot change an
angle prediction.
``acts_at_ms`` names the prediction horizons at which the loop judges the
effect's change of J_φ,p: where it acts (a delay within the first 100–250 ms
of a prediction; a change of gain or of the passive system over a second).

Writing a new effect is a few lines::

    @register_effect
    @dataclasses.dataclass(frozen=True)
    class CubicTorqueAngle(Effect):
        kind = "gain"
        name = "cubic_torque_angle"
        params = (Param("c3", "1/deg^3", prior=("normal", 0.0, 1e-6)),)
        c3: float = 0.0

        def factor(self, ctx):
            return 1.0 + self.c3 * ctx.angle**3

``register_effect`` makes the class a JAX pytree whose leaves are the declared
parameters (so models can be jitted, differentiated and vmapped over parameter
draws) and lists it in the registry by ``name``.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..common._arrays import is_whole_number
from ..data._paper import HORIZONS_MS

__all__ = [
    "prior_arrays",
    "from_standard",
    "to_standard",
    "from_unconstrained",
    "sin_deg",
    "Param",
    "Effect",
    "StepContext",
    "register_effect",
    "registered_effects",
    "check_contribution",
    "CONTRIBUTIONS",
    "user_effects",
    "get_effect",
    "ZeroOrderActivation",
    "Darma",
    "LinearTorqueAngle",
    "LinearTorqueVelocity",
    "Damping",
    "Gravity",
    "ExponentialElasticity",
    "AngleDelay",
    "PulseContext",
    "PeakTorqueAngle",
    "HillTorqueVelocity",
    "Fatigue",
    "Potentiation",
    "RecruitmentPower",
    "FractionalDelay",
    "ActivationDamping",
    "GoniometerOffset",
    "AccelResonance",
    "TwitchVariability",
]

LEVELS = ("population", "subject", "leg")
KINDS = ("activation", "gain", "pulse", "passive", "delay", "output", "measurement", "noise")
SUPPORTS = ("real", "positive", "negative", "unit_interval")


def prior_arrays(prior, shape=(), dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
    """(loc, scale) of a declared prior ``(family, loc, scale)``, broadcast to ``shape``."""
    return (np.broadcast_to(np.asarray(prior[1], dtype), shape), np.broadcast_to(np.asarray(prior[2], dtype), shape))


def from_unconstrained(x, prior, xp=np):
    """A value from its unconstrained form: exp(x) for a log-normal prior, x itself for a normal one."""
    return xp.exp(x) if prior[0] == "lognormal" else x


def from_standard(z, prior, shape=(), *, xp=np, dtype=np.float64, flat: bool = False):
    """The value ``z`` prior scales from the prior's centre: g⁻¹(loc + scale·z), g = log for a
    log-normal prior.  ``flat``: the components (of a vector parameter) lie flattened on z's last axis.

    This standardisation is the one every stage uses: the fit samples z, the screen optimises
    it, starts and reports are stated in it.
    """
    loc, scale = prior_arrays(prior, shape, dtype)
    if flat:
        loc, scale = loc.reshape(-1), scale.reshape(-1)
    return from_unconstrained(loc + scale * z, prior, xp)


def to_standard(x, prior, shape=(), dtype=np.float64) -> np.ndarray:
    """The inverse of :func:`from_standard`: (g(x) − loc)/scale (−∞ for x ≤ 0 under a log-normal prior)."""
    loc, scale = prior_arrays(prior, shape, dtype)
    x = np.asarray(x, dtype)
    if prior[0] == "lognormal":
        with np.errstate(divide="ignore", invalid="ignore"):
            x = np.where(x > 0, np.log(np.where(x > 0, x, 1.0)), -np.inf)
    return (x - loc) / scale


@dataclasses.dataclass(frozen=True)
class Param:
    """Declaration of one parameter of an effect.

    ``prior`` is a tuple ``(family, *args)`` with family one of ``normal``
    (loc, scale) or ``lognormal`` (loc and scale of the log); it describes the
    population-level belief in the parameter's own units; for a vector
    parameter loc and scale may be tuples, one entry per component.  ``shape``
    is ``()`` for a scalar, or a tuple for a vector parameter.  The hierarchical
    fit (:mod:`quadshank.inference._nuts`) turns each declaration into population, subject
    and leg levels down to ``level``.
    """

    name: str
    units: str
    support: str = "real"
    prior: tuple = ("normal", 0.0, 1.0)
    level: str = "leg"
    doc: str = ""
    shape: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.isidentifier():
            raise ValueError(f"parameter {self.name!r}: its name must be a Python identifier (a string)")
        if not isinstance(self.units, str):
            raise ValueError(f"parameter {self.name!r}: units must be a string ('' for none), not {self.units!r}")
        if not isinstance(self.shape, tuple) or any(
                not is_whole_number(n) or n < 1 for n in self.shape):
            raise ValueError(f"parameter {self.name!r}: shape {self.shape!r} must be () or a tuple of sizes of at least 1")
        if self.level not in LEVELS:
            raise ValueError(f"parameter {self.name!r}: level {self.level!r} not in {LEVELS}")
        if self.support not in SUPPORTS:
            raise ValueError(f"parameter {self.name!r}: support {self.support!r} not in {SUPPORTS}")
        if not isinstance(self.prior, tuple) or not self.prior or self.prior[0] not in ("normal", "lognormal"):
            raise ValueError(f"parameter {self.name!r}: prior {self.prior!r} is not ('normal' or 'lognormal', "
                             "location, scale)")
        args = self.prior[1:]
        try:  # a number each, or one per component of a vector parameter
            loc, scale = (np.asarray(a, dtype=float) for a in args) if len(args) == 2 else (None, None)
        except (TypeError, ValueError):
            loc = scale = None
        if loc is None or not (np.all(np.isfinite(loc)) and np.all(np.isfinite(scale)) and np.all(scale > 0)):
            raise ValueError(f"parameter {self.name!r}: prior {self.prior!r} must be ({self.prior[0]!r}, location, scale) "
                             "with finite numbers and a positive scale")
        size = int(np.prod(self.shape))
        if any(np.size(a) not in (1, size) for a in (loc, scale)):
            raise ValueError(f"parameter {self.name!r}: prior {self.prior!r} gives {max(np.size(loc), np.size(scale))} "
                             f"components for a parameter of shape {self.shape}")
        if self.prior[0] == "lognormal" and self.support != "positive":
            raise ValueError(f"parameter {self.name!r}: a lognormal prior draws positive values only, and its support "
                             f"is {self.support!r}; declare support='positive' or a normal prior")

    def from_standard(self, z, *, xp=np, dtype=np.float64, flat: bool = False):
        """:func:`from_standard` with this parameter's prior and shape."""
        return from_standard(z, self.prior, self.shape, xp=xp, dtype=dtype, flat=flat)

    def to_standard(self, x, dtype=np.float64) -> np.ndarray:
        """:func:`to_standard` with this parameter's prior and shape."""
        return to_standard(x, self.prior, self.shape, dtype)


class StepContext(NamedTuple):
    """What an effect sees at one sample: the state at the start of the sample."""

    angle: Any  # deg
    velocity: Any  # deg/s
    u: Any  # delayed recruitment level reaching the muscle at this sample
    u_now: Any  # recruitment level of the pulse delivered at this sample


class PulseContext(NamedTuple):
    """What a pulse effect sees when a pulse is delivered."""

    u: Any  # recruitment level of the pulse
    ipi_s: Any  # time since the preceding pulse of the trial [s] (large for the first)
    count: Any  # pulses delivered before this one in the trial
    time_s: Any  # time in the trial [s]
    angle: Any  # deg, at delivery
    velocity: Any  # deg/s, at delivery


#: ``PulseContext.ipi_s`` of a trial's first pulse [s].
FIRST_IPI_S = 100.0


class Effect:
    """Base of all effects.  Subclasses are frozen dataclasses; see module docs."""

    kind: ClassVar[str] = ""
    name: ClassVar[str] = ""
    params: ClassVar[tuple[Param, ...]] = ()
    #: Effects this one generalises and takes the place of when added to a model.
    replaces: ClassVar[tuple[str, ...]] = ()
    #: The residual feature where this effect's absence shows (see module docs).
    signature: ClassVar[str] = ""
    #: Offered as a candidate by the modelling loop's ranking.
    candidate: ClassVar[bool] = True
    #: False for an effect on the acceleration channel only: it cannot change an angle prediction.
    predicts_angle: ClassVar[bool] = True
    #: Prediction horizons [ms] at which the modelling loop judges the effect's change of J: where it acts.
    acts_at_ms: ClassVar[tuple[int, ...]] = (500, 1000)
    #: Activation effects only: "sample" when the effect describes the twitch's
    #: shape, "twitch" when only its integral (see :mod:`quadshank.model._likelihood`).
    resolution: ClassVar[str] = "sample"
    #: Activation effects only: samples of the impulse response the likelihood keeps.
    response_length: ClassVar[int] = 40

    # --- introspection ------------------------------------------------------------
    def declared_params(self) -> tuple[Param, ...]:
        return self.params

    def values(self) -> dict[str, Any]:
        return {p.name: getattr(self, p.name) for p in self.declared_params()}

    def with_values(self, **values) -> Effect:
        unknown = set(values) - {p.name for p in self.declared_params()}
        if unknown:
            raise KeyError(f"effect {self.name!r} has no parameter(s) {sorted(unknown)}")
        return dataclasses.replace(self, **values)

    # --- defaults for the kinds -----------------------------------------------------
    def init_state(self):
        return ()

    def gain(self, state, ctx: StepContext):
        return state, self.factor(ctx)

    def factor(self, ctx: StepContext):  # pragma: no cover - abstract for gains
        raise NotImplementedError(f"gain effect {self.name!r} must define factor() or gain()")

    def pulse_factor(self, pctx: PulseContext):  # pragma: no cover - abstract for pulse effects
        raise NotImplementedError(f"pulse effect {self.name!r} must define pulse_factor()")

    def output_factor(self, ctx: StepContext):  # pragma: no cover - abstract for output effects
        raise NotImplementedError(f"output effect {self.name!r} must define output_factor()")

    # measurement effects: identity unless overridden
    def true_angle(self, measured):
        return measured

    def measured_angle(self, true):
        return true

    def acceleration_response(self, dt: float):
        """Impulse response of the accelerometer chain (unit sum), or None for a perfect accelerometer."""
        return None

    def pulse_variance(self):  # pragma: no cover - abstract for noise effects
        """Noise effects: the variance of a pulse's random gain relative to its mean (CV²)."""
        raise NotImplementedError(f"noise effect {self.name!r} must define pulse_variance()")


_REGISTRY: dict[str, type[Effect]] = {}


def register_effect(cls: type[Effect]) -> type[Effect]:
    """Register an effect class: a JAX pytree over its declared parameters, listed by name."""
    if not dataclasses.is_dataclass(cls) or not cls.__dataclass_params__.frozen:
        raise TypeError(f"{cls.__name__} must be a frozen dataclass (decorate with @dataclasses.dataclass(frozen=True))")
    if cls.kind not in KINDS:
        raise TypeError(f"{cls.__name__}.kind must be one of {', '.join(KINDS)}, not {cls.kind!r}")
    if not cls.name:
        raise TypeError(f"{cls.__name__} needs a class attribute 'name'")
    fields = [f.name for f in dataclasses.fields(cls)]
    param_names = [p.name for p in cls.params]
    twice = sorted({n for n in param_names if param_names.count(n) > 1})
    if twice:
        raise TypeError(f"{cls.__name__}: parameter(s) {twice} declared twice")
    missing = [n for n in param_names if n not in fields]
    if missing:
        raise TypeError(f"{cls.__name__}: declared parameters {missing} are not dataclass fields")
    if not cls.acts_at_ms or not set(cls.acts_at_ms) <= set(HORIZONS_MS):
        raise TypeError(f"{cls.__name__}.acts_at_ms must name some of the horizons {HORIZONS_MS} [ms], "
                        f"not {cls.acts_at_ms!r}")
    builtin = _REGISTRY.get(cls.name)
    if builtin is not None and builtin.__module__ == __name__ and cls.__module__ != __name__:
        raise TypeError(f"{cls.__name__}: the name {cls.name!r} is a built-in effect's; give the effect a name of its own")
    if builtin is not None and (builtin.__module__, builtin.__qualname__) != (cls.__module__, cls.__qualname__):
        warnings.warn(f"effect {cls.name!r}: {cls.__module__}.{cls.__qualname__} replaces {builtin.__module__}."
                      f"{builtin.__qualname__}, registered under that name before", stacklevel=2)
    if cls.__module__ != __name__:  # the built-ins are checked by the tests
        check_contribution(cls)
    discrete = list(getattr(cls, "discrete", ()))
    meta = [n for n in fields if n not in param_names and n not in discrete]
    register_pytree(cls, param_names + discrete, meta)
    _REGISTRY[cls.name] = cls
    return cls


def user_effects(effects) -> list[str]:
    """The names of those of ``effects`` (instances) that are not quadshank's own: where a model's
    numbers are not finite, the first place a user's effect would be looked for."""
    return [e.name for e in effects if type(e).__module__.split(".")[0] != "quadshank"]


#: The method through which each kind of effect contributes, given the state at a sample (or a pulse).
CONTRIBUTIONS = {"gain": "factor", "pulse": "pulse_factor", "passive": "acceleration", "output": "output_factor"}


def check_contribution(cls: type[Effect]) -> None:
    """Refuse an effect class whose contribution (:data:`CONTRIBUTIONS`) is missing, or returns
    another shape than one value per sample it is given: the models call it on one sample (shape
    ``()``) and the likelihood on every sample at once (shape ``(n,)``), and a wrong shape would
    surface as a message from deep inside JAX.  Traced abstractly (``jax.eval_shape``) at the class's
    default values; a class without defaults for every field, or whose method cannot be traced
    at them, is left to fail where it is used."""
    method = CONTRIBUTIONS.get(cls.kind)
    if method is None or (cls.kind == "gain" and cls.gain is not Effect.gain):  # a stateful gain defines gain()
        return
    try:
        effect = cls()
    except TypeError:
        return
    for shape in ((), (5,)):
        x = jax.ShapeDtypeStruct(shape, jnp.float32)
        args = {"passive": (x, x), "pulse": (PulseContext(x, x, x, x, x, x),)}.get(cls.kind, (StepContext(x, x, x, x),))
        try:
            out = jax.eval_shape(getattr(effect, method), *args)
        except NotImplementedError as e:
            raise TypeError(f"{cls.__name__}: {e}") from None
        except Exception:  # noqa: BLE001 - not judged here: the fit or the prediction will name it
            return
        try:
            fits = hasattr(out, "shape") and np.broadcast_shapes(tuple(out.shape), shape) == shape
        except ValueError:
            fits = False
        if not fits:
            raise TypeError(f"{cls.__name__}.{method}() must return one value per sample it is given (shape {shape} "
                            f"for inputs of shape {shape}), not {getattr(out, 'shape', out)}: it is called on one "
                            "sample in a prediction and on every sample at once in the likelihood")


def register_pytree(cls: type, data: list[str], meta: list[str]) -> None:
    """Make the frozen dataclass ``cls`` a JAX pytree: leaves ``data``, static ``meta``.

    A custom node, not ``jax.tree_util.register_dataclass``: with that, the tree
    structures of two dataclasses with the same number of leaves compare equal
    while their hashes differ, so jit's cache could (by chance of the hash, once
    in a few processes) run the program compiled for another effect.
    """

    def flatten(obj):
        return [getattr(obj, n) for n in data], tuple(getattr(obj, n) for n in meta)

    def flatten_with_keys(obj):
        return [(jax.tree_util.GetAttrKey(n), getattr(obj, n)) for n in data], tuple(getattr(obj, n) for n in meta)

    def unflatten(aux, children):
        obj = object.__new__(cls)  # leaves may be tracers or None: no __init__ checks
        for n, v in zip(data, children):
            object.__setattr__(obj, n, v)
        for n, v in zip(meta, aux):
            object.__setattr__(obj, n, v)
        return obj

    jax.tree_util.register_pytree_with_keys(cls, flatten_with_keys, unflatten, flatten)


def registered_effects() -> dict[str, type[Effect]]:
    """Every registered effect class by name: the built-in ones and those a user registered."""
    return dict(_REGISTRY)


def reads_sensor_only(effect: Effect | type[Effect]) -> bool:
    """Whether ``effect`` (an effect or its class) changes only what the accelerometer reads: a
    measurement effect that cannot change an angle prediction (``predicts_angle = False``)."""
    return effect.kind == "measurement" and not effect.predicts_angle


def get_effect(name: str) -> type[Effect]:
    """The registered effect class called ``name``; a ``KeyError`` naming the known effects otherwise."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown effect {name!r}; known effects: {', '.join(sorted(_REGISTRY))}") from None


# ==================================================================== activation


@register_effect
@dataclasses.dataclass(frozen=True)
class ZeroOrderActivation(Effect):
    """Zero-order activation, eqs. (3) and (5): M_k/I = gain · u_{k-d}.

    A pulse becomes one sample of equivalent acceleration, so ``gain`` is the
    integrated twitch response (G'_1 of model 1, G'_2 of model 3).
    """

    kind = "activation"
    name = "zero_order"
    candidate = False
    #: The likelihood compares it with data summed over each twitch window (see _likelihood).
    resolution = "twitch"
    #: Samples of the response to one pulse (its impulse response is one sample).
    response_length = 1
    params = (
        Param(
            "gain",
            "deg/s^2",
            support="positive",
            prior=("lognormal", math.log(1.0e4), 0.6),
            doc="integrated equivalent acceleration of one twitch (G'_1, G'_2); Tables I, III: 7e3-1.7e4",
        ),
    )
    gain: Any = 1.0e4

    def step(self, state, u):
        return state, self.gain * u


@register_effect
@dataclasses.dataclass(frozen=True)
class NoMuscle(Effect):
    """No active torque at all: the passive pendulum of eq. (8) alone (``paper_model("passive")``).

    The activation of a model fitted to pendulum tests, which hold no pulses: it has no
    parameters, so the fit samples the passive system only (its delay, summed out, stays the
    prior's and means nothing).
    """

    kind = "activation"
    name = "no_muscle"
    candidate = False
    response_length = 1
    params = ()

    def step(self, state, u):
        return state, 0.0 * u


@register_effect
@dataclasses.dataclass(frozen=True)
class Darma(Effect):
    """DARMA activation of order N, eqs. (1) and (4).

    M_k = -Σ_i a_i M_{k-i} + Σ_i b_i u_{k-i-d}; the state holds the last N
    outputs and the last N delayed inputs.  Table II (N = 2): a ≈ (-1.46, 0.59),
    b ≈ (480, 510) deg/s².
    """

    kind = "activation"
    name = "darma"
    candidate = False
    #: Its twitch has a shape, so the likelihood compares it with every sample.
    resolution = "sample"
    #: Samples of the impulse response kept (poles near 0.77: 0.77**40 < 1e-4).
    response_length = 40
    params = (
        Param(
            "a",
            "1",
            prior=("normal", (-1.46, 0.59), (0.2, 0.1)),
            doc="autoregressive coefficients a_1..a_N; Table II: a_1 -1.50..-1.41, a_2 0.55..0.61",
            shape=(2,),
        ),
        Param(
            "b",
            "deg/s^2",
            prior=("normal", (500.0, 500.0), (300.0, 300.0)),
            doc="moving-average coefficients b'_1..b'_N; Table II: 3.2e2..6.5e2",
            shape=(2,),
        ),
    )
    a: Any = (-1.46, 0.59)
    b: Any = (480.0, 510.0)

    def declared_params(self):
        n = self.order
        if n == 2:
            return self.params
        # other orders: a weakly informative prior per coefficient
        generic = {"a": ((0.0,) * n, (0.5,) * n), "b": ((300.0,) * n, (300.0,) * n)}
        return tuple(
            dataclasses.replace(p, shape=(n,), prior=(p.prior[0], *generic[p.name])) for p in self.params
        )

    @property
    def order(self) -> int:
        return len(self.a) if isinstance(self.a, (tuple, list)) else int(jnp.shape(self.a)[-1])

    def init_state(self):
        z = jnp.zeros(self.order)
        return (z, z)

    def step(self, state, u):
        m_hist, u_hist = state  # m_hist[i] = M_{k-1-i}, u_hist[i] = u_{k-1-i-d}
        a = jnp.asarray(self.a)
        b = jnp.asarray(self.b)
        m = -jnp.dot(a, m_hist) + jnp.dot(b, u_hist)
        m_hist = jnp.concatenate([jnp.reshape(m, (1,)), m_hist[:-1]])
        u_hist = jnp.concatenate([jnp.reshape(jnp.asarray(u, m_hist.dtype), (1,)), u_hist[:-1]])
        return (m_hist, u_hist), m


# ==================================================================== gains


@register_effect
@dataclasses.dataclass(frozen=True)
class LinearTorqueAngle(Effect):
    """Linear torque–angle factor of model 3, eq. (5): 1 + γ_angle·φ."""

    kind = "gain"
    name = "linear_torque_angle"
    signature = "angle"
    params = (
        Param(
            "gamma_angle",
            "1/deg",
            prior=("normal", -1.0e-2, 1.0e-2),
            doc="Table III: -2.2e-2 to -5.3e-3",
        ),
    )
    gamma_angle: Any = -1.0e-2

    def factor(self, ctx):
        return 1.0 + self.gamma_angle * ctx.angle


@register_effect
@dataclasses.dataclass(frozen=True)
class LinearTorqueVelocity(Effect):
    """Linear torque–velocity factor of model 3, eq. (5): 1 + γ_velocity·φ̇."""

    kind = "gain"
    name = "linear_torque_velocity"
    signature = "velocity"
    params = (
        Param(
            "gamma_velocity",
            "s/deg",
            prior=("normal", -2.0e-3, 1.0e-3),
            doc="Table III: -2.5e-3 to -1.6e-3",
        ),
    )
    gamma_velocity: Any = -2.0e-3

    def factor(self, ctx):
        return 1.0 + self.gamma_velocity * ctx.velocity


# ==================================================================== passive


@register_effect
@dataclasses.dataclass(frozen=True)
class Damping(Effect):
    """Viscous damping in the knee, eq. (8): -D'·φ̇."""

    kind = "passive"
    name = "damping"
    candidate = False
    params = (
        Param("damping", "1/s", support="positive", prior=("lognormal", math.log(1.0), 0.5), doc="D' = D/I"),
    )
    damping: Any = 1.0

    def acceleration(self, angle, velocity):
        return -self.damping * velocity


@register_effect
@dataclasses.dataclass(frozen=True)
class Gravity(Effect):
    """Gravity on the shank as a pendulum, eq. (8): -G'·sin φ (φ in degrees)."""

    kind = "passive"
    name = "gravity"
    candidate = False
    params = (
        Param(
            "gravity",
            "deg/s^2",
            support="positive",
            prior=("lognormal", math.log(1800.0), 0.2),
            doc="G' = G/I; natural frequency sqrt(G'·π/180)/(2π) ≈ 0.8-1 Hz",
        ),
    )
    gravity: Any = 1800.0

    def acceleration(self, angle, velocity):
        return -self.gravity * sin_deg(angle)


#: Taylor coefficients of sin(r)/r − 1 in r², highest first: on |r| ≤ π/2 the remainder is below 1e-9.
_SIN_TAYLOR = tuple(float((-1) ** n / math.factorial(2 * n + 1)) for n in range(6, 0, -1))


def sin_deg(angle):
    """sin of an angle in degrees.

    In single precision (the rollouts of J_φ,p) XLA's CPU sine costs about as
    much as the rest of an RK4 step of the pendulum together, so there the angle
    is reduced to r = angle − 180°·k in [−90°, 90°] (exact in float32 below
    2²⁴°), turned into radians with one rounding, and sin r = r(1 + r²·P(r²))
    with P the Taylor polynomial of degree 12 in r (remainder < 1e-9), times
    (−1)^k.  Its error is no larger than that of ``jnp.sin(jnp.deg2rad(angle))``
    in float32 (``tests/test_effects.py`` checks both against float64), and
    round's zero derivative leaves its gradient the cosine.  Other precisions
    (the fit samples in float64) use ``jnp.sin`` as it is.
    """
    angle = jnp.asarray(angle)
    if angle.dtype != jnp.float32:
        return jnp.sin(jnp.deg2rad(angle))
    k = jnp.round(angle * (1.0 / 180.0))
    r = (angle - 180.0 * k) * (math.pi / 180.0)
    r2 = r * r
    poly = 0.0
    for c in _SIN_TAYLOR:
        poly = (poly + c) * r2
    odd = k - 2.0 * jnp.floor(0.5 * k)  # k mod 2
    return (1.0 - 2.0 * odd) * (r + r * poly)


@register_effect
@dataclasses.dataclass(frozen=True)
class ExponentialElasticity(Effect):
    """Passive elasticity significant in flexion, eq. (8): k1'·(exp(-k2·φ) - 1)."""

    kind = "passive"
    name = "elasticity"
    candidate = False
    params = (
        Param("k1", "deg/s^2", support="positive", prior=("lognormal", math.log(25.0), 0.8), doc="k1' = k1/I"),
        Param("k2", "1/deg", support="positive", prior=("lognormal", math.log(0.05), 0.4)),
    )
    k1: Any = 25.0
    k2: Any = 0.05

    def acceleration(self, angle, velocity):
        return self.k1 * (jnp.exp(-self.k2 * angle) - 1.0)


# ==================================================================== delay


class TwoPathDelay(Effect):
    """A delay effect under which a share ``pulse_weight(angle)`` of each pulse takes
    delay d − shift and the rest delay d (``shift`` discrete, summed out by the fit).
    A change of delay moves a prediction's first few hundred milliseconds, and the loop
    judges it there."""

    kind = "delay"
    acts_at_ms = (100, 250)

    def pulse_weight(self, angle):  # pragma: no cover - abstract
        raise NotImplementedError

    def select(self, d, u_hist, angle_hist):
        short = jnp.maximum(d - jnp.asarray(self.shift), 0)
        w_long = 1.0 - self.pulse_weight(angle_hist[d])
        w_short = self.pulse_weight(angle_hist[short])
        return jnp.where(short == d, u_hist[d], u_hist[d] * w_long + u_hist[short] * w_short)


@register_effect
@dataclasses.dataclass(frozen=True)
class AngleDelay(TwoPathDelay):
    """A delay ``shift`` samples shorter for pulses delivered below ``threshold`` (section IV-C).

    The paper found the delay one sample (10 ms) shorter for knee angles below
    about −20° in all subjects ("the muscle must first take up slack" at short
    lengths is its explanation for the longer delay near extension).  A pulse
    delivered at angle φ takes delay d − shift with weight
    w(φ) = σ((threshold − φ)/softness_deg) and d with weight 1 − w: a step
    smoothed over a degree, so the threshold has a gradient for the screen's
    optimisation; ``softness_deg=0`` is the hard step w = [φ < threshold].
    ``shift`` in 0 … max_shift is discrete and summed out with d by the fit;
    shift 0 is no angle dependence at all, so the posterior of shift says
    whether the delay changes, by how much, and the threshold where.

    The hierarchical fit sums the threshold out too (``step_param``), for the
    hard step: between two neighbouring pulse angles every threshold splits the
    pulses alike, so the likelihood is a staircase in the threshold, each stair
    weighted by its prior mass (see :mod:`quadshank.model._likelihood`).  Sampled,
    the staircase (smoothed over a degree) holds NUTS to steps a fraction of a
    degree long: 127 leapfrog steps per draw against 15 without the effect.
    """

    kind = "delay"
    name = "angle_delay"
    signature = "onset"
    #: Largest shortening considered [samples].
    max_shift = 2
    #: Width of the smoothed step [deg] by default: about the goniometer's noise and a pulse's angle uncertainty.
    SOFTNESS_DEG = 1.0
    discrete = ("shift",)
    #: The parameter at which the pulse weight steps, summed out by the hierarchical fit.
    step_param = "threshold"
    params = (
        Param(
            "threshold",
            "deg",
            prior=("normal", 0.0, 25.0),
            doc="knee angle below which the delay is shorter; section IV-C: about -20 deg; "
            "prior over the operating range (-40 to 60 deg), not centred on the paper's value",
        ),
    )
    threshold: Any = -20.0
    shift: Any = 1
    #: Width of the smoothed step [deg]; 0 for the hard step (static, not a parameter).
    softness_deg: float = SOFTNESS_DEG

    def pulse_weight(self, angle):
        """Share of a pulse delivered at ``angle`` that takes the shorter delay."""
        if self.softness_deg == 0:
            return (jnp.asarray(angle) < self.threshold).astype(jnp.result_type(float))
        return jax.nn.sigmoid((self.threshold - angle) / self.softness_deg)


@register_effect
@dataclasses.dataclass(frozen=True)
class FractionalDelay(TwoPathDelay):
    """A delay that need not be a whole number of samples: d − shift·fraction.

    The paper resolves the delay to T_s = 10 ms and names that resolution as a
    source of error.  The input reaching the muscle is interpolated linearly
    between u_{k−d} and u_{k−d+1}: a share ``fraction`` of each pulse takes
    delay d − 1, the rest d, so its twitch starts ``fraction`` of a sample
    earlier (to first order in the twitch's shape).  The modelling loop does
    not offer it on model3s, whose DARMA(2,2) numerator already moves a twitch
    by part of a sample (see ``candidate``).  ``shift`` ∈ {0, 1} is
    summed out with d: shift 0 is a whole-sample delay, so the posterior of
    shift says whether the data ask for a fractional part at all.
    """

    name = "fractional_delay"
    signature = "onset"
    #: Not offered by the loop: on a DARMA(2,2) twitch (model 2, model3s) a fraction w of a
    #: sample is a re-parametrisation of b (numerator b1·w, b1(1 − w) + b2·w, b2(1 − w)), so it
    #: can only matter with a twitch whose shape cannot shift (e.g. a first-order DARMA).
    candidate = False
    max_shift = 1
    discrete = ("shift",)
    params = (
        Param(
            "fraction",
            "samples",
            prior=("normal", 0.5, 0.3),
            doc="part of a sample by which the delay is shorter than d; used clipped to [0, 1]",
        ),
    )
    fraction: Any = 0.5
    shift: Any = 1

    def pulse_weight(self, angle):
        return jnp.broadcast_to(jnp.clip(self.fraction, 0.0, 1.0), jnp.shape(angle))


# ==================================================================== the loop's candidates


@register_effect
@dataclasses.dataclass(frozen=True)
class GravityOffset(Effect):
    """Gravity about a vertical that is not angle 0: −G'·sin(φ − φ_g).

    Eq. (8) takes angle 0 to be the gravity vertical, where the shank hangs.
    A recording zeroed elsewhere, or a shank that rests away from the vertical
    (passive tension, a seat that tilts the thigh), has gravity acting about
    another angle while the tissues' elasticity stays where it was: the quiet
    swings of a pendulum test then settle, and reverse, off the vertical.
    Unlike ``goniometer_offset`` it moves gravity alone, not the elasticity or
    the muscle's angle factors.  Replaces ``gravity``.
    """

    kind = "passive"
    name = "gravity_offset"
    signature = "angle"
    replaces = ("gravity",)
    params = (
        Param("gravity", "deg/s^2", support="positive", prior=("lognormal", math.log(1800.0), 0.2),
              doc="G' = G/I, as in eq. (8)"),
        Param("gravity_angle", "deg", prior=("normal", 0.0, 10.0), doc="knee angle of the gravity vertical"),
    )
    gravity: Any = 1800.0
    gravity_angle: Any = 0.0

    def acceleration(self, angle, velocity):
        return -self.gravity * sin_deg(angle - self.gravity_angle)


#: Knee angle [deg] at which ``extension_limit`` states its stiffness: full extension.
FULL_EXTENSION_DEG = 90.0
#: The largest exponent a limit's torque takes (``ExtensionLimit``).
LIMIT_EXPONENT_MAX = 20.0


@register_effect
@dataclasses.dataclass(frozen=True)
class ExtensionLimit(Effect):
    """The end of the knee's range in extension: −K·exp((φ − 90°)/w).

    Eq. (8)'s elasticity stiffens in flexion only; a real knee meets the end of its range near
    full extension (capsule, ligaments, the hamstrings stretched in the seated position), where
    the passive torque rises steeply.  ``limit_stiffness`` K is that torque at full extension
    (:data:`FULL_EXTENSION_DEG`), ``limit_width`` w how steeply it rises (by e per w).  Its
    prior reaches down to torques too small to matter, so a knee that never meets its limit
    is described by the effect too.  Its absence shows as a residual against the angle at the
    top of the swing, and in predictions that swing past the range where the knee stopped.
    """

    kind = "passive"
    name = "extension_limit"
    signature = "angle"
    params = (
        Param("limit_stiffness", "deg/s^2", support="positive", prior=("lognormal", math.log(30.0), 2.5),
              doc="the limit's torque at full extension (90°)"),
        Param("limit_width", "deg", support="positive", prior=("lognormal", math.log(6.0), 0.5),
              doc="rise of the limit's torque by e"),
    )
    limit_stiffness: Any = 30.0
    limit_width: Any = 6.0

    def acceleration(self, angle, velocity):
        # the exponent is bounded (e^20 past the limit is beyond any knee) so that a steep limit tried
        # by an optimiser or a sampler gives a large, finite torque rather than an overflow
        return -self.limit_stiffness * jnp.exp(jnp.minimum((angle - FULL_EXTENSION_DEG) / self.limit_width, LIMIT_EXPONENT_MAX))


@register_effect
@dataclasses.dataclass(frozen=True)
class PeakTorqueAngle(Effect):
    """Torque–angle relation with a maximum: f(φ) = exp(−((φ − φ_opt)² − φ_opt²)/(2w²)).

    A Gaussian in the knee angle, normalised to f(0) = 1 so the gain keeps its
    meaning at rest; the force–length relation of the quadriceps peaks at an
    optimal length inside the range of motion, which the linear factor of
    model 3 cannot show.  Replaces ``linear_torque_angle``.
    """

    kind = "gain"
    name = "torque_angle_peak"
    signature = "angle"
    replaces = ("linear_torque_angle",)
    params = (
        Param("phi_opt", "deg", prior=("normal", 10.0, 25.0), doc="knee angle of the largest twitch"),
        Param("width", "deg", support="positive", prior=("lognormal", math.log(30.0), 0.5), doc="width of the maximum"),
    )
    phi_opt: Any = 10.0
    width: Any = 30.0

    def factor(self, ctx):
        return jnp.exp(-((ctx.angle - self.phi_opt) ** 2 - self.phi_opt**2) / (2.0 * self.width**2))


@register_effect
@dataclasses.dataclass(frozen=True)
class HillTorqueVelocity(Effect):
    """Hill-type torque–velocity: a hyperbola when shortening, a plateau when lengthening.

    For knee-extension velocity v > 0 (the quadriceps shortens)
    g = max(0, (1 − v/v_max)/(1 + v/(k·v_max))); for v < 0 (eccentric)
    g = 1 + (g_ecc − 1)·(−v)/(−v + v_half), rising to the plateau g_ecc.
    Replaces ``linear_torque_velocity``.
    """

    kind = "gain"
    name = "hill_velocity"
    signature = "velocity"
    replaces = ("linear_torque_velocity",)
    params = (
        Param("vmax", "deg/s", support="positive", prior=("lognormal", math.log(600.0), 0.5), doc="shortening velocity of no force"),
        Param("hill_k", "1", support="positive", prior=("lognormal", math.log(0.25), 0.5), doc="curvature a/F0 of Hill's hyperbola"),
        Param("g_ecc", "1", prior=("normal", 1.3, 0.3), doc="eccentric plateau (1: none)"),
        Param("v_half", "deg/s", support="positive", prior=("lognormal", math.log(50.0), 0.7), doc="lengthening velocity of half the plateau"),
    )
    vmax: Any = 600.0
    hill_k: Any = 0.25
    g_ecc: Any = 1.3
    v_half: Any = 50.0

    def factor(self, ctx):
        vp = jnp.maximum(ctx.velocity, 0.0)
        vn = -jnp.minimum(ctx.velocity, 0.0)
        concentric = jnp.maximum((1.0 - vp / self.vmax) / (1.0 + vp / (self.hill_k * self.vmax)), 0.0)
        return concentric + (self.g_ecc - 1.0) * vn / (vn + self.v_half)


@register_effect
@dataclasses.dataclass(frozen=True)
class Fatigue(Effect):
    """Twitch gain falling with the pulses delivered: f_min + (1 − f_min)·exp(−n/N_f).

    n counts the pulses delivered before this one in the trial; each trial is
    taken to start rested (for the protocol's 15-min rests, recovery is
    nearly complete after a first trial; later trials start somewhat
    fatigued, which a per-trial fit absorbs in its gain).
    """

    kind = "pulse"
    name = "fatigue"
    signature = "pulse_count"
    params = (
        Param("f_min", "1", prior=("normal", 0.6, 0.25), doc="gain left when fully fatigued"),
        Param("n_fatigue", "pulses", support="positive", prior=("lognormal", math.log(800.0), 0.8), doc="pulses to fatigue by 1/e"),
    )
    f_min: Any = 0.6
    n_fatigue: Any = 800.0

    def pulse_factor(self, pctx):
        return self.f_min + (1.0 - self.f_min) * jnp.exp(-pctx.count / self.n_fatigue)


@register_effect
@dataclasses.dataclass(frozen=True)
class Potentiation(Effect):
    """Nonlinear summation: a twitch following closely on another is larger, 1 + P·exp(−(IPI − T_s)/τ_p).

    P < 0 describes depression instead.  The preceding interpulse interval IPI
    is that of the delivered pulses; the first pulse of a trial has none.
    """

    kind = "pulse"
    name = "potentiation"
    signature = "ipi"
    params = (
        Param("potentiation", "1", prior=("normal", 0.3, 0.5), doc="extra twitch at the shortest interval"),
        Param("tau_p", "s", support="positive", prior=("lognormal", math.log(0.06), 0.6), doc="decay of potentiation with the interval"),
    )
    potentiation: Any = 0.3
    tau_p: Any = 0.06
    #: The interval [s] at which ``potentiation`` is the extra twitch: the paper's shortest, one
    #: of its 10-ms samples (a fixed reference, whatever the data's sampling period).
    REFERENCE_IPI_S = 0.01

    def pulse_factor(self, pctx):
        return 1.0 + self.potentiation * jnp.exp(-(pctx.ipi_s - self.REFERENCE_IPI_S) / self.tau_p)


@register_effect
@dataclasses.dataclass(frozen=True)
class RecruitmentPower(Effect):
    """Recruitment nonlinearity: a pulse of level u acts as u^κ (κ = 1: linear recruitment)."""

    kind = "pulse"
    name = "recruitment_power"
    signature = "u"
    params = (Param("kappa", "1", support="positive", prior=("lognormal", 0.0, 0.3), doc="exponent of the recruitment curve"),)
    kappa: Any = 1.0

    def pulse_factor(self, pctx):
        u = jnp.maximum(pctx.u, 1e-6)
        return jnp.where(pctx.u > 0, jnp.exp((self.kappa - 1.0) * jnp.log(u)), 0.0)


@register_effect
@dataclasses.dataclass(frozen=True)
class RecruitmentSigmoid(Effect):
    """A recruitment curve: a pulse of relative charge u (its pulse width × current over the leg's
    largest, see docs/data-format.md) recruits the share R(u) of the muscle, a logistic curve
    through R(0) = 0 and R(1) = 1:

        R(u) = (σ((u − u50)/w) − σ(−u50/w)) / (σ((1 − u50)/w) − σ(−u50/w)),

    u50 the charge of half the recruitment (for a steep curve), w its width.  Real stimulators
    deliver trains whose pulse width or current is modulated; the twitch scales with the
    fibres recruited, which rise along such an S-curve, not linearly.  Not offered by the
    modelling loop: with the two levels of a protocol like the paper's (u = 0.5 and 1) it says
    no more than ``recruitment_power``; it needs pulses of many levels.
    """

    kind = "pulse"
    name = "recruitment_sigmoid"
    signature = "u"
    candidate = False
    #: Parameters in relative charge: a report gives them in the stimulator's unit too, where the
    #: fit keeps the charge the leg's levels are relative to (``FitResult.charge_scale``).
    in_charge = ("u50", "u_width")
    params = (
        Param("u50", "1", prior=("normal", 0.5, 0.2), doc="relative charge of half the recruitment"),
        Param("u_width", "1", support="positive", prior=("lognormal", math.log(0.15), 0.5),
              doc="width of the curve in relative charge"),
    )
    u50: Any = 0.5
    u_width: Any = 0.15

    def recruitment(self, u):
        def s(x):
            return jax.nn.sigmoid((x - self.u50) / self.u_width)

        return (s(u) - s(0.0)) / (s(1.0) - s(0.0))

    def pulse_factor(self, pctx):
        u = jnp.maximum(pctx.u, 1e-6)
        return jnp.where(pctx.u > 0, self.recruitment(u) / u, 0.0)


@register_effect
@dataclasses.dataclass(frozen=True)
class ActivationDamping(Effect):
    """Passive damping that grows with activation: M_k/I·(1 − β·φ̇_k).

    The paper assumes the passive properties do not change when the muscle is
    active.  An active muscle is stiffer and more viscous; the simplest form
    adds a damping term −β·(M_k/I)·φ̇_k proportional to the active output, at
    every sample of a twitch (model 3's torque–velocity factor acts once, at
    its onset).
    """

    kind = "output"
    name = "activation_damping"
    signature = "velocity"
    params = (
        Param(
            "beta_damping",
            "s/deg",
            prior=("normal", 0.0, 1.0e-3),
            doc="damping per unit of active output; 1e-3: 20 % less output at 200 deg/s",
        ),
    )
    beta_damping: Any = 0.0

    def output_factor(self, ctx):
        return 1.0 - self.beta_damping * ctx.velocity


# ==================================================================== measurement


@register_effect
@dataclasses.dataclass(frozen=True)
class GoniometerOffset(Effect):
    """The goniometer reads ``angle_offset`` when the shank hangs at rest.

    Angle 0 of the interchange format is the shank at rest; a goniometer
    zeroed elsewhere puts gravity's sin φ (eq. 8) and every angle-dependent
    factor at the wrong angle.  The dynamics run on φ = φ_measured − offset;
    predictions are read as φ + offset.
    """

    kind = "measurement"
    name = "goniometer_offset"
    signature = "angle"
    params = (
        Param("angle_offset", "deg", prior=("normal", 0.0, 3.0), doc="goniometer reading at rest; a few degrees"),
    )
    angle_offset: Any = 0.0

    def true_angle(self, measured):
        return measured - self.angle_offset

    def measured_angle(self, true):
        return true + self.angle_offset


@register_effect
@dataclasses.dataclass(frozen=True)
class AccelResonance(Effect):
    """The accelerometers sit on soft tissue: a base-excited resonance between shank and sensor.

    The sensor's acceleration follows the shank's through
    H(s) = (2ζω s + ω²)/(s² + 2ζω s + ω²), ω = 2π f_res, unit gain at low
    frequencies and a peak near f_res: ripple and overshoot after every twitch
    (the paper's discussion of Fig. 2(d)).  Discretised at T_s by the bilinear
    transform prewarped at f_res, its impulse response kept for
    ``RESPONSE_SAMPLES`` samples and renormalised to unit sum.  It changes only
    what the accelerometer reads, so it cannot change an angle prediction.
    """

    kind = "measurement"
    name = "accel_resonance"
    signature = "frequency"
    predicts_angle = False
    RESPONSE_SAMPLES = 24
    params = (
        Param("f_res", "Hz", support="positive", prior=("lognormal", math.log(18.0), 0.3), doc="skin-motion resonance"),
        Param("zeta_res", "1", support="positive", prior=("lognormal", math.log(0.3), 0.5), doc="its damping ratio"),
    )
    f_res: Any = 18.0
    zeta_res: Any = 0.3

    def acceleration_response(self, dt: float):
        w = 2.0 * math.pi * self.f_res
        c = w / jnp.tan(w * dt / 2.0)  # prewarped: the peak stays at f_res
        zwc = 2.0 * self.zeta_res * w * c
        b = jnp.stack([zwc + w**2, 2.0 * w**2, w**2 - zwc])
        a = jnp.stack([c**2 + zwc + w**2, 2.0 * w**2 - 2.0 * c**2, c**2 - zwc + w**2])
        b, a = b / a[0], a / a[0]
        x = jnp.zeros(self.RESPONSE_SAMPLES).at[0].set(1.0)

        def body(carry, xk):
            x1, x2, y1, y2 = carry
            y = b[0] * xk + b[1] * x1 + b[2] * x2 - a[1] * y1 - a[2] * y2
            return (xk, x1, y, y1), y

        z = jnp.zeros((), x.dtype)
        _, g = jax.lax.scan(body, (z, z, z, z), x)
        return g / jnp.sum(g)


# ========================================================================== noise


@register_effect
@dataclasses.dataclass(frozen=True)
class TwitchVariability(Effect):
    """Twitches vary from pulse to pulse: each pulse's twitch is scaled by its own random gain.

    The gain is log-normal with mean 1 and coefficient of variation ``twitch_cv``
    (the paper's Table IV: 12–29 % for the integrated twitch), independent
    between pulses.  It is noise, not dynamics: the model's prediction is the
    mean twitch, and the likelihood adds each pulse's variance,
    twitch_cv² × (its modelled output)², to the noise of the samples or
    windows it reaches (:mod:`quadshank.model._likelihood`), so that a large
    twitch that misses its prediction by a fifth is not evidence for an effect.
    """

    kind = "noise"
    name = "twitch_variability"
    signature = "onset"
    predicts_angle = False  # noise: the mean prediction, and so J, is the model's without it
    params = (
        Param("twitch_cv", "1", support="positive", prior=("lognormal", math.log(0.15), 0.75),
              doc="pulse-to-pulse coefficient of variation of the twitch's size"),
    )
    twitch_cv: Any = 0.15

    def pulse_variance(self):
        return self.twitch_cv**2
