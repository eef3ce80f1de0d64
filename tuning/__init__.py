"""Gain tuning of dscjax controllers through the closed loop: CMA-ES (default) or exact gradients.

    import dscjax, tuning
    setup = dscjax.paper_example()
    problem = tuning.build_problem(setup, dscjax.RunSpec.make(), tuning.TuningConfig())
    result = tuning.run(problem, out_dir="results/tune")
    result.best_setup
    tuning.adversarial.run(setup, options, config_with_rounds, out_dir)   # min-max tuning

docs/tuning.md describes the objective and the settings.
"""

from tuning.config import AdversarialSpec, BatchSpec, ObjectiveSpec, OptimizerSpec, TuningConfig
from tuning.config import from_dict as config_from_dict
from tuning.objective import Objective, Scales, aggregate
from tuning.optimize import loss_function, value_and_grad
from tuning.params import DSC_GAINS, DSC_INITIAL_ESTIMATES, Selection, Tuned
from tuning.reductions import TuningMetrics
from tuning.requirements import Envelope, StepResponse, UBound, URate
from tuning.runner import Problem, Result, build_problem, run

__all__ = [
    "AdversarialSpec", "BatchSpec", "DSC_GAINS", "DSC_INITIAL_ESTIMATES",
    "Envelope", "Objective", "ObjectiveSpec", "OptimizerSpec", "Problem", "Result", "Scales",
    "Selection", "StepResponse", "Tuned", "TuningConfig", "TuningMetrics", "UBound",
    "URate", "aggregate", "build_problem", "config_from_dict", "loss_function", "run",
    "value_and_grad",
]
