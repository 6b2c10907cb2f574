"""What the residuals still hold: structure that no candidate effect took up, and what kind of effect would.

When the modelling loop's verdict is ``none``, the model may still fail in a way
no registered candidate describes.  :func:`residual_structure` looks for it in the
one-step residuals of every leg (:func:`quadshank.evaluation._residuals.point_residuals`):

1. For each feature of :func:`quadshank.evaluation._residuals.features` (knee
   angle, velocity, time in trial, preceding interpulse interval, pulse count,
   recruitment level), the binned trend of the residual
   (:func:`~quadshank.evaluation._residuals.binned_trend`) per leg, about the
   residual's own mean there (m̄, the bins' precision-weighted mean; χ² on one degree
   of freedom fewer than bins); the legs' χ² add up, and so do their degrees of
   freedom.  How strong: the share of the residual's sum of squares that the trend
   carries (Σ n_b·(mean_b − m̄)² / Σ r²) and the range of the bin means; how sure:
   the combined p-value and the legs whose own trend is significant.  A feature
   needs at least :data:`MIN_BINS` distinct bins in every leg to be named (a single
   recruitment level has no trend).
2. The feature with the largest share among the significant ones (p below
   ``alpha`` divided by the number of features, a Bonferroni bound) is named; its
   trend is taken out of the residual and the search repeats (at most
   ``max_steps`` features), so that a trend that only mirrors a named one (the
   angle of a swing seen through its velocity) is not named twice.
3. For a named feature, the trend is measured again on the *quiet* samples (no
   pulse within the model's twitch response before them) and on the samples
   *during twitches*.  Structure as strong between twitches as during them is
   passive (the knee's own torque, or the sensors), structure during twitches only
   is active (the twitch's gain or its pulses); the feature then says which kind
   of effect would describe it (:data:`KIND_HINTS`).

A constant is not a change with a feature.  The residual's offset (its mean per leg
against its standard error) is judged apart, with the same bound, quiet and during
twitches: a constant torque the model lacks, or twitches too large or too small on
average.

The twitch-locked part (the residual's cross-correlation with the stimulation,
:func:`~quadshank.evaluation._residuals.ccf`) is judged per leg as the residual
findings judge it, and named when it stands out in most legs.

Everything here is NumPy; :func:`quadshank.outputs._residual_figures.plot_structure` draws the
named trends, quiet and during twitches side by side.
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from . import _residuals as R

__all__ = ["residual_structure", "structure_sentence", "KIND_HINTS", "NOTHING_FOUND", "nothing_found"]

#: Feature -> (where the structure shows) -> the kind of effect that would describe it, in words.
#: "passive": as strong between twitches as during them; "active": during twitches only.
KIND_HINTS = {
    "angle": {
        "passive": "a passive torque that depends on the knee angle (stiffness, a rest angle, the end of the range): "
                   "an effect of kind 'passive'",
        "active": "a twitch whose size depends on the knee angle: an effect of kind 'gain' (a torque–angle factor)",
    },
    "velocity": {
        "passive": "a passive torque that depends on the angular velocity (friction, non-linear damping): "
                   "an effect of kind 'passive'",
        "active": "a twitch whose size depends on the angular velocity: an effect of kind 'gain' "
                  "(a torque–velocity factor) or 'output'",
    },
    "time": {
        "passive": "a slow drift not tied to the twitches (a sensor's drift, a passive property that changes over "
                   "the trial): an effect of kind 'measurement' or 'passive'",
        "active": "twitches that change over the trial: an effect of kind 'pulse' with a state (as fatigue and "
                  "potentiation are)",
    },
    "pulse_count": {
        "passive": "a slow drift not tied to the twitches (a sensor's drift, a passive property that changes over "
                   "the trial): an effect of kind 'measurement' or 'passive'",
        "active": "twitches that change with the pulses delivered: an effect of kind 'pulse' with a state "
                  "(as fatigue and potentiation are)",
    },
    "ipi": {
        "passive": "a state that follows the stimulation's rhythm beyond the twitch: an effect of kind 'pulse'",
        "active": "twitches that depend on the interval since the previous pulse: an effect of kind 'pulse'",
    },
    "u": {
        "passive": "a state that follows the stimulation's level beyond the twitch: an effect of kind 'pulse'",
        "active": "twitches that do not scale with the recruitment level as modelled: an effect of kind 'pulse' "
                  "(a recruitment curve)",
    },
}
#: Where a constant offset of the residual shows -> what it asks for.
OFFSET_HINTS = {
    "passive": "a constant torque the model lacks (a rest angle off the gravity vertical, an offset of the "
               "goniometer): an effect of kind 'passive' or 'measurement'",
    "active": "twitches too large or too small on average: the twitch's gain or its shape (kind 'gain' or "
              "'activation')",
}
#: What is said when no feature is named and the residual is not locked to the stimulation, where
#: the features screened are not known (:func:`nothing_found` names them).
NOTHING_FOUND = ("The residuals change with none of knee angle, velocity, time in trial, interpulse interval, pulse "
                 "count and recruitment level beyond chance.")


def nothing_found(structure: dict) -> str:
    """What is said when :func:`residual_structure` named no feature: the features the residuals
    were screened against, those the data have (a pendulum test has no pulse count)."""
    words = [R.FEATURE_WORDS.get(k, (k, ""))[0] for k in structure.get("screened", {})]
    if not words:
        return NOTHING_FOUND
    listed = words[0] if len(words) == 1 else f"{', '.join(words[:-1])} and {words[-1]}"
    return f"The residuals change with none of {listed} beyond chance."
TWITCH_LOCKED_HINT = "the twitch's shape or timing: an effect of kind 'activation' or 'delay'"

#: Fewer masked-in samples than this on one side (quiet, during twitches) and the side is not judged.
MIN_SIDE_SAMPLES = 200
#: A feature with fewer distinct bins than this in some leg (one recruitment level throughout) has
#: no trend to name: its single bin's mean is the residual's offset, not a change with the feature.
MIN_BINS = 3
#: Structure between twitches at least this fraction of its size during them is called passive.
PASSIVE_RATIO = 0.5


def _during_twitch(stimulation, trial_start, response_samples: int) -> np.ndarray:
    """True where a pulse of the same trial came at most ``response_samples`` samples before."""
    u = np.nan_to_num(np.asarray(stimulation, float))
    k = np.arange(u.size)
    last = np.maximum.accumulate(np.where(u > 0, k, -1))
    return (last >= np.asarray(trial_start, int)) & (k - last <= response_samples)


def _trend(residual, feature, mask) -> dict | None:
    """:func:`binned_trend` on ``mask``, its χ² and sum of squares taken about the bins' weighted
    mean (the offset, kept as ``offset``); None without data."""
    if int(np.sum(mask & np.isfinite(feature) & np.isfinite(residual))) < 20:
        return None
    try:
        t = R.binned_trend(residual, feature, mask)
    except ValueError:
        return None
    # the trend about the residual's own offset there: a constant is not a change with the feature
    w = 1.0 / t["se"] ** 2
    t["offset"] = float(np.sum(w * t["mean"]) / np.sum(w))
    dev = t["mean"] - t["offset"]
    t["chi2"] = float(np.sum((dev / t["se"]) ** 2))
    t["dof"] = len(dev) - 1
    t["p_value"] = float(stats.chi2.sf(t["chi2"], t["dof"])) if t["dof"] > 0 else 1.0
    t["ss_means"] = float(np.sum(t["count"] * dev**2))
    t["ss"] = float(np.nansum(np.where(mask, residual, np.nan) ** 2))
    t["amplitude"] = float(np.sqrt(t["ss_means"] / max(int(np.sum(t["count"])), 1)))  # RMS of the bin means
    return t


def _subtract_bins(residual, feature, mask, t) -> np.ndarray:
    """The residual less the trend of ``t`` about its offset (bins split halfway between the bin centres)."""
    f = np.asarray(feature, float)
    centre = np.asarray(t["centre"])
    idx = np.clip(np.searchsorted((centre[1:] + centre[:-1]) / 2, f, side="right"), 0, len(centre) - 1)
    use = mask & np.isfinite(f)
    return np.where(use, residual - (np.asarray(t["mean"]) - t["offset"])[idx], residual)


def _side(legs: dict, key: str, side_mask: dict) -> dict:
    """The trend of ``key`` pooled over legs on one side (quiet / during twitches)."""
    trends = [_trend(L["residual"], L["features"][key], L["mask"] & side_mask[leg]) for leg, L in legs.items()]
    trends = [t for t in trends if t is not None]
    n = int(sum(np.sum(t["count"]) for t in trends))
    if not trends or n < MIN_SIDE_SAMPLES:
        return {"judged": False, "n": n}
    chi2 = float(sum(t["chi2"] for t in trends))
    dof = int(sum(t["dof"] for t in trends))
    if dof == 0:
        return {"judged": False, "n": n}
    return {
        "judged": True, "n": n, "chi2": chi2, "dof": dof, "p_value": float(stats.chi2.sf(chi2, dof)),
        "amplitude": float(np.sqrt(sum(t["ss_means"] for t in trends) / n)),
    }  # fmt: skip


def residual_structure(residuals: dict[str, dict], dt: float, response_samples: int, *, alpha: float = 0.01,
                       min_share: float = 0.01, max_steps: int = 3, features=None) -> dict:
    """Structure left in the residuals of every leg (module docs); JSON-able.

    ``residuals``: leg -> :func:`~quadshank.evaluation._residuals.point_residuals`;
    ``response_samples``: the model's twitch response [samples], which separates the
    samples during twitches from the quiet ones.  A feature is named when its combined
    p-value is below ``alpha / n_features`` (``features``: the names of
    :data:`~quadshank.evaluation._residuals.FEATURE_LABELS` to look at, default all) and its
    trend carries at least ``min_share`` of the residual's sum of squares.  Returns ``found``
    (the named features in order, each with its strength, certainty, side and hint),
    ``screened`` (every feature's first-pass numbers), ``offset`` (the residual's constant
    offset, judged the same way) and ``twitch_locked`` (legs whose residual correlates with
    the stimulation beyond chance).
    """
    legs = {}
    for leg, r in residuals.items():
        mask = R._valid(r["residual"], r["sample_mask"])
        feats = R.features(r["angle"], r["velocity"], r["stimulation"], r["sample_mask"], r["trial_start"], dt)
        legs[leg] = {"residual": np.where(mask, np.asarray(r["residual"], float), np.nan), "mask": mask,
                     "features": feats, "twitch": _during_twitch(r["stimulation"], r["trial_start"], response_samples)}
    keys = list(R.FEATURE_LABELS) if features is None else [k for k in R.FEATURE_LABELS if k in set(features)]
    bound = alpha / len(keys)
    offset = _offset(legs, bound, min_share)  # on the residual as it is, before any trend is taken out
    found, screened = [], {}
    remaining = list(keys)
    for step in range(max_steps):
        rows = {}
        for key in remaining:
            trends = {leg: _trend(L["residual"], L["features"][key], L["mask"]) for leg, L in legs.items()}
            trends = {leg: t for leg, t in trends.items() if t is not None}
            if not trends:
                continue
            chi2 = float(sum(t["chi2"] for t in trends.values()))
            dof = int(sum(t["dof"] for t in trends.values()))
            if dof == 0:
                continue
            ss = sum(t["ss"] for t in trends.values())
            rows[key] = {
                "chi2": chi2, "dof": dof, "p_value": float(stats.chi2.sf(chi2, dof)),
                "share": float(sum(t["ss_means"] for t in trends.values()) / ss) if ss > 0 else 0.0,
                "legs_significant": sorted(leg for leg, t in trends.items() if t["p_value"] < alpha),
                "n_legs": len(trends),
                "min_bins": int(min(len(t["mean"]) for t in trends.values())),
                "range": [float(min(t["mean"].min() for t in trends.values())),
                          float(max(t["mean"].max() for t in trends.values()))],
                "trends": trends,
            }  # fmt: skip
        if step == 0:
            screened = {k: {n: v for n, v in row.items() if n != "trends"} for k, row in rows.items()}
        named = [k for k, row in rows.items()
                 if row["p_value"] < bound and row["share"] >= min_share and row["min_bins"] >= MIN_BINS]
        if not named:
            break
        key = max(named, key=lambda k: rows[k]["share"])
        row = rows.pop(key)
        quiet = _side(legs, key, {leg: ~L["twitch"] for leg, L in legs.items()})
        during = _side(legs, key, {leg: L["twitch"] for leg, L in legs.items()})
        side = _which_side(quiet, during, bound)
        hint = KIND_HINTS[key].get(side) if side in ("passive", "active") else None
        found.append({
            "feature": key, **{n: v for n, v in row.items() if n != "trends"},
            "quiet": quiet, "during_twitches": during, "side": side, "hint": hint,
            "pooled": _pooled(legs, key),
        })  # fmt: skip
        for leg, t in row["trends"].items():  # take the named trend out before looking further
            L = legs[leg]
            L["residual"] = _subtract_bins(L["residual"], L["features"][key], L["mask"], t)
        remaining.remove(key)
    locked = []
    for leg, r in residuals.items():
        if not R.has_pulses(r["stimulation"]):
            continue  # a pendulum test: nothing to correlate with
        cc = R.ccf(r["residual"], r["stimulation"], r["sample_mask"])
        if R._significant_lags(cc, alpha)[0]:
            locked.append(leg)
    return {
        "found": found, "screened": screened, "offset": offset, "alpha": alpha, "min_share": min_share,
        "twitch_locked": {"legs": locked, "n_legs": len(residuals),
                          "flagged": len(locked) > len(residuals) / 2, "hint": TWITCH_LOCKED_HINT},
        "response_samples": int(response_samples),
    }  # fmt: skip


def _offsets(legs: dict, pick) -> dict:
    """The residual's mean per leg on the samples ``pick(L)``, combined: χ² = Σ (mean/se)² on as many
    degrees of freedom as legs (se allowing for the autocorrelation, as in :func:`binned_trend`)."""
    means, chi2, dof, n, ss = [], 0.0, 0, 0, 0.0
    for L in legs.values():
        m = L["mask"] & pick(L)
        if int(m.sum()) < MIN_SIDE_SAMPLES:
            continue
        t = R.binned_trend(L["residual"], np.zeros(L["residual"].size), m)  # one bin: the mean and its se
        means.append(float(t["mean"][0]))
        chi2 += float((t["mean"][0] / t["se"][0]) ** 2)
        dof += 1
        n += int(t["count"][0])
        ss += float(t["count"][0] * t["mean"][0] ** 2)
    if not dof:
        return {"judged": False, "n": n}
    return {"judged": True, "n": n, "chi2": chi2, "dof": dof, "p_value": float(stats.chi2.sf(chi2, dof)),
            "amplitude": float(np.sqrt(ss / n)), "means": means}


def _offset(legs: dict, bound: float, min_share: float) -> dict:
    """Whether the residual's mean is off zero (a constant the model lacks), and where: between
    twitches as during them (passive, or the sensors) or during twitches only (the twitch's size)."""
    all_ = _offsets(legs, lambda L: np.ones_like(L["mask"]))
    if not all_["judged"]:
        return {"found": False}
    ss = sum(float(np.nansum(np.where(L["mask"], L["residual"], np.nan) ** 2)) for L in legs.values())
    share = all_["amplitude"] ** 2 * all_["n"] / ss if ss > 0 else 0.0
    quiet = _offsets(legs, lambda L: ~L["twitch"])
    during = _offsets(legs, lambda L: L["twitch"])
    side = _which_side(quiet, during, bound)
    hint = OFFSET_HINTS.get(side)
    return {"found": bool(all_["p_value"] < bound and share >= min_share), "share": float(share),
            "chi2": all_["chi2"], "dof": all_["dof"], "p_value": all_["p_value"], "means": all_["means"],
            "quiet": quiet, "during_twitches": during, "side": side, "hint": hint}


def _which_side(quiet: dict, during: dict, bound: float) -> str:
    """'passive', 'active', or 'unknown' (a side with too few samples) of a named feature."""
    if not quiet["judged"] and during["judged"]:
        return "unknown"  # no quiet samples (stimulation throughout)
    if quiet["judged"] and not during["judged"]:
        return "passive"  # no twitches at all: it can only be passive
    if not quiet["judged"]:
        return "unknown"
    if quiet["p_value"] < bound and quiet["amplitude"] >= PASSIVE_RATIO * during["amplitude"]:
        return "passive"
    if during["p_value"] < bound:
        return "active"
    return "unknown"


def _pooled(legs: dict, key: str) -> dict:
    """Bin means ± se of the current residual against ``key``, legs pooled, quiet and during twitches
    (for :func:`plot_structure`)."""
    out = {}
    for side, pick in (("quiet", lambda L: ~L["twitch"]), ("during twitches", lambda L: L["twitch"])):
        r = np.concatenate([L["residual"] for L in legs.values()])
        f = np.concatenate([L["features"][key] for L in legs.values()])
        m = np.concatenate([L["mask"] & pick(L) for L in legs.values()])
        t = _trend(r, f, m)
        if t is not None and int(np.sum(t["count"])) >= MIN_SIDE_SAMPLES:
            out[side] = {"centre": t["centre"].tolist(), "mean": t["mean"].tolist(), "se": t["se"].tolist()}
    return out


def _fmt_p(p: float) -> str:
    if p < 1e-300:  # below what a double's χ² tail resolves
        return "p < 1e-300"
    return f"p = {p:.1e}" if p < 0.001 else f"p = {p:.3f}"


#: How the diagnosis's sentence opens what :func:`structure_sentence` found.
NO_CANDIDATE_LEAD = "The residuals still carry structure that no candidate describes"


def structure_sentence(structure: dict, lead: str = NO_CANDIDATE_LEAD) -> str:
    """What :func:`residual_structure` found, in words, after ``lead``; empty when nothing stands out."""
    sides = {"passive": "as much between twitches as during them", "active": "during twitches, not between them",
             "unknown": "(quiet and twitch samples could not be told apart)"}
    parts = []
    for f in structure["found"]:
        words = R.FEATURE_WORDS.get(f["feature"], (f["feature"], ""))[0]
        lo, hi = f["range"]
        where = sides[f["side"]]
        if not f["during_twitches"]["judged"] and f["quiet"]["judged"]:
            where = "without stimulation (there are no twitches to compare with)"
        text = (f"they change with the {words} ({100 * f['share']:.1f} % of the residual's variance; bin means "
                f"from {R._fmt_num(lo)} to {R._fmt_num(hi)} deg/s²; χ²({f['dof']}) = {f['chi2']:.0f}, "
                f"{_fmt_p(f['p_value'])}, significant in {len(f['legs_significant'])} of {f['n_legs']} legs), {where}")
        parts.append(text + (f": {f['hint']}" if f["hint"] else ""))
    off = structure.get("offset", {})
    if off.get("found"):
        text = (f"they are off zero by a constant (mean {R._fmt_num(float(np.mean(off['means'])))} deg/s², "
                f"{100 * off['share']:.1f} % of the residual's variance; χ²({off['dof']}) = {off['chi2']:.0f}, "
                f"{_fmt_p(off['p_value'])}), {sides[off['side']]}")
        parts.append(text + (f": {off['hint']}" if off["hint"] else ""))
    locked = structure["twitch_locked"]
    if locked["flagged"]:
        parts.append(f"they correlate with the stimulation at fixed lags in {len(locked['legs'])} of "
                     f"{locked['n_legs']} legs: {locked['hint']}")
    if not parts:
        return ""
    return (f"{lead}: " + "; ".join(parts) + ". An effect for each can be written and added (docs/models.md, "
            "'Writing an effect'), then screened as a candidate.")
