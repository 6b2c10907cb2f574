"""The benchmark's peer: quadshank's hierarchical model written in PyMC, sampled by nutpie.

The same joint density as :func:`quadshank.inference._nuts.numpyro_model` for the paper's
model 3 with the angle-dependent delay (or without it): legs standardised by
their priors with the population mean, subject level and spreads integrated
out (s_leg ~ Σ_g w_g MVN(0, 11ᵀ + r_s,g²S + r_l,g²I) on quadshank's grid of
spreads), per-leg Student-t noise on twitch-window sums of the equivalent
acceleration, the delay d ∈ {0…10}, the shift and the threshold (its states
between the pulse angles) summed out by log-sum-exp.  It reads the same
touch and step tables (``quadshank.model._likelihood.prepare``) and is checked
against quadshank's log density at a common point (:func:`check_same_density`)
before any timing is trusted.

Needs the optional ``bench`` extra (pymc, nutpie); nothing in quadshank imports it.
"""

from __future__ import annotations

import math

import numpy as np

from quadshank.inference._priors import (
    NU_PRIOR,
    SIGMA_PRIOR,
    log_shift_prior,
    model_params,
    spread_grid,
)
from quadshank.model._likelihood import N_DELAYS, LikelihoodData

SUPPORTED = {"zero_order", "linear_torque_angle", "linear_torque_velocity", "damping", "gravity", "elasticity",
             "angle_delay"}  # fmt: skip


def _t_logpdf(pt, x, nu, scale):
    z = x / scale
    return (
        pt.gammaln(0.5 * (nu + 1.0))
        - pt.gammaln(0.5 * nu)
        - 0.5 * pt.log(nu * math.pi)
        - pt.log(scale)
        - 0.5 * (nu + 1.0) * pt.log1p(z * z / nu)
    )


def build_pymc_model(model, data: LikelihoodData):
    """A ``pm.Model`` with the same log density as quadshank's numpyro model of ``model`` on ``data``."""
    import pymc as pm
    import pytensor.tensor as pt

    names = {e.name for e in model.effects}
    if not names <= SUPPORTED:
        raise ValueError(f"the PyMC peer covers {sorted(SUPPORTED)}, not {sorted(names - SUPPORTED)}")
    if model.activation.name != "zero_order":
        raise ValueError("the PyMC peer is written for the zero-order activation (models 1 and 3)")
    L = data.n_legs
    R, K = data.response_length, data.max_shift
    log_w, _, _, prec, logdet, _ = spread_grid(tuple(int(i) for i in data.leg_subject))
    with pm.Model() as pmodel:
        leg, step_prior = {}, None
        for p in model_params(model):
            if p.name == "threshold":  # summed out in the likelihood, as in quadshank's fit
                step_prior = tuple(p.prior[1:3])
                continue
            if p.shape:
                raise ValueError(f"parameter {p.name!r} is a vector; the peer handles scalars")
            family, loc, scale = p.prior[:3]
            # the spreads summed out on quadshank's grid: s ~ Σ_g w_g MVN(0, C_g)
            s = pm.Flat(f"{p.name}_s_leg", shape=L)
            quad = pt.sum(pt.dot(prec, s) * s[None, :], axis=-1)  # (G,)
            pm.Potential(f"{p.name}_spread_prior", pt.logsumexp(log_w - 0.5 * (quad + logdet + L * math.log(2 * math.pi))))
            x = loc + scale * s
            leg[p.name] = pt.exp(x) if family == "lognormal" else x
        sigma = pm.LogNormal("sigma", mu=SIGMA_PRIOR[0], sigma=SIGMA_PRIOR[1], shape=L)
        nu = pm.Gamma("nu", alpha=NU_PRIOR[0], beta=NU_PRIOR[1], shape=L)
        shift_prior = log_shift_prior(K)
        total = 0.0
        for i in range(L):
            values = {k: v[i] for k, v in leg.items()} | {"threshold_prior": step_prior}
            total = total + _leg_marginal(pt, data, i, values, sigma[i], nu[i], R, K, shift_prior, step_prior is not None)
        pm.Potential("likelihood", total)
    return pmodel


def _leg_marginal(pt, data, i, v, sigma, nu, R, K, shift_prior, angle_delay):
    angle, velocity = data.angle[i].astype(float), data.velocity[i].astype(float)
    mask = data.sample_mask[i]
    passive = -v["damping"] * velocity - v["gravity"] * np.sin(np.deg2rad(angle)) + v["k1"] * (pt.exp(-v["k2"] * angle) - 1.0)
    e = pt.switch(mask, data.acceleration[i] - passive, 0.0)
    W = data.window_len.shape[-1]
    E = pt.zeros(W)[data.window[i]].inc(e)
    n = data.window_len[i]  # a window's sum as quadshank's window_noise: the sum's variance and kurtosis
    x = pt.maximum(nu - 4.0, 0.0)
    nu_w = nu + (n - 1.0) * x * x / (x + 0.5)
    scale = sigma * pt.sqrt(n * nu / nu_w * (1.0 + (nu_w - nu) / pt.maximum(nu - 2.0, 1.0)))
    lp0 = pt.switch(data.window_mask[i], _t_logpdf(pt, E, nu_w, scale), 0.0)
    F = 1.0
    if "gamma_angle" in v:
        F = F * (1.0 + v["gamma_angle"] * angle)
    if "gamma_velocity" in v:
        F = F * (1.0 + v["gamma_velocity"] * velocity)
    F = F * pt.ones(angle.shape)
    h_pad = pt.concatenate([pt.zeros(K), pt.stack([v["gain"]]), pt.zeros(R - 1 + K)])  # the one-sample response
    u = data.pulse_u[i][:, None]
    D, U = N_DELAYS, data.touch_window.shape[-1]
    ts, valid, pos = data.touch_sample[i], data.touch_valid[i], data.touch_pos[i]  # (D, P*(R+K))
    tw, tm = data.touch_window[i], data.touch_mask[i]  # (D, U)
    flat_pos = (pos + np.arange(D)[:, None] * U).ravel()

    def amplitudes(shift):  # (D, P*(R+K)): the one-sample response, F at the sample it reaches
        return pt.switch(valid, (u * h_pad[shift : shift + R + K][None, :]).ravel()[None, :] * F[ts], 0.0)

    a_long = amplitudes(0)
    M = pt.zeros(D * U)[flat_pos].inc(a_long.ravel()).reshape((D, U))
    r0 = E[tw] - M
    lp = _t_logpdf(pt, r0, nu_w[tw], scale[tw]) - lp0[tw]
    ell_long = pt.sum(lp0) + pt.sum(pt.switch(tm, lp, 0.0), axis=1)  # (D,)
    if not (K and angle_delay):
        return pt.logsumexp(ell_long - math.log(N_DELAYS) + shift_prior[:, 0])
    # the threshold summed out under the hard step, as quadshank's leg_loglik_by_threshold:
    # state j shortens the j pulses of lowest angle; running sums over (window, pulse) pairs
    Q, P = data.step_pair_mask.shape[-1], data.pulse_sample.shape[-1]
    rows_d = np.arange(D)[:, None]
    pair_window, pair_first = data.step_pair_window[i], data.step_pair_first[i]  # (D, Q)
    flat_pair = (data.step_entry_pair[i] + rows_d * Q).ravel()
    flat_pulse = (data.step_pair_pulse[i] + rows_d * P).ravel()
    r_pair = r0[rows_d, pair_window]
    s_pair = scale[tw][rows_d, pair_window]
    nu_pair = nu_w[tw][rows_d, pair_window]
    keep = data.step_pair_mask[i] & tm[rows_d, pair_window]
    order, valid_order = data.step_order[i], data.step_pulse_valid[i]
    a = angle[data.pulse_sample[i][order]]
    z = np.where(valid_order, (a - v["threshold_prior"][0]) / v["threshold_prior"][1], np.inf)
    edges = np.concatenate([[-np.inf], z, [np.inf]])
    from scipy.special import ndtr

    with np.errstate(divide="ignore"):
        log_mass = np.log(np.where(edges[:-1] + edges[1:] > 0, ndtr(-edges[:-1]) - ndtr(-edges[1:]), ndtr(edges[1:]) - ndtr(edges[:-1])))
    log_mass = np.maximum(log_mass, -1e30)

    def kernel(x):
        zz = x / s_pair
        return -0.5 * (nu_pair + 1.0) * pt.log1p(zz * zz / nu_pair)

    cols = [pt.logsumexp(ell_long[:, None] + log_mass[None, :], axis=1)]  # shift 0: every state alike
    for shift in range(1, K + 1):
        b = pt.zeros(D * Q)[flat_pair].inc((amplitudes(shift) - a_long).ravel()).reshape((D, Q))
        cs = pt.cumsum(b, axis=1)
        incl = cs - (cs[rows_d, pair_first] - b[rows_d, pair_first])
        delta = pt.switch(keep, kernel(r_pair - incl) - kernel(r_pair - incl + b), 0.0)
        per_pulse = pt.zeros(D * P)[flat_pulse].inc(delta.ravel()).reshape((D, P))
        steps = pt.switch(valid_order[None, :], per_pulse[:, order], 0.0)
        states = ell_long[:, None] + pt.concatenate([pt.zeros((D, 1)), pt.cumsum(steps, axis=1)], axis=1)  # (D, P + 1)
        cols.append(pt.logsumexp(states + log_mass[None, :], axis=1))
    logp = pt.stack(cols, axis=1) - math.log(N_DELAYS) + shift_prior  # (D, K + 1)
    return pt.logsumexp(logp)


def check_same_density(pmodel, numpyro_potential, point_unconstrained: dict) -> tuple[float, float]:
    """(PyMC log density, −numpyro potential) at the same unconstrained point.

    PyMC's log-transformed values are named ``{name}_log__``; numpyro's unconstrained
    values are keyed by site name.  Both include the transforms' Jacobians.
    """
    logp = pmodel.compile_logp(jacobian=True)
    ip = {}
    for rv in pmodel.value_vars:
        base = rv.name.removesuffix("_log__")
        ip[rv.name] = np.asarray(point_unconstrained[base], dtype=float)
    return float(logp(ip)), float(-numpyro_potential(point_unconstrained))
