"""quadshank: identification of electrically stimulated quadriceps–shank dynamics.

After Franken et al., IEEE Trans. Rehab. Eng. 1995.  Models are compositions of
effects (:class:`Effect`) run in JAX; classical identification follows the
paper's eqs. (8)–(11); predictions are scored by J_φ,p (eq. 12).

The subpackages are the pipeline's stages, each importing only those below it:
:mod:`quadshank.data` → :mod:`quadshank.model` → :mod:`quadshank.inference` →
:mod:`quadshank.evaluation` → :mod:`quadshank.loop` → :mod:`quadshank.outputs` →
:mod:`quadshank.commands`.  The names here are the ones most scripts need.
"""

from .common import __version__
from .data import (
    EFFECTS,
    Cohort,
    InterchangeError,
    Trial,
    convert,
    default_truth,
    derive_velocity,
    leg_key,
    load_cohort,
    read_interchange,
    simulate_cohort,
    write_interchange,
)
from .evaluation import evaluate_cohort, prediction_errors, predictions, sign_tests, table_v
from .inference import (
    FitSettings,
    IdentificationError,
    build_model,
    fit,
    identify_cohort,
    identify_leg,
    identify_passive,
    load_fit,
    save_fit,
    to_inference_data,
)
from .model import (
    AngleDelay,
    Damping,
    Darma,
    Effect,
    ExponentialElasticity,
    Fatigue,
    Gravity,
    HillTorqueVelocity,
    LinearTorqueAngle,
    LinearTorqueVelocity,
    Model,
    Param,
    PeakTorqueAngle,
    Potentiation,
    PulseContext,
    RecruitmentPower,
    StepContext,
    ZeroOrderActivation,
    equivalent_acceleration,
    get_effect,
    paper_model,
    passive_effects,
    predict_ahead,
    register_effect,
    registered_effects,
    simulate_angles,
)

__all__ = [
    "Cohort", "Trial", "derive_velocity", "leg_key",
    "Effect", "Param", "StepContext", "PulseContext", "register_effect", "registered_effects", "get_effect",
    "ZeroOrderActivation", "Darma", "LinearTorqueAngle", "LinearTorqueVelocity",
    "Damping", "Gravity", "ExponentialElasticity",
    "AngleDelay", "PeakTorqueAngle", "HillTorqueVelocity", "Fatigue", "Potentiation", "RecruitmentPower",
    "Model", "paper_model", "passive_effects", "equivalent_acceleration", "simulate_angles", "predict_ahead",
    "IdentificationError", "identify_leg", "identify_cohort", "identify_passive",
    "evaluate_cohort", "prediction_errors", "predictions", "sign_tests", "table_v",
    "InterchangeError", "read_interchange", "write_interchange", "load_cohort", "convert",
    "EFFECTS", "default_truth", "simulate_cohort",
    "FitSettings", "build_model", "fit", "to_inference_data", "save_fit", "load_fit",
    "__version__",
]  # fmt: skip
