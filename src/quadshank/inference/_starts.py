"""Where the chains start when they do not start from the screen: the classical estimate, jittered."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np

from ..data._cohort import Cohort
from ..model._likelihood import LikelihoodData
from ..model._model import Model
from ._identify import IdentificationError, identify_leg
from ._priors import model_params

#: Classical models whose estimates start a model's chains (model3s: model 2's twitch, model 3's gains).
CLASSICAL_SOURCES = {"model3s": ("model3", "model2")}


#: Spread of the chains' starting points about the classical estimate [prior scales].
INIT_JITTER = 0.05


#: A classical estimate further than this from the prior median [prior scales] is not used.
INIT_MAX_Z = 3.0


def classical_start(cohort: Cohort, model: Model, data: LikelihoodData, trial: int) -> dict:
    """Standardised leg values ``{p}_s_leg`` at the classical least-squares identification.

    Each d gives its own best (a, b) or gain, so the posterior over the continuous
    parameters has one mode per delay; chains started at the prior median settle
    in whichever mode is near and rarely leave it (a model-2 chain on data with
    d = 4 stayed at d = 3).  The paper's identification (model 2 over every d, the
    smallest residual) finds the leading mode, and the chains start there.  A leg
    the classical identification cannot handle (too few isolated twitches) starts
    its values at the prior median (s = 0), with a warning; so does an estimate more
    than ``INIT_MAX_Z`` prior scales out (least squares running along a ridge the data
    do not close); parameters it does not estimate (an added effect's) are left to
    the prior median.
    """

    base = model.name.split("+")[0]
    per_leg = []
    for leg in data.legs:
        try:
            ident = identify_leg(cohort.get(leg, trial))
            values = {}
            for source in CLASSICAL_SOURCES.get(base, (base,)):
                values.update(ident.models[source].params() if source in ident.models else {})
            per_leg.append(values)
        except (IdentificationError, KeyError, ValueError) as exc:
            warnings.warn(f"{leg}: chains start at the prior median, not the classical estimate ({exc})", stacklevel=2)
            per_leg.append({})
    out = {}
    for p in model_params(model):
        if p.level != "leg" or not any(p.name in v for v in per_leg):
            continue
        cols = []
        for v in per_leg:
            if p.name not in v:
                cols.append(np.zeros(p.shape))
                continue
            z = p.to_standard(v[p.name])
            # beyond INIT_MAX_Z prior scales the least squares ran along a ridge the data do
            # not close (k1 with k2 and G' when the knee stays out of flexion): prior median
            cols.append(np.where(np.isfinite(z) & (np.abs(z) <= INIT_MAX_Z), z, 0.0))
        s = np.stack(cols, axis=-1)  # (*shape, L): (L,) scalar, (C, L) vector
        out[f"{p.name}_s_leg"] = s.reshape(-1, len(data.legs)) if p.shape else s
    return out


def _init_near(site=None, values=None, jitter=INIT_JITTER, fallback=None):
    """numpyro init strategy: ``values[name]`` plus N(0, jitter²) per chain; others from ``fallback``."""
    if site["name"] in values and site["type"] == "sample" and not site["is_observed"]:
        v = jnp.asarray(values[site["name"]], jnp.float32)
        key = site["kwargs"].get("rng_key")
        if key is None:
            return v
        return v + jitter * jax.random.normal(key, v.shape, v.dtype)
    return fallback(site)
