"""Hierarchical Bayesian identification with NUTS (numpyro).

The numpyro model is generated from the Model's declared parameters
(:class:`quadshank.model._effects.Param`).  Each parameter with prior
``(family, loc, scale)`` lives on an unconstrained scale x (log θ for a
``lognormal`` prior, θ itself for ``normal``) and is built non-centred down to
its declared level:

    x_leg = μ + τ_subject · z_subject[s(leg)] + τ_leg · z_leg[leg]
    μ ~ Normal(loc, scale)        population mean, the declared prior
    τ_subject, τ_leg ~ HalfNormal(scale)
    z ~ Normal(0, 1)

so the declared prior is the population-level belief and the spread between
subjects and between the legs of a subject is learnt (weakly informative: at
most about one prior scale).  That is the non-centred form
(``FitSettings(centred=False)``), for sparse data.  By default the legs are
sampled directly, standardised by the prior, x_leg = loc + scale · s_leg, with
the population mean and the subject level integrated out analytically,

    s_leg ~ MultivariateNormal(0, 11ᵀ + r_s² S + r_l² I),  S_ij = [legs i, j share a subject],

r = τ/scale, because each leg's thousands of samples pin its values down: a
sampled population mean or subject level between them is a funnel, and
parameters whose prior scales differ by seven orders of magnitude
(γ_velocity, G') defeat the mass matrix's adaptation unless standardised.
The relative spreads are summed out too, as the delay is: their HalfNormal(1)
prior is put on a grid (:data:`SPREAD_GRID`, each point holding the prior mass
of its cell) and s_leg's prior is the mixture Σ_g w_g MVN(0, C(r_g))
(:class:`SpreadMixture`).  A sampled r is the funnel once more: where the legs
agree, r → 0 draws them together, the sampler's step has to shrink with r, and
the trajectories run to the tree's depth with divergences.  Summed out, the
prior of s_leg is smooth and bounded (its peak at agreeing legs is at most a few
times its height elsewhere), and r is drawn afterwards from its conditional on
the grid (:func:`spread_draws`).
Population means and subject values are drawn afterwards from their Gaussian
conditional given each draw and its spreads (:func:`hyper_draws`).  A dense mass matrix absorbs the remaining linear correlations
(k1 with k2, gain with the gain factors).  Noise (Student-t, see
:mod:`quadshank.model._likelihood`) is per leg: σ ~ LogNormal(log 40 deg/s², 1),
ν ~ Gamma(2, 0.1).  The delay d of each leg has a uniform prior on 0 … 10
samples (or another fit's posterior, :func:`delay_prior_from`) and is summed
out exactly, jointly with a delay effect's shift; P(d | data) is the posterior mean of the
per-draw conditional P(d | θ, data), and one d per draw is drawn from that
conditional for the pointwise log-likelihood (so PSIS-LOO is over (θ, d)).
Chains start at each leg's mode from the screen (:func:`screen_start`,
:mod:`quadshank.inference._screen`), whose Laplace covariances are also the metric:
each d has its own mode in θ, the screen's multi-start optimisation of the
marginal posterior finds one, restarted at the delay that a Laplace
approximation per delay weighs most where that is another
(:func:`delay_start`), and each leg's block is narrow and
correlated in a way a short warm-up cannot estimate.  The classical
least-squares start (:func:`classical_start`) and the prior median remain
as options.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from numpyro.infer import MCMC, NUTS, init_to_median, init_to_uniform
from numpyro.util import is_prng_key

from ..data._cohort import Cohort
from ..model._effects import Param, get_effect
from ..model._likelihood import (
    N_DELAYS,
    LikelihoodData,
    leg_loglik_by_delay,
    leg_loglik_by_threshold,
    leg_pointwise,
    prepare,
    step_edges,
    step_log_mass,
)
from ..model._model import Model, paper_model

__all__ = [
    "FitSettings",
    "model_params",
    "numpyro_model",
    "fit",
    "build_model",
    "NOISE_PARAMS",
]

#: Noise parameters per leg: name -> (units, doc).
NOISE_PARAMS = {
    "sigma": ("deg/s^2", "Student-t scale of one sample of equivalent acceleration"),
    "nu": ("1", "Student-t degrees of freedom"),
}
SIGMA_PRIOR = (math.log(40.0), 1.0)
#: Probability spread evenly over all delays when a delay prior comes from another fit.
DELAY_PRIOR_FLOOR = 1e-3
NU_PRIOR = (2.0, 0.1)


#: Where chains can start (:attr:`FitSettings.start`).
STARTS = ("screen", "classical", "prior")
#: What :attr:`FitSettings.chain_method` takes.
CHAIN_METHODS = ("auto", "vectorized", "sequential", "parallel")
#: Compared samples (all legs) from which chain_method "auto" runs the chains one after another.
SEQUENTIAL_FROM_SAMPLES = 100_000


@dataclasses.dataclass(frozen=True)
class FitSettings:
    chains: int = 4
    warmup: int = 1000
    draws: int = 1000
    seed: int = 0
    target_accept: float = 0.9
    max_tree_depth: int = 8
    centred: bool = True
    dense_mass: bool = True
    trials: tuple[int, ...] = (1,)
    #: numpyro's ``chain_method``: "vectorized" (all chains in one batched program),
    #: "sequential" (one after another), "parallel" (one device per chain), or "auto":
    #: sequential from :data:`SEQUENTIAL_FROM_SAMPLES` compared samples on, else vectorized
    #: (:func:`chain_method`).  The draws are the same; the time is not.  On the 2-core CPU,
    #: model3s on 2 legs × 1.5 min (18 000 samples; the demo's fit, 2 chains × 150 + 150)
    #: took 32 s vectorized against 50 s sequential; model 3 + angle_delay on 5 legs × 5 min
    #: (150 000 samples; 4 chains × 100 + 100 from the screen) 116 s against 83 s.  Batched
    #: over 4 chains, that likelihood's gradient costs 2.2 single gradients per chain on the
    #: 150 000 samples, 0.8–1.0 on 30 000 or 60 000 (5 legs × 1 min, 2 legs × 5 min).
    chain_method: str = "auto"
    #: Where the chains start: "screen" (each leg's mode and Laplace covariance from the
    #: screen, which also give the metric; see :func:`screen_start`), "classical" (the
    #: classical least-squares estimate, jittered) or "prior" (the prior median).
    start: str = "screen"
    #: With ``start="screen"``, adapt the metric in warm-up as well (by default the screen's
    #: is kept and only the step size adapts); the other starts always adapt it.
    adapt_metric: bool = False
    #: With ``start="screen"``, weigh each leg's delays by a Laplace approximation per delay
    #: before sampling (:func:`delay_start`): the screen restarts at the best delay where it
    #: missed it, and the weights, stored in the fit, are checked against the chains' P(d):
    #: a delay holding ≥ 0.1 of that weight that no chain visits draws a warning.
    delay_evidence: bool = True

    def __post_init__(self):
        if self.start not in STARTS:
            raise ValueError(f"start must be one of {', '.join(STARTS)}, not {self.start!r}")
        if self.chain_method not in CHAIN_METHODS:
            raise ValueError(f"chain_method must be one of {', '.join(CHAIN_METHODS)}, not {self.chain_method!r}")


def chain_method(settings: FitSettings, data: LikelihoodData) -> str:
    """numpyro's chain method for a fit of ``data``: the settings' own, or for "auto",
    "sequential" from :data:`SEQUENTIAL_FROM_SAMPLES` compared samples on, else "vectorized"."""
    if settings.chain_method != "auto":
        return settings.chain_method
    return "sequential" if int(np.sum(data.sample_mask)) >= SEQUENTIAL_FROM_SAMPLES else "vectorized"


#: Classical models whose estimates start a model's chains (model3s: model 2's twitch, model 3's gains).
CLASSICAL_SOURCES = {"model3s": ("model3", "model2")}

#: Spread of the chains' starting points about the classical estimate [prior scales].
INIT_JITTER = 0.05
#: A classical estimate further than this from the prior median [prior scales] is not used.
INIT_MAX_Z = 3.0


def build_model(name: str, add_effects=()) -> Model:
    """One of the paper's models, optionally extended by registered effects (by name or instance)."""
    base = paper_model(name)
    extra = [get_effect(e)() if isinstance(e, str) else e for e in add_effects]
    if not extra:
        return base
    suffix = "+".join(e.name for e in extra)
    return base.add(*extra, name=f"{base.name}+{suffix}")


def model_params(model: Model) -> list[Param]:
    """The declared parameters of every effect, in order."""
    return [p for e in model.effects for p in e.declared_params()]


def _arr(v, shape):
    return jnp.broadcast_to(jnp.asarray(v, jnp.float32), shape)


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
    from scipy.special import erf

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
    family, loc, scale = p.prior[:3]
    shape = tuple(p.shape)
    loc = _arr(loc, shape)
    scale = _arr(scale, shape)
    transform = jnp.exp if family == "lognormal" else (lambda x: x)
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
        x_leg = loc + scale * jnp.reshape(s_leg.T, (n_legs, *shape))
        return numpyro.deterministic(p.name, transform(x_leg))
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
    leg_values = numpyro.deterministic(p.name, transform(x_leg))
    numpyro.deterministic(f"{p.name}_subject", transform(x_subject))
    return leg_values


def numpyro_model(
    model: Model,
    data: LikelihoodData,
    arrays: dict | None = None,
    centred: bool = True,
    log_delay_prior=None,
):
    """The hierarchical numpyro model of ``model`` on ``data`` (delay summed out).

    ``log_delay_prior`` (legs, 11): log π(d) per leg; uniform when None.
    """
    x = arrays if arrays is not None else data.leg_arrays()
    n_legs, n_subjects = data.n_legs, len(data.subjects)
    leg_subject = np.asarray(data.leg_subject)  # a constant: the spread grid is built from it
    step = step_param(model, data)
    values = {p.name: _hierarchical(p, n_legs, n_subjects, leg_subject, centred) for p in model_params(model) if step is None or p.name != step.name}
    if step is not None:  # summed out in the likelihood; the value is never read
        values[step.name] = jnp.zeros((n_legs, *step.shape), jnp.float32)
    with numpyro.plate("legs", n_legs):
        sigma = numpyro.sample("sigma", dist.LogNormal(*SIGMA_PRIOR))
        nu = numpyro.sample("nu", dist.Gamma(*NU_PRIOR))
    stacked = _with_discrete_axes(model.with_params(values), (n_legs,))
    R, K = data.response_length, data.max_shift
    d_prior = jnp.full((n_legs, N_DELAYS), -math.log(N_DELAYS)) if log_delay_prior is None else jnp.asarray(log_delay_prior)
    step_prior = None if step is None else tuple(float(v) for v in step.prior[1:3])
    delay_logp, joint, total = cohort_delay_terms(stacked, sigma, nu, x, d_prior, R, K, step_prior)
    numpyro.deterministic("delay_logp", delay_logp)
    if K:
        numpyro.deterministic("delay_shift_logp", joint)
    numpyro.factor("likelihood", jnp.sum(total))


@functools.partial(jax.jit, static_argnames=("R", "K", "step_prior"))
def cohort_delay_terms(stacked: Model, sigma, nu, x: dict, d_prior, R: int, K: int, step_prior=None):
    """The likelihood's terms of every leg with the delay (and its shift) summed out:
    log P(d | θ, y) (L, D), log P(d, shift | θ, y) (L, D, K + 1) and log p(y | θ) (L,).

    ``d_prior`` (L, D): log π(d); ``step_prior`` (loc, scale) of a step delay effect's
    threshold, which is summed out too, or None.  Jitted as a whole: numpyro runs the
    model eagerly to initialise, under its gradient and mapped over chains, and each
    of the primitives here would be compiled on its own for each.
    """
    if step_prior is None:
        ll = cohort_loglik_by_delay(stacked, sigma, nu, x, R, K)
    else:
        ll = jax.scipy.special.logsumexp(cohort_loglik_by_threshold(stacked, sigma, nu, x, R, K, *step_prior), axis=-1)
    logp = ll + d_prior[:, :, None] + jnp.asarray(log_shift_prior(K))[None]  # (L, D, K + 1)
    total = jax.scipy.special.logsumexp(logp, axis=(-2, -1))
    joint = logp - total[:, None, None]
    return jax.scipy.special.logsumexp(joint, axis=-1), joint, total


def cohort_loglik_by_delay(stacked: Model, sigma, nu, x: dict, R: int, K: int):
    """log p(y_leg | θ_leg, d, shift) of every leg, (L, D, K + 1) (traced inside
    :func:`cohort_delay_terms`, which is jitted whole)."""
    return jax.vmap(lambda m, s, n, xi: leg_loglik_by_delay(m, {"sigma": s, "nu": n}, xi, R, K))(stacked, sigma, nu, x)


@functools.partial(jax.jit, static_argnames=("R", "K"))
def cohort_loglik_by_threshold(stacked: Model, sigma, nu, x: dict, R: int, K: int, loc, scale):
    """log p(y_leg, state j | θ_leg, d, shift) of every leg, (L, D, K + 1, P + 1), for a step delay
    effect whose threshold has the prior Normal(loc, scale): the likelihood of each threshold
    state plus the log prior mass of its interval."""

    def one(m, s, n, xi):
        ll = leg_loglik_by_threshold(m, {"sigma": s, "nu": n}, xi, R, K)
        return ll + step_log_mass(m, xi, loc, scale)

    return jax.vmap(one)(stacked, sigma, nu, x)


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


def classical_start(cohort: Cohort, model: Model, data: LikelihoodData, trial: int) -> dict:
    """Standardised leg values ``{p}_s_leg`` at the classical least-squares identification.

    Each d gives its own best (a, b) or gain, so the posterior over the continuous
    parameters has one mode per delay; chains started at the prior median settle
    in whichever mode is near and rarely leave it (a model-2 chain on data with
    d = 4 stayed at d = 3).  The paper's identification (model 2 over every d, the
    smallest residual) finds the leading mode, and the chains start there.  A leg
    the classical identification cannot handle (too few isolated twitches) starts
    its values at the prior median (s = 0), with a warning; so does an estimate more
    than ``INIT_MAX_Z`` prior scales out (least squares running along a ridge the data
    do not close); parameters it does not estimate (an added effect's) are left to
    the prior median.
    """
    from ._identify import IdentificationError, identify_leg

    base = model.name.split("+")[0]
    per_leg = []
    for leg in data.legs:
        try:
            ident = identify_leg(cohort.get(leg, trial))
            values = {}
            for source in CLASSICAL_SOURCES.get(base, (base,)):
                values.update(ident.models[source].params() if source in ident.models else {})
            per_leg.append(values)
        except (IdentificationError, KeyError, ValueError) as exc:
            warnings.warn(f"{leg}: chains start at the prior median, not the classical estimate ({exc})", stacklevel=2)
            per_leg.append({})
    out = {}
    for p in model_params(model):
        if p.level != "leg" or not any(p.name in v for v in per_leg):
            continue
        family, loc, scale = p.prior[:3]
        loc = np.broadcast_to(np.asarray(loc, np.float64), p.shape)
        scale = np.broadcast_to(np.asarray(scale, np.float64), p.shape)
        cols = []
        for v in per_leg:
            if p.name not in v:
                cols.append(np.zeros(p.shape))
                continue
            x = np.asarray(v[p.name], np.float64)
            if family == "lognormal":
                x = np.log(np.maximum(x, 1e-30))
            z = (x - loc) / scale
            # beyond INIT_MAX_Z prior scales the least squares ran along a ridge the data do
            # not close (k1 with k2 and G' when the knee stays out of flexion): prior median
            cols.append(np.where(np.isfinite(z) & (np.abs(z) <= INIT_MAX_Z), z, 0.0))
        s = np.stack(cols, axis=-1)  # (*shape, L): (L,) scalar, (C, L) vector
        out[f"{p.name}_s_leg"] = s.reshape(-1, len(data.legs)) if p.shape else s
    return out


def uses_screen(model: Model, settings: FitSettings) -> bool:
    """Whether the chains start from the screen: the screen's vector maps onto the standardised
    leg sites, and a parameter declared at the subject or population level has none (such a
    model starts as "classical" does)."""
    return settings.start == "screen" and settings.centred and all(p.level == "leg" for p in model_params(model))


def fit_screen(cohort: Cohort, model: Model, settings: FitSettings, legs=None, n_starts: int = 3, progress: bool = False):
    """The screen :func:`fit` starts its chains from (None where it starts otherwise, see
    :func:`uses_screen`); computed ahead so that :func:`quadshank.inference._screen.delay_evidence` can
    start from it too."""
    from ._screen import laplace_fit

    if not uses_screen(model, settings):
        return None
    if progress:
        print("fit: each leg's mode and Laplace covariance (the screen) for the chains' start and metric",
              file=sys.stderr, flush=True)
    return laplace_fit(cohort, model, trials=settings.trials, legs=legs, n_starts=n_starts,
                       n_draws=max(settings.chains, 2), seed=settings.seed, loo=False)


def delay_start(cohort: Cohort, settings: FitSettings, screen, log_delay_prior=None, progress: bool = False):
    """Each leg's delays weighed by a Laplace approximation per delay, and the screen restarted
    where it missed the best of them.  Returns ``(screen, evidence, moved)``.

    The screen's L-BFGS of the marginal posterior settles in the basin it starts in, and
    where each delay has its own mode in θ (model 3) that basin can be a delay's that
    holds little mass: on 18 s of TN-left (model3s + angle_delay) the screen sat at
    d = 3 while the mode at d = 4 had a log density 120 higher, and the chains, started
    there, never left d = 3.  :func:`quadshank.inference._screen.delay_modes` finds every delay's
    mode; where that evidence (times ``log_delay_prior``, the fit's delay prior) gives the
    delay the screen sits at (its P(d)'s mode) less than half of what it gives the best
    delay, the leg is screened again from the best delay's mode.  Where the data do not
    tell the delays apart (model 1, whose window sums cannot see d) the screen stays.
    ``evidence``: (legs, 11) P(d | data) of each leg alone; ``moved``: ``{leg: (d of the
    old screen, d of the new)}``.
    """
    from ._screen import delay_modes, restart_screen

    dm = delay_modes(screen)
    evidence = dm.probability
    if log_delay_prior is not None:  # the fit's delay prior, not the evidence's uniform one
        evidence = evidence * np.exp(np.asarray(log_delay_prior, np.float64))
        evidence = evidence / evidence.sum(axis=1, keepdims=True)
    best = evidence.argmax(axis=1)
    sits = screen.delay_posterior.argmax(axis=1)
    starts, moved = {}, {}
    for i, leg in enumerate(screen.legs):
        if evidence[i, sits[i]] < 0.5 * evidence[i, best[i]]:
            starts[leg] = dm.modes[i, best[i]]
            moved[leg] = (int(sits[i]), int(best[i]))
    if starts:
        if progress:
            print("fit: the screen restarted at the delay the evidence weighs most: "
                  + ", ".join(f"{leg} d = {a} -> {b}" for leg, (a, b) in moved.items()), file=sys.stderr, flush=True)
        screen = restart_screen(screen, cohort, starts, trials=settings.trials, seed=settings.seed)
    return screen, evidence, moved


def screen_start(model: Model, data: LikelihoodData, settings: FitSettings, conditioned, arrays, scr):
    """Starting points and a metric for NUTS from the per-leg screen (:mod:`quadshank.inference._screen`).

    ``scr``: the screen of the fit's legs (:func:`fit_screen`).

    Returns ``(init_params, inverse_mass_matrix)``: unconstrained values per chain
    (chain c of leg i starts at the c-th Laplace draw of that leg) and a dense inverse
    metric holding each leg's Laplace covariance.  Each leg's thousands of samples
    make its block nearly Gaussian and very narrow (posterior sds down to 1e-3 prior
    scales, correlated k1–k2, a–b, gain–gain factors); a metric estimated from a short
    warm-up misses that, and chains that start at different points settle at
    different delays.  The screen's multi-start optimisation of the marginal
    posterior finds the leading mode and the Laplace covariance is the metric for it.
    The legs are the whole latent vector (the levels above them are summed out), and
    the legs are coupled only through their prior, so the metric is block-diagonal.
    """
    from numpyro import handlers

    chains = settings.chains
    if scr.legs != data.legs or scr.draws.shape[1] < chains:
        raise ValueError(f"the screen is of legs {', '.join(scr.legs)} with {scr.draws.shape[1]} draws; "
                         f"the fit needs {', '.join(data.legs)} and {chains}: make it with fit_screen()")
    def latent_values(arrays):
        trace = handlers.trace(handlers.seed(conditioned, settings.seed)).get_trace(arrays)
        return {k: v["value"] for k, v in trace.items() if v["type"] == "sample" and not v["is_observed"]}

    # the latent sites' shapes, traced abstractly: nothing drawn, nothing compiled
    shapes = {k: tuple(v.shape) for k, v in jax.eval_shape(latent_values, arrays).items()}
    names = sorted(shapes)  # numpyro's order of the flattened latent vector
    offsets, n = {}, 0
    for k in names:
        offsets[k] = n
        n += math.prod(shapes[k])
    L = data.n_legs

    # a parameter the fit sums out (a step delay effect's threshold) has no site: its entries
    # of the screen's vector are dropped, and the Laplace covariance of the rest is the block of it
    kept = np.concatenate([np.full(s.size, f"{s.name}_s_leg" in offsets) for s in scr.specs] + [np.ones(2, bool)])

    def positions(i):
        """Where leg i's screen vector (z per parameter, log σ, log ν; kept entries) sits in the latent vector."""
        out = []
        for s in scr.specs:
            site = f"{s.name}_s_leg"
            if site in offsets:
                out += [offsets[site] + (c * L + i if s.shape else i) for c in range(s.size)]
        return np.asarray(out + [offsets["sigma"] + i, offsets["nu"] + i])

    inits = np.zeros((chains, n))
    imm = np.zeros((n, n))
    covered = np.zeros(n, bool)
    for i in range(L):
        idx = positions(i)
        imm[np.ix_(idx, idx)] = scr.covariance[i][np.ix_(kept, kept)]
        inits[:, idx] = scr.draws[i, :chains][:, kept]
        covered[idx] = True
    if not covered.all():
        missing = [k for k in names if not covered[offsets[k] : offsets[k] + math.prod(shapes[k])].all()]
        raise ValueError(f"the screen gives no start for {', '.join(missing)}; use start='classical' or 'prior'")
    init_params = {}
    for k in names:
        shape = shapes[k]
        v = inits[:, offsets[k] : offsets[k] + math.prod(shape)].reshape((chains, *shape))
        init_params[k] = jnp.asarray(v if chains > 1 else v[0], jnp.result_type(float))
    return init_params, {tuple(names): jnp.asarray(imm, jnp.result_type(float))}


def _init_near(site=None, values=None, jitter=INIT_JITTER, fallback=None):
    """numpyro init strategy: ``values[name]`` plus N(0, jitter²) per chain; others from ``fallback``."""
    if site["name"] in values and site["type"] == "sample" and not site["is_observed"]:
        v = jnp.asarray(values[site["name"]], jnp.float32)
        key = site["kwargs"].get("rng_key")
        if key is None:
            return v
        return v + jitter * jax.random.normal(key, v.shape, v.dtype)
    return fallback(site)


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


def delay_prior_from(summary: dict, legs, floor: float = DELAY_PRIOR_FLOOR) -> np.ndarray:
    """log π(d) per leg (legs, 11) from another fit's ``summary.json`` (its ``delay_posterior``).

    This is the paper's procedure made Bayesian: the delay is identified where the
    data show it, by the shaped twitch of model 2 (Table I: "the delay d was taken
    such that it yielded the smallest residual error in the least squares
    identification of model 2"), and carried to the zero-order models, whose
    twitch-window likelihood cannot see a twitch's onset.  A ``floor`` mixed in
    keeps every d possible.
    """
    rows = []
    for leg in legs:
        if leg not in summary.get("legs", {}):
            raise KeyError(f"leg {leg!r} is not in the fit the delay prior is taken from (it has {sorted(summary.get('legs', {}))})")
        p = np.asarray(summary["legs"][leg]["delay_posterior"], np.float64)
        if p.shape != (N_DELAYS,) or not np.all(np.isfinite(p)) or p.sum() <= 0:
            raise ValueError(f"leg {leg!r}: delay_posterior must be {N_DELAYS} probabilities")
        p = (1.0 - floor) * p / p.sum() + floor / N_DELAYS
        rows.append(np.log(p))
    return np.stack(rows)


def fit(
    cohort: Cohort,
    model: Model,
    settings: FitSettings = FitSettings(),
    legs=None,
    progress: bool = True,
    log_delay_prior=None,
    screen=None,
):
    """Run NUTS; returns (mcmc, data).  ``log_delay_prior``: see :func:`delay_prior_from`;
    ``screen``: the chains' start (:func:`fit_screen`, then :func:`delay_start`), made here
    when needed and not given.

    Samples in double precision, as the screen optimises: the log density of five
    5-minute legs is ~1e6, where single precision rounds it to ~0.06, and NUTS,
    seeing that noise in every energy difference, shrinks its step until the trees
    reach their depth (model 3 + angle_delay, 5 legs × 5 min: 255 leapfrog steps per
    draw in single precision, 12 in double).
    """
    with jax.enable_x64(True):
        return _fit(cohort, model, settings, legs, progress, log_delay_prior, screen)


class _StartedNUTS(NUTS):
    """NUTS for chains whose starting points are given (the screen's).

    numpyro initialises a model by tracing it and then searching for a valid start
    per chain, compiling the log density and its gradient into a loop over the
    chains, and it does that even when ``init_params`` replace the start it finds.
    Here that search runs for one chain only (with ``init_strategy`` init_to_uniform,
    which draws nothing from the prior), eagerly, and is discarded as before: the
    model's transforms and potential are the same, and so are the draws; one
    compilation of the gradient fewer.
    """

    # numpyro's private hook, (rng_key, model_args, model_kwargs, init_params) for many releases;
    # the test that compares this kernel's first state with NUTS's watches it
    def _init_state(self, rng_key, *args, **kwargs):
        init_params = kwargs.get("init_params", args[2] if len(args) > 2 else None)
        if init_params is not None and not is_prng_key(rng_key):
            rng_key = rng_key[0]  # one chain's key: one eager search, not a compiled loop over chains
        return super()._init_state(rng_key, *args, **kwargs)


def _fit(cohort, model, settings, legs, progress, log_delay_prior, screen):
    data = prepare(cohort, model, trials=settings.trials, legs=legs)
    arrays = {k: v.astype(jnp.float64) if jnp.issubdtype(v.dtype, jnp.floating) else v for k, v in data.leg_arrays().items()}
    if log_delay_prior is not None:
        log_delay_prior = np.asarray(log_delay_prior, np.float32)
        if log_delay_prior.shape != (data.n_legs, N_DELAYS):
            raise ValueError(f"log_delay_prior must have shape ({data.n_legs}, {N_DELAYS})")

    # the model and data are closed over, not passed as arguments: numpyro maps its
    # arguments as pytrees, and a Model must not be rebuilt from placeholder leaves
    def conditioned(arrays):
        return numpyro_model(model, data, arrays, settings.centred, log_delay_prior)

    init = init_to_median(num_samples=15)
    init_params, imm = None, None
    if uses_screen(model, settings):
        if screen is None:
            screen = fit_screen(cohort, model, settings, legs=data.legs, progress=progress)
            if settings.delay_evidence:
                screen = delay_start(cohort, settings, screen, log_delay_prior, progress=progress)[0]
        init_params, imm = screen_start(model, data, settings, conditioned, arrays, screen)
        init = init_to_uniform  # the start numpyro finds is replaced by init_params: no prior draws for it
        if not settings.dense_mass:
            imm = {k: jnp.diagonal(v) for k, v in imm.items()}
    elif settings.start in ("screen", "classical") and settings.centred:
        start = classical_start(cohort, model, data, settings.trials[0])
        init = functools.partial(_init_near, values=start, fallback=init)
    kernel = (NUTS if init_params is None else _StartedNUTS)(
        conditioned,
        target_accept_prob=settings.target_accept,
        max_tree_depth=settings.max_tree_depth,
        init_strategy=init,
        dense_mass=settings.dense_mass,
        inverse_mass_matrix=imm,
        adapt_mass_matrix=settings.adapt_metric or imm is None,
    )
    mcmc = MCMC(
        kernel,
        num_warmup=settings.warmup,
        num_samples=settings.draws,
        num_chains=settings.chains,
        chain_method=chain_method(settings, data),
        progress_bar=progress,
        # the data are arguments of the jitted sampler, not constants folded into it:
        # the chains (and later fits of the same shapes) compile it once
        jit_model_args=True,
    )
    mcmc.run(jax.random.PRNGKey(settings.seed), arrays, extra_fields=("diverging", "energy", "num_steps"), init_params=init_params)
    return mcmc, data


# ============================================================================ after sampling


def leg_models(model: Model, posterior: dict[str, np.ndarray]) -> Model:
    """``model`` with leaves of shape (draws, legs, ...) taken from flat posterior arrays."""
    values = {p.name: jnp.asarray(posterior[p.name]) for p in model_params(model)}
    lead = next(iter(values.values())).shape[:2]
    return _with_discrete_axes(model.with_params(values), lead)


def _with_discrete_axes(model: Model, lead: tuple) -> Model:
    """The discrete leaves (delay, a delay effect's shift), which the likelihood sums out
    and never reads, given the leading axes of the parameters so the model can be vmapped."""
    zeros = jnp.zeros(lead, jnp.int32)
    model = model.with_params(delay=zeros)
    return model.with_delay_shift(zeros) if model.delay_effect is not None else model


def hyper_draws(model: Model, samples: dict, leg_subject, n_subjects: int, seed: int) -> dict:
    """Population means and subject values, drawn from their conditional given each draw.

    For the centred form, where μ and the subject level are integrated out: in prior-scale
    units, μ ~ N(0, 1), b_s ~ N(0, r_s²), s_leg = μ + b_s(leg) + N(0, r_l²), so (μ, b | s_leg, r)
    is Gaussian.  ``samples`` arrays have leading axes (chains, draws); returns
    ``{name}_mu`` (chains, draws, *shape) and ``{name}_subject`` (chains, draws, subjects, *shape)
    in the parameter's units, and the spreads of :func:`spread_draws` where ``samples`` has none.
    """
    leg_subject = np.asarray(leg_subject)
    spreads = spread_draws(model, samples, leg_subject, seed)
    samples = {**samples, **spreads}
    n_legs = leg_subject.size
    A = np.zeros((n_legs, n_subjects + 1))
    A[:, 0] = 1.0
    A[np.arange(n_legs), 1 + leg_subject] = 1.0
    rng = np.random.default_rng(seed + 2)
    out = {}
    for p in model_params(model):
        if f"{p.name}_s_leg" not in samples:
            continue
        family, loc, scale = p.prior[:3]
        shape = tuple(p.shape)
        lead = np.shape(samples[f"{p.name}_s_leg"])[:2]
        C = int(np.prod(shape)) if shape else 1
        s_leg = np.asarray(samples[f"{p.name}_s_leg"], np.float64).reshape(*lead, C, n_legs)
        r_s = np.asarray(samples[f"{p.name}_sd_subject_rel"], np.float64).reshape(*lead, C)
        r_l = np.asarray(samples[f"{p.name}_sd_leg_rel"], np.float64).reshape(*lead, C)
        prior_prec = np.concatenate(
            [np.ones((*lead, C, 1)), np.repeat((1.0 / r_s**2)[..., None], n_subjects, axis=-1)], axis=-1
        )
        prec = np.einsum("...i,ij->...ij", prior_prec, np.eye(n_subjects + 1)) + (A.T @ A) / (r_l**2)[..., None, None]
        cov = np.linalg.inv(prec)
        mean = np.einsum("...ij,...j->...i", cov, np.einsum("li,...l->...i", A, s_leg) / (r_l**2)[..., None])
        z = rng.standard_normal(mean.shape)
        chol = np.linalg.cholesky(0.5 * (cov + np.swapaxes(cov, -1, -2)))
        draw = mean + np.einsum("...ij,...j->...i", chol, z)  # (ch, dr, C, 1 + S)
        mu_std = draw[..., 0]
        subj_std = draw[..., :1] + draw[..., 1:]  # (ch, dr, C, S)
        loc_a = np.broadcast_to(np.asarray(loc, np.float64), shape).reshape(-1)
        scale_a = np.broadcast_to(np.asarray(scale, np.float64), shape).reshape(-1)
        tf = np.exp if family == "lognormal" else (lambda v: v)
        out[f"{p.name}_mu"] = tf(loc_a + scale_a * mu_std).reshape(*lead, *shape)
        subj = tf(loc_a[:, None] + scale_a[:, None] * subj_std)  # (ch, dr, C, S)
        out[f"{p.name}_subject"] = np.moveaxis(subj, -1, 2).reshape(*lead, n_subjects, *shape)
    return {**spreads, **out}


def spread_draws(model: Model, samples: dict, leg_subject, seed: int) -> dict:
    """The relative spreads (r_s, r_l) of each draw, from their conditional on the grid.

    Given the standardised leg values s of a draw, P(r_g | s) ∝ w_g MVN(s; 0, C(r_g))
    (:func:`spread_log_weights`); one grid point is drawn per draw and parameter
    component.  Returns ``{name}_sd_subject_rel`` and ``{name}_sd_leg_rel``
    (chains, draws, *shape) and the same in the parameter's units, ``{name}_sd_subject``
    and ``{name}_sd_leg``, for the parameters whose spreads ``samples`` does not hold.
    """
    _, r_s, r_l, *_ = spread_grid(tuple(int(i) for i in np.asarray(leg_subject)))
    rng = np.random.default_rng(seed + 3)
    out = {}
    for p in model_params(model):
        site = f"{p.name}_s_leg"
        if site not in samples or f"{p.name}_sd_leg_rel" in samples:
            continue
        shape = tuple(p.shape)
        lead = np.shape(samples[site])[:2]
        s_leg = np.asarray(samples[site], np.float64).reshape(*lead, -1, len(leg_subject))  # (ch, dr, C, L)
        logp = spread_log_weights(s_leg, leg_subject)
        g = np.argmax(logp + rng.gumbel(size=logp.shape), axis=-1)  # (ch, dr, C)
        scale = np.broadcast_to(np.asarray(p.prior[2], np.float64), shape).reshape(-1)
        for key, r in (("subject", r_s[g]), ("leg", r_l[g])):
            out[f"{p.name}_sd_{key}_rel"] = r.reshape(*lead, *shape)
            out[f"{p.name}_sd_{key}"] = (r * scale).reshape(*lead, *shape)
    return out


def sample_delays(delay_logp: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """One (d, shift) per draw and leg from P(d, shift | θ, data) by Gumbel-max.

    ``delay_logp`` is (..., legs, D) (no delay effect: shift 0) or the joint
    (..., legs, D, K + 1).  Returns (d, shift), each (..., legs).
    """
    logp = np.asarray(delay_logp)
    if logp.ndim >= 3 and logp.shape[-1] != N_DELAYS:
        flat = logp.reshape(*logp.shape[:-2], -1)
        n_shift = logp.shape[-1]
    else:
        flat, n_shift = logp, 1
    g = jax.random.gumbel(jax.random.PRNGKey(seed + 1), flat.shape)
    k = np.asarray(jnp.argmax(jnp.asarray(flat) + g, axis=-1))
    return k // n_shift, k % n_shift


def hard_step(model: Model) -> Model:
    """``model`` with its delay effect's step hard (``softness_deg = 0``), as the fit sums it out."""
    eff = model.delay_effect
    if eff is None or not hasattr(eff, "softness_deg"):
        return model
    return dataclasses.replace(model, effects=tuple(dataclasses.replace(e, softness_deg=0.0) if e is eff else e for e in model.effects))


def sample_step_states(model: Model, data: LikelihoodData, posterior: dict, log_delay_prior, seed: int, chunk: int = 16):
    """(d, shift, threshold) per draw and leg, for a fit that summed a step delay effect's threshold out.

    (d, shift, state) are drawn jointly from P(d, shift, state | θ, data) by Gumbel-max, state
    being the threshold's interval between two neighbouring pulse angles
    (:func:`quadshank.model._likelihood.step_tables`), and the threshold from its Normal prior
    truncated to that interval.  With shift 0 the states are alike, so the threshold is drawn
    from its prior: the data say nothing of it.  ``posterior`` arrays are (draws, legs, ...);
    ``log_delay_prior`` (legs, D) or None (uniform).  Returns three (draws, legs) arrays.
    """
    with jax.enable_x64(True):  # the states' log-likelihoods are ~1e5: single precision would blur them
        return _sample_step_states(model, data, posterior, log_delay_prior, seed, chunk)


def _sample_step_states(model, data, posterior, log_delay_prior, seed, chunk):
    from scipy.stats import truncnorm

    step = step_param(model, data)
    loc, scale = step.prior[1:3]
    x = data.leg_arrays()
    R, K = data.response_length, data.max_shift
    n_draws, L = np.shape(posterior["sigma"])
    d_prior = np.full((L, N_DELAYS), -math.log(N_DELAYS)) if log_delay_prior is None else np.asarray(log_delay_prior)
    prior = jnp.asarray(d_prior[:, :, None] + log_shift_prior(K)[None])[..., None]  # (L, D, K + 1, 1)
    stacked = leg_models(model, {**posterior, step.name: np.zeros((n_draws, L))})

    def one_draw(m, sigma, nu, key):
        logp = cohort_loglik_by_threshold(m, sigma, nu, x, R, K, loc, scale) + prior  # (L, D, K + 1, J)
        flat = logp.reshape(L, -1)
        k = jnp.argmax(flat + jax.random.gumbel(key, flat.shape), axis=-1)
        J = logp.shape[-1]
        d, rest = k // ((K + 1) * J), k % ((K + 1) * J)
        state = rest % J
        edges = jax.vmap(lambda mi, xi: step_edges(mi, xi, loc, scale))(m, x)  # (L, J + 1)
        lo = jnp.take_along_axis(edges, state[:, None], axis=1)[:, 0]
        hi = jnp.take_along_axis(edges, state[:, None] + 1, axis=1)[:, 0]
        return d, rest // J, lo, hi

    f = jax.jit(jax.vmap(one_draw))
    keys = jax.random.split(jax.random.PRNGKey(seed + 4), n_draws)
    out = []
    for i in range(0, n_draws, chunk):
        sl = slice(i, min(i + chunk, n_draws))
        m = jax.tree_util.tree_map(lambda v: v[sl], stacked)
        out.append([np.asarray(v) for v in f(m, jnp.asarray(posterior["sigma"][sl]), jnp.asarray(posterior["nu"][sl]), keys[sl])])
    d, shift, lo, hi = (np.concatenate([o[j] for o in out]) for j in range(4))
    lo, hi = lo.astype(np.float64), hi.astype(np.float64)  # the drawn state's edges in prior scales
    rng = np.random.default_rng(seed + 5)
    threshold = loc + scale * truncnorm.rvs(lo, hi, random_state=rng)
    return d, shift, threshold.astype(np.float32)


def pointwise_loglik(
    model: Model, data: LikelihoodData, posterior: dict, delays: np.ndarray, shifts: np.ndarray, chunk: int = 64
):
    """log p(segment | θ, d, shift) per draw, leg and 1-s segment: array (draws, legs, segments)."""
    x = data.leg_arrays()
    R, K = data.response_length, data.max_shift
    S = data.n_segments

    def one_leg(mi, si, ni, xi, di, ki):
        return leg_pointwise(mi, {"sigma": si, "nu": ni}, xi, di, R, S, K, ki)

    def one_draw(m, s, n, d, k):
        return jax.vmap(one_leg)(m, s, n, x, d, k)

    stacked = leg_models(model, posterior)
    f = jax.jit(jax.vmap(one_draw))
    n_draws = delays.shape[0]
    out = []
    for i in range(0, n_draws, chunk):
        sl = slice(i, min(i + chunk, n_draws))
        m = jax.tree_util.tree_map(lambda v: v[sl], stacked)
        args = (posterior["sigma"][sl], posterior["nu"][sl], jnp.asarray(delays[sl]), jnp.asarray(shifts[sl]))
        out.append(np.asarray(f(m, *args)))
    ll = np.concatenate(out, axis=0)
    return np.where(data.segment_mask[None], ll, np.nan)


def describe_fit(model: Model, data: LikelihoodData, settings: FitSettings) -> dict:
    return {
        "model": model.name,
        "effects": [e.name for e in model.effects],
        "params": {
            p.name: {"units": p.units, "prior": list(p.prior), "level": p.level, "shape": list(p.shape), "doc": p.doc}
            for p in model_params(model)
        },
        "noise": {k: {"units": u, "doc": doc} for k, (u, doc) in NOISE_PARAMS.items()},
        "legs": list(data.legs),
        "subjects": list(data.subjects),
        "leg_subject": [int(i) for i in data.leg_subject],
        "trials": list(data.trials),
        "resolution": data.resolution,
        "settings": dataclasses.asdict(settings),
        "chain_method": chain_method(settings, data),
        "sampling_period_s": model.sampling_period_s,
    }


def model_from_description(desc: dict) -> Model:
    """Rebuild the (unparameterised) Model a fit was made with."""
    effects = [get_effect(n)() for n in desc["effects"]]
    model = Model(tuple(effects), name=desc["model"], sampling_period_s=desc.get("sampling_period_s", 0.01))
    # a fit that summed a step parameter out drew it under the hard step, and is evaluated so
    return hard_step(model) if desc.get("summed_out") else model


def to_json(desc: dict) -> str:
    return json.dumps(desc, sort_keys=True)


def from_json(text: str) -> dict:
    return json.loads(text)
