"""``quadshank predict``: the angle a planned stimulation sequence would produce, per fitted leg,
with posterior bands (CSV, figure, ``summary.json``)."""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import warnings
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..common._io import atomic_write_text, save_figure
from ..common._results import Result
from ..data._interchange import DataWarning, read_plan
from ..evaluation._posterior import load_fits, plan_predictions
from ..inference._fitio import posterior_models
from ..inference._summaries import INTERVAL, interval
from ..outputs._figures import plot_plan_predictions

__all__ = ["PlanPrediction", "run_predict"]


@dataclasses.dataclass
class PlanPrediction(Result):
    """What ``quadshank predict`` computed: per leg, the median and 90 % band of the angle a
    stimulation plan would produce (the numbers themselves are in ``predictions.csv``)."""

    KIND: ClassVar[str] = "prediction"

    fit: str  # the fit folder
    model: str
    plan: str  # the stimulation plan's file
    legs: list
    angle0_deg: float | None  # None: each draw started at its own rest (``rest_deg`` gives it per leg)
    velocity0_deg_s: float
    n_draws: int
    interval: list
    samples: int
    files: list
    extremes: dict  # leg -> the band at the plan's last sample, its lowest and highest angle
    plan_columns: list | None = None  # a stimulator's columns the plan gave, made each leg's levels; None: levels
    fitted_angle_range_deg: dict | None = None  # leg -> [lowest, highest] angle of the samples the fit saw
    beyond_fitted_range: dict | None = None  # leg -> the start or predicted angle beyond that range by more than the margin
    banner: str | None = None  # the fit's, where it failed its checks: its bands come from draws not to be trusted
    diverged_draws: dict | None = None  # leg -> {"draws", "first_s"}: draws whose run left the numbers, left out from there
    beyond_reach: dict | None = None  # leg -> {"what", "time_s", "angle_deg"}: where the median (else band) passes ±180°
    seed: int = 0  # which posterior draws were rolled out
    rest_deg: dict | None = None  # with angle0 None: leg -> median, lo, hi of the draws' rest as the goniometer reads it


#: How far [deg] a start or a predicted median may leave the angles the fit saw before a warning
#: says the model is extrapolated there.
EXTRAPOLATION_MARGIN_DEG = 10.0
#: A predicted angle beyond ± this [deg] has the shank over the top, where no knee goes: a model
#: without an end of range (``extension_limit``) can get there, and a plan that drives it there is told so.
KNEE_REACH_DEG = 180.0


def _band(predictions: np.ndarray) -> tuple[dict, np.ndarray]:
    """Median and 90 % band over the draws (rows) at each sample, of the draws whose run is still
    finite there, and the draws whose run left the numbers (a boolean per draw)."""
    finite = np.isfinite(predictions)
    if finite.all():
        return {k: np.asarray(v) for k, v in interval(predictions, axis=0).items()}, np.zeros(len(predictions), bool)
    # a draw that overflows is left out from where it does; at a sample no draw reaches, the band is NaN
    values = np.where(finite, predictions, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN samples: NaN, said below
        lo, hi = np.nanquantile(values, INTERVAL, axis=0)
        median = np.nanmedian(values, axis=0)
    return {"median": median, "lo": lo, "hi": hi}, ~finite.all(axis=1)


def _finite_or_none(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def fitted_angle_range(idata, leg: str) -> tuple[float, float] | None:
    """The lowest and highest angle of ``leg``'s samples that a saved fit's likelihood saw (None
    where the fit holds no angles)."""
    data = getattr(idata, "constant_data", None)
    if data is None or "angle" not in data or leg not in list(data["leg"].values):
        return None
    i = list(data["leg"].values).index(leg)
    angle = np.asarray(data["angle"])[i]
    if "sample_mask" in data:
        angle = angle[np.asarray(data["sample_mask"])[i].astype(bool)]
    angle = angle[np.isfinite(angle)]
    return (float(angle.min()), float(angle.max())) if angle.size else None


def _beyond(angle0: float, band: dict, seen: tuple[float, float]) -> dict | None:
    """Where the start, the median prediction or, the median within, its 90 % band (``band``:
    ``median``, ``lo``, ``hi``) leaves ``seen`` by more than the margin: the angle furthest out."""
    lo, hi = seen[0] - EXTRAPOLATION_MARGIN_DEG, seen[1] + EXTRAPOLATION_MARGIN_DEG
    far = [("start", angle0)] if not lo <= angle0 <= hi else []
    for what, values in (("prediction", band["median"]), ("band", np.concatenate([band["lo"], band["hi"]]))):
        out = values[(values < lo) | (values > hi)]
        if out.size:
            far.append((what, float(out[np.argmax(np.abs(out - 0.5 * (lo + hi)))])))
            break  # the band leaves the range wherever its median does
    return {what: round(v, 2) for what, v in far} or None


def run_predict(
    fit_dir, plan, out, *, legs=None, angle0: float | None = None, velocity0: float = 0.0, n_draws: int = 200,
    seed: int = 0,
) -> PlanPrediction:
    """Roll each fitted leg's posterior draws through the stimulation ``plan`` (a CSV with
    time_s,stimulation at the fit's period, or time_s and the stimulator's columns the fitted
    data gave, :func:`~quadshank.data.read_plan`) from the start state (``angle0`` [deg] as the
    goniometer reads it, ``velocity0`` [deg/s], the muscle at rest; ``angle0`` None, the default:
    each draw at its own rest, where its shank settles without stimulation, which is not angle 0
    where a gravity or goniometer offset was fitted); write ``predictions.csv``
    (time, the plan's column(s), each leg's level where it differs, and per leg median, lo, hi),
    ``predictions.png`` and, last, ``summary.json``."""
    if n_draws < 1:
        raise ValueError(f"--draws must be at least 1, not {n_draws}")
    if isinstance(seed, bool) or not float(seed).is_integer() or not 0 <= int(seed) < 2**32:
        raise ValueError(f"--seed must be a whole number from 0 to {2**32 - 1}, not {seed}")
    # a knee's angle lies within a turn of its rest, its speed within a few thousand deg/s
    if angle0 is not None and not (math.isfinite(angle0) and abs(angle0) <= 360.0):
        raise ValueError(f"--angle0 must be a knee angle in degrees, within ±360, not {angle0}")
    if not (math.isfinite(velocity0) and abs(velocity0) <= 5000.0):
        raise ValueError(f"--velocity0 must be an angular velocity in deg/s, within ±5000, not {velocity0}")
    if angle0 is None and velocity0 != 0.0:
        raise ValueError("--velocity0 acts only with --angle0 (without it each draw starts at its rest, where the "
                         "shank is still)")
    fit_dir, out = Path(fit_dir), Path(out)
    (fit,) = load_fits([fit_dir])
    planned = read_plan(plan, fit.model.sampling_period_s)
    time_s = planned.time_s
    fitted = list(fit.desc["legs"])
    legs = list(legs) if legs else fitted
    unknown = [leg for leg in legs if leg not in fitted]
    if unknown:
        raise KeyError(f"{fit_dir}: the fit has no leg {', '.join(unknown)} (it has {', '.join(fitted)})")
    scales = fit.summary.charge_scale or {}
    try:  # every leg's levels before any rollout: a plan one leg cannot take is refused at once
        levels = {leg: planned.levels(leg, scales) for leg in legs}
    except ValueError as err:
        raise ValueError(f"{plan}: {err}") from None
    available = fit.idata.posterior.sizes["chain"] * fit.idata.posterior.sizes["draw"]
    if n_draws > available:
        warnings.warn(f"{fit_dir}: --draws {n_draws}, and the fit holds {available} draws: all {available} are rolled "
                      "out", DataWarning, stacklevel=2)
    elif n_draws < 20:
        warnings.warn(f"--draws {n_draws}: a 90 % band of so few draws says little of the posterior's spread",
                      DataWarning, stacklevel=2)
    bands, diverged, reach = {}, {}, {}
    for leg in legs:
        models, _ = posterior_models(fit.idata, fit.model, leg, n_draws, seed)
        predictions = np.asarray(plan_predictions(models, levels[leg], angle0, velocity0), dtype=float)
        bands[leg], gone = _band(predictions)
        if gone.any():
            first = int(np.argmax(~np.isfinite(predictions[gone]).any(axis=0)))
            diverged[leg] = {"draws": int(gone.sum()), "first_s": round(float(time_s[first]), 6)}
            warnings.warn(f"{leg}: {int(gone.sum())} of {len(predictions)} draws ran off to no finite angle under the "
                          f"plan, the first at {time_s[first]:.2f} s; the band is of the draws still finite at each "
                          "sample (and none where none is). The plan drives the model far beyond what the fit saw",
                          DataWarning, stacklevel=2)
        for what, values in (("median prediction", bands[leg]["median"]),
                             ("90 % band", np.fmax(np.abs(bands[leg]["lo"]), np.abs(bands[leg]["hi"])))):
            over = np.flatnonzero(np.abs(np.nan_to_num(values, nan=np.inf)) > KNEE_REACH_DEG)
            if not over.size:
                continue
            i = int(over[0])
            angle = _finite_or_none(values[i])
            reach[leg] = {"what": what.split()[-1], "time_s": round(float(time_s[i]), 6),
                          "angle_deg": None if angle is None else round(angle, 1)}
            warnings.warn(f"{leg}: the {what} passes ±{KNEE_REACH_DEG:g}° at {time_s[i]:.2f} s"
                          + (f" ({angle:.4g}°)" if angle is not None else "") + ": the shank over the top, where no "
                          "knee goes. The model has no end of range that stops it (extension_limit describes one); its angles "
                          "from there say only that the plan "
                          "would drive the knee to the end of its range", DataWarning, stacklevel=2)
            break  # the band passes wherever its median does
    seen = {leg: fitted_angle_range(fit.idata, leg) for leg in legs}
    beyond = {}
    for leg, r in seen.items():
        start = float(bands[leg]["median"][0]) if angle0 is None else angle0
        far = _beyond(start, bands[leg], r) if r is not None else None
        if far:
            beyond[leg] = far
            names = {"start": "the start", "prediction": "the median prediction", "band": "the 90 % band"}
            what = " and ".join(f"{names[k]} at {v:.4g}°" for k, v in far.items())
            warnings.warn(f"{leg}: {what} {'lies' if len(far) == 1 else 'lie'} beyond the angles the fit saw "
                          f"({r[0]:.1f}° to {r[1]:.1f}°): "
                          "the model is extrapolated there and its bands do not say how far to trust it",
                          DataWarning, stacklevel=2)
    # the plan's columns as given and, for a stimulator's, each leg's levels (its charge over the leg's largest)
    values = planned.stimulator or {"stimulation": planned.stimulation}
    given = list(values)
    per_leg = [f"{leg} stimulation" for leg in legs] if planned.columns else []
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["time_s", *given, *per_leg, *[f"{leg} {k} [deg]" for leg in legs for k in ("median", "lo", "hi")]])
    for i in range(time_s.size):
        w.writerow([repr(float(time_s[i])), *[repr(float(values[c][i])) for c in given],
                    *([repr(float(levels[leg][i])) for leg in legs] if planned.columns else []),
                    *[f"{float(bands[leg][k][i]):.6g}" for leg in legs for k in ("median", "lo", "hi")]])
    atomic_write_text(out / "predictions.csv", buf.getvalue())
    shown = planned.stimulation if planned.stimulation is not None else planned.charge
    ylabel = None if planned.unit is None else (
        {"µs": "pulse width", "mA": "current"}.get(planned.unit, "pulse charge") + f" [{planned.unit}]")
    label = fit.label + (" — FIT FAILED ITS CHECKS" if fit.summary.banner else "")
    save_figure(plot_plan_predictions(time_s, shown, bands, label, ylabel=ylabel,
                                      fitted_range={leg: r for leg, r in seen.items() if r is not None}),
                out / "predictions.png")
    used = min(n_draws, available)
    result = PlanPrediction(
        fit=str(fit_dir), model=fit.label, plan=str(plan), legs=legs, angle0_deg=None if angle0 is None else float(angle0),
        velocity0_deg_s=float(velocity0), n_draws=used, interval=list(INTERVAL), samples=int(time_s.size),
        files=["predictions.csv", "predictions.png"], plan_columns=list(planned.columns) or None,
        extremes={leg: {"end": {k: _finite_or_none(b[k][-1]) for k in ("median", "lo", "hi")},
                       "max_deg": _finite_or_none(np.max(b["hi"], initial=-np.inf, where=np.isfinite(b["hi"]))),
                       "min_deg": _finite_or_none(np.min(b["lo"], initial=np.inf, where=np.isfinite(b["lo"])))}
                  for leg, b in bands.items()},
        fitted_angle_range_deg={leg: [round(r[0], 3), round(r[1], 3)] for leg, r in seen.items() if r is not None},
        beyond_fitted_range=beyond,
        banner=fit.summary.banner,
        diverged_draws=diverged or None,
        beyond_reach=reach or None,
        seed=int(seed),
        rest_deg=None if angle0 is not None else {
            leg: {k: _finite_or_none(b[k][0]) for k in ("median", "lo", "hi")} for leg, b in bands.items()},
    )
    result.write(out)
    return result
