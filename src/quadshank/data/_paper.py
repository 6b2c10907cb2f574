"""Numbers published in Franken et al. (1995), kept in one place.

Tables I–III give the active parameters per leg, Table V the mean k-step-ahead
angle prediction errors J_φ,p.  Units follow the paper: accelerations in
deg/s², angles in deg, velocities in deg/s, delays in samples of T_s = 10 ms.
"""

from __future__ import annotations

SAMPLING_PERIOD_S = 0.01
#: Horizons of eq. (12) in milliseconds; in samples of the paper's T_s; and the map between them.
HORIZONS_MS = (100, 250, 500, 1000)
HORIZONS = tuple(int(round(h / 1000 / SAMPLING_PERIOD_S)) for h in HORIZONS_MS)
HORIZON_MS = dict(zip(HORIZONS, HORIZONS_MS))
#: Largest delay scanned (samples), as in the paper.
MAX_DELAY = 10
#: Assumed twitch duration (samples) = length of an isolated-twitch epoch.
TWITCH_SAMPLES = 25
#: How long [s] after its pulse a twitch may still act on the shank: the largest delay and the
#: twitch at the paper's period (350 ms).
TWITCH_REACH_S = (MAX_DELAY + TWITCH_SAMPLES) * SAMPLING_PERIOD_S

LEGS = ("TN-left", "TN-right", "JM-left", "JM-right", "OT-left")

#: Table I: G'_1 [deg/s²] and delay d [samples].
TABLE_I = {
    "TN-left": {"G1": 1.46e4, "delay": 4},
    "TN-right": {"G1": 1.43e4, "delay": 5},
    "JM-left": {"G1": 7.98e3, "delay": 4},
    "JM-right": {"G1": 8.00e3, "delay": 5},
    "OT-left": {"G1": 7.32e3, "delay": 4},
}

#: Table II: model-2 DARMA coefficients (b' in deg/s²).
TABLE_II = {
    "TN-left": {"a1": -1.41, "a2": 0.60, "b1": 5.41e2, "b2": 6.45e2},
    "TN-right": {"a1": -1.46, "a2": 0.60, "b1": 5.14e2, "b2": 6.14e2},
    "JM-left": {"a1": -1.50, "a2": 0.60, "b1": 4.06e2, "b2": 3.24e2},
    "JM-right": {"a1": -1.42, "a2": 0.61, "b1": 5.33e2, "b2": 6.40e2},
    "OT-left": {"a1": -1.49, "a2": 0.55, "b1": 4.22e2, "b2": 3.28e2},
}

#: Table III: model 3, G'_2 [deg/s²], γ_angle [1/deg], γ_velocity [s/deg].
TABLE_III = {
    "TN-left": {"G2": 1.67e4, "gamma_angle": -7.31e-3, "gamma_velocity": -1.64e-3},
    "TN-right": {"G2": 1.55e4, "gamma_angle": -5.31e-3, "gamma_velocity": -2.05e-3},
    "JM-left": {"G2": 8.67e3, "gamma_angle": -2.16e-2, "gamma_velocity": -1.60e-3},
    "JM-right": {"G2": 8.46e3, "gamma_angle": -1.90e-2, "gamma_velocity": -1.70e-3},
    "OT-left": {"G2": 7.74e3, "gamma_angle": -9.40e-3, "gamma_velocity": -2.50e-3},
}

#: Table IV: % RMS error of the integrated twitch response, model 1 and model 3.
TABLE_IV = {
    "TN-left": (30, 20),
    "TN-right": (34, 21),
    "JM-left": (48, 12),
    "JM-right": (32, 29),
    "OT-left": (21, 15),
}

#: Table V: mean (s.d.) of J_φ,p [deg] over legs, per trial, model and horizon [ms].
TABLE_V = {
    "1": {
        "model1": {100: (2.7, 0.6), 250: (5.7, 1.0), 500: (6.4, 1.9), 1000: (10.5, 2.5)},
        "model2": {100: (2.7, 0.6), 250: (5.8, 1.0), 500: (6.5, 1.9), 1000: (8.2, 2.5)},
        "model3": {100: (2.7, 0.6), 250: (5.4, 1.1), 500: (5.4, 1.3), 1000: (6.7, 1.7)},
    },
    "2": {
        "model1": {100: (2.5, 0.5), 250: (6.9, 1.6), 500: (9.8, 3.8), 1000: (12.4, 4.0)},
        "model2": {100: (2.5, 0.5), 250: (6.9, 1.6), 500: (9.9, 3.8), 1000: (12.5, 4.0)},
        "model3": {100: (2.5, 0.6), 250: (5.5, 1.1), 500: (6.0, 1.6), 1000: (7.5, 2.3)},
    },
    "3": {
        "model1": {100: (1.9, 0.4), 250: (4.6, 1.1), 500: (5.8, 1.7), 1000: (6.7, 3.5)},
        "model2": {100: (1.9, 0.4), 250: (5.2, 1.0), 500: (7.3, 2.1), 1000: (8.2, 3.5)},
        "model3": {100: (1.9, 0.4), 250: (4.5, 1.1), 500: (5.5, 1.6), 1000: (6.3, 2.4)},
    },
}

#: Mean RMS of the measured knee angle per trial [deg] (Table V caption).
RMS_ANGLE = {"1": 23.6, "2": 24.1, "3": 19.3}

#: Recruitment level per trial in the protocol.
TRIAL_RECRUITMENT = {1: 1.0, 2: 1.0, 3: 0.5}

#: Knee angle [deg] below which the delay was one sample shorter (section IV-C).
DELAY_STEP_ANGLE = -20.0
