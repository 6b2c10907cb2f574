"""Typed results: what a stage hands the next, and its ``summary.json`` form.

A result is a dataclass deriving from :class:`Result`.  Its JSON form carries ``schema``
(``quadshank/<kind>``) and ``schema_version`` besides its fields; :meth:`Result.read` reads
a folder's ``summary.json`` back into the type and refuses another kind, another version
or a summary without them, naming the file.  The fields are documented in
``docs/results-schema.md``.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, ClassVar

from ._io import read_json, write_json

__all__ = ["SCHEMA_VERSION", "Result", "SchemaError"]

#: The version of every result's JSON form; a reader refuses any other.
SCHEMA_VERSION = 1


class SchemaError(ValueError):
    """A summary that is not the result it should be: another kind, another version, a field missing."""


def _optional(field: dataclasses.Field) -> bool:
    return field.default is not dataclasses.MISSING or field.default_factory is not dataclasses.MISSING


@dataclasses.dataclass
class Result:
    """Base of the typed results.  Subclasses set :attr:`KIND` and declare their fields; a field
    whose metadata says ``{"json": False}`` (a live object) is left out of the JSON form, and an
    optional field (one with a default) that is None is left out too: a part the run did not make."""

    KIND: ClassVar[str] = ""

    @classmethod
    def schema(cls) -> str:
        return f"quadshank/{cls.KIND}"

    def to_json(self) -> dict[str, Any]:
        body = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if f.metadata.get("json", True) and not (getattr(self, f.name) is None and _optional(f))}
        return {"schema": self.schema(), "schema_version": SCHEMA_VERSION, **body}

    @classmethod
    def from_json(cls, doc: dict, source: str = "summary.json"):
        """The result ``doc`` holds (the JSON form of :meth:`to_json`)."""
        if not isinstance(doc, dict):
            raise SchemaError(f"{source}: not a quadshank summary (a JSON object is expected)")
        if doc.get("schema") != cls.schema():
            found = doc.get("schema")
            raise SchemaError(
                f"{source}: not a {cls.KIND} summary (its schema is {found!r})" if found else
                f"{source}: a summary without a schema (written by an older quadshank): run the command again"
            )
        if doc.get("schema_version") != SCHEMA_VERSION:
            raise SchemaError(f"{source}: schema version {doc.get('schema_version')!r}; this quadshank reads version "
                              f"{SCHEMA_VERSION}: run the command again")
        fields = {f.name: f for f in dataclasses.fields(cls) if f.metadata.get("json", True)}
        required = [n for n, f in fields.items() if not _optional(f)]
        missing = [n for n in required if n not in doc]
        if missing:
            raise SchemaError(f"{source}: the {cls.KIND} summary lacks {', '.join(missing)}")
        return cls(**{n: doc[n] for n in fields if n in doc})

    @classmethod
    def read(cls, folder: str | os.PathLike):
        """The result in ``folder/summary.json``."""
        path = Path(folder) / "summary.json"
        return cls.from_json(read_json(path), str(path))

    def write(self, folder: str | os.PathLike) -> Path:
        """Write ``folder/summary.json`` atomically (last, by the commands: a folder with one is complete)."""
        return write_json(Path(folder) / "summary.json", self.to_json())
