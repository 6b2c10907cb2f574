"""Chains across several JAX devices: forced CPU devices stand in for several GPUs."""

import os
import subprocess
import sys
import textwrap
from types import SimpleNamespace

import jax
import numpy as np
import pytest

from quadshank.inference._nuts import FitSettings, chain_method

# Run in a fresh process: the number of host devices is fixed when JAX starts.
SCRIPT = textwrap.dedent(
    """
    import sys
    from types import SimpleNamespace

    import jax
    import numpy as np

    from quadshank.data._simulate import simulate_cohort
    from quadshank.inference import _nuts
    from quadshank.inference._nuts import FitSettings, chain_method, fit
    from quadshank.inference._priors import build_model

    assert jax.local_device_count() == 2, jax.devices()
    data = SimpleNamespace(sample_mask=np.ones((1, 100), bool))
    methods = [chain_method(FitSettings(chains=c), data) for c in (2, 4)]
    methods.append(chain_method(FitSettings(chains=2, target_ess=200), data))  # blocks: one compilation

    # equal twitches: a short, smooth posterior whose chains draw no divergence (the runs, not the data, are tested)
    cohort, _ = simulate_cohort(legs=["TN-left"], minutes=0.3, seed=2, trials=(1,), twitch_cv=0.0)
    model = build_model("model1")
    out = {}
    for method in ("sequential", "parallel"):
        # in double precision each device's program rounds nearly as one device's does, so the draws
        # agree to about 1e-5 (two chains differ by 1e-2; at mixed precision the chains part)
        settings = FitSettings(chains=2, warmup=20, draws=10, seed=5, chain_method=method, start="prior", precision="double")
        mcmc, _ = fit(cohort, model, settings, progress=False)
        out[method] = np.asarray(mcmc.get_samples(group_by_chain=True)["gain"])
        out[method + "_steps"] = np.asarray(mcmc.get_extra_fields(group_by_chain=True)["num_steps"])

    calls = []

    def met_at_second(samples, *args):  # the stopping rule has its own tests; here, the blocks on devices
        calls.append(samples["gain_s_leg"].shape[1])
        return {"met": len(calls) == 2, "draws_per_chain": calls[-1], "ess_needed": 200, "rhat_max": 1.0,
                "ess_bulk_min": 0.0, "ess_tail_min": 0.0, "lagging": "gain"}

    _nuts.target_status = met_at_second
    settings = FitSettings(chains=2, warmup=20, draws=5, seed=5, chain_method="parallel", start="prior", target_ess=200,
                           precision="double")
    blocks, _ = fit(cohort, model, settings, progress=False)
    out["blocks"] = np.asarray(blocks.get_samples(group_by_chain=True)["gain"])
    np.savez(sys.argv[1], methods=np.asarray(methods), **out)
    """
)


def test_parallel_chains_on_two_devices_draw_what_one_device_draws(tmp_path):
    script, result = tmp_path / "devices.py", tmp_path / "draws.npz"
    script.write_text(SCRIPT)
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2", "JAX_PLATFORMS": "cpu"}
    run = subprocess.run([sys.executable, str(script), str(result)], env=env, capture_output=True, text=True,
                         timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    got = np.load(result)
    # auto: a device per chain runs the chains in parallel; four chains on two devices do not, nor
    # a fit drawn to a target ESS in blocks (parallel chains would compile once per block)
    assert list(got["methods"]) == ["parallel", "vectorized", "vectorized"]
    seq, par = got["sequential"], got["parallel"]
    assert par.shape[:2] == (2, 10)
    assert not np.allclose(par[0], par[1])  # each device ran its own chain, not one chain twice
    np.testing.assert_allclose(par, seq, rtol=1e-4)
    np.testing.assert_array_equal(got["parallel_steps"], got["sequential_steps"])
    # drawing to a target on devices: two blocks of 5 continue the chains as one run of 10
    np.testing.assert_allclose(got["blocks"], par, rtol=1e-4)


def test_parallel_chains_without_a_device_each_run_one_after_another_and_say_so():
    data = SimpleNamespace(sample_mask=np.ones((1, 100), bool))
    chains = jax.local_device_count() + 1
    with pytest.warns(UserWarning, match=rf"needs a JAX device per chain: {chains} chains"):
        assert chain_method(FitSettings(chains=chains, chain_method="parallel"), data) == "sequential"
    assert chain_method(FitSettings(chains=chains), data) == "vectorized"
