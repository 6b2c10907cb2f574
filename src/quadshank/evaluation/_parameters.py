"""Credible parameters of a saved fit at the leg, subject and population levels."""

from __future__ import annotations

import numpy as np

from ..inference._summaries import interval, pooled_draws
from ..model._effects import from_unconstrained, prior_arrays


def _pooled64(post, name: str) -> np.ndarray:
    """A posterior variable's draws, chains pooled, in double precision."""
    return pooled_draws(post, name).astype(np.float64)


def _components(name: str, shape) -> list[tuple[str, tuple]]:
    """(label, index) of each component: ``a[1]``, ``a[2]`` (the paper's a1, a2) for a vector parameter."""
    if not shape:
        return [(name, ())]
    return [(f"{name}[{k + 1}]", (k,)) for k in range(int(np.prod(shape)))]


def leg_parameters(idata, desc: dict, fit_legs: dict) -> dict:
    """Credible parameters per leg at the leg, subject and population levels.

    Returns ``{leg: {label: {"units", "doc", "prior", "leg", "subject", "population"}}}``
    with each level ``{"median", "lo", "hi"}`` (None where the parameter has no such
    level: the noise parameters).  A leg's level is the fit summary's numbers (``fit_legs``:
    ``FitResult.legs``).
    """
    post = idata.posterior
    subjects = list(desc["subjects"])
    out: dict = {}
    for i, leg in enumerate(desc["legs"]):
        s_idx = int(desc["leg_subject"][i])
        rows: dict = {}
        for name, info in desc["params"].items():
            shape = tuple(info["shape"])
            loc, scale = prior_arrays(info["prior"], shape)
            sub = _pooled64(post, f"{name}_subject")[:, s_idx] if f"{name}_subject" in post else None
            mu = _pooled64(post, f"{name}_mu") if f"{name}_mu" in post else None
            if mu is not None and f"{name}_s_leg" not in post:
                mu = from_unconstrained(mu, info["prior"])  # the non-centred form samples it unconstrained
            leg_q = fit_legs[leg]["params"][name]
            for label, index in _components(name, info["shape"]):
                rows[label] = {
                    "units": info["units"],
                    "doc": info.get("doc", ""),
                    "prior": [info["prior"][0], float(loc[index]), float(scale[index])],
                    "leg": {k: float(np.asarray(leg_q[k], float)[index]) for k in ("median", "lo", "hi")},
                    "subject": None if sub is None else interval(sub[(slice(None), *index)]),
                    "population": None if mu is None else interval(mu[(slice(None), *index)]),
                }
        for name, info in desc["noise"].items():
            q = fit_legs[leg]["params"][name]
            rows[name] = {"units": info["units"], "doc": info.get("doc", ""), "prior": None,
                          "leg": {k: float(q[k]) for k in ("median", "lo", "hi")}, "subject": None, "population": None}
        out[leg] = {"subject": subjects[s_idx], "params": rows}
    return out


def population_spreads(idata, desc: dict) -> dict:
    """Spread between subjects and between legs [units of the prior's scale] per parameter component."""
    post = idata.posterior
    out = {}
    for name, info in desc["params"].items():
        for label, index in _components(name, info["shape"]):
            row = {}
            for key, var in (("sd_subject", f"{name}_sd_subject"), ("sd_leg", f"{name}_sd_leg")):
                if var in post:
                    row[key] = interval(_pooled64(post, var)[(slice(None), *index)])
            out[label] = row
    return out
