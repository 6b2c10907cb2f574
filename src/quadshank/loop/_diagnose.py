"""Which effect is missing: rank one-effect extensions of a model by the evidence.

For a model and a dataset, every candidate effect (each registered effect
with ``candidate = True`` that the model lacks; an effect that generalises one
in the model takes its place) is added in turn, and the extension is compared
with the model on the same data by

- ΔELPD: PSIS-LOO over the likelihood's 1-s segments, paired segment by
  segment, with its standard error (the screen of :mod:`quadshank.inference._screen`);
- ΔJ_φ,p: the k-step-ahead angle error (eq. 12) at 500 and 1000 ms on the
  evaluation trials, as bands over the posterior draws of each model;
- the residual signature: the trend of the model's one-step residual over
  the feature where the effect's absence shows (its ``signature``: knee
  angle, velocity, pulse count, preceding interpulse interval, ...).

An effect *clears the bar* when its ΔELPD exceeds ``ELPD_SE_BAR`` standard
errors and it lowers J at 500 and 1000 ms beyond the bands (the extension's
upper 90 % limit below the model's lower one); an effect on what the
accelerometer reads alone (``predicts_angle = False``: a skin-motion
resonance) cannot change an angle prediction, and its bar is ΔELPD alone.
The verdict is the highest-
ranked effect that clears the bar, or ``none``: a misfit that some effect
absorbs a little of (ΔELPD of a few units, within noise on J) is not called a
missing effect.

The ranking screens (per-leg MAP and Laplace draws); the leaders that clear
the bar are then confirmed with hierarchical NUTS (:func:`confirm_leaders`):
refitted with a saved fit's settings and judged against the same bar by
PSIS-LOO and J bands over posterior draws.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from ..data._cohort import Cohort
from ..model._effects import registered_effects
from ..inference._fit import build_model
from ..common._io import write_json
from ..model._likelihood import leg_active_output, leg_window_cdf
from ..model._model import Model, equivalent_acceleration
from ..evaluation._posterior import interval, posterior_prediction_errors
from ..common._progress import progress_bar
from ..inference._screen import LaplaceFit, delta_elpd, laplace_fit, leg_draw_models, paired_difference

__all__ = ["candidates", "rank_effects", "ELPD_SE_BAR", "J_HORIZONS_MS", "leg_residuals", "fit_residuals", "residual_figures"]

#: ΔELPD must exceed this many standard errors.
ELPD_SE_BAR = 2.0
#: Horizons [ms] at which the extension must lower J beyond the bands.
J_HORIZONS_MS = (500, 1000)
#: Posterior draws, and the stride between prediction starts, of the J bands behind the bar.
J_DRAWS, J_START_STRIDE = 40, 5


def candidates(model: Model) -> list[str]:
    """Registered candidate effects that one-effect extensions of ``model`` can add."""
    have = {e.name for e in model.effects}
    replaced = {r for e in model.effects for r in e.replaces}  # a generalisation is in the model
    out = []
    for name, cls in sorted(registered_effects().items()):
        if not cls.candidate or name in have or name in replaced:
            continue
        if cls.kind == "delay" and model.delay_effect is not None:
            continue
        out.append(name)
    return out


def _trials_of(cohort: Cohort, legs) -> tuple[int, ...]:
    """Every trial number that some leg of ``legs`` has in ``cohort``."""
    return tuple(sorted({t.trial for leg in legs for t in cohort.trials_of(leg)}))


def _extend(model: Model, name: str) -> Model:
    return model.add(name, name=f"{model.name}+{name}")


def j_draws(fit: LaplaceFit, cohort: Cohort, trials, *, n_draws: int, start_stride: int) -> np.ndarray:
    """J_φ,p [deg] per draw at J_HORIZONS_MS, averaged over legs and ``trials``: (draws, horizons)."""
    return _mean_j(lambda leg: leg_draw_models(fit, leg, n_draws), fit.legs, fit.model, cohort, trials, start_stride)


def nuts_j_draws(fit, cohort: Cohort, trials, *, n_draws: int, start_stride: int, seed: int = 0) -> np.ndarray:
    """:func:`j_draws` for a saved NUTS fit (a :class:`quadshank.evaluation._posterior.LoadedFit`)."""
    from ..inference._fitio import posterior_models

    def models(leg):
        return posterior_models(fit.idata, fit.model, leg, n_draws, seed)[0]

    return _mean_j(models, fit.desc["legs"], fit.model, cohort, trials, start_stride)


def _mean_j(leg_models, legs, model: Model, cohort: Cohort, trials, start_stride: int) -> np.ndarray:
    """J per draw at J_HORIZONS_MS of the draws ``leg_models(leg)``, averaged over ``legs`` and ``trials``."""
    horizons = tuple(int(round(h / 1000 / model.sampling_period_s)) for h in J_HORIZONS_MS)
    per = []
    for leg in legs:
        models = leg_models(leg)
        for t in cohort.trials_of(leg):
            if t.trial in trials:
                per.append(posterior_prediction_errors(models, t, horizons, start_stride))
    if not per:
        raise KeyError(f"no evaluation trial {sorted(trials)} for legs {list(legs)}")
    return np.mean(per, axis=0)


def leg_residuals(fit: LaplaceFit, leg: str) -> dict[str, np.ndarray]:
    """One-step residual of the equivalent acceleration at the screen's mode of ``leg`` (its modal d).

    Returns per-sample arrays over the identification trials (with the likelihood's
    gaps, masked): residual, angle, velocity, stimulation, sample_mask, trial_start.
    """
    i = fit.legs.index(leg)
    values = {k: v for k, v in fit.values(leg).items() if k not in ("sigma", "nu")}
    d = int(np.argmax(fit.delay_posterior[i]))
    K = fit.data.max_shift
    shift = int(np.bincount(fit.shifts[i], minlength=K + 1).argmax()) if K else 0
    return point_residuals(fit.model, fit.data, i, values, d, shift)


def fit_residuals(idata, model: Model, data, leg: str) -> dict[str, np.ndarray]:
    """:func:`leg_residuals` for a saved (NUTS) fit: at the posterior medians of ``leg`` and its modal d and shift."""
    post = idata.posterior
    i = list(post["leg"].values).index(leg)
    flat = lambda name: np.asarray(post[name]).reshape(-1, *post[name].shape[2:])[:, i]  # noqa: E731
    values = {p.name: np.median(flat(p.name), axis=0) for e in model.effects for p in e.declared_params()}
    d = int(np.bincount(flat("delay").astype(int)).argmax())
    shift = int(np.bincount(flat("delay_shift").astype(int)).argmax()) if "delay_shift" in post else 0
    return point_residuals(model, data, data.legs.index(leg), values, d, shift)


def point_residuals(model: Model, data, i: int, values: dict, d: int, shift: int) -> dict[str, np.ndarray]:
    """One-step residual of leg ``i`` of ``data`` (a LikelihoodData) for one parameter point."""
    x = {k: jnp.asarray(v[i]) for k, v in data.leg_arrays().items()}
    K = data.max_shift
    model = model.with_params({k: jnp.asarray(v, jnp.float32) for k, v in values.items()}, delay=d)
    if K:
        model = model.with_delay_shift(shift)
    M = np.asarray(leg_active_output(model, x, d, data.response_length, K, shift))
    e = np.asarray(equivalent_acceleration(model, x["angle"], x["velocity"], x["acceleration"], mask=x["sample_mask"]))
    mask = np.asarray(data.sample_mask[i])
    starts = np.flatnonzero(mask & ~np.concatenate([[False], mask[:-1]]))  # first sample of each trial
    trial_start = starts[np.clip(np.searchsorted(starts, np.arange(mask.size), side="right") - 1, 0, None)]
    return {
        "residual": np.where(mask, e - M, np.nan),
        "angle": np.asarray(data.angle[i], float),
        "velocity": np.asarray(data.velocity[i], float),
        "stimulation": np.asarray(data.stimulation[i], float),
        "sample_mask": mask,
        "trial_start": trial_start,
    }


@dataclasses.dataclass
class Ranking:
    """The result of :func:`rank_effects`."""

    base: LaplaceFit
    fits: dict  # effect -> LaplaceFit of the extension
    rows: list  # best first, JSON-able
    verdict: str
    J_base: dict  # horizon_ms -> interval
    #: candidates that could not be screened: effect -> why (the ranking goes on without them)
    failed: dict = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "model": self.base.model.name,
            "legs": list(self.base.legs),
            "elpd": {"value": self.base.elpd, "se": self.base.elpd_se},
            "J_ms": self.J_base,
            "ranking": self.rows,
            "failed": [{"effect": k, "error": v} for k, v in self.failed.items()],
            "verdict": self.verdict,
            "bar": {"elpd_se": ELPD_SE_BAR, "J_horizons_ms": list(J_HORIZONS_MS)},
        }


def rank_effects(
    cohort: Cohort,
    model: Model | str,
    *,
    trials=(1,),
    eval_trials=None,
    legs=None,
    effects=None,
    n_draws: int = 200,
    n_j_draws: int = J_DRAWS,
    start_stride: int = J_START_STRIDE,
    seed: int = 0,
    n_starts: int = 3,
    base: LaplaceFit | None = None,
    progress: bool = False,
) -> Ranking:
    """Screen every one-effect extension of ``model``; returns a :class:`Ranking`.

    ``eval_trials``: where J is measured (default: every trial of the legs in
    the cohort, the identification trials included: the loop asks where the
    model fails on the measurements it has).  ``n_starts``: prior draws tried, besides the
    prior median, for the parameters an extension adds (:func:`quadshank.inference._screen.laplace_fit`).
    """
    model = build_model(model) if isinstance(model, str) else model
    legs = tuple(legs) if legs is not None else cohort.legs
    if eval_trials is None:
        eval_trials = _trials_of(cohort, legs)
    known = registered_effects()
    if effects is None:
        effects = candidates(model)
    else:
        unknown = [e for e in effects if e not in known]
        if unknown:
            raise KeyError(f"unknown effect(s) {', '.join(map(repr, unknown))}; known effects: {', '.join(sorted(known))}")
        have = {e.name for e in model.effects}
        offered = set(candidates(model)) | {e for e in effects if not known[e].candidate and e not in have}
        effects = [e for e in effects if e in offered]  # not those the model has (a later round of discover)

    kw = dict(n_draws=n_draws, seed=seed, n_starts=n_starts)
    if base is None:
        base = laplace_fit(cohort, model, trials, legs, **kw)
    J0 = j_draws(base, cohort, eval_trials, n_draws=n_j_draws, start_stride=start_stride)
    fits, rows, failed = {}, [], {}
    for name in progress_bar(effects, desc="screening effects", enabled=progress):
        try:
            ext = laplace_fit(cohort, _extend(model, name), trials, legs, start=base, **kw)
            d, se = delta_elpd(base, ext)
            J1 = j_draws(ext, cohort, eval_trials, n_draws=n_j_draws, start_stride=start_stride)
        except Exception as err:  # noqa: BLE001 - one candidate (a user's effect, say) must not end the screen
            failed[name] = f"{type(err).__name__}: {err}"
            warnings.warn(f"the screen of {model.name} + {name} failed and is left out of the ranking: {failed[name]}",
                          RuntimeWarning, stacklevel=2)
            continue
        fits[name] = ext
        row = {
            "effect": name,
            **_bar(d, se, J0, J1, known[name].predicts_angle),
            "pareto_k_max": float(np.nanmax(ext.pareto_k)),
            # how well the Laplace Gaussian stands for the posterior (n_draws: exactly)
            "importance_ess_min": float(np.min(ext.weights_ess)),
            "signature": known[name].signature,
        }
        row["parameters"] = {
            leg: {p.name: np.asarray(ext.values(leg)[p.name]).round(6).tolist() for e in ext.model.effects if e.name == name for p in e.declared_params()}
            for leg in ext.legs
        }
        rows.append(row)
    rows.sort(key=lambda r: (-r["clears_bar"], -r["delta_elpd"]))
    verdict = next((r["effect"] for r in rows if r["clears_bar"]), "none")
    J_base = {f"{h}": interval(J0[:, j]) for j, h in enumerate(J_HORIZONS_MS)}
    return Ranking(base=base, fits=fits, rows=rows, verdict=verdict, J_base=J_base, failed=failed)


def _bar(d: float, se: float, J0: np.ndarray, J1: np.ndarray, predicts_angle: bool) -> dict:
    """The evidence for one extension against its model, and whether it clears the bar (module docs):
    ΔELPD ± SE, J at J_HORIZONS_MS before and after (from per-draw J, (draws, horizons))."""
    out = {"delta_elpd": d, "delta_elpd_se": se}
    lowered = []
    for j, h in enumerate(J_HORIZONS_MS):
        b, x = interval(J0[:, j]), interval(J1[:, j])
        out[f"J_{h}ms"] = {"before": b, "after": x, "change": x["median"] - b["median"]}
        lowered.append(x["hi"] < b["lo"])
    out["J_lowered_beyond_bands"] = bool(all(lowered))
    out["predicts_angle"] = bool(predicts_angle)
    out["clears_bar"] = bool(d > ELPD_SE_BAR * se and (all(lowered) or not predicts_angle))
    return out


def verdict_sentence(ranking: Ranking) -> str:
    """The verdict in words, with the numbers behind it."""
    if ranking.verdict == "none":
        best = ranking.rows[0] if ranking.rows else None
        if best is None:
            return "No candidate effect was screened."
        return (
            f"Nothing is missing that the candidates describe: the best, {best['effect']}, changes ELPD by "
            f"{best['delta_elpd']:.1f} ± {best['delta_elpd_se']:.1f} and J at 1 s from "
            f"{best['J_1000ms']['before']['median']:.2f}° to {best['J_1000ms']['after']['median']:.2f}°, "
            f"short of the bar (ΔELPD > {ELPD_SE_BAR:g} SE and J lowered beyond the 90 % bands at 500 and 1000 ms)."
        )
    r = next(r for r in ranking.rows if r["effect"] == ranking.verdict)
    j5, j10 = r["J_500ms"], r["J_1000ms"]
    if not r.get("predicts_angle", True):
        return (
            f"Adding {r['effect']} improves ELPD by {r['delta_elpd']:.0f} ± {r['delta_elpd_se']:.0f}; it changes what the "
            f"accelerometer reads, not the angle, so J at 1 s stays near {j10['before']['median']:.2f}° "
            f"({j10['after']['median']:.2f}° with it)."
        )
    return (
        f"Adding {r['effect']} improves ELPD by {r['delta_elpd']:.0f} ± {r['delta_elpd_se']:.0f} and lowers J at 0.5 s "
        f"from {j5['before']['median']:.2f}° [{j5['before']['lo']:.2f}, {j5['before']['hi']:.2f}] to "
        f"{j5['after']['median']:.2f}° [{j5['after']['lo']:.2f}, {j5['after']['hi']:.2f}] and at 1 s from "
        f"{j10['before']['median']:.2f}° to {j10['after']['median']:.2f}°."
    )


# ============================================================================ NUTS confirmation


def confirm_with_nuts(
    cohort: Cohort,
    base,
    effect: str,
    out,
    *,
    eval_trials=None,
    n_j_draws: int = J_DRAWS,
    start_stride: int = J_START_STRIDE,
    J_base: np.ndarray | None = None,
    progress: bool = False,
) -> dict:
    """Confirm a screened extension with hierarchical NUTS.

    Fits the model of ``base`` (a saved NUTS fit: its folder, or the
    :class:`quadshank.evaluation._posterior.LoadedFit`) plus ``effect`` to the same data, legs and
    trials with the same settings (``out``, a fit folder), and measures the
    evidence as the screen does: ΔELPD by PSIS-LOO over the same 1-s segments,
    paired, and J at J_HORIZONS_MS as bands over posterior draws, against the
    same bar.  ``J_base``: the base fit's J draws, if already computed
    (:func:`nuts_j_draws`).  Returns the JSON-able evidence, with the fit's
    folder, model, diagnostics and failure banner (a fit that fails its checks
    is reported, not hidden).
    """
    from pathlib import Path

    from ..inference._fit import FitSettings
    from ..commands._pipeline import run_fit
    from ..evaluation._posterior import LoadedFit, load_fits, psis_loo

    if not isinstance(base, LoadedFit):
        (base,) = load_fits([base])
    desc = base.desc
    settings = FitSettings(**{**desc["settings"], "trials": tuple(desc["trials"])})
    trials = tuple(eval_trials) if eval_trials is not None else _trials_of(cohort, desc["legs"])
    base_name, *adds = desc["model"].split("+")
    s = run_fit(cohort, out, base_name, [*adds, effect], settings, legs=desc["legs"], progress=progress,
                data_source=base.summary.get("data"))
    (ext,) = load_fits([out])
    loo_a, loo_b = psis_loo(base.idata, str(base.folder)), psis_loo(ext.idata, str(ext.folder))
    if list(loo_a.loo_i["observation"].values) != list(loo_b.loo_i["observation"].values):
        raise ValueError(f"{base.folder} and {out}: the fits' PSIS-LOO segments differ; they are not of the same data")
    d, se = paired_difference(loo_a.loo_i.values, loo_b.loo_i.values)
    if J_base is None:
        J_base = nuts_j_draws(base, cohort, trials, n_draws=n_j_draws, start_stride=start_stride)
    J_ext = nuts_j_draws(ext, cohort, trials, n_draws=n_j_draws, start_stride=start_stride)
    return {
        "effect": effect,
        "model": s["model"],
        "folder": str(Path(out)),
        **_bar(d, se, J_base, J_ext, registered_effects()[effect].predicts_angle),
        "pareto_k_max": float(np.max(np.asarray(loo_b.pareto_k))),
        "diagnostics": s["diagnostics"],
        "banner": s.get("banner"),
    }


def confirm_leaders(cohort: Cohort, ranking: Ranking, base_folder, out, *, n_confirm: int = 1, progress: bool = False) -> str:
    """Confirm the ``n_confirm`` best candidates that clear the screen's bar with NUTS (each
    row gets ``nuts``: :func:`confirm_with_nuts`, its fit in ``out/fit-EFFECT``); returns the
    verdict under NUTS: the best of them that clears the bar there too, or ``none``."""
    from pathlib import Path

    from ..evaluation._posterior import load_fits

    leaders = [r for r in ranking.rows if r["clears_bar"]][:n_confirm]
    if not leaders:
        return "none"
    (base,) = load_fits([base_folder])
    trials = _trials_of(cohort, base.desc["legs"])
    J0 = nuts_j_draws(base, cohort, trials, n_draws=J_DRAWS, start_stride=J_START_STRIDE)
    for r in progress_bar(leaders, desc="confirming with NUTS", enabled=progress):
        r["nuts"] = confirm_with_nuts(cohort, base, r["effect"], Path(out) / f"fit-{r['effect']}",
                                      eval_trials=trials, J_base=J0, progress=progress)
    return next((r["effect"] for r in leaders if r["nuts"]["clears_bar"]), "none")


def nuts_sentence(summary: dict) -> str:
    """What NUTS said of the screen's leaders, in words."""
    parts = []
    for r in summary["ranking"]:
        n = r.get("nuts")
        if n is None:
            continue
        j10 = n["J_1000ms"]
        parts.append(
            f"NUTS {'confirms' if n['clears_bar'] else 'does not confirm'} {r['effect']}: ΔELPD "
            f"{n['delta_elpd']:.0f} ± {n['delta_elpd_se']:.0f}, J at 1 s {j10['before']['median']:.2f}° → "
            f"{j10['after']['median']:.2f}° [{j10['after']['lo']:.2f}, {j10['after']['hi']:.2f}]"
            + (f" (caution: {n['banner']})" if n.get("banner") else "") + "."
        )
    return " ".join(parts)


# ============================================================================ outputs


def _screen_residuals(fit: LaplaceFit) -> dict[str, dict]:
    return {leg: leg_residuals(fit, leg) for leg in fit.legs}


def residual_figures(residuals: dict[str, dict], out, label: str, dt: float) -> tuple[list, dict]:
    """Residual diagnostics per leg (trends, correlations, twitch-triggered average) of
    ``residuals`` (leg -> :func:`point_residuals`).  Returns (figure paths, findings per leg in words)."""
    from ..evaluation import _residuals as R

    paths, notes = [], {}
    for leg, r in residuals.items():
        feats = R.features(r["angle"], r["velocity"], r["stimulation"], r["sample_mask"], r["trial_start"], dt)
        trends = {k: R.binned_trend(r["residual"], v, r["sample_mask"]) for k, v in feats.items()}
        ac = R.acf(r["residual"], r["sample_mask"])
        cc = R.ccf(r["residual"], r["stimulation"], r["sample_mask"])
        found = R.findings(trends, ac, cc)
        notes[leg] = found
        stem = f"{label}_{leg}"
        paths.append(R.plot_trends(trends, out / f"residual_trends_{stem}.png", notes=found))
        paths.append(R.plot_correlations(ac, cc, out / f"residual_correlation_{stem}.png", notes=found))
        groups = np.where(r["angle"] < -20.0, "pulse below -20°", "pulse above -20°")
        tta = R.twitch_triggered_average(r["residual"], r["stimulation"], r["sample_mask"], groups=groups)
        paths.append(R.plot_twitch_average(tta, out / f"twitch_average_{stem}.png", dt, notes=found))
        spec = R.spectrum(r["residual"], r["sample_mask"], dt)
        peak = R.spectrum_finding(spec)
        found.extend(peak)
        paths.append(R.plot_spectrum(spec, out / f"residual_spectrum_{stem}.png", notes=peak))
    return paths, notes


def loo_pit(fit: LaplaceFit, leg: str, n_draws: int = 100) -> np.ndarray:
    """LOO-PIT of every likelihood window of ``leg`` (twitch windows or samples) under the screen's posterior.

    For each draw s (Laplace draws resampled towards the posterior) the predictive
    CDF of the window's measured equivalent acceleration is exact (Student-t); the
    draws are weighted by their Pareto-smoothed leave-one-segment-out weights
    ∝ 1/p(y_segment | θ_s), so each PIT leaves its own 1-s segment out.
    """
    import arviz as az

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

    return jax.vmap(one)(models, delays, shifts, log_noise)


def elpd_in_time(fit: LaplaceFit, cohort: Cohort, leg: str) -> list[dict]:
    """The pointwise PSIS-LOO ELPD of ``leg``'s 1-s segments, each located in its trial:
    a list of {trial, start_s, elpd}, in the likelihood's segment order."""
    from ..model._likelihood import SEGMENT_SAMPLES

    i = fit.legs.index(leg)
    rows = []
    for t in cohort.trials_of(leg):
        if t.trial in fit.data.trials:
            n_seg = -(-t.n_samples // SEGMENT_SAMPLES)
            rows += [{"trial": t.trial, "start_s": k * SEGMENT_SAMPLES * t.sampling_period_s} for k in range(n_seg)]
    for r, e in zip(rows, fit.elpd_i[i]):
        r["elpd"] = float(e)
    return [r for r in rows if np.isfinite(r["elpd"])]


def worst_seconds_sentence(leg: str, rows: list[dict], n: int = 3) -> str:
    """Where ``leg``'s worst-predicted seconds are, against the median second, in words."""
    med = float(np.median([r["elpd"] for r in rows]))
    worst = sorted(rows, key=lambda r: r["elpd"])[:n]
    where = ", ".join(f"trial {r['trial']} at {r['start_s']:.0f}–{r['start_s'] + 1:.0f} s (ELPD {r['elpd']:.0f})" for r in worst)
    return f"{leg}: the worst-predicted seconds are {where}, against {med:.0f} for the median second."


def predictive_checks(fit: LaplaceFit, cohort: Cohort, out, label: str) -> tuple[list, dict]:
    """The model's predictive checks from its screen: measured against predicted angle one step
    (10 ms) and 1 s ahead with 90 % bands over posterior draws, LOO-PIT, and the pointwise ELPD in
    time.  Returns (figure paths, JSON-able results with their findings in words)."""
    from ..evaluation import _residuals as R
    from ..common._io import save_figure
    from ..outputs._figures import plot_posterior_predictions
    from ..evaluation._posterior import FIGURE_WINDOW_S, posterior_predictions

    paths, result = [], {"loo_pit": {}, "worst_seconds": {}, "notes": []}
    shown = "JM-left" if "JM-left" in fit.legs else fit.legs[0]
    trial = [t for t in cohort.trials_of(shown) if t.trial in fit.data.trials][-1]
    dt = trial.sampling_period_s
    start_s = min(FIGURE_WINDOW_S[0], max(0.0, trial.n_samples * dt - FIGURE_WINDOW_S[1]))
    i0 = int(round(start_s / dt))
    i1 = min(trial.n_samples, i0 + int(round(FIGURE_WINDOW_S[1] / dt)))
    models = leg_draw_models(fit, shown, J_DRAWS)
    for p, name in ((1, "one_step"), (100, "1s")):
        starts = np.arange(max(0, i0 - p), i1 - p)
        predicted = {fit.model.name: (starts, posterior_predictions(models, trial, starts, (p,))[:, :, 0])}
        fig = plot_posterior_predictions(trial, predicted, p, start_s=start_s, length_s=FIGURE_WINDOW_S[1])
        paths.append(save_figure(fig, out / f"predictions_{name}_{label}_{shown}.png"))
    pits, seconds = {}, {}
    for leg in fit.legs:
        values = loo_pit(fit, leg)
        summ = R.loo_pit_summary(values, int(fit.data.segment_mask[fit.legs.index(leg)].sum()))
        pits[leg] = (values, summ)
        result["loo_pit"][leg] = summ
        result["notes"] += [f"{leg}: {n}" for n in summ["notes"]] or [
            f"{leg}: LOO-PIT is uniform within its band (ECDF distance {summ['distance']:.3f} ≤ {summ['band']:.3f})."
        ]
        seconds[leg] = elpd_in_time(fit, cohort, leg)
        result["worst_seconds"][leg] = sorted(seconds[leg], key=lambda r: r["elpd"])[:3]
        result.setdefault("elpd_total", {})[leg] = float(sum(r["elpd"] for r in seconds[leg]))
    worst = [worst_seconds_sentence(leg, rows) for leg, rows in seconds.items()]
    paths.append(R.plot_loo_pit(pits, out / f"loo_pit_{label}.png", notes=list(result["notes"])))
    paths.append(R.plot_elpd_in_time(seconds, out / f"elpd_in_time_{label}.png", notes=worst))
    result["notes"] += worst
    return paths, result


def ranking_markdown(summary: dict, command: str | None = None) -> str:
    rows = summary["ranking"]
    md = [f"# Which effect is missing from {summary['model']}", ""]
    if command:
        md += [f"Regenerate: `{command}`", ""]
    md += [f"**Verdict: {summary['verdict']}.** {summary['sentence']}", ""]
    md += [
        "| rank | effect | ΔELPD ± SE | J 500 ms before → after [deg] | J 1000 ms before → after [deg] | clears the bar | Pareto k max | importance ESS |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for i, r in enumerate(rows, 1):
        j5, j10 = r["J_500ms"], r["J_1000ms"]
        md.append(
            f"| {i} | {r['effect']} | {r['delta_elpd']:.1f} ± {r['delta_elpd_se']:.1f} | "
            f"{j5['before']['median']:.3f} → {j5['after']['median']:.3f} [{j5['after']['lo']:.3f}, {j5['after']['hi']:.3f}] | "
            f"{j10['before']['median']:.3f} → {j10['after']['median']:.3f} [{j10['after']['lo']:.3f}, {j10['after']['hi']:.3f}] | "
            f"{'yes' if r['clears_bar'] else 'no'} | {r['pareto_k_max']:.2f} | {r['importance_ess_min']:.0f} |"
        )
    md += [
        "",
        f"The bar: ΔELPD above {ELPD_SE_BAR:g} standard errors (PSIS-LOO over 1-s segments, paired) and J lowered "
        "beyond the 90 % bands at 500 and 1000 ms.  ELPD and bands come from the screen (per-leg MAP, Laplace draws "
        "importance-weighted towards the posterior); a Pareto k above 0.7 or a small importance ESS says the Gaussian "
        "stands poorly for that posterior, and NUTS is the confirmation (`quadshank diagnose FITDIR --confirm`).",
    ]
    confirmed = [r for r in rows if "nuts" in r]
    if confirmed:
        md += [
            "",
            f"## Confirmed with hierarchical NUTS (against the fit in `{summary.get('confirmed_from', '')}`)",
            "",
            "| effect | ΔELPD ± SE (PSIS-LOO) | J 500 ms before → after [deg] | J 1000 ms before → after [deg] | clears the bar | fit |",
            "|---|---|---|---|---|---|",
        ]
        for r in confirmed:
            n = r["nuts"]
            j5, j10 = n["J_500ms"], n["J_1000ms"]
            md.append(
                f"| {r['effect']} | {n['delta_elpd']:.1f} ± {n['delta_elpd_se']:.1f} | "
                f"{j5['before']['median']:.3f} → {j5['after']['median']:.3f} [{j5['after']['lo']:.3f}, {j5['after']['hi']:.3f}] | "
                f"{j10['before']['median']:.3f} → {j10['after']['median']:.3f} [{j10['after']['lo']:.3f}, {j10['after']['hi']:.3f}] | "
                f"{'yes' if n['clears_bar'] else 'no'} | `{n['folder']}`{' — ' + n['banner'] if n.get('banner') else ''} |"
            )
        md += ["", f"The screen's verdict: {summary.get('screen_verdict')}; under NUTS: {summary['verdict']}."]
    failed = summary.get("failed", [])
    if failed:
        md += ["", "## Candidates that could not be screened", ""]
        md += [f"- **{f['effect']}**: {f['error']}" for f in failed]
    checks = summary.get("predictive_checks")
    if checks:
        md += ["", "## Predictive checks of the baseline (LOO-PIT, pointwise ELPD in time)", ""]
        md += [f"- {n}" for n in checks["notes"]]
    findings = summary.get("residual_findings", {})
    if findings:
        md += ["", "## Where the model fails (residuals of the baseline)", ""]
        for leg, lines in findings.items():
            md.append(f"- {leg}: " + (" ".join(lines) if lines else "nothing stands out."))
    return "\n".join(md) + "\n"


def run_diagnose(
    cohort: Cohort,
    model: Model | str,
    out,
    *,
    trials=(1,),
    legs=None,
    effects=None,
    figures: bool = True,
    command: str | None = None,
    progress: bool = False,
    base: LaplaceFit | None = None,
    seed: int = 0,
    n_starts: int = 3,
    confirm_from=None,
    n_confirm: int = 1,
) -> dict:
    """Rank the candidate effects for ``model``; writes figures, report.md and summary.json (last).

    ``n_starts``: see :func:`rank_effects`.  ``confirm_from``: a NUTS fit folder of
    ``model`` on the same data; then the ``n_confirm`` best candidates that clear
    the screen's bar are refitted with NUTS (``out/confirm/fit-EFFECT``, the same
    settings) and the verdict is the best that clears the bar under NUTS too
    (:func:`confirm_leaders`); the screen's own is kept as ``screen_verdict``."""
    from pathlib import Path

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ranking = rank_effects(cohort, model, trials=trials, legs=legs, effects=effects, base=base, seed=seed,
                           n_starts=n_starts, progress=progress)
    screen_verdict = ranking.verdict
    if confirm_from is not None:
        ranking.verdict = confirm_leaders(cohort, ranking, confirm_from, out / "confirm", n_confirm=n_confirm,
                                          progress=progress)
    summary = ranking.to_json()
    summary["sentence"] = verdict_sentence(ranking)
    if confirm_from is not None:
        summary["screen_verdict"] = screen_verdict
        summary["confirmed_from"] = str(confirm_from)
        said = nuts_sentence(summary)
        if ranking.verdict == "none" and screen_verdict != "none":
            summary["sentence"] = f"The screen's leader, {screen_verdict}, is not confirmed by NUTS. {said}"
        elif said:
            summary["sentence"] += " " + said
    summary["trials"] = [int(t) for t in trials]
    dt = ranking.base.model.sampling_period_s
    if figures:
        paths, checks = predictive_checks(ranking.base, cohort, out, "baseline")
        summary["predictive_checks"] = checks
        more, notes = residual_figures(_screen_residuals(ranking.base), out, "baseline", dt)
        paths += more
        if ranking.verdict != "none":
            more, after = residual_figures(_screen_residuals(ranking.fits[ranking.verdict]), out, "with_" + ranking.verdict, dt)
            paths += more
            summary["residual_findings_after"] = after
        summary["residual_findings"] = notes
        summary["figures"] = [p.name for p in paths]
    (out / "report.md").write_text(ranking_markdown(summary, command))
    write_json(out / "summary.json", summary)
    summary["_ranking"] = ranking
    return summary


def _fit_entry(summary: dict, folder: str) -> dict:
    return {"folder": folder, "model": summary["model"], "banner": summary.get("banner"), "diagnostics": summary["diagnostics"]}


def _compare_start_final(cohort, out, fits: dict, *, n_draws, start_stride, progress) -> dict:
    """The loop's first and last NUTS fits (folders relative to ``out``) compared in
    ``out/confirm/compare``: J bands, PSIS-LOO, residuals before and after."""
    from ..evaluation._posterior import run_posterior_evaluate

    cmp = run_posterior_evaluate(cohort, [out / fits["start"]["folder"], out / fits["final"]["folder"]], out / "confirm" / "compare",
                                 n_draws=n_draws, start_stride=start_stride, progress=progress, residuals=True)
    a, b = fits["start"]["model"], fits["final"]["model"]
    group = (cmp["loo"]["compare"] or [{}])[0].get("table", {})
    J = cmp["J"]
    trial = sorted(J[a])[-1]
    ja, jb = J[a][trial]["1000"], J[b][trial]["1000"]
    elpd = group.get(a, {})
    text = (f"NUTS: {b} against {a}: ELPD difference {elpd.get('elpd_diff', float('nan')):.1f} ± {elpd.get('dse', float('nan')):.1f} "
            f"in favour of {'the final model' if group.get(b, {}).get('rank') == 0 else 'the start model'}; "
            f"J at 1 s on trial {trial} {ja['median']:.2f}° [{ja['lo']:.2f}, {ja['hi']:.2f}] → {jb['median']:.2f}° [{jb['lo']:.2f}, {jb['hi']:.2f}].")
    banners = [f"{f['model']}: {f['banner']}" for f in fits.values() if f["banner"]]
    if banners:
        text += " Caution, the fits failed their checks: " + "; ".join(banners)
    return {"sentence": text, "elpd_diff": elpd.get("elpd_diff"), "elpd_dse": elpd.get("dse"),
            "J_1000ms": {a: ja, b: jb}, "trial": trial}


def run_discover(
    cohort: Cohort,
    out,
    *,
    model: Model | str = "model3s",
    trials=(1,),
    legs=None,
    effects=None,
    max_rounds: int = 3,
    command: str | None = None,
    progress: bool = False,
    confirm=None,
    data_source: str | None = None,
    compare_draws: int = 100,
    compare_stride: int = 10,
) -> dict:
    """The whole loop: diagnose, add the leading effect, diagnose again, while an effect clears the bar.

    ``confirm`` (a :class:`quadshank.inference._fit.FitSettings`): then every round's leader
    is confirmed with hierarchical NUTS before it is added: the starting model is
    fitted (``confirm/fit-start``), each round refits its leader against the
    previous round's fit (``round-K/confirm/fit-EFFECT``, see :func:`run_diagnose`)
    and the loop goes on only while NUTS agrees; the first and last fits are then
    compared (``confirm/compare``: J bands over ``compare_draws`` posterior draws,
    PSIS-LOO, residuals before and after).
    """
    from pathlib import Path

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    current = build_model(model) if isinstance(model, str) else model
    fits, nuts_folder = {}, None
    if confirm is not None:
        from ..commands._pipeline import run_fit

        base_name, *adds = current.name.split("+")
        nuts_folder = out / "confirm" / "fit-start"
        s = run_fit(cohort, nuts_folder, base_name, adds, confirm, legs=legs, progress=progress, data_source=data_source)
        fits["start"] = fits["final"] = _fit_entry(s, "confirm/fit-start")
    rounds, base = [], None
    for k in range(1, max_rounds + 1):
        s = run_diagnose(
            cohort, current, out / f"round-{k}", trials=trials, legs=legs, effects=effects, base=base, progress=progress,
            confirm_from=nuts_folder,
        )
        ranking = s.pop("_ranking")
        rounds.append({"model": current.name, "verdict": s["verdict"], "sentence": s["sentence"], "J_ms": s["J_ms"], "elpd": s["elpd"]})
        if "screen_verdict" in s:
            rounds[-1]["screen_verdict"] = s["screen_verdict"]
        if s["verdict"] == "none":
            break
        base = ranking.fits[s["verdict"]]
        current = base.model
        if confirm is not None:
            row = next(r for r in s["ranking"] if r["effect"] == s["verdict"])
            nuts_folder = Path(row["nuts"]["folder"])
            fits["final"] = _fit_entry(row["nuts"], nuts_folder.relative_to(out).as_posix())
    summary = {"model": rounds[0]["model"], "final_model": current.name, "rounds": rounds,
               "added": [r["verdict"] for r in rounds if r["verdict"] != "none"]}
    if confirm is not None:
        summary["confirm"] = dict(fits)
        if summary["added"]:
            summary["confirm"].update(_compare_start_final(cohort, out, fits, n_draws=compare_draws,
                                                           start_stride=compare_stride, progress=progress))
        else:
            summary["confirm"]["sentence"] = "Nothing was added; the start model's fit is in confirm/fit-start."
    md = ["# The modelling loop (`quadshank discover`)", ""]
    if command:
        md += [f"Regenerate: `{command}`", ""]
    for k, r in enumerate(rounds, 1):
        J = r["J_ms"]
        md.append(
            f"{k}. **{r['model']}**: J at 0.5 s {J['500']['median']:.3f}° [{J['500']['lo']:.3f}, {J['500']['hi']:.3f}], "
            f"at 1 s {J['1000']['median']:.3f}°; ELPD {r['elpd']['value']:.0f} ± {r['elpd']['se']:.0f}. "
            f"Verdict: {r['verdict']}. {r['sentence']} (details: [round-{k}/report.md](round-{k}/report.md))"
        )
    md += ["", f"Final model: **{current.name}**."]
    if confirm is not None:
        c = summary["confirm"]
        md += ["", "## Confirmed with hierarchical NUTS", "", c["sentence"], "",
               f"Fits: [{c['start']['folder']}]({c['start']['folder']}), [{c['final']['folder']}]({c['final']['folder']}); "
               f"comparison with residuals before and after: [confirm/compare/report.md](confirm/compare/report.md)."]
    (out / "report.md").write_text("\n".join(md) + "\n")
    write_json(out / "summary.json", summary)
    return summary
