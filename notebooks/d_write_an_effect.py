# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # (d) Writing your own effect
#
# A model in quadshank is a flat tuple of *effects*. Each effect declares its
# parameters (units, support, prior, hierarchy level) and adds to the dynamics
# through one pure JAX method. Once registered, an effect goes everywhere a
# built-in one goes: the hierarchical fit (`build_model(..., [name])`,
# `quadshank fit --add-effect name`), the modelling loop's candidates
# (`diagnose`, `discover`), and the registry-driven checks of
# `tests/test_effects.py`.
#
# This notebook writes one, simulates data from a model that has it, and shows
# that the modelling loop's screen finds it and recovers its parameter.

# %%
import dataclasses
import json
import os
import warnings
from pathlib import Path

from tqdm import TqdmWarning

warnings.filterwarnings("ignore", category=TqdmWarning)

import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from quadshank import (
    Cohort,
    Effect,
    Param,
    Trial,
    build_model,
    register_effect,
    registered_effects,
    simulate_angles,
    simulate_cohort,
)
from quadshank.inference import leg_draw_models
from quadshank.loop import candidates, rank_effects, verdict_sentence
from quadshank.model import measure

# %matplotlib inline
plt.rcParams["figure.dpi"] = 72
pd.set_option("display.precision", 3)

# %% [markdown]
# ## Settings

# %%
SMALL = os.environ.get("QUADSHANK_NOTEBOOK_SMALL") == "1"
LEG, SEED = "JM-left", 4
if SMALL:
    MINUTES, N_DRAWS, N_J_DRAWS, STRIDE = 0.5, 60, 10, 20
    COMPETITORS = ["hill_velocity"]
else:
    MINUTES, N_DRAWS, N_J_DRAWS, STRIDE = 1.0, 150, 30, 5
    COMPETITORS = ["hill_velocity", "torque_angle_peak", "potentiation"]
WORK = Path("_work") / "d_write_an_effect"
WORK.mkdir(parents=True, exist_ok=True)

# %% [markdown]
# ## The effect
#
# Model 3 scales each twitch by a torque–angle factor times a torque–velocity
# factor, (1 + γ_angle·φ)(1 + γ_velocity·φ̇). The two are *separable*: the
# velocity dependence is the same at every knee angle. Muscle is not quite
# like that. How steeply force falls with shortening velocity depends on the
# muscle's length. The simplest departure from separability is a coupling
# term in the product φ·φ̇:
#
#     factor = exp(c · (φ / 30°) · (φ̇ / 300 deg/s))
#
# The angle and velocity are scaled by typical values, so c is
# dimensionless. The exponential keeps the factor positive, and c = 0 is
# model 3.
#
# It is a *gain* effect: it scales the twitch through `factor(ctx)`, where `ctx`
# holds the knee angle and velocity at the twitch's onset. Gain effects must
# be stateless to be fitted. This is the whole of it:

# %%
@register_effect
@dataclasses.dataclass(frozen=True)
class AngleVelocityCoupling(Effect):
    """Torque–angle–velocity coupling: the twitch × exp(c·(φ/30°)·(φ̇/300 deg/s))."""

    kind = "gain"
    name = "angle_velocity_coupling"
    signature = "velocity"  # the residual feature where its absence shows
    params = (Param("coupling", "1", prior=("normal", 0.0, 0.3), doc="c: log-gain at 30° and 300 deg/s"),)
    coupling: float = 0.0

    def factor(self, ctx):
        return jnp.exp(self.coupling * (ctx.angle / 30.0) * (ctx.velocity / 300.0))


NAME = AngleVelocityCoupling.name
print(NAME in registered_effects(), NAME in candidates(build_model("model3s")))

# %% [markdown]
# `register_effect` makes the class a JAX pytree over its declared parameters
# and lists it by name. It is now one of the candidates the modelling loop
# offers for `model3s`, and `build_model` composes it like any built-in effect:

# %%
model = build_model("model3s", [NAME])
[(e.name, e.kind, [p.name for p in e.declared_params()]) for e in model.effects]

# %% [markdown]
# ## Data from a model that has it
#
# The screen should find the effect where it is present. Data are made by
# the extended model itself. The stimulation is the simulated cohort's
# pseudorandom sequence for JM-left, trial 1. The parameters are model3s's
# defaults with c = 0.6: at 30° and 300 deg/s of extension the twitch is
# exp(0.6) ≈ 1.8 times as large, and in flexion it is smaller. The model is
# run through its sensors, and Gaussian noise of 40 deg/s² is added to the
# acceleration, about the simulator's accelerometer noise.

# %%
TRUE_C = 0.6
true_model = model.with_params(coupling=TRUE_C, delay=4)

template, _ = simulate_cohort(legs=[LEG], minutes=MINUTES, seed=SEED, trials=(1,))
stim = template.get(LEG, 1).stimulation
angle, velocity, m = simulate_angles(true_model, jnp.asarray(stim, jnp.float32))
seen_angle, seen_acc = (np.asarray(v, np.float64) for v in measure(true_model, angle, velocity, m))
rng = np.random.default_rng(SEED)
acc = seen_acc + 40.0 * rng.standard_normal(seen_acc.shape)
subject, side = LEG.split("-")
trial = Trial.from_signals(
    subject, side, 1, 0.01, seen_angle, acc, stim,
    velocity_deg_s=np.asarray(velocity, np.float64), source=f"model3s+{NAME}, c = {TRUE_C}",
)
cohort = Cohort((trial,))
print(f"{trial.n_samples} samples, {int((stim > 0).sum())} pulses; knee angle {seen_angle.min():.0f}° to {seen_angle.max():.0f}°")

# %% [markdown]
# How the coupling scales the twitches of these data: the factor at each
# pulse's onset state, against the knee velocity, coloured by the knee angle.

# %%
pulses = np.flatnonzero(stim > 0) + 4  # the state at the twitch's onset, d = 4 samples later
pulses = pulses[pulses < trial.n_samples]
f_true = np.exp(TRUE_C * (seen_angle[pulses] / 30.0) * (np.asarray(velocity)[pulses] / 300.0))
fig, ax = plt.subplots(figsize=(6, 3.6))
sc = ax.scatter(np.asarray(velocity)[pulses], f_true, c=seen_angle[pulses], cmap="coolwarm", s=12)
fig.colorbar(sc, label="knee angle [deg]")
ax.axhline(1.0, color="k", lw=0.8)
ax.set_xlabel("knee velocity at onset [deg/s]")
ax.set_ylabel("coupling factor")
ax.set_title(f"The true coupling (c = {TRUE_C}) at each pulse")
fig.tight_layout()

# %% [markdown]
# ## Screen it against the baseline
#
# `rank_effects` adds each candidate to `model3s` in turn and compares by
# ΔELPD and ΔJ_φ,p (notebook (c) explains the bar). Besides the new effect,
# the candidates here are built-in effects that also bend the twitch with
# angle or velocity, and could absorb part of the coupling.

# %%
ranking = rank_effects(
    cohort, "model3s", trials=(1,), legs=[LEG], effects=[NAME, *COMPETITORS],
    n_draws=N_DRAWS, n_j_draws=N_J_DRAWS, start_stride=STRIDE,
)
pd.DataFrame(
    [
        {
            "effect": r["effect"],
            "ΔELPD": r["delta_elpd"],
            "± SE": r["delta_elpd_se"],
            "J 1 s before [deg]": r["J_1000ms"]["before"]["median"],
            "J 1 s after [deg]": r["J_1000ms"]["after"]["median"],
            "clears the bar": "yes" if r["clears_bar"] else "no",
        }
        for r in ranking.rows
    ]
).set_index("effect")

# %%
print(f"Verdict: {ranking.verdict}.")
print(verdict_sentence(ranking))

# %% [markdown]
# ## The parameter recovered
#
# The screen of `model3s + angle_velocity_coupling` gives c at the posterior
# mode, and a band from its importance-weighted Laplace draws:

# %%
screen = ranking.fits[NAME]
draws = np.asarray(leg_draw_models(screen, LEG).effect(NAME).coupling, float)
c_mode = float(screen.values(LEG)["coupling"])
c_lo, c_hi = np.quantile(draws, [0.05, 0.95])
prior_sd = AngleVelocityCoupling.params[0].prior[2]
print(f"c: truth {TRUE_C}; mode {c_mode:.3f}, 90 % [{c_lo:.3f}, {c_hi:.3f}] (prior N(0, {prior_sd}))")

fig, ax = plt.subplots(figsize=(6, 3.2))
grid = np.linspace(-1.0, 1.5, 300)
ax.plot(grid, np.exp(-0.5 * (grid / prior_sd) ** 2) / (prior_sd * np.sqrt(2 * np.pi)), "k:", label="prior")
ax.hist(draws, bins=25, density=True, alpha=0.6, label="screen's draws (importance-resampled)")
ax.axvline(TRUE_C, color="tab:red", label="truth")
ax.set_xlabel("coupling c")
ax.set_yticks([])
ax.legend(fontsize=8)
fig.tight_layout()

# %% [markdown]
# The screen's posterior is far narrower than the prior and lies near the
# truth. Its band is a Laplace approximation about one mode, importance-weighted,
# and it can be narrower than the posterior: the cell below says whether the
# truth falls inside it. A band to quote comes from NUTS (`quadshank fit …
# --add-effect angle_velocity_coupling`); the screen's job is to rank.

# %%
half = (c_hi - c_lo) / 2
inside = c_lo <= TRUE_C <= c_hi
print(f"mode − truth = {c_mode - TRUE_C:+.3f}, {abs(c_mode - TRUE_C) / half:.1f} half-widths of the band; "
      f"truth {'inside' if inside else 'outside'} the screen's 90 % band; "
      f"prior 90 % width {2 * 1.645 * prior_sd:.2f}, the screen's {c_hi - c_lo:.3f}")

# %% [markdown]
# The other parameters of the extended model come out as well, here the
# linear gain factors that model 3 already had:

# %%
pd.Series({k: float(np.ravel(v)[0]) if np.size(v) == 1 else np.round(np.asarray(v), 3).tolist()
           for k, v in screen.values(LEG).items()}, dtype=object)

# %% [markdown]
# ## Beyond the screen
#
# The same name works in every other place a built-in effect does:
#
# ```python
# from quadshank import FitSettings, build_model, fit
# mcmc, data = fit(cohort, build_model("model3s", ["angle_velocity_coupling"]), FitSettings(chains=2))
# ```
#
# On the command line (with the effect registered in a module imported
# before the CLI runs, as `tests/conftest.py` does for the README's
# `cubic_torque_angle`):
#
# ```sh
# quadshank fit DATA --model model3s --add-effect angle_velocity_coupling --out fit
# quadshank discover DATA --effects angle_velocity_coupling,hill_velocity --out loop
# ```
#
# Registered in `tests/conftest.py`, the effect would also go through the
# checks of `tests/test_effects.py`. Those check that the likelihood's
# pulse-by-pulse output equals the rollout's, that gradients are finite, that
# jit and vmap agree, that prior draws give finite likelihoods, and that
# simulated data are recovered by the screen.

# %%
result = {
    "notebook": "d_write_an_effect",
    "small": SMALL,
    "effect": NAME,
    "verdict": ranking.verdict,
    "truth": TRUE_C,
    "recovered": {"mode": round(c_mode, 4), "lo": round(float(c_lo), 4), "hi": round(float(c_hi), 4)},
}
print(json.dumps(result))
