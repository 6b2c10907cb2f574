"""A black-box yardstick: a linear ARX model of the angle, scored by J_φ,p beside the physical models.

What the data can predict, with no physics in it: the angle from its own past and the
stimulation's,

    φ[n] = Σ_{i=1..na} a_i φ[n−i] + Σ_{j=1..nb} b_j u[n−j] + c,

fitted by least squares (numpy's ``lstsq``) on the identification trial, its orders (na output
lags, an input memory of nb samples) chosen by validation: fitted on the trial's first
:data:`TRAIN_SHARE`, each candidate is scored by its mean J over the horizons on the rest, and
the best is fitted again on the whole trial.  It predicts p samples ahead from each start n as
the physical models do (:func:`quadshank.evaluation.prediction_starts`, the same starts): from
the measured angles up to n (the first sample repeated before the trial, the angle at n in
place of a lag that meets an excluded sample) and the stimulation, which is known ahead,
feeding its own predictions back.

Where the black box predicts better than a physical model at some horizon, the physical model
misses something the data hold at that horizon.  Where it does not, that is no proof that
nothing is missing: a linear ARX cannot represent what the physical models' nonlinearities do.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..data._cohort import Cohort, Trial
from ..data._paper import HORIZONS_MS
from ._prediction import horizon_samples, prediction_starts

__all__ = ["ARX", "fit_arx", "arx_errors", "blackbox_j", "better_than", "OUTPUT_LAGS", "INPUT_MEMORY_MS", "TRAIN_SHARE"]

#: Candidate numbers of output lags.
OUTPUT_LAGS = (2, 4, 6)
#: Candidate input memories [ms], as whole samples of the trial's period.
INPUT_MEMORY_MS = (100, 250, 500, 1000)
#: Share of the identification trial the candidates are fitted on; the rest validates them.
TRAIN_SHARE = 0.75
#: Starts of the validation, one in this many (the choice needs no more).
VALIDATION_STRIDE = 5


@dataclasses.dataclass(frozen=True)
class ARX:
    """A fitted ARX model: ``coef`` = (a_1 … a_na, b_1 … b_nb, c)."""

    na: int
    nb: int
    coef: np.ndarray
    #: the mean J [deg] over the horizons on the validation part, for each candidate (na, nb)
    validation: dict

    def predict(self, trial: Trial, starts: np.ndarray, horizons) -> np.ndarray:
        """Angles [deg] predicted ``horizons`` samples after each start: array (starts, horizons)."""
        return _predict(self.coef, self.na, self.nb, trial.angle_deg, trial.stimulation, np.asarray(starts), horizons,
                        trial.exclude)


def _lagged(x: np.ndarray, lags: int, first: int = 1) -> np.ndarray:
    """(N, lags): column j holds x[n − first − j], the first value repeated before the start."""
    pad = np.concatenate([np.full(lags + first, x[0]), x])
    n = len(x)
    return np.stack([pad[lags - j : lags - j + n] for j in range(lags)], axis=1)


def _design(angle: np.ndarray, stim: np.ndarray, na: int, nb: int) -> np.ndarray:
    return np.concatenate([_lagged(angle, na), _lagged(stim, nb), np.ones((len(angle), 1))], axis=1)


def _usable_rows(trial: Trial, lo: int, hi: int, lag: int) -> np.ndarray:
    """Rows n in [lo, hi) whose target and lags lie inside the trial and meet no excluded sample."""
    rows = np.arange(max(lo, lag), hi)
    if trial.exclude.any():
        before = np.concatenate([[0], np.cumsum(trial.exclude, dtype=np.int64)])
        rows = rows[before[rows + 1] == before[rows - lag]]
    return rows


def _fit(trial: Trial, na: int, nb: int, lo: int, hi: int) -> np.ndarray:
    X = _design(trial.angle_deg, trial.stimulation, na, nb)
    rows = _usable_rows(trial, lo, hi, max(na, nb))
    coef, *_ = np.linalg.lstsq(X[rows], trial.angle_deg[rows], rcond=None)
    return coef


def _predict(coef, na: int, nb: int, angle, stim, starts: np.ndarray, horizons, excluded=None) -> np.ndarray:
    a, b, c = coef[:na], coef[na : na + nb], coef[-1]
    history = _lagged(angle, na, first=0)[starts]  # (S, na): φ[n], φ[n−1], …
    if excluded is not None and excluded.any():  # a lag in an excluded stretch holds the start's angle
        held = _lagged(excluded.astype(float), na, first=0)[starts] > 0
        history = np.where(held, history[:, :1], history)
    inputs = _lagged(stim, nb, first=0)  # row m: u[m], u[m−1], …
    wanted = {int(p): i for i, p in enumerate(horizons)}
    out = np.empty((len(starts), len(wanted)))
    for step in range(1, max(wanted) + 1):
        nxt = history @ a + inputs[starts + step - 1] @ b + c
        history = np.concatenate([nxt[:, None], history[:, :-1]], axis=1)
        if step in wanted:
            out[:, wanted[step]] = nxt
    return out


def _errors(pred: np.ndarray, trial: Trial, starts: np.ndarray, horizons) -> np.ndarray:
    target = trial.angle_deg[starts[:, None] + np.asarray(horizons)[None, :]]
    return np.sqrt(np.mean((target - pred) ** 2, axis=0))


def fit_arx(trial: Trial, horizons_ms=HORIZONS_MS) -> ARX:
    """The ARX model of ``trial``, orders chosen by validation (see the module's docstring)."""
    horizons = tuple(horizon_samples(trial.sampling_period_s, horizons_ms).values())
    split = int(TRAIN_SHARE * trial.n_samples)
    held = _held_out(trial, split, max(horizons))
    scores = {}
    for na in OUTPUT_LAGS:
        for memory in INPUT_MEMORY_MS:
            nb = max(1, round(memory / 1000.0 / trial.sampling_period_s))
            coef = _fit(trial, na, nb, 0, split)
            pred = _predict(coef, na, nb, trial.angle_deg, trial.stimulation, held, horizons, trial.exclude)
            scores[na, nb] = float(np.mean(_errors(pred, trial, held, horizons)))
    na, nb = min(scores, key=scores.get)
    return ARX(na, nb, _fit(trial, na, nb, 0, trial.n_samples), {f"{k[0]},{k[1]}": v for k, v in scores.items()})


def _held_out(trial: Trial, split: int, horizon: int) -> np.ndarray:
    starts = prediction_starts(trial, horizon, VALIDATION_STRIDE)
    held = starts[starts >= split]
    if not held.size:
        raise ValueError(f"{trial.key} trial {trial.trial}: too short to validate a black box "
                         f"({trial.n_samples} samples; its last {1 - TRAIN_SHARE:.0%} must hold a {horizon}-sample run)")
    return held


def arx_errors(arx: ARX, trial: Trial, horizons, start_stride: int = 1) -> np.ndarray:
    """J_φ,p [deg] of ``arx`` on ``trial`` per horizon [samples], from the starts the physical
    models use (:func:`quadshank.evaluation.prediction_starts`)."""
    starts = prediction_starts(trial, max(horizons), start_stride)
    return _errors(arx.predict(trial, starts, horizons), trial, starts, horizons)


def blackbox_j(cohort: Cohort, train_trials: dict, horizons_ms=HORIZONS_MS, start_stride: int = 1) -> dict:
    """The ARX yardstick on every leg and trial of ``cohort``, each leg's model fitted on its trial
    ``train_trials[leg]``: ``{"J_per_leg": {leg: {trial: {h_ms: J}}}, "J": {trial: {h_ms: mean over
    legs}}, "orders": {leg: {"output_lags", "input_lags", "trained_on"}}}``."""
    per_leg: dict = {}
    orders: dict = {}
    for leg in cohort.legs:
        arx = fit_arx(cohort.get(leg, train_trials[leg]), horizons_ms)
        orders[leg] = {"output_lags": arx.na, "input_lags": arx.nb, "trained_on": int(train_trials[leg])}
        for t in cohort.trials_of(leg):
            hs = horizon_samples(t.sampling_period_s, horizons_ms)
            errs = arx_errors(arx, t, tuple(hs.values()), start_stride)
            per_leg.setdefault(leg, {})[str(t.trial)] = {str(h): float(e) for h, e in zip(hs, errs)}
    mean: dict = {}
    for tr in sorted({tr for trials in per_leg.values() for tr in trials}, key=int):
        have = [trials[tr] for trials in per_leg.values() if tr in trials]
        mean[tr] = {h: float(np.mean([x[h] for x in have])) for h in have[0]}
    return {"J": mean, "J_per_leg": per_leg, "orders": orders}


def better_than(blackbox: dict, physical: dict) -> list[dict]:
    """Where the black box's J (mean over legs) is below a physical model's: ``physical`` is
    ``{model: {trial: {h_ms: J}}}``; one row per model and trial, with the horizons [ms]."""
    rows = []
    for model, trials in physical.items():
        for tr, hv in trials.items():
            if tr not in blackbox["J"]:
                continue
            lower = [h for h, v in hv.items() if h in blackbox["J"][tr] and blackbox["J"][tr][h] < v]
            if lower:
                rows.append({"model": model, "trial": tr, "horizons_ms": sorted(lower, key=int)})
    return rows
