"""A config's digital controller as C99: the sampled loop's initialisation and update law,
exactly.

    files = dscjax.export.c_files(setup, spec)   # {"dsc_controller.h": text, ".c": text}
    files = dscjax.export.c_files(setup, spec, precision="float")   # C float throughout

Two functions are generated from jaxprs of the sampled loop, for the concrete config (gains,
sample time and delay are constants; `law.trace`):
- `dsc_init` from the loop's initialisation (`Controller.prepare`, `closed_loop.initial_state`
  and the delay line's first input) as a function of x(0) and the reference at the start: the
  controller starts from the measured state exactly as dscjax's loop starts from plant.x0;
- `dsc_step` from `closed_loop.sample_update` (the law, the advance of the controller's
  states by `spec.discretisation`, the delay line), with x, t and the reference's
  derivatives as inputs.
One C statement per primitive, in double (or float) precision, with no dependency beyond
<math.h> (`c`). Measurement noise belongs to the sensor and the actuator's limits to the
actuator: neither is part of the controller (u is returned unbounded, as the simulation
applies it).
"""

from dscjax.export.c import HEADER, PRECISIONS, SOURCE, c_files
from dscjax.export.law import ExportError, Law, Program, trace

__all__ = ["HEADER", "PRECISIONS", "SOURCE", "ExportError", "Law", "Program", "c_files", "trace"]
