"""A user's own effects, from a Python file or an installed package, and where each came from.

An effect is registered by importing the code that defines it (``@register_effect``).  Within
one Python process that is the user's own import; across processes (the command line, a fit
reloaded tomorrow) quadshank must find the code again:

- :func:`load_effects_file` imports a Python file (``--effects-file my_effects.py``) and
  returns the effects it registered;
- :func:`load_entry_point_effects` imports what installed packages offer under the entry-point
  group :data:`ENTRY_POINT_GROUP` (``[project.entry-points."quadshank.effects"]`` in their
  ``pyproject.toml``: a module, or the effect class itself);
- :func:`effect_origin` says where a registered effect came from: its module, its file and a
  hash of its class's source.  A fit records it for every effect that is not built in, and
  :func:`ensure_effects` (run when a fit is loaded) imports the recorded file again where the
  effect is not registered, and refuses, naming the effect and the file, when the source is
  not the one the fit was made with.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import importlib.util
import inspect
import sys
from pathlib import Path

from . import _effects
from ._effects import Effect, register_effect

__all__ = ["load_effects_file", "load_entry_point_effects", "effect_origin", "ensure_effects", "ENTRY_POINT_GROUP",
           "EffectSourceError"]

#: The entry-point group under which installed packages offer effects.
ENTRY_POINT_GROUP = "quadshank.effects"
_BUILT_IN_MODULE = "quadshank.model._effects"


class EffectSourceError(ValueError):
    """A user effect that cannot be found again, or whose source is not the one recorded."""


def _source_hash(cls: type) -> str | None:
    try:
        text = inspect.getsource(cls)
    except (OSError, TypeError):
        return None
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def effect_origin(name: str) -> dict | None:
    """Where the registered effect ``name`` came from: ``{"module", "file", "source_sha256"}``
    (the hash of its class's source), or None for a built-in effect."""
    cls = _effects._REGISTRY[name]
    if cls.__module__ == _BUILT_IN_MODULE:
        return None
    file = inspect.getsourcefile(cls) if not cls.__module__.startswith("__main__") else None
    return {"module": cls.__module__, "file": str(Path(file).resolve()) if file else None,
            "source_sha256": _source_hash(cls)}


def load_effects_file(path) -> list[str]:
    """Import the Python file ``path``, registering the effects it defines; returns their names
    (in the order registered).  Importing the same file twice registers its effects again,
    from the file as it is now."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such effects file (a Python file defining @register_effect classes)")
    if path.suffix != ".py":
        raise ValueError(f"{path}: an effects file is a Python file ending in .py")
    resolved = path.resolve()
    module_name = "quadshank_user_effects_" + hashlib.sha256(str(resolved).encode()).hexdigest()[:12]
    before = dict(_effects._REGISTRY)
    spec = importlib.util.spec_from_file_location(module_name, resolved)
    module = importlib.util.module_from_spec(spec)
    sys.modules[module_name] = module  # dataclasses and inspect look the module up by name
    try:
        spec.loader.exec_module(module)
    except (Exception, SystemExit) as exc:  # a script's sys.exit() too: the file is not an effects module
        sys.modules.pop(module_name, None)
        _effects._REGISTRY.clear()  # what it registered before it failed is not kept
        _effects._REGISTRY.update(before)
        raise ValueError(f"{path}: the effects file failed to import: {type(exc).__name__}: {exc}") from exc
    found = [n for n, cls in _effects._REGISTRY.items() if before.get(n) is not cls]
    if not found:
        raise ValueError(f"{path}: defines no effect (decorate each with @register_effect)")
    return found


def load_entry_point_effects() -> list[str]:
    """Import every entry point of the group :data:`ENTRY_POINT_GROUP`; returns the effects they
    registered.  An entry point that fails to load is named in the error."""
    before = dict(_effects._REGISTRY)
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        try:
            obj = ep.load()
        except Exception as exc:
            raise ValueError(f"the effects of entry point {ep.name!r} ({ep.value}) failed to load: "
                             f"{type(exc).__name__}: {exc}") from exc
        if inspect.isclass(obj) and issubclass(obj, Effect) and obj.name not in _effects._REGISTRY:
            register_effect(obj)
    return [n for n, cls in _effects._REGISTRY.items() if before.get(n) is not cls]


def ensure_effects(names, origins: dict | None, where: str) -> None:
    """Make sure every effect in ``names`` is registered with the source ``origins`` records
    (``{name: effect_origin(name)}`` of the fit, built-ins left out).  An effect not yet
    registered is imported again from its recorded file; one whose source differs from the
    recorded hash is refused.  ``where``: what asks (for the message)."""
    origins = origins or {}
    for name in names:
        origin = origins.get(name)
        if name not in _effects._REGISTRY and origin and origin.get("file") and Path(origin["file"]).is_file():
            load_effects_file(origin["file"])
        if name not in _effects._REGISTRY:
            hint = (f"it came from {origin['file']}, which is not there any more" if origin and origin.get("file")
                    else "give the file that defines it with --effects-file")
            raise EffectSourceError(f"{where}: effect {name!r} is not registered; {hint}")
        if origin and origin.get("source_sha256"):
            now = _source_hash(_effects._REGISTRY[name])
            if now is not None and now != origin["source_sha256"]:
                raise EffectSourceError(
                    f"{where}: effect {name!r} has changed since the fit was made (its source hashes to {now}, "
                    f"the fit's to {origin['source_sha256']}; from {origin.get('file') or origin.get('module')}): "
                    "restore the version the fit used, or fit again")
