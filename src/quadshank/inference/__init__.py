"""Inference: classical identification (the paper's least squares), the screen, hierarchical NUTS, fit files.

:func:`identify_cohort` is the paper's eqs. (8)–(11); :func:`laplace_fit` the per-leg
screen (MAP and Laplace draws); :func:`fit` the hierarchical NUTS fit across legs, saved and
reloaded as arviz InferenceData by :func:`save_fit` and :func:`load_fit`.
"""

from ._density import numpyro_model
from ._draws import leg_models
from ._fitio import (
    THRESHOLDS,
    FitFolderError,
    FitResult,
    check_fit_files,
    diagnose_sampling,
    fit_summary,
    load_fit,
    posterior_models,
    read_summary,
    sampled_vars,
    save_fit,
    to_inference_data,
    weakly_informed,
)
from ._identify import (
    Identification,
    IdentificationError,
    LegIdentification,
    PassiveIdentification,
    identify_cohort,
    identify_leg,
    identify_passive,
    identify_passive_free_run,
    load_identification,
    models_from_summary,
    passive_model,
)
from ._nuts import BlockDraws, FitRun, FitSettings, convergence_status, fit, fit_screen, run_nuts
from ._priors import build_model, delay_prior_from, model_params
from ._screen import (
    DelayModes,
    LaplaceFit,
    delay_evidence,
    delay_modes,
    delta_elpd,
    laplace_fit,
    leg_draw_models,
)
from ._summaries import INTERVAL, interval, pooled_draws

__all__ = [
    "IdentificationError", "LegIdentification", "PassiveIdentification", "identify_cohort", "identify_leg", "identify_passive",
    "identify_passive_free_run", "passive_model",
    "Identification", "models_from_summary", "load_identification",
    "FitSettings", "fit", "run_nuts", "BlockDraws", "convergence_status", "FitRun", "FitResult", "fit_screen", "build_model", "model_params", "delay_prior_from", "numpyro_model",
    "LaplaceFit", "laplace_fit", "leg_draw_models", "delay_evidence", "delay_modes", "DelayModes", "delta_elpd",
    "to_inference_data", "save_fit", "load_fit", "read_summary", "fit_summary", "diagnose_sampling", "sampled_vars", "weakly_informed",
    "posterior_models", "leg_models", "FitFolderError", "THRESHOLDS", "check_fit_files",
    "INTERVAL", "interval", "pooled_draws",
]  # fmt: skip
