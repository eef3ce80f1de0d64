"""Controllers of the closed loop: each a pytree with a small common interface (`base.py`)."""

from dscjax.controllers.backstepping import Backstepping, BacksteppingState
from dscjax.controllers.base import ControlInfo, Controller
from dscjax.controllers.dsc import DSC, DSCState

__all__ = ["Backstepping", "BacksteppingState", "Controller", "ControlInfo", "DSC", "DSCState"]
