"""Figures like the paper's.  Each function takes data, returns a Figure, never shows it."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from ..common._arrays import stretches
from ..data._paper import HORIZONS_MS, TABLE_V

__all__ = [
    "plot_signals", "plot_twitch_dependence", "plot_predictions", "plot_j_vs_horizon", "plot_delay_scan",
    "plot_delay_angle", "plot_plan_predictions", "plot_recording",
]  # fmt: skip

_MODEL_COLOURS = {"model1": "tab:blue", "model2": "tab:orange", "model3": "tab:green"}


def _window(trial, start_s: float, length_s: float):
    """The samples of a figure's window from ``start_s`` [s], ``length_s`` long; on a trial too short
    for it the start moves earlier (as :func:`quadshank.evaluation.figure_window` moves it)."""
    dt = trial.sampling_period_s
    start_s = min(start_s, max(0.0, trial.n_samples * dt - length_s))
    i0 = int(round(start_s / dt))
    i1 = min(trial.n_samples, i0 + int(round(length_s / dt)))
    return slice(i0, i1)


def _pulses(ax, t, u, y):
    k = u > 0
    ax.vlines(t[k], 0, y * u[k], color="k", lw=0.8, label="stimulation (scaled by u)")


def _shade_excluded(ax, trial, sl: slice) -> None:
    """Grey bands over the trial's excluded samples (``Trial.exclude``) within ``sl``."""
    t, dt = trial.time_s[sl], trial.sampling_period_s
    for n, (a, b) in enumerate(stretches(trial.exclude[sl])):
        ax.axvspan(t[a] - dt / 2, t[b - 1] + dt / 2, color="0.85", zorder=0, lw=0,
                   label="excluded (not compared)" if n == 0 else None)


def plot_signals(trial, equivalent_acc, *, start_s: float = 20.0, length_s: float = 8.0):
    """Fig. 2: angle, velocity, acceleration and equivalent acceleration M/I with pulses."""
    sl = _window(trial, start_s, length_s)
    t = trial.time_s[sl]
    u = trial.stimulation[sl]
    fig, axes = plt.subplots(4, 1, figsize=(9, 8), sharex=True)
    axes[0].plot(t, trial.angle_deg[sl])
    _shade_excluded(axes[0], trial, sl)
    axes[0].set_ylabel("angle [deg]")
    axes[1].plot(t, trial.velocity_deg_s[sl])
    axes[1].set_ylabel("velocity [deg/s]")
    acc = trial.acceleration_deg_s2[sl]
    axes[2].plot(t, acc)
    _pulses(axes[2], t, u, 0.8 * np.max(np.abs(acc)))
    axes[2].set_ylabel("acceleration [deg/s²]")
    mi = np.asarray(equivalent_acc)[sl]
    axes[3].plot(t, mi)
    _pulses(axes[3], t, u, 0.8 * np.max(np.abs(mi)))
    axes[3].set_ylabel("M/I [deg/s²]")
    axes[3].set_xlabel("time [s]")
    velocity_note = "measured" if trial.velocity_measured else "derived from the angle"
    axes[0].set_title(f"{trial.key}, trial {trial.trial}: measured signals (velocity {velocity_note})")
    fig.tight_layout()
    return fig


def plot_twitch_dependence(ident):
    """Figs. 3 and 4: integrated twitch responses against angle and velocity, raw and compensated."""
    p = ident.models["model3"].flat_params()
    ga, gv = p["gamma_angle"], p["gamma_velocity"]
    phi, dphi, T = ident.angle_at_d, ident.velocity_at_d, ident.integrated
    fig, axes = plt.subplots(2, 2, figsize=(9, 7))
    panels = [
        (axes[0, 0], phi, T, "φ at d [deg]", "ΣM/I [deg/s²]", "raw (model 1)"),
        (axes[0, 1], dphi, T, "φ̇ at d [deg/s]", "ΣM/I [deg/s²]", "raw (model 1)"),
        (axes[1, 0], phi, T / (1 + gv * dphi), "φ at d [deg]", "ΣM/I / (1 + γ_v φ̇)", "velocity compensated"),
        (axes[1, 1], dphi, T / (1 + ga * phi), "φ̇ at d [deg/s]", "ΣM/I / (1 + γ_a φ)", "angle compensated"),
    ]
    for ax, x, y, xl, yl, title in panels:
        ax.plot(x, y, ".", ms=3, alpha=0.6)
        ok = np.isfinite(x) & np.isfinite(y)
        if np.count_nonzero(ok) > 1 and np.ptp(x[ok]) > 0:  # no line through points at one abscissa
            x, y = x[ok], y[ok]
            c = np.polyfit(x, y, 1)
            xs = np.linspace(np.min(x), np.max(x), 10)
            ax.plot(xs, np.polyval(c, xs), "r-", lw=1.5, label=f"slope {c[0]:.3g}")
            ax.legend(fontsize=8)
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_title(title, fontsize=9)
    fig.suptitle(f"{ident.leg}, trial {ident.trial}: integrated twitch responses ({len(T)} isolated twitches)")
    fig.tight_layout()
    return fig


def plot_predictions(trial, predicted: dict, p: int, *, start_s: float = 30.0, length_s: float = 20.0):
    """Figs. 5 and 6: measured angle and the angle predicted ``p`` samples ahead, per model.

    ``predicted[model] = (starts, pred)`` as returned by :func:`quadshank.predictions`.
    """
    sl = _window(trial, start_s, length_s)
    names = sorted(predicted)
    fig, axes = plt.subplots(len(names), 1, figsize=(9, 2.6 * len(names)), sharex=True, squeeze=False)
    for ax, name in zip(axes[:, 0], names):
        starts, pred = predicted[name]
        target = starts + p
        keep = (target >= sl.start) & (target < sl.stop)
        ax.plot(trial.time_s[sl], trial.angle_deg[sl], "k-", lw=1.2, label="measured")
        _shade_excluded(ax, trial, sl)
        shown = np.full(len(trial.time_s[sl]), np.nan)  # NaN where no prediction is scored: a gap, not a bridge
        shown[target[keep] - sl.start] = pred[keep, p - 1]
        ax.plot(trial.time_s[sl], shown, "--", color=_MODEL_COLOURS.get(name), lw=1.2,
                label=f"{name}, {p * trial.sampling_period_s * 1000:.0f} ms ahead")
        err = trial.angle_deg[target] - pred[:, p - 1]
        ax.set_title(f"{name}: J = {np.sqrt(np.mean(err ** 2)):.2f}° over the trial", fontsize=9)
        ax.set_ylabel("angle [deg]")
        ax.legend(fontsize=8, loc="upper right")
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(f"{trial.key}, trial {trial.trial}: prediction {p * trial.sampling_period_s * 1000:.0f} ms ahead")
    fig.tight_layout()
    return fig


def plot_j_vs_horizon(table: dict):
    """Table V as a figure: mean J ± s.d. over legs against horizon, with the paper's values."""
    trials = sorted(table)
    fig, axes = plt.subplots(1, len(trials), figsize=(4.2 * len(trials), 3.8), sharey=True, squeeze=False)
    for ax, trial in zip(axes[0], trials):
        for model in sorted(table[trial]):
            hs = sorted(table[trial][model])
            mean = np.array([table[trial][model][h][0] for h in hs])
            sd = np.nan_to_num(np.array([table[trial][model][h][1] for h in hs]))
            colour = _MODEL_COLOURS.get(model)
            ax.errorbar(hs, mean, yerr=sd, marker="o", capsize=3, color=colour, label=f"{model} (here)")
            paper = TABLE_V.get(trial, {}).get(model)
            if paper:
                ax.plot(list(paper), [v[0] for v in paper.values()], ":", marker="x", color=colour,
                        label=f"{model} (paper)")
        horizon_axis(ax, minor=True)
        ax.set_title(f"trial {trial}")
    axes[0, 0].set_ylabel("J_φ,p [deg]")
    axes[0, -1].legend(fontsize=7)
    fig.tight_layout()
    return fig


def plot_delay_scan(ident: dict):
    """Model-2 residual against the delay d, per leg; the chosen d is marked."""
    fig, ax = plt.subplots(figsize=(6, 3.8))
    for leg, r in ident.items():
        res = np.asarray(r.delay_residuals)
        line, = ax.plot(np.arange(res.size), res, marker=".", label=leg)
        ax.plot([r.delay], [res[r.delay]], "o", mfc="none", ms=10, color=line.get_color())
    ax.set_yscale("log")
    dt = next(iter(ident.values())).models["model1"].sampling_period_s if ident else 0.01
    ax.set_xlabel(f"delay d [samples of {dt * 1000:g} ms]")
    ax.set_ylabel("model-2 residual mean square [(deg/s²)²]")
    ax.set_title("Delay scan (circle: chosen d, the smallest residual)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def horizon_axis(ax, minor: bool = False):
    """A log axis of prediction horizons [ms], ticked at the paper's."""
    ax.set_xscale("log")
    ax.set_xticks(list(HORIZONS_MS))
    ax.set_xticklabels([str(h) for h in HORIZONS_MS])
    if not minor:
        ax.minorticks_off()
    ax.set_xlabel("prediction horizon [ms]")


def plot_posterior_j_vs_horizon(J: dict):
    """Posterior Table V: median J of the mean over legs with its 90 % band, per model and trial.

    ``J[model][trial][horizon_ms] = {"median", "lo", "hi"}`` (horizon keys str or int);
    the paper's mean ± s.d. is drawn beside for the models it reports.
    """
    trials = sorted({t for by_trial in J.values() for t in by_trial}, key=int)
    fig, axes = plt.subplots(1, len(trials), figsize=(4.2 * len(trials), 3.8), sharey=True, squeeze=False)
    for ax, trial in zip(axes[0], trials):
        for model in sorted(J):
            if trial not in J[model]:
                continue
            hv = sorted(J[model][trial].items(), key=lambda kv: int(kv[0]))
            hs = [int(h) for h, _ in hv]
            line, = ax.plot(hs, [v["median"] for _, v in hv], marker="o", color=_MODEL_COLOURS.get(model),
                            label=f"{model} (posterior median, 90 %)")
            ax.fill_between(hs, [v["lo"] for _, v in hv], [v["hi"] for _, v in hv], color=line.get_color(),
                            alpha=0.25)
            paper = TABLE_V.get(trial, {}).get(model)
            if paper:
                ax.errorbar([h * 1.04 for h in paper], [v[0] for v in paper.values()],
                            yerr=[v[1] for v in paper.values()], fmt=":x", capsize=3, color=line.get_color(),
                            label=f"{model} (paper, mean ± s.d.)")
        horizon_axis(ax)
        ax.set_title(f"trial {trial}")
    axes[0, 0].set_ylabel("J_φ,p, mean over legs [deg]")
    axes[0, -1].legend(fontsize=7)
    fig.tight_layout()
    return fig


def plot_posterior_predictions(trial, predicted: dict, p: int, *, j: dict | None = None,
                               start_s: float = 30.0, length_s: float = 20.0):
    """Figs. 5 and 6 from a posterior: measured angle, median prediction ``p`` samples ahead and 90 % band.

    ``predicted[model] = (starts, pred)`` with ``pred`` of shape (draws, starts): the
    angle predicted p samples after each start, per draw.  ``j[model]``, when
    given, is the trial's J {"median", "lo", "hi"} at this horizon, for the titles.
    """
    sl = _window(trial, start_s, length_s)
    names = sorted(predicted)
    fig, axes = plt.subplots(len(names), 1, figsize=(9, 2.6 * len(names)), sharex=True, squeeze=False)
    ms = p * trial.sampling_period_s * 1000
    for ax, name in zip(axes[:, 0], names):
        starts, pred = predicted[name]
        target = np.asarray(starts) + p
        keep = (target >= sl.start) & (target < sl.stop)
        t = trial.time_s[target[keep]]
        lo, med, hi = np.quantile(np.asarray(pred)[:, keep], (0.05, 0.5, 0.95), axis=0)
        ax.plot(trial.time_s[sl], trial.angle_deg[sl], "k-", lw=1.2, label="measured")
        _shade_excluded(ax, trial, sl)
        line, = ax.plot(t, med, "--", color=_MODEL_COLOURS.get(name), lw=1.2,
                        label=f"{name}, {ms:.0f} ms ahead (median)")
        ax.fill_between(t, lo, hi, color=line.get_color(), alpha=0.3, lw=0, label="90 % band over draws")
        band = (j or {}).get(name)
        title = name
        if band:
            title += f": J = {band['median']:.2f}° [{band['lo']:.2f}, {band['hi']:.2f}] over the trial"
        ax.set_title(title, fontsize=9)
        ax.set_ylabel("angle [deg]")
        ax.legend(fontsize=8, loc="upper right")
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle(f"{trial.key}, trial {trial.trial}: posterior prediction {ms:.0f} ms ahead")
    fig.tight_layout()
    return fig


def plot_delay_angle(legs: dict, label: str = "", population: dict | None = None):
    """The delay–angle curve d − shift·w(φ) per leg with its 90 % band, and the population's.

    ``legs``: a fit's per-leg summaries (:attr:`quadshank.inference.FitResult.legs`), those of
    an ``angle_delay`` fit holding ``delay_angle``; ``population``: the pooled curve
    (``delay_angle_population``).  The pulses' angle range of each leg is marked: outside it
    the data say nothing about the threshold.  The paper's −20° is drawn dotted.
    """
    legs = {leg: s["delay_angle"] for leg, s in legs.items() if "delay_angle" in s}
    pop = population
    n = len(legs) + (pop is not None)
    cols = min(3, n)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.0 * cols, 3.0 * rows), sharex=True, sharey=True, squeeze=False)
    panels = [(leg, da) for leg, da in legs.items()] + ([("population (legs pooled)", pop)] if pop else [])
    for ax, (name, da) in zip(axes.flat, panels):
        phi = np.asarray(da["angle_deg"])
        ax.fill_between(phi, da["lo"], da["hi"], step="mid", color="tab:purple", alpha=0.25, label="90 % band")
        ax.step(phi, da["median"], where="mid", color="tab:purple", label="posterior median")
        if "pulse_angle_range_deg" in da:
            lo, hi = da["pulse_angle_range_deg"]
            ax.axvspan(phi[0], lo, color="0.9", zorder=0)
            ax.axvspan(hi, phi[-1], color="0.9", zorder=0, label="no pulses")
            ax.set_title(f"{name}: P(change) {da['change_probability']:.2f}", fontsize=9)
        else:
            ax.set_title(name, fontsize=9)
        ax.axvline(-20.0, color="k", ls=":", lw=1, label="paper: about −20°")
        ax.set_xlabel("knee angle at the pulse [deg]")
    for ax in axes[:, 0]:
        ax.set_ylabel("delay [samples]")
    for ax in list(axes.flat)[len(panels):]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=7)
    fig.suptitle(f"Delay against knee angle{': ' + label if label else ''}", fontsize=10)
    fig.tight_layout()
    return fig


#: The plan figure shows angles within ± this [deg]: beyond, a diverging draw would flatten the rest.
PLAN_FIGURE_REACH_DEG = 200.0


def _plan_panels(ax_angle, ax_stim, time_s, stimulation, bands: dict, sl: slice, ylabel, fitted_range) -> None:
    """The medians and bands of ``bands`` and the plan's pulses within ``sl`` on two axes, the
    angles cut at ±:data:`PLAN_FIGURE_REACH_DEG` where they go beyond (said on the axes)."""
    t = np.asarray(time_s)[sl]
    shown = []
    for leg, b in bands.items():
        line, = ax_angle.plot(t, np.asarray(b["median"])[sl], lw=1.2, label=f"{leg} (median)")
        ax_angle.fill_between(t, np.asarray(b["lo"])[sl], np.asarray(b["hi"])[sl], color=line.get_color(), alpha=0.25,
                              lw=0)
        shown += [np.asarray(b[k], float)[sl] for k in ("lo", "hi", "median")]
        if fitted_range and leg in fitted_range:
            for y in fitted_range[leg]:
                ax_angle.axhline(y, color=line.get_color(), ls=":", lw=0.8)
    values = np.concatenate(shown) if shown else np.zeros(1)
    values = values[np.isfinite(values)]
    if values.size and np.abs(values).max() > PLAN_FIGURE_REACH_DEG:
        low = max(float(values.min()), -PLAN_FIGURE_REACH_DEG)
        high = min(float(values.max()), PLAN_FIGURE_REACH_DEG)
        pad = 0.05 * (high - low) + 1.0
        ax_angle.set_ylim(low - pad, high + pad)
        ax_angle.text(0.01, 0.02, f"angles beyond ±{PLAN_FIGURE_REACH_DEG:g}° cut off (the shank over the top: "
                      "no knee goes there)", transform=ax_angle.transAxes, fontsize=8, color="tab:red")
    ax_angle.set_ylabel("knee angle [deg]")
    u = np.asarray(stimulation)
    k = u[sl] > 0
    ax_stim.vlines(t[k], 0, u[sl][k], color="k", lw=0.8)
    ax_stim.set_ylim(0, 1.05 * (1.0 if ylabel is None else max(float(u.max(initial=0.0)), 1e-12)))
    ax_stim.set_ylabel("u" if ylabel is None else ylabel)
    ax_stim.set_xlabel("time [s]")


def plot_plan_predictions(time_s, stimulation, bands: dict, label: str = "", ylabel: str | None = None,
                          fitted_range: dict | None = None):
    """A planned stimulation sequence and, per leg, the angle it would produce: the posterior
    median with its 90 % band (``bands``: leg -> {"median", "lo", "hi"} arrays over samples; NaN
    where no draw stayed finite).  ``ylabel``: None for recruitment levels u, else what the
    stimulator's values are (pulse width [µs], …).  ``fitted_range``: leg -> (lowest, highest)
    angle the fit saw, drawn as dotted lines in the leg's colour.  Angles beyond
    ±:data:`PLAN_FIGURE_REACH_DEG` are cut off, and the figure says so.  A plan longer than
    :data:`RECORDING_ZOOM_AFTER_S` gets a second view below of :data:`RECORDING_ZOOM_S` seconds
    from its first pulse, as a recording's figure does."""
    time_s = np.asarray(time_s)
    period = float(np.median(np.diff(time_s))) if time_s.size > 1 else 1.0
    def draw(ax_angle, ax_stim, sl):
        _plan_panels(ax_angle, ax_stim, time_s, stimulation, bands, sl, ylabel, fitted_range)

    fig, axes = _whole_and_first_pulses(time_s, stimulation, period, (9, 6, 10), draw)
    axes[0].fill_between([], [], [], color="0.6", alpha=0.4, lw=0, label="90 % band")
    if fitted_range:
        axes[0].plot([], [], color="0.4", ls=":", lw=0.8, label="angles the fit saw (each leg's colour)")
    axes[0].set_title(f"Predicted response to the plan{' (' + label + ')' if label else ''}: median and 90 % band")
    axes[0].legend(fontsize=8, loc="best")
    fig.tight_layout()
    return fig


#: A trial longer than this [s] gets a second view of :data:`RECORDING_ZOOM_S` in its figure
#: (:func:`plot_recording`): at minutes per panel the pulses merge into a band.
RECORDING_ZOOM_AFTER_S = 60.0
#: The length [s] of that second view, from the first pulse (or the first sample without any).
RECORDING_ZOOM_S = 20.0


def _whole_and_first_pulses(time_s, stimulation, period: float, size: tuple[float, float, float], draw):
    """A figure of a whole recording or plan, an angle over its pulses (``draw(ax_angle, ax_stim,
    sl)`` draws one view of the samples ``sl``), and, where it lasts longer than
    :data:`RECORDING_ZOOM_AFTER_S`, a second view below of :data:`RECORDING_ZOOM_S` seconds from
    its first pulse, that span shaded in the whole view.  ``size``: the width and the height
    without and with the second view.  Returns the figure and its axes (the whole view first)."""
    time_s = np.asarray(time_s)
    n = time_s.size
    zoom = n * period > RECORDING_ZOOM_AFTER_S
    rows = 4 if zoom else 2
    fig, axes = plt.subplots(rows, 1, figsize=(size[0], size[2] if zoom else size[1]),
                             gridspec_kw={"height_ratios": [3, 1] * (rows // 2)})
    axes[1].sharex(axes[0])
    draw(axes[0], axes[1], slice(0, n))
    if zoom:
        width = int(round(RECORDING_ZOOM_S / period))
        pulses = np.flatnonzero(np.asarray(stimulation) > 0)
        a = int(pulses[0]) if pulses.size else 0
        b = min(n, a + width)
        a = max(0, min(a, b - width))
        axes[3].sharex(axes[2])
        draw(axes[2], axes[3], slice(a, b))
        axes[0].axvspan(time_s[a], time_s[b - 1], color="tab:orange", alpha=0.15, lw=0, zorder=0)
        axes[2].set_title(f"{time_s[a]:.1f}-{time_s[b - 1]:.1f} s (shaded above)", fontsize=9)
    return fig, axes


def _recording_panels(ax_angle, ax_stim, trial, sl: slice, isolated) -> None:
    """The angle (excluded stretches shaded) and the pulses (isolated twitches in red) of
    ``trial`` within ``sl`` on two axes."""
    t = trial.time_s[sl]
    ax_angle.plot(t, trial.angle_deg[sl], lw=0.7, color="tab:blue")
    _shade_excluded(ax_angle, trial, sl)
    ax_angle.set_ylabel("knee angle [deg]")
    u = trial.stimulation[sl]
    k = u > 0
    ax_stim.vlines(t[k], 0, u[k], color="k", lw=0.6, label="pulse")
    if isolated is not None and len(isolated):
        i = np.asarray(isolated, int)
        i = i[(i >= sl.start) & (i < sl.stop)]
        ax_stim.vlines(trial.time_s[i], 0, trial.stimulation[i], color="tab:red", lw=0.9, label="isolated twitch")
    if k.any():
        ax_stim.legend(fontsize=7, loc="upper right", ncol=2)
    if trial.exclude[sl].any():
        ax_angle.legend(fontsize=8, loc="upper right")
    ax_stim.set_ylim(0, 1.3)
    ax_stim.set_ylabel("stimulation u")
    ax_stim.set_xlabel("time [s]")


def plot_recording(trial, isolated=None, summary: str = ""):
    """A whole trial as read: the angle (the excluded stretches shaded) over the stimulation's
    pulses at their levels, the isolated twitches the classical identification uses (``isolated``:
    their sample indices) in red; ``summary`` and the signals the reader derived in the title.
    A trial longer than :data:`RECORDING_ZOOM_AFTER_S` gets a second view below of its first
    :data:`RECORDING_ZOOM_S` seconds from the first pulse, where single twitches can be seen
    (its span shaded in the whole view)."""
    def draw(ax_angle, ax_stim, sl):
        _recording_panels(ax_angle, ax_stim, trial, sl, isolated)

    fig, axes = _whole_and_first_pulses(trial.time_s, trial.stimulation, trial.sampling_period_s, (10, 5, 9), draw)
    derived = [name for name, measured in (("velocity", trial.velocity_measured),
                                           ("acceleration", trial.acceleration_measured)) if not measured]
    note = "; ".join(x for x in (summary, f"{' and '.join(derived)} derived from the angle" if derived else "") if x)
    axes[0].set_title(f"{trial.key}, trial {trial.trial}" + (f": {note}" if note else ""), fontsize=10)
    fig.tight_layout()
    return fig
