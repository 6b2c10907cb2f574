"""The classical identification against the simulator's truth, with tolerances per parameter."""

from __future__ import annotations

from ..inference._identify import LegIdentification

#: Relative tolerances (|estimate - truth| / |truth|) within which the classical
#: identification must recover the simulator's truth; see README "Recovery".
TOLERANCES = {
    "damping": 0.25,
    "gravity": 0.05,
    "k1": 0.6,
    "k2": 0.5,
    "G2": 0.25,
    "gamma_angle": 0.5,
    "gamma_velocity": 0.5,
}


#: The identified delay must be within this many samples of the true (fractional) delay.
DELAY_TOLERANCE = 1.0


def recovery(ident: dict[str, LegIdentification], truth: dict) -> dict:
    """Identified vs true parameters per leg, with the tolerance check of :data:`TOLERANCES`
    (legs the truth does not describe are left out)."""
    out = {}
    for leg, r in ident.items():
        t = (truth.get("legs") or {}).get(leg)
        if not isinstance(t, dict) or not {"passive", "active"} <= set(t) or "model3" not in r.models:
            continue  # a leg the truth does not describe, or one identified without its muscle
        m3 = r.models["model3"].flat_params()
        pairs = {
            "damping": (r.passive["damping"], t["passive"]["damping"]),
            "gravity": (r.passive["gravity"], t["passive"]["gravity"]),
            "k1": (r.passive["k1"], t["passive"]["k1"]),
            "k2": (r.passive["k2"], t["passive"]["k2"]),
            "G2": (m3["gain"], t["active"]["G2"]),
            "gamma_angle": (m3["gamma_angle"], t["active"]["gamma_angle"]),
            "gamma_velocity": (m3["gamma_velocity"], t["active"]["gamma_velocity"]),
        }
        leg_out = {}
        for name, (est, true) in pairs.items():
            rel = abs(est - true) / abs(true)
            leg_out[name] = {
                "estimate": est,
                "truth": true,
                "relative_error": rel,
                "tolerance": TOLERANCES[name],
                "ok": bool(rel <= TOLERANCES[name]),
            }
        dtrue = t["active"]["delay_samples"]
        leg_out["delay_samples"] = {
            "estimate": r.delay,
            "truth": dtrue,
            "abs_error": abs(r.delay - dtrue),
            "tolerance": DELAY_TOLERANCE,
            "ok": bool(abs(r.delay - dtrue) <= DELAY_TOLERANCE),
        }
        out[leg] = leg_out
    return out


def recovery_rows(rec: dict) -> list[dict]:
    rows = []
    for leg, params in rec.items():
        for name, v in params.items():
            err = v.get("relative_error", v.get("abs_error"))
            rows.append(
                {
                    "leg": leg,
                    "parameter": name,
                    "estimate": v["estimate"],
                    "truth": v["truth"],
                    "error": err,
                    "tolerance": v["tolerance"],
                    "within": "yes" if v["ok"] else "NO",
                }
            )
    return rows
