"""The package's shape: one-way imports between the stages, a public API, no work at import.

The layers contract lives in ``pyproject.toml`` ([tool.importlinter]) and is run here with
import-linter, on the package as it is and on a copy with one upward import added.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"
SUBPACKAGES = ("common", "data", "model", "inference", "evaluation", "loop", "outputs", "commands")
LINT = Path(sys.executable).with_name("lint-imports")


def _lint(config: Path, src: Path, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(src)}
    return subprocess.run([str(LINT), "--config", str(config), "--no-cache"], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)


def test_the_import_contracts_are_kept():
    run = _lint(ROOT / "pyproject.toml", SRC, ROOT)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "2 kept, 0 broken" in run.stdout


@pytest.mark.parametrize(
    ("module", "line", "broken"),
    [
        ("data/_cohort.py", "from ..inference import _nuts  # noqa", "quadshank.data is not allowed to import quadshank.inference"),
        ("inference/_screen.py", "from . import _nuts  # noqa", "No cycles are allowed in quadshank.inference"),
    ],
)
def test_an_upward_import_or_a_cycle_breaks_a_contract(tmp_path, module, line, broken):
    """The same contracts on a copy of the package with one import added: the layers contract
    refuses data importing inference, the acyclic-siblings one a module importing its importer."""
    shutil.copytree(SRC / "quadshank", tmp_path / "src" / "quadshank", ignore=shutil.ignore_patterns("__pycache__"))
    path = tmp_path / "src" / "quadshank" / module
    text = path.read_text()
    path.write_text(text.replace("from __future__ import annotations\n", f"from __future__ import annotations\n\n{line}\n", 1))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    run = _lint(tmp_path / "pyproject.toml", tmp_path / "src", tmp_path)
    assert run.returncode != 0
    assert broken in run.stdout, run.stdout


def _private_imports(source: str) -> list[str]:
    """Imports of a private quadshank module or name in Python source."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "quadshank":
            parts = node.module.split(".")
            names = [a.name for a in node.names]
            if any(p.startswith("_") for p in parts) or any(n.startswith("_") and n != "__version__" for n in names):
                found.append(f"from {node.module} import {', '.join(names)}")
        elif isinstance(node, ast.Import):
            found += [a.name for a in node.names if a.name.startswith("quadshank") and "._" in a.name]
        elif isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            base = node.value
            while isinstance(base, ast.Attribute):
                base = base.value
            if isinstance(base, ast.Name) and base.id in ("quadshank", "qs"):
                found.append(ast.unparse(node))
    return found


@pytest.mark.parametrize("notebook", sorted((ROOT / "notebooks").glob("[a-z]_*.py")), ids=lambda p: p.stem)
def test_notebooks_use_the_public_api_only(notebook):
    assert _private_imports(notebook.read_text()) == []


def test_the_private_import_check_sees_one():
    assert _private_imports("from quadshank.inference._nuts import fit\nimport quadshank.model._model\n")
    assert _private_imports("import quadshank as qs\nqs.model._model\n")
    assert not _private_imports("from quadshank.inference import fit\nfrom quadshank import __version__\n")


def _public(module):
    for name in module.__all__:
        yield name, getattr(module, name)


@pytest.mark.parametrize("name", ("quadshank",) + tuple(f"quadshank.{s}" for s in SUBPACKAGES))
def test_every_public_name_exists_and_is_documented(name):
    module = importlib.import_module(name)
    assert module.__doc__, f"{name} has no docstring"
    undocumented = [n for n, obj in _public(module) if (inspect.isfunction(obj) or inspect.isclass(obj)) and not inspect.getdoc(obj)]
    assert undocumented == []


def test_the_subpackages_are_the_whole_package():
    """Every module sits in a stage's subpackage (or is the command line), so the contract sees all of it."""
    top = sorted(p.name for p in (SRC / "quadshank").iterdir() if p.suffix == ".py" or (p / "__init__.py").exists())
    assert top == sorted(["__init__.py", "cli.py", *SUBPACKAGES])


def test_importing_quadshank_does_no_work(tmp_path):
    """No backend switch, no umask read, no file written, no array computed at import."""
    script = textwrap.dedent("""
        import os, sys
        calls = []
        real = os.umask
        os.umask = lambda m: (calls.append(m), real(m))[1]
        import matplotlib
        before = matplotlib.rcParams._get_backend_or_none()
        import quadshank, quadshank.cli, quadshank.commands
        assert matplotlib.rcParams._get_backend_or_none() == before, "the backend was switched"
        assert not calls, "the umask was read"
        import jax
        print("ok")
    """)
    env = {k: v for k, v in os.environ.items() if k != "MPLBACKEND"}
    run = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "ok"
    assert list(tmp_path.iterdir()) == []


def test_no_function_level_imports_of_the_package():
    """Imports of quadshank's own modules sit at the top of each module: the layers make them one-way."""
    inner = []
    for path in (SRC / "quadshank").rglob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                inner += [f"{path.relative_to(SRC)}:{sub.lineno}" for sub in ast.walk(node)
                          if isinstance(sub, ast.ImportFrom) and (sub.level or (sub.module or "").startswith("quadshank"))]
    assert inner == []


def test_fit_orchestration_has_no_private_numpyro_hook():
    """The sampler is numpyro's NUTS as published: starts and metric go in through its public arguments.
    The one kernel built on it, the jumps between delay modes, adds Metropolis–Hastings moves after
    NUTS's own transitions and hands its start and metric to NUTS unchanged."""
    import inspect

    from quadshank.inference._jumps import ModeJumpNUTS

    kernels = []
    for path in (SRC / "quadshank").rglob("*.py"):
        kernels += [(path.name, m) for m in re.findall(r"class (\w+)\((?:NUTS|HMC|MCMCKernel)\)", path.read_text())]
    assert kernels == [("_jumps.py", "ModeJumpNUTS")]
    own = {k for k, v in vars(ModeJumpNUTS).items() if callable(v) and not k.startswith("__")}
    assert own == {"init", "sample"}
    init = inspect.getsource(ModeJumpNUTS.init)
    assert "super().init(rng_key, num_warmup, init_params, model_args, model_kwargs)" in init
    assert "super().sample(" in inspect.getsource(ModeJumpNUTS.sample)
    source = "\n".join(p.read_text() for p in (SRC / "quadshank").rglob("*.py"))
    assert "_init_state" not in source


def test_randomness_comes_from_named_streams_of_one_seed():
    """No integer offsets of a seed (seed + 1, seed + i) anywhere: streams are split by name."""
    source = "\n".join(p.read_text() for p in (SRC / "quadshank").rglob("*.py"))
    assert not re.search(r"\bseed\s*\+\s*\w", source)
    from quadshank.common import jax_key, numpy_rng

    a, b = numpy_rng(3, "x").random(4), numpy_rng(3, "y").random(4)
    assert not (a == b).any() and (numpy_rng(3, "x").random(4) == a).all()
    assert (jax_key(3, "delays", 1) != jax_key(3, "delays", 2)).any()
