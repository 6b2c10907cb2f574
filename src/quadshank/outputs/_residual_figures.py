"""Figures of the residual diagnostics (:mod:`quadshank.evaluation._residuals`).

Each ``plot_*`` function draws on a fresh :class:`matplotlib.figure.Figure` (no pyplot
state), writes the notes in words below the panels, saves a PNG atomically and returns
its path.
"""

from __future__ import annotations

import math
import textwrap

import numpy as np
from matplotlib.figure import Figure

from ..common._io import save_figure
from ..evaluation._residuals import FEATURE_LABELS, FEATURE_WORDS, format_p

__all__ = [
    "plot_trends", "plot_correlations", "plot_twitch_average", "plot_spectrum", "plot_loo_pit", "plot_elpd_in_time",
    "plot_structure",
]  # fmt: skip


def _note_lines(notes, width_in: float) -> list[str]:
    return [ln for note in (notes or []) for ln in textwrap.wrap("• " + note, int(width_in * 13))]


def _figure(n_rows: int, n_cols: int, panel_w: float, panel_h: float, notes):
    """A figure with room for the panels and, below them, the notes wrapped to its width."""
    lines = _note_lines(notes, n_cols * panel_w)
    notes_h = 0.2 * len(lines) + (0.3 if lines else 0.0)
    fig = Figure(figsize=(n_cols * panel_w, n_rows * panel_h + notes_h))
    return fig, fig.subplots(n_rows, n_cols, squeeze=False)


def _save(fig, path, notes):
    """Lay the panels out above the notes, write the notes, save a PNG and return ``path``."""
    width, height = fig.get_size_inches()
    lines = _note_lines(notes, width)
    notes_h = 0.2 * len(lines) + (0.3 if lines else 0.0)
    fig.tight_layout(rect=(0.0, notes_h / height, 1.0, 1.0))
    if lines:
        fig.text(0.02, (notes_h - 0.1) / height, "\n".join(lines), va="top", ha="left", fontsize=9)
    return save_figure(fig, path, dpi=110, tight=False)


def plot_trends(trends: dict[str, dict], path, notes: list[str] | None = None):
    """One panel per feature: binned mean residual ± 2 se against the feature, titled with the p-value."""
    n_cols = min(3, len(trends))
    n_rows = math.ceil(len(trends) / n_cols)
    fig, axes = _figure(n_rows, n_cols, 4.2, 3.2, notes)
    for ax, (key, t) in zip(axes.flat, trends.items()):
        ax.axhline(0.0, color="k", lw=0.8)
        ax.errorbar(t["centre"], t["mean"], yerr=2 * t["se"], fmt="o-", ms=4, capsize=3)
        ax.set_xlabel(FEATURE_LABELS.get(key, key))
        ax.set_ylabel("mean residual ± 2 se [deg/s²]")
        ax.set_title(f"{FEATURE_WORDS.get(key, (key,))[0]}: {format_p(t['p_value'])}", fontsize=10)
    for ax in axes.flat[len(trends) :]:
        ax.set_visible(False)
    return _save(fig, path, notes)


def _stems(ax, result, title):
    ax.axhspan(-result["band"], result["band"], color="tab:blue", alpha=0.2, lw=0)
    ax.stem(result["lags"], result["value"], basefmt=" ")
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_xlabel("lag [samples]")
    ax.set_title(title, fontsize=10)


def plot_correlations(acf_result: dict, ccf_result: dict, path, notes: list[str] | None = None):
    """Autocorrelation of the residual and its cross-correlation with the stimulation, with 95 % bands
    (``ccf_result`` ``None``: no pulses, the panel says so)."""
    fig, axes = _figure(1, 2, 5.5, 3.6, notes)
    band = f"shaded: ±1.96/√N, N = {acf_result['n']}, 95 % of a white residual's lags"
    _stems(axes[0, 0], acf_result, f"residual autocorrelation\n({band})")
    axes[0, 0].set_ylabel("autocorrelation")
    if ccf_result is None:  # a pendulum test
        axes[0, 1].text(0.5, 0.5, "no pulses in these trials:\nno stimulation to correlate with", ha="center",
                        va="center", transform=axes[0, 1].transAxes)
        axes[0, 1].set_axis_off()
    else:
        _stems(axes[0, 1], ccf_result, f"stimulation(k) vs residual(k + lag)\n({band})")
        axes[0, 1].set_ylabel("cross-correlation")
    return _save(fig, path, notes)


def plot_twitch_average(tta: dict, path, dt: float = 0.01, notes: list[str] | None = None):
    """Twitch-triggered average residual ± 2 se per group against time after the pulse [ms]."""
    fig, axes = _figure(1, 1, 7.0, 4.0, notes)
    ax = axes[0, 0]
    t_ms = tta["lags"] * dt * 1000.0
    ax.axhline(0.0, color="k", lw=0.8)
    for label, g in tta["groups"].items():
        (line,) = ax.plot(t_ms, g["mean"], label=f"{label} ({g['count']} pulses)")
        ax.fill_between(t_ms, g["mean"] - 2 * g["se"], g["mean"] + 2 * g["se"], color=line.get_color(), alpha=0.25)
    ax.set_xlabel("time after pulse [ms]")
    ax.set_ylabel("mean residual ± 2 se [deg/s²]")
    ax.set_title("twitch-triggered average residual", fontsize=10)
    ax.legend(fontsize=8)
    return _save(fig, path, notes)


def plot_spectrum(spec: dict, path, notes: list[str] | None = None):
    """Welch PSD of the residual on a log scale, the peak above 1 Hz marked."""
    fig, axes = _figure(1, 1, 7.0, 4.0, notes)
    ax = axes[0, 0]
    ax.semilogy(spec["freq_hz"], spec["psd"])
    if np.isfinite(spec["peak_hz"]):
        ax.axvline(spec["peak_hz"], color="tab:red", ls="--", lw=1, label=f"peak above 1 Hz: {spec['peak_hz']:.2f} Hz")
        ax.legend(fontsize=8)
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("PSD [(deg/s²)²/Hz]")
    ax.set_title("power spectral density of the residual (Welch)", fontsize=10)
    return _save(fig, path, notes)


def plot_loo_pit(pits: dict, path, notes: list[str] | None = None):
    """LOO-PIT per leg as the ECDF's difference from uniform, with the 95 % band (``pits[leg] =
    (values, summary)``, the summary from :func:`loo_pit_summary`)."""
    fig, axes = _figure(1, 1, 7.0, 4.0, notes)
    ax = axes[0, 0]
    u = np.linspace(0.0, 1.0, 201)
    for leg, (values, summ) in pits.items():
        v = np.sort(np.asarray(values, float)[np.isfinite(values)])
        (line,) = ax.plot(u, np.searchsorted(v, u, side="right") / v.size - u, label=f"{leg} (distance {summ['distance']:.3f})")
        ax.axhline(summ["band"], color=line.get_color(), ls=":", lw=1)
        ax.axhline(-summ["band"], color=line.get_color(), ls=":", lw=1)
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_xlabel("PIT value")
    ax.set_ylabel("ECDF − uniform")
    ax.set_title("LOO-PIT of the equivalent acceleration (dotted: 95 % band over 1-s segments)", fontsize=10)
    ax.legend(fontsize=8)
    return _save(fig, path, notes)


def plot_elpd_in_time(segments: dict, path, notes: list[str] | None = None, n_worst: int = 3):
    """Pointwise ELPD per 1-s segment against time, a panel per leg, trials side by side, the
    ``n_worst`` segments marked (``segments[leg]`` = list of {trial, start_s, elpd})."""
    fig, axes = _figure(len(segments), 1, 9.0, 2.6, notes)
    for ax, (leg, rows) in zip(axes[:, 0], segments.items()):
        offsets, end = {}, 0.0  # trial -> where its time axis starts
        for trial in sorted({r["trial"] for r in rows}):
            these = [r for r in rows if r["trial"] == trial]
            offsets[trial] = end
            t = np.array([r["start_s"] for r in these]) + end
            ax.plot(t, [r["elpd"] for r in these], lw=0.9, color="tab:blue")
            ax.axvline(end, color="0.7", lw=0.8)
            ax.text(end, 1.0, f" trial {trial}", transform=ax.get_xaxis_transform(), va="top", fontsize=8)
            end = t[-1] + 5.0
        for r in sorted(rows, key=lambda r: r["elpd"])[:n_worst]:
            ax.plot(r["start_s"] + offsets[r["trial"]], r["elpd"], "o", color="tab:red", ms=5)
        ax.set_ylabel("ELPD per second")
        ax.set_title(f"{leg}: pointwise PSIS-LOO ELPD in time (red: the {n_worst} worst seconds)", fontsize=10)
    axes[-1, 0].set_xlabel("time in trial [s] (trials side by side)")
    return _save(fig, path, notes)


def plot_structure(structure: dict, path, notes: list[str] | None = None):
    """One panel per named feature: the binned mean residual ± 2 se against it, legs pooled,
    quiet samples and samples during twitches side by side; None when nothing was named."""
    found = structure["found"]
    if not found:
        return None
    fig, axes = _figure(1, len(found), max(4.6, 8.0 / len(found)), 3.4, notes)
    for ax, f in zip(axes[0], found):
        ax.axhline(0.0, color="k", lw=0.8)
        for side, colour in (("quiet", "0.4"), ("during twitches", "tab:blue")):
            t = f["pooled"].get(side)
            if t is None:
                continue
            ax.errorbar(t["centre"], t["mean"], yerr=2 * np.asarray(t["se"]), fmt="o-", ms=4, capsize=3,
                        color=colour, label=side)
        ax.set_xlabel(FEATURE_LABELS.get(f["feature"], f["feature"]))
        ax.set_ylabel("mean residual ± 2 se [deg/s²]")
        ax.set_title(f"{FEATURE_WORDS[f['feature']][0]}: {100 * f['share']:.1f} % of variance, {f['side']}",
                     fontsize=10)
        ax.legend(fontsize=8)
    return _save(fig, path, notes)
