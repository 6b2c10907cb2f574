"""Benchmark: the modelling loop's wait, `quadshank discover` from its start to its end.

Three legs × 2 min of one trial with potentiation hidden, the default model, every registered
candidate, up to three rounds: the command as a user runs it, in a fresh process, timed from
start to end.  Side by side in one run:

- a first run, with an empty compilation cache of its own that it fills: each screen's L-BFGS
  in the coordinates the baseline's Laplace covariance whitens (the default), and in the plain
  standardised coordinates (``quadshank.inference._screen.WHITEN_FROM_START = False``);
- what a user iterating on a model waits for: the default run again with the cache the first
  run left, and again after writing an effect of their own (``--effects-file``, one candidate
  more, whose programs nothing compiled before).

    python benchmarks/bench_discover.py [--legs TN-left,TN-right,JM-left] [--minutes 2]
        [--out results/benchmarks.md] [--record results/bench_discover.json]
"""

from __future__ import annotations

import argparse
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from results_md import discover_rounds, publish, run_quadshank  # noqa: E402

SECTION = "bench_discover"
#: (variant, whitened coordinates, the cache folder it uses, with the user's effect)
VARIANTS = (
    ("whitened (default), first run", True, "whitened", False),
    ("whitened (default), run again", True, "whitened", False),
    ("whitened (default), run again after writing an effect", True, "whitened", True),
    ("plain coordinates, first run", False, "plain", False),
)

#: The effect a user writes between two runs (``--effects-file``): a torque–angle factor with a
#: quadratic term, a gain effect the loop screens as a candidate like the built-in ones.
USER_EFFECT = """\
import dataclasses
from quadshank import Effect, Param, register_effect


@register_effect
@dataclasses.dataclass(frozen=True)
class QuadraticTorqueAngle(Effect):
    kind = "gain"
    name = "quadratic_torque_angle"
    params = (Param("c2", "1/deg^2", prior=("normal", 0.0, 1e-4)),)
    c2: float = 0.0

    def factor(self, ctx):
        return 1.0 + self.c2 * ctx.angle**2
"""


def discover(data: str, out: str, whiten: bool, cache: str, effects_file: str | None = None) -> float:
    """``quadshank -q discover DATA --out OUT`` in a fresh process with the compilation cache in
    ``cache``; its wall time [s]."""
    cli = ("import sys; from quadshank.inference import _screen; "
           f"_screen.WHITEN_FROM_START = {whiten}; from quadshank.cli import main; sys.exit(main())")
    extra = ["--effects-file", effects_file] if effects_file else []
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", cli, "-q", "discover", data, "--out", out, *extra],
                          capture_output=True, text=True, env={**os.environ, "QUADSHANK_XLA_CACHE": cache})
    seconds = time.perf_counter() - t
    if proc.returncode not in (0, 3):
        raise RuntimeError(f"discover failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return seconds


def rounds(out: Path) -> list[dict]:
    """Each round's verdict and its leader's ΔELPD ± SE, from the round's summary."""
    return [{"verdict": s.get("verdict"), "leader": top.get("effect"), "delta_elpd": top.get("delta_elpd"),
             "delta_elpd_se": top.get("delta_elpd_se")} for s, top in discover_rounds(out)]


def render(record: dict) -> str:
    lines = [
        "## The modelling loop's wait: `discover` on 3 legs × 2 min",
        "",
        f"Command: `{record['command']}`",
        "",
        f"{', '.join(record['legs'])}, {record['minutes']:g} min of trial 1 each with potentiation hidden; "
        "`quadshank discover DATA` (model3s, every registered candidate, up to three rounds) in a fresh process, "
        "wall time from its start to its end. Each screen's modes are sought by L-BFGS in the coordinates the "
        "baseline's Laplace covariance whitens (the default), or in the plain standardised coordinates. A first "
        "run starts with an empty compilation cache of its own and fills it; a run again uses the cache the "
        "default's first run left, as a user's next command does (the command line keeps the cache by "
        "default), and after writing an effect it screens one candidate more "
        "(`--effects-file`, a quadratic torque–angle gain), whose programs it compiles.",
        "",
        "| run | wall [s] | rounds: verdict (leader's ΔELPD ± SE) |",
        "|---|---|---|",
    ]
    rows = {r["variant"]: r for r in record["rows"]}
    for r in record["rows"]:
        said = "; ".join(f"{x['verdict']} ({x['leader']} {x['delta_elpd']:.0f} ± {x['delta_elpd_se']:.0f})"
                         for x in r["rounds"])
        lines.append(f"| {r['variant']} | {r['seconds']:.0f} | {said} |")
    first, plain = rows[VARIANTS[0][0]]["seconds"], rows[VARIANTS[3][0]]["seconds"]
    again, written = rows[VARIANTS[1][0]]["seconds"], rows[VARIANTS[2][0]]["seconds"]
    lines += ["", f"Whitened, the first run took {first / plain:.2f}× the wall time of the plain coordinates'. "
              f"Run again, it took {again / first:.2f}× its first run's, and {written / first:.2f}× after "
              "writing an effect.",
              "", f"Measured {record['date']} on {record['machine']}."]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--legs", default="TN-left,TN-right,JM-left")
    ap.add_argument("--minutes", type=float, default=2.0)
    ap.add_argument("--out", default="results/benchmarks.md")
    ap.add_argument("--record", default="results/bench_discover.json")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        data = str(tmp / "data")
        run_quadshank("simulate", "--out", data, "--legs", args.legs, "--minutes", str(args.minutes), "--trials", "1",
                      "--effects", "potentiation", "--seed", "2")
        effects_file = tmp / "my_effects.py"
        effects_file.write_text(USER_EFFECT)
        for k, (variant, whiten, cache, user) in enumerate(VARIANTS):
            out = tmp / f"discover-{k}"
            seconds = discover(data, str(out), whiten, str(tmp / f"cache-{cache}"), str(effects_file) if user else None)
            rows.append({"variant": variant, "seconds": seconds, "rounds": rounds(out)})
            print(variant, f"{seconds:.0f} s", flush=True)
    record = {"command": "python benchmarks/bench_discover.py " + shlex.join(sys.argv[1:]), "legs": args.legs.split(","),
              "minutes": args.minutes, "rows": rows}
    publish(record, args.record, args.out, SECTION, render)


if __name__ == "__main__":
    main()
