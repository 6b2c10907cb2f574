"""``quadshank discover``: the modelling loop, round after round, while an effect clears the bar."""

from __future__ import annotations

from pathlib import Path

from ..common._io import atomic_write_text
from ..data._cohort import Cohort
from ..inference._identify import check_delay_range
from ..inference._priors import build_model
from ..loop._diagnose import SCREEN_STARTS, STOPPED_AT_LIMIT, STOPPED_NOTHING, Discovery
from ..model._model import Model
from ..outputs._loop import discovery_markdown
from .diagnose import run_diagnose
from .evaluate import run_posterior_evaluate
from .fit import run_fit


def _fit_entry(folder: str, model: str, banner: str | None, diagnostics: dict) -> dict:
    return {"folder": folder, "model": model, "banner": banner, "diagnostics": diagnostics}


def _compare_start_final(cohort, out, fits: dict, *, n_draws, start_stride, progress) -> dict:
    """The loop's first and last NUTS fits (folders relative to ``out``) compared in
    ``out/confirm/compare``: J bands, PSIS-LOO, residuals before and after."""

    cmp = run_posterior_evaluate(cohort, [out / fits["start"]["folder"], out / fits["final"]["folder"]], out / "confirm" / "compare",
                                 n_draws=n_draws, start_stride=start_stride, progress=progress, residuals=True)
    a, b = fits["start"]["model"], fits["final"]["model"]
    group = (cmp.loo["compare"] or [{}])[0].get("table", {})
    J = cmp.J
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
    n_starts: int = SCREEN_STARTS,
) -> Discovery:
    """The whole loop: diagnose, add the leading effect, diagnose again, while an effect clears the bar.

    ``confirm`` (a :class:`quadshank.inference._nuts.FitSettings`): then every round's leader
    is confirmed with hierarchical NUTS before it is added: the starting model is
    fitted (``confirm/fit-start``), each round refits its leader against the
    previous round's fit (``round-K/confirm/fit-EFFECT``, see :func:`run_diagnose`)
    and the loop goes on only while NUTS agrees; the first and last fits are then
    compared (``confirm/compare``: J bands over ``compare_draws`` posterior draws,
    PSIS-LOO, residuals before and after).  ``n_starts``: see :func:`rank_effects`.
    """

    if int(max_rounds) < 1:
        raise ValueError(f"--max-rounds must be at least 1, not {max_rounds}")
    current = build_model(model, sampling_period_s=cohort.sampling_period_s) if isinstance(model, str) else model
    check_delay_range(cohort.sampling_period_s, muscle=current.activation.name != "no_muscle",
                      warn=current.activation.name != "no_muscle")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    fits, nuts_folder = {}, None
    if confirm is not None:
        base_name, *adds = current.name.split("+")
        nuts_folder = out / "confirm" / "fit-start"
        s = run_fit(cohort, nuts_folder, base_name, adds, confirm, legs=legs, progress=progress, data_source=data_source)
        fits["start"] = fits["final"] = _fit_entry("confirm/fit-start", s.model, s.banner, s.diagnostics)
    rounds, base, s, nuts_ok = [], None, None, []
    for k in range(1, max_rounds + 1):
        s = run_diagnose(
            cohort, current, out / f"round-{k}", trials=trials, legs=legs, effects=effects, base=base, progress=progress,
            confirm_from=nuts_folder, progress_label=f"round {k} of at most {max_rounds}: ", previous=s,
            n_starts=n_starts,
        )
        rounds.append({"model": current.name, "verdict": s.verdict, "sentence": s.sentence, "J_ms": s.J_ms, "elpd": s.elpd})
        if s.nuts_fits_ok is not None:
            nuts_ok.append(s.nuts_fits_ok)
        if s.screen_verdict is not None:
            rounds[-1]["screen_verdict"] = s.screen_verdict
        if s.verdict == "none":
            break
        base = s.screened.fits[s.verdict]
        current = base.model
        if confirm is not None:
            nuts = next(r for r in s.ranking if r["effect"] == s.verdict)["nuts"]
            nuts_folder = Path(nuts["folder"])
            fits["final"] = _fit_entry(nuts_folder.relative_to(out).as_posix(), nuts["model"], nuts["banner"], nuts["diagnostics"])
    summary = Discovery(model=rounds[0]["model"], final_model=current.name, rounds=rounds,
                        added=[r["verdict"] for r in rounds if r["verdict"] != "none"],
                        stopped=STOPPED_NOTHING if rounds[-1]["verdict"] == "none" else STOPPED_AT_LIMIT)
    if confirm is not None:
        summary.confirm = dict(fits)
        summary.nuts_fits_ok = bool(fits["start"]["diagnostics"].get("ok", False)) and all(ok for ok in nuts_ok)
        if summary.added:
            summary.confirm.update(_compare_start_final(cohort, out, fits, n_draws=compare_draws,
                                                        start_stride=compare_stride, progress=progress))
        else:
            summary.confirm["sentence"] = "Nothing was added; the start model's fit is in confirm/fit-start."
    atomic_write_text(out / "report.md", discovery_markdown(summary, command))
    summary.write(out)
    return summary
