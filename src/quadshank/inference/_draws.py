"""After sampling: leg models from posterior arrays, hyperparameters and discrete latents drawn
from their conditionals, and the pointwise log-likelihood for PSIS-LOO."""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import truncnorm

from ..common._random import jax_key, numpy_rng
from ..model._effects import prior_arrays
from ..model._likelihood import N_DELAYS, LikelihoodData, leg_pointwise, step_edges
from ..model._model import Model
from ._density import cohort_loglik_by_threshold
from ._priors import (
    _with_discrete_axes,
    log_shift_prior,
    model_params,
    spread_grid,
    spread_log_weights,
    step_param,
)


#: Draws evaluated together by :func:`over_draws`.
DRAW_BATCH = 4


def over_draws(f, *xs, batch_size: int = DRAW_BATCH):
    """``f`` applied along the leading (draw) axis of the arrays or pytrees ``xs``, in a loop of
    batches of ``batch_size`` draws (:func:`jax.lax.map`); stacked results.

    Not ``jax.vmap`` over every draw: the likelihood gathers and scatters along its samples, and
    XLA's CPU code for those ops with a wide batch axis runs several times slower per draw than
    the program of one draw (the screen's 200 Laplace draws of one 2-minute leg, every delay:
    0.43 s vmapped, 0.074 s in batches of 4, the same numbers).  A batch of a few draws keeps
    the vector units busy; a wide one brings the slowdown back (0.14 s in batches of 16)."""
    return jax.lax.map(lambda a: f(*a), xs, batch_size=batch_size)


def leg_models(model: Model, posterior: dict[str, np.ndarray]) -> Model:
    """``model`` with leaves of shape (draws, legs, ...) taken from flat posterior arrays."""
    values = {p.name: jnp.asarray(posterior[p.name]) for p in model_params(model)}
    lead = next(iter(values.values())).shape[:2]
    return _with_discrete_axes(model.with_params(values), lead)


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
    rng = numpy_rng(seed, "hyperparameters")
    out = {}
    for p in model_params(model):
        if f"{p.name}_s_leg" not in samples:
            continue
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
        out[f"{p.name}_mu"] = p.from_standard(mu_std, flat=True).reshape(*lead, *shape)
        subj = p.from_standard(np.moveaxis(subj_std, -1, -2), flat=True)  # (ch, dr, S, C)
        out[f"{p.name}_subject"] = subj.reshape(*lead, n_subjects, *shape)
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
    rng = numpy_rng(seed, "spreads")
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
        scale = prior_arrays(p.prior, shape)[1].reshape(-1)
        for key, r in (("subject", r_s[g]), ("leg", r_l[g])):
            out[f"{p.name}_sd_{key}_rel"] = r.reshape(*lead, *shape)
            out[f"{p.name}_sd_{key}"] = (r * scale).reshape(*lead, *shape)
    return out


def sample_delays(delay_logp: np.ndarray, key) -> tuple[np.ndarray, np.ndarray]:
    """One (d, shift) per draw and leg from P(d, shift | θ, data) by Gumbel-max.

    ``delay_logp`` is (..., legs, D) (no delay effect: shift 0) or the joint
    (..., legs, D, K + 1); ``key`` a JAX key (a stream of the fit's seed, :func:`quadshank.common.jax_key`).
    Returns (d, shift), each (..., legs).
    """
    logp = np.asarray(delay_logp)
    if logp.ndim >= 3 and logp.shape[-1] != N_DELAYS:
        flat = logp.reshape(*logp.shape[:-2], -1)
        n_shift = logp.shape[-1]
    else:
        flat, n_shift = logp, 1
    g = jax.random.gumbel(key, flat.shape)
    k = np.asarray(jnp.argmax(jnp.asarray(flat) + g, axis=-1))
    return k // n_shift, k % n_shift


def hard_step(model: Model) -> Model:
    """``model`` with its delay effect's step hard (``softness_deg = 0``), as the fit sums it out."""
    eff = model.delay_effect
    if eff is None or not hasattr(eff, "softness_deg"):
        return model
    return dataclasses.replace(model, effects=tuple(dataclasses.replace(e, softness_deg=0.0) if e is eff else e for e in model.effects))


def sample_step_states(model: Model, data: LikelihoodData, posterior: dict, log_delay_prior, seed: int, chunk: int = 1024):
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

    f = jax.jit(lambda *a: over_draws(one_draw, *a))
    keys = jax.random.split(jax_key(seed, "step states"), n_draws)
    out = []
    for i in range(0, n_draws, chunk):
        sl = slice(i, min(i + chunk, n_draws))
        m = jax.tree_util.tree_map(lambda v: v[sl], stacked)
        out.append([np.asarray(v) for v in f(m, jnp.asarray(posterior["sigma"][sl]), jnp.asarray(posterior["nu"][sl]), keys[sl])])
    d, shift, lo, hi = (np.concatenate([o[j] for o in out]) for j in range(4))
    lo, hi = lo.astype(np.float64), hi.astype(np.float64)  # the drawn state's edges in prior scales
    rng = numpy_rng(seed, "thresholds")
    threshold = loc + scale * truncnorm.rvs(lo, hi, random_state=rng)
    return d, shift, threshold.astype(np.float32)


def pointwise_loglik(
    model: Model, data: LikelihoodData, posterior: dict, delays: np.ndarray, shifts: np.ndarray, chunk: int = 1024
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
    f = jax.jit(lambda *a: over_draws(one_draw, *a))
    n_draws = delays.shape[0]
    out = []
    for i in range(0, n_draws, chunk):
        sl = slice(i, min(i + chunk, n_draws))
        m = jax.tree_util.tree_map(lambda v: v[sl], stacked)
        args = (posterior["sigma"][sl], posterior["nu"][sl], jnp.asarray(delays[sl]), jnp.asarray(shifts[sl]))
        out.append(np.asarray(f(m, *args)))
    ll = np.concatenate(out, axis=0)
    return np.where(data.segment_mask[None], ll, np.nan)
