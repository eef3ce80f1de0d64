"""Controllers of the closed loop: each a pytree with a small common interface (`base.py`)."""

from dscjax.controllers.base import ControlInfo, Controller
from dscjax.controllers.dsc import DSC, DSCState

__all__ = ["Controller", "ControlInfo", "DSC", "DSCState"]
