"""A cheap posterior for screening models: per-leg MAP with a Laplace approximation.

The modelling loop (:mod:`quadshank.loop._diagnose`) asks, for every candidate
effect, whether adding it to a model improves it.  A hierarchical NUTS fit per
candidate takes many minutes; this screen takes seconds per leg:

1. Each leg on its own, with the declared population prior as its prior (no
   pooling between legs), the same likelihood as the NUTS fit
   (:mod:`quadshank.model._likelihood`: Student-t on the equivalent acceleration, the
   delay d and a delay effect's shift summed out exactly).
2. The posterior mode by L-BFGS on the standardised scale the fit samples on
   (x = loc + scale·z for each declared parameter, log σ, log ν), started at
   the classical identification (or another screen's mode) and, for the
   parameters that start has no value for, at the prior median and at
   ``n_starts`` draws from the prior; the best mode wins.  A delay effect's
   step parameter (``angle_delay``'s threshold), on whose staircase L-BFGS
   cannot move far, starts at the best point of a profile over its prior
   (:func:`_step_profile_start`).  Started from another
   screen, L-BFGS runs in the coordinates that screen's Laplace covariance
   whitens for the parameters the two share (:func:`_start_whitening`).  A run
   that stops short is restarted (:data:`LBFGS_RESTARTS`), and the mode is
   polished in the coordinates its own curvature whitens (:data:`CURVATURE_POLISH`).
3. The Laplace approximation there: a Gaussian with the inverse Hessian as
   covariance (eigenvalues floored at the prior precision, so no direction is
   wider than its prior), ``n_draws`` draws, and for each a (d, shift) drawn
   from P(d, shift | θ, data).
4. PSIS-LOO over the same 1-s segments as the NUTS fit, with the Laplace
   draws corrected towards the posterior by importance weights: for segment i
   the log ratio of draw s is log p(θ_s, y) − log q(θ_s) − log p(y_i | θ_s, d_s),
   Pareto-smoothed (``az.psislw``), as for LOO from an approximate posterior
   (Magnusson, Andersen, Jonasson and Vehtari 2019).  Where the Gaussian is a
   poor proposal (a ridge, an unidentified parameter of an effect that is not
   there) the Pareto k says so; a NUTS fit is the confirmation.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import arviz as az
import jax
import jax.numpy as jnp
import numpy as np
from scipy import optimize, special

from ..common._random import jax_key
from ..data._cohort import Cohort
from ..model._effects import Param, user_effects
from ..model._likelihood import (
    N_DELAYS,
    LikelihoodData,
    leg_loglik_by_delay,
    leg_pointwise,
    prepare,
)
from ..model._model import Model
from ._draws import over_draws, sample_delays
from ._priors import (
    NU_PRIOR,
    SIGMA_PRIOR,
    SIGMA_PRIORS,
    _with_discrete_axes,
    log_shift_prior,
    model_params,
)
from ._starts import classical_start

__all__ = ["LaplaceFit", "laplace_fit", "DelayModes", "delay_modes", "delay_evidence", "restart_screen", "delta_elpd", "leg_draw_models"]


@dataclasses.dataclass(frozen=True)
class _Spec:
    """A parameter's place in the screen's unconstrained vector: its standardised components."""

    param: Param

    @property
    def name(self) -> str:
        return self.param.name

    @property
    def shape(self) -> tuple:
        return tuple(self.param.shape)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape)) if self.shape else 1


def _specs(model: Model) -> list[_Spec]:
    return [_Spec(p) for p in model_params(model)]


def _unpack(specs: list[_Spec], vec):
    """Parameter values, σ, ν and the standardised z's from a flat unconstrained vector."""
    values, zs, i = {}, [], 0
    for s in specs:
        z = jnp.reshape(vec[i : i + s.size], s.shape)
        i += s.size
        values[s.name] = s.param.from_standard(z, xp=jnp)
        zs.append(jnp.reshape(z, (-1,)))
    return values, jnp.exp(vec[i]), jnp.exp(vec[i + 1]), jnp.concatenate(zs) if zs else jnp.zeros(0)


def _values_np(specs, vecs: np.ndarray) -> dict[str, np.ndarray]:
    """Parameter values from unconstrained vectors (..., dim), in NumPy (outside the screen's x64 scope)."""
    values, i = {}, 0
    lead = vecs.shape[:-1]
    for s in specs:
        z = vecs[..., i : i + s.size].reshape(lead + tuple(s.shape))
        i += s.size
        values[s.name] = s.param.from_standard(z)
    return values


@dataclasses.dataclass(frozen=True, eq=False)
class LaplaceFit:
    """The screen's result for one model on the legs of one dataset."""

    model: Model
    data: LikelihoodData
    specs: tuple
    mode: np.ndarray  # (L, dim) unconstrained mode per leg
    neg_logpost: np.ndarray  # (L,) at the mode
    covariance: np.ndarray  # (L, dim, dim) the Laplace covariance (eigenvalues capped at the prior's)
    draws: np.ndarray  # (L, S, dim) unconstrained Laplace draws
    delays: np.ndarray  # (L, S) d per draw
    shifts: np.ndarray  # (L, S)
    delay_posterior: np.ndarray  # (L, 11) P(d | data), averaged over draws
    pointwise: np.ndarray  # (L, S, segments) log p(segment | θ, d, shift); NaN for padding
    elpd_i: np.ndarray  # (L, segments) PSIS-LOO pointwise elpd; NaN for padding
    pareto_k: np.ndarray  # (L, segments)
    resampled: np.ndarray  # (L, S) draw indices resampled by the importance weights p(θ | y)/q(θ)
    weights_ess: np.ndarray  # (L,) effective sample size of those weights (S: the Gaussian is the posterior)

    @property
    def legs(self) -> tuple[str, ...]:
        return self.data.legs

    @property
    def elpd(self) -> float:
        """Σ of the pointwise PSIS-LOO ELPD (NaN for a screen run with ``loo=False``)."""
        return float(np.nansum(self.elpd_i)) if np.isfinite(self.elpd_i).any() else float("nan")

    @property
    def elpd_se(self) -> float:
        v = self.elpd_i[np.isfinite(self.elpd_i)]
        return float(math.sqrt(v.size * np.var(v)))

    def values(self, leg: str) -> dict[str, np.ndarray]:
        """Parameter values at the mode of ``leg`` (and its σ, ν)."""
        i = self.legs.index(leg)
        out = _values_np(self.specs, self.mode[i])
        out.update(sigma=float(np.exp(self.mode[i, -2])), nu=float(np.exp(self.mode[i, -1])))
        return out

    def z_values(self, leg: str) -> dict[str, np.ndarray]:
        """Standardised values at the mode of ``leg``: ``{name: z}`` plus ``log_sigma``, ``log_nu``."""
        i = self.legs.index(leg)
        out, j = {}, 0
        for s in self.specs:
            out[s.name] = self.mode[i, j : j + s.size].reshape(s.shape)
            j += s.size
        out["log_sigma"], out["log_nu"] = self.mode[i, j], self.mode[i, j + 1]
        return out


def leg_draw_models(fit: LaplaceFit, leg: str, n: int | None = None) -> Model:
    """The model of ``leg`` with leaves (draws,): Laplace draws resampled by their importance
    weights towards the posterior (so a poor Gaussian direction does not widen the bands), delays included."""
    i = fit.legs.index(leg)
    idx = fit.resampled[i] if n is None else fit.resampled[i, :n]
    draws = fit.draws[i, idx]
    values = {k: jnp.asarray(v, jnp.float32) for k, v in _values_np(fit.specs, draws).items()}
    m = fit.model.with_params(values, delay=jnp.asarray(fit.delays[i, idx], jnp.int32))
    if fit.model.delay_effect is not None:
        m = m.with_delay_shift(jnp.asarray(fit.shifts[i, idx], jnp.int32))
    return m


def _log_prior(specs: list[_Spec], vec, sigma_prior=SIGMA_PRIOR):
    """log prior density of the unconstrained vector (up to a constant); ``sigma_prior``: σ's
    (:data:`~quadshank.inference._priors.SIGMA_PRIORS`)."""
    z = _unpack(specs, vec)[3]
    log_nu = vec[-1]
    nu_a, nu_b = NU_PRIOR
    return (
        -0.5 * jnp.sum(z**2)
        - 0.5 * ((vec[-2] - sigma_prior[0]) / sigma_prior[1]) ** 2
        + nu_a * log_nu - nu_b * jnp.exp(log_nu)  # Gamma(a, b) on ν, with the Jacobian of log ν
    )


def _objective(model: Model, specs: list[_Spec], R: int, K: int, sigma_prior=SIGMA_PRIOR):
    log_prior_dk = jnp.asarray(log_shift_prior(K), jnp.float64) - math.log(N_DELAYS)  # (D, K + 1)

    def joint(vec, x):
        """(D, K + 1) log p(y, d, shift | θ) and the log prior of the unconstrained vector."""
        values, sigma, nu, _ = _unpack(specs, vec)
        m = _with_discrete_axes(model.with_params(values), ())
        ll = leg_loglik_by_delay(m, {"sigma": sigma, "nu": nu}, x, R, K)
        return ll + log_prior_dk, _log_prior(specs, vec, sigma_prior)

    def neg_logpost(vec, x):
        logp, prior = joint(vec, x)
        return -(jax.scipy.special.logsumexp(logp) + prior)

    return joint, neg_logpost


def _neg_logpost_at_delay(joint):
    """−log p(θ, d, y) with d fixed (a traced index: one compilation serves every d)."""

    def f(vec, x, d):
        logp, prior = joint(vec, x)
        return -(jax.scipy.special.logsumexp(logp[d]) + prior)

    return f


def _leg_arrays64(data: LikelihoodData) -> dict:
    """The likelihood's per-leg arrays, floating ones in double precision (the screen optimises in it)."""
    return {k: jnp.asarray(v, jnp.float64) if np.issubdtype(v.dtype, np.floating) else v for k, v in data.leg_arrays().items()}


_COMPILED: dict = {}

#: Whether a screen started from another one seeks its modes in the coordinates that screen's
#: Laplace covariance whitens (:func:`_start_whitening`); ``False`` (the plain standardised
#: coordinates) is kept for ``benchmarks/bench_discover.py``, which measures the difference.
WHITEN_FROM_START = True

#: Standardised values (prior sds about the prior median) at which the profile of a delay effect's
#: step parameter is evaluated before L-BFGS, where the start has no value for it
#: (:func:`_step_profile_start`): 0.1 prior sd apart, 2.5° for ``angle_delay``'s threshold.
STEP_PROFILE_Z = np.linspace(-2.0, 2.0, 41)


def _compiled(model: Model, specs: list[_Spec], R: int, K: int, n_segments: int, objective: str = "acceleration"):
    """The jitted functions of one model structure and its priors, made once per process
    (screens of many datasets of one shape then compile once); ``objective``: what the
    likelihood compares (σ's prior follows it)."""
    key = (jax.tree_util.tree_structure(model), tuple((s.name, s.shape, repr(s.param.prior)) for s in specs), R, K, n_segments,
           objective)
    if key in _COMPILED:
        return _COMPILED[key]
    sigma_prior = SIGMA_PRIORS[objective]
    joint, neg_logpost = _objective(model, specs, R, K, sigma_prior)

    def pointwise_one(v, d, k, x):
        values, sigma, nu, _ = _unpack(specs, v)
        m = _with_discrete_axes(model.with_params(values), ())
        return leg_pointwise(m, {"sigma": sigma, "nu": nu}, x, d, R, n_segments, K, k)

    out = (
        joint,
        jax.jit(jax.value_and_grad(neg_logpost)),
        jax.jit(lambda V, x: over_draws(lambda v: joint(v, x)[0], V)),
        jax.jit(jax.vmap(lambda v: _log_prior(specs, v, sigma_prior))),
        jax.jit(lambda V, d, k, x: over_draws(lambda v, di, ki: pointwise_one(v, di, ki, x), V, d, k)),
        jax.jit(jax.value_and_grad(_neg_logpost_at_delay(joint))),  # compiled on first use (delay_modes)
    )
    _COMPILED[key] = out
    return out


def _hessian(value_and_grad, mode: np.ndarray, x: dict, step: float = 1e-5) -> np.ndarray:
    """The Hessian of the negative log posterior at ``mode`` by central differences of its
    exact gradient, symmetrised.  The gradient is already compiled for L-BFGS; a second
    compiled function (``jax.hessian``) cost each screened model about as much compilation
    as the gradient itself, while 2·dim gradient calls take a fraction of a second.  On the
    standardised scale (prior sd 1) a step of 1e-5 leaves a relative error of order
    (step / posterior sd)² in the curvature, below 1e-4 for posterior sds down to 1e-3."""
    n = mode.size
    H = np.empty((n, n))
    for j in range(n):
        e = np.zeros(n)
        e[j] = step
        g_hi = np.asarray(value_and_grad(jnp.asarray(mode + e, jnp.float64), x)[1], np.float64)
        g_lo = np.asarray(value_and_grad(jnp.asarray(mode - e, jnp.float64), x)[1], np.float64)
        H[:, j] = (g_hi - g_lo) / (2.0 * step)
    return 0.5 * (H + H.T)


def _floored_curvature(value_and_grad, mode: np.ndarray, x: dict) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues and eigenvectors of the Hessian at ``mode`` (entries that are not finite taken as
    0), the eigenvalues floored at 1: never wider than the prior (unit precision on the
    standardised scale)."""
    H = _hessian(value_and_grad, mode, x)
    w, V = np.linalg.eigh(np.where(np.isfinite(H), H, 0.0))
    return np.maximum(w, 1.0), V


def _positions(specs: list[_Spec]) -> tuple[dict[str, range], int]:
    """Where each parameter's components lie in the screen's vector, and where log σ starts."""
    at, k = {}, 0
    for sp in specs:
        at[sp.name] = range(k, k + sp.size)
        k += sp.size
    return at, k


def _start_whitening(start: LaplaceFit, leg: str, specs: list[_Spec]) -> np.ndarray:
    """The linear map ``S`` (v = v0 + S u) under which L-BFGS seeks a mode started from the
    screen ``start`` of a related model: for the parameters the two share (log σ and log ν
    included) the square root of ``start``'s Laplace covariance of them, so that its
    posterior is the unit ball in u; the identity for the parameters ``start`` lacks (their
    prior sd is 1 on this scale).  The posterior's scales span three decades on the
    standardised scale, where L-BFGS took 200–480 evaluations per start, often stopping at
    its iteration limit short of the mode; started from the baseline's mode, a one-effect
    extension then takes 20–120 (the same whitening as :func:`delay_modes`)."""
    i = start.legs.index(leg)
    at, k = _positions(specs)
    at_start, j = _positions(start.specs)
    shared = [name for name in at if len(at_start.get(name, ())) == len(at[name])]
    mine = [p for name in shared for p in at[name]] + [k, k + 1]  # then log σ, log ν
    theirs = [p for name in shared for p in at_start[name]] + [j, j + 1]
    w, V = np.linalg.eigh(start.covariance[i][np.ix_(theirs, theirs)])
    S = np.eye(k + 2)
    S[np.ix_(mine, mine)] = V * np.sqrt(np.clip(w, 1e-12, None))[None, :]
    return S


#: L-BFGS is started again from where it stopped, with its curvature memory cleared, until a
#: restart gains less than LBFGS_RESTART_GAIN in the log posterior, at most this often (within
#: the one iteration budget).  Its stopping rule (the objective's relative reduction) ends a run
#: wherever the line search makes a tiny step: on the screen's badly scaled posteriors (an offset
#: of gravity that moves every passive parameter, say) that was hundreds of units short of the
#: mode, at a point that moved with the start's last digits; a fresh memory goes on from there.
LBFGS_RESTARTS = 4
LBFGS_RESTART_GAIN = 1e-2
#: After the Hessian at the mode is computed, L-BFGS goes on from the mode in the coordinates that
#: curvature whitens (the posterior's scales span decades; whitened, they are all one), at most
#: this often, each time the mode moves by more than LBFGS_RESTART_GAIN in the log posterior.
CURVATURE_POLISH = 2


def _minimize_from(value_and_grad, v0: np.ndarray, S: np.ndarray, x: dict, max_iter: int):
    """L-BFGS of ``value_and_grad`` (the negative log posterior and its gradient) over
    v = v0 + S u from u = 0, restarted as :data:`LBFGS_RESTARTS` says; returns scipy's result
    (in u) and the v it ends at."""

    def f(u):
        val, g = value_and_grad(jnp.asarray(v0 + S @ u, jnp.float64), x)
        val, g = float(val), np.asarray(g, np.float64)
        if not (np.isfinite(val) and np.isfinite(g).all()):
            # a step into parameters where the model overflows (a steep limit, say): reported as
            # infinitely bad, so the line search steps back, rather than as NaN, which ends the search
            return math.inf, np.zeros(u.size)
        return val, S.T @ g

    res = optimize.minimize(f, np.zeros(v0.size), jac=True, method="L-BFGS-B", options={"maxiter": max_iter})
    used = res.nit
    for _ in range(LBFGS_RESTARTS):
        if used >= max_iter or not np.isfinite(res.fun):
            break
        again = optimize.minimize(f, res.x, jac=True, method="L-BFGS-B", options={"maxiter": max_iter - used})
        used += again.nit
        gained = res.fun - again.fun
        if again.fun <= res.fun:
            res = again
        if not gained > LBFGS_RESTART_GAIN:
            break
    return res, v0 + S @ res.x


def _step_profile_start(value_and_grad, v0: np.ndarray, specs, step: str, x: dict) -> np.ndarray:
    """``v0`` with the delay effect's step parameter ``step`` (``angle_delay``'s threshold) moved to
    the best of :data:`STEP_PROFILE_Z`, the other parameters held at ``v0``.

    The likelihood is a staircase in a step parameter: between two neighbouring pulse angles
    every threshold splits the pulses alike, and the smoothed step (a degree wide) gives a
    gradient only from pulses within a degree or two of it.  From one start L-BFGS therefore
    stays on the stair it starts on (the prior median, typically); the profile over the prior's
    central range finds the stair where the data place the step, and L-BFGS refines it there."""
    at, _ = _positions(specs)
    if len(at[step]) != 1:
        return v0
    i = at[step][0]
    values = []
    for z in STEP_PROFILE_Z:
        v = v0.copy()
        v[i] = z
        values.append(float(value_and_grad(jnp.asarray(v, jnp.float64), x)[0]))
    values = np.where(np.isfinite(values), values, np.inf)
    if not np.isfinite(values).any():
        return v0
    out = v0.copy()
    out[i] = STEP_PROFILE_Z[int(np.argmin(values))]
    return out


def _start_vector(specs, known: dict, log_sigma: float, log_nu: float, rng, draw_unknown: bool) -> np.ndarray:
    parts = []
    for s in specs:
        if s.name in known:
            parts.append(np.asarray(known[s.name], np.float64).reshape(-1))
        elif draw_unknown:
            parts.append(rng.standard_normal(s.size))
        else:
            parts.append(np.zeros(s.size))
    return np.concatenate(parts + [np.array([log_sigma, log_nu])])


def laplace_fit(cohort: Cohort, model: Model, trials=(1,), legs=None, **kw) -> LaplaceFit:
    """Per-leg MAP and Laplace approximation of ``model`` on ``cohort`` (see module docs).

    Keywords: ``start`` (a screen of a related model on the same data, whose
    modes start the parameters the two share, e.g. the baseline of a one-effect
    extension), ``n_starts`` (prior draws tried for the other parameters),
    ``n_draws``, ``seed``, ``max_iter``, ``loo`` (False: no pointwise
    log-likelihood and PSIS-LOO, whose ELPD fields are then NaN; the posterior
    alone, for a quicker look), ``objective`` (what the likelihood compares,
    :func:`quadshank.model._likelihood.resolve_objective`), ``whiten`` (False: from ``start``,
    L-BFGS in the plain standardised coordinates, not those :func:`_start_whitening`
    gives).  Runs in double precision: the log
    posterior of thousands of samples is ~1e5, and single precision leaves
    L-BFGS and the Hessian with a noise of order one at the mode.
    """
    with jax.enable_x64(True):
        return _laplace_fit(cohort, model, trials, legs, **kw)


def _laplace_fit(
    cohort: Cohort,
    model: Model,
    trials=(1,),
    legs=None,
    *,
    start: LaplaceFit | None = None,
    n_starts: int = 3,
    n_draws: int = 200,
    seed: int = 0,
    max_iter: int = 400,
    loo: bool = True,
    objective: str = "auto",
    whiten: bool = True,
) -> LaplaceFit:
    data = prepare(cohort, model, trials=trials, legs=legs, objective=objective)
    if start is None and data.objective == "angle" and model.activation.name != "no_muscle":
        # Runs of a muscle from a poor start (a prior draw, the classical DARMA) can diverge, and the
        # angle then holds no gradient; the same model's screen on the acceleration lands near the
        # angle's mode in a few seconds.
        start = _laplace_fit(cohort, model, trials, legs, n_starts=n_starts, n_draws=max(n_draws, 2), seed=seed,
                             max_iter=max_iter, loo=False, objective="acceleration")
    specs = _specs(model)
    R, K = data.response_length, data.max_shift
    joint, value_and_grad, joint_b, prior_b, pw, _ = _compiled(model, specs, R, K, data.n_segments, data.objective)
    arrays = _leg_arrays64(data)
    dim = sum(s.size for s in specs) + 2
    rng = np.random.default_rng(seed)  # the root seed's own stream: the starts and the Laplace draws
    step = getattr(model.delay_effect, "step_param", None)  # profiled where no start has it

    if start is None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            classical = classical_start(cohort, model, data, tuple(trials)[0])
    modes, nlp, all_draws, log_q, covs = [], [], [], [], []
    for i, leg in enumerate(data.legs):
        x = {k: v[i] for k, v in arrays.items()}
        S = np.eye(dim)
        if start is not None and leg in start.legs:
            known = {k: v for k, v in start.z_values(leg).items() if any(s.name == k for s in specs)}
            zs = start.z_values(leg)
            log_sigma, log_nu = float(zs["log_sigma"]), float(zs["log_nu"])
            if start.data.objective != data.objective:  # σ in other units, a curvature of another scale
                log_sigma, log_nu = SIGMA_PRIORS[data.objective][0], math.log(10.0)
            elif WHITEN_FROM_START and whiten:
                S = _start_whitening(start, leg, specs)
        else:
            known = {k[: -len("_s_leg")]: (v[..., i] if np.ndim(v) > 1 else v[i]) for k, v in classical.items()}
            sizes = {sp.name: sp.size for sp in specs}
            known = {k: v for k, v in known.items() if np.size(v) == sizes.get(k)}  # e.g. not a DARMA of another order
            log_sigma, log_nu = SIGMA_PRIORS[data.objective][0], math.log(10.0)
        unknown = [s for s in specs if s.name not in known]
        n_try = 1 + (n_starts if unknown else 0)
        best = None
        for j in range(n_try):
            v0 = _start_vector(specs, known, log_sigma, log_nu, rng, draw_unknown=j > 0)
            if j == 0 and step in {s.name for s in unknown}:
                v0 = _step_profile_start(value_and_grad, v0, specs, step, x)

            res, v = _minimize_from(value_and_grad, v0, S, x, max_iter)
            if np.isfinite(res.fun) and (best is None or res.fun < best[0].fun):
                best = (res, v)
        if best is None:
            own = user_effects(model.effects)
            raise FloatingPointError(
                f"{leg}: the screen of {model.name} found no finite posterior density from any start: the model "
                "diverges on these data from every start" + (f", or an effect ({', '.join(own)}) returns a value that "
                                                            "is not finite" if own else ""))
        best, mode = best[0], np.asarray(best[1], np.float64)
        w, V = _floored_curvature(value_and_grad, mode, x)
        for _ in range(CURVATURE_POLISH):  # on from the mode in the coordinates its curvature whitens
            res, v = _minimize_from(value_and_grad, mode, V / np.sqrt(w)[None, :], x, max_iter)
            if not (np.isfinite(res.fun) and res.fun < best.fun - LBFGS_RESTART_GAIN):
                break
            best, mode = res, np.asarray(v, np.float64)
            w, V = _floored_curvature(value_and_grad, mode, x)
        eps = rng.standard_normal((n_draws, dim))
        all_draws.append(mode[None, :] + (eps / np.sqrt(w)[None, :]) @ V.T)
        covs.append((V / w[None, :]) @ V.T)
        modes.append(mode)
        nlp.append(float(best.fun))

        log_q.append(-0.5 * np.sum(eps**2, axis=1))  # log q(θ_s) up to a constant (a constant cancels)

    draws = np.stack(all_draws)  # (L, S, dim)
    # (d, shift) per draw from P(d, shift | θ, data), then the pointwise log-likelihood
    delays, shifts, dpost, pointwise, log_post = [], [], [], [], []
    for i in range(data.n_legs):
        x = {k: v[i] for k, v in arrays.items()}
        logp = np.asarray(joint_b(jnp.asarray(draws[i], jnp.float64), x), np.float64)  # (S, D, K + 1)
        log_post.append(np.asarray(jax.scipy.special.logsumexp(logp, axis=(-2, -1))) + prior_b(jnp.asarray(draws[i], jnp.float64)))
        logp = logp - jax.scipy.special.logsumexp(logp, axis=(-2, -1), keepdims=True)
        d, k = sample_delays(logp, jax_key(seed, "screen delays", i))
        delays.append(d)
        shifts.append(k)
        dpost.append(np.exp(np.asarray(jax.scipy.special.logsumexp(logp, axis=-1))).mean(axis=0))
        if not loo:
            pointwise.append(np.full((n_draws, data.n_segments), np.nan))
            continue
        ll = np.asarray(pw(jnp.asarray(draws[i], jnp.float64), jnp.asarray(d), jnp.asarray(k), x), np.float64)
        pointwise.append(np.where(data.segment_mask[i][None], ll, np.nan))
    pointwise = np.stack(pointwise)
    elpd_i = np.full(pointwise.shape[::2], np.nan)
    pareto_k = np.full(pointwise.shape[::2], np.nan)
    resampled, weights_ess = [], []
    for i in range(data.n_legs):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            lw_all, _ = az.psislw(np.asarray(log_post[i]) - log_q[i], reff=1.0)
        w = np.exp(np.asarray(lw_all) - np.max(lw_all))
        weights_ess.append(float(w.sum() ** 2 / np.sum(w**2)))
        u = (rng.random() + np.arange(n_draws)) / n_draws  # systematic resampling
        resampled.append(rng.permutation(np.minimum(np.searchsorted(np.cumsum(w / w.sum()), u), n_draws - 1)))
        ok = data.segment_mask[i] if loo else np.zeros_like(data.segment_mask[i])
        if not ok.any():
            continue
        ll = pointwise[i][:, ok]  # (S, n)
        log_w = (np.asarray(log_post[i]) - log_q[i])[:, None]  # log p(θ, y) − log q(θ), up to a constant
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            lw, k = az.psislw((log_w - ll).T, reff=1.0)  # (n, S): independent draws, normalised over draws
        elpd_i[i, ok] = np.asarray(jax.scipy.special.logsumexp(np.asarray(lw) + ll.T, axis=1))
        pareto_k[i, ok] = np.asarray(k)
    return LaplaceFit(
        model=model,
        data=data,
        specs=tuple(specs),
        mode=np.stack(modes),
        neg_logpost=np.asarray(nlp),
        covariance=np.stack(covs),
        draws=draws,
        delays=np.stack(delays),
        shifts=np.stack(shifts),
        delay_posterior=np.stack(dpost),
        pointwise=pointwise,
        elpd_i=elpd_i,
        pareto_k=pareto_k,
        resampled=np.stack(resampled),
        weights_ess=np.asarray(weights_ess),
    )


@dataclasses.dataclass(frozen=True, eq=False)
class DelayModes:
    """Each leg's mode and Laplace evidence at every delay (:func:`delay_modes`)."""

    probability: np.ndarray  # (L, 11) P(d | data) ∝ p(y, d), uniform prior on d
    log_evidence: np.ndarray  # (L, 11) log p(y, d) up to a constant; -inf where no finite mode
    modes: np.ndarray  # (L, 11, dim) θ̂_d on the screen's unconstrained scale
    #: (L, 11, dim, dim) the Laplace covariance at θ̂_d (the curvature's eigenvalues floored as in
    #: the evidence); None where not computed
    covariances: np.ndarray | None = None


def delay_evidence(screen: LaplaceFit, max_iter: int = 400) -> np.ndarray:
    """P(d | data) per leg from one Laplace approximation per delay: ``(legs, 11)``
    (:func:`delay_modes`, its probabilities)."""
    return delay_modes(screen, max_iter).probability


def delay_modes(screen: LaplaceFit, max_iter: int = 400) -> DelayModes:
    """Each leg's mode θ̂_d and Laplace evidence at every delay d.

    The screen's own P(d) (and a NUTS chain's) averages P(d | θ, data) over θ near
    one mode.  Where d is learned through θ (model 3 reads its gains at the states
    a delayed pulse meets, so each d has its own mode in θ), that is P(d | θ) at
    the mode of one delay, near 1 for it, however much mass the modes of other
    delays hold.  Here each d gets its own mode θ̂_d (L-BFGS from the screen's mode)
    and Laplace evidence log p(y, d) ≈ log p(y, d, θ̂_d) − ½ log det H_d (the
    curvature's eigenvalues floored at the prior precision, as in the screen), and
    P(d | data) ∝ p(y, d).  L-BFGS runs in the coordinates the screen's Laplace
    covariance whitens (θ = mode + S u, S Sᵀ = covariance): the posterior's scales
    span three decades, and unwhitened it took 150–450 iterations per delay where
    whitened it takes 20–250.  Eleven optimisations per leg: a check of the
    delay's modes, and the start of the chains where the screen missed the best
    (:func:`quadshank.inference._nuts.delay_start`).
    """
    with jax.enable_x64(True):
        return _delay_modes(screen, max_iter)


def _delay_modes(screen: LaplaceFit, max_iter: int) -> DelayModes:
    data = screen.data
    value_and_grad = _compiled(screen.model, list(screen.specs), data.response_length, data.max_shift, data.n_segments,
                               data.objective)[5]
    arrays = _leg_arrays64(data)
    log_ev = np.full((data.n_legs, N_DELAYS), -np.inf)
    modes = np.repeat(screen.mode[:, None, :], N_DELAYS, axis=1).astype(np.float64)
    covariances = np.repeat(np.asarray(screen.covariance, np.float64)[:, None], N_DELAYS, axis=1)
    for i in range(data.n_legs):
        x = {k: v[i] for k, v in arrays.items()}
        w, V = np.linalg.eigh(screen.covariance[i])
        S = V * np.sqrt(np.maximum(w, 0.0))[None, :]
        mode = np.asarray(screen.mode[i], np.float64)
        for d in range(N_DELAYS):
            dd = jnp.asarray(d, jnp.int32)

            def vg(v, x, dd=dd):
                return value_and_grad(jnp.asarray(v, jnp.float64), x, dd)

            res, v = _minimize_from(vg, mode, S, x, max_iter)
            if not np.isfinite(res.fun):
                continue
            modes[i, d] = v
            w_d, V_d = np.linalg.eigh(_hessian(vg, modes[i, d], x))
            w_d = np.maximum(w_d, 1.0)
            log_ev[i, d] = -res.fun - 0.5 * np.sum(np.log(w_d))
            covariances[i, d] = (V_d / w_d[None, :]) @ V_d.T
        if not np.isfinite(log_ev[i]).any():
            raise FloatingPointError(f"{data.legs[i]}: no delay has a finite posterior density under {screen.model.name}")
    probability = np.exp(log_ev - special.logsumexp(log_ev, axis=1, keepdims=True))
    return DelayModes(probability=probability, log_evidence=log_ev, modes=modes, covariances=covariances)


def restart_screen(screen: LaplaceFit, cohort: Cohort, starts: dict[str, np.ndarray], trials=(1,), seed: int = 0) -> LaplaceFit:
    """The screen again, each leg of ``starts`` started at the vector given for it (e.g. its
    mode at another delay, :func:`delay_modes`) and the other legs at their modes."""
    mode = screen.mode.copy()
    for leg, v in starts.items():
        mode[screen.legs.index(leg)] = v
    # the plain coordinates: the start is already a mode, one delay's, found whitened by
    # delay_modes; L-BFGS only carries it to the mode of the posterior with d summed out
    return laplace_fit(cohort, screen.model, trials=trials, legs=screen.legs, start=dataclasses.replace(screen, mode=mode),
                       n_starts=0, n_draws=screen.draws.shape[1], seed=seed, loo=False, objective=screen.data.objective,
                       whiten=False)


def delta_elpd(a: LaplaceFit, b: LaplaceFit) -> tuple[float, float]:
    """ELPD(b) − ELPD(a) and its standard error, paired over the same segments."""
    return paired_difference(a.elpd_i, b.elpd_i)


def paired_difference(a_i, b_i) -> tuple[float, float]:
    """Σ(b_i − a_i) over the segments where both pointwise ELPDs are finite, and its standard error."""
    a_i, b_i = np.asarray(a_i, float), np.asarray(b_i, float)
    diff = (b_i - a_i)[np.isfinite(a_i) & np.isfinite(b_i)]
    if diff.size == 0:  # no segment to compare (every one left out): no difference, and no evidence
        return 0.0, 0.0
    return float(diff.sum()), float(math.sqrt(diff.size * np.var(diff)))
