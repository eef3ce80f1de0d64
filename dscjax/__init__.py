"""dscjax: a differentiable JAX simulator of adaptive dynamic surface control (DSC) for
uncertain strict-feedback plants driven through backlash-like hysteresis.

    import jax; jax.config.update("jax_enable_x64", True)   # float64 references
    import dscjax
    traj = dscjax.simulate(dscjax.paper_example(), t_final=20.0, dt=1e-3)
"""

from dscjax import closed_loop, disturbance, metrics, params, xla
from dscjax.closed_loop import Observation, Setup, State, initial_state, prepared, vector_field
from dscjax.controllers import DSC, Backstepping, BacksteppingState, Controller, DSCState
from dscjax.examples import order_n_example, paper_example
from dscjax.hysteresis import Backlash, closed_form
from dscjax.integrate import Status, integrate, rk4_step
from dscjax.params import cast
from dscjax.plant import CustomPlant, PaperPlant, Plant, StrictFeedback, check_strict_feedback
from dscjax.reference import InitialOffset, MultiSine, Reference, Sine, SmoothStep
from dscjax.simulate import (
    DivergenceError,
    Trajectory,
    canonical,
    default_window,
    divergence_report,
    nan_if_diverged,
    refinement_level,
    run,
    simulate,
    simulate_batch,
)
from dscjax.validation import ConfigError, validate_setup

__version__ = "0.1.0"  # the only place: pyproject.toml reads it (dynamic version)

__all__ = [
    "Backlash", "Backstepping", "BacksteppingState", "ConfigError", "Controller", "CustomPlant",
    "DSC", "DSCState", "DivergenceError", "InitialOffset", "MultiSine", "Observation",
    "PaperPlant", "Plant", "Reference", "Setup", "Sine", "SmoothStep", "State", "Status",
    "StrictFeedback", "Trajectory", "canonical", "cast", "check_strict_feedback", "closed_form",
    "closed_loop", "default_window", "disturbance", "divergence_report", "initial_state",
    "integrate", "metrics", "nan_if_diverged", "order_n_example", "paper_example", "params",
    "prepared", "refinement_level", "rk4_step", "run", "simulate", "simulate_batch",
    "validate_setup", "vector_field", "xla",
]
