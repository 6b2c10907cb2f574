"""The ``quadshank`` command: wires the package's functions; no numerics here."""

from __future__ import annotations

import argparse
import math
import os
import re
import shlex
import sys
import time
import unicodedata
import warnings
from pathlib import Path

import matplotlib

from .commands.check import Check, check_table, run_check
from .commands.demo import Demo, run_demo
from .commands.diagnose import run_diagnose
from .commands.discover import run_discover
from .commands.evaluate import run_evaluate, run_posterior_evaluate
from .commands.fit import run_fit
from .commands.identify import run_identify
from .commands.predict import PlanPrediction, run_predict
from .commands.recovery import run_likelihood_calibration, run_recovery
from .commands.report import Report, run_report
from .commands.reproduce import Reproduction, run_reproduce
from .common._io import read_json
from .common._progress import write_above_bars
from .common._interrupt import handling_interrupts, interrupt_requested
from .common._xla_cache import use_compilation_cache
from .data._interchange import DataWarning, convert, load_cohort, write_interchange
from .data._paper import LEGS
from .data._simulate import TRIAL_RECRUITMENT, TWITCH_CV, simulate_cohort, write_truth
from .evaluation._posterior import PosteriorEvaluation, check_fit_legs, load_fits
from .evaluation._prediction import Evaluation
from .inference._fitio import FitResult, read_summary
from .inference._identify import Identification, load_identification
from .inference._nuts import PRECISIONS, SEQUENTIAL_FROM_SAMPLES, STARTS, FitSettings
from .loop._diagnose import SCREEN_STARTS, STOPPED_AT_LIMIT, Diagnosis, Discovery
from .model._model import FIT_MODELS
from .model._plugins import load_effects_file, load_entry_point_effects

__all__ = ["main"]

EXPECTED_ERRORS: tuple[type[BaseException], ...] = (OSError, KeyError, ValueError, FloatingPointError)

#: The result kinds (``summary.json`` schema) a command may find in its output folder from an earlier run of its own.
OUTPUT_KINDS = {
    "identify": {Identification.KIND}, "evaluate": {Evaluation.KIND, PosteriorEvaluation.KIND}, "fit": {FitResult.KIND},
    "reproduce": {Reproduction.KIND}, "diagnose": {Diagnosis.KIND}, "discover": {Discovery.KIND},
    "compare": {PosteriorEvaluation.KIND}, "report": {Report.KIND}, "demo": {Demo.KIND}, "recovery": set(),
    "likelihood-check": set(), "simulate": set(), "convert": set(), "predict": {PlanPrediction.KIND},
    "check": {Check.KIND},
}
#: Commands whose --out is optional (without it they write nothing).
OPTIONAL_OUT = ("check",)
#: Commands that build or load models, and so may need a user's effects (--effects-file).
EFFECT_USERS = ("fit", "diagnose", "discover", "compare", "evaluate", "report", "predict", "recovery")
#: Options that act only beside another: per command, (option, whether ``args`` gives what it acts
#: beside, why it would be ignored). Such an option given alone is refused before any work.
_WITH_CONFIRM = "acts only with --confirm (the NUTS fits); without it discover screens alone"
NEEDS_PARTNER = {
    "fit": [("--time-limit", lambda a: a.target_ess is not None,
             "acts only with --target-ess (a fit of fixed length runs to its end)")],
    "evaluate": [
        *[(option, lambda a: bool(a.fit), "acts only with --fit (the posterior's bands); without it evaluate "
                                          "scores the classical models' point estimates")
          for option in ("--draws", "--start-stride", "--band-mcse")],
        *[(option, lambda a: a.band_mcse is None, f"is chosen by --band-mcse: give one of {option} and --band-mcse")
          for option in ("--draws", "--start-stride")],
    ],
    "discover": [
        *[(option, lambda a: bool(a.confirm), _WITH_CONFIRM)
          for option in ("--chains", "--target-ess", "--time-limit", "--warmup", "--draws", "--target-accept",
                         "--seed")],
        ("--time-limit", lambda a: a.target_ess != 0, "acts only with --target-ess above 0 (fits of fixed length "
                                                      "run to their end)"),
    ],
    "report": [("--start-stride", lambda a: not a.evaluation,
                "acts only where report computes J: with --evaluation, J's bands are that evaluation's")],
    "predict": [("--velocity0", lambda a: a.angle0 is not None,
                 "acts only with --angle0 (without it each draw starts at its rest, where the shank is still)")],
    "demo": [("--time-limit", lambda a: a.target_ess != 0,
              "acts only with --target-ess above 0 (a fit of fixed length runs to its end)")],
}


def _given(parser, args, option: str) -> bool:
    """Whether ``option`` is on ``args``' command line, as itself, as ``option=value`` or as the
    unambiguous prefix argparse takes for it."""
    sub = next(a for a in parser._subparsers._group_actions if a.choices).choices[args.command]
    names = [n for n in sub._option_string_actions if n.startswith("--")]
    for token in args.argv[args.argv.index(args.command) + 1:]:
        if token == "--":
            break
        name = token.split("=", 1)[0]
        if name == option or (len(name) > 2 and option.startswith(name)
                              and [n for n in names if n.startswith(name)] == [option]):
            return True
    return False


def refuse_lone_options(parser, args) -> None:
    """Refuse an option given without the one it acts beside (:data:`NEEDS_PARTNER`)."""
    for option, present, why in NEEDS_PARTNER.get(args.command, ()):
        if not present(args) and _given(parser, args, option):
            raise ValueError(f"{option} {why}")


#: Commands whose output folder is a folder of recordings.
DATA_WRITERS = ("simulate", "convert")
#: The hidden file that marks a folder as a command's output: the command's name on its first
#: line, then the files that run wrote (relative paths), which a rerun into the folder removes first.
OUTPUT_MARK = ".quadshank-output"


def _files_in(out: Path) -> set[str]:
    """The files under ``out`` (relative POSIX paths; the mark itself left out)."""
    return {p.relative_to(out).as_posix() for p in out.rglob("*")
            if (p.is_file() or p.is_symlink()) and p.name != OUTPUT_MARK}


def _reusable_fit(path: Path, out: Path) -> bool:
    """Whether ``path`` lies in a finished fit of ``recovery`` (a folder of ``out`` holding
    ``fit.nc``, ``summary.json`` and ``truth.json``), which a rerun takes again where the truth,
    the settings and the code are the same."""
    folder = path.parent
    return folder.resolve() != out.resolve() and all((folder / n).is_file() for n in ("fit.nc", "summary.json", "truth.json"))


#: Commands whose earlier output holds work a rerun reuses, and the files that are that work.
REUSED = {"recovery": _reusable_fit}


def _remove_earlier_files(out: Path, keep=None) -> set[str]:
    """Remove the files an earlier run of the same command listed in its mark, and the folders
    that leaves empty: a rerun must not leave pages, tables or figures of legs it no longer has
    beside its own.  Files the mark does not list (the user's) stay, and so do those ``keep(path,
    out)`` holds to be work the rerun reuses (:data:`REUSED`); returns the latter."""
    try:
        listed = (out / OUTPUT_MARK).read_text().splitlines()[1:]
    except (OSError, UnicodeDecodeError):
        return set()
    root = out.resolve()
    reused = set()
    for rel in listed:
        path = out / rel
        if not rel or rel.startswith("/") or not path.resolve().is_relative_to(root):
            continue  # a mark edited by hand names nothing outside the folder
        if keep is not None and keep(path, out):
            reused.add(rel)
        elif path.is_file() or path.is_symlink():
            path.unlink()
    _remove_empty_folders(out)
    return reused


def _remove_empty_folders(out: Path) -> None:
    """Remove the folders under ``out`` that hold nothing (deepest first, so a folder that held
    only empty ones goes too)."""
    for folder in sorted((p for p in out.rglob("*") if p.is_dir() and not p.is_symlink()),
                         key=lambda p: len(p.parts), reverse=True):
        if not any(folder.iterdir()):
            folder.rmdir()


def _command_line(args) -> str:
    """The command as typed, quoted for a shell: written beside the figures it made."""
    return "quadshank " + " ".join(shlex.quote(a) for a in args.argv)


def _csv_list(text: str, option: str = "") -> list[str]:
    """A comma-separated list; with ``option`` (its name, for the error), one that names something
    and names nothing twice (a leg listed twice would count its data twice)."""
    items = [x.strip() for x in text.split(",") if x.strip()]
    if option:
        if not items:
            raise ValueError(f"{option}: {text!r} names nothing (give names separated by commas)")
        twice = sorted({x for x in items if items.count(x) > 1})
        if twice:
            raise ValueError(f"{option}: {', '.join(map(repr, twice))} given twice")
    return items


def _int_list(text: str, option: str) -> list[int]:
    """A comma-separated list of whole numbers, or an error naming the option."""
    out = []
    for x in _csv_list(text, option):
        if not re.fullmatch(r"[+-]?[0-9]+", x):
            raise ValueError(f"{option}: {x!r} is not a whole number (give numbers separated by commas)")
        out.append(int(x))
    return out


def _say(args, *lines: str) -> None:
    if not args.quiet:
        for line in lines:
            print(line, file=sys.stderr)


def _truth_beside(data: Path) -> dict | None:
    """The simulator's truth written beside the data (``quadshank simulate``), or None; a
    ``truth.json`` of another kind is left aside with a warning."""
    path = data / "truth.json" if data.is_dir() else data.with_name("truth.json")
    if not path.exists():
        return None
    try:
        truth = read_json(path)
    except ValueError as exc:
        print(f"quadshank: warning: {exc}; left aside (not the simulator's truth)", file=sys.stderr)
        return None
    if not isinstance(truth, dict) or not isinstance(truth.get("legs"), dict) or not all(
            isinstance(v, dict) for v in truth["legs"].values()):
        print(f"quadshank: warning: {path}: not the simulator's truth (a 'legs' object of legs); left aside",
              file=sys.stderr)
        return None
    return truth


def _inputs(args) -> list[Path]:
    """The folders and files a command reads."""
    names = ("data", "fitdir", "identified", "evaluation", "diagnosis", "delay_from", "fit_a", "fit_b", "src", "plan")
    # (an evaluation or diagnosis folder given to `report` is read, so it is an input too)
    found = [getattr(args, n, None) for n in names] + list(getattr(args, "fit", None) or [])
    return [Path(p) for p in found if p]


def _earlier_output(out: Path, command: str) -> bool:
    """Whether ``out`` holds an earlier output of ``command`` (its mark, or its kind of summary)."""
    mark = out / OUTPUT_MARK
    if mark.is_file():
        try:
            return (mark.read_text().splitlines() or [""])[0].strip() == command
        except (OSError, UnicodeDecodeError):
            return False
    summary = out / "summary.json"
    if summary.is_file():
        try:
            doc = read_json(summary)
        except (OSError, ValueError):
            return False
        schema = doc.get("schema", "") if isinstance(doc, dict) else ""
        return schema.removeprefix("quadshank/") in OUTPUT_KINDS.get(command, set())
    return False


def _other_summary(out: Path, command: str) -> str | None:
    """The command whose ``summary.json`` ``out`` holds, where that is another command's (None otherwise)."""
    try:
        doc = read_json(out / "summary.json")
    except (OSError, ValueError):
        return None
    kind = doc.get("schema", "").removeprefix("quadshank/") if isinstance(doc, dict) else ""
    if not kind or kind in OUTPUT_KINDS.get(command, set()):
        return None
    return next((name for name, kinds in OUTPUT_KINDS.items() if kind in kinds), kind)


def prepare_output(out: Path, command: str, inputs, overwrite: bool = False):
    """Check the output folder before any work: a folder (or a name for a new one) that is
    writable, not inside or equal to an input, and new, empty or an earlier output of the same
    command (``overwrite``: any folder; files of the same names are replaced, others kept).
    Then remove its ``summary.json``: until the new one lands, the folder is incomplete.

    Returns the function that marks the folder as this command's once the command has run,
    where the folder exists by then: a command refused before it wrote anything leaves no folder
    behind, and one that failed (``mark(failed=True)``) removes a folder it made and left empty."""
    resolved = out.resolve()
    for p in inputs:
        src = p.resolve()
        if resolved == src:
            raise ValueError(f"{out}: is the input {p}; write the results to a folder of their own")
        data_folder = src if src.is_dir() else src.parent if src.name == "manifest.csv" else None
        if data_folder is not None and (data_folder / "manifest.csv").is_file() and resolved.is_relative_to(data_folder):
            raise ValueError(f"{out}: inside the data folder {data_folder}; write the results to a folder of their own")
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"{out}: exists and is not a folder; give a folder for the results")
    if (out / "manifest.csv").is_file() and command not in DATA_WRITERS:
        raise ValueError(f"{out}: holds recordings (manifest.csv); write the results to a folder of their own")
    existing = out if out.exists() else next(p for p in out.parents if p.exists())
    if not existing.is_dir():
        raise NotADirectoryError(f"{out}: {existing} is a file, not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise PermissionError(f"{out}: {existing} is not writable")
    foreign = out.is_dir() and any(out.iterdir()) and not _earlier_output(out, command)
    if foreign and not overwrite:
        raise FileExistsError(
            f"{out}: the folder is not empty and holds no earlier output of `quadshank {command}`; give a new "
            "folder (or --overwrite to write into it: files of the same names are replaced, others kept)")
    other = _other_summary(out, command) if foreign else None
    if other:
        raise FileExistsError(
            f"{out}: holds the output of `quadshank {other}` (its summary.json), which --overwrite would replace with "
            f"this command's and leave a folder that is neither; give a folder of its own")
    reused = _remove_earlier_files(out, REUSED.get(command)) if out.is_dir() and not foreign else set()
    (out / "summary.json").unlink(missing_ok=True)
    new = not out.exists()
    kept = _files_in(out) - reused if out.is_dir() else set()  # the user's files, which this run did not write

    def mark(failed: bool = False) -> None:
        if failed and new and out.is_dir():
            # made for this output: the folders that nothing came of go (a round begun, say), then
            # the output folder itself where nothing else was written
            _remove_empty_folders(out)
            if not any(out.iterdir()):
                out.rmdir()
                return
        # a folder written into by --overwrite stays unmarked: it holds more than this output
        if not foreign and out.is_dir():
            try:
                written = sorted(_files_in(out) - kept)
                (out / OUTPUT_MARK).write_text("".join(f"{line}\n" for line in [command, *written]))
            except OSError:  # the command's own outcome is what the user needs to hear of
                pass

    return mark


# ---------------------------------------------------------------------------- commands


def cmd_simulate(args) -> int:
    legs = _csv_list(args.legs, "--legs") if args.legs is not None else list(LEGS)
    effects = _csv_list(args.effects, "--effects") if args.effects else []
    trials = _int_list(args.trials, "--trials")
    lacking = sorted(set(range(1, max(trials, default=0) + 1)) - set(trials))
    if lacking and all(t in TRIAL_RECRUITMENT for t in trials):  # an unknown trial: simulate_cohort says which exist
        raise ValueError(f"--trials {args.trials}: a folder of recordings numbers each leg's trials from 1, and "
                         f"trial(s) {', '.join(map(str, lacking))} would be missing; simulate "
                         f"{','.join(map(str, range(1, max(trials) + 1)))} and choose trials in later commands "
                         "(their --trials)")
    cohort, truth = simulate_cohort(
        legs=legs, minutes=args.minutes, seed=args.seed, effects=effects, trials=trials, progress=not args.quiet,
        sampling_period_s=args.sampling_period_ms / 1000.0, twitch_cv=args.twitch_cv,
    )
    out = Path(args.out)
    write_interchange(cohort, out, overwrite=True)  # the folder was checked before the work began
    write_truth(truth, out / "truth.json")
    _say(args, f"simulated {len(cohort)} trials of {len(legs)} legs -> {out}/manifest.csv (truth: {out}/truth.json)")
    return 0


def cmd_check(args) -> int:
    result = run_check(args.data, args.out, identification_trial=args.trial)
    print(check_table(result))
    if args.out is not None:
        _say(args, f"recordings.csv and .md, a figure per trial and summary.json in {args.out}")
    return 0


def cmd_convert(args) -> int:
    # a folder of recordings was checked (new, empty, an earlier conversion or --overwrite) before the work began
    if args.resample is not None and not args.resample > 0:
        raise ValueError(f"--resample {args.resample:g}: the new sampling period must be positive (in seconds)")
    dst = convert(args.src, args.dst, overwrite=args.overwrite or Path(args.dst).suffix.lower() != ".nc",
                  resample_s=args.resample, repair_artefacts=args.repair_artefacts)
    _say(args, f"converted {args.src} -> {dst}" + (f", resampled to {args.resample * 1000:g} ms" if args.resample else "")
         + (", stimulation artefacts repaired where found" if args.repair_artefacts else ""))
    return 0


def cmd_identify(args) -> int:
    data = Path(args.data)
    cohort = load_cohort(data)
    summary = run_identify(cohort, args.out, truth=_truth_beside(data), trial=args.trial, progress=not args.quiet,
                           passive_objective=args.passive_objective, gravity_offset=args.gravity_offset)
    _say(args, *(f"{leg}: passive system only, from trial(s) {', '.join(map(str, s['passive_trials']))} "
                 f"(no pulses in the identification trial), fitted to the {s['passive_objective']}"
                 if s.get("passive_only") else
                 f"{leg}: d = {s['delay_samples']} samples" + (
                     f"; passive system from trial(s) {', '.join(map(str, s['passive_trials']))} (no pulses)"
                     if s.get("passive_trials") else "")
                 for leg, s in summary.legs.items()))
    muscle = any(not s.get("passive_only") for s in summary.legs.values())  # the figures are of twitches
    _say(args, ("tables, figures and" if muscle else "tables and") + f" summary.json in {args.out}")
    return 0


def cmd_evaluate(args) -> int:
    data = Path(args.data)
    out = Path(args.out)
    if args.fit:

        if args.identified:
            raise ValueError("give --fit (posterior evaluation) or --identified (point estimates), not both")
        summary = run_posterior_evaluate(
            load_cohort(data), args.fit, out, n_draws=args.draws, start_stride=args.start_stride,
            progress=not args.quiet, band_accuracy=args.band_mcse,
        )
        for model, info in summary.fits.items():
            if info["banner"]:
                print(f"quadshank: warning: {model} ({info['folder']}): {info['banner']}", file=sys.stderr)
        for model, trials in summary.J.items():
            _say(args, f"{model}: " + "; ".join(
                f"trial {t}: " + ", ".join(f"{h} ms {v['median']:.1f}° [{v['lo']:.1f}, {v['hi']:.1f}]"
                                           for h, v in hv.items())
                for t, hv in trials.items()
            ))
        for model, v in summary.loo["fits"].items():
            _say(args, f"{model}: elpd_loo {v['elpd_loo']:.1f} ± {v['se']:.1f}, p_loo {v['p_loo']:.1f}, "
                       f"{v['pareto_k_over_0.7']} segment(s) with Pareto k > 0.7")
        for group in summary.loo["compare"]:
            ranked = sorted(group["table"].items(), key=lambda kv: kv[1]["rank"])
            _say(args, "LOO ranking: " + ", ".join(
                f"{m} (Δelpd {r['elpd_diff']:.1f} ± {r['dse']:.1f}, weight {r['weight']:.2f})" for m, r in ranked
            ))
        m = summary.band_mcse
        short = f"; NOT within the {m['target']:g} deg asked for" if "target" in m and not m["met"] else ""
        _say(args, f"J bands from {summary.n_draws} draws, one start in {summary.start_stride}: the largest Monte Carlo "
                   f"standard error of a band end {m['largest_cohort']:.3f} deg (mean over legs), "
                   f"{m['largest_legs']:.3f} deg (one leg){short}")
        _say(args, f"posterior Table V, sign tests, PSIS-LOO, figures and summary.json in {out}")
        return 0
    cohort = load_cohort(data)
    if args.identified:
        models = load_identification(args.identified, cohort.sampling_period_s)
    else:
        _say(args, f"no --identified folder given: identifying from trial 1 into {out / 'identify'}")
        models = run_identify(cohort, out / "identify", truth=_truth_beside(data), progress=not args.quiet).models()
    summary = run_evaluate_and_report(args, cohort, models, out)
    return 0 if summary else 1


def run_evaluate_and_report(args, cohort, models, out):
    summary = run_evaluate(cohort, models, out, progress=not args.quiet)
    for model, trials in summary.J.items():
        _say(args, f"{model}: " + "; ".join(
            f"trial {t}: " + ", ".join(f"{h} ms {v:.1f}°" if math.isfinite(v) else f"{h} ms not finite" for h, v in hv.items())
            for t, hv in trials.items()
        ))
    _say(args, f"Table V, sign tests, figures and summary.json in {out}")
    return summary


#: ``fit``'s warm-up and draws per chain by default, and with ``--target-ess`` (a short warm-up
#: from the screen's metric, then blocks of draws)
FIXED_LENGTHS = (1000, 1000)
TARGET_LENGTHS = (200, 100)


def fit_lengths(args, target_ess: int | None, fixed: tuple[int, int] = FIXED_LENGTHS) -> tuple[int, int]:
    """Warm-up and draws (or block) per chain: the user's, else the defaults for how the fit draws
    (to ``target_ess``, or ``fixed`` lengths without one)."""
    warmup, draws = TARGET_LENGTHS if target_ess is not None else fixed
    return (warmup if args.warmup is None else args.warmup, draws if args.draws is None else args.draws)


def cmd_fit(args) -> int:
    cohort = load_cohort(Path(args.data))
    warmup, draws = fit_lengths(args, args.target_ess)
    settings = FitSettings(
        chains=args.chains,
        warmup=warmup,
        draws=draws,
        target_ess=args.target_ess,
        time_limit_s=args.time_limit,
        seed=args.seed,
        trials=tuple(_int_list(args.trials, "--trials")),
        start=args.start,
        adapt_metric=args.adapt_metric,
        delay_evidence=args.delay_evidence,
        mode_jumps=args.mode_jumps,
        max_tree_depth=args.max_tree_depth,
        target_accept=args.target_accept,
        chain_method=args.chain_method,
        likelihood=args.likelihood,
        precision=args.precision,
    )
    legs = _csv_list(args.legs, "--legs") if args.legs is not None else None
    summary = run_fit(
        cohort,
        args.out,
        args.model,
        args.add_effect or (),
        settings,
        legs=legs,
        delay_from=args.delay_from or None,
        progress=not args.quiet,
        data_source=str(Path(args.data).resolve()),
    )
    for leg, s in summary.legs.items() if "no_muscle" not in summary.effects else ():  # the pendulum alone: no delay
        p = s["delay_posterior"]
        if leg in (summary.uninformed or {}):  # no pulses to inform it: the prior's mode says nothing
            _say(args, f"{leg}: P(d) is the prior's (too few pulses to inform it)")
        else:
            _say(args, f"{leg}: P(d) mode {s['delay_mode_samples']} samples ({max(p):.2f})")
    diag = summary.diagnostics
    _say(
        args,
        f"R-hat max {diag['rhat_max']:.3f}, bulk ESS min {diag['ess_bulk_min']:.0f}, "
        f"divergences {diag['divergences']}, E-BFMI min {diag['bfmi_min']:.2f}"
        + ("" if diag.get("mode_jumps") is None else f", jumps between delay modes {diag['mode_jumps']}"),
    )
    if summary.target is not None:
        t = summary.target
        floor = t.get("ess_needed", t["target_ess"])  # the fit's checks ask at least 100 per chain
        target = f"{t['target_ess']}" + (f" (drawn to {floor:g}, what the fit's checks ask)" if floor > t["target_ess"] else "")
        _say(args, f"target ESS {target}: {t['stopped']}, after {t['blocks']} block(s), "
                   f"{t['draws_per_chain']} draws per chain, {t['seconds']:.0f} s from the start")
    for w in diag.get("warnings", []):
        print(f"quadshank: warning: {w}", file=sys.stderr)
    for leg, u in (summary.uninformed or {}).items():
        print(f"quadshank: warning: {leg}: {u['why']} in the fitted trials: its delay and {', '.join(u['params'])} "
              "are the prior's and the other legs', not estimates from its data", file=sys.stderr)
    if not diag["ok"]:
        print(f"quadshank: {summary.banner}", file=sys.stderr)
        for a in diag["advice"]:
            print(f"quadshank: advice: {a}", file=sys.stderr)
        print(f"quadshank: the fit is saved in {args.out} but should not be trusted", file=sys.stderr)
        return 3
    _say(args, f"fit.nc and summary.json in {args.out}")
    return 0


def cmd_recovery(args) -> int:
    command = _command_line(args)
    settings = FitSettings(
        chains=args.chains, warmup=args.warmup, draws=args.draws, start=args.start, adapt_metric=args.adapt_metric,
        delay_evidence=args.delay_evidence, mode_jumps=args.mode_jumps,
    )
    result = run_recovery(
        args.out,
        models=_csv_list(args.models, "--models"),
        seeds=_int_list(args.seeds, "--seeds"),
        legs=_csv_list(args.legs, "--legs") if args.legs is not None else None,
        minutes=args.minutes,
        settings=settings,
        progress=not args.quiet,
        command=command,
        add_effects=args.add_effect or (),
        truth_effects=None if args.truth_effects is None else _csv_list(args.truth_effects),
    )
    code = 0
    for model, m in result["models"].items():
        lo, hi = m["expected_band_95"]
        passed, n_fits = sum(bool(f["ok"]) for f in m["fits"]), len(m["fits"])
        reused = sum(bool(f["reused"]) for f in m["fits"])
        if "delay_legs" not in m:
            delay = ""
        elif m.get("delay_seen_legs"):
            delay = f", delay mode right for {m['delay_mode_right']}/{m['delay_legs']} legs"
        else:  # the mode of a flat P(d) is no estimate (model 1's likelihood does not see the delay)
            delay = ", the delay not estimated (P(d) stayed the prior's on every leg)"
        _say(
            args,
            f"{model}: {m['covered']}/{m['n_intervals']} 90 % intervals cover the truth ({m['coverage']:.2f}; "
            f"{lo:.2f}-{hi:.2f} expected if calibrated){delay}; {passed}/{n_fits} fits passed their checks"
            + (f" ({reused} reused from this folder)" if reused else ""),
        )
        if passed < n_fits:
            print(f"quadshank: warning: {model}: {n_fits - passed} of {n_fits} fits failed their checks (R-hat, ESS, "
                  "divergences; coverage.md): its coverage is no evidence of calibration", file=sys.stderr)
            code = 3
    _say(args, f"table: {Path(args.out) / 'coverage.md'}")
    return code


def cmd_likelihood_check(args) -> int:
    command = _command_line(args)
    result = run_likelihood_calibration(
        args.out,
        models=_csv_list(args.models, "--models"),
        seeds=_int_list(args.seeds, "--seeds"),
        legs=_csv_list(args.legs, "--legs") if args.legs is not None else None,
        minutes=args.minutes,
        replicates=args.replicates,
        progress=not args.quiet,
        command=command,
    )
    for r in result["runs"]:
        lo, hi = r["expected_band_95"]
        _say(
            args,
            f"{r['model']} seed {r['seed']}: {r['covered']}/{r['intervals']} Wald 90 % intervals cover the truth "
            f"({r['coverage']:.3f}; calibrated: {lo:.3f}-{hi:.3f})",
        )
    _say(args, f"table: {Path(args.out) / 'likelihood.md'}")
    return 0


def _loop_data(args, fit_summary: FitResult | None = None):
    data = args.data or (fit_summary.data if fit_summary is not None else None)
    if not data:
        raise ValueError("no data: give --data (the fit does not record where its data came from)")
    return load_cohort(Path(data)), data


def _say_ranking(args, summary: Diagnosis) -> None:
    for i, r in enumerate(summary.ranking, 1):
        mark = "  <- clears the bar" if r["clears_bar"] else ""
        _say(args, f"{i}. {r['effect']}: dELPD {r['delta_elpd']:.1f} +- {r['delta_elpd_se']:.1f}, "
                   f"J at 1 s {r['J_1000ms']['before']['median']:.3f} -> {r['J_1000ms']['after']['median']:.3f} deg{mark}")
    for f in summary.failed:
        _say(args, f"not screened: {f['effect']} ({f['error']})")
    for f in summary.not_applicable:
        _say(args, f"not applicable: {f['effect']} ({f['why']})")
    _say(args, f"verdict: {summary.verdict}. {summary.sentence}")


def cmd_diagnose(args) -> int:
    n_starts = _starts(args)
    (fit,) = load_fits([args.fitdir])
    model, desc = fit.model, fit.desc
    cohort, _ = _loop_data(args, fit.summary)
    check_fit_legs([fit], cohort)
    command = _command_line(args)
    if args.confirm < 0:
        raise ValueError(f"--confirm must be a number of leaders, at least 0, not {args.confirm}")
    summary = run_diagnose(
        cohort, model, args.out, trials=tuple(desc["trials"]), legs=desc["legs"],
        effects=_csv_list(args.effects, "--effects") if args.effects else None, command=command,
        progress=not args.quiet,
        confirm_from=args.fitdir if args.confirm else None, n_confirm=args.confirm,
        objective=desc.get("likelihood", "acceleration"),  # the screens compare what the fit compared
        n_starts=n_starts,
    )
    _say_ranking(args, summary)
    _say(args, f"report: {Path(args.out) / 'report.md'}")
    return _nuts_fits_code(summary.nuts_fits_ok, args.out)


def _nuts_fits_code(ok: bool | None, out) -> int:
    """3, said on the console, where a NUTS fit the loop made to confirm a leader failed its checks."""
    if ok is False:
        print(f"quadshank: a NUTS fit made to confirm failed its checks (see {Path(out) / 'report.md'}): its verdict "
              "rests on chains that should not be trusted; fit longer (--target-ess, --time-limit)", file=sys.stderr)
        return 3
    return 0


#: ``discover --confirm``'s warm-up and draws per chain with ``--target-ess 0`` (a fixed length)
CONFIRM_FIXED_LENGTHS = (300, 300)
#: ``discover --confirm``'s ESS target for each NUTS fit: a leader is added on the evidence of fits that
#: pass their checks (R-hat, ESS), not of chains stopped after a fixed number of draws
CONFIRM_TARGET_ESS = 400


def confirm_settings(args, trials) -> FitSettings | None:
    """The NUTS fits of ``discover --confirm`` (None without ``--confirm``): drawn in blocks to
    ``--target-ess`` within ``--time-limit`` each, or of the fixed ``--warmup`` and ``--draws``
    with ``--target-ess 0``."""
    if not args.confirm:
        return None
    if args.target_ess < 0:
        raise ValueError(f"--target-ess must be at least 0 (0: a fixed --warmup and --draws), not {args.target_ess}")
    target = args.target_ess or None
    warmup, draws = fit_lengths(args, target, CONFIRM_FIXED_LENGTHS)
    return FitSettings(chains=args.chains, warmup=warmup, draws=draws, target_ess=target,
                       time_limit_s=args.time_limit, target_accept=args.target_accept, seed=args.seed, trials=trials)


def _starts(args) -> int:
    if args.starts < 0:
        raise ValueError(f"--starts must be at least 0, not {args.starts}")
    return args.starts


def _target_accept_option(parser, scope: str = "") -> None:
    parser.add_argument("--target-accept", type=float, default=FitSettings.target_accept, metavar="P",
                        help=f"{scope}NUTS's target acceptance probability, between 0 and 1: higher takes smaller "
                             f"steps, which divergent transitions call for (default {FitSettings.target_accept})")


def _starts_option(parser) -> None:
    parser.add_argument("--starts", type=int, default=SCREEN_STARTS, metavar="N",
                        help="prior draws tried for each candidate's new parameters, besides their prior median, "
                             f"each a start of the screen's optimisation per leg (default {SCREEN_STARTS}); more "
                             "guard against a local mode, each costing one more optimisation per leg and candidate")


def cmd_discover(args) -> int:
    n_starts = _starts(args)
    cohort, data = _loop_data(args)
    command = _command_line(args)
    trials = tuple(_int_list(args.trials, "--trials"))
    confirm = confirm_settings(args, trials)
    summary = run_discover(
        cohort, args.out, model=args.model, trials=trials,
        legs=_csv_list(args.legs, "--legs") if args.legs is not None else None,
        effects=_csv_list(args.effects, "--effects") if args.effects else None,
        max_rounds=args.max_rounds, command=command, progress=not args.quiet, confirm=confirm,
        data_source=str(Path(data).resolve()), n_starts=n_starts,
    )
    for k, r in enumerate(summary.rounds, 1):
        _say(args, f"round {k}: {r['model']}: verdict {r['verdict']}")
    if summary.confirm is not None:
        _say(args, summary.confirm["sentence"])
    _say(args, f"final model: {summary.final_model}; report: {Path(args.out) / 'report.md'}")
    if summary.stopped == STOPPED_AT_LIMIT:
        _say(args, f"stopped at --max-rounds {args.max_rounds}: the last round still added an effect; a further "
                   "round may find more")
    return _nuts_fits_code(summary.nuts_fits_ok, args.out)


def cmd_compare(args) -> int:
    cohort, _ = _loop_data(args, read_summary(args.fit_a))
    summary = run_posterior_evaluate(cohort, [args.fit_a, args.fit_b], args.out, n_draws=args.draws,
                                     start_stride=args.start_stride, progress=not args.quiet, residuals=True)
    for group in summary.loo.get("compare", []):
        for label, row in group["table"].items():
            _say(args, f"{label}: rank {row['rank']}, elpd difference {row['elpd_diff']:.1f} +- {row['dse']:.1f}")
    for label, legs in summary.residual_findings.items():
        for leg, lines in legs.items():
            _say(args, f"{label} {leg} residuals: " + (" ".join(lines) if lines else "nothing stands out."))
    _say(args, f"J bands, PSIS-LOO, residuals before and after, figures: {Path(args.out) / 'report.md'}")
    return 0


def cmd_report(args) -> int:
    fit_summary = read_summary(args.fitdir)
    cohort, _ = _loop_data(args, fit_summary)
    summary = run_report(args.fitdir, args.out, cohort=cohort, evaluation=args.evaluation or None,
                         diagnosis=args.diagnosis or None, n_draws=args.draws, start_stride=args.start_stride,
                         progress=not args.quiet)
    if not summary.diagnostics_ok:
        print(f"quadshank: warning: {args.fitdir}: {fit_summary.banner}", file=sys.stderr)
    _say(args, f"{len(summary.pages) - 1} subject page(s), per-leg CSV and JSON; open {Path(args.out) / 'index.html'}")
    return 0


def cmd_predict(args) -> int:
    legs = _csv_list(args.legs, "--legs") if args.legs is not None else None
    summary = run_predict(args.fitdir, args.plan, args.out, legs=legs,
                          angle0=args.angle0, velocity0=args.velocity0, n_draws=args.draws, seed=args.seed)
    if summary.banner:
        print(f"quadshank: warning: {args.fitdir}: {summary.banner}", file=sys.stderr)
    def deg(x):  # None where no draw stayed finite; beyond a knee's reach, said as such (the warning says more)
        if x is None:
            return "no finite angle"
        return f"{x:.1f}°" if abs(x) <= 180.0 else ("beyond +180°" if x > 0 else "beyond -180°")

    for leg, e in summary.extremes.items():
        if args.angle0 is None:
            start = f"rest ({deg(summary.rest_deg[leg]['median'])})"
        else:
            start = f"{args.angle0:g}°" + (f" at {args.velocity0:g} deg/s" if args.velocity0 else "")
        _say(args, f"{leg}: from {start} the angle ranges over [{deg(e['min_deg'])}, {deg(e['max_deg'])}] "
                   f"(90 % band) and ends at {deg(e['end']['median'])} [{deg(e['end']['lo'])}, {deg(e['end']['hi'])}]")
    _say(args, f"predictions.csv and predictions.png in {args.out}")
    return 0


def cmd_reproduce(args, default_out: str | None = None) -> int:
    out = Path(args.out or default_out)
    command = _command_line(args)
    t0 = time.perf_counter()
    summary = run_reproduce(
        out,
        minutes=args.minutes,
        seed=args.seed,
        effects=_csv_list(args.effects, "--effects") if args.effects else (),
        legs=_csv_list(args.legs, "--legs") if args.legs is not None else None,
        progress=not args.quiet,
        command=command,
        twitch_cv=args.twitch_cv,
    )
    _say(
        args,
        "mean RMS angle per trial: " + ", ".join(f"{t}: {v:.1f}°" for t, v in summary.rms_angle_deg.items()),
        "J [deg], mean over legs, trial 2: "
        + "; ".join(f"{m}: " + ", ".join(f"{h} ms {v:.1f}" for h, v in summary.J[m].get("2", {}).items())
                    for m in sorted(summary.J)),
        f"parameters within tolerance of the truth: {'yes' if summary.recovery_ok else 'NO'}",
        f"done in {time.perf_counter() - t0:.0f} s; report: {out / 'report.md'}",
    )
    return 0


def cmd_demo(args) -> int:
    command = _command_line(args)
    t0 = time.perf_counter()
    summary = run_demo(
        args.out, minutes=args.minutes, seed=args.seed,
        effects=_csv_list(args.effects, "--effects") if args.effects else (),
        hidden=() if args.hide == "none" else _csv_list(args.hide, "--hide"), twitch_cv=args.twitch_cv,
        legs=_csv_list(args.legs, "--legs") if args.legs is not None else None,
        chains=args.chains, warmup=args.warmup, draws=args.draws,
        max_tree_depth=args.max_tree_depth, target_ess=args.target_ess or None, time_limit_s=args.time_limit,
        progress=not args.quiet, command=command,
    )
    if not summary.fit_ok:
        print(f"quadshank: warning: the demo's short fit did not pass its checks ({summary.fit_banner}); "
              "its report says so on every page", file=sys.stderr)
    _say(
        args,
        f"diagnosis verdict: {summary.verdict}"
        + (f" ({', '.join(summary.hidden)} was hidden: {'found' if summary.found else 'not found'})"
           if summary.hidden else ""),
        f"done in {time.perf_counter() - t0:.0f} s; open the report: {summary.report}",
    )
    return 0


# ---------------------------------------------------------------------------- parser


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="quadshank", description=__doc__.splitlines()[0] if __doc__ else None)
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bars or messages (for scripts)")
    sub = p.add_subparsers(dest="command", required=True)

    def start_options(sp):
        sp.add_argument("--start", choices=STARTS, default="screen",
                        help="where the chains start: each leg's mode from the screen, whose Laplace covariance is "
                             "also the metric (default); the classical least-squares identification; the prior median")
        sp.add_argument("--adapt-metric", action="store_true",
                        help="with --start screen, adapt the metric in warm-up too (by default the screen's is kept)")
        sp.add_argument("--no-delay-evidence", dest="delay_evidence", action="store_false",
                        help="with --start screen, skip weighing each leg's delays by a Laplace approximation per "
                             "delay (11 optimisations per leg: the screen restarts at the best delay where it missed "
                             "it, and the chains' P(d) is compared with it in a warning)")
        sp.add_argument("--no-mode-jumps", dest="mode_jumps", action="store_false",
                        help="with the delays weighed, do not follow each NUTS transition with Metropolis-Hastings "
                             "jumps between a leg's delay modes (which NUTS alone does not cross)")

    def sim_options(sp, minutes_default):
        sp.add_argument("--minutes", type=float, default=minutes_default, help="length of each trial [min]")
        sp.add_argument("--seed", type=int, default=0)
        sp.add_argument("--effects", default="", help="hidden effects to switch on, comma-separated")
        sp.add_argument("--twitch-cv", type=float, default=TWITCH_CV, metavar="CV",
                        help=f"the twitches' coefficient of variation from pulse to pulse (default {TWITCH_CV:g}, "
                             "the paper's Table IV; 0: equal twitches)")
        sp.add_argument("--legs", default=None, help="legs, comma-separated (default: the paper's five)")

    s = sub.add_parser("simulate", help="simulate the paper's cohort into the interchange format")
    s.add_argument("--out", required=True)
    sim_options(s, 5.0)
    s.add_argument("--trials", default="1,2,3", help="trial numbers, comma-separated")
    s.add_argument("--sampling-period-ms", type=float, default=10.0,
                   help="the recordings' sampling period [ms], a whole number from 1 to 32 (default: the paper's 10)")
    s.set_defaults(func=cmd_simulate)

    k = sub.add_parser("check", help="read recordings as every command does: every problem at once, or a row per "
                                     "trial and what identify and fit can do with each leg")
    k.add_argument("data", help="interchange folder or .nc cohort file")
    k.add_argument("--out", default=None, help="also write recordings.csv and .md, a figure per trial and summary.json here")
    k.add_argument("--trial", type=int, default=1, help="the identification trial to judge (identify's --trial, default 1)")
    k.set_defaults(func=cmd_check)

    c = sub.add_parser("convert", help="interchange folder <-> NetCDF file, losslessly (or resampled)")
    c.add_argument("src")
    c.add_argument("dst")
    c.add_argument("--resample", type=float, default=None, metavar="PERIOD_S",
                   help="resample every trial to this period [s] (anti-aliased; irregular time stamps allowed)")
    c.add_argument("--repair-artefacts", action="store_true",
                   help="replace the samples a stimulation artefact holds at each pulse (found as the reader warns) "
                        "by a straight line between their neighbours")
    c.set_defaults(func=cmd_convert)

    i = sub.add_parser("identify", help="classical identification as the paper (Tables I-IV)")
    i.add_argument("data", help="interchange folder or .nc cohort file")
    i.add_argument("--out", required=True)
    i.add_argument("--trial", type=int, default=1, help="identification trial (default 1, as the paper)")
    i.add_argument("--passive-objective", choices=("auto", "acceleration", "angle"), default="auto",
                   help="fit the passive system of pendulum tests to their angle (a free run: output error) or to "
                        "the acceleration (eq. 8 on each sample); auto: the angle for pendulum tests, the "
                        "acceleration on the quiet samples between pulses")
    i.add_argument("--gravity-offset", action="store_true",
                   help="also identify the angle gravity acts about (a shank resting off angle 0, or an angle zeroed "
                        "off it; from the pendulum tests or the quiet samples between twitches)")
    i.set_defaults(func=cmd_identify)

    e = sub.add_parser("evaluate", help="k-step-ahead prediction errors J (Table V), sign tests, Figs. 5-6")
    e.add_argument("data", help="interchange folder or .nc cohort file")
    e.add_argument("--out", required=True)
    e.add_argument("--identified", default="", help="output folder of `quadshank identify` (default: identify now)")
    e.add_argument("--fit", action="append", metavar="DIR",
                   help="fit folder of `quadshank fit` (repeat for several models): evaluate the posterior, "
                        "with 90 %% bands and PSIS-LOO, instead of identifying")
    e.add_argument("--draws", type=int, default=200, help="posterior draws per fit to evaluate (default 200)")
    e.add_argument("--band-mcse", type=float, default=None, metavar="DEG",
                   help="choose the draws and the start stride so that the ends of the bands of the mean over legs "
                        "carry at most this Monte Carlo standard error (e.g. 0.05); --draws and --start-stride are "
                        "then unused")
    e.add_argument("--start-stride", type=int, default=1, metavar="K",
                   help="posterior J from every K-th start sample (default 1: all, as eq. 12)")
    e.set_defaults(func=cmd_evaluate)

    f = sub.add_parser("fit", help="hierarchical Bayesian fit (NUTS) of one model across legs")
    f.add_argument("data", help="interchange folder or .nc cohort file")
    f.add_argument("--model", choices=list(FIT_MODELS), default="model3",
                   help="the model; passive: the pendulum alone, for pendulum tests (default model3)")
    f.add_argument("--add-effect", action="append", metavar="NAME", help="extend the model by a registered effect")
    f.add_argument("--likelihood", choices=("auto", "acceleration", "angle"), default="auto",
                   help="what the likelihood compares: the equivalent acceleration (equation error, every model) or "
                        "the angle of runs from the measured state (output error: free swings for --model passive, "
                        "1-s shooting segments for a model with a muscle and no delay or noise effect); auto "
                        "(default): the angle for --model passive, the acceleration otherwise")
    f.add_argument("--precision", choices=PRECISIONS, default=FitSettings.precision,
                   help="the sampled density's precision: mixed (default: each sample's terms at the data's single "
                        "precision, their sums in double) or double throughout; the angle likelihood is always double")
    f.add_argument("--trials", default="1", help="identification trials, comma-separated (default 1, as the paper)")
    f.add_argument("--legs", default=None, help="legs, comma-separated (default: all in the data)")
    f.add_argument("--chains", type=int, default=4)
    f.add_argument("--warmup", type=int, default=None,
                   help=f"warm-up draws per chain (default {FIXED_LENGTHS[0]}; {TARGET_LENGTHS[0]} with --target-ess)")
    f.add_argument("--draws", type=int, default=None,
                   help=f"draws per chain (default {FIXED_LENGTHS[1]}); with --target-ess the size of each block "
                        f"(default {TARGET_LENGTHS[1]})")
    f.add_argument("--target-ess", type=int, default=None, metavar="N",
                   help="draw in blocks until bulk and tail ESS reach N for every parameter and R-hat passes, "
                        "or until --time-limit; the summary says which")
    f.add_argument("--time-limit", type=float, default=FitSettings.time_limit_s, metavar="SECONDS",
                   help="with --target-ess: begin no block that would end later than this after the start "
                        f"(default {FitSettings.time_limit_s:.0f})")
    f.add_argument("--seed", type=int, default=0)
    f.add_argument(
        "--delay-from",
        default="",
        metavar="FITDIR",
        help="take the delay prior from another fit's delay posterior (the paper took d from model 2)",
    )
    start_options(f)
    f.add_argument("--max-tree-depth", type=int, default=8, help="NUTS tree depth limit (at most 2^depth - 1 leapfrog steps a draw)")
    _target_accept_option(f)

    f.add_argument("--chain-method", choices=("auto", "vectorized", "sequential", "parallel"), default=FitSettings.chain_method,
                   help="run the chains as one batched program (faster on small data), one after another "
                        "(faster on large data: 1.4x at 5 legs x 5 min), or each on its own JAX device (several "
                        "GPUs, or CPU devices from XLA_FLAGS=--xla_force_host_platform_device_count=N); auto "
                        f"(default): parallel where there is a device per chain and no --target-ess, else sequential from "
                        f"{SEQUENTIAL_FROM_SAMPLES} compared samples on; the posterior is the same")
    f.add_argument("--out", required=True)
    f.set_defaults(func=cmd_fit)

    rc = sub.add_parser("recovery", help="coverage of the posterior intervals on data simulated from the fitted model")
    rc.add_argument("--models", default="model1,model2,model3", help="models, comma-separated")
    rc.add_argument("--seeds", default="0,1,2", help="simulation and sampling seeds, comma-separated")
    rc.add_argument("--legs", default=None, help="legs, comma-separated (default: the paper's five)")
    rc.add_argument("--add-effect", action="append", metavar="NAME", help="extend every fitted model by an effect")
    rc.add_argument("--truth-effects", default=None, metavar="A,B",
                    help="effects in the simulated truth (default: the added ones; '' for none)")
    rc.add_argument("--minutes", type=float, default=1.0, help="length of trial 1 [min]")
    rc.add_argument("--chains", type=int, default=2)
    rc.add_argument("--warmup", type=int, default=500)
    rc.add_argument("--draws", type=int, default=500)
    start_options(rc)
    rc.add_argument("--out", required=True)
    rc.set_defaults(func=cmd_recovery)

    lc = sub.add_parser(
        "likelihood-check",
        help="calibration of the likelihood alone: maximum likelihood on noise replicates of a matching truth",
    )
    lc.add_argument("--models", default="model1,model2,model3", help="models, comma-separated")
    lc.add_argument("--seeds", default="0", help="simulation seeds (one trajectory per leg each), comma-separated")
    lc.add_argument("--legs", default=None, help="legs, comma-separated (default: the paper's five)")
    lc.add_argument("--minutes", type=float, default=1.0, help="length of trial 1 [min]")
    lc.add_argument("--replicates", type=int, default=100, help="noise replicates per trajectory")
    lc.add_argument("--out", required=True)
    lc.set_defaults(func=cmd_likelihood_check)

    r = sub.add_parser("reproduce", help="simulate, identify, evaluate: the paper end to end")
    r.add_argument("--out", required=True)
    sim_options(r, 5.0)
    r.set_defaults(func=cmd_reproduce)

    dg = sub.add_parser("diagnose", help="which effect is missing from a fitted model: ranking with evidence, residual plots")
    dg.add_argument("fitdir", help="fit folder of `quadshank fit`")
    dg.add_argument("--data", default="", help="the fit's data (default: the folder or file the fit records)")
    dg.add_argument("--effects", default="", help="candidate effects, comma-separated (default: every registered candidate)")
    dg.add_argument("--confirm", type=int, nargs="?", const=1, default=0, metavar="N",
                    help="refit the N best candidates that clear the screen's bar (default 1) with NUTS, with the fit's "
                         "settings, and give the verdict under NUTS")
    _starts_option(dg)
    dg.add_argument("--out", required=True)
    dg.set_defaults(func=cmd_diagnose)

    dc = sub.add_parser("discover", help="the modelling loop in one command: diagnose, add the leading effect, repeat")
    dc.add_argument("data", help="interchange folder or .nc cohort file")
    dc.add_argument("--model", choices=list(FIT_MODELS), default="model3s",
                    help="the model the loop starts from (default model3s; passive for pendulum tests)")
    dc.add_argument("--trials", default="1", help="identification trials, comma-separated (default 1)")
    dc.add_argument("--legs", default=None, help="legs, comma-separated (default: all in the data)")
    dc.add_argument("--effects", default="", help="candidate effects, comma-separated (default: every registered candidate)")
    dc.add_argument("--max-rounds", type=int, default=3)
    dc.add_argument("--confirm", action="store_true",
                    help="confirm with hierarchical NUTS: fit the start model, refit each round's leader before adding it "
                         "(the loop goes on only while NUTS agrees), compare the first and last fits (J, PSIS-LOO, residuals)")
    dc.add_argument("--chains", type=int, default=2, help="with --confirm (default 2)")
    dc.add_argument("--target-ess", type=int, default=CONFIRM_TARGET_ESS, metavar="N",
                    help="with --confirm: each NUTS fit draws in blocks until bulk and tail ESS reach N for every "
                         f"parameter and R-hat passes, or until --time-limit (default {CONFIRM_TARGET_ESS}; "
                         "0: a fixed --warmup and --draws)")
    dc.add_argument("--time-limit", type=float, default=FitSettings.time_limit_s, metavar="SECONDS",
                    help="with --confirm and --target-ess: each fit begins no block that would end later than this "
                         f"after its start (default {FitSettings.time_limit_s:.0f})")
    dc.add_argument("--warmup", type=int, default=None,
                    help=f"with --confirm: warm-up draws per chain (default {TARGET_LENGTHS[0]}; "
                         f"{CONFIRM_FIXED_LENGTHS[0]} with --target-ess 0)")
    dc.add_argument("--draws", type=int, default=None,
                    help=f"with --confirm: the size of each block of draws per chain (default {TARGET_LENGTHS[1]}); "
                         f"with --target-ess 0 the draws per chain (default {CONFIRM_FIXED_LENGTHS[1]})")
    _target_accept_option(dc, "with --confirm: ")
    dc.add_argument("--seed", type=int, default=0, help="with --confirm")
    _starts_option(dc)
    dc.add_argument("--out", required=True)
    dc.set_defaults(func=cmd_discover)

    cp = sub.add_parser("compare", help="two fits side by side: J bands per horizon, PSIS-LOO, figures")
    cp.add_argument("fit_a")
    cp.add_argument("fit_b")
    cp.add_argument("--data", default="", help="the fits' data (default: what fit A records)")
    cp.add_argument("--draws", type=int, default=200)
    cp.add_argument("--start-stride", type=int, default=1)
    cp.add_argument("--out", required=True)
    cp.set_defaults(func=cmd_compare)

    rp = sub.add_parser("report", help="credible-parameter report of a fit: HTML page per subject, cohort index, CSV/JSON per leg")
    rp.add_argument("fitdir", help="fit folder of `quadshank fit`")
    rp.add_argument("--data", default="", help="the fit's data (default: the folder or file the fit records)")
    rp.add_argument("--evaluation", default="", metavar="EVALDIR",
                    help="output folder of `quadshank evaluate --fit` to take J's bands from (default: compute them)")
    rp.add_argument("--diagnosis", default="", metavar="DIAGDIR",
                    help="output folder of `quadshank diagnose` or `discover` whose ranking to show")
    rp.add_argument("--draws", type=int, default=50, help="posterior draws for J and the prediction bands (default 50)")
    rp.add_argument("--start-stride", type=int, default=10, metavar="K",
                    help="J from every K-th start sample when computed here (default 10)")
    rp.add_argument("--out", required=True)
    rp.set_defaults(func=cmd_report)

    pr = sub.add_parser("predict", help="the angle a planned stimulation sequence would produce, per fitted leg, "
                                        "with posterior bands")
    pr.add_argument("fitdir", help="fit folder of `quadshank fit`")
    pr.add_argument("--stimulation", dest="plan", required=True, metavar="PLAN.csv",
                    help="the plan: a CSV with time_s,stimulation at the fit's sampling period, or with "
                         "time_s and the stimulator's columns (pulse_width_us and/or current_mA) of legs "
                         "fitted on them")
    pr.add_argument("--angle0", type=float, default=None,
                    help="start angle [deg] as the goniometer reads it (default: each posterior draw's rest, where "
                         "its shank settles without stimulation)")
    pr.add_argument("--velocity0", type=float, default=0.0, help="start velocity [deg/s] (default 0; with --angle0)")
    pr.add_argument("--legs", default=None, help="legs, comma-separated (default: every fitted leg)")
    pr.add_argument("--draws", type=int, default=200, help="posterior draws (default 200)")
    pr.add_argument("--seed", type=int, default=0)
    pr.add_argument("--out", required=True)
    pr.set_defaults(func=cmd_predict)

    d = sub.add_parser("demo", help="the main job on the built-in simulated cohort: reproduce, fit, evaluate, "
                                    "diagnose, report (writes results/demo)")
    d.add_argument("--out", default="results/demo")
    sim_options(d, 1.5)
    d.add_argument("--hide", default="torque_angle_peak", metavar="EFFECT[,EFFECT]",
                   help="effects hidden in the legs the loop is shown on, which the diagnosis should find "
                        "(default torque_angle_peak; none: nothing hidden)")
    d.add_argument("--chains", type=int, default=2)
    d.add_argument("--warmup", type=int, default=150)
    d.add_argument("--draws", type=int, default=100, help="draws per chain in each block (default 100)")
    d.add_argument("--target-ess", type=int, default=200, metavar="N",
                   help="the fit draws blocks until R-hat and ESS N pass (default 200; 0: one block, no target)")
    d.add_argument("--time-limit", type=float, default=150.0, metavar="SECONDS",
                   help="begin no block of the fit that would end later than this after its start (default 150)")
    d.add_argument("--max-tree-depth", type=int, default=5,
                   help="NUTS tree depth: at most 2^depth - 1 leapfrog steps a draw (quadshank fit: 8)")
    d.set_defaults(func=cmd_demo)
    for name, sp in sub.choices.items():
        sp.add_argument("--overwrite", action="store_true",
                        help="write into a folder that holds something else (files of the same names are "
                             "replaced, nothing else is touched)")
        if name in EFFECT_USERS:
            sp.add_argument("--effects-file", action="append", metavar="FILE.py", default=[],
                            help="a Python file defining your own effects (@register_effect), loaded first; "
                                 "a fit records it, and later commands import it again from there")
    return p


def _error_text(exc: BaseException) -> str:
    """An expected error as the text after ``quadshank: error:`` (its first line names the file)."""
    if isinstance(exc, KeyError) and exc.args:
        return str(exc.args[0])
    if isinstance(exc, OSError) and exc.filename and exc.strerror:
        return f"{exc.filename}: {exc.strerror}"
    return str(exc) or type(exc).__name__


#: matplotlib's warning that the font lacks a character ("Glyph 24739 (\\N{CJK ...}) missing from font(s) ...").
_MISSING_GLYPH = re.compile(r"Glyph \d+ \(\\N\{(.*?)\}\) missing from font")


def _one_line_warnings(previous):
    """A ``warnings.showwarning`` that prints a quadshank warning about the data as one line,
    ``quadshank: warning: ...``, and hands any other warning to ``previous``."""

    missing: set[str] = set()

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        glyph = _MISSING_GLYPH.match(str(message))
        if issubclass(category, DataWarning):
            write_above_bars(f"quadshank: warning: {message}")
        elif glyph:  # matplotlib warns at every figure; one line per character is enough
            if glyph.group(1) not in missing:
                missing.add(glyph.group(1))
                try:
                    char = repr(unicodedata.lookup(glyph.group(1)))
                except KeyError:
                    char = glyph.group(1)
                write_above_bars(f"quadshank: warning: the figures' font has no {char} ({glyph.group(1)}, in a "
                                 "subject's name?); it shows as a box")
        else:
            previous(message, category, filename, lineno, file, line)

    return show


def main(argv: list[str] | None = None) -> int:
    """Run one command; returns its exit code (0, 2 for an error, 3 for a fit that failed its
    checks, 130 when interrupted).  Ctrl-C and SIGTERM are honoured at the latest when the step
    running then ends (:mod:`quadshank.common._interrupt`)."""
    with handling_interrupts():
        return _main(argv)


def _main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = argv
    # the command line draws only into files: no window, whatever the display
    matplotlib.use("Agg")
    use_compilation_cache()  # a program compiled by an earlier command is loaded, not compiled again
    mark = None
    try:
        refuse_lone_options(parser, args)
        if args.command == "convert":
            if not args.dst.strip():
                raise ValueError("convert: give the destination (a folder, or a file ending in .nc)")
            if Path(args.dst).suffix.lower() != ".nc":  # a folder of recordings
                mark = prepare_output(Path(args.dst), "convert", _inputs(args), args.overwrite)
        elif hasattr(args, "out") and not (args.command in OPTIONAL_OUT and args.out is None):
            if not (args.out or "").strip():
                raise ValueError("--out: give the folder for the results (an empty name is the current folder)")
            mark = prepare_output(Path(args.out), args.command, _inputs(args), args.overwrite)
        with warnings.catch_warnings():
            warnings.simplefilter("always", DataWarning)
            warnings.showwarning = _one_line_warnings(warnings.showwarning)
            if args.command in EFFECT_USERS:
                load_entry_point_effects()
                for path in args.effects_file:
                    _say(args, f"effects from {path}: {', '.join(load_effects_file(path))}")
            failed = True
            try:
                code = int(args.func(args) or 0)
                failed = False
            finally:
                if mark is not None:
                    mark(failed)
            if interrupt_requested():  # asked for while a compiled step ran (NUTS's sampling), seen when it was done
                print("quadshank: interrupted; the step running then was finished (a fit's draws are complete and "
                      "saved), and what the command wrote is complete", file=sys.stderr)
                return 130
            return code
    except KeyboardInterrupt:
        print("quadshank: interrupted; files already written are complete, nothing half-written", file=sys.stderr)
        return 130
    except EXPECTED_ERRORS as exc:
        if os.environ.get("QUADSHANK_DEBUG"):
            raise
        print(f"quadshank: error: {_error_text(exc)}", file=sys.stderr)
        return 2


def run() -> None:
    """The ``quadshank`` console script: :func:`main`, then exit with its code.  An interrupted run
    leaves at once (``os._exit``) once its output is settled and its lines flushed: tearing the
    interpreter down while XLA's threads still run the interrupted work can crash it (a
    segmentation fault, exit 139, after the "interrupted" line)."""
    code = main()
    if code == 130:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":  # pragma: no cover
    run()
