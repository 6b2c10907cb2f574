"""The likelihood of a Model on measured accelerations, with the delay marginalised.

What is compared
    The equivalent acceleration of eq. (8), e_k = a_k − Σ passive(φ_k, φ̇_k),
    with the model's active output M̂_k = Σ_i u_i q_i F_{p_i+d} h(k − p_i − d):
    the activation effect's impulse response h (computed by stepping the
    effect itself, so its physics is written once) placed at every pulse p_i,
    scaled by the recruitment level u_i, by the pulse effects' factor q_i
    (fatigue, potentiation: known from the stimulation alone) and by the gain
    effects' factors F at the measured state at the twitch's onset (eqs. 2–5).
    The passive parameters enter through e_k, so they are fitted jointly with
    the active ones.

At what resolution
    The activation effect says.  A shaped twitch (DARMA, ``resolution =
    "sample"``) is compared sample by sample.  The zero-order activation of
    models 1 and 3 puts a whole twitch into one sample; compared sample by
    sample it would fit the twitch's peak, not its integral, so it is compared
    on *twitch windows* (``resolution = "twitch"``): a window runs from a pulse
    until MAX_DELAY samples and 250 ms (TWITCH_S) after the last pulse of its burst
    (pulses closer than that share a window), data and model summed over it,
    so every twitch lies whole inside one window for any d (a window that the
    end of a trial cuts short is left out).  This is the paper's
    integrated twitch response (eqs. 9, 11) extended to every pulse; samples
    outside twitch windows stay single windows.  Within a window the timing of
    a twitch is not compared, so a zero-order model learns its delay only
    through the state at which its gain factors are evaluated (model 3) or not
    at all (model 1: its P(d | data) stays the prior).  The onset delay is
    what model 2's shaped twitch measures, as in the paper (Table I).

Noise
    Student-t with per-leg scale σ and degrees of freedom ν per sample.  A
    window's sum of n samples is not Student-t; it is compared as one
    (:func:`window_noise`) with the sum's variance and, for ν > 4, its
    kurtosis, so its tails thin with n as the sum's do.  Scaling σ√n with ν
    alone would make a twitch window's sum too heavy-tailed and too narrow in
    its middle, and the active parameters' intervals too narrow with it.
    Most windows are one sample (outside the twitch windows, and all of them
    at ``resolution = "sample"``); they keep σ and ν as scalars, and only the
    longer windows take theirs from a table of the leg's window lengths.
    The accelerometers' skin-motion resonance (the paper's discussion, ref.
    [35]) shows as bursts of large residual after sudden motions, i.e. heavy
    tails; the paper's answer, a whitening filter estimated jointly with the
    input dynamics (eq. 10), it found "troublesome" when the disturbance
    correlates with the input.  ν is fitted, so clean data give a large ν
    (close to Gaussian).  A noise effect (``twitch_variability``: a random
    gain per pulse with coefficient of variation CV) widens each window it
    reaches: its squared scale grows by CV² × Σ over the window's pulses of
    (the pulse's output summed over the window)², the exact variance of a
    twitch window's sum, and of each one sample (:func:`_widened`).

The delay
    d ∈ {0 … MAX_DELAY} per leg is summed out exactly:
    log p(y | θ) = logsumexp_d [log π(d) + ℓ_d(θ)].  ℓ_d = ℓ_base + Δ_d, where
    ℓ_base is the likelihood with no active output (one pass over all windows)
    and Δ_d corrects only the windows that the pulses' responses reach at
    delay d.  Those windows depend on the data alone and are found once here,
    so the cost of the delay and of the active parameters follows the pulses
    and their response windows, not the trial's length; nothing runs as a
    sequential scan over samples.  On twitch windows a pulse's whole response
    stays in its own window for every d (checked by :func:`pulse_tables`), so
    a window's model sum has one term per pulse, u_i q_i F(p_i + d) Σh, and
    the gain factors are evaluated at the pulses' samples only (the
    pulse-level path; ``benchmarks/bench_likelihood.py`` times its gradient
    against one term per (pulse, lag)).

A delay that steps with the angle
    With a delay effect that shortens d for the pulses below a threshold angle
    (``step_param``), the fit sums the threshold out as well
    (:func:`leg_loglik_by_threshold`): ordered by angle, the pulses split into
    P + 1 threshold states, and moving from one state to the next changes only
    the windows the next pulse reaches, by a running sum over (window, pulse)
    pairs in angle order (:func:`step_tables`, data alone).  Each state is
    weighted by its interval's prior mass (:func:`step_log_mass`).

The angle, for the pendulum alone
    A model without a muscle (``--model passive``, pendulum tests) can instead be compared on
    the angle (``objective="angle"``, output error): each stretch of compared samples (a trial,
    or the part of it between excluded samples) is run freely from its first sample's measured
    angle and velocity by RK4, and every later sample's measured angle is Student-t about the
    run's (σ in degrees).  A free swing's error accumulates, so neighbouring residuals are
    correlated and the posterior is narrower than the noise alone would make it; what this
    buys is a fit that follows the swing, where the acceleration (derived from a noisy angle
    when there is no accelerometer) weighs the noise of its derivative.

The angle, for a model with a muscle (multiple shooting)
    With ``objective="angle"`` a model with a muscle is compared on the angle too, segment by
    segment: each stretch of compared samples is cut into shooting segments of SHOOTING_S, and
    each segment is run from its first sample's measured angle and velocity, the active part
    carried there by the measured state from the trial's start at rest, exactly as J's
    rollouts start (:func:`quadshank.model._model.predict_ahead`).  Every later sample of the
    segment is Student-t about the run's angle; the delay is summed out as with the
    acceleration, one run per d.  Not for models with a delay effect or a noise effect: those
    are summed out window by window on the acceleration.

Precision
    In the likelihood NUTS samples (:func:`leg_loglik_by_delay`, :func:`leg_loglik_by_threshold`)
    each term (a sample's passive acceleration, a window's sum, its log density kernel) is
    computed at the precision of the data given, and every sum over samples, windows, pulses
    and threshold states in double where JAX's x64 is on (:func:`_at_data_precision`): the fit
    gives single-precision data by default and double with ``precision="double"``.
Units for PSIS-LOO
    Windows are summed into segments of SEGMENT_S (1 s) per trial: the
    residual's correlation (twitch-shape misfit, resonance) dies out within a
    twitch (250 ms), so 1-s segments are close to conditionally independent,
    and leaving one out asks how well the model predicts a new second of
    movement.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

from ..data._cohort import Cohort
from ..data._interchange import check_cohort
from ..data._paper import MAX_DELAY, SAMPLING_PERIOD_S, TWITCH_SAMPLES
from ._effects import FIRST_IPI_S, Effect, PulseContext, StepContext
from ._model import (
    Model,
    acceleration_response,
    _active_step,
    _carries,
    _rk4,
    causal_fir,
    measured_acceleration,
    measured_angle,
    passive_acceleration,
    pulse_factors,
    true_angle,
)

__all__ = [
    "LikelihoodData",
    "prepare",
    "impulse_response",
    "gain_factors",
    "leg_loglik_by_delay",
    "leg_loglik_by_threshold",
    "step_log_mass",
    "step_edges",
    "leg_pointwise",
    "leg_active_output",
    "student_t_logpdf",
    "window_noise",
    "max_shift",
    "response_length",
    "SEGMENT_S",
    "segment_samples",
    "N_DELAYS",
    "OBJECTIVES",
    "resolve_objective",
    "PULSE_LEVEL_FIELDS",
    "SHOOTING_S",
    "shooting_samples",
]

#: What the likelihood can compare: the equivalent acceleration (equation error, every model) or
#: the angle of runs from the measured state (output error: free runs for the pendulum alone,
#: shooting segments of SHOOTING_S for a model with a muscle).
OBJECTIVES = ("acceleration", "angle")
#: Length [s] of a PSIS-LOO unit, a segment of a trial.
SEGMENT_S = 1.0
#: Length [s] of a shooting segment of the angle objective for a model with a muscle: the longest
#: horizon of J (eq. 12), and the PSIS-LOO unit's length, so that each unit is one segment's run.
SHOOTING_S = 1.0


def segment_samples(sampling_period_s: float) -> int:
    """Samples per PSIS-LOO unit at ``sampling_period_s``: :data:`SEGMENT_S` in whole samples
    (100 at the paper's 10 ms)."""
    return max(1, int(round(SEGMENT_S / sampling_period_s)))


#: Bounds [deg, deg/s] on a shooting run's state and on the active part's states (see :func:`_bounded`).
RUN_LIMIT_DEG, RUN_LIMIT_DEG_S = 360.0, 1.0e4
CARRY_LIMIT = 1.0e7


def shooting_samples(sampling_period_s: float) -> int:
    """Samples per shooting segment of the angle objective at ``sampling_period_s``:
    :data:`SHOOTING_S` in whole samples (100 at the paper's 10 ms), at least 2."""
    return max(2, int(round(SHOOTING_S / sampling_period_s)))


#: Delays considered: 0 .. MAX_DELAY samples.
N_DELAYS = MAX_DELAY + 1
#: Longest twitch window at the paper's 10 ms: the largest delay plus the twitch duration.
TWITCH_WINDOW = MAX_DELAY + TWITCH_SAMPLES
#: How long a twitch acts [s]: the paper's 25 samples of 10 ms.
TWITCH_S = TWITCH_SAMPLES * SAMPLING_PERIOD_S


def twitch_window(sampling_period_s: float) -> int:
    """Samples of a twitch window at ``sampling_period_s``: the largest delay (in samples, as the
    delays are counted) plus :data:`TWITCH_S` in whole samples (35 at the paper's 10 ms).  Counted
    in samples alone, a window at 5 ms would hold half a twitch, and the zero-order model would
    take the rest for a misfit that only its delay could move (its fit chose 5 ms for a 43-ms
    delay)."""
    return MAX_DELAY + max(1, int(round(TWITCH_S / sampling_period_s)))


#: The pulse-level path's tables (:func:`pulse_tables`, :func:`pulse_step_tables`): given
#: arrays without them, the likelihood takes the (pulse, lag) path.
PULSE_LEVEL_FIELDS = ("pulse_slot", "slot_window", "slot_mask", "step_slot_order", "step_slot_first", "step_rank_pos")


class LikelihoodError(ValueError):
    """The model cannot be written as this likelihood (e.g. a stateful gain)."""


@dataclasses.dataclass(frozen=True, eq=False)
class LikelihoodData:
    """Per-leg arrays, padded to common sizes and stacked on a leading leg axis.

    Trials of a leg are concatenated with masked gaps between them, so no
    pulse's response reaches into the next trial.  A trial's excluded samples
    (``Trial.exclude``) are masked with the whole window they fall in.
    """

    legs: tuple[str, ...]
    subjects: tuple[str, ...]
    leg_subject: np.ndarray  # (L,) index into subjects
    trials: tuple[int, ...]
    resolution: str
    response_length: int
    max_shift: int  # K: the delay effect may shorten d by 0 … K samples (0 without one)
    angle: np.ndarray  # (L, N) deg
    velocity: np.ndarray  # (L, N) deg/s
    acceleration: np.ndarray  # (L, N) deg/s²
    stimulation: np.ndarray  # (L, N)
    sample_mask: np.ndarray  # (L, N) bool
    window: np.ndarray  # (L, N) window of each sample (padding -> last, masked window)
    window_len: np.ndarray  # (L, W) samples per window
    window_lengths: np.ndarray  # (L, Z) the leg's distinct window lengths (padding: 1)
    window_length_index: np.ndarray  # (L, W) each window's length in window_lengths
    window_mask: np.ndarray  # (L, W) bool
    single_mask: np.ndarray  # (L, W) bool: compared windows of one sample
    multi_window: np.ndarray  # (L, T) compared windows of more than one sample (T = 0 where there are none)
    multi_mask: np.ndarray  # (L, T) bool
    window_segment: np.ndarray  # (L, W) PSIS-LOO unit of each window
    n_segments: int
    segment_mask: np.ndarray  # (L, S) bool
    pulse_sample: np.ndarray  # (L, P)
    pulse_u: np.ndarray  # (L, P) 0 for padding
    pulse_ipi_s: np.ndarray  # (L, P) time since the trial's preceding pulse [s]
    pulse_count: np.ndarray  # (L, P) pulses before this one in its trial
    pulse_time_s: np.ndarray  # (L, P) time in the trial [s]
    touch_sample: np.ndarray  # (L, D, P*(R+K)) sample reached by pulse i, lag j - K at delay d
    touch_valid: np.ndarray  # (L, D, P*(R+K)) bool
    touch_pos: np.ndarray  # (L, D, P*(R+K)) index into touch_window
    touch_window: np.ndarray  # (L, D, U) windows reached at delay d
    touch_mask: np.ndarray  # (L, D, U) bool
    # with a step delay effect (its step parameter summed out, see step_tables); else None
    step_order: np.ndarray | None = None  # (L, P) pulses by increasing angle (padding last)
    step_pulse_valid: np.ndarray | None = None  # (L, P) bool, in that order
    step_entry_pair: np.ndarray | None = None  # (L, D, P*(R+K)) (window, pulse) pair of each entry
    step_pair_window: np.ndarray | None = None  # (L, D, Q) index into touch_window
    step_pair_pulse: np.ndarray | None = None  # (L, D, Q) pulse of each pair
    step_pair_first: np.ndarray | None = None  # (L, D, Q) first pair of the same window
    step_pair_mask: np.ndarray | None = None  # (L, D, Q) bool
    # the pulse-level path (see pulse_tables): a twitch stays inside its pulse's window; else None
    pulse_slot: np.ndarray | None = None  # (L, P) slot of each pulse's window (padding -> spare, masked slot)
    slot_window: np.ndarray | None = None  # (L, V) window of each slot
    slot_mask: np.ndarray | None = None  # (L, V) bool
    step_slot_order: np.ndarray | None = None  # (L, P) pulses by slot, then by angle
    step_slot_first: np.ndarray | None = None  # (L, P) position (in that order) of the slot's first pulse
    step_rank_pos: np.ndarray | None = None  # (L, P) position in that order of the j-th pulse by angle
    #: (L, N) first sample of each sample's trial (padding: 0); not read by the likelihood, whose mask
    #: starts again after every excluded stretch: the residual features' time in trial and pulse count
    trial_start: np.ndarray | None = None
    #: What the likelihood compares (:data:`OBJECTIVES`): the equivalent acceleration, or the angle of
    #: free runs started afresh from the measured state at ``reset``
    objective: str = "acceleration"
    #: (L, N) bool, with the angle objective: the first sample of each stretch of compared samples,
    #: where a free run starts from the measured angle and velocity (not itself compared); else None
    reset: np.ndarray | None = None
    #: (L, N) bool, with the angle objective and a muscle: the first sample of each trial, where the
    #: active part starts at rest; else None
    begin: np.ndarray | None = None
    #: (L, S) with ``begin``: the samples where ``reset`` is set, in order (spare entries 0)
    shoot_start: np.ndarray | None = None

    @property
    def n_legs(self) -> int:
        return len(self.legs)

    def leg_arrays(self) -> dict[str, jnp.ndarray]:
        """The arrays the JAX functions need, keyed by name, leading axis = leg."""
        names = (
            "angle velocity acceleration stimulation sample_mask window window_lengths window_length_index window_mask "
            "single_mask multi_window multi_mask window_segment "
            "segment_mask pulse_sample pulse_u pulse_ipi_s pulse_count pulse_time_s touch_sample touch_valid touch_pos touch_window touch_mask"
        ).split()
        names += [f.name for f in dataclasses.fields(self) if f.name.startswith("step_") or f.name in PULSE_LEVEL_FIELDS]
        names += ["reset", "begin", "shoot_start"]
        return {n: jnp.asarray(getattr(self, n)) for n in names if getattr(self, n) is not None}


def _bucket(n: int) -> int:
    """``n`` rounded up to a size of a coarse ladder (steps of 1/16 of the power of two below, at least 16).

    Arrays padded to these sizes (masked) give datasets of similar size the same
    shapes, so jitted likelihoods compile once for all of them: a screen of many
    datasets (the modelling loop) pays compilation once per model, not per dataset,
    for at most ~6 % more work.
    """
    step = max(16, 1 << max(0, int(n).bit_length() - 5))
    return -(-int(n) // step) * step


def _windows(stim: np.ndarray, resolution: str, window: int = TWITCH_WINDOW) -> np.ndarray:
    """Window start flags for one trial: True where a new window begins (``window``: a twitch
    window's samples, :func:`twitch_window`)."""
    n = stim.size
    if resolution == "sample":
        return np.ones(n, bool)
    if resolution != "twitch":
        raise LikelihoodError(f"unknown likelihood resolution {resolution!r}; use 'sample' or 'twitch'")
    pulses = np.flatnonzero(stim > 0)
    # covered: a pulse at most window - 1 samples earlier (or now) may still act
    hits = np.zeros(n + window, int)
    np.add.at(hits, pulses, 1)
    np.add.at(hits, pulses + window, -1)
    covered = np.cumsum(hits)[:n] > 0
    previous = np.concatenate([[False], covered[:-1]])
    starts = ~covered | (covered & ~previous)
    return starts


def _uncut(stim: np.ndarray, starts: np.ndarray, resolution: str, window: int = TWITCH_WINDOW) -> np.ndarray:
    """Samples the likelihood compares: all, but for a twitch window cut short by the end of the trial.

    A zero-order twitch lies whole inside its window for every delay only if
    the window runs its full length; when the recording ends sooner, whether
    the twitch falls inside would depend on d, and the window would tell the
    delay that the window sums are meant not to see.  So that last window
    (with its pulses) is left out.
    """
    mask = np.ones(stim.size, bool)
    if resolution != "twitch":
        return mask
    pulses = np.flatnonzero(stim > 0)
    if pulses.size and pulses[-1] + window > stim.size:
        mask[np.flatnonzero(starts[: pulses[-1] + 1])[-1] :] = False
    return mask


def _excluded_windows(exclude: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """True on every sample of a window that holds an excluded sample: a window's sum is
    compared whole or not at all (on one-sample windows, the excluded samples themselves)."""
    if not exclude.any():
        return np.zeros(exclude.size, bool)
    window = np.cumsum(starts) - 1
    return np.isin(window, np.unique(window[exclude]))


def max_shift(model: Model) -> int:
    """Largest shortening of the delay the model's delay effect allows (0 without one)."""
    eff = model.delay_effect
    if eff is None:
        return 0
    if not hasattr(eff, "pulse_weight") or not hasattr(eff, "max_shift"):
        raise LikelihoodError(
            f"effect {eff.name!r}: the hierarchical fit needs a delay effect to declare max_shift and pulse_weight(angle)"
        )
    return int(eff.max_shift)


def response_length(model: Model) -> int:
    """Samples of one pulse's response the likelihood keeps: the activation effect's,
    lengthened by an accelerometer response."""
    R = int(getattr(model.activation, "response_length", 40))
    g = acceleration_response(model)
    return R if g is None else R + int(g.shape[0]) - 1


def resolve_objective(model: Model, objective: str = "auto") -> str:
    """What the likelihood of ``model`` compares (:data:`OBJECTIVES`): ``"auto"`` is the angle for
    the pendulum alone (a model without a muscle: its free swing predicts the angle better than
    the acceleration's fit does, ``benchmarks/bench_pendulum.py``) and the acceleration for a
    model with a muscle (``benchmarks/bench_angle_objective.py`` compares the two).  The angle
    of a model with a muscle is compared in shooting segments (:data:`SHOOTING_S`), and not
    for a model with a delay or noise effect (a :class:`LikelihoodError` says why)."""
    if objective not in OBJECTIVES + ("auto",):
        raise LikelihoodError(f"unknown likelihood {objective!r}; use auto, {' or '.join(OBJECTIVES)}")
    muscle = model.activation.name != "no_muscle"
    if objective == "auto":
        return "acceleration" if muscle else "angle"
    if objective == "angle" and muscle:
        why = [f"{e.name!r}, a {e.kind} effect" for e in model.effects if e.kind in ("delay", "noise")]
        if why:
            raise LikelihoodError(
                f"model {model.name!r} has {' and '.join(why)}: the angle likelihood of a model with a muscle "
                "(shooting segments from the measured state) sums out the delay alone; a delay effect's "
                "threshold and shift and a noise effect's random twitch gains are summed out window by window "
                "on the acceleration, so fit this model with --likelihood acceleration")
    return objective


def chosen_legs(cohort: Cohort, legs=None, trials=(1,)) -> tuple[tuple[str, ...], tuple[int, ...]]:
    """The legs (all of ``cohort``'s by default; one name is one leg) and trial numbers a fit uses,
    refused where a leg is unknown or given twice, or lacks a trial: checked before any work."""
    legs = (legs,) if isinstance(legs, str) else tuple(legs) if legs is not None else cohort.legs
    if not legs:
        have = f"the data has {', '.join(cohort.legs)}" if len(cohort) else "the data hold no trials"
        raise ValueError(f"legs: give at least one leg ({have})")
    twice = sorted({leg for leg in legs if legs.count(leg) > 1})
    if twice:  # its data would enter the likelihood twice, as two legs of the hierarchy
        raise ValueError(f"legs: {', '.join(twice)} given twice")
    trials = tuple(int(t) for t in trials)
    unknown = [leg for leg in legs if leg not in cohort.legs]
    if unknown:
        raise KeyError(f"no leg {', '.join(unknown)} in the data (it has {', '.join(cohort.legs)})")
    for leg in legs:
        have = sorted(t.trial for t in cohort.trials_of(leg))
        if not set(trials) & set(have):
            raise KeyError(f"leg {leg} has no trial {', '.join(map(str, trials))} (it has {have})")
        missing = [tr for tr in trials if tr not in have]
        if missing:  # a leg fitted to fewer trials than asked for would be recorded as fitted to all
            raise KeyError(f"leg {leg} has no trial {', '.join(map(str, missing))} (it has {have}); ask for the "
                           "trials every leg has, or leave this leg out")
    return legs, trials


def prepare(cohort: Cohort, model: Model, trials=(1,), legs=None, objective: str = "auto") -> LikelihoodData:
    """Arrange a cohort's chosen trials for the likelihood of ``model``; ``objective``: what it
    compares (:func:`resolve_objective`)."""
    check_cohort(cohort)  # a cohort built in Python meets the rules a file's does
    objective = resolve_objective(model, objective)
    act = model.activation
    resolution = getattr(act, "resolution", "sample")
    R = response_length(model)
    K = max_shift(model)
    legs, trials = chosen_legs(cohort, legs, trials)
    gap = MAX_DELAY + R + 1
    per_leg = []
    for leg in legs:
        chosen = [t for t in cohort.trials_of(leg) if t.trial in trials]
        cols = {k: [] for k in ("angle", "velocity", "acceleration", "stimulation", "mask", "pulse_ok", "start", "segment",
                                 "trial_start")}
        offset = 0
        seg0 = 0
        for t in chosen:
            model.check_period(t.sampling_period_s, f"{leg} trial {t.trial}")
            n = t.n_samples
            cols["angle"] += [t.angle_deg, np.zeros(gap)]
            cols["velocity"] += [t.velocity_deg_s, np.zeros(gap)]
            cols["acceleration"] += [t.acceleration_deg_s2, np.zeros(gap)]
            cols["stimulation"] += [t.stimulation, np.zeros(gap)]
            window = twitch_window(t.sampling_period_s)
            starts = _windows(t.stimulation, resolution, window)
            uncut = _uncut(t.stimulation, starts, resolution, window)
            compared = uncut & ~_excluded_windows(t.exclude, starts)
            cols["mask"] += [compared, np.zeros(gap, bool)]
            cols["pulse_ok"] += [uncut, np.zeros(gap, bool)]
            cols["start"] += [starts, np.ones(gap, bool)]
            seg = seg0 + np.arange(n) // segment_samples(t.sampling_period_s)
            cols["segment"] += [seg, np.full(gap, -1)]
            cols["trial_start"] += [np.full(n + gap, offset)]
            offset += n + gap
            seg0 = int(seg[-1]) + 1
        per_leg.append({k: np.concatenate(v) for k, v in cols.items()} | {"n_segments": seg0})
        per_leg[-1]["subject"] = chosen[0].subject

    N = _bucket(max(x["angle"].size for x in per_leg))
    L = len(legs)

    def pad(key, fill, dtype):
        out = np.full((L, N), fill, dtype=dtype)
        for i, x in enumerate(per_leg):
            out[i, : x[key].size] = x[key]
        return out

    angle = pad("angle", 0.0, np.float32)
    velocity = pad("velocity", 0.0, np.float32)
    acceleration = pad("acceleration", 0.0, np.float32)
    stimulation = pad("stimulation", 0.0, np.float32)
    sample_mask = pad("mask", False, bool)
    reset = begin = shoot_start = None
    if objective == "angle":  # each stretch of compared samples starts a free run from its measured state
        reset = sample_mask & ~np.concatenate([np.zeros((L, 1), bool), sample_mask[:, :-1]], axis=1)
        if act.name != "no_muscle":  # and again every shooting segment, the active part carried from the trial's start
            at = np.arange(N)
            since = at - np.maximum.accumulate(np.where(reset, at, 0), axis=1)  # samples since the stretch began
            reset |= sample_mask & (since % shooting_samples(model.sampling_period_s) == 0)
            begin = at[None, :] == pad("trial_start", -1, np.int64)
            counts = reset.sum(axis=1)
            shoot_start = np.zeros((L, _bucket(int(counts.max()))), np.int64)  # spare runs start at 0, unread
            for i in range(L):
                shoot_start[i, : counts[i]] = np.flatnonzero(reset[i])
        sample_mask = sample_mask & ~reset
    starts = pad("start", True, bool)
    sample_segment = pad("segment", -1, np.int64)

    window = np.cumsum(starts, axis=1) - 1
    W = _bucket(int(window.max()) + 2)  # + at least one spare, masked window
    window_len = np.zeros((L, W), np.float32)
    window_mask = np.zeros((L, W), bool)
    window_segment = np.zeros((L, W), np.int64)
    for i in range(L):
        m = sample_mask[i]
        np.add.at(window_len[i], window[i][m], 1.0)
        window_mask[i] = window_len[i] > 0
        first = np.flatnonzero(starts[i] & m)
        window_segment[i, window[i][first]] = sample_segment[i][first]
    window_len = np.maximum(window_len, 1.0)
    # the noise of a window depends on its length alone (window_noise): computed once per length
    distinct = [np.unique(window_len[i]) for i in range(L)]
    window_lengths = np.ones((L, _bucket(max(d.size for d in distinct))), np.float32)
    window_length_index = np.zeros((L, W), np.int64)
    for i, d in enumerate(distinct):
        window_lengths[i, : d.size] = d
        window_length_index[i] = np.searchsorted(d, window_len[i])
    # one-sample windows (most of them) take σ and ν as scalars; only the longer ones need the table
    single_mask = window_mask & (window_len == 1.0)
    multi = [np.flatnonzero(window_mask[i] & (window_len[i] > 1.0)) for i in range(L)]
    T = max(m.size for m in multi)
    T = _bucket(T) if T else 0
    multi_window = np.full((L, T), W - 1, np.int64)
    multi_mask = np.zeros((L, T), bool)
    for i, m in enumerate(multi):
        multi_window[i, : m.size] = m
        multi_mask[i, : m.size] = True
    S = max(x["n_segments"] for x in per_leg)
    segment_mask = np.zeros((L, S), bool)
    for i in range(L):
        # a segment is a PSIS-LOO unit where a compared window starts in it: one whose samples are
        # all excluded, cut off or inside a window credited to the segment before holds nothing
        first = np.flatnonzero(starts[i] & sample_mask[i])
        segment_mask[i, sample_segment[i][first]] = True

    pulse_ok = pad("pulse_ok", False, bool)
    delivered = [np.flatnonzero((stimulation[i] > 0) & pulse_ok[i]) for i in range(L)]
    # the pulses whose response the likelihood compares somewhere: a pulse in an excluded stretch
    # still acts on the samples after it, except on twitch windows, where its response lies whole
    # in its own (excluded) window.  Every delivered pulse counts for the pulse effects' history
    # (count, interval) below.
    acting = [sample_mask[i][p] | (resolution != "twitch") for i, p in enumerate(delivered)]
    pulses = [p[a] for p, a in zip(delivered, acting)]
    P = _bucket(max(1, max(p.size for p in pulses)))
    pulse_sample = np.zeros((L, P), np.int64)
    pulse_u = np.zeros((L, P), np.float32)
    pulse_ipi = np.full((L, P), FIRST_IPI_S, np.float32)
    pulse_count = np.zeros((L, P), np.float32)
    pulse_time = np.zeros((L, P), np.float32)
    dt = model.sampling_period_s
    for i, (p, a) in enumerate(zip(delivered, acting)):
        k0 = per_leg[i]["trial_start"][p]  # first sample of each pulse's trial
        new_trial = np.concatenate([[True], k0[1:] != k0[:-1]])
        first = np.maximum.accumulate(np.where(new_trial, np.arange(p.size), 0))
        ipi = np.where(new_trial, FIRST_IPI_S + (p - k0) * dt, np.concatenate([[0.0], np.diff(p) * dt]))
        n = int(a.sum())
        pulse_sample[i, :n] = p[a]
        pulse_u[i, :n] = stimulation[i, p[a]]
        pulse_count[i, :n] = (np.arange(p.size) - first)[a]
        pulse_time[i, :n] = ((p - k0) * dt)[a]
        pulse_ipi[i, :n] = ipi[a]

    # at delay d a pulse's response may reach from d - K (the shortest delay an angle
    # effect allows) to d + R - 1 samples after it: R + K extended lags
    D = N_DELAYS
    RK = R + K
    lag = np.arange(RK) - K
    touch_sample = np.zeros((L, D, P * RK), np.int64)
    touch_valid = np.zeros((L, D, P * RK), bool)
    touch_pos = np.zeros((L, D, P * RK), np.int64)
    found = []
    for i in range(L):
        for d in range(D):
            s = (pulse_sample[i][:, None] + d + lag[None, :]).reshape(-1)
            ok = (s >= 0) & (s < N) & (pulse_u[i][:, None] > 0).repeat(RK, axis=1).reshape(-1)
            s = np.where(ok, s, 0)
            ok &= sample_mask[i][s]
            w = window[i][s]
            uniq, inv = np.unique(np.where(ok, w, -1), return_inverse=True)
            touch_sample[i, d] = s
            touch_valid[i, d] = ok
            found.append((i, d, uniq, inv.reshape(-1)))
    U = _bucket(max(1, max(u.size for _, _, u, _ in found)))
    touch_window = np.full((L, D, U), W - 1, np.int64)
    touch_mask = np.zeros((L, D, U), bool)
    for i, d, uniq, inv in found:
        touch_window[i, d, : uniq.size] = np.where(uniq >= 0, uniq, W - 1)
        touch_mask[i, d, : uniq.size] = uniq >= 0
        touch_pos[i, d] = inv

    window = np.where(sample_mask, window, W - 1)
    step = {}
    if K and getattr(model.delay_effect, "step_param", None):
        step = step_tables(angle, pulse_sample, pulse_u, touch_valid, touch_pos, R + K)
    slots = pulse_tables(window, sample_mask, pulse_sample, pulse_u, R, W) if resolution == "twitch" and not model.outputs else {}
    if slots and step:
        slots |= pulse_step_tables(step["step_order"], slots["pulse_slot"])
    subjects = tuple(dict.fromkeys(x["subject"] for x in per_leg))
    return LikelihoodData(
        legs=legs,
        subjects=subjects,
        leg_subject=np.array([subjects.index(x["subject"]) for x in per_leg]),
        trials=trials,
        resolution=resolution,
        response_length=R,
        max_shift=K,
        angle=angle,
        velocity=velocity,
        acceleration=acceleration,
        stimulation=stimulation,
        sample_mask=sample_mask,
        window=window,
        window_len=window_len,
        window_lengths=window_lengths,
        window_length_index=window_length_index,
        window_mask=window_mask,
        single_mask=single_mask,
        multi_window=multi_window,
        multi_mask=multi_mask,
        window_segment=window_segment,
        n_segments=S,
        segment_mask=segment_mask,
        pulse_sample=pulse_sample,
        pulse_u=pulse_u,
        pulse_ipi_s=pulse_ipi,
        pulse_count=pulse_count,
        pulse_time_s=pulse_time,
        touch_sample=touch_sample,
        touch_valid=touch_valid,
        touch_pos=touch_pos,
        touch_window=touch_window,
        touch_mask=touch_mask,
        **step,
        **slots,
        trial_start=pad("trial_start", 0, np.int64),
        objective=objective,
        reset=reset,
        begin=begin,
        shoot_start=shoot_start,
    )


def pulse_tables(window, sample_mask, pulse_sample, pulse_u, R: int, W: int) -> dict:
    """The pulse-level path's tables, or {} where it does not apply.

    On twitch windows (the zero-order activation) a pulse's whole response lies
    inside the window of its own sample for every delay, so a window's model sum
    is Σ over its pulses of u_i q_i F(p_i + d − shift) Σh: one term per pulse
    rather than one per (pulse, lag), the same windows for every d.  Checked
    here on the data: every sample from a pulse to MAX_DELAY + R − 1 after it
    must lie in the pulse's window and be compared.  (The lags before a pulse,
    which only a shift longer than d reaches, are not checked: the prior gives
    those combinations no mass.)  A slot is a window holding at least one pulse.
    """
    L, P = pulse_sample.shape
    N = window.shape[1]
    reach = np.arange(MAX_DELAY + R)
    found = []
    for i in range(L):
        ok = pulse_u[i] > 0
        p = pulse_sample[i][ok]
        s = p[:, None] + reach[None, :]
        if s.size and s.max() >= N:
            return {}
        if not (sample_mask[i][s].all() and (window[i][s] == window[i][p][:, None]).all()):
            return {}
        uniq, inv = np.unique(window[i][p], return_inverse=True)
        found.append((ok, uniq, inv.reshape(-1)))
    V = _bucket(max(u.size for _, u, _ in found) + 1)  # + a spare, masked slot for the padding pulses
    pulse_slot = np.full((L, P), V - 1, np.int64)
    slot_window = np.full((L, V), W - 1, np.int64)  # the last window is masked
    slot_mask = np.zeros((L, V), bool)
    for i, (ok, uniq, inv) in enumerate(found):
        pulse_slot[i, ok] = inv
        slot_window[i, : uniq.size] = uniq
        slot_mask[i, : uniq.size] = True
    return {"pulse_slot": pulse_slot, "slot_window": slot_window, "slot_mask": slot_mask}


def pulse_step_tables(step_order, pulse_slot) -> dict:
    """:func:`step_tables` for the pulse-level path: a (window, pulse) pair is a pulse, so the
    running sums run over the pulses ordered by slot, then by angle."""
    L, P = pulse_slot.shape
    rank = np.argsort(step_order, axis=1)
    slot_order = np.stack([np.lexsort((rank[i], pulse_slot[i])) for i in range(L)])
    pos = np.argsort(slot_order, axis=1)  # each pulse's position in that order
    sorted_slot = np.take_along_axis(pulse_slot, slot_order, axis=1)
    new_slot = np.concatenate([np.ones((L, 1), bool), sorted_slot[:, 1:] != sorted_slot[:, :-1]], axis=1)
    first = np.maximum.accumulate(np.where(new_slot, np.arange(P)[None, :], 0), axis=1)
    return {
        "step_slot_order": slot_order,
        "step_slot_first": first,
        "step_rank_pos": np.take_along_axis(pos, step_order, axis=1),
    }


def step_tables(angle, pulse_sample, pulse_u, touch_valid, touch_pos, RK: int) -> dict:
    """What summing out a step delay effect's threshold needs, from the data alone.

    Under the hard step the pulses delivered below the threshold take the shorter
    delay; ordering the pulses by their angle, every threshold between the j-th and
    the (j+1)-th angle shortens the first j, so the threshold's P + 1 intervals are
    P + 1 states.  Moving from state j to j + 1 changes the windows that pulse j+1
    reaches; in each such window, what the pulses before it in angle order have
    already changed is a running sum over the window's (window, pulse) pairs, taken
    in angle order.  Returns the ``step_*`` fields of :class:`LikelihoodData`.
    """
    L, P = pulse_sample.shape
    D = touch_valid.shape[1]
    key = np.where(pulse_u > 0, np.take_along_axis(angle, pulse_sample, axis=1), np.inf)
    order = np.argsort(key, axis=1, kind="stable")
    rank = np.argsort(order, axis=1)
    pulse_of_entry = np.repeat(np.arange(P), RK)
    found = []
    for i in range(L):
        for d in range(D):
            ok = touch_valid[i, d]
            pairs = np.stack([touch_pos[i, d], rank[i][pulse_of_entry]], axis=1)[ok]
            uniq, inv = np.unique(pairs, axis=0, return_inverse=True)
            found.append((i, d, ok, uniq, inv.reshape(-1)))
    Q = _bucket(max(1, max(u.shape[0] for *_, u, _ in found)) + 1)  # + a spare pair for the masked entries
    entry_pair = np.full((L, D, P * RK), Q - 1, np.int64)
    pair_window = np.zeros((L, D, Q), np.int64)
    pair_pulse = np.zeros((L, D, Q), np.int64)
    pair_first = np.zeros((L, D, Q), np.int64)
    pair_mask = np.zeros((L, D, Q), bool)
    for i, d, ok, uniq, inv in found:
        n = uniq.shape[0]
        entry_pair[i, d, ok] = inv
        pair_window[i, d, :n] = uniq[:, 0]
        pair_pulse[i, d, :n] = order[i][uniq[:, 1]]
        new_window = np.concatenate([[True], uniq[1:, 0] != uniq[:-1, 0]]) if n else np.zeros(0, bool)
        pair_first[i, d, :n] = np.maximum.accumulate(np.where(new_window, np.arange(n), 0))
        pair_first[i, d, n:] = np.arange(n, Q)
        pair_mask[i, d, :n] = True
    return {
        "step_order": order,
        "step_pulse_valid": np.take_along_axis(pulse_u > 0, order, axis=1),
        "step_entry_pair": entry_pair,
        "step_pair_window": pair_window,
        "step_pair_pulse": pair_pulse,
        "step_pair_first": pair_first,
        "step_pair_mask": pair_mask,
    }


# ============================================================================ JAX side


def free_run_angles(model: Model, x: dict):
    """The goniometer reading that ``model``'s free run predicts at every sample of one leg: a run
    starts afresh from the measured angle and velocity at each ``x["reset"]`` sample and steps
    by RK4 until the next: eq. (8)'s passive system alone, or, for a model with a muscle
    (``x["begin"]`` present), the whole model at its delay (:func:`_shooting_run`).
    Differentiable in the model's parameters (not in the data)."""
    if "begin" in x:
        return _shooting_run(model, x)
    return _free_run(model, x["angle"], x["velocity"], x["reset"])


def _shooting_run(model: Model, x: dict):
    """The angle of a model with a muscle run from the measured state at every ``x["reset"]``
    sample (listed in ``x["shoot_start"]``) for at most :func:`shooting_samples`.  The active
    part is first driven through the leg by the measured angle and velocity, from rest at each
    ``x["begin"]`` (a trial's first sample); each run takes it over where it starts, as
    :func:`quadshank.model._model.predict_ahead` does.  The runs are independent, so they go
    side by side (a scan as long as one segment): in reverse mode this costs about an eighth of
    one scan through every sample that restarts at each reset."""
    dt = model.sampling_period_s
    p = shooting_samples(dt)
    dtype = _run_dtype(model, x["angle"])
    true = true_angle(model, x["angle"].astype(dtype))
    velocity, stimulation, starts = x["velocity"].astype(dtype), x["stimulation"].astype(dtype), x["shoot_start"]
    carries = _carries(model, true, velocity, stimulation, begin=x["begin"], bound=_bounded)

    def run(active, a, v, us):
        def body(state, u):
            active, a, v = state
            active, m = _active_step(model, active, u, a, v)
            a2, v2 = _rk4(model, a, v, m, dt)
            return (_bounded(active), jnp.clip(a2, -RUN_LIMIT_DEG, RUN_LIMIT_DEG),
                    jnp.clip(v2, -RUN_LIMIT_DEG_S, RUN_LIMIT_DEG_S)), a

        return jax.lax.scan(body, (active, a, v), us)[1]

    n = stimulation.shape[0]
    us = jnp.concatenate([stimulation, jnp.zeros(p, stimulation.dtype)])[starts[:, None] + jnp.arange(p)]
    runs = jax.vmap(run)(jax.tree_util.tree_map(lambda c: c[starts], carries), true[starts], velocity[starts], us)
    segment = jnp.clip(jnp.cumsum(x["reset"]) - 1, 0, starts.shape[0] - 1)  # the run each sample belongs to
    offset = jnp.clip(jnp.arange(n) - starts[segment], 0, p - 1)  # within its segment (samples outside are masked)
    return measured_angle(model, runs[segment, offset])


def _run_dtype(model: Model, data):
    """The precision a run of ``model`` on ``data`` computes in: that of the parameters and the
    data together (a scan's carry must keep one type, and double-precision parameters on
    single-precision data would otherwise start it in single and step it in double)."""
    return jnp.result_type(data, _float_leaves(model)[3])


def _bounded(carry):
    """``carry`` with its floating leaves within ±:data:`CARRY_LIMIT`.  Far from the mode (an
    optimiser's trial step, an unstable twitch filter) the active part and a run can grow without
    bound and overflow into NaN, whose gradient no mask removes; bounded, such a run is merely
    improbable (a residual of a turn or more), and the optimiser steps back."""
    return jax.tree_util.tree_map(
        lambda c: jnp.clip(c, -CARRY_LIMIT, CARRY_LIMIT) if jnp.issubdtype(c.dtype, jnp.floating) else c, carry)


def _at_delay(model: Model, x: dict, d):
    """``model`` at delay ``d`` where its angle objective runs the muscle (``x["begin"]``);
    else ``model`` (the pendulum alone has no delay, the acceleration sums it out itself)."""
    return model.with_params(delay=d) if "begin" in x else model


def _free_run_plain(model: Model, angle, velocity, reset):
    dt = model.sampling_period_s
    dtype = _run_dtype(model, angle)
    true, velocity = true_angle(model, angle.astype(dtype)), velocity.astype(dtype)

    def body(state, inputs):
        start, a_meas, v_meas = inputs
        a = jnp.where(start, a_meas, state[0])
        v = jnp.where(start, v_meas, state[1])
        return _rk4(model, a, v, 0.0, dt), a

    _, predicted = jax.lax.scan(body, (true[0], velocity[0]), (reset, true, velocity))
    return measured_angle(model, predicted)


def _float_leaves(model: Model):
    """The model's leaves, its tree, the positions of its floating leaves (the parameters), their
    concatenation and the function that splits a vector of that length back into them."""
    leaves, tree = jax.tree_util.tree_flatten(model)
    at = [i for i, v in enumerate(leaves) if jnp.issubdtype(jnp.result_type(v), jnp.inexact)]
    flat, unravel = jax.flatten_util.ravel_pytree([leaves[i] for i in at])
    return leaves, tree, at, flat, unravel


def _with_floats(leaves, tree, at, floats):
    """The tree of ``leaves`` with the leaves at positions ``at`` replaced by ``floats``."""
    out = list(leaves)
    for i, leaf in zip(at, floats):
        out[i] = leaf
    return tree.unflatten(out)


# The free run's gradient by forward sensitivities: a reverse pass through the scan over every
# sample costs about six forward runs, while the handful of parameters of the pendulum alone ride
# along a single forward run as tangents (jacfwd), and J^T g is then one product.
@jax.custom_vjp
def _free_run(model: Model, angle, velocity, reset):
    return _free_run_plain(model, angle, velocity, reset)


def _free_run_fwd(model, angle, velocity, reset):
    leaves, tree, at, flat, unravel = _float_leaves(model)

    def run(v):
        out = _free_run_plain(_with_floats(leaves, tree, at, unravel(v)), angle, velocity, reset)
        return out, out

    jac, predicted = jax.jacfwd(run, has_aux=True)(flat)  # (N, parameters)
    return predicted, (model, jac, angle, velocity, reset)


def _free_run_bwd(res, g):
    model, jac, angle, velocity, reset = res
    leaves, tree, at, _, unravel = _float_leaves(model)
    zeros = [np.zeros(np.shape(v), jax.dtypes.float0) for v in leaves]
    # the data are measured, not differentiated
    return (_with_floats(zeros, tree, at, unravel(g @ jac)), jnp.zeros_like(angle), jnp.zeros_like(velocity),
            np.zeros(np.shape(reset), jax.dtypes.float0))


_free_run.defvjp(_free_run_fwd, _free_run_bwd)


def _angle_logpdf(model: Model, noise: dict, x: dict):
    """Student-t log density (σ and ν in degrees) of each compared sample's measured angle about
    its free run's (:func:`free_run_angles`), 0 where not compared."""
    r = x["angle"] - free_run_angles(model, x)
    return jnp.where(x["sample_mask"], student_t_logpdf(r, noise["nu"], noise["sigma"]), 0.0)


def student_t_logpdf(x, nu, scale):
    """log density of a Student-t with ``nu`` degrees of freedom and ``scale`` at ``x``."""
    return _t_norm(nu, scale) + _t_kernel(x, nu, scale)


def _t_norm(nu, scale):
    """The Student-t log density's normalising term (the part that does not depend on x)."""
    gammaln = jax.scipy.special.gammaln
    return gammaln(0.5 * (nu + 1.0)) - gammaln(0.5 * nu) - 0.5 * jnp.log(nu * math.pi) - jnp.log(scale)


def _pulse_variance(model: Model):
    """Σ of the noise effects' pulse variances (a pulse's random gain's variance relative to its
    mean, CV²); None for a model without noise effects."""
    if not model.noises:
        return None
    return sum(e.pulse_variance() for e in model.noises)


def _widened(scale, c2, V):
    """The scale of a window whose pulses' random gains add ``c2 · V`` to its squared scale
    (``V``: Σ over the window's pulses of their modelled output's square), and the change this
    makes to the log density's normalising term, log(scale) − log(widened scale)."""
    wide = jnp.sqrt(scale * scale + c2 * V)
    return wide, jnp.log(scale) - jnp.log(wide)


def _square_sums(model: Model, c, key, RK: int, n: int):
    """Σ over each window's pulses of (the pulse's output in that window)², by window ``key`` (n,):
    per unit CV², the variance the pulses' random gains add to the window.  ``c`` and ``key`` are
    flat over (pulse, extended lag), RK lags per pulse.  Every lag reaches its own sample, so on
    one-sample windows (``resolution = "sample"``) that is Σ c²; on twitch windows a pulse's lags
    in one window form one run of equal keys, summed before squaring."""
    if model.activation.resolution == "sample":
        return jax.ops.segment_sum(c * c, key, num_segments=n)
    k = key.reshape(-1, RK)
    start = jnp.concatenate([jnp.ones((k.shape[0], 1), bool), k[:, 1:] != k[:, :-1]], axis=1).reshape(-1)
    run = jnp.round(_cumsum(start.astype(c.dtype)[None, :])[0]).astype(key.dtype) - 1  # see _cumsum: not jnp.cumsum
    m = c.shape[-1]
    run_sum = jax.ops.segment_sum(c, run, num_segments=m)
    run_key = jnp.clip(jax.ops.segment_max(key, run, num_segments=m), 0, n - 1)  # unused runs hold 0
    return jax.ops.segment_sum(run_sum * run_sum, run_key, num_segments=n)


def _sensed(model: Model, x: dict) -> dict:
    """The leg's arrays with the goniometer's reading replaced by the true angle."""
    return dict(x, angle=true_angle(model, x["angle"])) if model.measurements else x


def model_response(model: Model, length: int):
    """The equivalent acceleration the accelerometer reads for a unit pulse at step 0 (no gain factors)."""
    h = impulse_response(model.activation, length)
    g = acceleration_response(model)
    return h if g is None else causal_fir(h, g)


def impulse_response(activation: Effect, length: int):
    """The activation effect's output for a unit pulse at step 0, ``length`` samples."""
    u = jnp.zeros(length).at[0].set(1.0)

    def body(state, x):
        return activation.step(state, x)

    _, h = jax.lax.scan(body, activation.init_state(), u)
    return h


def _is_stateless(effect: Effect) -> bool:
    return type(effect).gain is Effect.gain


def gain_factors(model: Model, angle, velocity, stimulation):
    """Π of the gain effects' factors at every sample's measured state."""
    F = jnp.ones_like(angle)
    ctx = StepContext(angle=angle, velocity=velocity, u=stimulation, u_now=stimulation)
    for g in model.gains:
        if not _is_stateless(g):
            raise LikelihoodError(
                f"effect {g.name!r} keeps a state across pulses; the hierarchical fit needs gains written as factor(ctx)"
            )
        F = F * g.factor(ctx)
    return F


def window_noise(sigma, nu, n):
    """Scale and degrees of freedom of the Student-t that stands for a sum of ``n`` samples of σ·t_ν.

    The sum's variance n σ² ν/(ν − 2) is matched exactly; for ν > 4 its excess
    kurtosis 6/(n(ν − 4)) is matched by ν_n = ν + (n − 1)(ν − 4), smoothed near
    ν = 4 as ν + (n − 1) x₊²/(x₊ + ½) with x = ν − 4 so that its gradient is
    continuous.  For ν ≤ 4 (no finite kurtosis) and for n = 1 it is σ√n and ν.
    """
    x = jnp.maximum(nu - 4.0, 0.0)
    nu_n = nu + (jnp.maximum(n, 1.0) - 1.0) * x * x / (x + 0.5)
    # ν(ν_n − 2) / ((ν − 2) ν_n), written so that ν ≤ 4 (where ν_n = ν) gives exactly 1
    ratio = nu / nu_n * (1.0 + (nu_n - nu) / jnp.maximum(nu - 2.0, 1.0))
    return sigma * jnp.sqrt(n * ratio), nu_n


def _at(v, i):
    """``v[i]`` for a per-window array, ``v`` itself for a scalar shared by every window."""
    return v if jnp.ndim(v) == 0 else v[i]


def _noise_table(noise: dict, x: dict):
    """Scale and degrees of freedom (:func:`window_noise`) per distinct window length of the
    leg, computed once per length: their log-gamma terms would otherwise cost more than the
    rest of the likelihood.  None where every window is one sample."""
    if x["multi_window"].shape[-1] == 0:
        return None
    return window_noise(noise["sigma"], noise["nu"], x["window_lengths"])


def _noise_at(noise: dict, table, x: dict, windows):
    """Scale and degrees of freedom of the sums of ``windows`` (an index array into the leg's
    windows): from the table, or σ and ν themselves (scalars) where every window is one sample."""
    if table is None:
        return noise["sigma"], noise["nu"]
    i = x["window_length_index"][windows]
    return table[0][i], table[1][i]


def _window_terms(model: Model, noise: dict, x: dict):
    """Window sums E of the equivalent acceleration, the noise table (:func:`_noise_table`),
    the base log-likelihood (every compared window's log density with no active output) and
    each window's log density kernel with no active output (W,), which the (pulse, lag) path
    subtracts for the windows a delay's pulses reach.  A one-sample window's density is σ t_ν
    as it is, with scalar σ and ν; only the windows of more than one sample (twitch windows)
    take theirs from the table."""
    W = x["window_length_index"].shape[-1]
    # x["angle"] is already the true angle (see _sensed)
    passive = jnp.where(x["sample_mask"], passive_acceleration(model, x["angle"], x["velocity"]), 0.0)
    e = x["acceleration"] - measured_acceleration(model, passive)
    e = jnp.where(x["sample_mask"], e, 0.0)
    E = jax.ops.segment_sum(e, x["window"], num_segments=W)
    sigma, nu = noise["sigma"], noise["nu"]
    k0 = _t_kernel(E, nu, sigma)
    base = _total(jnp.where(x["single_mask"], k0, 0.0))
    base = base + jnp.sum(x["single_mask"]) * _t_norm(nu, sigma)
    table = _noise_table(noise, x)
    if table is not None:
        mw = x["multi_window"]
        s, n = _noise_at(noise, table, x, mw)
        k_multi = _t_kernel(E[mw], n, s)
        base = base + _total(jnp.where(x["multi_mask"], _t_norm(n, s) + k_multi, 0.0))
        # padding entries name the spare window W − 1, which holds no sample (E = 0, kernel 0)
        k0 = k0.at[mw].set(k_multi)
    return E, table, base, k0


def _all_windows(model: Model, noise: dict, x: dict):
    """Window sums E of the equivalent acceleration with every window's scale, degrees of
    freedom and log density's normalising term (for the LOO-PIT and the pointwise values)."""
    E, table, _, _ = _window_terms(model, noise, x)
    if table is None:
        scale, nu = noise["sigma"], noise["nu"]
        return E, scale, nu, _t_norm(nu, scale)
    scale_z, nu_z = table
    i = x["window_length_index"]
    return E, scale_z[i], nu_z[i], _t_norm(nu_z, scale_z)[i]


def _pulse_q(model: Model, x: dict):
    """u_i · q_i: each pulse's recruitment level times the pulse effects' factor."""
    u = x["pulse_u"]
    if not model.pulses:
        return u
    p = x["pulse_sample"]
    pctx = PulseContext(
        u=u, ipi_s=x["pulse_ipi_s"], count=x["pulse_count"], time_s=x["pulse_time_s"], angle=x["angle"][p], velocity=x["velocity"][p]
    )
    return u * pulse_factors(model, pctx)


def output_factors(model: Model, angle, velocity, stimulation):
    """Π of the output effects' factors at every sample's state (None without output effects)."""
    if not model.outputs:
        return None
    ctx = StepContext(angle=angle, velocity=velocity, u=stimulation, u_now=stimulation)
    G = jnp.ones_like(angle)
    for o in model.outputs:
        G = G * o.output_factor(ctx)
    return G


def _padded_response(model: Model, R: int, K: int, G=None):
    """The model's response to a unit pulse, R samples, with K zeros on either side: the slice
    of R + K from ``shift`` is the response on the extended lags −K … R − 1 at delay d − shift.
    With output factors ``G`` and an accelerometer response, the activation's own response: the
    factors act on the muscle's output before the accelerometer reads it (:func:`_outputs`)."""
    h = impulse_response(model.activation, R) if _outputs_before_sensor(model, G) else model_response(model, R)
    return jnp.concatenate([jnp.zeros(K, h.dtype), h, jnp.zeros(K, h.dtype)])


def _outputs_before_sensor(model: Model, G) -> bool:
    return G is not None and acceleration_response(model) is not None


def _outputs(model: Model, x: dict, amp, d, K: int, G, samples):
    """Each (pulse, extended lag)'s output ``amp`` (P, R + K), flattened, times the output factors
    ``G`` at the sample it reaches.  With an accelerometer response ``amp`` is the muscle's own
    output (:func:`_padded_response`): the factors scale it at every sample it reaches, and each
    pulse's row then passes through the response, as the simulator measures M·G + passive."""
    if G is None:
        return amp.reshape(-1)
    if not _outputs_before_sensor(model, G):
        return amp.reshape(-1) * G[samples]
    # the samples the lags reach, excluded ones included: their output still reaches the
    # accelerometer's later samples (``samples`` names sample 0 where a lag is not compared)
    reach = x["pulse_sample"][:, None] + d - K + jnp.arange(amp.shape[-1])[None, :]
    G_reach = G[jnp.clip(reach, 0, G.shape[-1] - 1)]
    return causal_fir(amp * G_reach, acceleration_response(model)).reshape(-1)


def _contributions(model: Model, x: dict, R: int, K: int, shift, d, F, uq, valid, samples, G=None):
    """M̂ of each (pulse, extended lag) at delay d and one shift, flattened; 0 where it reaches no sample.

    Extended lag q is sample p_i + d − K + q.  A pulse takes delay d with weight
    1 − w_i and d − shift with weight w_i (w from the delay effect at the pulse's
    angle), so shift 0 is the plain response; each part is scaled by the gain
    factors at its own onset, and the whole by the output factors ``G`` at the
    sample it reaches (``samples``).  ``shift`` and ``d`` may be traced.
    """
    h_pad = _padded_response(model, R, K, G)
    long = h_pad[None, : R + K]
    p = x["pulse_sample"]
    last = F.shape[-1] - 1
    F_long = F[jnp.clip(p + d, 0, last)][:, None]
    if K == 0:
        amp = uq[:, None] * F_long * long
    else:
        w = model.delay_effect.pulse_weight(x["angle"][p])[:, None]
        short = jax.lax.dynamic_slice_in_dim(h_pad, shift, R + K)[None, :]
        F_short = F[jnp.clip(p + d - shift, 0, last)][:, None]
        amp = uq[:, None] * ((1.0 - w) * F_long * long + w * F_short * short)
    return jnp.where(valid, _outputs(model, x, amp, d, K, G, samples), 0.0)


def _leg_terms(model: Model, noise: dict, x: dict):
    """What every delay of one leg shares: the arrays with the true angle, the window sums of
    the equivalent acceleration, the noise table (:func:`_noise_table`), the base
    log-likelihood, each window's kernel with no active output, the gain and output factors
    at every sample, and each pulse's u·q."""
    x = _sensed(model, x)
    E, table, base, k0 = _window_terms(model, noise, x)
    F = gain_factors(model, x["angle"], x["velocity"], x["stimulation"])
    G = output_factors(model, x["angle"], x["velocity"], x["stimulation"])
    return x, E, table, base, k0, F, G, _pulse_q(model, x)


def leg_loglik_by_delay(model: Model, noise: dict, x: dict, R: int, K: int = 0):
    """log p(y_leg | θ, d, shift), shape (MAX_DELAY + 1, K + 1), one leg (vmap over legs outside).

    Entries with shift > d are computed but meaningless (the prior excludes them).
    """
    if "reset" in x and "begin" in x:  # the angle objective with a muscle: one run per delay (K = 0)
        lp = jax.vmap(lambda d: jnp.sum(_angle_logpdf(_at_delay(model, x, d), noise, x)))(jnp.arange(N_DELAYS))
        return jnp.broadcast_to(lp[:, None], (N_DELAYS, K + 1))
    if "reset" in x:  # the angle objective: no muscle, so every delay alike
        return jnp.broadcast_to(jnp.sum(_angle_logpdf(model, noise, x)), (N_DELAYS, K + 1))
    model = _at_data_precision(model, x)
    if "pulse_slot" in x:
        return _by_delay_pulses(model, noise, x, R, K)
    x, E, table, base, k0, F, G, uq = _leg_terms(model, noise, x)
    c2 = _pulse_variance(model)
    U = x["touch_window"].shape[-1]
    delays = jnp.arange(x["touch_sample"].shape[0])
    out = []
    for shift in range(K + 1):

        def one(d, valid, samples, pos, tw, tm, shift=shift):
            c = _contributions(model, x, R, K, shift, d, F, uq, valid, samples, G)
            M = jax.ops.segment_sum(c, pos, num_segments=U)
            s, n = _noise_at(noise, table, x, tw)
            if c2 is None:
                lp = _t_kernel(E[tw] - M, n, s) - k0[tw]
            else:
                wide, dnorm = _widened(s, c2, _square_sums(model, c, pos, R + K, U))
                lp = _t_kernel(E[tw] - M, n, wide) + dnorm - k0[tw]
            return _total(jnp.where(tm, lp, 0.0))

        out.append(jax.vmap(one)(delays, x["touch_valid"], x["touch_sample"], x["touch_pos"], x["touch_window"], x["touch_mask"]))
    return base + jnp.stack(out, axis=-1)


def _t_kernel(x, nu, scale):
    """The part of the Student-t log density that depends on ``x``: a difference of two
    log densities at the same scale needs only this.  At ``x``'s precision (see
    :func:`_at_data_precision`)."""
    x = jnp.asarray(x)
    nu, scale = jnp.asarray(nu, x.dtype), jnp.asarray(scale, x.dtype)
    z = x / scale
    return -0.5 * (nu + 1.0) * jnp.log1p(z * z / nu)


def _at_data_precision(model: Model, x: dict) -> Model:
    """``model`` with its floating parameters at the precision of the leg's data.

    The fit's likelihood is a sum of about 10⁵ terms: each term is computed at the data's
    precision and the terms are summed in double where JAX's x64 is on (:func:`_total`).  Given
    single-precision data (as :func:`prepare` stores them) and double-precision parameters (as
    the fit samples), each sample's passive acceleration, window sum and log density kernel
    cost half the memory traffic and vector width of double precision, while the sums, whose
    rounding in single precision (0.06 on a log density of 10⁶) NUTS would see in every energy
    difference, stay in double.  Given double-precision data, everything is double."""
    dtype = x["acceleration"].dtype

    def cast(v):
        v = jnp.asarray(v)
        return v.astype(dtype) if jnp.issubdtype(v.dtype, jnp.floating) and v.dtype != dtype else v

    return jax.tree_util.tree_map(cast, model)


def _fine_dtype(dtype):
    """``dtype`` or the finest floating precision enabled, whichever is finer (double where JAX's x64 is on)."""
    return jnp.promote_types(dtype, jax.dtypes.canonicalize_dtype(jnp.float64))


def _fine(a):
    """``a`` at the finest floating precision enabled (:func:`_fine_dtype`)."""
    a = jnp.asarray(a)
    return a.astype(_fine_dtype(a.dtype))


def _total(a, axis=None):
    """Σ of ``a`` along ``axis`` at the finest precision enabled (:func:`_at_data_precision`)."""
    a = jnp.asarray(a)
    return jnp.sum(a, axis=axis, dtype=_fine_dtype(a.dtype))


def _cumsum(x, block: int = 32):
    """Cumulative sum along the last axis in blocks: within each block by a triangular matrix
    product, then the blocks' totals.  XLA lowers ``jnp.cumsum`` on the CPU to a window
    reduction whose cost grows with the square of the length (5 ms for 110 rows of 2500)."""
    n = x.shape[-1]
    m = -(-n // block)
    xp = jnp.pad(x, [(0, 0)] * (x.ndim - 1) + [(0, m * block - n)]).reshape(*x.shape[:-1], m, block)
    within = xp @ jnp.triu(jnp.ones((block, block), x.dtype))
    before = within[..., -1] @ jnp.triu(jnp.ones((m, m), x.dtype), 1)  # the earlier blocks' totals
    return (within + before[..., None]).reshape(*x.shape[:-1], m * block)[..., :n]


def _running(b, first):
    """Along the last axis, the running sum of ``b`` within each window's pairs: including
    this pair, and excluding it (``first``: the position of the window's first pair)."""
    cs = _cumsum(b)
    incl = cs - (jnp.take(cs, first, axis=-1) - jnp.take(b, first, axis=-1))  # this pair and the window's earlier ones
    return incl, incl - b


def _pair_deltas(b, first, r, s, keep, nu, noise_terms=None):
    """Along the last axis, (window, pulse) pairs in window order and, within a window, in angle
    order: the change of each pair's window log density when its pulse takes the shorter delay
    after the window's pulses before it have.  ``b`` is each pair's change of the window's model
    sum, ``first`` the position of its window's first pair, ``r``, ``s`` and ``nu`` the window's
    residual (every pulse at the long delay), scale and degrees of freedom; 0 where ``keep`` is False.
    With random pulse gains, ``noise_terms`` = (bv, v0, c2): each pair's change of the window's
    Σ output², the window's Σ output² with every pulse at the long delay, and CV² (:func:`_widened`)."""
    incl, excl = _running(b, first)
    if noise_terms is None:
        return jnp.where(keep, _t_kernel(r - incl, nu, s) - _t_kernel(r - excl, nu, s), 0.0)
    bv, v0, c2 = noise_terms
    v_incl, v_excl = _running(bv, first)
    s_incl, n_incl = _widened(s, c2, v0 + v_incl)
    s_excl, n_excl = _widened(s, c2, v0 + v_excl)
    return jnp.where(keep, _t_kernel(r - incl, nu, s_incl) + n_incl - _t_kernel(r - excl, nu, s_excl) - n_excl, 0.0)


def _state_rows(ell_long, steps):
    """log-likelihood of threshold states 0 … P (last axis): state 0's ``ell_long`` (no pulse
    shortened) plus the running sum of the pulses' ``steps`` in increasing angle."""
    steps = _fine(steps)
    zero = jnp.zeros((*steps.shape[:-1], 1), steps.dtype)
    return ell_long[..., None] + jnp.concatenate([zero, _cumsum(steps)], axis=-1)


def leg_loglik_by_threshold(model: Model, noise: dict, x: dict, R: int, K: int):
    """log p(y_leg | θ, d, shift, state j), (MAX_DELAY + 1, K + 1, P + 1), one leg, for a step delay effect.

    State j: the threshold lies between the j-th and (j+1)-th pulse angle (pulses
    in increasing angle, :func:`step_tables`), so the first j pulses take delay
    d − shift under the hard step.  Column shift 0 is the same for every j.  The
    effect's own threshold is not read.
    """
    model = _at_data_precision(model, x)
    if "pulse_slot" in x:
        return _by_threshold_pulses(model, noise, x, R, K)
    x, E, table, base, k0, F, G, uq = _leg_terms(model, noise, x)
    c2 = _pulse_variance(model)
    U = x["touch_window"].shape[-1]
    Q = x["step_pair_mask"].shape[-1]
    P = x["pulse_sample"].shape[-1]
    h_pad = _padded_response(model, R, K, G)
    p = x["pulse_sample"]
    last = F.shape[-1] - 1

    def one(d, valid, samples, pos, tw, tm, entry_pair, pair_window, pair_pulse, pair_first, pair_mask):
        def amplitudes(shift):
            resp = jax.lax.dynamic_slice_in_dim(h_pad, shift, R + K)[None, :]
            amp = (uq * F[jnp.clip(p + d - shift, 0, last)])[:, None] * resp
            return jnp.where(valid, _outputs(model, x, amp, d, K, G, samples), 0.0)

        a_long = amplitudes(0)
        M = jax.ops.segment_sum(a_long, pos, num_segments=U)
        r0 = E[tw] - M
        s, n = _noise_at(noise, table, x, tw)
        if c2 is None:
            s_long, dnorm = s, 0.0
        else:  # each pulse's random gain scales its whole output in a window: (window, pulse) sums
            p_long = jax.ops.segment_sum(a_long, entry_pair, num_segments=Q)
            v_long = jax.ops.segment_sum(p_long * p_long, pair_window, num_segments=U)
            s_long, dnorm = _widened(s, c2, v_long)
        lp_long = jnp.where(tm, _t_kernel(r0, n, s_long) + dnorm - k0[tw], 0.0)
        ell_long = base + _total(lp_long)
        rows = [jnp.full((P + 1,), ell_long)]
        r_pair = r0[pair_window]
        s_pair = _at(s, pair_window)
        nu_pair = _at(n, pair_window)
        keep = pair_mask & tm[pair_window]
        for shift in range(1, K + 1):
            b = jax.ops.segment_sum(amplitudes(shift) - a_long, entry_pair, num_segments=Q)  # per (window, pulse)
            terms = None if c2 is None else ((p_long + b) ** 2 - p_long**2, v_long[pair_window], c2)
            delta = _pair_deltas(b, pair_first, r_pair, s_pair, keep, nu_pair, terms)
            per_pulse = jax.ops.segment_sum(delta, pair_pulse, num_segments=P)
            steps = jnp.where(x["step_pulse_valid"], per_pulse[x["step_order"]], 0.0)
            rows.append(_state_rows(ell_long, steps))
        return jnp.stack(rows)  # (K + 1, P + 1)

    delays = jnp.arange(x["touch_sample"].shape[0])
    return jax.vmap(one)(
        delays, x["touch_valid"], x["touch_sample"], x["touch_pos"], x["touch_window"], x["touch_mask"],
        x["step_entry_pair"], x["step_pair_window"], x["step_pair_pulse"], x["step_pair_first"], x["step_pair_mask"],
    )  # fmt: skip


# --------------------------------------------------------------- the pulse-level path


def _pulse_terms(model: Model, noise: dict, x: dict, R: int, K: int):
    """What the pulse-level path shares (see :func:`pulse_tables`): the arrays with the true
    angle, the base log-likelihood, the slots' window sums, scales, degrees of freedom and
    log density kernels with no active output, and each pulse's whole-twitch output (K + 1, D, P) at delay d when it takes shift s,
    u_i q_i F(p_i + d − s) Σh, the gain factors evaluated at those samples only."""
    x = _sensed(model, x)
    E, table, base, _ = _window_terms(model, noise, x)
    p = x["pulse_sample"]
    last = x["angle"].shape[-1] - 1
    at = jnp.clip(p[None, :] + jnp.arange(-K, N_DELAYS)[:, None], 0, last)  # (K + D, P): p + j, j = −K … MAX_DELAY
    F = gain_factors(model, x["angle"][at], x["velocity"][at], x["stimulation"][at])
    uq = _pulse_q(model, x)
    whole = uq * jnp.sum(model_response(model, R).astype(uq.dtype))  # summed at the data's precision
    amp = jnp.stack([whole * F[K - s : K - s + N_DELAYS] for s in range(K + 1)])
    sw = x["slot_window"]
    ss, nu = _noise_at(noise, table, x, sw)
    Es = E[sw]
    return x, base, Es, ss, nu, _t_kernel(Es, nu, ss), x["slot_mask"] & x["window_mask"][sw], amp


def _slot_sums(a, slot, V: int):
    """Σ over each slot's pulses of ``a`` (..., P) -> (..., V)."""
    lead = a.shape[:-1]
    flat = a.reshape(-1, a.shape[-1]).T  # (P, rest): one scatter of rows
    return jax.ops.segment_sum(flat, slot, num_segments=V).T.reshape(*lead, V)


def _by_delay_pulses(model: Model, noise: dict, x: dict, R: int, K: int):
    """:func:`leg_loglik_by_delay` on the pulse-level path."""
    x, base, Es, ss, nu, k0, keep, amp = _pulse_terms(model, noise, x, R, K)
    if K:
        w = model.delay_effect.pulse_weight(x["angle"][x["pulse_sample"]])
        amp = (1.0 - w) * amp[:1] + w * amp  # shift 0 is the plain response
    V = x["slot_window"].shape[-1]
    M = _slot_sums(jnp.moveaxis(amp, 0, 1), x["pulse_slot"], V)  # (D, K + 1, V)
    c2 = _pulse_variance(model)
    if c2 is None:
        lp = _t_kernel(Es - M, nu, ss) - k0
    else:
        wide, dnorm = _widened(ss, c2, _slot_sums(jnp.moveaxis(amp * amp, 0, 1), x["pulse_slot"], V))
        lp = _t_kernel(Es - M, nu, wide) + dnorm - k0
    return base + _total(jnp.where(keep, lp, 0.0), axis=-1)


def _by_threshold_pulses(model: Model, noise: dict, x: dict, R: int, K: int):
    """:func:`leg_loglik_by_threshold` on the pulse-level path: a (window, pulse) pair is a pulse."""
    x, base, Es, ss, nu, k0, keep, amp = _pulse_terms(model, noise, x, R, K)
    V = x["slot_window"].shape[-1]
    P = x["pulse_sample"].shape[-1]
    r0 = Es - _slot_sums(amp[0], x["pulse_slot"], V)  # (D, V): every pulse at its long delay
    c2 = _pulse_variance(model)
    if c2 is None:
        s_long, dnorm = ss, 0.0
    else:
        v_long = _slot_sums(amp[0] * amp[0], x["pulse_slot"], V)
        s_long, dnorm = _widened(ss, c2, v_long)
    ell_long = base + _total(jnp.where(keep, _t_kernel(r0, nu, s_long) + dnorm - k0, 0.0), axis=-1)
    order, first = x["step_slot_order"], x["step_slot_first"]
    slot = x["pulse_slot"][order]
    r_pair, s_pair, nu_pair, keep_pair = r0[:, slot], _at(ss, slot), _at(nu, slot), keep[slot]
    rows = [jnp.broadcast_to(ell_long[:, None], (N_DELAYS, P + 1))]
    for shift in range(1, K + 1):
        b = (amp[shift] - amp[0])[:, order]  # (D, P) by slot, then angle
        terms = None if c2 is None else ((amp[shift] ** 2 - amp[0] ** 2)[:, order], v_long[:, slot], c2)
        delta = _pair_deltas(b, first, r_pair, s_pair, keep_pair, nu_pair, terms)
        steps = jnp.where(x["step_pulse_valid"], delta[:, x["step_rank_pos"]], 0.0)  # by angle
        rows.append(_state_rows(ell_long, steps))
    return jnp.stack(rows, axis=1)  # (D, K + 1, P + 1)


def step_edges(model: Model, x: dict, loc, scale):
    """The threshold states' edges in prior scales (P + 2,), one leg: −∞, the pulses' true
    angles in increasing order, +∞ (padding pulses at +∞)."""
    x = _sensed(model, x)
    a = x["angle"][x["pulse_sample"][x["step_order"]]]
    z = jnp.where(x["step_pulse_valid"], (a - loc) / scale, jnp.inf)
    return jnp.concatenate([jnp.full(1, -jnp.inf, z.dtype), z, jnp.full(1, jnp.inf, z.dtype)])


def step_log_mass(model: Model, x: dict, loc, scale):
    """log prior mass of each threshold state (P + 1,), one leg, for a Normal(loc, scale) threshold:
    the intervals between the pulses' true angles in increasing order (padding: mass 0)."""
    edges = step_edges(model, x, loc, scale)
    lo, hi = edges[:-1], edges[1:]
    # from the nearer tail, so that intervals far out keep their (small) mass in float32
    mass = jnp.where(lo + hi > 0, jax.scipy.special.ndtr(-lo) - jax.scipy.special.ndtr(-hi),
                     jax.scipy.special.ndtr(hi) - jax.scipy.special.ndtr(lo))  # fmt: skip
    return jnp.where(mass > 0, jnp.log(jnp.where(mass > 0, mass, 1.0)), -jnp.inf)


def leg_active_output(model: Model, x: dict, d_index, R: int, K: int = 0, shift=0):
    """M̂_k/I at every sample of one leg at delay ``d_index`` and ``shift``: what the likelihood
    compares (through the accelerometer's response, if the model has one)."""
    return _active_output(model, _sensed(model, x), d_index, R, K, shift)


def _active_output(model: Model, x: dict, d_index, R: int, K: int, shift):
    samples, c = _active_entries(model, x, d_index, R, K, shift)
    return jax.ops.segment_sum(c, samples, num_segments=x["angle"].shape[-1])


def _active_entries(model: Model, x: dict, d_index, R: int, K: int, shift):
    """The sample each (pulse, extended lag) reaches and its M̂, flat (0 where it reaches none)."""
    F = gain_factors(model, x["angle"], x["velocity"], x["stimulation"])
    G = output_factors(model, x["angle"], x["velocity"], x["stimulation"])
    samples = x["touch_sample"][d_index]
    c = _contributions(model, x, R, K, shift, d_index, F, _pulse_q(model, x), x["touch_valid"][d_index], samples, G)
    return samples, c


def _active_windows(model: Model, x: dict, d_index, R: int, K: int, shift, scale):
    """M̂ summed over each likelihood window, and each window's scale: ``scale`` widened by the
    pulses' random gains (:func:`_widened`), with the change of the normalising term (0 without)."""
    samples, c = _active_entries(model, x, d_index, R, K, shift)
    W = x["window_mask"].shape[-1]
    win = x["window"][samples]
    M = jax.ops.segment_sum(c, win, num_segments=W)
    c2 = _pulse_variance(model)
    if c2 is None:
        return M, scale, 0.0
    return (M, *_widened(scale, c2, _square_sums(model, c, win, R + K, W)))


def student_t_cdf(z, nu):
    """CDF of a standard Student-t with ``nu`` degrees of freedom at ``z``."""
    tail = 0.5 * jax.scipy.special.betainc(0.5 * nu, 0.5, nu / (nu + z * z))
    return jnp.where(z < 0, tail, 1.0 - tail)


def leg_window_cdf(model: Model, noise: dict, x: dict, d_index, R: int, K: int = 0, shift=0):
    """The predictive CDF of each likelihood window's measured equivalent acceleration at
    (θ, d, shift): P(E_rep ≤ E | θ) under the Student-t noise model (the LOO-PIT's ingredient).
    With the angle objective, of each compared sample's angle (its one-sample window)."""
    if "reset" in x:
        z = (x["angle"] - free_run_angles(_at_delay(model, x, d_index), x)) / noise["sigma"]
        cdf = jnp.where(x["sample_mask"], student_t_cdf(z, noise["nu"]), 0.0)
        return jax.ops.segment_sum(cdf, x["window"], num_segments=x["window_mask"].shape[-1])
    x = _sensed(model, x)
    E, scale, nu, _ = _all_windows(model, noise, x)
    M, scale, _ = _active_windows(model, x, d_index, R, K, shift, scale)
    return student_t_cdf((E - M) / scale, nu)


def leg_pointwise(model: Model, noise: dict, x: dict, d_index, R: int, n_segments: int, K: int = 0, shift=0):
    """log p(y_segment | θ, d, shift) per PSIS-LOO segment of one leg."""
    if "reset" in x:
        lp = _angle_logpdf(_at_delay(model, x, d_index), noise, x)
        seg = jnp.where(x["sample_mask"], x["window_segment"][x["window"]], n_segments)
        return jax.ops.segment_sum(lp, seg, num_segments=n_segments + 1)[:n_segments]
    x = _sensed(model, x)
    E, scale, nu, norm = _all_windows(model, noise, x)
    M, scale, dnorm = _active_windows(model, x, d_index, R, K, shift, scale)
    lp = jnp.where(x["window_mask"], norm + dnorm + _t_kernel(E - M, nu, scale), 0.0)
    seg = jnp.where(x["window_mask"], x["window_segment"], n_segments)
    return jax.ops.segment_sum(lp, seg, num_segments=n_segments + 1)[:n_segments]
