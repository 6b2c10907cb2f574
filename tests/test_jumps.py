"""Jumps between modes (quadshank.inference._jumps): the kernel keeps the posterior, crosses what NUTS cannot."""

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
import pytest
from numpyro.infer import MCMC, NUTS

from quadshank.inference._jumps import PRECISION_FLOOR, JumpBlocks, ModeJumpNUTS

# three well-separated 2-D Gaussians of unequal weight, size and correlation: NUTS cannot cross
# the valleys (tens of sds wide), and a jump that forgot its Jacobian or its check of the mode it
# lands nearest would weigh them wrongly
WEIGHTS = np.array([0.5, 0.3, 0.2])
MEANS = np.array([[6.0, 6.0], [-6.0, -6.0], [6.0, -6.0]])
COVS = np.array([[[0.09, 0.0], [0.0, 0.09]], [[0.36, 0.2], [0.2, 0.25]], [[0.04, -0.03], [-0.03, 0.16]]])
CHOLS = np.linalg.cholesky(COVS)


def _mixture():
    x = numpyro.sample("x", dist.ImproperUniform(dist.constraints.real_vector, (), (2,)))
    lp = jnp.log(WEIGHTS) + dist.MultivariateNormal(MEANS, COVS).log_prob(x)
    numpyro.factor("mixture", jax.scipy.special.logsumexp(lp))


def _run(kernel, chains=3, draws=3000):
    mcmc = MCMC(kernel, num_warmup=300, num_samples=draws, num_chains=chains, chain_method="vectorized",
                progress_bar=False)
    # every chain starts in the first mode
    extra = ("mode_jump",) if isinstance(kernel, ModeJumpNUTS) else ()
    mcmc.run(jax.random.PRNGKey(3), init_params={"x": jnp.asarray(np.tile(MEANS[0], (chains, 1)))}, extra_fields=extra)
    x = np.asarray(mcmc.get_samples(group_by_chain=True)["x"])
    label = np.argmin(((x[..., None, :] - MEANS) ** 2).sum(-1), axis=-1)  # (chains, draws)
    return mcmc, x, label


def test_the_jumping_chains_weigh_separated_modes_as_the_posterior_does():
    blocks = JumpBlocks(index=np.array([[0, 1]]), mean=MEANS[None], chol=CHOLS[None], valid=np.ones((1, 3), bool))
    mcmc, x, label = _run(ModeJumpNUTS(_mixture, blocks=blocks))
    share = np.stack([(label == m).mean(axis=1) for m in range(3)], axis=1)  # (chains, modes)
    # every chain finds every mode in proportion to its weight (a few hundred visits each)
    np.testing.assert_allclose(share, np.tile(WEIGHTS, (3, 1)), atol=0.06)
    np.testing.assert_allclose(share.mean(axis=0), WEIGHTS, atol=0.035)
    # and within each mode the draws have its Gaussian's covariance
    pooled, lab = x.reshape(-1, 2), label.reshape(-1)
    for m in range(3):
        np.testing.assert_allclose(np.cov(pooled[lab == m].T), COVS[m], atol=0.2 * np.abs(COVS[m]).max())
    jumped = np.asarray(mcmc.get_extra_fields(group_by_chain=True)["mode_jump"])
    # one leg here, three rounds of jumps after each transition: 0 … 3 per draw
    assert set(np.unique(jumped)) == {0, 1, 2, 3} and 0.3 < jumped.mean() < 2.7


def test_nuts_alone_stays_in_the_mode_it_starts_in():
    """The premise of the jumps: without them no chain leaves the first mode."""
    _, _, label = _run(NUTS(_mixture), draws=1000)
    assert np.all(label == 0)


def test_a_leg_needs_two_modes_and_consistent_shapes():
    ok = dict(index=np.array([[0, 1]]), mean=MEANS[None], chol=CHOLS[None], valid=np.ones((1, 3), bool))
    JumpBlocks(**ok)
    with pytest.raises(ValueError, match="two modes"):
        JumpBlocks(**{**ok, "valid": np.array([[True, False, False]])})
    with pytest.raises(ValueError, match="disagree"):
        JumpBlocks(**{**ok, "index": np.array([[0, 1, 2]])})


def test_a_jump_landing_nearer_a_third_mode_is_refused():
    """From x = 2.5 in the tail of mode 0 (at 0), the map to mode 1 (at 10) lands at 12.5, nearer
    mode 2 (at 13): the reverse jump would start from mode 2, so the move is refused however high
    the density there.  The map to mode 2 (landing at 15.5) may be taken."""
    from numpyro.infer.hmc import HMCState

    from quadshank.inference._jumps import jumps

    means = np.array([[0.0], [10.0], [13.0]])

    def potential(z):
        return -jax.scipy.special.logsumexp(-0.5 * ((z["x"] - means[:, 0]) ** 2))

    kernel = ModeJumpNUTS(_mixture, blocks=JumpBlocks(index=np.array([[0]]), mean=means[None],
                                                      chol=np.ones((1, 3, 1, 1)), valid=np.ones((1, 3), bool)))
    blocks = {k: jnp.asarray(v) for k, v in kernel._arrays.items()}
    z = {"x": jnp.asarray(2.5)}
    ends = []
    for seed in range(40):
        state = HMCState(0, z, {"x": jnp.asarray(0.0)}, potential(z), potential(z), None, None, 0, 0.0, 0.0, False, None,
                         jax.random.PRNGKey(seed))
        new, moved = jumps(potential, blocks, state)
        ends.append(float(new.z["x"]))
        assert int(moved) == (ends[-1] != 2.5)
        assert float(new.potential_energy) == pytest.approx(float(potential(new.z)))
    assert set(np.round(ends, 6)) == {2.5, 15.5}


def test_legs_jump_in_turn_under_a_prior_that_couples_them():
    """Two legs, each with two modes in its likelihood, coupled by a prior on their sum: the jumps,
    scoring every leg's likelihood in one pass and the prior leg by leg (``split``), weigh the four
    joint modes as a quadrature of the posterior does."""
    centres = np.array([[-5.0, 5.0], [-5.0, 5.0]])
    sds = np.array([[0.4, 0.8], [0.5, 0.3]])
    log_w = np.log(np.array([[0.6, 0.4], [0.5, 0.5]]))

    def leg_loglik(z):
        x = z["x"]
        return jax.scipy.special.logsumexp(log_w + dist.Normal(centres, sds).log_prob(x[:, None]), axis=1)

    def prior_potential(z):
        return 0.5 * ((z["x"].sum() - 3.0) / 8.0) ** 2

    def model():
        x = numpyro.sample("x", dist.ImproperUniform(dist.constraints.real_vector, (), (2,)))
        numpyro.factor("legs", leg_loglik({"x": x}).sum())
        numpyro.factor("prior", -prior_potential({"x": x}))

    blocks = JumpBlocks(index=np.array([[0], [1]]), mean=centres[..., None], chol=sds[..., None, None],
                        valid=np.ones((2, 2), bool), leg=np.array([0, 1]))
    kernel = ModeJumpNUTS(model, blocks=blocks, split=lambda args, kwargs: (leg_loglik, prior_potential))
    mcmc = MCMC(kernel, num_warmup=300, num_samples=3000, num_chains=3, chain_method="vectorized", progress_bar=False)
    mcmc.run(jax.random.PRNGKey(1), init_params={"x": jnp.full((3, 2), -5.0)}, extra_fields=("mode_jump",))
    x = np.asarray(mcmc.get_samples()["x"])
    share = np.array([[np.mean(((x[:, 0] > 0) == s0) & ((x[:, 1] > 0) == s1)) for s1 in (0, 1)] for s0 in (0, 1)])
    # the posterior's mass in each quadrant, by quadrature
    g = np.linspace(-12.0, 12.0, 2401)
    X0, X1 = np.meshgrid(g, g, indexing="ij")
    z = {"x": jnp.stack([jnp.asarray(X0.ravel()), jnp.asarray(X1.ravel())], axis=1)}
    lp = np.asarray(jax.vmap(lambda v: leg_loglik({"x": v}).sum() - prior_potential({"x": v}))(z["x"])).reshape(X0.shape)
    p = np.exp(lp - lp.max())
    exact = np.array([[p[((X0 > 0) == s0) & ((X1 > 0) == s1)].sum() for s1 in (0, 1)] for s0 in (0, 1)])
    exact /= exact.sum()
    assert exact.min() > 0.05  # every joint mode matters
    np.testing.assert_allclose(share, exact, atol=0.03)
    # two legs in three rounds: more than one leg jumps after a transition
    assert 2 < np.asarray(mcmc.get_extra_fields()["mode_jump"]).max() <= 6


def test_refined_blocks_sit_at_each_labels_mode_with_its_covariance():
    """refine_blocks moves rough Gaussians (three sds off, twice as wide) to each leg's mode under
    each label and to the curvature there, all legs in one optimisation per slot."""
    from quadshank.inference._jumps import refine_blocks

    centres = np.array([[[1.0, -2.0], [4.0, 0.5]], [[-3.0, 1.0], [2.0, 2.0]]])  # (legs, labels, 2)
    covs = np.array([[COVS[1], COVS[2]], [COVS[2], COVS[1]]])

    def conditional_loglik(z):
        x = z["x"].reshape(2, 2)
        return dist.MultivariateNormal(jnp.asarray(centres), jnp.asarray(covs)).log_prob(x[:, None, :])

    def prior_potential(z):
        return 1e-8 * jnp.sum(z["x"] ** 2)

    rough_chol = 2.0 * np.linalg.cholesky(covs)
    rough = JumpBlocks(index=np.array([[0, 1], [2, 3]]), mean=centres + np.einsum("lmij,j->lmi", rough_chol, [1.5, -1.0]),
                       chol=rough_chol, valid=np.ones((2, 2), bool), delays=np.array([[0, 1], [0, 1]]),
                       legs=("a", "b"), leg=np.array([0, 1]))
    with jax.enable_x64(True):  # as a fit runs it
        new = refine_blocks(rough, {"x": jnp.zeros(4)}, conditional_loglik, prior_potential)
    np.testing.assert_allclose(new.mean, centres, atol=1e-3)
    np.testing.assert_allclose(np.einsum("lmij,lmkj->lmik", new.chol, new.chol), covs, atol=2e-3)
    assert np.allclose(np.triu(new.chol, 1), 0.0) and new.legs == ("a", "b")


def test_the_jumps_can_be_switched_off_from_the_command_line():
    from quadshank.cli import build_parser

    for command in ("fit", "recovery"):
        extra = ["d", "--out", "o"] if command == "fit" else ["--out", "o"]
        assert build_parser().parse_args([command, *extra]).mode_jumps is True
        assert build_parser().parse_args([command, *extra, "--no-mode-jumps"]).mode_jumps is False


def test_refined_blocks_climb_to_the_mode_of_the_density_the_chains_sample():
    """Two labels about as likely at one θ (their centres 0.8 sd apart) make one mode of the density
    with the labels summed out, halfway between theirs: the refined slot sits there, where the
    chains do, and the far third label keeps a slot of its own."""
    from quadshank.inference._jumps import refine_blocks

    centres = np.array([[[0.0, 0.0], [0.8, 0.0], [8.0, 1.0]]])  # (legs, labels, 2), unit covariances

    def conditional_loglik(z):
        return dist.MultivariateNormal(jnp.asarray(centres), jnp.eye(2)).log_prob(z["x"].reshape(1, 1, 2))

    def prior_potential(z):
        return 1e-8 * jnp.sum(z["x"] ** 2)

    rough = JumpBlocks(index=np.array([[0, 1]]), mean=centres + 0.3, chol=np.tile(np.eye(2), (1, 3, 1, 1)),
                       valid=np.ones((1, 3), bool), delays=np.array([[0, 1, 2]]), legs=("a",), leg=np.array([0]))
    with jax.enable_x64(True):
        new = refine_blocks(rough, {"x": jnp.zeros(2)}, conditional_loglik, prior_potential)
    kept = new.mean[0][new.valid[0]]
    assert len(kept) == 2
    np.testing.assert_allclose(kept[0], [0.4, 0.0], atol=1e-3)  # the sum's mode, by symmetry
    np.testing.assert_allclose(kept[1], [8.0, 1.0], atol=1e-3)


def test_a_direction_the_data_leave_flat_keeps_the_mode_with_the_priors_width():
    """A mode whose curvature is 0 along one direction (the data do not inform it) stays a slot, its
    Gaussian as wide as the prior (unit precision on the standardised scale) along it."""
    from quadshank.inference._jumps import refine_blocks

    centres = np.array([[-3.0, 3.0]])  # (legs, labels): x0's mode per label; x1 no label informs

    def conditional_loglik(z):
        return -0.5 * ((z["x"][0] - jnp.asarray(centres)) / 0.5) ** 2

    def prior_potential(z):
        return 1e-8 * z["x"][0] ** 2

    rough = JumpBlocks(index=np.array([[0, 1]]), mean=np.array([[[-2.5, 0.0], [2.5, 0.0]]]),
                       chol=np.tile(np.eye(2), (1, 2, 1, 1)), valid=np.ones((1, 2), bool), delays=np.array([[0, 1]]),
                       legs=("a",), leg=np.array([0]))
    with jax.enable_x64(True):
        new = refine_blocks(rough, {"x": jnp.zeros(2)}, conditional_loglik, prior_potential)
    assert new is not None and new.valid.all()
    np.testing.assert_allclose(new.mean[0, :, 0], [-3.0, 3.0], atol=1e-3)
    cov = np.einsum("mij,mkj->mik", new.chol[0], new.chol[0])
    np.testing.assert_allclose(cov[:, 0, 0], 0.25, rtol=1e-3)
    np.testing.assert_allclose(cov[:, 1, 1], 1.0 / PRECISION_FLOOR, rtol=1e-6)
