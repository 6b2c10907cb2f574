"""Hierarchical Bayesian identification with NUTS (numpyro): settings, the chains' start, the run.

The numpyro model itself is in :mod:`quadshank.inference._density`; its priors in
:mod:`quadshank.inference._priors`.  Chains start at each leg's mode from the screen
(:func:`screen_start`, :mod:`quadshank.inference._screen`), whose Laplace covariances are
also the metric: each d has its own mode in θ, the screen's multi-start optimisation of
the marginal posterior finds one, restarted at the delay that a Laplace approximation per
delay weighs most where that is another (:func:`delay_start`), and each leg's block is
narrow and correlated in a way a short warm-up cannot estimate.  The classical
least-squares start (:func:`quadshank.inference._starts.classical_start`) and the prior
median remain as options.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import io
import math
import sys
import time
import warnings

import arviz as az
import jax
import jax.numpy as jnp
import numpy as np
from numpyro import handlers
from numpyro.infer import MCMC, NUTS, init_to_median, init_to_uniform
from numpyro.infer.util import constrain_fn, potential_energy
from scipy import optimize

from ..common._random import numpy_rng
from ..common._arrays import is_whole_number
from ..common._interrupt import check_interrupt, interrupt_requested
from ..data._cohort import Cohort
from ..model._likelihood import (
    N_DELAYS,
    OBJECTIVES,
    LikelihoodData,
    chosen_legs,
    prepare,
)
from ..model._model import Model
from ._density import numpyro_model
from ._draws import hyper_draws
from ._priors import (
    STIFFNESS_SITE,
    model_params,
    step_param,
    stiffness_from_standard,
    stiffness_jacobian,
    stiffness_params,
)
from ._jumps import JumpBlocks, ModeJumpNUTS, refine_blocks
from ._screen import DelayModes, _hessian, delay_modes, laplace_fit, restart_screen
from ._starts import _init_near, classical_start
from ._summaries import THRESHOLDS

__all__ = [
    "FitSettings",
    "FitRun",
    "BlockDraws",
    "run_nuts",
    "target_status",
    "convergence_status",
    "model_params",
    "numpyro_model",
    "fit",
]

#: Where chains can start (:attr:`FitSettings.start`).
STARTS = ("screen", "classical", "prior")
#: Most chains a fit runs: every chain's draws are held in memory, and more chains than a
#: machine has cores or devices run one after another.
MAX_CHAINS = 64
#: Most warm-up or draws per chain (or per block): every draw of every parameter is held in memory.
MAX_DRAWS = 100_000
#: What :attr:`FitSettings.chain_method` takes.
CHAIN_METHODS = ("auto", "vectorized", "sequential", "parallel")
#: The precisions the fit's density can be evaluated at (:attr:`FitSettings.precision`).
PRECISIONS = ("mixed", "double")
#: Compared samples (all legs) from which chain_method "auto" runs the chains one after another.
SEQUENTIAL_FROM_SAMPLES = 100_000
#: The least P(d | data) (a leg alone, per-delay Laplace) of a delay whose mode the chains jump to
#: (:func:`jump_blocks`): below it a mode's share of the draws is too small to matter for the checks.
JUMP_MODE_FLOOR = 0.01


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
    #: numpyro's ``chain_method``: "vectorized" (all chains in one batched program),
    #: "sequential" (one after another), "parallel" (each chain on its own JAX device), or
    #: "auto": parallel where there are at least as many devices as chains (several GPUs, or
    #: CPU devices made with ``XLA_FLAGS=--xla_force_host_platform_device_count=N``) and no
    #: ``target_ess``, else
    #: sequential from :data:`SEQUENTIAL_FROM_SAMPLES` compared samples on, else vectorized
    #: (:func:`chain_method`).  The posterior is the same; the time is not.  On the 2-core CPU,
    #: model3s on 2 legs × 1.5 min (18 000 samples; the demo's fit, 2 chains × 150 + 150)
    #: took 32 s vectorized against 50 s sequential; model 3 + angle_delay on 5 legs × 5 min
    #: (150 000 samples; 4 chains × 100 + 100 from the screen) 116 s against 83 s.  Batched
    #: over 4 chains, that likelihood's gradient costs 2.2 single gradients per chain on the
    #: 150 000 samples, 0.8–1.0 on 30 000 or 60 000 (5 legs × 1 min, 2 legs × 5 min).
    chain_method: str = "auto"
    #: Where the chains start: "screen" (each leg's mode and Laplace covariance from the
    #: screen, which also give the metric; see :func:`screen_start`), "classical" (the
    #: classical least-squares estimate, jittered) or "prior" (the prior median).
    start: str = "screen"
    #: With ``start="screen"``, adapt the metric in warm-up as well (by default the screen's
    #: is kept and only the step size adapts); the other starts always adapt it.
    adapt_metric: bool = False
    #: With ``start="screen"``, weigh each leg's delays by a Laplace approximation per delay
    #: before sampling (:func:`delay_start`): the screen restarts at the best delay where it
    #: missed it, and the weights, stored in the fit, are checked against the chains' P(d):
    #: a delay holding ≥ 0.1 of that weight that no chain visits draws a warning.
    delay_evidence: bool = True
    #: With ``delay_evidence``: each NUTS transition is followed by Metropolis–Hastings jumps
    #: between each leg's delay modes in θ (:class:`quadshank.inference._jumps.ModeJumpNUTS`,
    #: :func:`jump_blocks`), which NUTS alone does not cross.
    mode_jumps: bool = True
    #: Draw to an effective sample size rather than a number of draws: after ``warmup`` and a first
    #: block of ``draws`` per chain, further blocks of ``draws`` follow until every check of the
    #: fit's R-hat and ESS passes with bulk and tail ESS at least this (and at least
    #: ``THRESHOLDS["ess_per_chain"]`` per chain), or until ``time_limit_s`` would pass
    #: (:func:`target_status`).  None: exactly ``warmup`` + ``draws``.
    target_ess: int | None = None
    #: With ``target_ess``: seconds from the fit's start (screen and compilation included) after
    #: which no further block is begun; a block that would end past it is not begun either.
    time_limit_s: float = 1800.0
    #: What the likelihood compares: "acceleration" (equation error: the equivalent acceleration,
    #: every model), "angle" (output error: runs from the measured state, free swings for the
    #: pendulum alone, 1-s shooting segments for a model with a muscle and no delay or noise
    #: effect) or "auto": the angle for the pendulum alone, the acceleration with a muscle
    #: (:func:`quadshank.model._likelihood.resolve_objective`).
    likelihood: str = "auto"
    #: The precision of the density NUTS samples: "mixed" (each sample's and window's terms at
    #: the data's single precision, as recorded, their sums and the parameters in double;
    #: :func:`quadshank.model._likelihood._at_data_precision`), or "double" throughout.  The
    #: angle objective is always double: its runs accumulate along the trial.
    precision: str = "mixed"

    def __post_init__(self):
        for name in ("chains", "warmup", "draws", "max_tree_depth", "seed", "target_ess"):
            v = getattr(self, name)
            if (v is not None or name != "target_ess") and not is_whole_number(v):
                raise ValueError(f"{_named(name)} must be a whole number, not {v!r}")
        for name in ("centred", "dense_mass", "adapt_metric", "delay_evidence", "mode_jumps"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"{name} must be True or False, not {getattr(self, name)!r}")
        trials = self.trials
        if isinstance(trials, (str, bytes)) or not hasattr(trials, "__iter__") or any(
                not is_whole_number(t) or t < 1 for t in trials):
            raise ValueError(f"trials: give the trial numbers to fit, whole numbers from 1 (a tuple: (1,)), not {trials!r}")
        object.__setattr__(self, "trials", tuple(int(t) for t in trials))
        if self.start not in STARTS:
            raise ValueError(f"start must be one of {', '.join(STARTS)}, not {self.start!r}")
        if self.chain_method not in CHAIN_METHODS:
            raise ValueError(f"chain_method must be one of {', '.join(CHAIN_METHODS)}, not {self.chain_method!r}")
        for name, least, most in (("chains", 1, MAX_CHAINS), ("warmup", 0, MAX_DRAWS), ("draws", 1, MAX_DRAWS),
                                  ("max_tree_depth", 1, 15)):
            if not least <= int(getattr(self, name)) <= most:
                raise ValueError(f"{_named(name)} must be at least {least} and at most {most}, not "
                                 f"{getattr(self, name)}")
        if not 0 <= int(self.seed) < 2**32:
            raise ValueError(f"{_named('seed')} must be a whole number from 0 to {2**32 - 1}, not {self.seed}")
        if not 0 < self.target_accept < 1:
            raise ValueError(f"{_named('target_accept')} must lie between 0 and 1, not {self.target_accept}")
        if not self.trials:
            raise ValueError("trials: give at least one trial to fit")
        if self.target_ess is not None and int(self.target_ess) < 1:
            raise ValueError(f"{_named('target_ess')} must be at least 1, not {self.target_ess}")
        if self.likelihood not in OBJECTIVES + ("auto",):
            raise ValueError(f"likelihood must be one of auto, {', '.join(OBJECTIVES)}, not {self.likelihood!r}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, not {self.precision!r}")
        if not self.time_limit_s > 0:
            raise ValueError(f"{_named('time_limit_s')} must be positive, not {self.time_limit_s}")


def _named(field: str) -> str:
    """A setting as Python and the command line name it: ``time_limit_s (--time-limit)``."""
    return f"{field} (--{field.removesuffix('_s').replace('_', '-')})"


def chain_method(settings: FitSettings, data: LikelihoodData) -> str:
    """numpyro's chain method for a fit of ``data``: the settings' own, or for "auto",
    "parallel" where JAX has a device for every chain (and the fit draws a fixed number: parallel
    chains compile their sampler again for every block of a fit to a target ESS), else "sequential"
    from :data:`SEQUENTIAL_FROM_SAMPLES` compared samples on, else "vectorized".  "parallel" asked
    for with fewer devices than chains runs "sequential" (numpyro's own fallback), with a warning."""
    devices = jax.local_device_count()
    method = settings.chain_method
    if method == "auto":
        if settings.chains > 1 and devices >= settings.chains and settings.target_ess is None:
            return "parallel"
        return "sequential" if int(np.sum(data.sample_mask)) >= SEQUENTIAL_FROM_SAMPLES else "vectorized"
    if method == "parallel" and devices < settings.chains:
        warnings.warn(f"chain_method 'parallel' needs a JAX device per chain: {settings.chains} chains, "
                      f"{devices} device{'s' if devices != 1 else ''}; the chains run one after another",
                      stacklevel=2)
        return "sequential"
    return method


def uses_screen(model: Model, settings: FitSettings) -> bool:
    """Whether the chains start from the screen: the screen's vector maps onto the standardised
    leg sites, and a parameter declared at the subject or population level has none (such a
    model starts as "classical" does)."""
    return settings.start == "screen" and settings.centred and all(p.level == "leg" for p in model_params(model))


def fit_screen(cohort: Cohort, model: Model, settings: FitSettings, legs=None, n_starts: int = 3, progress: bool = False):
    """The screen :func:`fit` starts its chains from (None where it starts otherwise, see
    :func:`uses_screen`); computed ahead so that :func:`quadshank.inference._screen.delay_evidence` can
    start from it too."""

    if not uses_screen(model, settings):
        return None
    if progress:
        print("fit: each leg's mode and Laplace covariance (the screen) for the chains' start and metric",
              file=sys.stderr, flush=True)
    return laplace_fit(cohort, model, trials=settings.trials, legs=legs, n_starts=n_starts,
                       n_draws=max(settings.chains, 2), seed=settings.seed, loo=False, objective=settings.likelihood)


def delay_start(cohort: Cohort, settings: FitSettings, screen, log_delay_prior=None, progress: bool = False):
    """Each leg's delays weighed by a Laplace approximation per delay, and the screen restarted
    where it missed the best of them.  Returns ``(screen, evidence, moved, modes)``.

    The screen's L-BFGS of the marginal posterior settles in the basin it starts in, and
    where each delay has its own mode in θ (model 3) that basin can be a delay's that
    holds little mass: on 18 s of TN-left (model3s + angle_delay) the screen sat at
    d = 3 while the mode at d = 4 had a log density 120 higher, and the chains, started
    there, never left d = 3.  :func:`quadshank.inference._screen.delay_modes` finds every delay's
    mode; where that evidence (times ``log_delay_prior``, the fit's delay prior) gives the
    delay the screen sits at (its P(d)'s mode) less than half of what it gives the best
    delay, the leg is screened again from the best delay's mode.  Where the data do not
    tell the delays apart (model 1, whose window sums cannot see d) the screen stays.
    ``evidence``: (legs, 11) P(d | data) of each leg alone; ``moved``: ``{leg: (d of the
    old screen, d of the new)}``.
    """

    dm = delay_modes(screen)
    evidence = dm.probability
    if log_delay_prior is not None:  # the fit's delay prior, not the evidence's uniform one
        evidence = evidence * np.exp(np.asarray(log_delay_prior, np.float64))
        evidence = evidence / evidence.sum(axis=1, keepdims=True)
    best = evidence.argmax(axis=1)
    sits = screen.delay_posterior.argmax(axis=1)
    starts, moved = {}, {}
    for i, leg in enumerate(screen.legs):
        if evidence[i, sits[i]] < 0.5 * evidence[i, best[i]]:
            starts[leg] = dm.modes[i, best[i]]
            moved[leg] = (int(sits[i]), int(best[i]))
    if starts:
        if progress:
            print("fit: the screen restarted at the delay the evidence weighs most: "
                  + ", ".join(f"{leg} d = {a} -> {b}" for leg, (a, b) in moved.items()), file=sys.stderr, flush=True)
        screen = restart_screen(screen, cohort, starts, trials=settings.trials, seed=settings.seed)
    return screen, evidence, moved, dm


def screen_start(model: Model, data: LikelihoodData, settings: FitSettings, conditioned, arrays, scr):
    """Starting points and a metric for NUTS from the per-leg screen (:mod:`quadshank.inference._screen`).

    ``scr``: the screen of the fit's legs (:func:`fit_screen`).

    Returns ``(init_params, inverse_mass_matrix)``: unconstrained values per chain
    (chain c of leg i starts at the c-th Laplace draw of that leg) and a dense inverse
    metric holding each leg's Laplace covariance.  Each leg's thousands of samples
    make its block nearly Gaussian and very narrow (posterior sds down to 1e-3 prior
    scales, correlated k1–k2, a–b, gain–gain factors); a metric estimated from a short
    warm-up misses that, and chains that start at different points settle at
    different delays.  The screen's multi-start optimisation of the marginal
    posterior finds the leading mode and the Laplace covariance is the metric for it.
    The legs are the whole latent vector (the levels above them are summed out), and
    the legs are coupled only through their prior, so the metric is block-diagonal.
    """

    chains = settings.chains
    if scr.legs != data.legs or scr.draws.shape[1] < chains:
        raise ValueError(f"the screen is of legs {', '.join(scr.legs)} with {scr.draws.shape[1]} draws; "
                         f"the fit needs {', '.join(data.legs)} and {chains}: make it with fit_screen()")
    names, shapes, offsets, kept, positions = _latent_layout(data, settings, conditioned, arrays, scr)
    n, L = sum(math.prod(s) for s in shapes.values()), data.n_legs
    draws, covariance = scr.draws[:, :chains], scr.covariance
    carry = _stiffness_carrier(scr, settings)
    if carry is not None:
        draws, covariance = carry(draws), carry.covariance(covariance, scr.mode)

    inits = np.zeros((chains, n))
    imm = np.zeros((n, n))
    covered = np.zeros(n, bool)
    for i in range(L):
        idx = positions(i)
        imm[np.ix_(idx, idx)] = covariance[i][np.ix_(kept, kept)]
        inits[:, idx] = draws[i][:, kept]
        covered[idx] = True
    if not covered.all():
        missing = [k for k in names if not covered[offsets[k] : offsets[k] + math.prod(shapes[k])].all()]
        raise ValueError(f"the screen gives no start for {', '.join(missing)}; use start='classical' or 'prior'")
    if step_param(model, data) is not None:
        noise = np.concatenate([offsets["sigma"] + np.arange(L), offsets["nu"] + np.arange(L)])
        _noise_at_the_fits_density(conditioned, arrays, names, shapes, offsets, noise, inits, imm, settings.seed)
    init_params = {}
    for k in names:
        shape = shapes[k]
        v = inits[:, offsets[k] : offsets[k] + math.prod(shape)].reshape((chains, *shape))
        init_params[k] = jnp.asarray(v if chains > 1 else v[0], jnp.result_type(float))
    return init_params, {tuple(names): jnp.asarray(imm, jnp.result_type(float))}


def _latent_layout(data: LikelihoodData, settings: FitSettings, conditioned, arrays, scr):
    """Where the screen's vectors sit in numpyro's flattened latent vector.

    Returns ``(names, shapes, offsets, kept, positions)``: the latent sites in numpyro's order
    (sorted by name), their shapes and offsets; ``kept`` (the screen's dim,) the entries of the
    screen's vector the fit samples (a parameter the fit sums out, a step delay effect's
    threshold, has no site); ``positions(i)``: where leg i's kept entries lie.
    """

    def latent_values(arrays):
        trace = handlers.trace(handlers.seed(conditioned, settings.seed)).get_trace(arrays)
        return {k: v["value"] for k, v in trace.items() if v["type"] == "sample" and not v["is_observed"]}

    # the latent sites' shapes, traced abstractly: nothing drawn, nothing compiled
    shapes = {k: tuple(v.shape) for k, v in jax.eval_shape(latent_values, arrays).items()}
    names = sorted(shapes)  # numpyro's order of the flattened latent vector
    offsets, n = {}, 0
    for k in names:
        offsets[k] = n
        n += math.prod(shapes[k])
    L = data.n_legs
    stiffness = stiffness_params(scr.model, settings.centred)

    def site(s):
        """The latent site of a screen parameter: G′'s is the stiffness at rest where the fit samples
        that (:func:`_stiffness_carrier` carries the screen's entry there)."""
        return STIFFNESS_SITE if stiffness is not None and s.name == stiffness[0].name else f"{s.name}_s_leg"

    # a parameter the fit sums out (a step delay effect's threshold) has no site: its entries of
    # the screen's vector are dropped, and the Laplace covariance of the rest is the block of it
    kept = np.concatenate([np.full(s.size, site(s) in offsets) for s in scr.specs] + [np.ones(2, bool)])

    def positions(i):
        """Where leg i's screen vector (z per parameter, log σ, log ν; kept entries) sits in the latent vector."""
        out = []
        for s in scr.specs:
            site_ = site(s)
            if site_ in offsets:
                out += [offsets[site_] + (c * L + i if s.shape else i) for c in range(s.size)]
        return np.asarray(out + [offsets["sigma"] + i, offsets["nu"] + i])

    return names, shapes, offsets, kept, positions


@dataclasses.dataclass(frozen=True)
class _StiffnessCarrier:
    """Carries the screen's vectors (z per parameter, log σ, log ν) to the fit's coordinates where the
    fit samples the stiffness at rest in place of G′ (:func:`quadshank.inference._priors.stiffness_params`):
    G′'s entry becomes the stiffness coordinate; a covariance is carried by the Jacobian at a point."""

    params: tuple
    index: tuple  # the screen vector's entries of G′, k1 and k2

    def __call__(self, vectors: np.ndarray) -> np.ndarray:
        out = np.array(vectors, np.float64, copy=True)
        g, a, b = self.index
        out[..., g] = stiffness_from_standard(out[..., g], out[..., a], out[..., b], self.params)
        return out

    def covariance(self, covariances: np.ndarray, at: np.ndarray) -> np.ndarray:
        """Covariances (..., dim, dim) in the screen's coordinates, carried at the points ``at`` (..., dim)."""
        cov = np.array(covariances, np.float64, copy=True)
        flat_cov, flat_at = cov.reshape(-1, *cov.shape[-2:]), np.asarray(at, np.float64).reshape(-1, cov.shape[-1])
        g, a, b = self.index
        for c, x in zip(flat_cov, flat_at):
            jac = np.eye(c.shape[0])
            jac[g, [g, a, b]] = stiffness_jacobian(x[g], x[a], x[b], self.params)
            c[...] = jac @ c @ jac.T
        return flat_cov.reshape(cov.shape)


def _stiffness_carrier(scr, settings: FitSettings) -> _StiffnessCarrier | None:
    """The carrier from the screen ``scr``'s coordinates to the fit's, or None where they are the same."""
    params = stiffness_params(scr.model, settings.centred)
    if params is None:
        return None
    offsets = np.cumsum([0] + [s.size for s in scr.specs])
    where = {s.name: int(offsets[j]) for j, s in enumerate(scr.specs)}
    return _StiffnessCarrier(params, tuple(where[p.name] for p in params))


def _at_sites(model: Model, start: dict, n_legs: int) -> dict:
    """Standardised leg values ``{p}_s_leg`` as the fit's latent sites: G′'s as the stiffness at rest
    where the fit samples that (:func:`quadshank.inference._priors.stiffness_params`)."""
    params = stiffness_params(model)
    if params is None or f"{params[0].name}_s_leg" not in start:
        return start
    out = dict(start)
    s_g = np.asarray(out.pop(f"{params[0].name}_s_leg"))
    s_k1, s_k2 = (np.asarray(out.get(f"{p.name}_s_leg", np.zeros(n_legs))) for p in params[1:])
    out[STIFFNESS_SITE] = stiffness_from_standard(s_g, s_k1, s_k2, params)
    return out


def jump_blocks(data: LikelihoodData, settings: FitSettings, conditioned, arrays, scr, modes: DelayModes,
                evidence: np.ndarray, floor: float = JUMP_MODE_FLOOR) -> JumpBlocks | None:
    """The legs whose chains jump between delay modes (:class:`ModeJumpNUTS`), or None.

    A leg's modes are those of the delays that hold at least ``floor`` of its P(d | data)
    (``evidence``, the per-delay Laplace weights of :func:`delay_start`, a leg alone) and
    the delays next to the best: the fit's posterior can move weight the leg-alone evidence
    does not see (pooling across legs; a step delay effect whose threshold the fit sums out
    where the screen holds a smooth one).  On 20 legs × 1 min (model 3 + ``angle_delay``) a
    leg the evidence gave d = 4 alone settled at d = 4 in one chain and at d = 5, at the same
    energy, in three.  Each mode's Gaussian is that of
    :func:`quadshank.inference._screen.delay_modes` over the model's parameters; log σ and
    log ν stay where the chain has them (delays that fit about equally well leave about the
    same noise, and the fit's noise can sit away from the screen's, see
    :func:`_noise_at_the_fits_density`).
    """
    if modes is None or modes.covariances is None or evidence is None:
        return None
    _, _, _, kept, positions = _latent_layout(data, settings, conditioned, arrays, scr)
    carry = _stiffness_carrier(scr, settings)
    K = data.max_shift
    params = kept.copy()
    params[-2:] = False  # log σ, log ν
    rows = []
    for i, leg in enumerate(data.legs):
        ev = np.asarray(evidence[i], np.float64)
        best = int(ev.argmax())
        wanted = (ev >= floor) | (np.abs(np.arange(N_DELAYS) - best) == 1)
        found = []
        for d in np.flatnonzero(wanted & np.isfinite(modes.log_evidence[i])):
            mode, cov = modes.modes[i, d], modes.covariances[i, d]
            if carry is not None:
                mode, cov = carry(mode), carry.covariance(cov, mode)
            cov = cov[np.ix_(params, params)]
            try:
                chol = np.linalg.cholesky(0.5 * (cov + cov.T))
            except np.linalg.LinAlgError:
                continue
            # a delay effect that shortens d by a shift: each (d, shift) can hold a mode of its own,
            # all started from the delay's (refine_blocks moves each to its own)
            found += [(int(d) * (K + 1) + s, mode[params], chol) for s in range(min(K, int(d)) + 1)]
        if len(found) >= 2:
            rows.append((i, positions(i)[:-2], found))
    if not rows:
        return None
    J, M, k = len(rows), max(len(f) for _, _, f in rows), len(rows[0][1])
    mean, chol = np.zeros((J, M, k)), np.tile(np.eye(k), (J, M, 1, 1))
    valid, delays = np.zeros((J, M), bool), np.full((J, M), -1)
    for j, (_, _, found) in enumerate(rows):
        for m, (d, mu, c) in enumerate(found):
            mean[j, m], chol[j, m], valid[j, m], delays[j, m] = mu, c, True, d
    return JumpBlocks(index=np.stack([idx for _, idx, _ in rows]), mean=mean, chol=chol, valid=valid,
                      legs=tuple(data.legs[i] for i, _, _ in rows), delays=delays,
                      leg=np.asarray([i for i, _, _ in rows]))


def _split_potential(model: Model, data: LikelihoodData, settings: FitSettings, log_delay_prior):
    """For :class:`ModeJumpNUTS`: a function of the model's arguments giving ``(leg_loglik,
    prior_potential)`` of the fit's numpyro model (its parts "legs" and "prior"), and with
    ``conditional=True`` a third, each leg's log p(y, d, shift | θ) (the labels of :func:`jump_blocks`)."""

    def with_legs(arrays):
        return numpyro_model(model, data, arrays, settings.centred, log_delay_prior, part="legs")

    def prior_only(arrays):
        return numpyro_model(model, data, arrays, settings.centred, log_delay_prior, part="prior")

    def split(model_args, model_kwargs, conditional=False):
        def values(z):
            return constrain_fn(with_legs, model_args, model_kwargs, z, return_deterministic=True)

        def leg_loglik(z):
            return values(z)["leg_loglik"]

        def prior_potential(z):
            return potential_energy(prior_only, model_args, model_kwargs, z)

        def by_delay(z):
            """log p(y, d, shift | θ) of each leg, (L, 11·(K + 1)): label d·(K + 1) + shift."""
            v = values(z)
            joint = v["delay_shift_logp"] if data.max_shift else v["delay_logp"]
            return v["leg_loglik"][:, None] + joint.reshape(data.n_legs, -1)

        return (leg_loglik, prior_potential, by_delay) if conditional else (leg_loglik, prior_potential)

    return split


def _noise_at_the_fits_density(conditioned, arrays, names, shapes, offsets, noise, inits, imm, seed) -> None:
    """Move the chains' start and metric for log σ and log ν (entries ``noise`` of the latent
    vector) to the fit's own density, in place.

    Where the fit sums out a step delay effect's threshold, the screen holds a smooth threshold
    as a parameter, and the pulses it places on the wrong side are outliers to it: on 30 s of
    TN-left (model3s + angle_delay) the screen's ν is 4.4 with a Laplace sd of 0.07 in log ν,
    where the fit's posterior has ν ≈ 37 and an sd of 0.32.  Chains started there with that
    metric travel 30 metric sds along ν and mix slowly.  Here the noise parameters are
    optimised under the fit's potential energy with the rest at the first chain's start
    (L-BFGS), their Gaussian there replaces their block of the metric (uncorrelated with the
    rest), and each chain starts at a draw from it.
    """

    base = inits[0].copy()

    def unflatten(vec):
        return {k: vec[offsets[k] : offsets[k] + math.prod(shapes[k])].reshape(shapes[k]) for k in names}

    def energy(s):
        vec = jnp.asarray(base).at[noise].set(s)
        return potential_energy(conditioned, (arrays,), {}, unflatten(vec))

    value_and_grad = jax.jit(jax.value_and_grad(energy))

    def f(s):
        val, g = value_and_grad(jnp.asarray(s, jnp.float64))
        return float(val), np.asarray(g, np.float64)

    res = optimize.minimize(f, base[noise], jac=True, method="L-BFGS-B")
    if not np.isfinite(res.fun):
        return
    mode, n = np.asarray(res.x, np.float64), noise.size
    H = _hessian(lambda v, _: value_and_grad(v), mode, None, step=1e-4)  # a Hessian of a few entries
    w, V = np.linalg.eigh(H)
    if not (np.all(np.isfinite(w)) and np.all(w > 0)):
        return
    cov = (V / w[None, :]) @ V.T
    imm[noise, :] = 0.0
    imm[:, noise] = 0.0
    imm[np.ix_(noise, noise)] = cov
    rng = numpy_rng(seed, "noise start")
    inits[:, noise] = mode[None, :] + (rng.standard_normal((inits.shape[0], n)) / np.sqrt(w)[None, :]) @ V.T


@dataclasses.dataclass(frozen=True)
class FitRun:
    """A finished NUTS run of :func:`run_nuts`, and how its chains were started."""

    mcmc: MCMC
    data: LikelihoodData
    #: (legs, 11) P(d | data) of each leg alone, from one Laplace approximation per delay (None: not weighed)
    delay_evidence: np.ndarray | None
    #: legs whose screen was restarted at another delay: leg -> (d before, d after)
    screen_restarted: dict
    #: seconds spent weighing the delays (None: not weighed), and on everything else up to the draws
    delay_evidence_seconds: float | None
    sampling_seconds: float
    #: with :attr:`FitSettings.target_ess`: how the blocks ended (:func:`target_status`, plus
    #: ``blocks``, ``stopped`` and ``seconds``); None for a fixed number of draws
    target: dict | None = None


def run_nuts(
    cohort: Cohort,
    model: Model,
    settings: FitSettings = FitSettings(),
    legs=None,
    progress: bool = True,
    log_delay_prior=None,
) -> FitRun:
    """The one path from data to posterior draws: the screen (the chains' start and metric,
    :func:`fit_screen`), each leg's delays weighed and the screen restarted where it missed the
    best (:func:`delay_start`), then NUTS.  ``log_delay_prior``: see :func:`delay_prior_from`.

    The log density NUTS samples is summed in double precision: that of five 5-minute
    legs is ~1e6, where single precision rounds it to ~0.06, and NUTS, seeing that noise
    in every energy difference, shrinks its step until the trees reach their depth (model
    3 + angle_delay, 5 legs × 5 min: 255 leapfrog steps per draw in single precision, 12 in
    double).  Its terms are computed at the data's precision (:attr:`FitSettings.precision`).
    """
    if not isinstance(model, Model):
        raise TypeError(f"model: give a Model (quadshank.build_model({model!r}) builds one from a name), not {model!r}"
                        if isinstance(model, str) else f"model: give a Model, not {type(model).__name__}")
    if not isinstance(settings, FitSettings):
        raise TypeError(f"settings: give a FitSettings, not {type(settings).__name__}")
    chosen_legs(cohort, legs, settings.trials)  # before the first progress line
    check_interrupt()  # no fit starts after an interrupt (recovery's next seed, say)
    t0 = time.perf_counter()
    screen = fit_screen(cohort, model, settings, legs=legs, progress=progress)
    evidence, moved, evidence_seconds, modes = None, {}, None, None
    muscle = model.activation.name != "no_muscle"  # the pendulum alone has no delay to weigh or jump between
    if screen is not None and settings.delay_evidence and muscle:
        if progress:
            print("fit: each leg's delays weighed by a Laplace approximation per delay", file=sys.stderr, flush=True)
        t1 = time.perf_counter()
        screen, evidence, moved, modes = delay_start(cohort, settings, screen, log_delay_prior, progress=progress)
        evidence_seconds = time.perf_counter() - t1
    jumps = (modes, evidence) if settings.mode_jumps and muscle else None
    with jax.enable_x64(True):
        mcmc, data = _fit(cohort, model, settings, legs, progress, log_delay_prior, screen, started=t0, jumps=jumps)
    # JAX dispatches asynchronously: the draws may still be computing when the run returns
    jax.block_until_ready(mcmc.get_samples(group_by_chain=True))
    sampling = time.perf_counter() - t0 - (evidence_seconds or 0.0)
    target = mcmc.target if isinstance(mcmc, BlockDraws) else None
    return FitRun(mcmc, data, evidence, moved, evidence_seconds, sampling, target)


def fit_arrays(data: LikelihoodData, settings: FitSettings) -> dict:
    """The leg arrays the fit's density takes (under JAX's x64): the data's floating arrays at
    their single precision for ``precision="mixed"`` on the acceleration, else in double."""
    single = settings.precision == "mixed" and data.objective == "acceleration"
    return {k: v.astype(jnp.float32 if single else jnp.float64) if jnp.issubdtype(v.dtype, jnp.floating) else v
            for k, v in data.leg_arrays().items()}


def fit(
    cohort: Cohort,
    model: Model,
    settings: FitSettings = FitSettings(),
    legs=None,
    progress: bool = True,
    log_delay_prior=None,
):
    """Run NUTS (:func:`run_nuts`); returns ``(mcmc, data)``, what :func:`quadshank.to_inference_data` takes."""
    run = run_nuts(cohort, model, settings, legs, progress, log_delay_prior)
    return run.mcmc, run.data


def _fit(cohort, model, settings, legs, progress, log_delay_prior, screen, started=None, jumps=None):
    data = prepare(cohort, model, trials=settings.trials, legs=legs, objective=settings.likelihood)
    arrays = fit_arrays(data, settings)
    if log_delay_prior is not None:
        log_delay_prior = np.asarray(log_delay_prior, np.float32)
        if log_delay_prior.shape != (data.n_legs, N_DELAYS):
            raise ValueError(f"log_delay_prior must have shape ({data.n_legs}, {N_DELAYS})")

    # the model and data are closed over, not passed as arguments: numpyro maps its
    # arguments as pytrees, and a Model must not be rebuilt from placeholder leaves
    def conditioned(arrays):
        return numpyro_model(model, data, arrays, settings.centred, log_delay_prior)

    init = init_to_median(num_samples=15)
    init_params, imm, blocks = None, None, None
    if screen is not None:
        init_params, imm = screen_start(model, data, settings, conditioned, arrays, screen)
        if jumps is not None:
            blocks = jump_blocks(data, settings, conditioned, arrays, screen, *jumps)
        if blocks is not None:
            if progress:
                print(f"fit: the delay modes of {blocks.n_legs} leg(s) located under the fit's density, for the chains' jumps",
                      file=sys.stderr, flush=True)
            split = _split_potential(model, data, settings, log_delay_prior)
            _, prior_potential, by_delay = split((arrays,), {}, conditional=True)
            start = {k: v[0] if settings.chains > 1 else v for k, v in init_params.items()}
            blocks = refine_blocks(blocks, start, by_delay, prior_potential)
        if blocks is not None and progress:
            print("fit: the chains jump between delay modes of "
                  + ", ".join(f"{leg} (d = {', '.join(str(d) for d in np.unique(ds[v] // (data.max_shift + 1)))})"
                              for leg, ds, v in zip(blocks.legs, blocks.delays, blocks.valid)),
                  file=sys.stderr, flush=True)
        init = init_to_uniform  # the start numpyro finds is replaced by init_params: no prior draws for it
        if not settings.dense_mass:
            imm = {k: jnp.diagonal(v) for k, v in imm.items()}
    elif settings.start in ("screen", "classical") and settings.centred:
        start = _at_sites(model, classical_start(cohort, model, data, settings.trials[0]), data.n_legs)
        init = functools.partial(_init_near, values=start, fallback=init)
    jumping = {} if blocks is None else {"blocks": blocks, "split": split}
    kernel = (NUTS if blocks is None else functools.partial(ModeJumpNUTS, **jumping))(
        conditioned,
        target_accept_prob=settings.target_accept,
        max_tree_depth=settings.max_tree_depth,
        init_strategy=init,
        dense_mass=settings.dense_mass,
        inverse_mass_matrix=imm,
        adapt_mass_matrix=settings.adapt_metric or imm is None,
    )
    method = chain_method(settings, data)
    mcmc = MCMC(
        kernel,
        num_warmup=settings.warmup,
        num_samples=settings.draws,
        num_chains=settings.chains,
        chain_method=method,
        # numpyro's stepping loop with a progress bar calls one jitted step, which later blocks of the
        # same size reuse; its loop without the bar is compiled whole, again for every block.  Parallel
        # chains compile their loop again for every run either way, and their bar (a callback inside
        # the loop) fails where double precision is switched on for the fit alone: no bar for them.
        progress_bar=(progress or settings.target_ess is not None) and method != "parallel",
        # the data are arguments of the jitted sampler, not constants folded into it:
        # the chains (and later fits of the same shapes) compile it once
        jit_model_args=True,
    )
    key = jax.random.PRNGKey(settings.seed)
    if settings.target_ess is not None:
        started = time.perf_counter() if started is None else started
        return _draw_to_target(mcmc, key, arrays, init_params, model, data, settings, started, progress), data
    # a Ctrl-C while XLA sampled (warm-up and draws are one compiled loop) is seen only now, when the
    # draws are complete: they are summarised and saved, and the command line says it was interrupted
    mcmc.run(key, arrays, extra_fields=_fields(mcmc), init_params=init_params)
    return mcmc, data


#: The sampler's statistics kept with every draw.
_FIELDS = ("diverging", "energy", "num_steps")


def _fields(mcmc: MCMC) -> tuple[str, ...]:
    """The statistics kept with every draw: :data:`_FIELDS`, and where the chains jump, how many jumps were taken."""
    return _FIELDS + (("mode_jump",) if isinstance(mcmc.sampler, ModeJumpNUTS) else ())


#: Sites that are no parameter: each leg's log P(d | θ) (and of (d, shift)), not checked for convergence.
_NOT_CHECKED = ("delay_logp", "delay_shift_logp")


@dataclasses.dataclass(frozen=True)
class BlockDraws:
    """Draws gathered in blocks by a fit with :attr:`FitSettings.target_ess`: the samples and
    statistics of every block, chain by chain, read as those of one numpyro ``MCMC``
    (:func:`quadshank.inference.to_inference_data` takes either)."""

    samples: dict
    extra: dict
    #: how the blocks ended: :func:`target_status` of all the draws, with ``blocks``, ``stopped``, ``seconds``
    target: dict

    @staticmethod
    def _grouped(values: dict, group_by_chain: bool) -> dict:
        if group_by_chain:
            return dict(values)
        return {k: v.reshape(v.shape[0] * v.shape[1], *v.shape[2:]) for k, v in values.items()}

    def get_samples(self, group_by_chain: bool = False) -> dict:
        """Every block's draws: ``{site: (chains, draws, ...)}``, or (chains·draws, ...) pooled."""
        return self._grouped(self.samples, group_by_chain)

    def get_extra_fields(self, group_by_chain: bool = False) -> dict:
        """Every block's sampler statistics (diverging, energy, num_steps), shaped as :meth:`get_samples`."""
        return self._grouped(self.extra, group_by_chain)


def convergence_status(draws: dict, needed: float, rhat_max: float = THRESHOLDS["rhat_max"]) -> dict:
    """Whether draws ``{name: (chains, draws, ...)}`` pass R-hat and ESS: the largest rank-normalised
    split R-hat below ``rhat_max`` (with two chains or more) and the smallest bulk and tail ESS
    (arviz) at least ``needed``.  ``lagging``: the variable furthest from passing."""
    post = az.convert_to_dataset({k: np.asarray(v) for k, v in draws.items()})
    chains, n = post.sizes["chain"], post.sizes["draw"]

    def per_var(ds, fn):
        out = {v: float(fn(np.asarray(ds[v]))) for v in ds.data_vars if np.isfinite(np.asarray(ds[v])).any()}
        return out or {"": float("nan")}

    rhat = per_var(az.rhat(post), np.nanmax) if chains > 1 else {"": float("nan")}
    bulk = per_var(az.ess(post, method="bulk"), np.nanmin)
    tail = per_var(az.ess(post, method="tail"), np.nanmin)
    ess = {v: min(bulk[v], tail.get(v, bulk[v])) for v in bulk}
    # how far each variable is from passing, as a ratio: needed ESS over its ESS, R-hat's excess over the limit's
    shortfall = {v: needed / max(e, 1e-9) for v, e in ess.items()}
    for v, r in rhat.items():
        if np.isfinite(r):
            shortfall[v] = max(shortfall.get(v, 0.0), (r - 1.0) / (rhat_max - 1.0))
    rhat_worst, bulk_min, tail_min = max(rhat.values()), min(bulk.values()), min(tail.values())
    met = bulk_min >= needed and tail_min >= needed and (chains < 2 or rhat_worst < rhat_max)
    lagging = max(shortfall, key=shortfall.get)
    return {"met": bool(met), "draws_per_chain": int(n), "ess_needed": needed, "rhat_max": rhat_worst,
            "ess_bulk_min": bulk_min, "ess_tail_min": tail_min, "lagging": lagging,
            "lagging_index": _lagging_entry(post, lagging, needed, rhat_max) if lagging else None}


def _lagging_entry(post, name: str, needed: float, rhat_max: float) -> list[int] | None:
    """Which entry of variable ``name`` (its index past chain and draw; [] for a scalar) is
    furthest from passing, by the shortfall :func:`convergence_status` ranks variables by."""
    one = post[[name]]
    ess = np.minimum(np.asarray(az.ess(one, method="bulk")[name]), np.asarray(az.ess(one, method="tail")[name]))
    short = needed / np.maximum(np.where(np.isfinite(ess), ess, np.inf), 1e-9)
    if post.sizes["chain"] > 1:
        r = np.asarray(az.rhat(one)[name])
        short = np.maximum(short, np.where(np.isfinite(r), (r - 1.0) / (rhat_max - 1.0), 0.0))
    short = np.atleast_1d(short)
    return [int(i) for i in np.unravel_index(int(np.argmax(short)), short.shape)] if np.ndim(ess) else []


def target_status(samples: dict, model: Model, data: LikelihoodData, settings: FitSettings) -> dict:
    """Whether a fit's draws ``{site: (chains, draws, ...)}`` meet :attr:`FitSettings.target_ess`
    (:func:`convergence_status`).

    Checks what the fit's acceptance (:func:`quadshank.inference.diagnose_sampling`) checks of
    R-hat and ESS, on the same variables: the sampled sites and the population and subject values
    drawn from them.  The ESS needed is the larger of the target and ``THRESHOLDS["ess_per_chain"]``
    per chain.  Divergences are counted by the caller.
    """
    chains = next(iter(samples.values())).shape[0]
    kept = {k: np.asarray(v) for k, v in samples.items() if k not in _NOT_CHECKED}
    kept.update(hyper_draws(model, kept, data.leg_subject, len(data.subjects), settings.seed))
    status = convergence_status(kept, max(int(settings.target_ess or 0), THRESHOLDS["ess_per_chain"] * chains))
    name, index = status["lagging"], status.pop("lagging_index")
    if name and index:  # the lagging entry's leg (or subject): its first axis past chain and draw
        names = data.subjects if name.endswith("_subject") else data.legs
        if np.shape(kept[name])[2] == len(names):
            status["lagging_at"] = str(names[index[0]])
    return status


def _draw_to_target(mcmc, key, arrays, init_params, model, data, settings, started, progress) -> BlockDraws:
    """Warm-up and a first block, then blocks of the same size until :func:`target_status` is met,
    a draw diverges (more draws do not mend that), or the next block would end past the time limit."""

    # numpyro writes its progress bar to stderr; a quiet fit sends it nowhere
    def quiet():
        return contextlib.nullcontext() if progress else contextlib.redirect_stderr(io.StringIO())

    samples, extra = [], []

    def draw(**kw):
        t = time.perf_counter()
        with quiet():
            mcmc.run(key if not samples else mcmc.post_warmup_state.rng_key, arrays, extra_fields=_fields(mcmc), **kw)
        samples.append({k: np.asarray(v) for k, v in mcmc.get_samples(group_by_chain=True).items()})
        extra.append({k: np.asarray(v) for k, v in mcmc.get_extra_fields(group_by_chain=True).items()})
        return time.perf_counter() - t

    # the first run's seconds hold the warm-up and the compilation as well: the next block is taken
    # to cost its share of the iterations (an overestimate) until one has been timed alone
    seconds = draw(init_params=init_params) * settings.draws / (settings.warmup + settings.draws)
    while True:
        joined = {k: np.concatenate([b[k] for b in samples], axis=1) for k in samples[0]}
        joined_extra = {k: np.concatenate([b[k] for b in extra], axis=1) for k in extra[0]}
        status = target_status(joined, model, data, settings)
        divergences = int(joined_extra["diverging"].sum())
        elapsed = time.perf_counter() - started
        if status["met"] and not divergences:
            stopped = "target met"
        elif interrupt_requested():  # a Ctrl-C during a block: the draws so far are kept, none added
            stopped = "interrupted: no further block was drawn"
        elif divergences:
            stopped = f"{divergences} divergent transitions (more draws do not mend them)"
        elif elapsed + seconds > settings.time_limit_s:
            stopped = f"time limit of {settings.time_limit_s:.0f} s: another block would end past it"
        else:
            if progress:
                print(f"fit: {status['draws_per_chain']} draws per chain (a block takes about {seconds:.0f} s): "
                      f"bulk ESS {status['ess_bulk_min']:.0f}, tail ESS {status['ess_tail_min']:.0f}, R-hat {status['rhat_max']:.3f} "
                      f"(needed: ESS {status['ess_needed']}, R-hat < {THRESHOLDS['rhat_max']}; furthest: "
                      f"{status['lagging']}{' of ' + status['lagging_at'] if status.get('lagging_at') else ''}); "
                      f"{settings.draws} more per chain", file=sys.stderr, flush=True)
            mcmc.post_warmup_state = mcmc.last_state
            seconds = draw()
            continue
        target = {**status, "target_ess": int(settings.target_ess), "divergences": divergences,
                  "blocks": len(samples), "stopped": stopped, "seconds": round(elapsed, 1),
                  "time_limit_s": settings.time_limit_s}
        return BlockDraws(joined, joined_extra, target)


# ============================================================================ after sampling


