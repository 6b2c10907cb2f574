"""quadshank: identification of electrically stimulated quadriceps–shank dynamics.

After Franken et al., IEEE Trans. Rehab. Eng. 1995.  Models are compositions of
effects (:class:`Effect`) run in JAX; classical identification follows the
paper's eqs. (8)–(11); predictions are scored by J_φ,p (eq. 12).
"""

from .data._cohort import Cohort, Trial, derive_velocity, leg_key
from .model._effects import (
    Damping,
    Darma,
    Effect,
    ExponentialElasticity,
    Gravity,
    LinearTorqueAngle,
    LinearTorqueVelocity,
    AngleDelay,
    Fatigue,
    HillTorqueVelocity,
    Param,
    PeakTorqueAngle,
    Potentiation,
    PulseContext,
    RecruitmentPower,
    StepContext,
    ZeroOrderActivation,
    get_effect,
    register_effect,
    registered_effects,
)
from .evaluation._prediction import evaluate_cohort, prediction_errors, predictions, sign_tests, table_v
from .inference._nuts import FitSettings, fit
from .inference._priors import build_model
from .inference._fitio import load_fit, save_fit, to_inference_data
from .inference._identify import IdentificationError, identify_cohort, identify_leg, identify_passive
from .data._interchange import InterchangeError, convert, load_cohort, read_interchange, write_interchange
from .model._model import Model, equivalent_acceleration, paper_model, passive_effects, predict_ahead, simulate_angles
from .data._simulate import EFFECTS, default_truth, simulate_cohort

from .common._provenance import __version__

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
