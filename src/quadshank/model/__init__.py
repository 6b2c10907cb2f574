"""Models: effects composed into a discrete-time model, and its likelihood; pure JAX, no I/O.

An :class:`Effect` is one physical mechanism declaring its parameters as data; a
:class:`Model` is a flat tuple of effects plus the delay; :func:`prepare` and the
``leg_*`` functions give its likelihood on a cohort with the delay summed out.
"""

from ._effects import (
    KINDS,
    LEVELS,
    AccelResonance,
    ActivationDamping,
    AngleDelay,
    Damping,
    Darma,
    Effect,
    ExponentialElasticity,
    ExtensionLimit,
    Fatigue,
    FractionalDelay,
    GoniometerOffset,
    Gravity,
    GravityOffset,
    HillTorqueVelocity,
    LinearTorqueAngle,
    LinearTorqueVelocity,
    Param,
    PeakTorqueAngle,
    NoMuscle,
    Potentiation,
    PulseContext,
    RecruitmentPower,
    RecruitmentSigmoid,
    StepContext,
    ZeroOrderActivation,
    get_effect,
    register_effect,
    registered_effects,
)
from ._likelihood import (
    N_DELAYS,
    SEGMENT_S,
    LikelihoodData,
    LikelihoodError,
    leg_active_output,
    leg_loglik_by_delay,
    leg_pointwise,
    leg_window_cdf,
    prepare,
    segment_samples,
)
from ._model import (
    FIT_MODELS,
    MODELS,
    PAPER_MODELS,
    Model,
    active_output,
    equivalent_acceleration,
    measure,
    paper_model,
    passive_acceleration,
    passive_effects,
    predict_ahead,
    simulate_angles,
)

__all__ = [
    "Effect", "Param", "StepContext", "PulseContext", "register_effect", "registered_effects", "get_effect",
    "KINDS", "LEVELS",
    "ZeroOrderActivation", "Darma", "LinearTorqueAngle", "LinearTorqueVelocity", "Damping", "Gravity",
    "ExponentialElasticity", "AngleDelay", "FractionalDelay", "PeakTorqueAngle", "HillTorqueVelocity", "Fatigue",
    "Potentiation", "RecruitmentPower", "ActivationDamping", "GoniometerOffset", "AccelResonance",
    "GravityOffset", "RecruitmentSigmoid", "NoMuscle", "ExtensionLimit",
    "Model", "paper_model", "passive_effects", "MODELS", "FIT_MODELS", "PAPER_MODELS", "equivalent_acceleration",
    "simulate_angles", "predict_ahead", "active_output", "measure", "passive_acceleration",
    "LikelihoodData", "LikelihoodError", "prepare", "leg_loglik_by_delay", "leg_pointwise", "leg_active_output",
    "leg_window_cdf", "SEGMENT_S", "segment_samples", "N_DELAYS",
]  # fmt: skip
