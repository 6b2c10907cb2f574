"""``quadshank identify``: classical identification as the paper did it, written to a folder.

Tables I–IV, figures, ``report.md`` and, last, ``summary.json``; every file atomically.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..common._io import atomic_write_text, save_figure
from ..data._cohort import Cohort
from ..data._interchange import kept_warnings
from ..evaluation._classical_recovery import recovery, recovery_rows
from ..inference._identify import PASSIVE_GRAVITY_REL_SE, Identification, identify_cohort, passive_separated
from ..model._model import equivalent_acceleration
from ..outputs._figures import plot_delay_scan, plot_signals, plot_twitch_dependence
from ..outputs._tables import (
    active_legs,
    markdown_table,
    table_i,
    table_ii,
    table_iii,
    table_iv,
    table_passive,
    write_table,
)


def _pick(preferred: str, available) -> str:
    available = list(available)
    return preferred if preferred in available else available[0]


def run_identify(
    cohort: Cohort, out: str | Path, *, truth: dict | None = None, trial: int = 1, progress: bool = False,
    passive_objective: str = "auto", gravity_offset: bool = False,
) -> Identification:
    """Classical identification of every leg; Tables I–IV, figures, summary.json.
    ``passive_objective``, ``gravity_offset``: see :func:`~quadshank.inference.identify_cohort`."""
    out = Path(out)
    with kept_warnings() as said:  # kept in the report and the summary, and said again
        ident = identify_cohort(cohort, trial=trial, progress=progress, passive_objective=passive_objective,
                                gravity_offset=gravity_offset)
    md = [f"# Classical identification (trial {trial})", ""]
    md.append(write_table(table_passive(ident, truth), out / "tables", "passive", "Passive system (eq. 8)"))
    unseparated = [leg for leg, r in ident.items() if not passive_separated(r.passive, r.passive_se)]
    md.append("±: standard errors of the least squares, widened by the residuals' correlation time." + (
                  f" Not separated: {', '.join(unseparated)}: their data do not tell gravity from the elasticity "
                  f"(G' known to worse than {PASSIVE_GRAVITY_REL_SE:.0%}), so G', k1' and k2 trade against each "
                  "other and are not the legs' values; a pendulum test, the accelerometer or a longer recording "
                  "separates them.\n" if unseparated else "\n"))
    md.append(write_table(table_i(ident, truth), out / "tables", "table1", "Table I: model 1 and delay"))
    md.append(write_table(table_ii(ident, truth), out / "tables", "table2", "Table II: model 2 (DARMA)"))
    md.append(write_table(table_iii(ident, truth), out / "tables", "table3", "Table III: model 3"))
    md.append(write_table(table_iv(ident), out / "tables", "table4", "Table IV: % RMS error of ΣM/I"))
    legs = {leg: r.summary() for leg, r in ident.items()}
    if truth:
        rec = recovery(ident, truth)
        md.append(markdown_table(recovery_rows(rec), "Recovery of the simulator's truth"))
        for leg, s in legs.items():
            if leg in rec:
                s["recovery"] = rec[leg]

    active = active_legs(ident)
    passive_only = [leg for leg in ident if leg not in active]
    if passive_only:
        md.append(f"Passive system only (no pulses in trial {trial}): {', '.join(passive_only)}.\n")
    if active:
        leg2 = _pick("TN-right", active)
        t2 = cohort.get(leg2, trial)
        mi = equivalent_acceleration(active[leg2].models["model1"], t2.angle_deg, t2.velocity_deg_s,
                                     t2.acceleration_deg_s2)
        save_figure(plot_signals(t2, np.asarray(mi)), out / "figures" / "fig2_signals.png")
        save_figure(plot_twitch_dependence(active[_pick("TN-left", active)]), out / "figures" / "fig3_4_twitch_dependence.png")
        save_figure(plot_delay_scan(active), out / "figures" / "delay_scan.png")
    if said:
        md += ["## Warnings", "", *[f"- {text}" for text in said], ""]
    atomic_write_text(out / "report.md", "\n".join(md))
    result = Identification(trial=trial, sampling_period_s=cohort.sampling_period_s, legs=legs, warnings=said)
    result.write(out)
    return result
