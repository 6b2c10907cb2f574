"""quadshank: identification of electrically stimulated quadriceps–shank dynamics."""

from ._cohort import Cohort, Trial, derive_velocity, leg_key

__version__ = "0.1.0"

__all__ = ["Cohort", "Trial", "derive_velocity", "leg_key", "__version__"]
