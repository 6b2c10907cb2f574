"""A fit as a file: arviz InferenceData with everything needed to use it later.

``DIR/fit.nc`` holds the posterior (hierarchical parameters, leg and subject
values, per-leg noise, ``delay_logp`` = log P(d | θ, data) per draw and the
drawn ``delay``), ``log_likelihood`` (``acceleration_segment``) per leg and 1-s segment (the PSIS-LOO
unit, see :mod:`quadshank.model._likelihood`), ``observed_data`` (acceleration),
``constant_data`` (angle, velocity, stimulation, sample mask), ``sample_stats``
and, as the attribute ``quadshank_model``, the model's description (JSON).
``DIR/summary.json`` condenses it.  Both are written atomically, fit.nc
first and summary.json last; summary.json is removed before a new fit starts,
so a folder whose fit was interrupted never looks complete.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import warnings
from pathlib import Path
from typing import ClassVar

import arviz as az
import jax.numpy as jnp
import numpy as np
from scipy.stats import rankdata

from ..common._io import atomic_path
from ..common._provenance import code_provenance
from ..common._random import jax_key, numpy_rng
from ..common._results import Result
from ..data._paper import SAMPLING_PERIOD_S
from ..model._effects import AngleDelay, get_effect
from ..model._plugins import effect_origin, ensure_effects
from ..model._likelihood import N_DELAYS, LikelihoodData
from ..model._model import Model
from ._draws import (
    hard_step,
    hyper_draws,
    pointwise_loglik,
    sample_delays,
    sample_step_states,
)
from ._nuts import FitSettings, chain_method
from ._priors import NOISE_PARAMS, SIGMA_UNITS, STIFFNESS_SITE, model_params, step_param
from ._summaries import INTERVAL, THRESHOLDS, interval, pooled_draws

__all__ = [
    "check_fit_files",
    "to_inference_data",
    "diagnose_sampling",
    "delay_splits",
    "delay_missed",
    "weakly_informed",
    "fit_summary",
    "save_fit",
    "load_fit",
    "read_summary",
    "FitFolderError",
    "FitResult",
    "THRESHOLDS",
]

#: Two chains whose P(d) of one leg lie further apart than this (total variation) sample different delays.
DELAY_SPLIT_TV = 0.5
#: A delay the per-delay Laplace evidence gives at least the first weight, and the chains' pooled
#: P(d) less than the second, is a delay the chains never visited (a warning: see diagnose_sampling).
DELAY_MISSED = (0.1, 0.01)


@dataclasses.dataclass
class FitResult(Result):
    """A hierarchical fit's summary: per leg the delay posterior and each parameter's median and
    90 % interval, the sampler's checks, and how the fit was made.  ``DIR/summary.json`` of a fit
    folder is its JSON form; the draws themselves are in ``DIR/fit.nc`` (:func:`load_fit`)."""

    KIND: ClassVar[str] = "fit"

    model: str
    effects: list
    trials: list
    legs: dict  # leg -> subject, delay_posterior, delay_mode_samples, params (and delay_evidence, delay_angle)
    diagnostics: dict
    banner: str | None  # the failed checks in one line, None when the fit passed them
    settings: dict
    chain_method: str
    sampling_period_s: float
    interval: list
    code: dict  # the package's version and source fingerprint
    delay_angle_population: dict | None = None
    data: str | None = None  # where the data came from, for the commands that read the fit later
    sampling_seconds: float | None = None
    delay_evidence_seconds: float | None = None
    screen_restarted: dict | None = None
    fit_id: str | None = None  # also in fit.nc: the two files of one fit carry the same
    data_fingerprint: str | None = None  # of the legs and trials fitted (Cohort.fingerprint)
    derived_signals: dict | None = None  # signals derived from the angle (no sensor): how, and for which trials
    uninformed: dict | None = None  # leg -> pulses, and the active parameters its own data hardly inform
    effect_origins: dict | None = None  # a user's effect -> its module, file and source hash (not built-ins)
    target: dict | None = None  # drawn to a target ESS: how the blocks ended (inference.target_status)
    likelihood: str = "acceleration"  # what the likelihood compared (model._likelihood.OBJECTIVES)
    charge_scale: dict | None = None  # leg -> the charge its levels are relative to (legs read from a stimulator's columns)

    @property
    def ok(self) -> bool:
        """Whether the fit passed its checks."""
        return bool(self.diagnostics.get("ok"))


class FitFolderError(FileNotFoundError):
    """A folder without a complete fit."""


def to_inference_data(
    mcmc, model: Model, data: LikelihoodData, settings: FitSettings, delay_source=None, log_delay_prior=None,
    delay_evidence=None,
):
    """InferenceData of a finished run, pointwise log-likelihood included.

    ``delay_source`` and ``log_delay_prior`` record where the delay prior came from
    (None: uniform on 0 … 10 samples).  ``delay_evidence``: (legs, 11) P(d | data) from
    one Laplace approximation per delay (:func:`quadshank.inference._screen.delay_evidence`),
    kept as ``constant_data.delay_evidence`` for :func:`delay_missed`.
    """

    samples = {k: np.asarray(v) for k, v in mcmc.get_samples(group_by_chain=True).items()}
    samples.update(hyper_draws(model, samples, data.leg_subject, len(data.subjects), settings.seed))
    chains, draws = samples["delay_logp"].shape[:2]
    flat = {k: v.reshape(chains * draws, *v.shape[2:]) for k, v in samples.items()}
    step = step_param(model, data)
    if step is None:
        joint = samples.get("delay_shift_logp", samples["delay_logp"])
        delays, shifts = sample_delays(joint.reshape(chains * draws, *joint.shape[2:]), jax_key(settings.seed, "delays"))
    else:  # the threshold was summed out: drawn with (d, shift) from their joint conditional
        delays, shifts, threshold = sample_step_states(model, data, flat, log_delay_prior, settings.seed)
        flat[step.name] = threshold
        samples[step.name] = threshold.reshape(chains, draws, data.n_legs)
        model = hard_step(model)
    ll = pointwise_loglik(model, data, flat, delays, shifts)
    samples["delay"] = delays.reshape(chains, draws, data.n_legs)
    if data.max_shift:
        samples["delay_shift"] = shifts.reshape(chains, draws, data.n_legs)

    legs = list(data.legs)
    subjects = list(data.subjects)
    coords = {"leg": legs, "subject": subjects, "delay_samples": np.arange(N_DELAYS)}
    dims = {"delay_logp": ["leg", "delay_samples"], "delay": ["leg"], "sigma": ["leg"], "nu": ["leg"], STIFFNESS_SITE: ["leg"]}
    if data.max_shift:
        coords["shift_samples"] = np.arange(data.max_shift + 1)
        dims["delay_shift_logp"] = ["leg", "delay_samples", "shift_samples"]
        dims["delay_shift"] = ["leg"]
    for p in model_params(model):
        comp = [f"{p.name}_dim"] if p.shape else []
        if p.shape:
            coords[f"{p.name}_dim"] = np.arange(p.shape[0])
        dims[p.name] = ["leg", *comp]
        dims[f"{p.name}_subject"] = ["subject", *comp]
        if p.level in ("subject", "leg"):
            dims[f"{p.name}_x_subject"] = ["subject", *comp]
            dims[f"{p.name}_z_subject"] = ["subject", *comp]
        if p.level == "leg":
            dims[f"{p.name}_z_leg"] = ["leg", *comp]
            dims[f"{p.name}_s_leg"] = [*comp, "leg"]
    extra = mcmc.get_extra_fields(group_by_chain=True)
    stats = {"diverging": np.asarray(extra["diverging"]), "energy": np.asarray(extra["energy"])}
    if "num_steps" in extra:
        stats["n_steps"] = np.asarray(extra["num_steps"])
    if "mode_jump" in extra:  # jumps between delay modes taken after the draw's transition
        stats["mode_jump"] = np.asarray(extra["mode_jump"]).astype(np.int32)
    n = data.angle.shape[1]
    coords["sample"] = np.arange(n)
    coords["segment"] = np.arange(data.n_segments)
    idata = az.from_dict(
        posterior=samples,
        sample_stats=stats,
        # one value per leg and 1-s segment of the observed acceleration
        log_likelihood={"acceleration_segment": ll.reshape(chains, draws, data.n_legs, data.n_segments)},
        observed_data={"acceleration": data.acceleration},
        constant_data={
            "angle": data.angle,
            "velocity": data.velocity,
            "stimulation": data.stimulation,
            "sample_mask": data.sample_mask.astype(np.int8),
            "segment_mask": data.segment_mask.astype(np.int8),
            **({} if delay_evidence is None else {"delay_evidence": np.asarray(delay_evidence, np.float64)}),
        },
        coords=coords,
        dims={
            **dims,
            "acceleration_segment": ["leg", "segment"],
            "acceleration": ["leg", "sample"],
            "angle": ["leg", "sample"],
            "velocity": ["leg", "sample"],
            "stimulation": ["leg", "sample"],
            "sample_mask": ["leg", "sample"],
            "segment_mask": ["leg", "segment"],
            "delay_evidence": ["leg", "delay_samples"],
        },
    )
    desc = describe_fit(model, data, settings)
    if step is not None:
        desc["summed_out"] = [step.name]  # drawn afterwards, under the hard step (see model_from_description)
    desc["delay_prior"] = {
        "source": delay_source or "uniform",
        "probabilities": None if log_delay_prior is None else np.exp(np.asarray(log_delay_prior, np.float64)).round(6).tolist(),
    }
    idata.posterior.attrs["quadshank_model"] = to_json(desc)
    return idata


def sampled_vars(idata) -> list[str]:
    """Variables checked for convergence: everything sampled or derived, but the discrete delay."""
    return [v for v in idata.posterior.data_vars if v not in ("delay", "delay_logp", "delay_shift", "delay_shift_logp")]


def delay_splits(idata) -> dict[str, list[int]]:
    """Legs whose chains settled at different delays: ``{leg: each chain's most probable delay}``.

    A chain's P(d) is its mean of P(d | θ, data) over its draws.  The delay is summed
    out, but θ moves with it (model 3 learns d through the states at which its gains
    are read), so a posterior can have one mode of θ per delay, which NUTS, moving θ
    continuously, rarely crosses.  Chains whose P(d) lie more than
    :data:`DELAY_SPLIT_TV` apart in total variation are in different modes, and the
    fit's P(d) is then an accident of where the chains started.
    """
    post = idata.posterior
    if "delay_logp" not in post.data_vars or post.sizes["chain"] < 2:
        return {}
    p = np.exp(np.asarray(post["delay_logp"], np.float64)).mean(axis=1)  # (chain, leg, D)
    tv = 0.5 * np.abs(p[:, None] - p[None, :]).sum(axis=-1).max(axis=(0, 1))  # (leg,)
    legs = [str(x) for x in post["leg"].values]
    return {leg: [int(m) for m in p[:, i].argmax(axis=-1)] for i, leg in enumerate(legs) if tv[i] > DELAY_SPLIT_TV}


def stored_delay_evidence(idata) -> np.ndarray | None:
    """(legs, 11) per-delay Laplace P(d) kept in the fit, or None (fits made without it, or before it)."""
    if "constant_data" not in idata.groups() or "delay_evidence" not in idata.constant_data:
        return None
    return np.asarray(idata.constant_data["delay_evidence"], np.float64)


def delay_missed(idata) -> dict[str, dict[int, list[float]]]:
    """Delays of a leg that hold weight by the per-delay Laplace evidence but that no chain
    visited: ``{leg: {d: [Laplace P(d), the chains' P(d)]}}`` (see :data:`DELAY_MISSED`).

    Chains that agree can still all sit in one mode of the delay, which is what
    :func:`delay_splits` cannot see: the evidence, one mode per delay, can.
    """
    ev = stored_delay_evidence(idata)  # (leg, D)
    if ev is None:
        return {}
    chains = np.exp(np.asarray(idata.posterior["delay_logp"], np.float64)).mean(axis=(0, 1))  # (leg, D)
    legs = [str(x) for x in idata.posterior["leg"].values]
    lo_ev, hi_chain = DELAY_MISSED
    out = {}
    for i, leg in enumerate(legs):
        missed = np.flatnonzero((ev[i] >= lo_ev) & (chains[i] < hi_chain))
        if missed.size:
            out[leg] = {int(d): [round(float(ev[i, d]), 3), round(float(chains[i, d]), 3)] for d in missed}
    return out


#: A leg's parameter whose posterior sd is at least this many of its prior's scale (the sd of its
#: standardised site ``NAME_s_leg``) is barely informed by the data: a quarter of the prior's
#: precision or less.  In the demo's fit (model3s, two legs of the simulated cohort) none lies above 0.1.
WEAK_SD = 0.5


def _leg_sites(post):
    """A posterior's standardised leg sites ``NAME_s_leg``: ``(NAME, its values)``."""
    for v in post.data_vars:
        if str(v).endswith("_s_leg") and "leg" in post[v].dims:
            yield str(v)[: -len("_s_leg")], post[v]


def _component(name: str, index: tuple) -> str:
    """A parameter's component as the report names it, counted from 1: ``a[2]`` (``name`` for a scalar)."""
    return name + "".join(f"[{i + 1}]" for i in index)


def _in_leg_order(post, per_leg: dict) -> dict:
    """``per_leg`` with its legs in the posterior's order."""
    order = [str(leg) for leg in post["leg"].values] if "leg" in post.coords else sorted(per_leg)
    return {leg: per_leg[leg] for leg in order if leg in per_leg}


def weakly_informed(idata) -> dict[str, dict[str, float]]:
    """Legs' parameters the data barely inform: ``{leg: {parameter: posterior sd in prior scales}}``.

    A leg's parameter θ = loc + scale·z (z on the log scale for a lognormal prior) is sampled as
    its standardised ``z``, whose prior sd is 1 at the population's level (wider with the spreads
    between subjects and legs).  Where z's posterior sd is :data:`WEAK_SD` or more, θ's value is
    mostly the prior's and the other legs', not the leg's data's, and NUTS moves through such a
    wide, often curved stretch slowly (the exponential elasticity's k1 and k2 on recordings
    that never reach deep flexion, say).  A vector parameter's component is named as in the
    report, counted from 1: ``a[2]``.
    """
    post = idata.posterior
    out: dict[str, dict[str, float]] = {}
    for name, site in _leg_sites(post):
        sd = site.std(dim=("chain", "draw"))
        others = [d for d in sd.dims if d != "leg"]
        sd = sd.transpose("leg", *others)
        for leg, row in zip(sd["leg"].values, np.asarray(sd, np.float64)):
            for index, value in np.ndenumerate(row):
                if np.isfinite(value) and value >= WEAK_SD:
                    out.setdefault(str(leg), {})[_component(name, index)] = round(float(value), 2)
    return _in_leg_order(post, out)


#: Where a fit's divergent transitions are located: a parameter is named when every divergent draw
#: lies in the same outer tail of the leg's draws, below this quantile or above one minus it, and
#: there are at least :data:`DIVERGENT_MIN` of them.  Divergent draws that fall anywhere do so with
#: probability 2·0.1ⁿ per parameter, at most 0.002 for n ≥ 3.
DIVERGENT_TAIL = 0.1
DIVERGENT_MIN = 3


def divergence_location(idata) -> dict[str, dict[str, float]]:
    """Where the divergent transitions lie: ``{leg: {parameter: q}}``, q the divergent draws' mean
    quantile among all the leg's draws of that parameter (near 0: where it is low; near 1: high),
    for the parameters whose divergent draws all lie in one outer tail (:data:`DIVERGENT_TAIL`;
    at least :data:`DIVERGENT_MIN` divergent draws, else nothing is named).

    Divergences gathered at one end of a parameter's posterior mark where the posterior bends or
    narrows (the end of a ridge, a funnel), a geometry that shorter steps seldom mend; divergences
    spread over the posterior are rather a step too long everywhere.  Components are named as in
    :func:`weakly_informed`; legs and parameters in the posterior's order, the most extreme first."""
    diverging = np.asarray(idata.sample_stats["diverging"], bool).reshape(-1)
    if diverging.sum() < DIVERGENT_MIN:
        return {}
    post = idata.posterior
    out: dict[str, dict[str, float]] = {}
    for name, site in _leg_sites(post):
        da = site.transpose("chain", "draw", "leg", ...)
        a = np.asarray(da, np.float64).reshape(diverging.size, da.sizes["leg"], -1)  # (draws, legs, components)
        q = (rankdata(a, axis=0) - 0.5) / a.shape[0]  # each draw's quantile among the leg's draws (ties: mean rank)
        at = q[diverging]  # (divergent draws, legs, components)
        low, high = (at <= DIVERGENT_TAIL).all(axis=0), (at >= 1.0 - DIVERGENT_TAIL).all(axis=0)
        for (i, c) in zip(*np.nonzero(low | high)):
            index = np.unravel_index(c, da.shape[3:]) if da.ndim > 3 else ()
            out.setdefault(str(da["leg"].values[i]), {})[_component(name, index)] = round(float(at[:, i, c].mean()), 3)
    extreme_first = {leg: dict(sorted(ps.items(), key=lambda kv: -abs(kv[1] - 0.5))) for leg, ps in out.items()}
    return _in_leg_order(post, extreme_first)


def located_words(where: dict[str, dict[str, float]]) -> str:
    """"JM-left's k1 is high (0.97) and k2 low (0.03)": :func:`divergence_location` in words."""

    def leg_words(leg, params):
        said = [f"{p} {'high' if q > 0.5 else 'low'} ({q:.2f})" for p, q in params.items()]
        said[0] = said[0].replace(" ", " is ", 1)
        return f"{leg}'s " + (said[0] if len(said) == 1 else ", ".join(said[:-1]) + " and " + said[-1])

    return "; ".join(leg_words(leg, params) for leg, params in where.items())


def _weak_lagging(worst: dict | None, weak: dict) -> str | None:
    """``"k1 of AA-left"`` where a failing check's worst entry is a parameter the data barely
    inform (of that leg, or of its subject where the entry is a subject's value)."""
    if not worst or not worst.get("at"):
        return None
    base = worst["variable"].removesuffix("_s_leg").removesuffix("_subject")
    at = [a.strip() for a in worst["at"].split(",")]
    for leg, params in weak.items():
        if any(p.split("[")[0] == base for p in params) and (leg in at or leg.rsplit("-", 1)[0] in at):
            return f"{base} of {leg}"
    return None


#: P(d) at the longest delay considered from which a fit's summary warns that the delay may lie beyond it.
DELAY_EDGE_P = 0.2


def delay_at_edge(idata, at: int = -1) -> dict[str, float]:
    """The legs whose delay posterior holds at least :data:`DELAY_EDGE_P` at the longest delay
    considered (``at=0``: at no delay, the shortest), with that probability (none for the
    pendulum alone, which has no delay)."""
    attrs = idata.posterior.attrs
    effects = from_json(attrs["quadshank_model"])["effects"] if "quadshank_model" in attrs else ()
    if "no_muscle" in effects or "delay_logp" not in idata.posterior:
        return {}
    p = np.exp(np.asarray(idata.posterior["delay_logp"], np.float64)).mean(axis=(0, 1))  # (leg, D)
    legs = [str(x) for x in idata.posterior["leg"].values]
    return {leg: round(float(p[i, at]), 3) for i, leg in enumerate(legs) if p[i, at] >= DELAY_EDGE_P}


def _where(ds, largest: bool) -> dict | None:
    """The entry of ``ds`` (one value per variable and coordinate, as arviz's R-hat or ESS) that is
    largest (or smallest): ``{"variable", "at", "value"}``, ``at`` naming its coordinates (a leg,
    say); None where nothing is finite.  A failing fit then says which parameter of which leg
    holds it back, not only by how much."""
    best = None
    for v in ds.data_vars:
        if (str(v).endswith("_s_leg") and str(v)[: -len("_s_leg")] in ds.data_vars) or v == STIFFNESS_SITE:
            continue  # a parameter's standardised site, or the stiffness G′ is sampled by: the parameter is named
        a = np.asarray(ds[v], np.float64)
        if not np.isfinite(a).any():
            continue
        flat = np.where(np.isfinite(a), a, -np.inf if largest else np.inf).ravel()
        i = int(np.argmax(flat) if largest else np.argmin(flat))
        value = float(flat[i])
        if best is None or (value > best["value"] if largest else value < best["value"]):
            index = np.unravel_index(i, a.shape) if a.ndim else ()
            at = ", ".join(str(ds[v][dim].values[k]) if dim in ds[v].coords else f"{dim} {k}"
                           for dim, k in zip(ds[v].dims, index))
            best = {"variable": str(v), "at": at, "value": value}
    return best


def _named(w: dict | None) -> str:
    """" (gain of OT-left)": where :func:`_where` found the worst value, for a problem's text."""
    return "" if not w else f" ({w['variable']}{' of ' + w['at'] if w['at'] else ''})"


def diagnose_sampling(idata) -> dict:
    """R-hat, bulk and tail ESS, divergences, E-BFMI against :data:`THRESHOLDS`, with advice."""

    names = sampled_vars(idata)
    post = idata.posterior[names]
    chains = idata.posterior.sizes["chain"]
    ess_bulk = az.ess(post, method="bulk")
    ess_tail = az.ess(post, method="tail")

    def extreme(ds, fn):
        vals = [float(fn(np.asarray(ds[v]))) for v in ds.data_vars if np.isfinite(np.asarray(ds[v])).any()]
        return fn(np.array(vals)) if vals else float("nan")

    # arviz logs a shape warning for R-hat of one chain, which has none
    rhat = az.rhat(post) if chains > 1 else None
    rhat_max = float(extreme(rhat, np.nanmax)) if chains > 1 else float("nan")
    ess_bulk_min = float(extreme(ess_bulk, np.nanmin))
    ess_tail_min = float(extreme(ess_tail, np.nanmin))
    worst = {"rhat": None if rhat is None else _where(rhat, largest=True), "ess_bulk": _where(ess_bulk, largest=False),
             "ess_tail": _where(ess_tail, largest=False)}
    divergences = int(np.asarray(idata.sample_stats["diverging"]).sum())
    bfmi = np.atleast_1d(az.bfmi(idata))
    bfmi_min = float(np.min(bfmi))
    ess_needed = THRESHOLDS["ess_per_chain"] * chains
    problems, advice = [], []
    if chains < 2:
        problems.append("one chain: R-hat cannot be computed")
        advice.append("run at least 2 chains (--chains 4)")
    elif not rhat_max < THRESHOLDS["rhat_max"]:
        problems.append(f"R-hat {rhat_max:.3f} ≥ {THRESHOLDS['rhat_max']}{_named(worst['rhat'])}: chains disagree")
        advice.append("run longer (--warmup, --draws) or check for several posterior modes")
    splits = delay_splits(idata)
    # jumps between delay modes taken after the transitions (None: the chains did not jump)
    mode_jumps = int(np.asarray(idata.sample_stats["mode_jump"]).sum()) if "mode_jump" in idata.sample_stats else None
    if splits:
        where = "; ".join(f"{leg} ({', '.join(f'chain {c}: {d}' for c, d in enumerate(modes))})" for leg, modes in splits.items())
        problems.append(f"chains settled at different delays [samples]: {where}")
        if mode_jumps:
            advice.append(
                f"the chains jump between the delays' modes ({mode_jumps} jumps in the draws) but have not yet mixed: "
                "draw more (--draws, or --target-ess), or give the delay a prior from another fit (--delay-from FITDIR)"
            )
        else:
            advice.append(
                "the delay has modes the sampler does not cross: fit more data (longer or more trials), or give "
                "the delay a prior from another fit (--delay-from FITDIR; the paper took d from model 2)"
            )
    # a warning, not a problem: the evidence is of each leg alone under the population prior,
    # and the pooled posterior of a leg (its prior narrowed by the other legs) can move mass
    # between neighbouring delays
    cautions = []
    missed = delay_missed(idata)
    if missed:
        where = "; ".join(
            f"{leg} (" + ", ".join(f"d = {d}: {e:.2f} by the evidence, {c:.2f} in the chains" for d, (e, c) in ds.items()) + ")"
            for leg, ds in missed.items()
        )
        cautions.append(
            f"the chains never visited a delay that a Laplace approximation per delay, of the leg alone, weighs: {where}. "
            "Either the pooling across legs moved that mass or the chains sit in one of the delay's modes; "
            "a fit of the leg alone (--legs) or more data tells which, and --delay-from FITDIR fixes the delay"
        )
    edge = delay_at_edge(idata)
    if edge:
        attrs = idata.posterior.attrs
        period = from_json(attrs["quadshank_model"]).get("sampling_period_s", SAMPLING_PERIOD_S) if "quadshank_model" in attrs \
            else SAMPLING_PERIOD_S
        longest = N_DELAYS - 1
        ms = longest * period * 1e3
        cautions.append(
            f"the delay's posterior holds at least {DELAY_EDGE_P:g} at the longest delay considered, {longest} samples "
            f"({ms:.0f} ms): " + ", ".join(f"{leg} {p:.2f}" for leg, p in edge.items()) + ". The muscle's delay may be "
            "longer than that, or the model's twitch shorter than the recorded one, so that its delay moves towards "
            "the twitch's middle (model 3's twitch is a single sample; model3s's is longer). `quadshank identify` "
            "gives the delay at the twitch's onset"
            + ("; resampled to 10 ms (`quadshank convert DATA data.nc --resample 0.01`) the delays considered reach "
               "100 ms" if period < SAMPLING_PERIOD_S * (1 - 1e-6) else "")
        )
    zero = delay_at_edge(idata, at=0)
    if zero:
        cautions.append(
            f"the delay's posterior holds at least {DELAY_EDGE_P:g} at no delay (0 samples): "
            + ", ".join(f"{leg} {p:.2f}" for leg, p in zero.items()) + ". No muscle's twitch starts with its pulse "
            "(25-50 ms after it): the model's twitch is then shaped otherwise than the recorded one, and its d is where "
            "the model's twitch fits best, not the onset (model 3's twitch is a single sample). `quadshank identify` "
            "gives the delay at the twitch's onset, and model2 or model3s (`--model`) a twitch with a shape"
        )
    weak = weakly_informed(idata)
    if weak:
        cautions.append(
            "the data barely inform "
            + "; ".join(f"{leg}'s {', '.join(f'{p} ({sd:.2g})' for p, sd in params.items())}" for leg, params in weak.items())
            + f": in parentheses, each posterior's sd in units of its prior's scale ({WEAK_SD:g} or more; the spreads "
            "between subjects and legs let it exceed 1), so its value is mostly the prior's and the other legs', not "
            "an estimate from the leg's data. Recordings that reach where such a parameter acts inform it (deep "
            "flexion for the elasticity's k1 and k2)"
        )
    if not ess_bulk_min >= ess_needed:
        problems.append(f"bulk ESS {ess_bulk_min:.0f}{_named(worst['ess_bulk'])} < {ess_needed} "
                        f"({THRESHOLDS['ess_per_chain']} per chain)")
        advice.append("draw more (--draws)")
    if not ess_tail_min >= ess_needed:
        problems.append(f"tail ESS {ess_tail_min:.0f}{_named(worst['ess_tail'])} < {ess_needed}: the 90 % intervals "
                        "are unreliable")
        advice.append("draw more (--draws)")
    located = divergence_location(idata)
    if divergences > THRESHOLDS["divergences"]:
        problems.append(f"{divergences} divergent transitions: the sampler missed part of the posterior")
        if located:
            advice.append(
                f"the divergent transitions all lie where {located_words(located)} (in parentheses, their mean quantile "
                "among the draws): the posterior bends or narrows at that end, which smaller steps seldom mend. "
                "Recordings that inform those parameters do; --target-accept 0.95 may lessen them")
        else:
            advice.append("raise the target acceptance (--target-accept 0.95) or lengthen the warm-up (--warmup)")
    if not bfmi_min > THRESHOLDS["bfmi_min"]:
        problems.append(f"E-BFMI {bfmi_min:.2f} ≤ {THRESHOLDS['bfmi_min']}: poor exploration of the energy")
        advice.append("lengthen the warm-up (--warmup) and let it adapt the metric (--adapt-metric), or fit more data")
    lagging = next(filter(None, (_weak_lagging(w, weak) for w in worst.values())), None) if problems else None
    if lagging:  # the most specific advice comes first
        advice.insert(0, f"{lagging} holds the fit back and the data barely inform it: chains cross its wide posterior "
                      "slowly, so draw to an ESS (--target-ess 400 --time-limit SECONDS), or fit recordings that inform it")
    return {
        "ok": not problems,
        "rhat_max": rhat_max,
        "ess_bulk_min": ess_bulk_min,
        "ess_tail_min": ess_tail_min,
        "divergences": divergences,
        "bfmi_min": bfmi_min,
        "worst": worst,
        "delay_splits": splits,
        "delay_missed": missed,
        "delay_at_edge": edge,
        "delay_at_zero": zero,
        "weakly_informed": weak,
        "divergences_at": located,
        "mode_jumps": mode_jumps,
        "chains": int(chains),
        "draws": int(idata.posterior.sizes["draw"]),
        "thresholds": {**THRESHOLDS, "ess_min": ess_needed},
        "problems": problems,
        "advice": list(dict.fromkeys(advice)),
        "warnings": cautions,
    }


#: Knee angles of the delay–angle curve [deg]: the operating range of section II.
ANGLE_GRID = np.arange(-40.0, 60.5, 1.0)
#: A threshold counts as a change only where it splits a leg's pulses, between these quantiles of their angles.
SPLIT_QUANTILES = (0.05, 0.95)


def _leg_draws(idata, name: str, i: int) -> np.ndarray:
    return pooled_draws(idata.posterior, name)[:, i]


def delay_angle_curve(idata, i: int) -> np.ndarray:
    """Effective delay [samples] of pulses delivered at each ANGLE_GRID angle, per draw: d − shift·[φ < threshold]."""

    d = _leg_draws(idata, "delay", i).astype(float)
    shift = _leg_draws(idata, "delay_shift", i).astype(float)
    threshold = _leg_draws(idata, "threshold", i)
    w = np.asarray(AngleDelay(threshold=threshold[:, None], softness_deg=0.0).pulse_weight(ANGLE_GRID[None, :]), np.float64)
    return d[:, None] - shift[:, None] * w


def delay_angle_summary(idata, i: int, curve: np.ndarray) -> dict:
    """Whether the delay of leg i changes with angle, by how much, where, and the curve's band.

    ``change_probability`` is the posterior mean of P(shift ≥ 1 | θ, data) over the
    draws whose threshold splits the leg's pulses (between the SPLIT_QUANTILES of
    their angles): a shorter delay for no pulse, or for all of them, is no angle
    dependence.  ``threshold_deg`` is the threshold's interval over the draws with
    a change.  ``curve`` is the leg's :func:`delay_angle_curve`.
    """
    joint = np.exp(_leg_draws(idata, "delay_shift_logp", i))  # (draws, D, K + 1)
    p_shift = joint.sum(axis=1)  # (draws, K + 1)
    threshold = _leg_draws(idata, "threshold", i)
    stim = np.asarray(idata.constant_data["stimulation"])[i]
    angle = np.asarray(idata.constant_data["angle"])[i]
    mask = np.asarray(idata.constant_data["sample_mask"])[i].astype(bool)
    pulse_angles = angle[(stim > 0) & mask]
    lo, hi = np.quantile(pulse_angles, SPLIT_QUANTILES) if pulse_angles.size else (np.inf, -np.inf)
    splits = (threshold > lo) & (threshold < hi)
    change = float(np.mean(np.where(splits, 1.0 - p_shift[:, 0], 0.0)))
    shifted = _leg_draws(idata, "delay_shift", i) > 0
    with_change = threshold[shifted & splits]
    return {
        "change_probability": change,
        "shift_posterior": p_shift.mean(axis=0).tolist(),
        "threshold_deg": interval(with_change) if with_change.size else None,
        "pulse_angle_range_deg": [float(lo), float(hi)],
        "angle_deg": ANGLE_GRID.tolist(),
        **interval(curve),
    }


def fit_summary(idata) -> dict:
    """Per leg: delay posterior and each parameter's median and 90 % interval; diagnostics."""
    desc = from_json(idata.posterior.attrs["quadshank_model"])
    post = idata.posterior
    flat = {v: pooled_draws(post, v) for v in post.data_vars}
    delay_post = np.exp(flat["delay_logp"]).mean(axis=0)  # (legs, D)
    evidence = stored_delay_evidence(idata)
    curves = [delay_angle_curve(idata, i) for i in range(len(desc["legs"]))] if "delay_shift_logp" in flat else None
    legs = {}
    for i, leg in enumerate(desc["legs"]):
        params = {}
        for name, info in desc["params"].items():
            params[name] = {**interval(flat[name][:, i]), "units": info["units"]}
        for name, (units, _doc) in {k: (v["units"], v["doc"]) for k, v in desc["noise"].items()}.items():
            params[name] = {**interval(flat[name][:, i]), "units": units}
        probs = delay_post[i]
        legs[leg] = {
            "subject": desc["subjects"][desc["leg_subject"][i]],
            "delay_posterior": [float(p) for p in probs],
            "delay_mode_samples": int(np.argmax(probs)),
            "params": params,
        }
        if evidence is not None:
            legs[leg]["delay_evidence"] = [float(p) for p in evidence[i]]
        if curves:
            legs[leg]["delay_angle"] = delay_angle_summary(idata, i, curves[i])
    diag = diagnose_sampling(idata)
    extra = {}
    if curves:
        # the population curve: every leg's draws pooled
        extra["delay_angle_population"] = {"angle_deg": ANGLE_GRID.tolist(), **interval(np.concatenate(curves))}
    if desc.get("effect_origins"):
        extra["effect_origins"] = desc["effect_origins"]
    return {
        "model": desc["model"],
        "effects": desc["effects"],
        "trials": desc["trials"],
        "legs": legs,
        **extra,
        "diagnostics": diag,
        "banner": None if diag["ok"] else "FIT FAILED ITS CHECKS: " + "; ".join(diag["problems"]),
        "settings": desc["settings"],
        "likelihood": desc.get("likelihood", "acceleration"),
        "chain_method": desc.get("chain_method", desc["settings"].get("chain_method")),
        "sampling_period_s": desc.get("sampling_period_s", SAMPLING_PERIOD_S),
        "interval": list(INTERVAL),
    }


def _fit_id(idata) -> str:
    """A hash of the fit's model description and draws: the same fit, the same id."""
    h = hashlib.sha256(str(idata.posterior.attrs.get("quadshank_model", "")).encode())
    for name in sorted(idata.posterior.data_vars):
        h.update(name.encode())
        h.update(np.ascontiguousarray(idata.posterior[name].values).tobytes())
    return h.hexdigest()[:16]


def save_fit(idata, folder: str | os.PathLike, extra: dict | None = None, *, overwrite: bool = False) -> FitResult:
    """Write fit.nc then summary.json (with ``extra`` entries and ``code``, the package's version
    and source fingerprint, :func:`quadshank.common._provenance.code_provenance`) atomically; returns the
    :class:`FitResult`.  ``folder`` must be new or empty unless ``overwrite``: a fit saved into a
    folder that holds another fit, or a data folder, would replace or blur what is there."""
    if not hasattr(idata, "posterior"):
        raise TypeError(f"idata: give the fit's InferenceData (to_inference_data), not {type(idata).__name__}")
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise NotADirectoryError(f"{folder}: exists and is not a folder")
    if not overwrite and folder.is_dir() and any(not p.name.startswith(".") for p in folder.iterdir()):
        held = "a fit" if (folder / "fit.nc").exists() or (folder / "summary.json").exists() else "files"
        raise FileExistsError(f"{folder}: the folder already holds {held}; give a new folder, or overwrite=True to "
                              "write fit.nc and summary.json over those there")
    folder.mkdir(parents=True, exist_ok=True)
    fit_id = _fit_id(idata)
    idata.posterior.attrs["quadshank_fit_id"] = fit_id
    with atomic_path(folder / "fit.nc") as tmp:  # the draws first: nothing after this loses them
        idata.to_netcdf(tmp)
    result = FitResult(**fit_summary(idata), code=code_provenance(), fit_id=fit_id, **(extra or {}))
    result.write(folder)
    return result


def begin_fit(folder: str | os.PathLike) -> None:
    """Mark a folder as holding no complete fit (before sampling starts)."""
    (Path(folder) / "summary.json").unlink(missing_ok=True)


def _complete_fit(folder: str | os.PathLike) -> Path:
    """``folder`` as a Path, after checking that it holds a complete fit."""
    folder = Path(folder)
    if not (folder / "summary.json").exists() or not (folder / "fit.nc").exists():
        raise FitFolderError(f"{folder}: no complete fit here (fit.nc and summary.json are written by `quadshank fit`)")
    return folder


def read_summary(folder: str | os.PathLike) -> FitResult:
    """The :class:`FitResult` of a complete fit folder (its ``summary.json``)."""
    return FitResult.read(_complete_fit(folder))


def load_fit(folder: str | os.PathLike):
    """(InferenceData, Model without values, description) of a saved fit."""

    path = _complete_fit(folder) / "fit.nc"
    try:
        idata = az.from_netcdf(path)
        desc = from_json(idata.posterior.attrs["quadshank_model"])
    except Exception as exc:  # noqa: BLE001 - whatever a damaged or foreign file raises, it is not a fit
        raise FitFolderError(f"{path}: not a readable quadshank fit ({exc}); run `quadshank fit` again into "
                             f"{folder}") from None
    return idata, model_from_description(desc), desc


def check_fit_files(folder: str | os.PathLike, idata, summary: FitResult) -> None:
    """Refuse a fit folder whose ``fit.nc`` and ``summary.json`` come from different fits, or name
    different legs (an edited summary)."""
    nc_id = idata.posterior.attrs.get("quadshank_fit_id")
    if (nc_id or summary.fit_id) and nc_id != summary.fit_id:
        raise FitFolderError(
            f"{folder}: fit.nc and summary.json come from different fits (fit ids {nc_id or 'none'} and "
            f"{summary.fit_id or 'none'}); run `quadshank fit` again into this folder")
    nc_legs = [str(leg) for leg in idata.posterior["leg"].values] if "leg" in idata.posterior.coords else None
    if nc_legs is not None and summary.legs and sorted(summary.legs) != sorted(nc_legs):
        raise FitFolderError(
            f"{folder}: summary.json and fit.nc name different legs ({', '.join(summary.legs)} against "
            f"{', '.join(nc_legs)}); run `quadshank fit` again into this folder")


def posterior_models(idata, model: Model, leg: str, n_draws: int | None = None, seed: int = 0):
    """The model of one leg with leaves of shape (draws,), and those draws' delays."""

    post = idata.posterior
    i = list(post["leg"].values).index(leg)
    total = post.sizes["chain"] * post.sizes["draw"]
    idx = np.arange(total)
    if n_draws is not None and n_draws < total:
        idx = np.sort(numpy_rng(seed, "posterior draws").choice(total, n_draws, replace=False))
    values = {p.name: jnp.asarray(pooled_draws(post, p.name)[idx, i]) for p in model_params(model)}
    delay = pooled_draws(post, "delay")[idx, i]
    stacked = model.with_params(values, delay=jnp.asarray(delay, jnp.int32))
    if "delay_shift" in post:
        shift = pooled_draws(post, "delay_shift")[idx, i]
        stacked = stacked.with_delay_shift(jnp.asarray(shift, jnp.int32))
    return stacked, delay


def describe_fit(model: Model, data: LikelihoodData, settings: FitSettings) -> dict:
    origins = {e.name: effect_origin(e.name) for e in model.effects}
    return {
        "model": model.name,
        "effects": [e.name for e in model.effects],
        "effect_origins": {name: o for name, o in origins.items() if o is not None},
        "params": {
            p.name: {"units": p.units, "prior": list(p.prior), "level": p.level, "shape": list(p.shape), "doc": p.doc}
            for p in model_params(model)
        },
        "noise": noise_description(data.objective),
        "likelihood": data.objective,
        "legs": list(data.legs),
        "subjects": list(data.subjects),
        "leg_subject": [int(i) for i in data.leg_subject],
        "trials": list(data.trials),
        "resolution": data.resolution,
        "settings": dataclasses.asdict(settings),
        "chain_method": _chain_method_quietly(settings, data),
        "sampling_period_s": model.sampling_period_s,
    }


def noise_description(objective: str) -> dict:
    """The noise parameters' units and meaning for a likelihood on ``objective``."""
    out = {k: {"units": u, "doc": doc} for k, (u, doc) in NOISE_PARAMS.items()}
    if objective == "angle":
        out["sigma"] = {"units": SIGMA_UNITS["angle"], "doc": "Student-t scale of one sample's angle about its free run"}
    return out


def _chain_method_quietly(settings: FitSettings, data) -> str:
    """The chain method that ran, without the fallback's warning a second time (the fit gave it)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return chain_method(settings, data)


def model_from_description(desc: dict) -> Model:
    """Rebuild the (unparameterised) Model a fit was made with; a user's effect is imported again
    from the file the fit recorded, and refused when its source changed (:func:`ensure_effects`)."""
    ensure_effects(desc["effects"], desc.get("effect_origins"), f"the fit of model {desc['model']!r}")
    effects = [get_effect(n)() for n in desc["effects"]]
    model = Model(tuple(effects), name=desc["model"], sampling_period_s=desc.get("sampling_period_s", SAMPLING_PERIOD_S))
    # a fit that summed a step parameter out drew it under the hard step, and is evaluated so
    return hard_step(model) if desc.get("summed_out") else model


def to_json(desc: dict) -> str:
    return json.dumps(desc, sort_keys=True)


def from_json(text: str) -> dict:
    return json.loads(text)
