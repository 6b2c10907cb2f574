"""Evaluation: J_φ,p (classical and over posterior draws), PSIS-LOO, residual statistics, calibration.

Numbers only: nothing here plots or writes files (:mod:`quadshank.outputs` does).
"""

from ._blackbox import ARX, arx_errors, better_than, blackbox_j, fit_arx
from ._checks import elpd_in_time, loo_pit
from ._classical_recovery import TOLERANCES, recovery
from ._parameters import leg_parameters, population_spreads
from ._posterior import (
    AccurateJ,
    LoadedFit,
    PosteriorEvaluation,
    accurate_j,
    band_mcse,
    check_fit_data,
    check_fit_legs,
    figure_window,
    largest_mcse,
    load_fits,
    loo_report,
    plan_predictions,
    posterior_j,
    posterior_j_and_stride_errors,
    posterior_prediction_errors,
    posterior_predictions,
    psis_loo,
    rest_states,
    stride_error,
    summarise_j,
    window_predictions,
)
from ._prediction import (
    Evaluation,
    evaluate_cohort,
    figure_trial,
    free_run_error,
    free_run_errors,
    free_runs,
    horizon_samples,
    prediction_errors,
    prediction_starts,
    predictions,
    sign_tests,
    table_v,
)
from ._recovery import (
    coverage_rows,
    likelihood_calibration,
    matching_values,
    simulate_matching,
)
from ._residuals import (
    acf,
    binned_trend,
    ccf,
    features,
    findings,
    fit_residuals,
    leg_residuals,
    point_residuals,
    spectrum,
    twitch_triggered_average,
)
from ._structure import residual_structure, structure_sentence

__all__ = [
    "ARX", "fit_arx", "arx_errors", "blackbox_j", "better_than",
    "AccurateJ", "accurate_j", "band_mcse", "largest_mcse", "posterior_j_and_stride_errors", "stride_error",
    "free_run_error", "free_run_errors", "free_runs", "prediction_errors", "prediction_starts", "predictions", "evaluate_cohort", "sign_tests", "table_v", "horizon_samples",
    "figure_trial", "Evaluation",
    "LoadedFit", "PosteriorEvaluation", "load_fits", "posterior_predictions", "posterior_prediction_errors", "posterior_j", "summarise_j",
    "psis_loo", "loo_report", "figure_window", "window_predictions", "check_fit_data", "check_fit_legs", "plan_predictions", "rest_states",
    "leg_parameters", "population_spreads",
    "features", "binned_trend", "acf", "ccf", "twitch_triggered_average", "spectrum", "findings",
    "point_residuals", "fit_residuals", "leg_residuals", "loo_pit", "elpd_in_time",
    "residual_structure", "structure_sentence",
    "recovery", "TOLERANCES", "matching_values", "simulate_matching", "coverage_rows", "likelihood_calibration",
]  # fmt: skip
