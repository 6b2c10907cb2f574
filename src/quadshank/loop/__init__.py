"""The modelling loop's numbers: candidate effects, their ranking by the evidence, the verdict.

Returns result objects and writes nothing; ``quadshank diagnose`` and ``discover``
(:mod:`quadshank.commands`) write them.
"""

from ._diagnose import (
    ELPD_SE_BAR,
    J_HORIZONS_MS,
    Diagnosis,
    Discovery,
    Ranking,
    candidates,
    j_draws,
    rank_effects,
    verdict_sentence,
)

__all__ = [
    "candidates", "rank_effects", "Ranking", "Diagnosis", "Discovery", "verdict_sentence", "j_draws", "ELPD_SE_BAR",
    "J_HORIZONS_MS",
]  # fmt: skip
