"""Posterior predictive evaluation of fitted models: J_φ,p with 90 % bands, sign tests, PSIS-LOO.

The classical evaluation (:mod:`quadshank.evaluation._prediction`) scores one identified
model per leg.  Here a model is a posterior, a fit folder written by
``quadshank fit`` (see :mod:`quadshank.inference._fitio`), and every score is computed
per posterior draw, so it comes with its uncertainty.

Prediction error J_φ,p (eq. 12)
    For ``n_draws`` posterior draws (a random subset, fixed seed; the same draw
    indices for every leg of a fit, so the draws stay joint across legs) the
    rollouts of :func:`quadshank.model._model.predict_ahead` are vmapped over draws
    (a :class:`~quadshank.model._model.Model` is a pytree whose leaves, the delay
    included, carry a leading draws axis) and, inside ``predict_ahead``, over
    starts.  Draws go through in chunks of equal size (the last one padded
    with a repeated draw, so one compiled function serves a whole trial) that
    keep the (draws × starts × horizon) rollout array under
    :data:`CHUNK_ELEMENTS`.  ``start_stride`` = k uses the starts
    n = 0, k, 2k, … < N - max(horizons): the same starts for every horizon, so
    horizons stay comparable; k = 1 is eq. (12) exactly, and for one draw the
    result equals :func:`quadshank.evaluation._prediction.prediction_errors`.

Summaries
    Per model, leg, trial and horizon: median and 90 % band (5 % and 95 %
    quantiles) over draws.  Per model, trial and horizon: the same for the
    per-draw mean over legs, i.e. the posterior of the Table V mean.  The
    paper's sign test (section III-E-1) is applied to the posterior-median J
    when at least two models are given.  Trials a fit was fitted on are
    in-sample; the summary records them per fit.

PSIS-LOO
    ``az.loo`` on the per-leg, 1-s-segment log-likelihood stored in each fit
    (legs × segments stacked into one observation axis, padded segments
    dropped), and ``az.compare`` among fits of the same data: same legs,
    trials and likelihood resolution, and identical observed accelerations.
    Fits without such a partner are listed as not compared, with the reason.

:func:`run_posterior_evaluate` writes tables, figures, ``report.md`` and,
last, ``summary.json`` into an output folder, every file atomically.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import time
import warnings
from pathlib import Path
from typing import Any, ClassVar, NamedTuple

import arviz as az
import jax
import jax.numpy as jnp
import numpy as np
import xarray as xr

from ..common._progress import progress_bar
from ..common._results import Result
from ..data._cohort import Cohort, Trial
from ..data._paper import HORIZONS_MS
from ..inference._fitio import (
    FitResult,
    check_fit_files,
    load_fit,
    posterior_models,
    read_summary,
    sampled_vars,
)
from ..inference._summaries import INTERVAL, interval
from ..model._model import Model, measured_angle, predict_ahead, simulate_angles, true_angle
from ._prediction import horizon_samples, prediction_starts, scored

__all__ = [
    "LoadedFit",
    "PosteriorEvaluation",
    "load_fits",
    "check_fit_legs",
    "check_fit_data",
    "posterior_predictions",
    "posterior_prediction_errors",
    "posterior_j",
    "posterior_j_and_stride_errors",
    "stride_error",
    "band_mcse",
    "largest_mcse",
    "AccurateJ",
    "accurate_j",
    "interval",
    "summarise_j",
    "psis_loo",
    "loo_report",
    "figure_window",
    "window_predictions",
    "plan_predictions",
    "CHUNK_ELEMENTS",
    "PARETO_K_BAD",
]

#: Largest (draws × starts × horizon) rollout array computed at once (float32: 64 MiB).
CHUNK_ELEMENTS = 1 << 24
#: Pareto k above which a PSIS-LOO observation's estimate is unreliable.
PARETO_K_BAD = 0.7
#: (start, length) [s] of the prediction figures' window; on shorter trials the start moves earlier.
FIGURE_WINDOW_S = (30.0, 20.0)


@dataclasses.dataclass
class PosteriorEvaluation(Result):
    """What ``quadshank evaluate --fit`` (and ``compare``) found: J over posterior draws, sign
    tests and PSIS-LOO for one or more fits of the same data."""

    KIND: ClassVar[str] = "posterior-evaluation"

    method: str
    J: dict  # model -> trial -> horizon [ms] -> interval of the mean over legs
    J_legs: dict  # model -> leg -> trial -> horizon [ms] -> interval
    sign_tests: list
    loo: dict
    fits: dict  # model -> folder, legs, trials fitted, draws used, banner
    legs: list
    horizons_samples: list
    interval: list
    n_draws: int
    start_stride: int
    seed: int
    evaluation_seconds: float
    residual_findings: dict | None = None
    #: per fit, the structure its residuals still carry (quadshank.evaluation._structure.residual_structure)
    unexplained: dict | None = None
    #: Monte Carlo standard errors [deg] of the band ends (band_mcse): "cohort", "legs", their
    #: largest ("largest_cohort", "largest_legs"), and with a band accuracy asked for, "target",
    #: "met" and "rounds" (accurate_j)
    band_mcse: dict | None = None
    #: the ARX yardstick's J (quadshank.evaluation._blackbox.blackbox_j) on the same starts, and where it
    #: is below a fit's posterior-median J of the mean over legs ("better_than")
    blackbox: dict | None = None


class LoadedFit(NamedTuple):
    """A fit folder in memory; ``label`` (the model's name) names it in every output."""

    label: str
    folder: Path
    idata: Any
    model: Model
    desc: dict
    summary: dict


def load_fits(folders) -> list[LoadedFit]:
    """Load fit folders; a missing or incomplete folder, or one given twice, is an error.  Each
    fit is labelled by its model's name, or, where two fits are of one model (another likelihood,
    other trials), by the model's name and its folder's (``model3@fit-angle``)."""
    fits = []
    for folder in folders:
        idata, model, desc = load_fit(folder)
        summary = read_summary(folder)
        check_fit_files(folder, idata, summary)
        fits.append(LoadedFit(desc["model"], Path(folder), idata, model, desc, summary))
    where: dict[Path, Path] = {}
    for f in fits:
        same = where.setdefault(f.folder.resolve(), f.folder)
        if same is not f.folder:
            raise ValueError(f"fits {same} and {f.folder} are one folder; give each fit once")
    names = [f.label for f in fits]
    labels = [f"{f.label}@{f.folder.resolve().name}" if names.count(f.label) > 1 else f.label for f in fits]
    labels = [f"{label}#{i + 1}" if labels.count(label) > 1 else label for i, label in enumerate(labels)]
    return [f._replace(label=label) for f, label in zip(fits, labels)]


def check_fit_legs(fits: list[LoadedFit], cohort: Cohort) -> None:
    """Refuse data that are not what each fit was fitted to: a leg missing, or (where the fit
    records it) another fingerprint of the fitted legs and trials."""
    for f in fits:
        check_fit_data(f.folder, f.summary, f.desc, cohort)


def check_fit_data(folder, summary: FitResult, desc: dict, cohort: Cohort) -> None:
    """Refuse ``cohort`` unless it holds the legs and trials the fit in ``folder`` was fitted to,
    bit for bit (by the fingerprint the fit records)."""
    source = cohort.attrs.get("source", "the data")
    missing = [leg for leg in desc["legs"] if leg not in cohort.legs]
    if missing:
        raise KeyError(
            f"{source}: lacks leg(s) {', '.join(missing)} of the fit in {folder} ({desc['model']}; "
            f"the data has {', '.join(cohort.legs)})"
        )
    if summary.data_fingerprint is None:
        return
    have = {(t.key, t.trial) for t in cohort.trials}
    lacking = [f"{leg} trial {t}" for leg in desc["legs"] for t in desc["trials"] if (leg, int(t)) not in have]
    if lacking or cohort.fingerprint(desc["legs"], desc["trials"]) != summary.data_fingerprint:
        why = f"it lacks {', '.join(lacking)}" if lacking else "its recordings of the fitted legs and trials differ"
        raise ValueError(
            f"{source}: not the data the fit in {folder} was fitted to ({why}); give the fit's data"
            + (f" ({summary.data})" if summary.data else "")
        )


# ============================================================================ J per draw


@functools.partial(jax.jit, static_argnames=("horizon", "columns"))
def _rollouts(models, angle, velocity, stimulation, starts, horizon, columns):
    """Predicted angles (draws, starts, len(columns)) at the given rollout columns."""
    cols = jnp.asarray(columns)
    return jax.vmap(lambda m: predict_ahead(m, angle, velocity, stimulation, starts, horizon)[:, cols])(models)


@jax.jit
def _plan_rollouts(models, stimulation, angle, velocity):
    """The goniometer's angle of each draw's run through ``stimulation`` from its own true state
    (``angle``, ``velocity``: one per draw)."""
    def one(m, a0, v0):
        run, _, _ = simulate_angles(m, stimulation, a0, v0)
        return measured_angle(m, run)

    return jax.vmap(one)(models, angle, velocity)


@jax.jit
def _true_starts(models, angle0):
    """Each draw's true angle where the goniometer reads ``angle0``."""
    return jax.vmap(lambda m: true_angle(m, angle0))(models)


#: How long [s] a draw's shank is left to swing without stimulation from the gravity vertical to
#: find its rest (:func:`rest_states`): a passive swing decays as exp(-D'·t/2), so 60 s take an
#: offset of tens of degrees to well under 0.01° for any damping above 0.3 /s.
REST_SETTLE_S = 60.0


@functools.partial(jax.jit, static_argnames=("samples",))
def _rest_states(models, samples: int):
    def one(m):
        angle, velocity, _ = simulate_angles(m, jnp.zeros(samples, jnp.float32), jnp.float32(0.0), jnp.float32(0.0))
        return angle[-1], velocity[-1]

    return jax.vmap(one)(models)


def rest_states(models: Model) -> tuple[np.ndarray, np.ndarray]:
    """Each draw's rest: the true angle [deg] and velocity [deg/s] its model comes to after
    :data:`REST_SETTLE_S` without stimulation, released at rest from the gravity vertical.  Angle 0
    where eq. (8) alone acts; elsewhere where a gravity offset, an end of range or a user's passive
    effect balances gravity (a settle run rather than a root of the passive acceleration, so that
    every effect that acts without stimulation counts)."""
    samples = max(2, int(round(REST_SETTLE_S / float(models.sampling_period_s))))
    angle, velocity = _rest_states(models, samples)
    return np.asarray(angle, dtype=float), np.asarray(velocity, dtype=float)


def plan_predictions(models: Model, stimulation, angle0: float | None = 0.0, velocity0: float = 0.0) -> np.ndarray:
    """The angle [deg] a planned stimulation sequence would produce, per draw: array (draws,
    samples), sample 0 being the start state (``angle0`` as the goniometer reads it,
    ``velocity0``; ``angle0`` None: each draw at its own rest, :func:`rest_states`, and
    ``velocity0`` unused); free-run from there, the muscle at rest before the first sample.  These
    are the rollouts of :func:`posterior_predictions` from a start with no pulse before it."""
    stim = jnp.asarray(stimulation, jnp.float32)
    if angle0 is None:
        angle, velocity = rest_states(models)
    else:
        angle = _true_starts(models, jnp.float32(angle0))
        velocity = np.full(_n_draws(models), velocity0)
    out = _plan_rollouts(models, stim, jnp.asarray(angle, jnp.float32), jnp.asarray(velocity, jnp.float32))
    return np.asarray(out, dtype=float)


def _n_draws(models: Model) -> int:
    return int(np.shape(models.delay)[0])


def _prediction_chunks(models: Model, trial: Trial, starts: np.ndarray, horizons):
    """Yield the predictions (chunk, starts, horizons) of consecutive chunks of draws."""
    horizon = max(horizons)
    n = _n_draws(models)
    size = int(np.clip(CHUNK_ELEMENTS // max(1, len(starts) * horizon), 1, n))
    columns = tuple(int(p) - 1 for p in horizons)
    starts = jnp.asarray(starts)
    for i in range(0, n, size):
        idx = np.minimum(np.arange(i, i + size), n - 1)  # the last chunk repeats the last draw
        chunk = jax.tree_util.tree_map(lambda x: x[idx], models)
        pred = _rollouts(chunk, trial.angle_deg, trial.velocity_deg_s, trial.stimulation, starts, horizon, columns)
        yield np.asarray(pred, dtype=float)[: min(size, n - i)]


def posterior_predictions(models: Model, trial: Trial, starts, horizons) -> np.ndarray:
    """Angles predicted p samples after each start, per draw: array (draws, starts, horizons).

    ``models`` has leaves with a leading draws axis (see
    :func:`quadshank.inference._fitio.posterior_models`); ``starts + max(horizons)`` must
    stay inside the trial.
    """
    models.check_period(trial.sampling_period_s, f"{trial.key} trial {trial.trial}")
    return np.concatenate(list(_prediction_chunks(models, trial, np.asarray(starts), horizons)), axis=0)


def figure_window(trial: Trial, window_s: tuple[float, float]) -> tuple[float, int, int]:
    """``(start_s, i0, i1)`` of a figure's window ``(start, length)`` [s] in ``trial``: samples
    i0 … i1 − 1; on a trial too short for it the start moves earlier."""
    dt = trial.sampling_period_s
    start_s = min(window_s[0], max(0.0, trial.n_samples * dt - window_s[1]))
    i0 = int(round(start_s / dt))
    return start_s, i0, min(trial.n_samples, i0 + int(round(window_s[1] / dt)))


def window_predictions(models: Model, trial: Trial, horizons, window: tuple[float, int, int]) -> dict:
    """Per horizon p [samples]: ``(starts, predicted)``, the angles predicted p samples after each
    start whose target falls in the :func:`figure_window` ``window``; predicted is (draws, starts),
    NaN where the run from the start meets an excluded sample (J does not score it, and a figure
    leaves a gap)."""
    _, i0, i1 = window
    out = {}
    for p in horizons:
        starts = np.arange(max(0, i0 - p), i1 - p)
        pred = posterior_predictions(models, trial, starts, (p,))[:, :, 0].astype(float)
        pred[:, ~scored(trial, starts, p)] = np.nan
        out[p] = (starts, pred)
    return out


def posterior_prediction_errors(models: Model, trial: Trial, horizons=None, start_stride: int = 1) -> np.ndarray:
    """J_φ,p [deg] (eq. 12) per draw and horizon [samples]: array (draws, len(horizons)); by default
    the horizons of :data:`quadshank.data.HORIZONS_MS` at the trial's period.  A draw whose
    predictions diverge somewhere (a stiff elasticity far from the data's angles, say) has an
    unbounded error: its J is +inf, so that a band's quantiles still order the draws (a NaN
    would make every quantile NaN)."""
    models.check_period(trial.sampling_period_s, f"{trial.key} trial {trial.trial}")
    if horizons is None:
        horizons = tuple(horizon_samples(trial.sampling_period_s).values())
    starts = prediction_starts(trial, max(horizons), start_stride)
    target = trial.angle_deg[starts[:, None] + np.asarray(horizons)[None, :]]  # (S, H)
    chunks = _prediction_chunks(models, trial, starts, horizons)
    J = np.concatenate([np.sqrt(np.mean((target[None] - pred) ** 2, axis=1)) for pred in chunks])
    return np.where(np.isfinite(J), J, np.inf)


def posterior_j(
    fits: list[LoadedFit],
    cohort: Cohort,
    *,
    horizons_ms=HORIZONS_MS,
    n_draws: int = 200,
    start_stride: int = 1,
    seed: int = 0,
    progress: bool = False,
) -> dict:
    """J per draw: ``J[label][leg][trial_str]`` = array (draws, len(horizons_ms)).

    Every leg of every fit is evaluated on all of that leg's trials in ``cohort``, each horizon
    [ms] as whole samples of the trial's period (:func:`quadshank.evaluation.horizon_samples`).
    """
    return _posterior_j(fits, cohort, horizons_ms, n_draws, start_stride, seed, progress, stride_errors=False)[0]


def posterior_j_and_stride_errors(
    fits: list[LoadedFit],
    cohort: Cohort,
    *,
    horizons_ms=HORIZONS_MS,
    n_draws: int = 200,
    start_stride: int = 1,
    seed: int = 0,
    progress: bool = False,
) -> tuple[dict, dict]:
    """:func:`posterior_j`'s draws, and per leg and trial the standard error [deg] that the start
    stride adds to each draw's J (:func:`stride_error`; zeros at stride 1), array (horizons,),
    shaped as the draws: ``(J, stride_sd)``."""
    return _posterior_j(fits, cohort, horizons_ms, n_draws, start_stride, seed, progress, stride_errors=True)


def _posterior_j(fits, cohort, horizons_ms, n_draws, start_stride, seed, progress, *, stride_errors: bool):
    jobs = [(f, leg, t) for f in fits for leg in f.desc["legs"] for t in cohort.trials_of(leg)]
    out: dict = {}
    sd: dict = {}
    loaded = None
    for f, leg, t in progress_bar(jobs, desc="posterior J", enabled=progress):
        if loaded != (f.label, leg):  # jobs come leg by leg: one leg's draws in memory at a time
            loaded = (f.label, leg)
            models, _ = posterior_models(f.idata, f.model, leg, n_draws, seed)
        horizons = tuple(horizon_samples(t.sampling_period_s, horizons_ms).values())
        errs = posterior_prediction_errors(models, t, horizons, start_stride)
        out.setdefault(f.label, {}).setdefault(leg, {})[str(t.trial)] = errs
        if not stride_errors:
            continue
        # the stride's error, measured on the draw whose J at the longest horizon is the median
        typical = int(np.argsort(errs[:, -1])[len(errs) // 2])
        one = jax.tree_util.tree_map(lambda x: x[typical : typical + 1], models)
        sd.setdefault(f.label, {}).setdefault(leg, {})[str(t.trial)] = stride_error(one, t, horizons, start_stride)
    return out, sd


def stride_error(model: Model, trial: Trial, horizons, stride: int) -> np.ndarray:
    """The standard error [deg] of J computed from every ``stride``-th start, per horizon: the
    standard deviation of J over the ``stride`` offsets o (starts o, o + stride, …) for one
    draw ``model`` (leaves with a draws axis of 1).  Zeros at stride 1, where J uses every start.

    J from one offset (the evaluation uses o = 0) is one of these ``stride`` estimates of the
    J of every start; their spread is the error the stride adds to each draw's J.  It costs
    the rollouts of one draw at every start."""
    if stride <= 1:
        return np.zeros(len(horizons))
    starts = prediction_starts(trial, max(horizons), 1)
    target = trial.angle_deg[starts[:, None] + np.asarray(horizons)[None, :]]  # (S, H)
    sq = (target - posterior_predictions(model, trial, starts, horizons)[0]) ** 2
    offsets = starts % stride
    # over the offsets the starts hold (a stride beyond the trial's length holds one per start)
    per_offset = [np.sqrt(sq[offsets == o].mean(axis=0)) for o in np.unique(offsets)]
    return np.std(per_offset, axis=0, ddof=1) if len(per_offset) > 1 else np.zeros(len(horizons))


def _quantile_mcse(x: np.ndarray, prob: float) -> float:
    """Monte Carlo standard error of the ``prob`` quantile of draws ``x`` in their posterior order
    (arviz's, which accounts for the autocorrelation left among the sorted subset of draws)."""
    if np.ptp(x) == 0:
        return 0.0
    return float(az.mcse(np.asarray(x, np.float64)[None, :], method="quantile", prob=prob))


def band_mcse(draws: dict, stride_sd: dict, horizons_ms=HORIZONS_MS) -> tuple[dict, dict]:
    """Monte Carlo standard errors [deg] of the ends of :func:`summarise_j`'s bands, shaped as they
    are: ``(cohort, legs)``, each end ``{"lo": e, "hi": e}``.

    Each end carries two errors, added in quadrature: the quantile's from the finite number of
    draws (:func:`_quantile_mcse`), and the start stride's (:func:`stride_error`), which moves
    every draw's J alike.  For the cohort's band, the mean over legs, the legs' stride errors
    add as independent errors of a mean.
    """
    keys = [str(h) for h in horizons_ms]

    def ends(x: np.ndarray, stride: float) -> dict:
        return {end: float(np.hypot(_quantile_mcse(x, q), stride)) for end, q in zip(("lo", "hi"), INTERVAL)}

    legs = {
        label: {leg: {tr: {h: ends(v[:, j], stride_sd[label][leg][tr][j]) for j, h in enumerate(keys)}
                      for tr, v in trials.items()}
                for leg, trials in by_leg.items()}
        for label, by_leg in draws.items()
    }
    cohort: dict = {}
    sd = _cohort_stride_sd(stride_sd)
    for label, by_leg in draws.items():
        for tr in sorted({tr for trials in by_leg.values() for tr in trials}, key=int):
            mean = np.mean([trials[tr] for trials in by_leg.values() if tr in trials], axis=0)  # (draws, H)
            cohort.setdefault(label, {})[tr] = {h: ends(mean[:, j], sd[label, tr][j]) for j, h in enumerate(keys)}
    return cohort, legs


def _cohort_stride_sd(stride_sd: dict) -> dict:
    """The stride's error of the mean over legs, per (label, trial): the legs' errors added as
    independent errors of a mean."""
    out = {}
    for label, by_leg in stride_sd.items():
        for tr in {tr for trials in by_leg.values() for tr in trials}:
            have = [trials[tr] for trials in by_leg.values() if tr in trials]
            out[label, tr] = np.sqrt(np.sum(np.square(have), axis=0)) / len(have)
    return out


def largest_mcse(mcse: dict) -> float:
    """The largest band-end error in a :func:`band_mcse` result (either part)."""
    out = 0.0
    stack = [mcse]
    while stack:
        d = stack.pop()
        if set(d) == {"lo", "hi"}:
            out = max(out, d["lo"], d["hi"])
        else:
            stack.extend(d.values())
    return out


@dataclasses.dataclass(frozen=True)
class AccurateJ:
    """J over posterior draws with draws and stride chosen for an accuracy (:func:`accurate_j`)."""

    draws: dict  # as posterior_j's
    stride_sd: dict  # per label, leg, trial: the stride's error of each draw's J, per horizon
    mcse: dict  # {"cohort": ..., "legs": ...}: band_mcse of the result
    n_draws: int
    start_stride: int
    target: float  # [deg], for the cohort's band ends
    met: bool
    rounds: list  # per round: draws, stride, the largest cohort band-end error, seconds


def accurate_j(
    fits: list[LoadedFit],
    cohort: Cohort,
    mcse: float = 0.05,
    *,
    horizons_ms=HORIZONS_MS,
    pilot: tuple[int, int] = (50, 10),
    max_rounds: int = 3,
    seed: int = 0,
    progress: bool = False,
) -> AccurateJ:
    """J bands whose ends carry a Monte Carlo standard error of at most ``mcse`` [deg]
    (:func:`band_mcse`) on the cohort's bands, choosing the number of draws and the start stride.

    A pilot of ``pilot`` = (draws, stride) measures both parts of the error. The quantile's part
    falls as 1/√draws and the stride's grows about as √stride, so the next round takes the
    largest stride, up to the pilot's, that keeps the stride's part within 0.6 of ``mcse`` and
    the draws that bring the quantile's part within 0.8 of it (0.6² + 0.8² = 1), capped at the
    draws the fits hold;
    rounds repeat, from the last round's measurements, until the error is met or ``max_rounds``
    have run.  The per-leg bands' errors are reported, not targeted: each is the error of one
    leg's J, larger than the cohort mean's.
    """
    if not mcse > 0:
        raise ValueError(f"the band accuracy (--band-mcse) must be positive, not {mcse}")
    available = min(f.idata.posterior.sizes["chain"] * f.idata.posterior.sizes["draw"] for f in fits)
    n, k = min(pilot[0], available), max(1, pilot[1])
    rounds = []
    while True:
        t = time.perf_counter()
        draws, sd = posterior_j_and_stride_errors(fits, cohort, horizons_ms=horizons_ms, n_draws=n, start_stride=k,
                                                  seed=seed, progress=progress)
        cohort_mcse, legs_mcse = band_mcse(draws, sd, horizons_ms)
        worst = largest_mcse(cohort_mcse)
        rounds.append({"draws": n, "start_stride": k, "largest_mcse": worst, "seconds": time.perf_counter() - t})
        if worst <= mcse or len(rounds) >= max_rounds:
            break
        # each part's worst over the cohort's band ends, then the draws and stride for the next round
        zero = {label: {leg: {tr: np.zeros_like(v) for tr, v in trials.items()} for leg, trials in by_leg.items()}
                for label, by_leg in sd.items()}
        quantile_part = largest_mcse(band_mcse(draws, zero, horizons_ms)[0])
        stride_part = max(float(np.max(v)) for v in _cohort_stride_sd(sd).values())
        k_next = k if stride_part == 0 else int(np.clip(k * (0.6 * mcse / stride_part) ** 2, 1, k))
        n_next = int(np.clip(np.ceil(n * (quantile_part / (0.8 * mcse)) ** 2), n, available))
        if (n_next, k_next) == (n, k):  # capped: more draws than the fits hold would be needed
            break
        n, k = n_next, k_next
    return AccurateJ(draws, sd, {"cohort": cohort_mcse, "legs": legs_mcse}, n, k, mcse, worst <= mcse, rounds)


def summarise_j(draws: dict, horizons_ms=HORIZONS_MS) -> tuple[dict, dict]:
    """(cohort, per leg) summaries of :func:`posterior_j`'s draws, horizon keys in ms (str).

    ``cohort[label][trial][h]`` summarises the per-draw mean over the legs that
    have that trial; ``legs[label][leg][trial][h]`` each leg's own draws.
    """
    keys = [str(h) for h in horizons_ms]
    legs = {
        label: {
            leg: {tr: {h: interval(v[:, j]) for j, h in enumerate(keys)} for tr, v in trials.items()}
            for leg, trials in by_leg.items()
        }
        for label, by_leg in draws.items()
    }
    cohort: dict = {}
    for label, by_leg in draws.items():
        for tr in sorted({tr for trials in by_leg.values() for tr in trials}, key=int):
            mean = np.mean([trials[tr] for trials in by_leg.values() if tr in trials], axis=0)  # (draws, H)
            cohort.setdefault(label, {})[tr] = {h: interval(mean[:, j]) for j, h in enumerate(keys)}
    return cohort, legs


def posterior_medians(J_legs: dict) -> dict:
    """Posterior-median J shaped as :func:`quadshank.evaluation._prediction.sign_tests` expects (horizon keys int)."""
    return {
        label: {leg: {tr: {int(h): v["median"] for h, v in hv.items()} for tr, hv in trials.items()}
                for leg, trials in by_leg.items()}
        for label, by_leg in J_legs.items()
    }


# ============================================================================ PSIS-LOO


def psis_loo(idata, source: str = "the fit"):
    """``az.loo`` (pointwise) over legs × 1-s segments of a fit, padded segments dropped.

    ``source`` names the fit in the error raised when an unpadded segment's
    log-likelihood is not finite.
    """

    ll = idata.log_likelihood["acceleration_segment"]
    legs = sorted(str(x) for x in ll["leg"].values)
    stacked = ll.sel(leg=legs).stack(observation=("leg", "segment"))
    keep = idata.constant_data["segment_mask"].sel(leg=legs).stack(observation=("leg", "segment")).values.astype(bool)
    stacked = stacked.isel(observation=np.flatnonzero(keep))
    names = [f"{leg}/{seg}" for leg, seg in zip(stacked["leg"].values, stacked["segment"].values)]
    stacked = stacked.drop_vars(["observation", "leg", "segment"]).assign_coords(observation=names)
    if not np.isfinite(stacked.values).all():
        raise ValueError(f"{source}: the log-likelihood is not finite on every unpadded segment")
    data = az.InferenceData(
        posterior=idata.posterior[sampled_vars(idata)],
        log_likelihood=xr.Dataset({"acceleration_segment": stacked}),
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # high Pareto k: reported in the summary instead
        return az.loo(data, pointwise=True, var_name="acceleration_segment")


def _data_key(f: LoadedFit) -> tuple:
    """What must agree for two fits' LOO to be comparable: legs, trials, resolution, observations."""
    acc = f.idata.observed_data["acceleration"].sel(leg=sorted(f.desc["legs"])).values
    digest = hashlib.sha1(np.ascontiguousarray(acc, dtype=np.float64).tobytes()).hexdigest()
    return tuple(sorted(f.desc["legs"])), tuple(sorted(f.desc["trials"])), f.desc.get("resolution"), acc.shape, digest


def loo_report(fits: list[LoadedFit]) -> dict:
    """PSIS-LOO per fit, and ``az.compare`` within each group of fits made on the same data."""

    elpd = {f.label: psis_loo(f.idata, str(f.folder)) for f in fits}
    per_fit = {}
    for label, e in elpd.items():
        k = np.asarray(e.pareto_k)
        per_fit[label] = {
            "elpd_loo": float(e.elpd_loo),
            "se": float(e.se),
            "p_loo": float(e.p_loo),
            "n_observations": int(e.n_data_points),
            "n_draws": int(e.n_samples),
            "pareto_k_max": float(np.max(k)),
            f"pareto_k_over_{PARETO_K_BAD}": int(np.sum(k > PARETO_K_BAD)),
        }
    groups: dict[tuple, list[LoadedFit]] = {}
    for f in fits:
        groups.setdefault(_data_key(f), []).append(f)
    compare, not_compared = [], []
    for (legs, trials, *_), members in groups.items():
        if len(members) < 2:
            if len(fits) > 1:
                not_compared.append({
                    "model": members[0].label,
                    "reason": "no other fit was made on the same data (legs, trials, resolution, observations)",
                })
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # arviz's own use of pandas
            table = az.compare({f.label: elpd[f.label] for f in members}, ic="loo")
        compare.append({
            "legs": list(legs),
            "trials": list(trials),
            "table": {
                str(label): {
                    "rank": int(row["rank"]),
                    "elpd_diff": float(row["elpd_diff"]),
                    "dse": float(row["dse"]),
                    "weight": float(row["weight"]),
                }
                for label, row in table.iterrows()
            },
        })
    return {"fits": per_fit, "compare": compare, "not_compared": not_compared}


# ============================================================================ tables


# ============================================================================ figures


# ============================================================================ the command


