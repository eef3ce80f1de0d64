"""Hysteresis actuators w = P[u] behind the DSC (docs/hysteresis.md): the backlash-like model
(4) of the paper ("backlash", the default) and Bouc-Wen ("bouc_wen"), whose state follows an
ODE (`differential`); Prandtl-Ishlinskii ("pi") and generalized P-I ("gpi"), play operators
advanced by the exact clamp (`plays`). Every model is a `Hysteresis` (`base`: one interface);
`open_loop` and `sine_loops` drive a model alone (`alone`).
"""

from dscjax.hysteresis.alone import open_loop, sine_loops
from dscjax.hysteresis.base import Hysteresis
from dscjax.hysteresis.differential import Backlash, BoucWen, closed_form
from dscjax.hysteresis.plays import GeneralizedPI, PrandtlIshlinskii, envelope, play

MODELS = (Backlash, PrandtlIshlinskii, GeneralizedPI, BoucWen)

__all__ = ["Backlash", "BoucWen", "GeneralizedPI", "Hysteresis", "MODELS",
           "PrandtlIshlinskii", "closed_form", "envelope", "open_loop", "play", "sine_loops"]
