"""Which effect is missing: rank one-effect extensions of a model by the evidence.

For a model and a dataset, every candidate effect (each registered effect
with ``candidate = True`` that the model lacks; an effect that generalises one
in the model takes its place) is added in turn, and the extension is compared
with the model on the same data by

- ΔELPD: PSIS-LOO over the likelihood's 1-s segments, paired segment by
  segment, with its standard error (the screen of :mod:`quadshank.inference._screen`);
- ΔJ_φ,p: the k-step-ahead angle error (eq. 12) at 100, 250, 500 and 1000 ms
  on the evaluation trials, as bands over the posterior draws of each model;
- the residual signature: the trend of the model's one-step residual over
  the feature where the effect's absence shows (its ``signature``: knee
  angle, velocity, pulse count, preceding interpulse interval, ...).

An effect is *supported by the evidence* when its ΔELPD exceeds
``ELPD_SE_BAR`` standard errors, both over every segment and over the
segments whose PSIS-LOO the extended model estimates reliably (Pareto k at
most ``PARETO_K_MAX``: :func:`k_checked_difference`).  It *clears the bar* when it is supported and
lowers J beyond the bands (the extension's upper 90 % limit below the model's
lower one) at every horizon where it acts (the effect's ``acts_at_ms``: a
delay at 100 and 250 ms, where a prediction feels it; the others at 500 and
1000 ms); an effect on what the accelerometer reads alone (``predicts_angle =
False``: a skin-motion resonance) cannot improve an angle prediction, and its
bar is ΔELPD, with J not raised beyond the bands where it is judged: an effect
on the sensor alone that makes the angle's predictions worse has moved the
dynamics' parameters to absorb a misfit of the dynamics, which is not the
sensor's.  A noise effect's bar is ΔELPD alone.  The candidates are ranked by the evidence among those
that clear the bar, then the rest; the verdict is the first, or ``none``: a
misfit that some effect absorbs a little of (ΔELPD of a few units, within
noise on J) is not called a missing effect.  The verdict's sentence says when
the evidence leads elsewhere: a candidate with more evidence that changes J
little where it acts, and a candidate that lowers J without being the best
explanation of the data.

The ranking screens (per-leg MAP and Laplace draws); the leaders that clear
the bar are then confirmed with hierarchical NUTS (:func:`confirm_leaders`):
refitted with a saved fit's settings and judged against the same bar by
PSIS-LOO and J bands over posterior draws.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path
from typing import ClassVar

import numpy as np

from ..common._progress import progress_bar
from ..common._results import Result
from ..data._cohort import Cohort
from ..data._paper import HORIZONS_MS
from ..evaluation._posterior import posterior_prediction_errors
from ..inference._fitio import posterior_models
from ..inference._identify import check_delay_range
from ..inference._priors import build_model
from ..inference._screen import LaplaceFit, delta_elpd, laplace_fit, leg_draw_models, paired_difference
from ..inference._summaries import interval
from ..model._effects import reads_sensor_only, registered_effects
from ..model._likelihood import resolve_objective
from ..model._model import Model

__all__ = ["candidates", "rank_effects", "Ranking", "Diagnosis", "Discovery", "ELPD_SE_BAR", "J_HORIZONS_MS", "evidence_notes",
           "PARETO_K_MAX", "k_checked_difference", "not_applicable", "MUSCLE_KINDS"]

#: ΔELPD must exceed this many standard errors.
ELPD_SE_BAR = 2.0
#: A segment whose PSIS-LOO has a Pareto k above this is not trusted (Vehtari et al., "Pareto
#: smoothed importance sampling", 2024): the evidence must hold without such segments too.
PARETO_K_MAX = 0.7
#: Where more than this share of the segments is above PARETO_K_MAX, it is the approximation of the
#: whole posterior that stands poorly (the screen's Laplace Gaussian on a curved ridge, say), not a
#: few influential segments: the sentence says so and sends the candidate to NUTS (``--confirm``).
#: The evidence must still hold on the reliable segments: an estimate that fails on most of the
#: data is no support, and a share just above or below this value must not decide the verdict.
K_SHARE_MAX = 0.5
#: Horizons [ms] at which J bands are drawn; each candidate is judged at its own (``Effect.acts_at_ms``).
J_HORIZONS_MS = HORIZONS_MS
#: Posterior draws, and the stride between prediction starts, of the J bands behind the bar.
J_DRAWS, J_START_STRIDE = 40, 5
#: Prior draws tried for an extension's new parameters, besides their prior median, each a start
#: of L-BFGS from the baseline's mode (per leg; the best mode wins).  One guards against a median
#: that is a stationary point of the new parameters (an effect switched off); each more costs one
#: more minimisation per leg and candidate.
SCREEN_STARTS = 1


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


#: Effect kinds that act through the stimulated muscle: on the pendulum alone, or on trials without
#: pulses, their parameters have nothing to explain, and a ΔELPD of a few units would be noise.
MUSCLE_KINDS = ("activation", "gain", "pulse", "delay", "output", "noise")


def not_applicable(model: Model, cohort: Cohort, effects, legs, trials, objective: str = "auto") -> dict:
    """The effects of ``effects`` that cannot change ``model``'s likelihood on these data, and why.

    An effect acting through the muscle (:data:`MUSCLE_KINDS`) on a model without one
    (``--model passive``) or on trials that hold no pulse, and an effect on what the
    accelerometer reads alone (``predicts_angle = False``) where the fit compares angles
    (``objective``, :func:`~quadshank.model._likelihood.resolve_objective`) or where no trial has
    an accelerometer (its acceleration derived from the angle: a filter's smoothing, not a
    sensor's response, which such an effect would take up), and a delay or noise effect where
    the fit compares angles (the angle likelihood of a muscle cannot hold one).
    They are listed, not screened: their ΔELPD could only be noise, or a filter's.
    """
    known = registered_effects()
    muscle = model.activation.name != "no_muscle"
    used = [t for leg in legs for t in cohort.trials_of(leg) if t.trial in trials]
    pulses = any(t.pulse_indices.size for t in used)
    accelerometer = any(t.acceleration_measured for t in used)
    by_angle = resolve_objective(model, objective) == "angle"
    out = {}
    for name in effects:
        cls = known[name]
        if cls.kind in MUSCLE_KINDS and not muscle:
            out[name] = f"acts through the muscle, and {model.name} is the pendulum alone"
        elif cls.kind in MUSCLE_KINDS and not pulses:
            out[name] = f"acts through the stimulation, and trial(s) {', '.join(map(str, trials))} hold no pulse"
        elif reads_sensor_only(cls) and by_angle:
            out[name] = "changes only what the accelerometer reads, and the fit compares angles"
        elif reads_sensor_only(cls) and not accelerometer:
            out[name] = (f"changes only what an accelerometer reads, and trial(s) {', '.join(map(str, trials))} have "
                         "none (their acceleration is derived from the angle)")
        elif cls.kind in ("delay", "noise") and by_angle:
            out[name] = (f"a {cls.kind} effect is summed out window by window on the acceleration alone, and the "
                         "fit compares angles")
    return out


def trials_of(cohort: Cohort, legs) -> tuple[int, ...]:
    """Every trial number that some leg of ``legs`` has in ``cohort``."""
    return tuple(sorted({t.trial for leg in legs for t in cohort.trials_of(leg)}))


def _extend(model: Model, name: str) -> Model:
    return model.add(name)


def j_draws(fit: LaplaceFit, cohort: Cohort, trials, *, n_draws: int, start_stride: int) -> np.ndarray:
    """J_φ,p [deg] per draw at J_HORIZONS_MS, averaged over legs and ``trials``: (draws, horizons)."""
    return _mean_j(lambda leg: leg_draw_models(fit, leg, n_draws), fit.legs, fit.model, cohort, trials, start_stride)


def nuts_j_draws(fit, cohort: Cohort, trials, *, n_draws: int, start_stride: int, seed: int = 0) -> np.ndarray:
    """:func:`j_draws` for a saved NUTS fit (a :class:`quadshank.evaluation._posterior.LoadedFit`)."""

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
    #: candidates that cannot change the likelihood on these data (:func:`not_applicable`): effect -> why
    not_applicable: dict = dataclasses.field(default_factory=dict)
    #: each extension's J draws (draws, horizons) behind its bands (the next round's base J, in discover)
    J_draws: dict = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "model": self.base.model.name,
            "legs": list(self.base.legs),
            "elpd": {"value": self.base.elpd, "se": self.base.elpd_se},
            "J_ms": self.J_base,
            "ranking": self.rows,
            "failed": [{"effect": k, "error": v} for k, v in self.failed.items()],
            "not_applicable": [{"effect": k, "why": v} for k, v in self.not_applicable.items()],
            "verdict": self.verdict,
            "bar": {"elpd_se": ELPD_SE_BAR, "J_horizons_ms": list(J_HORIZONS_MS), "J_judged_at": "acts_at_ms"},
        }


@dataclasses.dataclass
class Diagnosis(Result):
    """What ``quadshank diagnose`` found: the candidates ranked by the evidence and the verdict.

    The JSON form (``summary.json``) holds every field but :attr:`screened`, the live
    :class:`Ranking` with the screens of the base model and of each extension.
    """

    KIND: ClassVar[str] = "diagnosis"

    model: str
    legs: list
    elpd: dict  # {"value", "se"} of the base model
    J_ms: dict  # horizon [ms] -> J interval of the base model
    ranking: list  # one row per screened candidate, best first
    verdict: str  # the effect that clears the bar, or "none"
    bar: dict
    sentence: str
    trials: list
    failed: list = dataclasses.field(default_factory=list)
    not_applicable: list = dataclasses.field(default_factory=list)  # candidates not screened, and why
    screen_verdict: str | None = None  # the screen's own verdict, where NUTS confirmed it
    confirmed_from: str | None = None
    #: whether every NUTS fit made to confirm a leader passed its checks (None: none was made)
    nuts_fits_ok: bool | None = None
    predictive_checks: dict | None = None
    residual_findings: dict | None = None
    residual_findings_after: dict | None = None
    figures: list | None = None
    #: the ARX yardstick's J on the same legs and trials, beside the baseline's (see commands.diagnose)
    blackbox: dict | None = None
    #: structure left in the baseline's residuals (:func:`quadshank.evaluation._structure.residual_structure`)
    unexplained: dict | None = None
    screened: Ranking | None = dataclasses.field(default=None, repr=False, metadata={"json": False})
    #: the folder it was written to (not in the JSON form: the folder holds it)
    folder: Path | None = dataclasses.field(default=None, repr=False, metadata={"json": False})


@dataclasses.dataclass
class Discovery(Result):
    """What ``quadshank discover`` found: the model of each round, its verdict, the effects added."""

    KIND: ClassVar[str] = "discovery"

    model: str
    final_model: str
    rounds: list  # per round: model, verdict, sentence, J_ms, elpd (and screen_verdict)
    added: list
    confirm: dict | None = None  # the NUTS fits of the loop's start and end, compared
    #: whether every NUTS fit the loop made (its start's, each round's leaders') passed its checks (None: none made)
    nuts_fits_ok: bool | None = None
    #: why the loop ended: no candidate cleared the bar, or the round limit came first (:data:`STOPPED_AT_LIMIT`)
    stopped: str | None = None


#: ``Discovery.stopped`` where the last round still added an effect: further rounds may find more.
STOPPED_AT_LIMIT = "round limit"
#: ``Discovery.stopped`` where the last round's verdict was none.
STOPPED_NOTHING = "no candidate cleared the bar"


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
    n_starts: int = SCREEN_STARTS,
    base: LaplaceFit | None = None,
    progress: bool = False,
    progress_label: str = "",
    objective: str = "auto",
    base_J: np.ndarray | None = None,
) -> Ranking:
    """Screen every one-effect extension of ``model``; returns a :class:`Ranking`.

    ``eval_trials``: where J is measured (default: every trial of the legs in
    the cohort, the identification trials included: the loop asks where the
    model fails on the measurements it has).  ``n_starts``: prior draws tried, besides the
    prior median, for the parameters an extension adds (:func:`quadshank.inference._screen.laplace_fit`).
    ``progress``: a progress bar over the candidates, naming the one being screened, its
    description prefixed by ``progress_label`` (discover: the round).  ``objective``: what the
    screens' likelihood compares (a saved fit's ``likelihood``; :func:`~quadshank.model._likelihood.resolve_objective`).
    ``base_J``: ``base``'s J draws on ``eval_trials``, where they were computed already (a round
    of discover: the previous round's, :attr:`Ranking.J_draws`).
    """
    model = build_model(model, sampling_period_s=cohort.sampling_period_s) if isinstance(model, str) else model
    # refused here too (diagnose and discover come here); the warning is the commands' to give once
    check_delay_range(cohort.sampling_period_s, muscle=model.activation.name != "no_muscle", warn=False)
    legs = tuple(legs) if legs is not None else cohort.legs
    if eval_trials is None:
        eval_trials = trials_of(cohort, legs)
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
    inapplicable = not_applicable(model, cohort, effects, legs, trials, objective)
    effects = [e for e in effects if e not in inapplicable]

    kw = dict(n_draws=n_draws, seed=seed, n_starts=n_starts, objective=objective)
    if base is None:
        base = laplace_fit(cohort, model, trials, legs, **kw)
    J0 = base_J if base_J is not None else j_draws(base, cohort, eval_trials, n_draws=n_j_draws,
                                                     start_stride=start_stride)
    fits, rows, failed, J_draws = {}, [], {}, {}
    bar = progress_bar(effects, desc=f"{progress_label}screening effects", enabled=progress)
    for name in bar:
        if hasattr(bar, "set_postfix_str"):
            bar.set_postfix_str(f"{model.name} + {name}")
        try:
            ext = laplace_fit(cohort, _extend(model, name), trials, legs, start=base, **kw)
            d, se = delta_elpd(base, ext)
            checked = k_checked_difference(base.elpd_i, ext.elpd_i, ext.pareto_k)
            J1 = j_draws(ext, cohort, eval_trials, n_draws=n_j_draws, start_stride=start_stride)
        except Exception as err:  # noqa: BLE001 - one candidate (a user's effect, say) must not end the screen
            failed[name] = f"{type(err).__name__}: {err}"
            warnings.warn(f"the screen of {model.name} + {name} failed and is left out of the ranking: {failed[name]}",
                          RuntimeWarning, stacklevel=2)
            continue
        fits[name] = ext
        J_draws[name] = J1
        row = {
            "effect": name,
            **evidence_bar(d, se, J0, J1, known[name].predicts_angle, known[name].acts_at_ms, checked, known[name].kind),
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
    return Ranking(base=base, fits=fits, rows=rows, verdict=verdict, J_base=J_base, failed=failed,
                   not_applicable=inapplicable, J_draws=J_draws)


def k_checked_difference(a_i, b_i, k_b) -> tuple[float, float, float]:
    """ΔELPD of ``b`` over ``a`` and its SE (:func:`~quadshank.inference._screen.paired_difference`)
    over the segments whose Pareto k in ``b`` (the extended model) is at most :data:`PARETO_K_MAX`,
    and the share of the compared segments left out.

    Only the extension's k counts: a PSIS-LOO estimate of high k tends to be optimistic, so a
    segment the extension estimates unreliably may inflate the difference, while one the baseline
    estimates unreliably (where a missing effect shows, typically) can only shrink it."""
    a_i, b_i = np.asarray(a_i, float), np.asarray(b_i, float)
    compared = np.isfinite(a_i) & np.isfinite(b_i)
    reliable = compared & (np.asarray(k_b, float) <= PARETO_K_MAX)
    d, se = paired_difference(np.where(reliable, a_i, np.nan), np.where(reliable, b_i, np.nan))
    return d, se, float(1.0 - reliable.sum() / max(int(compared.sum()), 1))


def evidence_bar(d: float, se: float, J0: np.ndarray, J1: np.ndarray, predicts_angle: bool,
                 acts_at_ms=(500, 1000), k_checked: tuple | None = None, kind: str = "") -> dict:
    """Whether an extension is supported by the evidence and clears the bar (module docs):
    ΔELPD ± SE, J at J_HORIZONS_MS before and after (from per-draw J, (draws, horizons)), judged
    at the horizons ``acts_at_ms`` where the effect acts.  ``k_checked``: ΔELPD, SE and the share
    of segments left out by :func:`k_checked_difference`; the evidence must hold there too.
    ``kind``: the effect's; an effect that does not predict the angle and is not a noise effect
    (an accelerometer's) must not raise J beyond the bands where it is judged."""
    out = {"delta_elpd": d, "delta_elpd_se": se}
    lowered, raised = [], []
    for j, h in enumerate(J_HORIZONS_MS):
        b, x = interval(J0[:, j]), interval(J1[:, j])
        out[f"J_{h}ms"] = {"before": b, "after": x, "change": x["median"] - b["median"]}
        if x["hi"] < b["lo"]:
            lowered.append(h)
        if x["lo"] > b["hi"]:
            raised.append(h)
    judged = [int(h) for h in acts_at_ms]
    out["judged_at_ms"] = judged
    out["J_lowered_at_ms"] = lowered
    out["J_raised_at_ms"] = raised
    out["J_lowered_beyond_bands"] = all(h in lowered for h in judged)
    out["sensor_raises_J"] = sensor_raises_J = not predicts_angle and kind != "noise" and any(h in raised for h in judged)
    out["predicts_angle"] = bool(predicts_angle)
    out["supported"] = bool(d > ELPD_SE_BAR * se)
    if k_checked is not None:
        d_k, se_k, share = k_checked
        out["delta_elpd_k_checked"], out["delta_elpd_k_checked_se"] = float(d_k), float(se_k)
        out["pareto_k_high_share"] = float(share)
        out["supported"] = bool(out["supported"] and d_k > ELPD_SE_BAR * se_k)
    out["clears_bar"] = bool(out["supported"] and (out["J_lowered_beyond_bands"] or not predicts_angle)
                             and not sensor_raises_J)
    return out


def _j_change(r: dict, horizons) -> str:
    """J before → after at ``horizons`` of a ranking row, in words."""
    parts = []
    for h in horizons:
        j = r[f"J_{h}ms"]
        parts.append(f"{j['before']['median']:.2f}° → {j['after']['median']:.2f}° at {h} ms")
    return ", ".join(parts)


def _unreliable_rest(r: dict) -> str:
    """What a row's evidence comes to on its reliable segments, where that leaves it unsupported."""
    if r["supported"] or "delta_elpd_k_checked" not in r:
        return ""
    if r["pareto_k_high_share"] >= 1.0:
        return ", and no segment is estimated reliably, so it is not counted as supported"
    return (f", and on the other segments it is {r['delta_elpd_k_checked']:.0f} ± {r['delta_elpd_k_checked_se']:.0f}, "
            "not counted as supported")


def evidence_notes(ranking: Ranking) -> str:
    """What the verdict alone does not say: a candidate with more evidence than the verdict that
    changes J little where it acts, and candidates that lower J there without being the best
    explanation (less evidence than the verdict, or than a candidate the evidence prefers)."""
    rows = ranking.rows
    if not rows:
        return ""
    lead = max(rows, key=lambda r: r["delta_elpd"])
    chosen = next((r for r in rows if r["effect"] == ranking.verdict), None)
    notes = []
    if lead["supported"] and not lead["clears_bar"] and not lead.get("sensor_raises_J"):
        notes.append(
            f"{lead['effect']} has the most evidence (ΔELPD {lead['delta_elpd']:.0f} ± {lead['delta_elpd_se']:.0f}) "
            f"but changes J little where it acts ({_j_change(lead, lead['judged_at_ms'])}; the bands overlap), so it is "
            "not called missing; more data, or a look at its residual signature, can settle it."
        )
    strong = [r for r in rows if r["delta_elpd"] > ELPD_SE_BAR * r["delta_elpd_se"]]
    loose = [r for r in strong if r.get("pareto_k_high_share", 0.0) > K_SHARE_MAX]
    shaky = [r for r in strong if not r["supported"] and "delta_elpd_k_checked" in r and r not in loose]
    for r in loose[:2]:
        notes.append(
            f"The screen's Laplace approximation stands poorly for the posterior with {r['effect']} (Pareto k > "
            f"{PARETO_K_MAX:g} in {100 * r['pareto_k_high_share']:.0f} % of the segments), so its ΔELPD is an "
            "approximation's" + _unreliable_rest(r)
            + "; NUTS (--confirm) checks it."
        )
    for r in shaky[:2]:
        notes.append(
            f"{r['effect']}'s evidence (ΔELPD {r['delta_elpd']:.0f} ± {r['delta_elpd_se']:.0f}) rests on segments whose "
            f"leave-one-out estimate is unreliable (Pareto k > {PARETO_K_MAX:g} in {100 * r['pareto_k_high_share']:.0f} % "
            f"of the segments): without them it is {r['delta_elpd_k_checked']:.0f} ± {r['delta_elpd_k_checked_se']:.0f}, so it "
            "is not counted as supported; NUTS (--confirm) can settle it."
        )
    raised = next((r for r in rows if r.get("sensor_raises_J") and r["supported"]), None)
    if raised is not None:
        notes.append(
            f"{raised['effect']} has evidence (ΔELPD {raised['delta_elpd']:.0f} ± {raised['delta_elpd_se']:.0f}) but acts on "
            f"what the accelerometer reads alone, and with it J rises beyond the bands "
            f"({_j_change(raised, raised['judged_at_ms'])}): it moves the dynamics' parameters to absorb a misfit of the "
            "dynamics, so it is not added."
        )
    best = chosen if chosen is not None else lead
    others = [r for r in rows if r is not best and r.get("predicts_angle", True) and r["J_lowered_beyond_bands"]
              and r["supported"] and r["delta_elpd"] < best["delta_elpd"]]
    for r in others[:2]:
        notes.append(
            f"{r['effect']} also lowers J ({_j_change(r, r['judged_at_ms'])}) but is not the best explanation: "
            f"ΔELPD {r['delta_elpd']:.0f} ± {r['delta_elpd_se']:.0f} against {best['effect']}'s "
            f"{best['delta_elpd']:.0f} ± {best['delta_elpd_se']:.0f}."
        )
    return " ".join(notes)


def verdict_sentence(ranking: Ranking) -> str:
    """The verdict in words, with the numbers behind it."""
    notes = evidence_notes(ranking)
    tail = f" {notes}" if notes else ""
    if ranking.verdict == "none":
        best = ranking.rows[0] if ranking.rows else None
        if best is None:
            return "No candidate effect was screened."
        return (
            f"Nothing is missing that the candidates describe: the best, {best['effect']}, changes ELPD by "
            f"{best['delta_elpd']:.1f} ± {best['delta_elpd_se']:.1f} and J {_j_change(best, best['judged_at_ms'])}, "
            f"short of the bar (ΔELPD > {ELPD_SE_BAR:g} SE and J lowered beyond the 90 % bands where the effect "
            f"acts).{tail}"
        )
    r = next(r for r in ranking.rows if r["effect"] == ranking.verdict)
    if not r.get("predicts_angle", True):
        j10 = r["J_1000ms"]
        cls = registered_effects().get(r["effect"])
        if cls is not None and cls.kind == "noise":
            return (
                f"Adding {r['effect']} improves ELPD by {r['delta_elpd']:.0f} ± {r['delta_elpd_se']:.0f}; it describes how "
                f"the measurements scatter about the model, not its dynamics, so J does not judge it (at 1 s "
                f"{j10['before']['median']:.2f}° without it, {j10['after']['median']:.2f}° with it). Keep it in the model: with it, "
                f"the next candidates are judged against that scatter, not taken for it.{tail}"
            )
        return (
            f"Adding {r['effect']} improves ELPD by {r['delta_elpd']:.0f} ± {r['delta_elpd_se']:.0f}; it changes what the "
            f"accelerometer reads, not the angle, so J does not judge it (at 1 s {j10['before']['median']:.2f}° "
            f"without it, {j10['after']['median']:.2f}° with it).{tail}"
        )
    parts = []
    for h in r["judged_at_ms"]:
        j = r[f"J_{h}ms"]
        parts.append(f"at {h} ms from {j['before']['median']:.2f}° [{j['before']['lo']:.2f}, {j['before']['hi']:.2f}] "
                     f"to {j['after']['median']:.2f}° [{j['after']['lo']:.2f}, {j['after']['hi']:.2f}]")
    return (
        f"Adding {r['effect']} improves ELPD by {r['delta_elpd']:.0f} ± {r['delta_elpd_se']:.0f} and lowers J "
        f"{' and '.join(parts)}.{tail}"
    )


# ============================================================================ NUTS confirmation


def nuts_sentence(rows: list) -> str:
    """What NUTS said of the screen's leaders (the ranking's rows), in words."""
    parts = []
    for r in rows:
        n = r.get("nuts")
        if n is None:
            continue
        j10 = n["J_1000ms"]
        said = ("confirms" if n["clears_bar"] else "does not confirm") if not n.get("banner") else \
            ("would confirm" if n["clears_bar"] else "would not confirm")  # a fit that failed its checks confirms nothing
        parts.append(
            f"NUTS {said} {r['effect']}: ΔELPD "
            f"{n['delta_elpd']:.0f} ± {n['delta_elpd_se']:.0f}, J at 1 s {j10['before']['median']:.2f}° → "
            f"{j10['after']['median']:.2f}° [{j10['after']['lo']:.2f}, {j10['after']['hi']:.2f}]"
            + (f" (but its fit failed its checks: {n['banner']})" if n.get("banner") else "") + "."
        )
    return " ".join(parts)


# ============================================================================ outputs


