"""Simulated cohort: a continuous-time "truth" of the paper's experiment.

The simulator produces recordings in the form of the paper's data (knee angle
from a goniometer, angular acceleration from accelerometers, the stimulation
sequence; T_s = 10 ms) for the five legs TN-left, TN-right, JM-left, JM-right
and OT-left, three trials each.  It is deliberately *richer* than the paper's
discrete models (3)–(5), so that identification methods can be judged against
a known truth that none of them contains exactly.

Protocol
--------
Trials 1, 2, 3 are run in this order with 15 min rest in between, 5 min each
by default; trials 1 and 2 at recruitment u = 1, trial 3 at u = 0.5
(section III-C).  Each trial starts with the shank hanging at rest.

Plant (continuous time, integrated with RK4 at 1 ms)
----------------------------------------------------
Passive system, eq. (8) with φ in degrees (the sine takes φ·π/180)::

    φ̈ = M/I − D'·φ̇ − G'·sin φ + k1'·(exp(−k2·φ) − 1) − R(φ)

R is the knee's range (always on, :data:`KNEE_RANGE`): towards full extension and deep flexion
the passive torque rises steeply, as capsule, ligaments and stretched muscles stop a real knee::

    R(φ) = K·exp((φ − φ_ext)/w) − K·exp((φ_flex − φ)/w),   K = 1000 deg/s², w = 1.5°,
    φ_ext = 88°, φ_flex = −66°

It is negligible within −55°…77° (below 1 deg/s²) and stops the rare large swings of random
stimulation: every trial of the default and hidden-effect cohorts stays within the anatomical
range :data:`ANATOMICAL_RANGE_DEG` (−75°…+100°: deep flexion of a seated knee to slight
hyperextension).  The paper's models (eq. 8) have no such term; the model library's
``extension_limit`` describes the extension side (the loop offers it), eq. (8)'s exponential
elasticity the flexion side.

Active system: every pulse j (time t_j, recruitment u_j) adds a twitch of
equivalent acceleration ``u_j·A·h(t − t_j − τ)`` with
``h(s) = s/tc²·exp(−s/tc)`` (s > 0, unit integral) and ``A = G'_2·T_s``, so the
sum over the 10-ms samples of M/I per twitch is G'_2, the paper's integrated
twitch response (Table III).  The superposition of twitches is realised
exactly as a critically damped second-order filter ``1/(tc·s + 1)²`` driven by
impulses; the delay τ is realised on the 1-ms grid with a pending-impulse
buffer.  The twitch time constant follows Table II: the sampled twitch of a
double pole at ρ = exp(−T_s/tc) has a2 = ρ², so ``tc = −T_s/ln(√a2)``
(33.5–40.4 ms).  The delay is the Table I delay plus a fractional part:
+0.3 sample for the 4-sample legs and −0.3 sample for the 5-sample legs
(τ = 43 ms and 47 ms), so it is never a whole number of samples but the
nearest whole sample is the paper's.  Note that the twitch decays slowly: of
its integral, 96–99 % lies within the paper's 25-sample epoch (the fraction
per leg is ``epoch_fraction`` in the truth).

Each twitch is scaled by the state at its onset, the instant t_j + τ at
which it starts to act (the continuous analogue of model 3, eq. 5, where
the pulse reaching the muscle at sample k is scaled by φ_k and φ̇_k)::

    M/I(t) = Σ_j u_j · A · f(φ(t_j + τ)) · g(φ̇(t_j + τ)) · h(t − t_j − τ),
    f = max(0, 1 + γ_angle·φ),  g = max(0, 1 + γ_velocity·φ̇)

with γ from Table III.  The ``max(0, ·)`` is there because a muscle cannot
push the shank backwards: the linear relations of the paper would turn
negative above φ ≈ 46° (JM-left) or φ̇ ≈ 400–600 deg/s.  Modulating the
whole twitch by its onset state, rather than continuously, is what makes the
truth have the paper's model-3 *structure*: with continuous modulation the
velocity change that gravity causes during the ~100 ms twitch leaks into the
torque–angle factor, and eq. (11) estimates γ_angle off by about
+γ_velocity·G'·(π/180)·100 ms ≈ +0.005/deg.  The hidden effects
``torque_angle_peak`` and ``hill_velocity`` replace f and g in the same
place.

Passive parameters
------------------
A paraplegic shank plus foot weighs about 4.5 kg with its centre of mass
about 0.25 m below the knee and a moment of inertia about the knee of about
0.35 kg·m².  As a pendulum, ω² = m·g·l/I ≈ 31.5 s⁻², i.e. f ≈ 0.9 Hz, and
G' = ω²·180/π ≈ 1800 deg/s² (small angles: ω² = G'·π/180).  Reference [16]
of the paper (Franken et al. 1993) identified lightly damped pendulum
dynamics with an elasticity that matters only in flexion (hence the
exponential term).  The values below are fixed (not random) and give
natural frequencies of 0.85–0.93 Hz, damping ratios 0.08–0.12 and an elastic
torque of 14–17 % of gravity at φ = −40° but ≤ 2 % at +60°.  The legs with
the weaker quadriceps (JM, OT) were given the lower gravity and damping
values, so that every leg can be driven through the operating range:

=========  ======  =====  =====  =====  ======  =====
leg        G'      D'     k1'    k2     f [Hz]  ζ
=========  ======  =====  =====  =====  ======  =====
TN-left    1950    1.30   30     0.050  0.93    0.11
TN-right   1900    1.40   35     0.048  0.92    0.12
JM-left    1700    0.90   20     0.055  0.87    0.08
JM-right   1720    0.95   25     0.050  0.87    0.09
OT-left    1650    0.86   15     0.060  0.85    0.08
=========  ======  =====  =====  =====  ======  =====

(G', k1' in deg/s², D' in 1/s, k2 in 1/deg; ζ = D'/(2ω).)

Stimulation
-----------
Pulses fall on 10-ms sample boundaries.  The interpulse intervals (IPIs)
follow a two-part density (ref. [22], Hunter & Korenberg 1983): a short part,
uniform on the multiples of 10 ms in [20, 120] ms (summating twitches), and a
long part, uniform on [0.5, 1.5] s (isolated twitches).  The sequence is a
succession of cycles: with probability ``p_burst`` a burst of b short IPIs
(b uniform on 1..``max_burst``), then one long IPI.  Bounding the runs of
short IPIs (the density's correlation structure, which [22] lets one specify
together with the density) keeps the swing within the operating range;
unbounded geometric runs of short IPIs produce rare, very large swings.  A
pulse counts as *isolated* when it has ≥ 250 ms without a pulse before it and
≥ 500 ms after it (the 25-sample epoch followed by a quiet twitch duration,
section III-D); every pulse that ends a long IPI and is followed by one is
isolated.  The long part reaches past the swing's period (1.1–1.2 s) on
purpose: with long IPIs of at most 1 s, the pulse ending one lands on the
back-swing after the previous burst, nearly every isolated twitch is
recorded while the shank falls into flexion (f·g ≈ 1.14), and G'_1 comes
out about 14 % above G'_2, where the paper's Tables I and III have G'_1 5–13 %
*below* G'_2.  Model 1 then over-drives every burst and its 1-s predictions
swing past 120°; spread over the swing, the isolated twitches give G'_1
within a few % of G'_2.

The density was calibrated per leg and recruitment level (as an
experimenter would, to bring each leg through the operating range; section
III-C) so that the cohort's mean RMS knee angle about 0 is near the paper's
23.6°/24.1° (trials 1–2) and 19.3° (trial 3), with bursts short enough
(at most 3–5 pulses at u = 1) that the models without angle and velocity
dependence (1 and 2) are not driven far past the measured swing:

=========  ====================  ====================
leg        u = 1: p_burst, max   u = 0.5: p_burst, max
=========  ====================  ====================
TN-left    0.25, 3               0.80, 6
TN-right   0.30, 3               0.90, 7
JM-left    0.55, 4               0.95, 11
JM-right   0.65, 4               0.95, 12
OT-left    0.75, 5               0.95, 14
=========  ====================  ====================

The swing saturates: longer or more frequent bursts mostly raise the mean
angle, because the velocity dependence g removes energy (twitches during
flexion are stronger than during extension) and f vanishes in extension for
JM.  With seed 0 and 5-min trials the mean RMS angle is 23.7° (trial 1),
24.5° (trial 2) and 18.8° (trial 3); per leg 21.9–26.2° at u = 1 and
15.8–22.5° at u = 0.5 (TN swings most).  99 % of the samples of trials 1–2
lie within −44°…70° (2.5 % outside −40°…60°, 0.03 % beyond 85°); the
extremes reach −64° and 93° (TN-left), and −71° and 94° with seeds 1 and 2,
where the knee's range stops the rare large swings.  Trial 1 has
55 (OT-left) to 216 (TN-left) isolated twitches per leg, of 451–829 pulses.

Sensors (always on)
-------------------
Goniometer: additive white noise (σ = 0.1°), then quantisation to 0.05°.
Accelerometer: the instantaneous angular acceleration at the sample instant
plus white noise (σ = 40 deg/s²).  The recorded stimulation is u at pulse
samples and 0 elsewhere.  No velocity is recorded: it is derived from the
angle off-line as the paper did (:func:`quadshank.derive_velocity`).

Hidden effects (off by default, switched on by name)
----------------------------------------------------
``torque_angle_peak``
    f(φ) = exp(−((φ − φ_opt)² − φ_opt²)/(2 w²)), φ_opt = 15°, w = 25°: a
    maximum inside the range, f(0) = 1.
``hill_velocity``
    g = (1 − v/v_max)/(1 + v/(k·v_max)) for shortening (v = φ̇ > 0), clipped
    at 0, v_max = 600 deg/s, k = 0.25; an eccentric plateau for v < 0:
    g = 1 + (g_ecc − 1)·(−v)/(−v + v_half), g_ecc = 1.5, v_half = 50 deg/s.
``angle_delay``
    the delay of a pulse is 10 ms shorter when φ at the pulse time is below
    −20° (section IV-C).
``fatigue``
    twitch gain × (f_min + (1 − f_min)·exp(−n/N_f)), n = pulses delivered so
    far, f_min = 0.5, N_f = 800; over the 15-min rest n recovers as
    n·exp(−15 min/τ_rec), τ_rec = 10 min.
``potentiation``
    twitch amplitude × (1 + P·exp(−(IPI − T_s)/τ_p)) for the preceding IPI,
    P = 0.8, τ_p = 60 ms.
``recruitment_power``
    a pulse of recruitment level u recruits u^κ of the muscle, κ = 1.5,
    instead of u: the protocol's trial 3 (u = 0.5) twitches at 0.35 of trial
    1's rather than half.  Only trials of different levels show it.
``accel_resonance``
    the accelerometer sits on soft tissue: the measured acceleration is that
    of a base-excited second-order system (f_r = 18 Hz, ζ = 0.25) integrated
    with the plant at 1 ms, giving ripple and overshoot after twitches (the
    paper's Fig. 2(d) discussion).
``goniometer_offset``
    the goniometer reads 3° when the shank hangs at rest (zeroed with the
    leg not quite vertical); the movement is unchanged.
``gravity_offset``
    gravity acts about 10° of extension instead of angle 0 (−G'·sin(φ − 10°)),
    the elasticity about 0 as before, so the shank rests near 10°; each
    trial starts at that rest.
``extension_limit``
    a range in extension that ends early (a contracture, say): a passive
    torque −1000·exp((φ − 75°)/5°) deg/s² besides the knee's own range, so
    the shank no longer swings far beyond 80°.

Twitches that vary (on by default)
----------------------------------
Each pulse's twitch amplitude is multiplied by a log-normal factor with mean 1 and coefficient
of variation ``twitch_cv`` (:data:`TWITCH_CV`, 0.2), drawn per pulse from a stream of its own
(the IPIs and sensor noise do not depend on it).  The paper's Table IV shows that even model 3
leaves 12–29 % RMS error in the integrated twitch responses, so real twitches vary from pulse to
pulse far beyond sensor noise: with CV 0.2 the simulated Table IV errors of model 3 are about
20 %, with ``twitch_cv=0`` (equal twitches) 1–3 %.  The model effect ``twitch_variability`` is
the likelihood's term for it.

Randomness
----------
All randomness (IPIs, sensor noise) comes from numpy Generators seeded by
``SeedSequence(seed, spawn_key=(leg index in LEGS, trial))``, so the data of a
leg do not depend on which other legs or trials are simulated, and the same
seed gives identical arrays.
"""

from __future__ import annotations

import functools
import json
import math
import os
from collections.abc import Iterable, Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from scipy.optimize import brentq
from tqdm.auto import tqdm

from ..common._arrays import is_whole_number
from ..common._io import write_json
from ._cohort import Cohort, Trial, mark_checked
from ._paper import (
    DELAY_STEP_ANGLE,
    LEGS,
    SAMPLING_PERIOD_S,
    TABLE_I,
    TABLE_II,
    TABLE_III,
    TRIAL_RECRUITMENT,
    TWITCH_SAMPLES,
)

__all__ = [
    "simulate_pendulum_test",
    "EFFECTS",
    "TWITCH_CV",
    "KNEE_RANGE",
    "ANATOMICAL_RANGE_DEG",
    "PASSIVE_TRUTH",
    "STIMULATION_DENSITY",
    "SENSOR",
    "default_truth",
    "simulate_cohort",
    "simulate_response",
    "stimulation_sequence",
    "isolated_pulses",
    "write_truth",
]

TRUTH_FORMAT = "quadshank-truth/1"

#: Internal integration step [s] and substeps per sample.
INTERNAL_STEP_S = 0.001
#: Rest between successive trials [s].
REST_BETWEEN_TRIALS_S = 15 * 60.0
#: Length [ms] of the shift register holding pending (delayed) twitch impulses.
_BUFFER = 64
#: Samples per jitted chunk of the time loop (one compilation serves any duration).
_CHUNK = 1500
#: Unrolling of the 10 internal steps of a sample (unrolling only slows XLA on CPU).
_UNROLL = 1

#: Known hidden effects, in a fixed order.
EFFECTS = (
    "torque_angle_peak",
    "hill_velocity",
    "angle_delay",
    "fatigue",
    "potentiation",
    "recruitment_power",
    "accel_resonance",
    "goniometer_offset",
    "gravity_offset",
    "extension_limit",
)

#: Parameters of each hidden effect (the same for every leg).
EFFECT_PARAMETERS = {
    "torque_angle_peak": {"phi_opt_deg": 15.0, "width_deg": 25.0},
    "hill_velocity": {"vmax_deg_s": 600.0, "k": 0.25, "g_ecc": 1.5, "v_half_deg_s": 50.0},
    "angle_delay": {"angle_deg": float(DELAY_STEP_ANGLE), "shortening_s": SAMPLING_PERIOD_S},
    "fatigue": {"f_min": 0.5, "n_f_pulses": 800.0, "tau_rec_s": 600.0, "rest_s": REST_BETWEEN_TRIALS_S},
    "potentiation": {"P": 0.8, "tau_p_s": 0.06},
    "recruitment_power": {"kappa": 1.5},
    "accel_resonance": {"f_r_hz": 18.0, "zeta": 0.25},
    "goniometer_offset": {"offset_deg": 3.0},
    "gravity_offset": {"angle_deg": 10.0},
    "extension_limit": {"phi_limit_deg": 75.0, "width_deg": 5.0, "torque_deg_s2": 1000.0},
}

#: Coefficient of variation of the twitches' amplitudes from pulse to pulse (module docs).
TWITCH_CV = 0.2

#: True passive parameters per leg: D' [1/s], G' [deg/s²], k1' [deg/s²], k2 [1/deg].
PASSIVE_TRUTH = {
    "TN-left": {"damping": 1.30, "gravity": 1950.0, "k1": 30.0, "k2": 0.050},
    "TN-right": {"damping": 1.40, "gravity": 1900.0, "k1": 35.0, "k2": 0.048},
    "JM-left": {"damping": 0.90, "gravity": 1700.0, "k1": 20.0, "k2": 0.055},
    "JM-right": {"damping": 0.95, "gravity": 1720.0, "k1": 25.0, "k2": 0.050},
    "OT-left": {"damping": 0.86, "gravity": 1650.0, "k1": 15.0, "k2": 0.060},
}

#: Fractional part added to the paper's whole-sample delay (Table I).
DELAY_FRACTION = {4: 0.3, 5: -0.3}

#: Sensor chain (always on).
SENSOR = {
    "angle_noise_deg": 0.1,
    "angle_resolution_deg": 0.05,
    "acceleration_noise_deg_s2": 40.0,
}

#: Short and long parts of the two-part IPI density [s] (multiples of T_s, inclusive).
IPI_SHORT_S = (0.02, 0.12)
IPI_LONG_S = (0.5, 1.5)
#: Burst probability and longest burst per leg and recruitment level (calibrated).
_BURSTS = {
    #            u = 1: (p_burst, max_burst)   u = 0.5
    "TN-left": {"1.0": (0.25, 3), "0.5": (0.80, 6)},
    "TN-right": {"1.0": (0.30, 3), "0.5": (0.90, 7)},
    "JM-left": {"1.0": (0.55, 4), "0.5": (0.95, 11)},
    "JM-right": {"1.0": (0.65, 4), "0.5": (0.95, 12)},
    "OT-left": {"1.0": (0.75, 5), "0.5": (0.95, 14)},
}
#: IPI density per leg and recruitment level (keys are ``f"{u:.1f}"``).
STIMULATION_DENSITY = {
    leg: {
        u: {"p_burst": pb, "max_burst": mb, "short_s": list(IPI_SHORT_S), "long_s": list(IPI_LONG_S)}
        for u, (pb, mb) in levels.items()
    }
    for leg, levels in _BURSTS.items()
}

#: Isolation criterion for counting twitches: quiet time before / after a pulse [s].
ISOLATION_BEFORE_S = TWITCH_SAMPLES * SAMPLING_PERIOD_S
ISOLATION_AFTER_S = 2 * TWITCH_SAMPLES * SAMPLING_PERIOD_S

_DEG = math.pi / 180.0


# ----------------------------------------------------------------------------- checks
def check_effects(effects) -> tuple[str, ...]:
    """The simulator's effects named in ``effects``, in the simulator's order; unknown names refused."""
    if isinstance(effects, str):
        effects = (effects,)
    effects = tuple(effects or ())
    if "twitch_variability" in effects:
        raise ValueError(f"twitch_variability is not a hidden effect: the simulated twitches vary by default (CV "
                         f"{TWITCH_CV:g}); set twitch_cv (--twitch-cv) for another variation, 0 for equal twitches")
    unknown = [e for e in effects if e not in EFFECTS]
    if unknown:
        raise ValueError(f"unknown effect(s) {', '.join(map(repr, unknown))}; known effects: {', '.join(EFFECTS)}")
    return tuple(e for e in EFFECTS if e in effects)


def check_legs(legs) -> tuple[str, ...]:
    if isinstance(legs, str):
        legs = (legs,)
    legs = tuple(legs)
    if not legs:
        raise ValueError(f"legs: give at least one leg; known legs: {', '.join(LEGS)}")
    unknown = [leg for leg in legs if leg not in LEGS]
    if unknown:
        raise ValueError(f"unknown leg(s) {', '.join(map(repr, unknown))}; known legs: {', '.join(LEGS)}")
    if len(set(legs)) != len(legs):
        raise ValueError(f"duplicated legs in {legs}")
    return legs


def check_trials(trials) -> tuple[int, ...]:
    trials = tuple(trials)
    if not trials:
        raise ValueError(f"trials: give at least one trial; the protocol has trials {tuple(TRIAL_RECRUITMENT)}")
    bad = [t for t in trials if not is_whole_number(t) or t not in TRIAL_RECRUITMENT]
    if bad:
        raise ValueError(f"unknown trial(s) {bad}; the protocol has trials {tuple(TRIAL_RECRUITMENT)}")
    return tuple(sorted(set(trials)))


# ----------------------------------------------------------------------------- truth
def _twitch_tc(leg: str) -> float:
    return -SAMPLING_PERIOD_S / math.log(math.sqrt(TABLE_II[leg]["a2"]))


def _delay_samples(leg: str) -> float:
    d = TABLE_I[leg]["delay"]
    return d + DELAY_FRACTION.get(d, 0.3)


def _sampled_twitch(G2: float, tc: float, delay_samples: float, n: int = 100) -> np.ndarray:
    """Noise-free M/I at the sample instants k·T_s after a pulse at k = 0 (u = 1, f = g = 1)."""
    s = (np.arange(n) - delay_samples) * SAMPLING_PERIOD_S
    pos = np.clip(s, 0.0, None)
    return np.where(s > 0, G2 * SAMPLING_PERIOD_S * pos / tc**2 * np.exp(-pos / tc), 0.0)


def _darma_fit(y: np.ndarray, d: int) -> dict:
    """Least-squares DARMA(2,2) fit (eq. 4) of an impulse response y (u = 1 at k = 0).

    y_k = −a1 y_{k−1} − a2 y_{k−2} + b1 u_{k−1−d} + b2 u_{k−2−d}.
    """
    n = y.size
    u = np.zeros(n)
    u[0] = 1.0
    ypad = np.concatenate([np.zeros(2), y])
    upad = np.concatenate([np.zeros(d + 2), u])
    k = np.arange(n)
    X = np.column_stack([-ypad[k + 1], -ypad[k], upad[k + 1], upad[k]])
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    a1, a2, b1, b2 = (float(c) for c in coef)
    return {"a1": a1, "a2": a2, "b1": b1, "b2": b2, "delay": int(d)}


def default_truth(legs: Sequence[str] = LEGS, effects: Iterable[str] = ()) -> dict:
    """Every true parameter of the simulated cohort, JSON-serialisable.

    Per leg: passive parameters (``damping`` D' [1/s], ``gravity`` G' [deg/s²],
    ``k1`` k1' [deg/s²], ``k2`` [1/deg], with the implied natural frequency and
    damping ratio), active parameters (G2, gamma_angle, gamma_velocity,
    delay_samples, delay_s, twitch_tc_s, twitch_area A = G2·T_s), the
    parameters of the switched-on hidden effects, and the equivalents of the
    paper's models 1 and 2 (``model2_equivalent``: least-squares DARMA(2,2)
    fit of eq. (4) to the noise-free sampled unmodulated twitch, with
    d = floor(delay_samples)).  Also the sensor chain, the stimulation density
    and the protocol.
    """
    legs = check_legs(legs)
    effects = check_effects(effects)
    out_legs = {}
    for leg in legs:
        subject, side = leg.split("-")
        p = PASSIVE_TRUTH[leg]
        omega2 = p["gravity"] * _DEG
        omega = math.sqrt(omega2)
        G2 = TABLE_III[leg]["G2"]
        tc = _twitch_tc(leg)
        dl = _delay_samples(leg)
        d = int(math.floor(dl))
        y = _sampled_twitch(G2, tc, dl, n=120)
        epoch = _sampled_twitch(G2, tc, dl, n=TWITCH_SAMPLES).sum()
        s_end = (TWITCH_SAMPLES * SAMPLING_PERIOD_S - dl * SAMPLING_PERIOD_S) / tc
        out_legs[leg] = {
            "subject": subject,
            "side": side,
            "passive": {
                **{k: float(v) for k, v in p.items()},
                "natural_frequency_hz": omega / (2 * math.pi),
                "damping_ratio": p["damping"] / (2 * omega),
                "elastic_fraction_of_gravity_at_-40deg": p["k1"] * (math.exp(40 * p["k2"]) - 1)
                / (p["gravity"] * math.sin(40 * _DEG)),
            },
            "active": {
                "G2": float(G2),
                "gamma_angle": float(TABLE_III[leg]["gamma_angle"]),
                "gamma_velocity": float(TABLE_III[leg]["gamma_velocity"]),
                "delay_samples": float(dl),
                "delay_s": float(dl * SAMPLING_PERIOD_S),
                "delay_paper_samples": int(TABLE_I[leg]["delay"]),
                "twitch_tc_s": float(tc),
                "twitch_area": float(G2 * SAMPLING_PERIOD_S),
                "sampled_twitch_sum": float(y.sum()),
                "epoch_sum": float(epoch),
                "epoch_fraction": float(1.0 - (1.0 + s_end) * math.exp(-s_end)),
            },
            "effects": {e: dict(EFFECT_PARAMETERS[e]) for e in effects},
            "model1_equivalent": {"G1": float(G2)},
            "model2_equivalent": _darma_fit(y, d),
        }
    return {
        "format": TRUTH_FORMAT,
        "sampling_period_s": SAMPLING_PERIOD_S,
        "internal_step_s": INTERNAL_STEP_S,
        "effects": list(effects),
        "effect_parameters": {e: dict(EFFECT_PARAMETERS[e]) for e in effects},
        "legs": out_legs,
        "knee_range": dict(KNEE_RANGE),
        "sensor": dict(SENSOR),
        "stimulation_density": {leg: json.loads(json.dumps(STIMULATION_DENSITY[leg])) for leg in legs},
        "isolation": {"quiet_before_s": ISOLATION_BEFORE_S, "quiet_after_s": ISOLATION_AFTER_S},
        "protocol": {
            "trials": {str(t): {"recruitment": float(u)} for t, u in TRIAL_RECRUITMENT.items()},
            "rest_between_trials_s": REST_BETWEEN_TRIALS_S,
            "initial_state": {"angle_deg": 0.0, "velocity_deg_s": 0.0},
        },
    }


# ----------------------------------------------------------------------------- stimulation
def _density(leg: str, u: float) -> dict:
    levels = STIMULATION_DENSITY[leg]
    key = f"{float(u):.1f}"
    return levels.get(key, levels["1.0"])


def stimulation_sequence(
    rng: np.random.Generator, n_samples: int, density: dict, sampling_period_s: float = SAMPLING_PERIOD_S
) -> np.ndarray:
    """Pulse sample indices of one pseudorandom-IPI sequence (pulses on sample boundaries).

    The sequence is a succession of cycles: with probability ``p_burst`` a
    burst of b short IPIs (b uniform on 1..``max_burst``, each uniform on the
    multiples of T_s in ``short_s``), then one long IPI (uniform on the
    multiples of T_s in ``long_s``).  The IPI density is thus two-part, with
    the length of runs of short IPIs bounded.  Cycles are drawn in fixed
    blocks, so a longer sequence from the same generator state starts with the
    shorter one.  T_s is ``sampling_period_s``, the recording's.
    """
    ts = sampling_period_s
    s_lo, s_hi = (int(round(x / ts)) for x in density["short_s"])
    l_lo, l_hi = (int(round(x / ts)) for x in density["long_s"])
    bmax = int(density["max_burst"])
    pulses = []
    k = 0
    block = 128
    while True:
        burst = rng.random(block) < density["p_burst"]
        length = rng.integers(1, bmax + 1, size=block)
        shorts = rng.integers(s_lo, s_hi + 1, size=(block, bmax))
        longs = rng.integers(l_lo, l_hi + 1, size=block)
        keep = np.arange(bmax)[None, :] < np.where(burst, length, 0)[:, None]
        ipi_mat = np.concatenate([np.where(keep, shorts, 0), longs[:, None]], axis=1)
        ipi = ipi_mat[ipi_mat > 0]
        ks = k + np.cumsum(ipi)
        inside = ks < n_samples
        pulses.append(ks[inside])
        if not inside.all():
            break
        k = int(ks[-1])
    return np.concatenate(pulses).astype(np.int64)


def isolated_pulses(pulses: np.ndarray, n_samples: int, sampling_period_s: float = SAMPLING_PERIOD_S) -> np.ndarray:
    """Boolean mask of isolated pulses: ≥ 250 ms quiet before and ≥ 500 ms after (pulse indices in
    samples of ``sampling_period_s``)."""
    pulses = np.asarray(pulses, dtype=np.int64)
    if pulses.size == 0:
        return np.zeros(0, bool)
    before = int(round(ISOLATION_BEFORE_S / sampling_period_s))
    after = int(round(ISOLATION_AFTER_S / sampling_period_s))
    prev_gap = np.diff(np.concatenate([[-(10**9)], pulses]))
    next_gap = np.diff(np.concatenate([pulses, [10**9]]))
    ok_before = (prev_gap >= before) & (pulses >= before)
    ok_after = (next_gap >= after) & (pulses + after <= n_samples)
    return ok_before & ok_after


# ----------------------------------------------------------------------------- the time loop
def _substeps(sampling_period_s: float) -> int:
    """Internal 1-ms steps per sample; the period must be a whole number of them that the
    impulse buffer holds."""
    if not math.isfinite(sampling_period_s) or sampling_period_s <= 0:
        raise ValueError(f"the simulator records at whole milliseconds from 1 to {_BUFFER // 2} ms, "
                         f"not a sampling period of {sampling_period_s} s")
    k = int(round(sampling_period_s / INTERNAL_STEP_S))
    if not (k >= 1 and abs(k * INTERNAL_STEP_S - sampling_period_s) < 1e-9 and k <= _BUFFER // 2):
        raise ValueError(f"the simulator records at whole milliseconds from 1 to {_BUFFER // 2} ms, "
                         f"not a sampling period of {sampling_period_s} s")
    return k


#: The knee's range (always on, module docs): past ``extension_deg`` and ``flexion_deg`` the passive
#: torque rises by e every ``width_deg``, from ``torque_deg_s2`` at each of those angles.
KNEE_RANGE = {"extension_deg": 88.0, "flexion_deg": -66.0, "width_deg": 1.5, "torque_deg_s2": 1000.0}
#: Angles [deg] no simulated trial leaves: a seated knee's deep flexion to slight hyperextension.
ANATOMICAL_RANGE_DEG = (-75.0, 100.0)


def _range_torque(phi):
    """R(φ): the knee range's torque at ``phi`` [deg], positive towards flexion (module docs)."""
    r = KNEE_RANGE
    return r["torque_deg_s2"] * (jnp.exp((phi - r["extension_deg"]) / r["width_deg"])
                                 - jnp.exp((r["flexion_deg"] - phi) / r["width_deg"]))


@functools.lru_cache(maxsize=None)
def _chunk_runner(substeps: int):
    """Jitted, vmapped scan over one chunk of samples (built lazily, cached per sampling period).

    Per sample: record the state at the sample instant, put the pulse of
    this sample into the pending-impulse buffer (a shift register with 1-ms
    slots) at its delay, take out the impulses arriving during the next
    sampling period and integrate ``substeps`` internal steps of 1 ms.  The twitch filter is linear and is
    advanced exactly (matrix exponential); the mechanical state and the
    accelerometer mount are advanced with RK4, with the twitch activation
    evaluated exactly at the RK4 stage times.  Each impulse is scaled by
    f(φ)·g(φ̇) at the internal step where it arrives (the twitch's onset).
    """

    dt = INTERNAL_STEP_S

    def one_trial(p, carry, amps):
        tc = p["tc"]
        e_half = jnp.exp(-0.5 * dt / tc)
        e_full = jnp.exp(-dt / tc)
        iota = jnp.arange(_BUFFER, dtype=jnp.int32)
        wr2 = p["omega_r"] ** 2
        c_r = 2.0 * p["zeta"] * p["omega_r"]

        def fmod(phi):
            lin = jnp.maximum(0.0, 1.0 + p["gamma_angle"] * phi)
            peak = jnp.exp(-((phi - p["phi_opt"]) ** 2 - p["phi_opt"] ** 2) / (2.0 * p["width"] ** 2))
            return jnp.where(p["on_peak"] > 0, peak, lin)

        def gmod(v):
            lin = jnp.maximum(0.0, 1.0 + p["gamma_velocity"] * v)
            vs = jnp.maximum(v, 0.0)
            conc = jnp.maximum(0.0, (1.0 - vs / p["vmax"]) / (1.0 + vs / (p["hill_k"] * p["vmax"])))
            ve = jnp.maximum(-v, 0.0)
            ecc = 1.0 + (p["g_ecc"] - 1.0) * ve / (ve + p["v_half"])
            hill = jnp.where(v > 0, conc, ecc)
            return jnp.where(p["on_hill"] > 0, hill, lin)

        def accel(phi, v, x2):
            m = x2
            passive = (-p["damping"] * v - p["gravity"] * jnp.sin((phi - p["gravity_angle"]) * _DEG)
                       + p["k1"] * (jnp.exp(-p["k2"] * phi) - 1.0)
                       - p["limit_torque"] * jnp.exp((phi - p["phi_limit"]) / p["limit_width"])
                       - _range_torque(phi))
            return m + passive, m

        def rhs(phi, v, z, zd, x2):
            a, _ = accel(phi, v, x2)
            zdd = (-c_r * zd - wr2 * z - a) * p["on_res"]
            return v, a, zd, zdd

        def substep(i, s):
            phi, v, x1, x2, z, zd, arr = s
            # a twitch is scaled by the state at its onset (model 3's structure, eq. 5)
            x1 = x1 + arr[i] * fmod(phi) * gmod(v) / tc
            # exact twitch filter at t + dt/2 and t + dt
            x2h = e_half * (x2 + 0.5 * dt / tc * x1)
            x2f = e_full * (x2 + dt / tc * x1)
            x1f = e_full * x1
            k1 = rhs(phi, v, z, zd, x2)
            k2 = rhs(phi + 0.5 * dt * k1[0], v + 0.5 * dt * k1[1], z + 0.5 * dt * k1[2], zd + 0.5 * dt * k1[3], x2h)
            k3 = rhs(phi + 0.5 * dt * k2[0], v + 0.5 * dt * k2[1], z + 0.5 * dt * k2[2], zd + 0.5 * dt * k2[3], x2h)
            k4 = rhs(phi + dt * k3[0], v + dt * k3[1], z + dt * k3[2], zd + dt * k3[3], x2f)
            new = [
                q + dt / 6.0 * (a + 2.0 * b + 2.0 * c + d)
                for q, a, b, c, d in zip((phi, v, z, zd), k1, k2, k3, k4)
            ]
            return new[0], new[1], x1f, x2f, new[2], new[3], arr

        def body(c, amp):
            s, buf = c
            phi, v, x1, x2, z, zd = s
            a, m = accel(phi, v, x2)
            measured = jnp.where(p["on_res"] > 0, -c_r * zd - wr2 * z, a)
            out = jnp.stack([phi, v, a, measured, m, x2])
            early = (p["on_adelay"] > 0) & (phi < p["adelay_angle"])
            d = jnp.where(early, p["delay_short_ms"], p["delay_ms"])
            buf = buf + amp * (iota == d)
            arr = buf[:substeps]
            buf = jnp.concatenate([buf[substeps:], jnp.zeros(substeps, buf.dtype)])
            st = lax.fori_loop(0, substeps, substep, (phi, v, x1, x2, z, zd, arr), unroll=_UNROLL)
            return (st[:6], buf), out

        carry, outs = lax.scan(body, carry, amps)
        return carry, outs

    return jax.jit(jax.vmap(one_trial))


_FLOAT_PARAMS = (
    "damping", "gravity", "k1", "k2", "gamma_angle", "gamma_velocity", "tc",
    "on_peak", "phi_opt", "width", "on_hill", "vmax", "hill_k", "g_ecc", "v_half",
    "on_adelay", "adelay_angle", "on_res", "omega_r", "zeta", "gravity_angle", "limit_torque", "phi_limit",
    "limit_width",
)  # fmt: skip


def _scan_params(leg: str, effects: tuple[str, ...]) -> dict:
    p = dict(PASSIVE_TRUTH[leg])
    p["gamma_angle"] = TABLE_III[leg]["gamma_angle"]
    p["gamma_velocity"] = TABLE_III[leg]["gamma_velocity"]
    p["tc"] = _twitch_tc(leg)
    ep = EFFECT_PARAMETERS
    p.update(
        on_peak=float("torque_angle_peak" in effects),
        phi_opt=ep["torque_angle_peak"]["phi_opt_deg"],
        width=ep["torque_angle_peak"]["width_deg"],
        on_hill=float("hill_velocity" in effects),
        vmax=ep["hill_velocity"]["vmax_deg_s"],
        hill_k=ep["hill_velocity"]["k"],
        g_ecc=ep["hill_velocity"]["g_ecc"],
        v_half=ep["hill_velocity"]["v_half_deg_s"],
        on_adelay=float("angle_delay" in effects),
        adelay_angle=ep["angle_delay"]["angle_deg"],
        on_res=float("accel_resonance" in effects),
        omega_r=2 * math.pi * ep["accel_resonance"]["f_r_hz"],
        zeta=ep["accel_resonance"]["zeta"],
        gravity_angle=ep["gravity_offset"]["angle_deg"] if "gravity_offset" in effects else 0.0,
        limit_torque=ep["extension_limit"]["torque_deg_s2"] if "extension_limit" in effects else 0.0,
        phi_limit=ep["extension_limit"]["phi_limit_deg"],
        limit_width=ep["extension_limit"]["width_deg"],
    )
    p["rest_deg"] = _rest_angle(p)
    delay_ms = int(round(_delay_samples(leg) * SAMPLING_PERIOD_S / INTERNAL_STEP_S))
    short_ms = delay_ms - int(round(ep["angle_delay"]["shortening_s"] / INTERNAL_STEP_S))
    if not 1 <= short_ms <= delay_ms < _BUFFER:
        raise ValueError(f"{leg}: delay {delay_ms} ms does not fit the impulse buffer")
    p["delay_ms"] = delay_ms
    p["delay_short_ms"] = short_ms
    return p


def _rest_angle(p: dict) -> float:
    """The angle [deg] where the passive torques balance (0 unless gravity acts about another angle)."""
    if p["gravity_angle"] == 0.0 and p["limit_torque"] == 0.0:
        return 0.0

    def torque(phi):
        return (-p["gravity"] * math.sin(math.radians(phi - p["gravity_angle"])) + p["k1"] * math.expm1(-p["k2"] * phi)
                - p["limit_torque"] * math.exp((phi - p["phi_limit"]) / p["limit_width"]))

    return float(brentq(torque, -90.0, 90.0))


def _run_plant(params: Sequence[dict], amps: np.ndarray, progress: bool = False,
               sampling_period_s: float = SAMPLING_PERIOD_S) -> np.ndarray:
    """Run the plant for a batch of trials.

    ``amps[i, k]``: twitch area (u·A·gain factors) of the pulse at sample k of
    trial i.  Returns ``(batch, n_samples, 6)``: true angle, velocity,
    acceleration, measured (sensor-dynamics) acceleration before noise,
    equivalent acceleration M/I, unmodulated twitch activation, all at the
    sample instants k·T_s.
    """

    amps = np.asarray(amps, dtype=np.float64)
    batch, n = amps.shape
    n_chunks = max(1, -(-n // _CHUNK))
    padded = np.zeros((batch, n_chunks * _CHUNK))
    padded[:, :n] = amps
    runner = _chunk_runner(_substeps(sampling_period_s))
    outs = []
    with jax.enable_x64(True):
        p = {k: jnp.asarray(np.array([q[k] for q in params], dtype=np.float64)) for k in _FLOAT_PARAMS}
        for k in ("delay_ms", "delay_short_ms"):
            p[k] = jnp.asarray(np.array([q[k] for q in params], dtype=np.int32))
        zeros = jnp.zeros(batch, dtype=jnp.float64)
        rest = jnp.asarray(np.array([q.get("rest_deg", 0.0) for q in params], dtype=np.float64))
        carry = ((rest,) + (zeros,) * 5, jnp.zeros((batch, _BUFFER), dtype=jnp.float64))
        it = range(n_chunks)
        if progress:

            it = tqdm(it, desc="simulating", unit="chunk")
        for c in it:
            chunk = jnp.asarray(padded[:, c * _CHUNK : (c + 1) * _CHUNK])
            carry, out = runner(p, carry, chunk)
            outs.append(np.asarray(out))
    return np.concatenate(outs, axis=1)[:, :n, :]


# ----------------------------------------------------------------------------- per-trial plan
def _streams(seed: int, leg: str, trial: int) -> tuple[np.random.Generator, ...]:
    ss = np.random.SeedSequence(int(seed), spawn_key=(LEGS.index(leg), int(trial)))
    # IPIs, angle noise, acceleration noise, twitch variability
    return tuple(np.random.default_rng(c) for c in ss.spawn(4))


def twitch_variability(rng: np.random.Generator, n_pulses: int, cv: float) -> np.ndarray:
    """Log-normal twitch-amplitude factors with mean 1 and coefficient of variation ``cv``."""
    s2 = math.log1p(cv**2)
    return np.exp(math.sqrt(s2) * rng.standard_normal(n_pulses) - 0.5 * s2)


def _recruited(u, effects: tuple[str, ...]):
    """The share of the muscle a pulse of recruitment level ``u`` recruits: u, or u^κ with ``recruitment_power``."""
    return np.power(u, EFFECT_PARAMETERS["recruitment_power"]["kappa"]) if "recruitment_power" in effects else u


def _pulse_gains(pulses: np.ndarray, effects: tuple[str, ...], n_start: float, sampling_period_s: float) -> np.ndarray:
    gain = np.ones(pulses.size)
    if "fatigue" in effects:
        fp = EFFECT_PARAMETERS["fatigue"]
        n = n_start + np.arange(pulses.size)
        gain *= fp["f_min"] + (1.0 - fp["f_min"]) * np.exp(-n / fp["n_f_pulses"])
    if "potentiation" in effects and pulses.size > 1:
        pp = EFFECT_PARAMETERS["potentiation"]
        ipi = np.diff(pulses) * sampling_period_s
        # potentiation is largest at the paper's shortest interval, one of its 10-ms samples
        gain[1:] *= 1.0 + pp["P"] * np.exp(-(ipi - SAMPLING_PERIOD_S) / pp["tau_p_s"])
    return gain


def plan_leg(leg: str, n_samples: int, seed: int, effects: tuple[str, ...],
             sampling_period_s: float = SAMPLING_PERIOD_S, twitch_cv: float = TWITCH_CV) -> dict:
    """IPIs, pulse gains (with the twitches' variation ``twitch_cv``) and fatigue state for all
    protocol trials of a leg, in order (pulses on the sample grid of ``sampling_period_s``)."""
    plans = {}
    n_carry = 0.0
    fp = EFFECT_PARAMETERS["fatigue"]
    for trial in sorted(TRIAL_RECRUITMENT):
        u = float(TRIAL_RECRUITMENT[trial])
        rng_ipi, rng_angle, rng_acc, rng_twitch = _streams(seed, leg, trial)
        pulses = stimulation_sequence(rng_ipi, n_samples, _density(leg, u), sampling_period_s)
        n_start = n_carry if "fatigue" in effects else 0.0
        gains = _pulse_gains(pulses, effects, n_start, sampling_period_s)
        if twitch_cv > 0:
            gains = gains * twitch_variability(rng_twitch, pulses.size, twitch_cv)
        plans[trial] = {
            "u": u,
            "pulses": pulses,
            "gains": gains,
            "fatigue_pulses_at_start": n_start,
            "rng_angle": rng_angle,
            "rng_acc": rng_acc,
        }
        n_carry = (n_start + pulses.size) * math.exp(-fp["rest_s"] / fp["tau_rec_s"])
    return plans


def _record(raw: np.ndarray, rng_angle, rng_acc, noise: bool = True, effects=()) -> tuple[np.ndarray, np.ndarray]:
    """Goniometer and accelerometer readings from the true signals."""
    angle = raw[:, 0].copy()
    if "goniometer_offset" in effects:
        angle = angle + EFFECT_PARAMETERS["goniometer_offset"]["offset_deg"]
    acc = raw[:, 3].copy()
    if noise:
        angle = angle + SENSOR["angle_noise_deg"] * rng_angle.standard_normal(angle.size)
        acc = acc + SENSOR["acceleration_noise_deg_s2"] * rng_acc.standard_normal(acc.size)
    q = SENSOR["angle_resolution_deg"]
    angle = np.round(angle / q) * q
    return angle, acc


# ----------------------------------------------------------------------------- public simulation
#: Longest trial the simulator makes [min]: a day, far beyond any recording session.
MAX_MINUTES = 1440.0


def simulate_cohort(
    legs: Sequence[str] = LEGS,
    minutes: float = 5.0,
    seed: int = 0,
    effects: Iterable[str] = (),
    trials: Sequence[int] = (1, 2, 3),
    progress: bool = False,
    sampling_period_s: float = SAMPLING_PERIOD_S,
    twitch_cv: float = TWITCH_CV,
) -> tuple[Cohort, dict]:
    """Simulate the protocol for ``legs``; returns the cohort and the truth.

    ``twitch_cv``: the coefficient of variation of the twitches' amplitudes from pulse to pulse
    (0.2 by default, the paper's Table IV; 0: equal twitches).
    ``sampling_period_s``: the recording's sampling period, a whole number of the plant's 1-ms
    steps (the paper's 10 ms by default); pulses fall on its sample grid.  The physiology (delays,
    twitch shape and area) is the same at every period; the truth's per-sample figures (delay in
    samples, DARMA equivalents) stay in the paper's 10-ms samples.

    All trials of all legs run as one batch (vmapped scan, float64, 1-ms
    steps); ``progress`` shows a bar over the chunks of the time loop.  The
    cohort's attrs record ``simulated`` = 1, the seed, the duration and the
    effects.  The truth is :func:`default_truth` plus the seed, the duration,
    a cohort ``summary`` per trial (mean RMS angle, angle range) and, per leg
    and trial, facts of the realisation: recruitment, pulse, isolated-twitch
    and short-IPI counts, RMS angle about 0, angle range, largest speed and
    the fatigue pulse count carried in.  Trials not simulated still have
    their stimulation sequence drawn (the fatigue carried into later trials
    depends on it), so a subset of legs or trials gets the same data as the
    full run.
    """
    legs = check_legs(legs)
    effects = check_effects(effects)
    trials = check_trials(trials)
    if not is_whole_number(seed) or not 0 <= seed < 2**32:
        raise ValueError(f"seed must be a whole number from 0 to {2**32 - 1}, not {seed!r}")
    if isinstance(minutes, (bool, str)) or not 0 < minutes <= MAX_MINUTES:
        raise ValueError(f"minutes must be positive and at most {MAX_MINUTES:g} (a day), got {minutes!r}")
    if isinstance(twitch_cv, (bool, str)) or not 0 <= twitch_cv <= 2:
        raise ValueError(f"twitch_cv must be a coefficient of variation from 0 (equal twitches) to 2, got {twitch_cv!r}")
    dt = float(sampling_period_s)
    _substeps(dt)  # checked before any work
    n = int(round(minutes * 60.0 / dt))
    truth = default_truth(legs, effects)
    truth["sampling_period_s"] = dt
    truth["twitch_cv"] = float(twitch_cv)
    jobs = []
    for leg in legs:
        plans = plan_leg(leg, n, seed, effects, dt, float(twitch_cv))
        G2 = TABLE_III[leg]["G2"]
        for trial in trials:
            plan = plans[trial]
            amps = np.zeros(n)
            amps[plan["pulses"]] = _recruited(plan["u"], effects) * G2 * SAMPLING_PERIOD_S * plan["gains"]
            jobs.append((leg, trial, plan, amps))
    params = {leg: _scan_params(leg, effects) for leg in legs}
    raw = _run_plant([params[j[0]] for j in jobs], np.stack([j[3] for j in jobs]), progress=progress, sampling_period_s=dt)

    out_trials = []
    for (leg, trial, plan, _), r in zip(jobs, raw):
        angle, acc = _record(r, plan["rng_angle"], plan["rng_acc"], effects=effects)
        stim = np.zeros(n)
        stim[plan["pulses"]] = plan["u"]
        subject, side = leg.split("-")
        out_trials.append(
            Trial.from_signals(
                subject, side, trial, dt, angle, acc, stim,
                source=f"simulated (seed {seed})",
            )
        )  # fmt: skip
        iso = isolated_pulses(plan["pulses"], n, dt)
        truth["legs"][leg].setdefault("trials", {})[str(trial)] = {
            "recruitment": plan["u"],
            "n_samples": n,
            "n_pulses": int(plan["pulses"].size),
            "n_isolated": int(iso.sum()),
            "n_short_ipi": int(np.sum(np.diff(plan["pulses"]) <= round(IPI_SHORT_S[1] / dt))),
            "rms_angle_deg": float(np.sqrt(np.mean(angle**2))),
            "angle_min_deg": float(angle.min()),
            "angle_max_deg": float(angle.max()),
            "velocity_max_abs_deg_s": float(np.abs(r[:, 1]).max()),
            "fatigue_pulses_at_start": float(plan["fatigue_pulses_at_start"]),
        }
    summary = {}
    for trial in trials:
        rms = [truth["legs"][leg]["trials"][str(trial)]["rms_angle_deg"] for leg in legs]
        summary[str(trial)] = {
            "mean_rms_angle_deg": float(np.mean(rms)),
            "angle_min_deg": float(min(truth["legs"][leg]["trials"][str(trial)]["angle_min_deg"] for leg in legs)),
            "angle_max_deg": float(max(truth["legs"][leg]["trials"][str(trial)]["angle_max_deg"] for leg in legs)),
        }
    truth.update(seed=int(seed), minutes=float(minutes), trials=list(trials), summary=summary)
    attrs = {
        "simulated": 1,
        "seed": int(seed),
        "minutes": float(minutes),
        "effects": list(effects),
        "twitch_cv": float(twitch_cv),
        "truth_format": TRUTH_FORMAT,
    }
    return mark_checked(Cohort(tuple(out_trials), attrs)), truth  # made within the rules (written and read back in its tests)


def simulate_response(
    leg: str,
    stimulation,
    effects: Iterable[str] = (),
    noise: bool = False,
    seed: int = 0,
    fatigue_pulses_at_start: float = 0.0,
    sampling_period_s: float = SAMPLING_PERIOD_S,
) -> dict:
    """Simulate one leg for a given stimulation array (u per sample of ``sampling_period_s``).

    Starting at rest, returns the recorded signals (``angle_deg`` — with
    quantisation, plus noise when ``noise`` — and ``acceleration_deg_s2``)
    and the noise-free truth at the sample instants: ``true_angle_deg``,
    ``true_velocity_deg_s``, ``true_acceleration_deg_s2``,
    ``equivalent_acceleration`` (M/I) and ``twitch_activation`` (M/I before
    the f·g modulation).  The twitches' variation from pulse to pulse (:data:`TWITCH_CV`) is drawn
    in the cohort's protocol only; here the twitches are equal.
    """
    (leg,) = check_legs((leg,))
    effects = check_effects(effects)
    stim = np.asarray(stimulation, dtype=float)
    pulses = np.flatnonzero(stim > 0)
    gains = _pulse_gains(pulses, effects, fatigue_pulses_at_start, sampling_period_s)
    amps = np.zeros(stim.size)
    amps[pulses] = _recruited(stim[pulses], effects) * TABLE_III[leg]["G2"] * SAMPLING_PERIOD_S * gains
    raw = _run_plant([_scan_params(leg, effects)], amps[None, :], sampling_period_s=sampling_period_s)[0]
    ss = np.random.SeedSequence(int(seed), spawn_key=(LEGS.index(leg), 99))
    rng_angle, rng_acc = (np.random.default_rng(c) for c in ss.spawn(2))
    angle, acc = _record(raw, rng_angle, rng_acc, noise=noise, effects=effects)
    return {
        "angle_deg": angle,
        "acceleration_deg_s2": acc,
        "stimulation": stim,
        "true_angle_deg": raw[:, 0],
        "true_velocity_deg_s": raw[:, 1],
        "true_acceleration_deg_s2": raw[:, 2],
        "equivalent_acceleration": raw[:, 4],
        "twitch_activation": raw[:, 5],
    }


# ----------------------------------------------------------------------------- output
#: The examiner's hand at the release of a simulated pendulum test: a push that falls linearly
#: from this acceleration [deg/s²] to 0 over RELEASE_S.
RELEASE_PUSH_DEG_S2 = 800.0
RELEASE_S = 0.3


def simulate_pendulum_test(
    passive: dict,
    *,
    subject: str = "PT",
    leg: str = "left",
    trial: int = 1,
    seconds: float = 8.0,
    angle0: float = 60.0,
    hand: bool = True,
    gravity_angle: float = 0.0,
    angle_noise_deg: float = 0.05,
    acceleration_noise_deg_s2: float | None = 30.0,
    sampling_period_s: float = SAMPLING_PERIOD_S,
    seed: int = 0,
) -> Trial:
    """A pendulum test: the shank held at ``angle0`` [deg], released and left to swing, no muscle.

    The passive system of eq. (8) with ``passive`` = {damping, gravity, k1, k2} (gravity acting
    about ``gravity_angle``, see the ``gravity_offset`` effect), integrated by RK4 at 0.5 ms and
    sampled every ``sampling_period_s``.  With ``hand`` the examiner's hand pushes for the first
    :data:`RELEASE_S` (from :data:`RELEASE_PUSH_DEG_S2` down to 0), a force no model has: the
    release a user excludes.  White sensor noise on the angle and, unless
    ``acceleration_noise_deg_s2`` is None (no accelerometer: derived from the angle), on the
    acceleration.
    """
    D, G, k1, k2 = (float(passive[k]) for k in ("damping", "gravity", "k1", "k2"))

    def f(x, t):
        a = -D * x[1] - G * math.sin(math.radians(x[0] - gravity_angle)) + k1 * math.expm1(-k2 * x[0])
        push = RELEASE_PUSH_DEG_S2 * (1 - t / RELEASE_S) if hand and t < RELEASE_S else 0.0
        return np.array([x[1], a + push])

    n = int(round(seconds / sampling_period_s))
    sub = max(1, int(round(sampling_period_s / 5e-4)))
    h = sampling_period_s / sub
    x, t, out = np.array([float(angle0), 0.0]), 0.0, np.zeros((n, 2))
    for k in range(n):
        out[k] = x[0], f(x, t)[1]
        for _ in range(sub):
            a1 = f(x, t)
            a2 = f(x + h / 2 * a1, t + h / 2)
            a3 = f(x + h / 2 * a2, t + h / 2)
            a4 = f(x + h * a3, t + h)
            x, t = x + h / 6 * (a1 + 2 * a2 + 2 * a3 + a4), t + h
    rng = np.random.default_rng(seed)
    angle = out[:, 0] + rng.normal(0, angle_noise_deg, n)
    acc = None if acceleration_noise_deg_s2 is None else out[:, 1] + rng.normal(0, acceleration_noise_deg_s2, n)
    return Trial.from_signals(subject, leg, trial, sampling_period_s, angle, acc, np.zeros(n),
                              source="simulated pendulum test")


def _jsonable(v):
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating,)):
        return float(v)
    if isinstance(v, (np.bool_,)):
        return bool(v)
    return v


def write_truth(truth: dict, path: str | os.PathLike) -> Path:
    """Write the truth as pretty-printed JSON, atomically (temporary file, then rename)."""

    return write_json(path, _jsonable(truth))
