"""Data: validated cohorts of recorded trials, the interchange format, the simulator, the paper's numbers.

A :class:`Cohort` is what every later stage reads; :func:`load_cohort` takes an interchange
folder or a NetCDF file, :func:`simulate_cohort` makes the built-in simulated cohort.
"""

from ._cohort import (
    ACCELERATION_WINDOW_S,
    VELOCITY_WINDOW,
    Cohort,
    Trial,
    derive_acceleration,
    derive_velocity,
    leg_key,
)
from ._artefacts import repair_stimulation_artefacts, stimulation_artefacts
from ._interchange import (
    DEFAULT_SAMPLING_PERIOD_S,
    DataWarning,
    MANIFEST_NAME,
    InterchangeError,
    Problem,
    convert,
    load_cohort,
    plausibility,
    parse_number,
    read_interchange,
    read_netcdf,
    StimulationPlan,
    charge_scales,
    check_cohort,
    read_plan,
    read_stimulation_plan,
    trim,
    write_interchange,
)
from ._paper import (
    HORIZON_MS,
    HORIZONS,
    HORIZONS_MS,
    LEGS,
    MAX_DELAY,
    SAMPLING_PERIOD_S,
    TABLE_I,
    TABLE_II,
    TABLE_III,
    TABLE_IV,
    TABLE_V,
    TWITCH_SAMPLES,
)
from ._resample import resample_cohort, resample_trial
from ._simulate import (
    EFFECTS,
    PASSIVE_TRUTH,
    default_truth,
    simulate_cohort,
    simulate_pendulum_test,
    simulate_response,
    stimulation_sequence,
    write_truth,
)

__all__ = [
    "Cohort", "Trial", "derive_velocity", "derive_acceleration", "leg_key", "VELOCITY_WINDOW", "ACCELERATION_WINDOW_S",
    "InterchangeError", "Problem", "DataWarning", "plausibility", "check_cohort", "read_interchange", "read_netcdf", "write_interchange", "load_cohort", "convert",
    "parse_number", "trim", "read_stimulation_plan", "read_plan", "StimulationPlan", "charge_scales", "resample_trial", "resample_cohort",
    "stimulation_artefacts", "repair_stimulation_artefacts",
    "MANIFEST_NAME", "DEFAULT_SAMPLING_PERIOD_S",
    "EFFECTS", "PASSIVE_TRUTH", "default_truth", "simulate_cohort", "simulate_pendulum_test", "simulate_response", "stimulation_sequence",
    "write_truth",
    "SAMPLING_PERIOD_S", "HORIZONS", "HORIZON_MS", "HORIZONS_MS", "MAX_DELAY", "TWITCH_SAMPLES", "LEGS",
    "TABLE_I", "TABLE_II", "TABLE_III", "TABLE_IV", "TABLE_V",
]  # fmt: skip
