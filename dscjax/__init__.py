"""dscjax: a differentiable JAX simulator of adaptive dynamic surface control (DSC) for
uncertain strict-feedback plants driven through backlash-like hysteresis.

    import jax; jax.config.update("jax_enable_x64", True)   # float64 references
    import dscjax
    traj = dscjax.simulate(dscjax.paper_example(), t_final=20.0, dt=1e-3)
"""

from dscjax import closed_loop, device, disturbance, metrics, params, xla
from dscjax.closed_loop import Observation, Setup, State, initial_state, prepared, vector_field
from dscjax.config import order_n_example, paper_example
from dscjax.controllers import DSC, Backstepping, BacksteppingState, Controller, DSCState
from dscjax.hysteresis import Backlash, closed_form
from dscjax.integrate import ETDRK4, RK4, Checkpointed, Status, TimeParallel, integrate, rk4_step
from dscjax.metrics import default_window
from dscjax.params import cast
from dscjax.plant import CustomPlant, PaperPlant, Plant, StrictFeedback, check_strict_feedback
from dscjax.pure import objective
from dscjax.reference import InitialOffset, MultiSine, Reference, Sine, SmoothStep
from dscjax.runspec import RunSpec
from dscjax.simulate import (
    DivergenceError,
    Trajectory,
    canonical,
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
    "Backlash", "Backstepping", "BacksteppingState", "canonical", "cast", "check_strict_feedback",
    "Checkpointed", "closed_form", "closed_loop", "ConfigError", "Controller", "CustomPlant",
    "default_window", "device", "disturbance", "divergence_report", "DivergenceError", "DSC",
    "DSCState",
    "ETDRK4", "initial_state", "InitialOffset", "integrate", "metrics", "MultiSine",
    "nan_if_diverged", "Observation", "order_n_example", "paper_example", "PaperPlant", "params",
    "Plant", "prepared", "Reference", "refinement_level", "RK4", "rk4_step", "run", "RunSpec",
    "objective", "Setup", "simulate", "simulate_batch", "Sine", "SmoothStep", "State", "Status",
    "StrictFeedback", "TimeParallel", "Trajectory", "validate_setup", "vector_field", "xla"
]
