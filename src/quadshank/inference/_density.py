"""The hierarchical numpyro model: priors from the declared parameters, the delay summed out.

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
Where the model has the built-in gravity and elasticity, G' is not sampled
itself: the standardised passive stiffness at rest, K₀ = G'·π/180 + k1'·k2,
is (:func:`~quadshank.inference._priors.stiffness_leg_values`), and G' with
its declared prior follows through the Jacobian, because a swing pins K₀ and
leaves its split between gravity and elasticity to the prior, a constraint
that is curved in (log G', log k1', log k2) and straight in K₀.
Population means and subject values are drawn afterwards from their Gaussian
conditional given each draw and its spreads (:func:`hyper_draws`).  A dense mass matrix absorbs the remaining linear correlations
(k1 with k2, gain with the gain factors).  Noise (Student-t, see
:mod:`quadshank.model._likelihood`) is per leg: σ ~ LogNormal(log 40 deg/s², 1)
(on the angle: LogNormal(log 0.5°, 1)),
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

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist

from ..model._likelihood import (
    N_DELAYS,
    LikelihoodData,
    leg_loglik_by_delay,
    leg_loglik_by_threshold,
    step_log_mass,
)
from ..model._model import Model
from ._priors import (
    NU_PRIOR,
    SIGMA_PRIORS,
    _hierarchical,
    _with_discrete_axes,
    log_shift_prior,
    model_params,
    step_param,
    stiffness_leg_values,
    stiffness_params,
)


def numpyro_model(
    model: Model,
    data: LikelihoodData,
    arrays: dict | None = None,
    centred: bool = True,
    log_delay_prior=None,
    part: str = "all",
):
    """The hierarchical numpyro model of ``model`` on ``data`` (delay summed out).

    ``log_delay_prior`` (legs, 11): log π(d) per leg; uniform when None.  ``part``: "all";
    "prior", without the likelihood; "legs", the whole model with each leg's log-likelihood
    recorded as the deterministic site ``leg_loglik`` (L,).  The potential energy is the
    prior's minus the legs' log-likelihoods, which is what jumps of one leg at a time
    (:class:`quadshank.inference._jumps.ModeJumpNUTS`) evaluate.
    """
    if part not in ("all", "prior", "legs"):
        raise ValueError(f"part must be 'all', 'prior' or 'legs', not {part!r}")
    x = arrays if arrays is not None else data.leg_arrays()
    n_legs, n_subjects = data.n_legs, len(data.subjects)
    leg_subject = np.asarray(data.leg_subject)  # a constant: the spread grid is built from it
    step = step_param(model, data)
    stiffness = stiffness_params(model, centred)
    values = {p.name: _hierarchical(p, n_legs, n_subjects, leg_subject, centred) for p in model_params(model)
              if (step is None or p.name != step.name) and (stiffness is None or p.name != stiffness[0].name)}
    if stiffness is not None:  # G′ through the stiffness at rest (see stiffness_params)
        s_k1, s_k2 = ((jnp.log(values[p.name]) - p.prior[1]) / p.prior[2] for p in stiffness[1:])
        values[stiffness[0].name] = stiffness_leg_values(n_legs, leg_subject, stiffness, s_k1, s_k2)
    if step is not None:  # summed out in the likelihood; the value is never read
        values[step.name] = jnp.zeros((n_legs, *step.shape), jnp.float32)
    with numpyro.plate("legs", n_legs):
        sigma = numpyro.sample("sigma", dist.LogNormal(*SIGMA_PRIORS[data.objective]))
        nu = numpyro.sample("nu", dist.Gamma(*NU_PRIOR))
    if part == "prior":
        return
    stacked = _with_discrete_axes(model.with_params(values), (n_legs,))
    R, K = data.response_length, data.max_shift
    d_prior = jnp.full((n_legs, N_DELAYS), -math.log(N_DELAYS)) if log_delay_prior is None else jnp.asarray(log_delay_prior)
    step_prior = None if step is None else tuple(float(v) for v in step.prior[1:3])
    delay_logp, joint, total = cohort_delay_terms(stacked, sigma, nu, x, d_prior, R, K, step_prior)
    numpyro.deterministic("delay_logp", delay_logp)
    if K:
        numpyro.deterministic("delay_shift_logp", joint)
    if part == "legs":
        numpyro.deterministic("leg_loglik", total)
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
