"""Posterior summaries shared by every stage: the interval quadshank reports, and draws pooled over chains."""

from __future__ import annotations

import arviz as az
import numpy as np

__all__ = ["INTERVAL", "THRESHOLDS", "interval", "pooled_draws"]

#: Acceptance of a fit: R-hat below, ESS (bulk and tail) at least per chain, no divergence, E-BFMI above.
THRESHOLDS = {"rhat_max": 1.01, "ess_per_chain": 100, "divergences": 0, "bfmi_min": 0.3}

#: Quantiles of the equal-tailed 90 % interval reported everywhere.
INTERVAL = (0.05, 0.95)


def interval(draws, axis: int = 0) -> dict:
    """Median and equal-tailed 90 % interval (quantiles :data:`INTERVAL`) of ``draws`` along ``axis``.

    ``{"median", "lo", "hi"}``: floats for one-dimensional draws, nested lists otherwise.
    arviz reports equal-tailed intervals only inside ``az.summary``'s table (its ``az.hdi``
    is the highest-density interval, another quantity); this is the same quantile of
    the same draws, kept as arrays.
    """
    draws = np.asarray(draws)
    # draws of +inf (a J whose predictions diverged) are ordered last; interpolating between two of
    # them would give inf − inf, so there each quantile is a draw's own value
    method = "linear" if np.isfinite(draws).all() else "inverted_cdf"
    lo, hi = np.quantile(draws, INTERVAL, axis=axis, method=method)
    return {"median": np.median(draws, axis=axis).tolist(), "lo": lo.tolist(), "hi": hi.tolist()}


def pooled_draws(posterior, name: str) -> np.ndarray:
    """The draws of posterior variable ``name`` with the chains pooled: array (chains·draws, ...),
    chain after chain (``az.extract``'s ``sample`` axis, moved first)."""
    var = az.extract(posterior, var_names=[name], combined=True, keep_dataset=False)
    return np.asarray(var.transpose("sample", ...).values)
