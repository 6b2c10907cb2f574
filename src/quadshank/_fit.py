"""Hierarchical Bayesian identification with NUTS (numpyro).

The numpyro model is generated from the Model's declared parameters
(:class:`quadshank._effects.Param`).  Each parameter with prior
``(family, loc, scale)`` lives on an unconstrained scale x (log θ for a
``lognormal`` prior, θ itself for ``normal``) and is built non-centred down to
its declared level:

    x_leg = μ + τ_subject · z_subject[s(leg)] + τ_leg · z_leg[leg]
    μ ~ Normal(loc, scale)        population mean, the declared prior
    τ_subject, τ_leg ~ HalfNormal(scale)
    z ~ Normal(0, 1)

so the declared prior is the population-level belief and the spread between
subjects and between the legs of a subject is learnt (weakly informative: at
most about one prior scale).  By default the legs are sampled directly
(centred) with the subject level integrated out analytically,

    x_leg ~ MultivariateNormal(μ, τ_subject² S + τ_leg² I),  S_ij = [legs i, j share a subject],

because each leg's thousands of samples pin its values down: with such
informative data the non-centred form turns the data's precision into a
narrow ridge between μ, τ and z, and a sampled subject level between μ and a
lone leg is a funnel.  Subject values (for shrinkage plots) are their
conditional means given the legs.  ``FitSettings(centred=False)`` gives the
fully non-centred form for sparse data.  A dense mass matrix absorbs the remaining linear correlations
(k1 with k2, gain with the gain factors).  Noise (Student-t, see
:mod:`quadshank._likelihood`) is per leg: σ ~ LogNormal(log 40 deg/s², 1),
ν ~ Gamma(2, 0.1).  The delay d of each leg has a uniform prior on 0 … 10
samples and is summed out exactly; P(d | data) is the posterior mean of the
per-draw conditional P(d | θ, data), and one d per draw is drawn from that
conditional for the pointwise log-likelihood (so PSIS-LOO is over (θ, d)).
"""

from __future__ import annotations

import dataclasses
import json
import math
import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from numpyro.infer import MCMC, NUTS, init_to_median

from ._cohort import Cohort
from ._effects import Param, get_effect
from ._likelihood import (
    N_DELAYS,
    LikelihoodData,
    leg_loglik_by_delay,
    leg_pointwise,
    prepare,
)
from ._model import Model, paper_model

__all__ = [
    "FitSettings",
    "model_params",
    "numpyro_model",
    "fit",
    "build_model",
    "NOISE_PARAMS",
]

#: Noise parameters per leg: name -> (units, doc).
NOISE_PARAMS = {
    "sigma": ("deg/s^2", "Student-t scale of one sample of equivalent acceleration"),
    "nu": ("1", "Student-t degrees of freedom"),
}
SIGMA_PRIOR = (math.log(40.0), 1.0)
NU_PRIOR = (2.0, 0.1)


@dataclasses.dataclass(frozen=True)
class FitSettings:
    chains: int = 4
    warmup: int = 1000
    draws: int = 1000
    seed: int = 0
    target_accept: float = 0.9
    max_tree_depth: int = 8
    centred: bool = True
    dense_mass: bool = True
    trials: tuple[int, ...] = (1,)


def build_model(name: str, add_effects=()) -> Model:
    """One of the paper's models, optionally extended by registered effects (by name or instance)."""
    base = paper_model(name)
    extra = [get_effect(e)() if isinstance(e, str) else e for e in add_effects]
    if not extra:
        return base
    suffix = "+".join(e.name for e in extra)
    return base.add(*extra, name=f"{base.name}+{suffix}")


def model_params(model: Model) -> list[Param]:
    """The declared parameters of every effect, in order."""
    return [p for e in model.effects for p in e.declared_params()]


def _arr(v, shape):
    return jnp.broadcast_to(jnp.asarray(v, jnp.float32), shape)


def _hierarchical(p: Param, n_legs: int, n_subjects: int, leg_subject, centred: bool = True):
    """Sample one parameter down to its level; returns the leg values (and records subject values)."""
    family, loc, scale = p.prior[:3]
    shape = tuple(p.shape)
    loc = _arr(loc, shape)
    scale = _arr(scale, shape)
    transform = jnp.exp if family == "lognormal" else (lambda x: x)
    ev = len(shape)
    mu = numpyro.sample(f"{p.name}_mu", dist.Normal(loc, scale).to_event(ev))
    x_subject = jnp.broadcast_to(mu, (n_subjects, *shape))
    if p.level == "leg" and centred:
        # legs sampled directly, the subject level integrated out analytically:
        # x_leg ~ MVN(μ, τ_s² S + τ_l² I), S[i, j] = 1 when legs i and j share a subject
        tau_s = numpyro.sample(f"{p.name}_sd_subject", dist.HalfNormal(scale).to_event(ev))
        tau_l = numpyro.sample(f"{p.name}_sd_leg", dist.HalfNormal(scale).to_event(ev))
        same = (leg_subject[:, None] == leg_subject[None, :]).astype(jnp.float32)
        onehot = (leg_subject[None, :] == jnp.arange(n_subjects)[:, None]).astype(jnp.float32)  # (S, L)
        n_per = onehot.sum(axis=1)
        comps = []
        for c in range(int(np.prod(shape)) if shape else 1):
            m, ts, tl = (v.reshape(-1)[c] if shape else v for v in (mu, tau_s, tau_l))
            cov = ts**2 * same + tl**2 * jnp.eye(n_legs)
            comps.append((m, ts, tl, cov))
        if shape:
            x_leg = numpyro.sample(
                f"{p.name}_x_leg",
                dist.MultivariateNormal(
                    jnp.stack([jnp.full(n_legs, m) for m, *_ in comps], -1).T,
                    jnp.stack([cov for *_, cov in comps]),
                ).to_event(1),
            ).T
        else:
            m, _, _, cov = comps[0]
            x_leg = numpyro.sample(f"{p.name}_x_leg", dist.MultivariateNormal(jnp.full(n_legs, m), cov))
        # subject values for reports: their conditional mean given the legs (Sherman–Morrison)
        dev = onehot @ (x_leg - mu)  # (S, *shape)
        n_b = n_per.reshape((-1,) + (1,) * ev)
        x_subject = mu + tau_s**2 * dev / (tau_l**2 + n_b * tau_s**2)
    else:
        if p.level in ("subject", "leg"):
            tau_s = numpyro.sample(f"{p.name}_sd_subject", dist.HalfNormal(scale).to_event(ev))
            with numpyro.plate("subjects", n_subjects):
                if centred:
                    x_subject = numpyro.sample(f"{p.name}_x_subject", dist.Normal(mu, tau_s).to_event(ev))
                else:
                    z = numpyro.sample(f"{p.name}_z_subject", dist.Normal(jnp.zeros(shape), 1.0).to_event(ev))
                    x_subject = mu + tau_s * z
        x_leg = x_subject[leg_subject]
        if p.level == "leg":
            tau_l = numpyro.sample(f"{p.name}_sd_leg", dist.HalfNormal(scale).to_event(ev))
            with numpyro.plate("legs", n_legs):
                z = numpyro.sample(f"{p.name}_z_leg", dist.Normal(jnp.zeros(shape), 1.0).to_event(ev))
                x_leg = x_leg + tau_l * z
    leg_values = numpyro.deterministic(p.name, transform(x_leg))
    numpyro.deterministic(f"{p.name}_subject", transform(x_subject))
    return leg_values


def numpyro_model(model: Model, data: LikelihoodData, arrays: dict | None = None, centred: bool = True):
    """The hierarchical numpyro model of ``model`` on ``data`` (delay summed out)."""
    x = arrays if arrays is not None else data.leg_arrays()
    n_legs, n_subjects = data.n_legs, len(data.subjects)
    leg_subject = jnp.asarray(data.leg_subject)
    values = {p.name: _hierarchical(p, n_legs, n_subjects, leg_subject, centred) for p in model_params(model)}
    with numpyro.plate("legs", n_legs):
        sigma = numpyro.sample("sigma", dist.LogNormal(*SIGMA_PRIOR))
        nu = numpyro.sample("nu", dist.Gamma(*NU_PRIOR))
    # the delay leaf is unused here (summed out below) but must carry the leg axis
    stacked = model.with_params(values, delay=jnp.zeros(n_legs, jnp.int32))
    R = data.response_length
    ll = jax.vmap(lambda m, s, n, xi: leg_loglik_by_delay(m, {"sigma": s, "nu": n}, xi, R))(stacked, sigma, nu, x)
    logp = ll - math.log(N_DELAYS)
    total = jax.scipy.special.logsumexp(logp, axis=-1)
    numpyro.deterministic("delay_logp", logp - total[:, None])
    numpyro.factor("likelihood", jnp.sum(total))


def fit(
    cohort: Cohort,
    model: Model,
    settings: FitSettings = FitSettings(),
    legs=None,
    progress: bool = True,
):
    """Run NUTS; returns (mcmc, data)."""
    data = prepare(cohort, model, trials=settings.trials, legs=legs)
    arrays = data.leg_arrays()
    kernel = NUTS(
        numpyro_model,
        target_accept_prob=settings.target_accept,
        max_tree_depth=settings.max_tree_depth,
        init_strategy=init_to_median(num_samples=15),
        dense_mass=settings.dense_mass,
    )
    mcmc = MCMC(
        kernel,
        num_warmup=settings.warmup,
        num_samples=settings.draws,
        num_chains=settings.chains,
        chain_method="sequential",
        progress_bar=progress,
    )
    mcmc.run(jax.random.PRNGKey(settings.seed), model, data, arrays, settings.centred, extra_fields=("diverging", "energy", "num_steps"))
    return mcmc, data


# ============================================================================ after sampling


def leg_models(model: Model, posterior: dict[str, np.ndarray]) -> Model:
    """``model`` with leaves of shape (draws, legs, ...) taken from flat posterior arrays."""
    values = {p.name: jnp.asarray(posterior[p.name]) for p in model_params(model)}
    lead = next(iter(values.values())).shape[:2]
    return model.with_params(values, delay=jnp.zeros(lead, jnp.int32))


def sample_delays(delay_logp: np.ndarray, seed: int) -> np.ndarray:
    """One d per draw and leg from P(d | θ, data) (Gumbel-max); delay_logp (..., legs, D)."""
    g = jax.random.gumbel(jax.random.PRNGKey(seed + 1), delay_logp.shape)
    return np.asarray(jnp.argmax(jnp.asarray(delay_logp) + g, axis=-1))


def pointwise_loglik(model: Model, data: LikelihoodData, posterior: dict, delays: np.ndarray, chunk: int = 64):
    """log p(segment | θ, d) per draw, leg and 1-s segment: array (draws, legs, segments)."""
    x = data.leg_arrays()
    R = data.response_length
    S = data.n_segments

    def one_draw(m, s, n, d):
        return jax.vmap(lambda mi, si, ni, xi, di: leg_pointwise(mi, {"sigma": si, "nu": ni}, xi, di, R, S))(
            m, s, n, x, d
        )

    stacked = leg_models(model, posterior)
    f = jax.jit(lambda m, s, n, d: jax.vmap(one_draw)(m, s, n, d))
    n_draws = delays.shape[0]
    out = []
    for i in range(0, n_draws, chunk):
        sl = slice(i, min(i + chunk, n_draws))
        m = jax.tree_util.tree_map(lambda v: v[sl], stacked)
        out.append(np.asarray(f(m, posterior["sigma"][sl], posterior["nu"][sl], jnp.asarray(delays[sl]))))
    ll = np.concatenate(out, axis=0)
    return np.where(data.segment_mask[None], ll, np.nan)


def describe_fit(model: Model, data: LikelihoodData, settings: FitSettings) -> dict:
    return {
        "model": model.name,
        "effects": [e.name for e in model.effects],
        "params": {
            p.name: {"units": p.units, "prior": list(p.prior), "level": p.level, "shape": list(p.shape), "doc": p.doc}
            for p in model_params(model)
        },
        "noise": {k: {"units": u, "doc": doc} for k, (u, doc) in NOISE_PARAMS.items()},
        "legs": list(data.legs),
        "subjects": list(data.subjects),
        "leg_subject": [int(i) for i in data.leg_subject],
        "trials": list(data.trials),
        "resolution": data.resolution,
        "settings": dataclasses.asdict(settings),
        "sampling_period_s": model.sampling_period_s,
    }


def model_from_description(desc: dict) -> Model:
    """Rebuild the (unparameterised) Model a fit was made with."""
    effects = [get_effect(n)() for n in desc["effects"]]
    return Model(tuple(effects), name=desc["model"], sampling_period_s=desc.get("sampling_period_s", 0.01))


def to_json(desc: dict) -> str:
    return json.dumps(desc, sort_keys=True)


def from_json(text: str) -> dict:
    return json.loads(text)
