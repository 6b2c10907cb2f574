"""Prediction error J_φ,p (eq. 12), the paper's sign test, and the Table V analogue.

J_φ,p = sqrt( (1/l) Σ_n (φ_{n+p} - φ̂_{n+p|n})² ): from every start n the model
runs ``max(horizons)`` samples ahead once, initialised with the measured
passive state at n and the active part carried over from the run that started
at n-1; the prediction is read at every horizon p.  All horizons use the same
l starts (n = 0 .. N-1-max(horizons)), so they are comparable.  A start whose run meets an
excluded sample (``Trial.exclude``) is left out.

The sign test follows section III-E-1: for each horizon and each pair of
models, the J values of the two models are paired within leg and trial (the
validation trials 2 and 3, 5 legs × 2 trials = 10 pairs in the paper's cohort)
and the number of pairs in which model A beats model B is tested against a
fair coin (two-sided exact binomial test, α = 0.05).
"""

from __future__ import annotations

import dataclasses
import itertools
import warnings
from typing import ClassVar

import numpy as np
from scipy.stats import binomtest

from ..common._arrays import is_whole_number, stretches
from ..common._progress import progress_bar
from ..common._results import Result
from ..data._cohort import Cohort, Trial
from ..data._interchange import DataWarning, check_cohort
from ..data._paper import HORIZONS_MS
from ..model._effects import user_effects
from ..model._model import Model, measured_angle, predict_ahead, simulate_angles, true_angle

__all__ = [
    "prediction_errors", "prediction_starts", "predictions", "evaluate_cohort", "sign_tests", "table_v", "ALPHA",
    "horizon_samples", "figure_trial", "Evaluation", "free_run_error", "free_runs", "free_run_errors",
]  # fmt: skip

ALPHA = 0.05


def horizon_samples(sampling_period_s: float, horizons_ms=HORIZONS_MS) -> dict[int, int]:
    """``{horizon_ms: samples}``: each horizon [ms] as whole samples of ``sampling_period_s``, the
    nearest (at least one).  At the paper's 10 ms: 100, 250, 500, 1000 ms are 10, 25, 50, 100
    samples; at 20 ms, 250 ms is 12 samples (240 ms) and keeps its name."""
    bad = [h for h in horizons_ms if not (isinstance(h, (int, float, np.integer, np.floating)) and np.isfinite(h) and h > 0)]
    if bad or not len(horizons_ms):
        raise ValueError(f"horizons_ms: {bad or 'none'}; a horizon is a positive number of milliseconds")
    return {int(h): max(1, int(round(h / 1000.0 / sampling_period_s))) for h in horizons_ms}


def scored(trial: Trial, starts, horizon: int) -> np.ndarray:
    """True for each start whose run from n to n + ``horizon`` meets no excluded sample
    (``Trial.exclude``): the predictions J scores."""
    starts = np.asarray(starts)
    before = np.concatenate([[0], np.cumsum(trial.exclude, dtype=np.int64)])  # excluded samples before k
    return before[starts + horizon + 1] == before[starts]


def prediction_starts(trial: Trial, horizon: int, stride: int = 1) -> np.ndarray:
    """Starts n = 0, stride, 2·stride, … < N - horizon (all horizons share them), leaving out
    every start whose run from n to n + horizon meets an excluded sample (``Trial.exclude``):
    its initial state or one of its targets would be one."""
    n = trial.n_samples - horizon
    if n <= 0:
        raise ValueError(f"{trial.key} trial {trial.trial}: {trial.n_samples} samples, fewer than the horizon {horizon}")
    starts = np.arange(0, n, stride)
    if trial.exclude.any():
        starts = starts[scored(trial, starts, horizon)]
        if not starts.size:
            raise ValueError(f"{trial.key} trial {trial.trial}: no stretch of {horizon + 1} samples without an "
                             "excluded sample, so no prediction to score")
    return starts


def predictions(model: Model, trial: Trial, horizon: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(starts, predicted) with predicted[i, j-1] the angle predicted j samples after starts[i];
    ``horizon`` [samples] defaults to the longest of :data:`HORIZONS_MS` at the trial's period."""
    model.check_period(trial.sampling_period_s, f"{trial.key} trial {trial.trial}")
    if horizon is None:
        horizon = max(horizon_samples(trial.sampling_period_s).values())
    starts = prediction_starts(trial, horizon)
    pred = predict_ahead(model, trial.angle_deg, trial.velocity_deg_s, trial.stimulation, starts, horizon)
    return starts, np.asarray(pred, dtype=float)


def prediction_errors(model: Model, trial: Trial, horizons=None) -> dict[int, float]:
    """J_φ,p [deg] for each horizon p (samples), eq. (12); by default those of :data:`HORIZONS_MS`
    at the trial's period."""
    check_cohort(Cohort((trial,)))  # a trial built in Python meets the rules a file's does
    if horizons is None:
        horizons = tuple(horizon_samples(trial.sampling_period_s).values())
    bad = [p for p in horizons if not is_whole_number(p) or p < 1]
    if bad or not len(horizons):
        raise ValueError(f"horizons: {bad or 'none'}; a horizon is a whole number of samples, at least 1")
    horizon = max(horizons)
    starts, pred = predictions(model, trial, horizon)
    out = {}
    for p in horizons:
        err = trial.angle_deg[starts + p] - pred[:, p - 1]
        out[p] = float(np.sqrt(np.mean(err**2)))
    lost = [p for p in horizons if not np.isfinite(out[p])]
    if lost:
        first = int(starts[np.flatnonzero(~np.isfinite(pred).all(axis=1))[0]])
        own = user_effects(model.effects)
        at = ", ".join(f"{p * trial.sampling_period_s * 1000:g} ms" for p in lost)
        warnings.warn(f"{model.name} on {trial.key} trial {trial.trial}: its predictions are not finite (J at {at}), "
                      f"first from sample {first}: the identified model is unstable or diverges on this trial"
                      + (f", or an effect ({', '.join(own)}) returns a value that is not finite" if own else "")
                      + "; a mean that includes it is not finite either", DivergedPredictionWarning, stacklevel=2)
    return out


def free_runs(model: Model, trial: Trial) -> list[tuple[int, np.ndarray]]:
    """Free runs of ``model`` over ``trial``: one per stretch of samples not excluded, from the
    stretch's first measured angle and velocity (the active part at rest), driven by the
    trial's stimulation.  Returns ``(start, angle)`` per stretch, the angle as the goniometer
    would read it."""
    model.check_period(trial.sampling_period_s, f"{trial.key} trial {trial.trial}")
    out = []
    for a, b in stretches(~trial.exclude):
        if b - a < 2:
            continue
        a0 = true_angle(model, np.float32(trial.angle_deg[a]))
        angle, _, _ = simulate_angles(model, np.asarray(trial.stimulation[a:b], np.float32), a0,
                                      np.float32(trial.velocity_deg_s[a]))
        out.append((int(a), np.asarray(measured_angle(model, angle), dtype=float)))
    return out


def free_run_error(model: Model, trial: Trial) -> float:
    """RMS [deg] of the free runs' angle (:func:`free_runs`) against the measured angle: how well
    the model reproduces a whole recording from its initial state alone (for a pendulum test,
    the swing from the release).  J judges predictions a fixed horizon ahead instead."""
    runs = free_runs(model, trial)
    if not runs:
        raise ValueError(f"{trial.key} trial {trial.trial}: no two consecutive samples not excluded")
    err = np.concatenate([angle - trial.angle_deg[a : a + angle.size] for a, angle in runs])
    return float(np.sqrt(np.mean(err**2)))


def evaluate_cohort(
    cohort: Cohort, models: dict[str, dict[str, Model]], horizons_ms=HORIZONS_MS, progress: bool = False
) -> dict:
    """J per model, leg, trial and horizon.

    ``models[leg][model_name]`` is the identified model of that leg, at the data's sampling
    period.  Returns ``J[model_name][leg][trial_str][horizon_ms]`` in degrees; each horizon is
    :func:`horizon_samples` of its trial's period.
    """

    J: dict = {}
    if not isinstance(models, dict) or not all(isinstance(v, dict) for v in models.values()):
        raise TypeError("models: give models[leg][model_name], one identified model per leg and name")
    missing = [leg for leg in cohort.legs if leg not in models]
    if missing:
        raise KeyError(f"models has no entry for leg(s) {', '.join(missing)} (it has {', '.join(models) or 'none'}); "
                       "models[leg][model_name] is the model identified on that leg")
    jobs = [(t, name, m) for t in cohort for name, m in models[t.key].items()]
    for t, name, m in progress_bar(jobs, desc="evaluate", enabled=progress):
        hs = horizon_samples(t.sampling_period_s, horizons_ms)
        errs = prediction_errors(m, t, tuple(hs.values()))
        J.setdefault(name, {}).setdefault(t.key, {})[str(t.trial)] = {h: errs[p] for h, p in hs.items()}
    return J


class DivergedPredictionWarning(DataWarning):
    """A model's predictions on a trial are not finite (an unstable identified filter, say)."""


def sign_tests(J: dict, trials=("2", "3"), alpha: float = ALPHA) -> list[dict]:
    """The paper's pairwise sign test between models, per horizon, over legs × trials (numbered as
    ``J``'s keys: ``"2"``; a number is taken as its text)."""
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must lie between 0 and 1, not {alpha}")
    trials = tuple(str(t) for t in trials)
    names = sorted(J)
    out = []
    for a, b in itertools.combinations(names, 2):
        legs = sorted(set(J[a]) & set(J[b]))
        horizons = sorted({h for leg in legs for t in trials if t in J[a][leg] for h in J[a][leg][t]})
        for h in horizons:
            diffs = [
                J[a][leg][t][h] - J[b][leg][t][h]
                for leg in legs
                for t in trials
                if t in J[a][leg] and t in J[b][leg]
            ]
            a_better = sum(d < 0 for d in diffs)
            b_better = sum(d > 0 for d in diffs)
            n = a_better + b_better
            p = binomtest(a_better, n, 0.5).pvalue if n else 1.0
            out.append(
                {
                    "model_a": a,
                    "model_b": b,
                    "horizon_ms": int(h),
                    "trials": list(trials),
                    "n_pairs": n,
                    "a_better": a_better,
                    "b_better": b_better,
                    "p_value": float(p),
                    "significant": bool(p < alpha),
                    "better": (a if a_better > b_better else b) if p < alpha else None,
                }
            )
    return out


def table_v(J: dict) -> dict:
    """Mean and s.d. of J over legs: ``T[trial][model][horizon_ms] = (mean, sd, n_legs)``."""
    T: dict = {}
    for name, by_leg in J.items():
        trials = sorted({t for leg in by_leg.values() for t in leg})
        for t in trials:
            horizons = sorted({h for leg in by_leg.values() if t in leg for h in leg[t]})
            for h in horizons:
                vals = np.array([leg[t][h] for leg in by_leg.values() if t in leg])
                sd = float(np.std(vals, ddof=1)) if vals.size > 1 else float("nan")
                T.setdefault(t, {}).setdefault(name, {})[h] = (float(vals.mean()), sd, int(vals.size))
    return T


def figure_trial(cohort: Cohort, leg: str) -> Trial:
    """The trial a prediction figure of ``leg`` shows: trial 2, as the paper's Figs. 5–6, where the
    leg has one, else the leg's first trial."""
    numbers = [t.trial for t in cohort.trials_of(leg)]
    return cohort.get(leg, 2 if 2 in numbers else numbers[0])


@dataclasses.dataclass
class Evaluation(Result):
    """What ``quadshank evaluate`` found with point estimates: J_φ,p (eq. 12) per model, trial
    and horizon (mean and s.d. over legs, and per leg) and the sign tests between models."""

    KIND: ClassVar[str] = "evaluation"

    J: dict  # model -> trial -> horizon [ms] -> mean over legs [deg]
    J_sd: dict  # model -> trial -> horizon [ms] -> s.d. over legs [deg]
    J_per_leg: dict  # model -> leg -> trial -> horizon [ms] -> J [deg]
    sign_tests: list
    legs: list
    horizons_samples: list
    evaluation_seconds: float
    free_run: dict = dataclasses.field(default_factory=dict)  # model -> leg -> trial -> [deg], pendulum tests
    blackbox: dict | None = None  # the ARX yardstick's J (evaluation._blackbox.blackbox_j) and where it is lower


def free_run_errors(cohort: Cohort, models: dict[str, dict[str, Model]]) -> dict:
    """:func:`free_run_error` of every model on every trial without pulses (a pendulum test: the
    swing from its release), ``{model: {leg: {trial: deg}}}``; trials with pulses are judged by J
    alone (a free run through minutes of twitches measures the drift, not the model)."""
    out: dict = {}
    for t in cohort:
        if np.any(t.stimulation > 0):
            continue
        for name, m in models[t.key].items():
            out.setdefault(name, {}).setdefault(t.key, {})[str(t.trial)] = free_run_error(m, t)
    return out
