"""Jumps between a leg's delay modes, made between NUTS transitions.

With the delay summed out, a leg whose data leave two delays plausible has a posterior
over θ with one narrow mode per delay (model 3 reads its gains at the states a delayed
pulse meets).  NUTS moves within a mode and does not cross the low-density valley
between them: chains started in one mode stay there, chains started in several disagree
for ever, and the more legs a cohort holds, the likelier one of them is such a leg.

:class:`ModeJumpNUTS` follows every NUTS transition with a Metropolis–Hastings jump of
each leg with several modes (:class:`JumpBlocks`), one leg after another, from the mode
it is nearest to, a, to another, b, chosen uniformly: the leg's entries x map to

    x' = μ_b + L_b L_a⁻¹ (x − μ_a),

where μ_d and L_d Lᵀ_d are the mode and Laplace covariance of delay d
(:func:`quadshank.inference._screen.delay_modes`).  "Nearest" is the mode under whose
Gaussian x is most probable, a deterministic function of x; a jump whose x' is not
nearest to b is refused, which makes the move its own reverse (b → a maps x' back to x),
and it is accepted with probability

    min(1, p(x') / p(x) · |L_b| / |L_a|)

(the determinant is the map's Jacobian; the choice of b is symmetric).  The move keeps
the posterior invariant, whatever the quality of the Gaussian approximations: they set
how often a jump is accepted, not where the chains go.  This is the mode-jumping idea
of Tjelmeland & Hegstad (2001, Scand. J. Stat. 28:205) with Laplace modes as the
deterministic map; numpyro has no such move, hence the kernel here.

A leg's likelihood depends on that leg's entries alone and the prior couples the legs:
every leg's proposal is then scored in one pass of the likelihood, and the jumps in turn
need the prior only (:func:`jumps`).  A transition costs two passes of the likelihood and
one gradient more than NUTS's (a trajectory takes tens of gradients).
"""

from __future__ import annotations

import dataclasses
from collections import namedtuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jax.scipy.linalg import solve_triangular
from numpyro.infer import NUTS
from numpyro.infer.hmc import HMCState
from scipy import optimize

__all__ = ["JumpBlocks", "ModeJumpNUTS", "JumpState", "jumps"]

#: NUTS's state and how many legs jumped after the transition (``mode_jump``, an extra field a fit can keep).
JumpState = namedtuple("JumpState", HMCState._fields + ("mode_jump",))


@dataclasses.dataclass(frozen=True)
class JumpBlocks:
    """The legs with several modes and their Gaussian approximations, padded to the same number of modes.

    ``index`` (J, k): where leg j's entries sit in the flattened latent vector (numpyro's order,
    the sites sorted by name); ``mean`` (J, M, k) and ``chol`` (J, M, k, k): each mode's centre and
    lower Cholesky factor of its covariance; ``valid`` (J, M): which modes exist (at least two per
    leg); ``legs``: their names; ``delays`` (J, M): each mode's label, which
    :func:`refine_blocks` reads (a fit's: d·(K + 1) + shift, a delay and the shift its delay
    effect makes).
    """

    index: np.ndarray
    mean: np.ndarray
    chol: np.ndarray
    valid: np.ndarray
    legs: tuple[str, ...] = ()
    delays: np.ndarray | None = None
    #: (J,) which leg of the cohort each block is (its entry of a per-leg log-likelihood); None: 0 … J − 1
    leg: np.ndarray | None = None

    def __post_init__(self):
        J, M, k = np.shape(self.mean)
        if np.shape(self.index) != (J, k) or np.shape(self.chol) != (J, M, k, k) or np.shape(self.valid) != (J, M):
            raise ValueError("JumpBlocks: index (J, k), mean (J, M, k), chol (J, M, k, k) and valid (J, M) disagree")
        if J == 0 or np.any(np.sum(self.valid, axis=1) < 2):
            raise ValueError("JumpBlocks: every leg needs two modes or more")

    @property
    def n_legs(self) -> int:
        return int(np.shape(self.mean)[0])


def _labels(x, mean, chol, logdet, valid):
    """The mode whose Gaussian makes x most probable (an index into M), and x whitened by each mode's."""
    w = solve_triangular(chol, (x[None, :] - mean)[..., None], lower=True)[..., 0]  # (M, k)
    logq = jnp.where(valid, -0.5 * jnp.sum(w**2, axis=-1) - logdet, -jnp.inf)
    return jnp.argmax(logq), w


def jumps(potential_fn, blocks: dict, state: HMCState, split=None, sweeps: int = 1) -> tuple[HMCState, jax.Array]:
    """``sweeps`` rounds of one mode jump for each leg of ``blocks``, leg after leg, from ``state`` (one chain).

    ``split``: None, or ``(leg_loglik, prior_potential)``, functions of the latent values with
    ``potential_fn = prior_potential − Σ leg_loglik``, where leg ℓ's log-likelihood depends on leg
    ℓ's entries alone.  Then every leg's proposal is evaluated in one pass (its likelihood does
    not see the other legs), and each jump in turn needs only the prior, which couples the legs;
    without it each jump evaluates the whole potential.  Returns the state (its potential energy
    and gradient those of the values it ends at) and how many jumps were taken.
    """
    flat, unravel = ravel_pytree(state.z)
    index, mean, chol, logdet, valid = (blocks[k] for k in ("index", "mean", "chol", "logdet", "valid"))
    J, M = valid.shape
    rows = jnp.arange(J)
    prior_fn = potential_fn if split is None else split[1]

    def leg_terms(f):
        """Each block's leg's log-likelihood (zeros without ``split``: the prior function is all of it)."""
        return jnp.zeros(J, f.dtype) if split is None else split[0](unravel(f))[blocks["leg"]].astype(f.dtype)

    def sweep(carry, key):
        flat, ll, energy = carry
        k_to, k_acc = jax.random.split(key)
        a, w = jax.vmap(_labels)(flat[index], mean, chol, logdet, valid)  # (J,), (J, M, k)
        others = valid & (jnp.arange(M)[None, :] != a[:, None])
        b = jax.random.categorical(k_to, jnp.where(others, 0.0, -jnp.inf))  # (J,)
        x_new = (mean[rows, b] + jnp.einsum("jkl,jl->jk", chol[rows, b], w[rows, a])).astype(flat.dtype)
        back, _ = jax.vmap(_labels)(x_new, mean, chol, logdet, valid)
        ll_new = leg_terms(flat.at[index].set(x_new))
        # the map's Jacobian (the choice of b is symmetric) and the likelihood's change
        log_ratio = logdet[rows, b] - logdet[rows, a] + ll_new - ll
        log_u = jnp.log(jax.random.uniform(k_acc, (J,)))

        def one(carry, j):
            flat_c, energy_c = carry
            flat_j = flat_c.at[index[j]].set(x_new[j])
            energy_j = prior_fn(unravel(flat_j))
            ratio = log_ratio[j] + energy_c - energy_j
            take = (back[j] == b[j]) & jnp.isfinite(ratio) & (log_u[j] < ratio)
            return (jnp.where(take, flat_j, flat_c), jnp.where(take, energy_j, energy_c)), take

        (flat, energy), taken = jax.lax.scan(one, (flat, energy), rows)
        return (flat, jnp.where(taken, ll_new, ll), energy), taken

    key, k_sweeps = jax.random.split(state.rng_key)
    (flat_end, _, _), taken = jax.lax.scan(sweep, (flat, leg_terms(flat), prior_fn(state.z)),
                                           jax.random.split(k_sweeps, sweeps))
    z_end = unravel(flat_end)
    pe, grad = jax.value_and_grad(potential_fn)(z_end)
    moved = jnp.any(taken)

    def pick(new, old):
        return jnp.where(moved, new, old)

    return state._replace(
        z=z_end,
        z_grad=jax.tree.map(pick, grad, state.z_grad),
        potential_energy=pick(pe, state.potential_energy),
        energy=state.energy + pick(pe - state.potential_energy, 0.0),
        rng_key=key,
    ), jnp.sum(taken).astype(jnp.int32)


class ModeJumpNUTS(NUTS):
    """NUTS, each transition followed by a mode jump for each leg of ``blocks`` (see the module's docstring).

    Takes NUTS's arguments, ``blocks`` (:class:`JumpBlocks`), ``split``: None, or a function
    of the model's arguments returning ``(leg_loglik, prior_potential)`` (see :func:`jumps`;
    ``blocks.leg`` then says which entry of ``leg_loglik`` is each block's), and ``sweeps``:
    rounds of jumps after each transition (with ``split`` each round costs one pass of the
    likelihood).  Its state is :data:`JumpState`: NUTS's, and ``mode_jump``, how many jumps
    were taken after the last transition.
    """

    def __init__(self, model=None, *, blocks: JumpBlocks, split=None, sweeps: int = 3, **kwargs):
        super().__init__(model, **kwargs)
        self.blocks = blocks
        self._split = split
        self._sweeps = int(sweeps)
        chol = np.asarray(blocks.chol, np.float64)
        self._arrays = {
            "index": np.asarray(blocks.index, np.int32),
            "mean": np.asarray(blocks.mean, np.float64),
            "chol": chol,
            "logdet": np.sum(np.log(np.abs(np.diagonal(chol, axis1=-2, axis2=-1))), axis=-1),
            "valid": np.asarray(blocks.valid, bool),
            "leg": np.asarray(blocks.leg if blocks.leg is not None else np.arange(blocks.n_legs), np.int32),
        }

    def init(self, rng_key, num_warmup, init_params=None, model_args=(), model_kwargs={}):
        state = super().init(rng_key, num_warmup, init_params, model_args, model_kwargs)
        return JumpState(*state, jnp.zeros(jnp.shape(state.i), jnp.int32))

    def sample(self, state, model_args, model_kwargs):
        hmc = super().sample(HMCState(*state[:-1]), model_args, model_kwargs)
        pe_fn = self.get_potential_fn(model_args, model_kwargs)
        split = None if self._split is None else self._split(model_args, model_kwargs)
        dtype = hmc.potential_energy.dtype
        arrays = {k: jnp.asarray(v, dtype if v.dtype.kind == "f" else v.dtype) for k, v in self._arrays.items()}

        def one(s):
            return jumps(pe_fn, arrays, s, split, self._sweeps)

        # vectorized chains hold a leading chain axis in every field
        hmc, moved = (jax.vmap(one) if jnp.ndim(hmc.i) else one)(hmc)
        return JumpState(*hmc, moved)


#: The smallest precision of a refined Gaussian along any direction, on the fit's standardised scale
#: (each leg's entries are its parameters standardised by their prior: unit precision is the prior's).
#: On 20 legs × 1 min (model 3 + ``angle_delay``) one leg's curvature at five of its modes held an
#: eigenvalue of −0.01 to −0.07 beside others near 1; dropping those modes dropped the one its chains
#: sat in, and every jump from there was refused.
PRECISION_FLOOR = 1.0


def refine_blocks(blocks: JumpBlocks, z0: dict, conditional_loglik, prior_potential, max_iter: int = 300,
                  step: float = 1e-4) -> JumpBlocks | None:
    """The modes and Gaussians of ``blocks`` moved to the posterior's own; None where no leg keeps two modes.

    ``blocks`` holds approximations of each leg's modes made elsewhere (a leg alone, a smoother
    model): a chain's draws in mode d can sit several of its sds away from them, and a jump
    that keeps the offset from one to the other lands off the target's mode and is refused.
    Here, for each slot m of the blocks, every leg's entries are optimised at once under the
    posterior given each leg's mode-m label: ``prior_potential(z) − Σ_j
    conditional_loglik(z)[leg_j, delays[j, m]]`` (L-BFGS in the coordinates each old Gaussian
    whitens, the other entries held at ``z0``); the likelihood is a sum over legs, so one
    optimisation serves all legs.  From there a second optimisation climbs the fit's own
    density, ``prior_potential(z) − Σ_j logsumexp_l conditional_loglik(z)[leg_j, l]``: the
    chains sample θ with the labels summed out, and where two labels are about as likely at
    one θ, that density's mode (where the chains sit) lies between the labels' own.  Slots
    that climb to one mode are then one (below).  Each leg's new Gaussian is the inverse of its
    block of the curvature there (central differences of the gradient, all legs' entry c perturbed
    together: the legs are coupled through the prior alone), its precision's eigenvalues
    floored at :data:`PRECISION_FLOOR`.  A slot whose optimum or curvature is not finite keeps
    nothing: the leg loses that mode.

    ``conditional_loglik(z)``: (L, D) log p(y_ℓ, label | θ_ℓ) of every leg and label.
    """
    flat0, unravel = ravel_pytree(z0)
    flat0 = np.asarray(flat0, np.float64)
    J, M, k = np.shape(blocks.mean)
    legs = np.asarray(blocks.leg if blocks.leg is not None else np.arange(J))
    index = np.asarray(blocks.index)
    mean, chol, valid = np.array(blocks.mean, np.float64), np.array(blocks.chol, np.float64), np.array(blocks.valid)

    def objective(u, labels, on, centre, scale, marginal):
        x = centre + jnp.einsum("jkl,jl->jk", scale, u.reshape(J, k))
        x = jnp.where(on[:, None], x, jnp.asarray(flat0)[index])
        z = unravel(jnp.asarray(flat0).at[index].set(x))
        by_label = conditional_loglik(z)[jnp.asarray(legs)]
        terms = jnp.where(marginal, jax.scipy.special.logsumexp(by_label, axis=-1),
                          jnp.take_along_axis(by_label, labels[:, None], axis=1)[:, 0])
        return prior_potential(z) - jnp.sum(jnp.where(on, terms, 0.0))

    # one compilation for every slot and stage: the slot's labels and Gaussians are arguments
    value_and_grad = jax.jit(jax.value_and_grad(objective))
    for m in range(M):
        if not valid[:, m].any():
            continue
        slot = (jnp.asarray(np.where(valid[:, m], blocks.delays[:, m], 0)), jnp.asarray(valid[:, m]),
                jnp.asarray(mean[:, m]), jnp.asarray(chol[:, m]))
        u = np.zeros(J * k)
        # first under each leg's label, which parts the slots; then under the fit's own density (the
        # labels summed out) from there, to the mode of it the chains find: on 20 legs × 1 min one
        # leg's chains sat four whitened sds from its label's mode, nearer one of the sum's
        for marginal in (False, True):
            stage = (*slot, jnp.asarray(marginal))
            f0 = float(value_and_grad(jnp.asarray(u), *stage)[0])

            def f(v, stage=stage, f0=f0):
                # less the start's value: L-BFGS's test of relative reduction is otherwise met at the
                # magnitude of a log density of thousands of samples, long before the mode
                val, g = value_and_grad(jnp.asarray(v, jnp.float64), *stage)
                return float(val) - f0, np.asarray(g, np.float64)

            res = optimize.minimize(f, u, jac=True, method="L-BFGS-B", options={"maxiter": max_iter, "gtol": 1e-4})
            u = res.x
        u = u.reshape(J, k)
        H = np.empty((J, k, k))
        for c in range(k):
            e = np.zeros((J, k))
            e[:, c] = step
            H[:, :, c] = (f((u + e).ravel())[1] - f((u - e).ravel())[1]).reshape(J, k) / (2.0 * step)
        for j in np.flatnonzero(valid[:, m]):
            if not (np.isfinite(res.fun) and np.all(np.isfinite(u[j])) and np.all(np.isfinite(H[j]))):
                valid[j, m] = False
                continue
            # x = mean + C u, and the curvature in u is H[j]: the precision in x is C⁻ᵀ H[j] C⁻¹, its
            # eigenvalues floored at the prior's unit precision, as the screen's are: a direction
            # the data leave flat (its curvature a rounding error either side of 0) is no reason
            # to lose the mode, which may be the one the chains sit in
            C = chol[j, m].copy()  # chol[j, m] is replaced below
            C_inv = np.linalg.solve(C, np.eye(k))
            P = C_inv.T @ H[j] @ C_inv
            w, V = np.linalg.eigh(0.5 * (P + P.T))
            w = np.maximum(w, PRECISION_FLOOR)
            cov = (V / w[None, :]) @ V.T
            try:
                chol[j, m] = np.linalg.cholesky(0.5 * (cov + cov.T))
            except np.linalg.LinAlgError:
                valid[j, m] = False
                continue
            mean[j, m] = mean[j, m] + C @ u[j]
    # slots that ended at one mode are one mode: a jump between them only wastes a proposal
    for j in range(J):
        for m in range(M):
            for m2 in range(m):
                if valid[j, m] and valid[j, m2]:
                    w = np.linalg.solve(chol[j, m2], mean[j, m] - mean[j, m2])
                    if np.linalg.norm(w) < 1.0:
                        valid[j, m] = False
    keep = valid.sum(axis=1) >= 2
    if not keep.any():
        return None
    return dataclasses.replace(blocks, index=index[keep], mean=mean[keep], chol=chol[keep], valid=valid[keep],
                               legs=tuple(n for n, kk in zip(blocks.legs, keep) if kk) if blocks.legs else (),
                               delays=None if blocks.delays is None else np.asarray(blocks.delays)[keep],
                               leg=legs[keep])
