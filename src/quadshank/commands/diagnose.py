"""``quadshank diagnose``: rank the candidate effects for a model, confirm the leaders with NUTS, write the report."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..common._io import atomic_write_text
from ..common._progress import progress_bar
from ..data._cohort import Cohort
from ..evaluation._blackbox import blackbox_j
from ..evaluation._posterior import LoadedFit, load_fits, psis_loo
from ..evaluation._structure import nothing_found, residual_structure, structure_sentence
from ..inference._nuts import FitSettings
from ..inference._screen import LaplaceFit, paired_difference
from ..loop._diagnose import (
    J_DRAWS,
    J_HORIZONS_MS,
    J_START_STRIDE,
    SCREEN_STARTS,
    Diagnosis,
    Ranking,
    evidence_bar,
    k_checked_difference,
    nuts_j_draws,
    nuts_sentence,
    rank_effects,
    trials_of,
    verdict_sentence,
)
from ..model._effects import registered_effects
from ..model._model import Model
from ..outputs._loop import (
    copy_figures,
    predictive_checks,
    ranking_markdown,
    residual_figures,
    screen_residuals,
)
from ..outputs._residual_figures import plot_structure
from .fit import run_fit


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

    if not isinstance(base, LoadedFit):
        (base,) = load_fits([base])
    desc = base.desc
    settings = FitSettings(**{**desc["settings"], "trials": tuple(desc["trials"])})
    trials = tuple(eval_trials) if eval_trials is not None else trials_of(cohort, desc["legs"])
    base_name, *adds = desc["model"].split("+")
    s = run_fit(cohort, out, base_name, [*adds, effect], settings, legs=desc["legs"], progress=progress,
                data_source=base.summary.data)
    (ext,) = load_fits([out])
    loo_a, loo_b = psis_loo(base.idata, str(base.folder)), psis_loo(ext.idata, str(ext.folder))
    if list(loo_a.loo_i["observation"].values) != list(loo_b.loo_i["observation"].values):
        raise ValueError(f"{base.folder} and {out}: the fits' PSIS-LOO segments differ; they are not of the same data")
    d, se = paired_difference(loo_a.loo_i.values, loo_b.loo_i.values)
    checked = k_checked_difference(loo_a.loo_i.values, loo_b.loo_i.values, loo_b.pareto_k.values)
    if J_base is None:
        J_base = nuts_j_draws(base, cohort, trials, n_draws=n_j_draws, start_stride=start_stride)
    J_ext = nuts_j_draws(ext, cohort, trials, n_draws=n_j_draws, start_stride=start_stride)
    return {
        "effect": effect,
        "model": s.model,
        "folder": str(Path(out)),
        **evidence_bar(d, se, J_base, J_ext, registered_effects()[effect].predicts_angle,
                       registered_effects()[effect].acts_at_ms, checked, registered_effects()[effect].kind),
        "pareto_k_max": float(np.max(np.asarray(loo_b.pareto_k))),
        "diagnostics": s.diagnostics,
        "banner": s.banner,
    }


def confirm_leaders(cohort: Cohort, ranking: Ranking, base_folder, out, *, n_confirm: int = 1, progress: bool = False) -> str:
    """Confirm the ``n_confirm`` best candidates that clear the screen's bar with NUTS (each
    row gets ``nuts``: :func:`confirm_with_nuts`, its fit in ``out/fit-EFFECT``); returns the
    verdict under NUTS: the best of them that clears the bar there too, or ``none``."""

    leaders = [r for r in ranking.rows if r["clears_bar"]][:n_confirm]
    if not leaders:
        return "none"
    (base,) = load_fits([base_folder])
    trials = trials_of(cohort, base.desc["legs"])
    J0 = nuts_j_draws(base, cohort, trials, n_draws=J_DRAWS, start_stride=J_START_STRIDE)
    for r in progress_bar(leaders, desc="confirming with NUTS", enabled=progress):
        r["nuts"] = confirm_with_nuts(cohort, base, r["effect"], Path(out) / f"fit-{r['effect']}",
                                      eval_trials=trials, J_base=J0, progress=progress)
    return next((r["effect"] for r in leaders if r["nuts"]["clears_bar"]), "none")


def blackbox_beside(cohort: Cohort, legs: list, trials, J_base: dict, known: dict | None = None) -> dict:
    """The ARX yardstick (:mod:`quadshank.evaluation._blackbox`) on the legs and trials the diagnosis
    scores the baseline on, at its horizons: J of the mean over legs and trials, the horizons where
    it predicts better than the baseline's median, and a sentence where it does.  ``known``: this
    function's result for the same data, legs and trials against another baseline (the yardstick
    does not depend on the model: its J and orders are reused)."""
    if known is not None and "skipped" in known:
        return {"skipped": known["skipped"]}
    if known is not None:
        J, orders = known["J_ms"], known["orders"]
    else:
        sub = cohort.select(legs=legs, trials=[int(t) for t in trials])
        try:
            bb = blackbox_j(sub, {leg: int(trials[0]) for leg in legs}, horizons_ms=J_HORIZONS_MS)
        except ValueError as e:  # a trial too short to validate one
            return {"skipped": str(e)}
        J = {str(h): float(np.mean([v[str(h)] for trials_ in bb["J_per_leg"].values() for v in trials_.values()]))
             for h in J_HORIZONS_MS}
        orders = bb["orders"]
    better = [h for h, v in J.items() if v < J_base[h]["median"]]
    out = {"J_ms": J, "orders": orders, "better_at_ms": better}
    if better:
        out["sentence"] = (
            f"A black box (a linear ARX model of the angle, orders chosen by validation) predicts better than "
            f"the baseline at {', '.join(better)} ms ("
            + ", ".join(f"J {J[h]:.2f}° against {J_base[h]['median']:.2f}°" for h in better)
            + "): the model misses something the data hold at that horizon.")
    return out


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
    n_starts: int = SCREEN_STARTS,
    progress_label: str = "",
    confirm_from=None,
    n_confirm: int = 1,
    objective: str = "auto",
    previous: Diagnosis | None = None,
) -> Diagnosis:
    """Rank the candidate effects for ``model``; writes figures, report.md and summary.json (last).

    ``n_starts``: see :func:`rank_effects`.  ``confirm_from``: a NUTS fit folder of
    ``model`` on the same data; then the ``n_confirm`` best candidates that clear
    the screen's bar are refitted with NUTS (``out/confirm/fit-EFFECT``, the same
    settings) and the verdict is the best that clears the bar under NUTS too
    (:func:`confirm_leaders`); the screen's own is kept as ``screen_verdict``.  ``objective``: what
    the screens' likelihood compares (the saved fit's ``likelihood``).  ``previous``: the diagnosis
    (the previous round of discover, on the same data, legs and trials) whose verdict's screen is
    ``base``: what it computed of that screen (its J draws, its residual figures) and the black-box
    yardstick are reused, not computed again."""

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    carried = previous is not None and previous.verdict != "none" and previous.screened is not None \
        and base is previous.screened.fits.get(previous.verdict)
    ranking = rank_effects(cohort, model, trials=trials, legs=legs, effects=effects, base=base, seed=seed,
                           n_starts=n_starts, progress=progress, progress_label=progress_label, objective=objective,
                           base_J=previous.screened.J_draws.get(previous.verdict) if carried else None)
    screen_verdict = ranking.verdict
    if confirm_from is not None:
        ranking.verdict = confirm_leaders(cohort, ranking, confirm_from, out / "confirm", n_confirm=n_confirm,
                                          progress=progress)
    result = Diagnosis(**ranking.to_json(), sentence=verdict_sentence(ranking), trials=[int(t) for t in trials],
                       screened=ranking)
    if confirm_from is not None:
        result.screen_verdict = screen_verdict
        result.confirmed_from = str(confirm_from)
        made = [r["nuts"] for r in result.ranking if r.get("nuts")]
        result.nuts_fits_ok = all(n["diagnostics"].get("ok", False) for n in made) if made else None
        said = nuts_sentence(result.ranking)
        if ranking.verdict == "none" and screen_verdict != "none":
            result.sentence = f"The screen's leader, {screen_verdict}, is not confirmed by NUTS. {said}"
        elif said:
            result.sentence += " " + said
    result.folder = out
    result.blackbox = blackbox_beside(cohort, list(ranking.base.legs), trials, ranking.J_base,
                                      known=previous.blackbox if carried else None)
    if result.blackbox.get("sentence"):
        result.sentence += " " + result.blackbox["sentence"]
    dt = ranking.base.model.sampling_period_s
    residuals = screen_residuals(ranking.base)
    result.unexplained = residual_structure(residuals, dt, ranking.base.data.response_length)
    left = structure_sentence(result.unexplained)
    if ranking.verdict == "none":
        result.sentence += " " + (left or nothing_found(result.unexplained))
    if figures:
        paths, result.predictive_checks = predictive_checks(ranking.base, cohort, out, "baseline")
        if carried and previous.folder is not None and previous.residual_findings_after is not None:
            # the previous round drew this screen's residuals as its verdict's, "with_EFFECT"
            more = copy_figures(previous.folder, previous.figures or [], f"with_{previous.verdict}", out, "baseline")
            result.residual_findings = previous.residual_findings_after
        else:
            more, result.residual_findings = residual_figures(residuals, out, "baseline", dt)
        paths += more
        if result.unexplained["found"]:
            paths.append(plot_structure(result.unexplained, out / "unexplained_structure.png", notes=[left]))
        if ranking.verdict != "none":
            more, result.residual_findings_after = residual_figures(
                screen_residuals(ranking.fits[ranking.verdict]), out, "with_" + ranking.verdict, dt)
            paths += more
        result.figures = [p.name for p in paths]
    atomic_write_text(out / "report.md", ranking_markdown(result, command))
    result.write(out)
    return result
