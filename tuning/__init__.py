"""Gain tuning of dscjax controllers through the closed loop: CMA-ES (default) or exact gradients.

    import dscjax, tuning
    setup = dscjax.paper_example()
    problem = tuning.build_problem(setup, dscjax.RunSpec.make(), tuning.TuningConfig())
    result = tuning.run(problem, out_dir="results/tune")
    result.best_setup
    tuning.adversarial.run(setup, options, config_with_rounds, out_dir)   # min-max tuning

docs/tuning.md describes the objective and the settings.
"""

from dscjax.selection import Selection, Tuned
from tuning.config import AdversarialSpec, BatchSpec, ObjectiveSpec, OptimizerSpec, TuningConfig
from tuning.objective import Objective
from tuning.optimize import CMAES, Adam, CVaR, Forward, Max, Mean, Plants, Reverse, loss_function
from tuning.reductions import tuning_metrics
from tuning.requirements import Envelope, StepResponse, UBound, URate
from tuning.runner import Problem, Result, build_problem, run
from tuning.scales import Scales

__all__ = ["CMAES", "Adam", "AdversarialSpec", "BatchSpec", "CVaR", "Envelope", "Forward", "Max",
           "Mean", "Objective", "ObjectiveSpec", "OptimizerSpec", "Plants", "Problem", "Result",
           "Reverse", "Scales", "Selection", "StepResponse", "Tuned", "TuningConfig", "UBound",
           "URate", "build_problem", "loss_function", "run", "tuning_metrics"]
