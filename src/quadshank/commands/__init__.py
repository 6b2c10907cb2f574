"""One module per subcommand: load, call the stages, hand the results to the writers.

Each ``run_*`` takes data in memory, writes its output folder (every file atomically,
``summary.json`` last) and returns its typed result, whose JSON form that ``summary.json`` is.
"""

from .check import Check, run_check
from .demo import Demo, run_demo
from .diagnose import run_diagnose
from .discover import run_discover
from .evaluate import run_evaluate, run_posterior_evaluate
from .fit import run_fit
from .predict import PlanPrediction, run_predict
from .identify import run_identify
from .recovery import run_likelihood_calibration, run_recovery
from .report import Report, run_report
from .reproduce import Reproduction, run_reproduce

__all__ = [
    "run_identify", "run_evaluate", "run_posterior_evaluate", "run_fit", "run_reproduce", "run_recovery",
    "run_likelihood_calibration", "run_diagnose", "run_discover", "run_report", "run_demo",
    "Reproduction", "Report", "Demo", "run_predict", "PlanPrediction", "run_check", "Check",
]  # fmt: skip
