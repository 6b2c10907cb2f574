"""The fit samples G′ through the passive stiffness at rest, K₀ = G′·π/180 + k1·k2: the coordinate
change, its Jacobian, and a posterior that is the one of the declared priors whatever the coordinates."""

import numpy as np
import pytest
from numpyro import handlers
from numpyro.infer.util import potential_energy

from quadshank.data._simulate import simulate_cohort
from quadshank.inference import _density
from quadshank.inference._density import numpyro_model
from quadshank.inference._priors import (
    STIFFNESS_SITE,
    build_model,
    standard_from_stiffness,
    stiffness_from_standard,
    stiffness_jacobian,
    stiffness_params,
)
from quadshank.model._likelihood import prepare

PARAMS = stiffness_params(build_model("model3s"))


def _points(n=200, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(0.0, 1.5, (3, n))  # (s_gravity, s_k1, s_k2), out to the priors' tails


def test_the_models_with_gravity_and_elasticity_sample_the_stiffness_and_others_do_not():
    assert [p.name for p in PARAMS] == ["gravity", "k1", "k2"]
    assert stiffness_params(build_model("passive")) is not None
    assert stiffness_params(build_model("model3s"), centred=False) is None  # the non-centred form keeps G′


def test_the_stiffness_coordinate_inverts_and_its_jacobians_are_the_derivatives():
    s_g, s_k1, s_k2 = _points()
    t = stiffness_from_standard(s_g, s_k1, s_k2, PARAMS)
    back, log_jac, valid = standard_from_stiffness(t, s_k1, s_k2, PARAMS)
    assert valid.all()
    np.testing.assert_allclose(back, s_g, atol=1e-9)
    h = 1e-6
    dsg_dt = (standard_from_stiffness(t + h, s_k1, s_k2, PARAMS)[0] - standard_from_stiffness(t - h, s_k1, s_k2, PARAMS)[0]) / (2 * h)
    np.testing.assert_allclose(log_jac, np.log(dsg_dt), atol=1e-6)
    assert log_jac.max() > 0.05  # where k1·k2 takes a share of K₀ the Jacobian is not 1
    for i in range(0, 200, 37):
        x = np.array([s_g[i], s_k1[i], s_k2[i]])
        fd = [(stiffness_from_standard(*(x + h * e), PARAMS) - stiffness_from_standard(*(x - h * e), PARAMS)) / (2 * h)
              for e in np.eye(3)]
        np.testing.assert_allclose(stiffness_jacobian(*x, PARAMS), fd, atol=1e-6)


def test_a_stiffness_below_the_elasticitys_share_has_no_gravity():
    """K₀ ≤ k1·k2 would need G′ ≤ 0: such a point is marked invalid (the fit gives it no density)."""
    s_k1, s_k2 = np.array([3.0]), np.array([3.0])  # k1·k2 = 25e^2.4 · 0.05e^1.2: K₀'s 30 deg/s²/deg and more
    t = np.array([-3.0])
    assert not standard_from_stiffness(t, s_k1, s_k2, PARAMS)[2].any()


@pytest.mark.parametrize("model_name", ["model3s", "passive"])
def test_the_posterior_is_the_same_in_either_coordinates(monkeypatch, model_name):
    """The fit's potential energy at (t, rest) equals that of the same model sampled in G′ at the
    G′ that t implies, less log |∂s_G′/∂t|: the declared priors and the likelihood, whichever
    coordinates the sampler moves in."""
    cohort, _ = simulate_cohort(legs=["TN-left", "JM-left"], minutes=0.2, seed=3, trials=(1,))
    model = build_model(model_name)
    data = prepare(cohort, model)
    arrays = data.leg_arrays()

    def sheared(arrays):
        return numpyro_model(model, data, arrays)

    with monkeypatch.context() as m:
        m.setattr(_density, "stiffness_params", lambda model, centred=True: None)
        trace = handlers.trace(handlers.seed(sheared, 5)).get_trace(arrays)
        plain = {k: v["value"] for k, v in trace.items() if v["type"] == "sample" and not v["is_observed"]}
        assert "gravity_s_leg" in plain and STIFFNESS_SITE not in plain
        plain["sigma"], plain["nu"] = np.log(plain["sigma"]), np.log(plain["nu"])  # their unconstrained values
        rng = np.random.default_rng(1)
        # stiff elasticities, where k1·k2 takes a fifth of K₀ or more and the Jacobian is far from 1
        shift = {"gravity_s_leg": 0.0, "k1_s_leg": 1.5, "k2_s_leg": 1.0}
        points = [{**plain, **{k: plain[k] + d + rng.normal(0.0, 0.3, np.shape(plain[k])) for k, d in shift.items()}}
                  for _ in range(3)]
        u_plain = [float(potential_energy(sheared, (arrays,), {}, p)) for p in points]

    for p, u in zip(points, u_plain):
        s = {k: np.asarray(p[f"{k}_s_leg"], np.float64) for k in ("gravity", "k1", "k2")}
        t = stiffness_from_standard(s["gravity"], s["k1"], s["k2"], PARAMS)
        log_jac = standard_from_stiffness(t, s["k1"], s["k2"], PARAMS)[1]
        q = {k: v for k, v in p.items() if k != "gravity_s_leg"} | {STIFFNESS_SITE: t.astype(np.float32)}
        u_sheared = float(potential_energy(sheared, (arrays,), {}, q))
        assert np.sum(log_jac) > 0.2
        # to a few roundings of the energy in single precision
        assert u_sheared == pytest.approx(u - float(np.sum(log_jac)), abs=8 * float(np.spacing(np.float32(abs(u)))))
