"""Outputs: figures, tables, Markdown and HTML; the only code that writes result folders.

Plot functions take data and return a matplotlib Figure (or, for the residual figures,
save it and return its path); they never show it.
"""

from ._figures import (
    plot_delay_angle,
    plot_delay_scan,
    plot_j_vs_horizon,
    plot_plan_predictions,
    plot_posterior_j_vs_horizon,
    plot_posterior_predictions,
    plot_predictions,
    plot_recording,
    plot_signals,
    plot_twitch_dependence,
)
from ._loop import (
    discovery_markdown,
    predictive_checks,
    ranking_markdown,
    residual_figures,
)
from ._report import (
    plot_delay_posterior,
    plot_leg_predictions,
    plot_shrinkage,
    write_report,
)
from ._residual_figures import (
    plot_correlations,
    plot_elpd_in_time,
    plot_loo_pit,
    plot_spectrum,
    plot_trends,
    plot_twitch_average,
)
from ._tables import (
    active_legs,
    markdown_table,
    sign_test_rows,
    table_i,
    table_ii,
    table_iii,
    table_iv,
    table_passive,
    table_v_rows,
    write_table,
)

__all__ = [
    "plot_signals", "plot_twitch_dependence", "plot_predictions", "plot_j_vs_horizon", "plot_delay_scan",
    "plot_delay_angle", "plot_posterior_j_vs_horizon", "plot_posterior_predictions", "plot_plan_predictions",
    "plot_recording",
    "plot_shrinkage", "plot_delay_posterior", "plot_leg_predictions", "write_report",
    "plot_trends", "plot_correlations", "plot_twitch_average", "plot_spectrum", "plot_loo_pit", "plot_elpd_in_time",
    "residual_figures", "predictive_checks", "ranking_markdown", "discovery_markdown",
    "markdown_table", "write_table", "active_legs", "table_passive", "table_i", "table_ii", "table_iii", "table_iv",
    "table_v_rows", "sign_test_rows",
]  # fmt: skip
