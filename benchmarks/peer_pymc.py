"""The benchmark's peer: quadshank's hierarchical model written in PyMC, sampled by nutpie.

The same joint density as :func:`quadshank._fit.numpyro_model` for the paper's
model 3 with the angle-dependent delay (or without it): legs standardised by
their priors with the population mean, subject level and spreads integrated out
(s_leg ~ Σ_g w_g MVN(0, 11ᵀ + r_s,g²S + r_l,g²I) on quadshank's grid of spreads), per-leg Student-t noise on twitch-window
sums of the equivalent acceleration, the delay d ∈ {0…10} and the shift summed
out by log-sum-exp.  It reads the same touch tables (``quadshank._likelihood.prepare``)
and is checked against quadshank's log density at a common point
(:func:`check_same_density`) before any timing is trusted.

Needs the optional ``bench`` extra (pymc, nutpie); nothing in quadshank imports it.
"""

from __future__ import annotations

import math

import numpy as np

from quadshank._fit import NU_PRIOR, SIGMA_PRIOR, log_shift_prior, model_params, spread_grid
from quadshank._likelihood import N_DELAYS, LikelihoodData

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
        leg = {}
        for p in model_params(model):
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
            total = total + _leg_marginal(pt, data, i, {k: v[i] for k, v in leg.items()}, sigma[i], nu[i], R, K,
                                          shift_prior, "threshold" in leg)  # fmt: skip
        pm.Potential("likelihood", total)
    return pmodel


def _leg_marginal(pt, data, i, v, sigma, nu, R, K, shift_prior, angle_delay):
    angle, velocity = data.angle[i].astype(float), data.velocity[i].astype(float)
    mask = data.sample_mask[i]
    passive = -v["damping"] * velocity - v["gravity"] * np.sin(np.deg2rad(angle)) + v["k1"] * (pt.exp(-v["k2"] * angle) - 1.0)
    e = pt.switch(mask, data.acceleration[i] - passive, 0.0)
    W = data.window_len.shape[-1]
    E = pt.zeros(W)[data.window[i]].inc(e)
    scale = sigma * np.sqrt(data.window_len[i])
    lp0 = pt.switch(data.window_mask[i], _t_logpdf(pt, E, nu, scale), 0.0)
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
    cols = []
    for shift in range(K + 1):
        long = h_pad[: R + K][None, :]
        if K and angle_delay:
            w = pt.sigmoid((v["threshold"] - angle[data.pulse_sample[i]]) / 1.0)[:, None]
            short = h_pad[shift: shift + R + K][None, :]
            amp = (u * ((1.0 - w) * long + w * short)).ravel()
        else:
            amp = (u * long).ravel()
        c = pt.switch(valid, amp[None, :] * F[ts], 0.0)  # (D, P*(R+K))
        M = pt.zeros(D * U)[flat_pos].inc(c.ravel()).reshape((D, U))
        lp = _t_logpdf(pt, E[tw] - M, nu, scale[tw]) - lp0[tw]
        cols.append(pt.sum(pt.switch(tm, lp, 0.0), axis=1))
    ll = pt.sum(lp0) + pt.stack(cols, axis=1)  # (D, K + 1)
    logp = ll - math.log(N_DELAYS) + shift_prior
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
