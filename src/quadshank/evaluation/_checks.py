"""Predictive checks of a screened model: LOO-PIT of every likelihood window and the pointwise ELPD in time."""

from __future__ import annotations

import functools
import warnings

import arviz as az
import jax
import jax.numpy as jnp
import numpy as np

from ..data._cohort import Cohort
from ..inference._draws import over_draws
from ..inference._screen import LaplaceFit, leg_draw_models
from ..model._likelihood import leg_window_cdf, segment_samples
from ..model._model import Model


def loo_pit(fit: LaplaceFit, leg: str, n_draws: int = 100) -> np.ndarray:
    """LOO-PIT of every likelihood window of ``leg`` (twitch windows or samples) under the screen's posterior.

    For each draw s (Laplace draws resampled towards the posterior) the predictive
    CDF of the window's measured equivalent acceleration is exact (Student-t); the
    draws are weighted by their Pareto-smoothed leave-one-segment-out weights
    ∝ 1/p(y_segment | θ_s), so each PIT leaves its own 1-s segment out.
    """

    i = fit.legs.index(leg)
    idx = fit.resampled[i, :n_draws]
    x = {k: v[i] for k, v in fit.data.leg_arrays().items()}
    cdf = np.asarray(_window_cdfs(
        leg_draw_models(fit, leg, n_draws), jnp.asarray(fit.delays[i, idx], jnp.int32),
        jnp.asarray(fit.shifts[i, idx], jnp.int32), jnp.asarray(fit.draws[i, idx, -2:], jnp.float32), x,
        R=fit.data.response_length, K=fit.data.max_shift,
    ))  # (draws, windows)
    valid = fit.data.segment_mask[i]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a high Pareto k is a property of the segment, not an error here
        lw, _ = az.psislw(-fit.pointwise[i, idx][:, valid].T)  # (segments, draws), normalised
    weights = np.zeros((valid.size, idx.size))
    weights[valid] = np.exp(lw)
    keep = fit.data.window_mask[i]
    seg = fit.data.window_segment[i][keep]
    return np.sum(weights[seg].T * cdf[:, keep], axis=0)


@functools.partial(jax.jit, static_argnames=("R", "K"))
def _window_cdfs(models: Model, delays, shifts, log_noise, x: dict, R: int, K: int):
    """:func:`quadshank.model._likelihood.leg_window_cdf` per draw (leaves, delays, shifts and
    (log σ, log ν) with a leading draw axis): compiled once per model structure and data shape."""

    def one(m, d, shift, ln):
        return leg_window_cdf(m, {"sigma": jnp.exp(ln[0]), "nu": jnp.exp(ln[1])}, x, d, R, K, shift)

    return over_draws(one, models, delays, shifts, log_noise)


def elpd_in_time(fit: LaplaceFit, cohort: Cohort, leg: str) -> list[dict]:
    """The pointwise PSIS-LOO ELPD of ``leg``'s 1-s segments, each located in its trial:
    a list of {trial, start_s, elpd}, in the likelihood's segment order."""

    i = fit.legs.index(leg)
    rows = []
    for t in cohort.trials_of(leg):
        if t.trial in fit.data.trials:
            seg = segment_samples(t.sampling_period_s)
            n_seg = -(-t.n_samples // seg)
            rows += [{"trial": t.trial, "start_s": k * seg * t.sampling_period_s} for k in range(n_seg)]
    for r, e in zip(rows, fit.elpd_i[i]):
        r["elpd"] = float(e)
    return [r for r in rows if np.isfinite(r["elpd"])]


def worst_seconds_sentence(leg: str, rows: list[dict], n: int = 3) -> str:
    """Where ``leg``'s worst-predicted seconds are, against the median second, in words."""
    med = float(np.median([r["elpd"] for r in rows]))
    worst = sorted(rows, key=lambda r: r["elpd"])[:n]
    where = ", ".join(f"trial {r['trial']} at {r['start_s']:.0f}–{r['start_s'] + 1:.0f} s (ELPD {r['elpd']:.0f})" for r in worst)
    return f"{leg}: the worst-predicted seconds are {where}, against {med:.0f} for the median second."
