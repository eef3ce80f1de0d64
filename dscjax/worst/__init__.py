"""Worst-case search: maximise a metric of the closed loop over a box of plant / hysteresis /
initial-state parameters and a bounded disturbance waveform.

    problem = make_problem(setup, ranges=[parse_range("hysteresis.alpha=30%")],
                           disturbance="fourier:16:0.5", t_final=20.0, dt=1e-3)
    result = worst_case(problem, time_limit=60.0, starts=4, out_dir="results/worst")

What is maximised is a `Problem` (`problem`), its compiled programs `Programs` (`programs`);
`worst_case` runs each method of `dscjax.search` on them for the same search time and
reports `simulate`'s value (with refinement) on the worst setup (+inf if it diverges), which
`worst_config.toml` reproduces (`run`; the files: `report`).
"""

from dscjax.worst.problem import (
    METRICS,
    REQUIREMENT,
    DisturbanceSpec,
    Problem,
    assumption_warnings,
    check_disturbance,
    make_problem,
)
from dscjax.worst.programs import Programs
from dscjax.worst.run import (
    DEFAULT_COARSENING,
    DEFAULT_STARTS,
    METHODS,
    Result,
    WorstSettings,
    best_value,
    check_search,
    run_methods,
    search_method,
    worst_case,
)

__all__ = ["DEFAULT_COARSENING", "DEFAULT_STARTS", "METHODS", "METRICS", "REQUIREMENT",
           "DisturbanceSpec", "Problem", "Programs", "Result", "WorstSettings",
           "assumption_warnings", "best_value", "check_disturbance", "check_search",
           "make_problem", "run_methods", "search_method", "worst_case"]
