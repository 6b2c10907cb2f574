"""Priors of the hierarchical model, generated from the effects' declared parameters.

See :mod:`quadshank.inference._density` for the model they enter: each parameter is
standardised by its declared prior, x = loc + scale · s (x = log θ for a log-normal prior),
and the spreads between subjects and legs are summed out on :data:`SPREAD_GRID`.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from scipy.special import erf

from ..data._paper import SAMPLING_PERIOD_S
from ..model._effects import Param, from_unconstrained, get_effect, prior_arrays
from ..model._likelihood import N_DELAYS, LikelihoodData
from ..model._model import Model, paper_model

#: Noise parameters per leg: name -> (units, doc).
NOISE_PARAMS = {
    "sigma": ("deg/s^2", "Student-t scale of one sample of equivalent acceleration"),
    "nu": ("1", "Student-t degrees of freedom"),
}


#: σ ~ LogNormal(loc, scale) per leg, by what the likelihood compares
#: (:data:`quadshank.model._likelihood.OBJECTIVES`): 40 deg/s² on the equivalent acceleration,
#: 0.5° on the angle (a goniometer's noise plus a free run's drift).
SIGMA_PRIORS = {"acceleration": (math.log(40.0), 1.0), "angle": (math.log(0.5), 1.0)}
SIGMA_PRIOR = SIGMA_PRIORS["acceleration"]
#: σ's units by objective (the noise table's "sigma" entry is the acceleration's).
SIGMA_UNITS = {"acceleration": "deg/s^2", "angle": "deg"}


#: Probability spread evenly over all delays when a delay prior comes from another fit.
DELAY_PRIOR_FLOOR = 1e-3


NU_PRIOR = (2.0, 0.1)


def build_model(name: str, add_effects=(), sampling_period_s: float = SAMPLING_PERIOD_S) -> Model:
    """One of the paper's models, optionally extended by registered effects (by name or instance),
    running at ``sampling_period_s`` (give the data's: ``cohort.sampling_period_s``)."""
    base = paper_model(name, sampling_period_s=sampling_period_s)
    if isinstance(add_effects, str) or not hasattr(add_effects, "__iter__"):
        add_effects = (add_effects,)  # one effect, by name or instance
    extra = [get_effect(e)() if isinstance(e, str) else e for e in add_effects]
    return base.add(*extra) if extra else base


def model_params(model: Model) -> list[Param]:
    """The declared parameters of every effect, in order."""
    return [p for e in model.effects for p in e.declared_params()]


#: Relative spreads r = τ/scale (between subjects, between legs) on which their HalfNormal(1)
#: prior is discretised and summed out: log-spaced, each point holding its cell's prior mass
#: (the first cell reaching down to 0, the last up to ∞).  The floor, 0.1 prior scales (6 % of
#: G′ between legs, 2 % of the gravity term), keeps the prior of the legs' differences no
#: narrower than what a well-determined leg's data resolve: with a floor of 0.02, the narrow
#: components pull the poorly-determined parameters (k1, k2) into a funnel of their own
#: (model 3, 5 legs × 1 min: step size 0.10 against 0.28, 31 leapfrog steps against 15).
SPREAD_GRID = np.geomspace(0.1, 3.0, 10)


@functools.lru_cache(maxsize=32)
def spread_grid(leg_subject: tuple[int, ...]):
    """The (r_s, r_l) grid for legs grouped into subjects as ``leg_subject``.

    Returns numpy arrays over the G = len(SPREAD_GRID)² points: log prior weight (G,),
    r_s and r_l (G,), and of C_g = 11ᵀ + r_s² S + r_l² I the inverse (G, L, L),
    log determinant (G,) and Cholesky factor (G, L, L).
    """

    r = SPREAD_GRID
    edges = np.concatenate([[0.0], np.sqrt(r[1:] * r[:-1]), [np.inf]])
    mass = np.diff(erf(edges / math.sqrt(2.0)))  # HalfNormal(1) mass of each cell
    r_s, r_l = (v.ravel() for v in np.meshgrid(r, r, indexing="ij"))
    log_w = (np.log(mass)[:, None] + np.log(mass)[None, :]).ravel()
    ls = np.asarray(leg_subject)
    L = ls.size
    same = (ls[:, None] == ls[None, :]).astype(np.float64)
    cov = 1.0 + r_s[:, None, None] ** 2 * same + r_l[:, None, None] ** 2 * np.eye(L)
    chol = np.linalg.cholesky(cov)
    logdet = 2.0 * np.log(np.diagonal(chol, axis1=-2, axis2=-1)).sum(-1)
    return log_w, r_s, r_l, np.linalg.inv(cov), logdet, chol


def spread_log_weights(s_leg, leg_subject) -> np.ndarray | jnp.ndarray:
    """log [w_g MVN(s_leg; 0, C_g)] over the spread grid, (..., G) for ``s_leg`` (..., L)."""
    log_w, _, _, prec, logdet, _ = spread_grid(tuple(int(i) for i in leg_subject))
    xp = jnp if isinstance(s_leg, jax.Array) else np
    dt = s_leg.dtype
    quad = xp.einsum("...l,glm,...m->...g", s_leg, prec.astype(dt), s_leg)
    L = prec.shape[-1]
    return log_w.astype(dt) - 0.5 * (quad + logdet.astype(dt) + L * math.log(2.0 * math.pi))


class SpreadMixture(dist.Distribution):
    """Prior of the standardised leg values of one parameter component, the spreads summed out:
    Σ_g w_g MVN(0, 11ᵀ + r_s,g² S + r_l,g² I) over :data:`SPREAD_GRID` (event: the legs)."""

    support = dist.constraints.real_vector
    reparametrized_params = []

    def __init__(self, leg_subject, batch_shape=(), *, validate_args=None):
        self.leg_subject = tuple(int(i) for i in leg_subject)
        super().__init__(batch_shape=tuple(batch_shape), event_shape=(len(self.leg_subject),), validate_args=validate_args)

    def log_prob(self, value):
        return _spread_log_prob(value, self.leg_subject)

    def sample(self, key, sample_shape=()):
        log_w, _, _, _, _, chol = spread_grid(self.leg_subject)
        shape = tuple(sample_shape) + self.batch_shape
        k1, k2 = jax.random.split(key)
        g = jax.random.categorical(k1, jnp.asarray(log_w, jnp.float32), shape=shape)
        z = jax.random.normal(k2, shape + self.event_shape)
        return jnp.einsum("...lm,...m->...l", jnp.asarray(chol, jnp.float32)[g], z)


@functools.partial(jax.jit, static_argnames=("leg_subject",))
def _spread_log_prob(value, leg_subject: tuple[int, ...]):
    """SpreadMixture's log density, jitted (numpyro evaluates the model eagerly to initialise)."""
    return jax.scipy.special.logsumexp(spread_log_weights(value, leg_subject), axis=-1)


def _hierarchical(p: Param, n_legs: int, n_subjects: int, leg_subject, centred: bool = True):
    """Sample one parameter down to its level; returns the leg values (and records subject values)."""
    shape = tuple(p.shape)
    loc, scale = (jnp.asarray(v) for v in prior_arrays(p.prior, shape, np.float32))
    ev = len(shape)
    if p.level == "leg" and centred:
        # Legs sampled directly, standardised by the prior (x = loc + scale·s), with the
        # population mean, the subject level and the spreads integrated out:
        #   s_leg ~ Σ_g w_g MVN(0, 11ᵀ + r_s,g² S + r_l,g² I),  S[i, j] = 1 when legs i and j share
        # a subject, r = τ/scale the spreads in prior scales on SPREAD_GRID (see the module's
        # docstring).  Standardising puts every parameter on a unit prior scale whatever its
        # units (γ_velocity ~ 1e-3 s/deg, G' ~ 1e4 deg/s²); summing μ and r out leaves no funnel.
        # r, μ and the subject values are drawn from their conditionals afterwards (hyper_draws).
        prior = SpreadMixture(np.asarray(leg_subject), batch_shape=shape)
        # (L,) for a scalar parameter, (C, L) for a vector one
        s_leg = numpyro.sample(f"{p.name}_s_leg", prior.to_event(ev))
        return numpyro.deterministic(p.name, p.from_standard(jnp.reshape(s_leg.T, (n_legs, *shape)), xp=jnp, dtype=np.float32))
    mu = numpyro.sample(f"{p.name}_mu", dist.Normal(loc, scale).to_event(ev))
    x_subject = jnp.broadcast_to(mu, (n_subjects, *shape))
    if p.level in ("subject", "leg"):
        tau_s = numpyro.sample(f"{p.name}_sd_subject", dist.HalfNormal(scale).to_event(ev))
        with numpyro.plate("subjects", n_subjects):
            if centred:
                x_subject = numpyro.sample(f"{p.name}_x_subject", dist.Normal(mu, tau_s).to_event(ev))
            else:
                z = numpyro.sample(f"{p.name}_z_subject", dist.Normal(jnp.zeros(shape), 1.0).to_event(ev))
                x_subject = mu + tau_s * z
    x_leg = x_subject[leg_subject]
    if p.level == "leg":
        tau_l = numpyro.sample(f"{p.name}_sd_leg", dist.HalfNormal(scale).to_event(ev))
        with numpyro.plate("legs", n_legs):
            z = numpyro.sample(f"{p.name}_z_leg", dist.Normal(jnp.zeros(shape), 1.0).to_event(ev))
            x_leg = x_leg + tau_l * z
    leg_values = numpyro.deterministic(p.name, from_unconstrained(x_leg, p.prior, jnp))
    numpyro.deterministic(f"{p.name}_subject", from_unconstrained(x_subject, p.prior, jnp))
    return leg_values


def step_param(model: Model, data: LikelihoodData) -> Param | None:
    """The delay effect's step parameter that the fit sums out (None: nothing to sum out).

    It needs the data's step tables (a delay that can shift) and a normal prior."""
    name = getattr(model.delay_effect, "step_param", None)
    if name is None or data.step_order is None:
        return None
    p = next(p for p in model.delay_effect.declared_params() if p.name == name)
    if p.prior[0] != "normal" or p.shape:
        raise ValueError(f"{model.delay_effect.name}: a summed-out step parameter needs a scalar normal prior, not {p.prior}")
    return p


def log_shift_prior(K: int) -> np.ndarray:
    """log π(shift | d), (D, K + 1): half the prior on no change, the rest spread over
    shifts 1 … K; a shift longer than d is impossible, and each row is renormalised, so
    d keeps its own prior π(d)."""
    if K == 0:
        return np.zeros((N_DELAYS, 1))
    p = np.concatenate([[0.5], np.full(K, 0.5 / K)])
    joint = np.where(np.arange(K + 1)[None, :] <= np.arange(N_DELAYS)[:, None], p[None, :], 0.0)
    joint = joint / joint.sum(axis=1, keepdims=True)  # π(shift | d): d keeps its own prior
    with np.errstate(divide="ignore"):
        return np.log(joint)


def delay_prior_from(fit_legs: dict, legs, floor: float = DELAY_PRIOR_FLOOR) -> np.ndarray:
    """log π(d) per leg (legs, 11) from another fit's per-leg summaries (``FitResult.legs``: their
    ``delay_posterior``).

    This is the paper's procedure made Bayesian: the delay is identified where the
    data show it, by the shaped twitch of model 2 (Table I: "the delay d was taken
    such that it yielded the smallest residual error in the least squares
    identification of model 2"), and carried to the zero-order models, whose
    twitch-window likelihood cannot see a twitch's onset.  A ``floor`` mixed in
    keeps every d possible.
    """
    rows = []
    for leg in legs:
        if leg not in fit_legs:
            raise KeyError(f"leg {leg!r} is not in the fit the delay prior is taken from (it has {sorted(fit_legs)})")
        p = np.asarray(fit_legs[leg]["delay_posterior"], np.float64)
        if p.shape != (N_DELAYS,) or not np.all(np.isfinite(p)) or p.sum() <= 0:
            raise ValueError(f"leg {leg!r}: delay_posterior must be {N_DELAYS} probabilities")
        p = (1.0 - floor) * p / p.sum() + floor / N_DELAYS
        rows.append(np.log(p))
    return np.stack(rows)


def _with_discrete_axes(model: Model, lead: tuple) -> Model:
    """The discrete leaves (delay, a delay effect's shift), which the likelihood sums out
    and never reads, given the leading axes of the parameters so the model can be vmapped."""
    zeros = jnp.zeros(lead, jnp.int32)
    model = model.with_params(delay=zeros)
    return model.with_delay_shift(zeros) if model.delay_effect is not None else model


# ============================================================ the stiffness at rest as a coordinate

#: The latent site that holds each leg's stiffness at rest where the fit samples it in place of
#: the gravity term (:func:`stiffness_params`); ``gravity_s_leg`` is then recorded as a deterministic.
STIFFNESS_SITE = "stiffness_t_leg"
#: The built-in effects whose parameters the stiffness at rest combines, and those parameters.
_STIFFNESS_EFFECTS = {"gravity": ("gravity",), "elasticity": ("k1", "k2")}
_DEG = math.pi / 180.0


def stiffness_params(model: Model, centred: bool = True) -> tuple[Param, Param, Param] | None:
    """``(gravity, k1, k2)`` where the fit samples the passive system's stiffness at rest in place
    of the gravity term G′, else None (a model without the built-in gravity and elasticity, or
    the non-centred form).

    A swing pins the passive torque's slope at rest, K₀ = G′·π/180 + k1·k2 (the gravity term's and
    the elasticity's, per degree), to a fraction of a per cent, and where the knee stays out of
    deep flexion it leaves how K₀ splits between the two to the prior: G′ trades with k1·k2, and
    k1 with k2.  In the standardised coordinates (log G′, log k1, log k2) that constraint,
    log(e^{log G′}·π/180 + e^{log k1 + log k2}) fixed, is curved, and a dense metric follows it
    along a straight line only: on 1 min of a leg the line leaves the curve by several of its
    widths within two posterior sds along the ridge, where the curvature the sampler meets is
    30–60 times that at the mode and its trajectories diverge.  Sampling K₀ itself
    (:func:`stiffness_from_standard`) keeps the pinned direction straight; G′ follows as
    (K₀ − k1·k2)·180/π, and its prior stays the declared one, carried over with the Jacobian.
    """
    if not centred or not set(_STIFFNESS_EFFECTS) <= {e.name for e in model.effects}:
        return None
    by_name = {p.name: p for e in model.effects if e.name in _STIFFNESS_EFFECTS for p in e.declared_params()}
    params = tuple(by_name.get(n) for names in _STIFFNESS_EFFECTS.values() for n in names)
    if any(p is None or p.level != "leg" or p.shape or p.prior[0] != "lognormal" for p in params):
        return None
    return params


def _log_gravity_part(s_gravity, params):
    """log G′·π/180, the gravity term's part of K₀, from G′'s standardised value."""
    g = params[0]
    return g.prior[1] + g.prior[2] * s_gravity + math.log(_DEG)


def _log_elastic_part(s_k1, s_k2, params):
    """log k1·k2, the elasticity's part of K₀, from the standardised values of k1 and k2."""
    _, k1, k2 = params
    return k1.prior[1] + k1.prior[2] * s_k1 + k2.prior[1] + k2.prior[2] * s_k2


def _stiffness_centre(params) -> float:
    """log K₀ at the priors' medians, the centre of the stiffness coordinate."""
    return float(np.logaddexp(_log_gravity_part(0.0, params), _log_elastic_part(0.0, 0.0, params)))


def stiffness_from_standard(s_gravity, s_k1, s_k2, params, xp=np):
    """The stiffness coordinate t = (log K₀ − log K₀,median)/scale_G′ from the standardised
    values of G′, k1 and k2 (:func:`stiffness_params`); near s_gravity where G′ dominates K₀."""
    log_g, log_s = _log_gravity_part(s_gravity, params), _log_elastic_part(s_k1, s_k2, params)
    return (xp.logaddexp(log_g, log_s) - _stiffness_centre(params)) / params[0].prior[2]


def standard_from_stiffness(t, s_k1, s_k2, params, xp=np):
    """The inverse of :func:`stiffness_from_standard` in s_gravity: ``(s_gravity, log_jacobian,
    valid)``, with log |∂s_gravity/∂t| = log K₀/(K₀ − k1·k2); ``valid`` is False where
    k1·k2 ≥ K₀ (no positive G′), and s_gravity is then finite but meaningless."""
    g = params[0]
    log_k0 = _stiffness_centre(params) + g.prior[2] * t
    log_s = _log_elastic_part(s_k1, s_k2, params)
    share = xp.exp(log_s - log_k0)  # k1·k2 / K₀
    valid = share < 1.0
    rest = xp.log1p(-xp.where(valid, share, 0.5))  # log (K₀ − k1·k2)/K₀
    s_gravity = (log_k0 + rest - math.log(_DEG) - g.prior[1]) / g.prior[2]
    return s_gravity, -rest, valid


def stiffness_jacobian(s_gravity, s_k1, s_k2, params) -> np.ndarray:
    """∂t/∂(s_gravity, s_k1, s_k2) at one point: the row by which a covariance in the standardised
    coordinates is carried to the stiffness coordinate."""
    g, k1, k2 = params
    log_g, log_s = _log_gravity_part(s_gravity, params), _log_elastic_part(s_k1, s_k2, params)
    w_s = float(np.exp(log_s - np.logaddexp(log_g, log_s)))  # k1·k2's share of K₀
    return np.array([1.0 - w_s, w_s * k1.prior[2] / g.prior[2], w_s * k2.prior[2] / g.prior[2]])


def stiffness_leg_values(n_legs: int, leg_subject, params, s_k1, s_k2):
    """Inside the numpyro model: sample each leg's stiffness coordinate (site :data:`STIFFNESS_SITE`)
    and return G′'s leg values, recording ``gravity_s_leg`` and ``gravity``.  The site is drawn
    with G′'s own prior and that prior is then replaced, by a factor, with the declared one at the
    implied G′ times the Jacobian, so the posterior is the same as when G′ is sampled."""
    g = params[0]
    prior = SpreadMixture(np.asarray(leg_subject))
    t = numpyro.sample(STIFFNESS_SITE, prior)
    s_g, log_jac, valid = standard_from_stiffness(t, s_k1, s_k2, params, xp=jnp)
    correction = prior.log_prob(s_g) - prior.log_prob(t) + jnp.sum(log_jac)
    numpyro.factor("stiffness_prior", jnp.where(jnp.all(valid), correction, -jnp.inf))
    s_g = numpyro.deterministic(f"{g.name}_s_leg", s_g)
    return numpyro.deterministic(g.name, g.from_standard(jnp.reshape(s_g, (n_legs,)), xp=jnp, dtype=np.float32))
