"""Grey-box identification from measured data (`dscjax identify`): a record (`data`), the
experiment as a function of numbers (`experiment`), the fit and its statistics (`fit`)."""

from dscjax.identify.data import Record, read
from dscjax.identify.experiment import Experiment, simulate
from dscjax.identify.fit import Problem, estimates, fit_figures, solve, solve_starts

__all__ = ["Experiment", "Problem", "Record", "estimates", "fit_figures", "read", "simulate",
           "solve", "solve_starts"]
