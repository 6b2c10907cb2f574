"""J_φ,p as a user would write it: a plain per-window NumPy loop (the benchmark's baseline).

Written independently of quadshank's JAX code, following the paper's text
(section III-E): from each start n, the passive state is the measured one,
the active part of model 2 is carried over from the previous run, the passive
system is integrated with RK4 per T_s with the active torque held constant.
"""

from __future__ import annotations

import math

import numpy as np


def _acc(phi, dphi, m, p):
    return (
        m
        - p["damping"] * dphi
        - p["gravity"] * math.sin(math.radians(phi))
        + p["k1"] * (math.exp(-p["k2"] * phi) - 1.0)
    )


def _rk4(phi, dphi, m, p, dt):
    k1a, k1v = dphi, _acc(phi, dphi, m, p)
    k2a, k2v = dphi + 0.5 * dt * k1v, _acc(phi + 0.5 * dt * k1a, dphi + 0.5 * dt * k1v, m, p)
    k3a, k3v = dphi + 0.5 * dt * k2v, _acc(phi + 0.5 * dt * k2a, dphi + 0.5 * dt * k2v, m, p)
    k4a, k4v = dphi + dt * k3v, _acc(phi + dt * k3a, dphi + dt * k3v, m, p)
    return (phi + dt / 6 * (k1a + 2 * k2a + 2 * k3a + k4a), dphi + dt / 6 * (k1v + 2 * k2v + 2 * k3v + k4v))


def j_phi_loop(model: str, params: dict, delay: int, angle, velocity, stimulation, horizons=(10, 25, 50, 100), dt=0.01):
    """J [deg] per horizon for 'model1', 'model2' or 'model3' with the given parameters."""
    angle = np.asarray(angle, float)
    velocity = np.asarray(velocity, float)
    u = np.asarray(stimulation, float)
    n = len(u)
    H = max(horizons)

    def u_del(k):
        return u[k - delay] if k - delay >= 0 else 0.0

    # model 2: activation history (M_{k-1}, M_{k-2}) carried from run to run
    m_prev = [0.0, 0.0]
    sq = {p: 0.0 for p in horizons}
    count = 0
    for start in range(n - H):
        phi, dphi = angle[start], velocity[start]
        mh = list(m_prev)
        carried = None
        for j in range(H):
            k = start + j
            if model == "model1":
                m = params["gain"] * u_del(k)
            elif model == "model3":
                m = params["gain"] * u_del(k) * (1 + params["gamma_angle"] * phi) * (1 + params["gamma_velocity"] * dphi)
            else:
                m = (
                    -params["a1"] * mh[0]
                    - params["a2"] * mh[1]
                    + params["b1"] * (u[k - 1 - delay] if k - 1 - delay >= 0 else 0.0)
                    + params["b2"] * (u[k - 2 - delay] if k - 2 - delay >= 0 else 0.0)
                )
                mh = [m, mh[0]]
                if j == 0:
                    carried = list(mh)
            phi, dphi = _rk4(phi, dphi, m, params, dt)
            if j + 1 in sq:
                sq[j + 1] += (angle[k + 1] - phi) ** 2
        if model == "model2":
            m_prev = carried
        count += 1
    return {p: math.sqrt(sq[p] / count) for p in horizons}
