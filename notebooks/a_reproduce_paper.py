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
# # (a) Reproducing Franken et al. (1995) on the simulated cohort
#
# The paper identified three discrete-time models of the FES-driven
# quadriceps–shank system on five legs, then scored them by how well they
# predict the knee angle 100 ms to 1 s ahead (J_φ,p, eq. 12; Table V). No
# measured data from the paper is public, so quadshank ships a simulator of its
# cohort (subjects TN, JM and OT). This notebook runs the paper's section 7 on
# that cohort and compares the outcome with the paper:
#
# 1. simulate the cohort (three trials per leg: u = 1, 1 and 0.5);
# 2. identify the passive system and models 1–3 from trial 1, as in section III-D;
# 3. evaluate J_φ,p on every trial, with the paper's sign test (Table V);
# 4. check the identified parameters against the simulator's truth.
#
# The command line does the same in one step: `quadshank reproduce --out DIR`.

# %%
import json
import os
import warnings
from pathlib import Path

from tqdm import TqdmWarning

warnings.filterwarnings("ignore", category=TqdmWarning)  # no ipywidgets: plain progress bars are off anyway

import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

import quadshank
from quadshank import __version__, evaluate_cohort, identify_cohort, predictions, sign_tests, simulate_cohort, table_v
from quadshank.data import TABLE_V
from quadshank.evaluation import TOLERANCES, recovery
from quadshank.outputs import (
    plot_delay_scan,
    plot_j_vs_horizon,
    plot_predictions,
    plot_signals,
    plot_twitch_dependence,
    table_i,
    table_ii,
    table_iii,
    table_passive,
)

# %matplotlib inline
plt.rcParams["figure.dpi"] = 72
pd.set_option("display.precision", 3)
pd.set_option("display.width", 160)

# %% [markdown]
# ## Settings
#
# The default is the paper's protocol in full: five legs, three trials of
# 5 min each. `QUADSHANK_NOTEBOOK_SMALL=1` (used by the test that executes this
# notebook) runs two legs for half a minute instead; the numbers then say little.

# %%
SMALL = os.environ.get("QUADSHANK_NOTEBOOK_SMALL") == "1"
SEED = 0
if SMALL:
    LEGS, MINUTES = ("TN-left", "JM-left"), 0.5
else:
    LEGS, MINUTES = ("TN-left", "TN-right", "JM-left", "JM-right", "OT-left"), 5.0
WORK = Path("_work") / "a_reproduce_paper"  # nothing is written outside it
WORK.mkdir(parents=True, exist_ok=True)
print(f"quadshank {__version__}: legs {', '.join(LEGS)}; {MINUTES:g} min per trial; seed {SEED}")

# %% [markdown]
# ## 1. The simulated cohort
#
# Each trial drives the simulator with the paper's randomised interpulse
# intervals. The truth is deliberately richer than the models: a continuous
# twitch shape, delays of 4.3 or 4.7 samples rather than whole samples, a 1-ms
# integration step, and a sensor chain with noise and quantisation. The truth is
# returned beside the data.

# %%
cohort, truth = simulate_cohort(legs=LEGS, minutes=MINUTES, seed=SEED)
pd.DataFrame(
    [
        {
            "leg": t.key,
            "trial": t.trial,
            "u": truth["legs"][t.key]["trials"][str(t.trial)]["recruitment"],
            "pulses": truth["legs"][t.key]["trials"][str(t.trial)]["n_pulses"],
            "isolated twitches": truth["legs"][t.key]["trials"][str(t.trial)]["n_isolated"],
            "RMS angle [deg]": truth["legs"][t.key]["trials"][str(t.trial)]["rms_angle_deg"],
        }
        for t in cohort
    ]
)

# %% [markdown]
# The mean RMS knee angle per trial is what the paper reports for its
# recordings (23.6°, 24.1° and 19.3°):

# %%
{trial: round(v["mean_rms_angle_deg"], 1) for trial, v in truth["summary"].items()}

# %% [markdown]
# ## 2. Classical identification (section III-D)
#
# Trial 1 of each leg is used. The passive system comes from quiet samples
# (eq. 8 with no active moment). The delay d is the one with the smallest
# model-2 residual, and models 1 and 3 come from isolated twitches (eqs. 9 and
# 11). The figure below is the analogue of the paper's Fig. 2: the measured
# signals and the equivalent acceleration M/I, with the pulses.

# %%
ident = identify_cohort(cohort, trial=1)
leg0 = LEGS[1] if len(LEGS) > 1 else LEGS[0]
trial0 = cohort.get(leg0, 1)
mi = quadshank.equivalent_acceleration(
    ident[leg0].models["model1"], trial0.angle_deg, trial0.velocity_deg_s, trial0.acceleration_deg_s2
)
fig = plot_signals(trial0, np.asarray(mi), start_s=min(20.0, MINUTES * 60 - 10), length_s=8.0)

# %% [markdown]
# The delay scan: the model-2 residual against d for each leg. The chosen d
# (circled) is the one every model then uses.

# %%
fig = plot_delay_scan(ident)

# %% [markdown]
# Tables I–III, with the simulator's true values and the paper's beside. The
# "true" model-2 coefficients are the DARMA fit to the simulator's noise-free
# twitch, since the simulated twitch is continuous and has no DARMA form of its
# own.

# %%
pd.DataFrame(table_i(ident, truth)).set_index("leg")

# %%
pd.DataFrame(table_ii(ident, truth)).set_index("leg")

# %%
pd.DataFrame(table_iii(ident, truth)).set_index("leg")

# %%
pd.DataFrame(table_passive(ident, truth)).set_index("leg")

# %% [markdown]
# Figs. 3 and 4 of the paper: the integrated twitch response against knee
# angle and velocity. Below, the same after compensation by model 3's
# factors. A slope that stays after compensation would be a dependence that
# model 3 misses.

# %%
fig = plot_twitch_dependence(ident[LEGS[0]])

# %% [markdown]
# ## 3. Evaluation: J_φ,p and Table V
#
# Each model predicts the knee angle p samples ahead from every start. The
# passive state at each start is the measured one, and the active part is
# carried over from the run that began one sample earlier. J_φ,p is the RMS
# error at p = 10, 25, 50 and 100 samples (100 ms to 1 s), on every trial,
# trial 1 included.

# %%
models = {leg: r.models for leg, r in ident.items()}
J = evaluate_cohort(cohort, models)
T = table_v(J)


def table_v_frame(T):
    """Mean (s.d.) over legs here, and the paper's Table V beside, per trial, model and horizon."""
    rows = []
    for trial in sorted(T):
        for model in sorted(T[trial]):
            row = {"trial": trial, "model": model}
            for h, (mean, sd, n) in sorted(T[trial][model].items()):
                paper = TABLE_V.get(trial, {}).get(model, {}).get(int(h))
                row[f"{h} ms here"] = f"{mean:.1f} ({sd:.1f})"
                row[f"{h} ms paper"] = f"{paper[0]} ({paper[1]})" if paper else "–"
            rows.append(row)
    return pd.DataFrame(rows).set_index(["trial", "model"])


table_v_frame(T)

# %% [markdown]
# The same as a figure. Solid lines are this cohort (mean ± s.d. over legs)
# and dotted lines the paper's Table V:

# %%
fig = plot_j_vs_horizon(T)

# %% [markdown]
# On the full cohort the errors grow with horizon, as in the paper, and model
# 3 is best at 1 s (8.6° against the paper's 7.5° in trial 2), with
# models 1 and 2 close to the paper's 12–13°. One result differs: model 2 is
# better at 100 ms, because its DARMA twitch matches the simulated twitch
# shape, which models 1 and 3 put into a single sample at the delay (the
# README's *Results* section says more).
#
# The paper's sign test pairs J within leg and trial, over trials 2 and 3, and
# is an exact two-sided binomial test at α = 0.05. With five legs there are 10
# pairs, so a significant result needs at least 9 of 10 the same way.

# %%
tests = sign_tests(J)
pd.DataFrame(
    [
        {
            "horizon [ms]": t["horizon_ms"],
            "pair": f"{t['model_a']} vs {t['model_b']}",
            "pairs": t["n_pairs"],
            "first better": t["a_better"],
            "second better": t["b_better"],
            "p": t["p_value"],
            "significant": t["better"] if t["significant"] else "no",
        }
        for t in tests
    ]
).set_index(["horizon [ms]", "pair"])

# %% [markdown]
# ## Measured against predicted angle (Figs. 5 and 6)
#
# The measured angle and each model's prediction 100 ms and 1 s ahead, on
# trial 2 of one leg. At 100 ms the models agree. At 1 s, models 1 and 2 run
# away in extension, where the truth's twitch fades.

# %%
leg_p = "JM-left" if "JM-left" in LEGS else LEGS[0]
trial_p = cohort.get(leg_p, 2)
window = dict(start_s=min(30.0, max(0.0, MINUTES * 60 - 20)), length_s=min(20.0, MINUTES * 60))
preds = {name: predictions(m, trial_p) for name, m in models[leg_p].items()}
fig = plot_predictions(trial_p, preds, 10, **window)

# %%
fig = plot_predictions(trial_p, preds, 100, **window)

# %% [markdown]
# ## 4. Recovery of the truth
#
# The simulator's parameters are known, so the classical identification can be
# checked against them. Each parameter must fall within a tolerance that the
# paper's method can resolve on 5 min of data (README, *Recovery*). The delay
# must be within one sample of the true fractional delay.

# %%
rec = recovery(ident, truth)
rec_rows = [
    {
        "leg": leg,
        "parameter": name,
        "estimate": v["estimate"],
        "truth": v["truth"],
        "error": v.get("relative_error", v.get("abs_error")),
        "tolerance": v["tolerance"],
        "within": "yes" if v["ok"] else "NO",
    }
    for leg, params in rec.items()
    for name, v in params.items()
]
recovery_ok = all(r["within"] == "yes" for r in rec_rows)
print(f"every parameter within its tolerance: {'yes' if recovery_ok else 'NO'}")
pd.DataFrame(rec_rows).set_index(["leg", "parameter"])

# %% [markdown]
# Relative errors per parameter across legs, against the tolerance (the
# dashed line). The delay is an absolute error in samples.

# %%
names = list(TOLERANCES) + ["delay_samples"]
fig, ax = plt.subplots(figsize=(8, 3.2))
for i, name in enumerate(names):
    errs = [rec[leg][name].get("relative_error", rec[leg][name].get("abs_error")) for leg in rec]
    ax.plot(np.full(len(errs), i), errs, "o", alpha=0.7)
    tol = rec[next(iter(rec))][name]["tolerance"]
    ax.plot([i - 0.3, i + 0.3], [tol, tol], "k--", lw=1)
ax.set_xticks(range(len(names)))
ax.set_xticklabels(names, rotation=20)
ax.set_ylabel("relative error (delay: samples)")
ax.set_title("Classical identification against the simulator's truth (dashed: tolerance)")
fig.tight_layout()

# %% [markdown]
# On the full cohort every parameter is within its tolerance. The delay is
# 4 samples where the truth is 4.3 or 4.7: the paper's method resolves it only
# to T_s = 10 ms. At the small test size (30 s per trial) there are too few
# isolated twitches for the tolerances to mean much.

# %%
result = {
    "notebook": "a_reproduce_paper",
    "small": SMALL,
    "legs": list(LEGS),
    "recovery_ok": recovery_ok,
    "J_trial2_1000ms": {m: round(T["2"][m][1000][0], 2) for m in sorted(T["2"])},
    "paper_J_trial2_1000ms": {m: TABLE_V["2"][m][1000][0] for m in sorted(TABLE_V["2"])},
}
print(json.dumps(result))
