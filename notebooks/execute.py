"""Execute the notebooks from their plain-text sources and write the paired ``.ipynb``.

    python notebooks/execute.py                 # every notebook at full size, outputs kept
    python notebooks/execute.py b_posterior_analysis.py --small   # the test's size

Each ``notebooks/X.py`` (jupytext percent format) is the source; ``X.ipynb`` is
made from it, executed, and written with its outputs, so that it reads well on
a repository page.  ``make notebooks`` runs the first line.  The kernel is this
interpreter's (a kernelspec written to a temporary folder), whatever other
kernels the machine has.  Work files go to ``notebooks/_work/`` (not committed).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
KERNEL = "quadshank-notebooks"


def sources() -> list[Path]:
    """The notebook sources, in reading order."""
    return sorted(p for p in HERE.glob("[a-z]_*.py"))


def _kernelspec(root: Path) -> None:
    spec = root / "kernels" / KERNEL
    spec.mkdir(parents=True, exist_ok=True)
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "Python 3 (quadshank)",
        "language": "python",
    }))


def execute(source: str | Path, *, small: bool, cwd: str | Path, timeout: int = 1800):
    """Run one notebook source; returns the executed notebook (nbformat), raising on the first error.

    ``small`` sets ``QUADSHANK_NOTEBOOK_SMALL=1``, the size the notebooks' test uses.
    """
    import jupytext
    from nbclient import NotebookClient

    nb = jupytext.read(source)
    saved = {k: os.environ.get(k) for k in ("QUADSHANK_NOTEBOOK_SMALL", "JUPYTER_PATH", "MPLBACKEND")}
    with tempfile.TemporaryDirectory() as tmp:
        _kernelspec(Path(tmp))
        os.environ["JUPYTER_PATH"] = os.pathsep.join(filter(None, [tmp, saved["JUPYTER_PATH"]]))
        os.environ["QUADSHANK_NOTEBOOK_SMALL"] = "1" if small else "0"
        os.environ.pop("MPLBACKEND", None)  # the inline backend, whatever the caller uses
        try:
            client = NotebookClient(nb, timeout=timeout, kernel_name=KERNEL, resources={"metadata": {"path": str(cwd)}})
            client.execute()
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
    # saved with the usual kernel's name, not the temporary one that ran it
    nb.metadata["kernelspec"] = {"display_name": "Python 3", "language": "python", "name": "python3"}
    return nb


def last_json(nb) -> dict:
    """The JSON line the notebook's last code cell prints (its result, for the test)."""
    last = [c for c in nb.cells if c.cell_type == "code"][-1]
    text = "".join(o.get("text", "") for o in last.get("outputs", []) if o.get("output_type") == "stream")
    return json.loads(text.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", help="notebook sources (default: all)")
    ap.add_argument("--small", action="store_true", help="the test's size (the .ipynb is not written)")
    args = ap.parse_args(argv)
    import nbformat

    chosen = [HERE / Path(n).with_suffix(".py").name for n in args.names] if args.names else sources()
    missing = [p.name for p in chosen if not p.exists()]
    if missing:
        ap.error(f"no notebook source {', '.join(missing)} in {HERE} (there are: {', '.join(p.stem for p in sources())})")
    for src in chosen:
        t0 = time.perf_counter()
        print(f"{src.name}: running ({'small' if args.small else 'full'} size) ...", flush=True)
        nb = execute(src, small=args.small, cwd=HERE)
        print(f"{src.name}: {time.perf_counter() - t0:.0f} s; {json.dumps(last_json(nb))}", flush=True)
        if not args.small:
            out = src.with_suffix(".ipynb")
            tmp = out.with_suffix(".ipynb.tmp")
            nbformat.write(nb, tmp)
            os.replace(tmp, out)  # never a half-written notebook
    return 0


if __name__ == "__main__":
    sys.exit(main())
