"""What every stage may use: atomic file writes, progress bars, the code's provenance.

Nothing here knows the model or the data; the other subpackages import it, never the reverse.
"""

from ._arrays import is_whole_number, stretches
from ._io import (
    atomic_path,
    atomic_write_bytes,
    atomic_write_text,
    read_json,
    save_figure,
    write_json,
)
from ._progress import progress_bar
from ._provenance import __version__, code_fingerprint, code_provenance
from ._random import jax_key, numpy_rng
from ._results import SCHEMA_VERSION, Result, SchemaError

__all__ = [
    "stretches", "is_whole_number",
    "atomic_path", "atomic_write_bytes", "atomic_write_text", "read_json", "write_json", "save_figure",
    "progress_bar", "code_fingerprint", "code_provenance", "__version__", "Result", "SchemaError", "SCHEMA_VERSION",
    "numpy_rng", "jax_key",
]  # fmt: skip
