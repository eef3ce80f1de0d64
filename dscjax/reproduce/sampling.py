"""How slowly the paper's gains and `dscjax tune`'s default gains may be sampled: the Ts sweep
of `dscjax.ts_sweep` on the two, as `dscjax reproduce` draws it (`fig_sampling`), with its
findings (for stdout too) and its section of summary.md.

`TUNED` is the controller of one `dscjax tune` run with its defaults (`tuning.sample_time`
1 ms, seed 0, 200 s; its figures are in docs/benchmarks.md)."""

from __future__ import annotations

from collections.abc import Sequence

from dscjax import ts_sweep
from dscjax.config import from_dict
from dscjax.markdown import ms
from dscjax.ts_sweep import SAMPLE_TIMES, criterion, largest_tracking, reach, table

# the controller of that run (its gains.json, the [controller] keys tuned)
TUNED = {
    "k": [33.23462715532851, 0.08475892254059818],
    "gamma_g": [619.3713607232775, 8.0],
    "eta": [2.792260390923935e-07, 0.01],
    "gamma_phi": [400.5465697652097],
    "sigma": [3.988823848130539e-11],
    "gamma_zeta": 0.24809778679565533,
    "eta_zeta": 4.561500525908476e-06,
    "gamma_d": 8.17815401458443,
    "eta_d": 1.1572687780287664e-05,
    "eps": 0.014211310661439451,
    "tau": [0.003930399566535375],
    "sat_width": 0.0019559910108478866,
}
GAINS = ("paper", "tuned")
LABELS = {"paper": "paper's gains", "tuned": "dscjax tune's default gains"}


def study(setup, t_final: float, dt: float, window_start: float = 1.0,
          sample_times: Sequence[float] = SAMPLE_TIMES) -> dict:
    """`ts_sweep.study` of the paper's gains and `TUNED`, as a batch of the controller's
    leaves; `ts_sweep.plot` draws it with `LABELS`."""
    tuned = from_dict({"controller": TUNED}, base=setup)[0]
    batch = ts_sweep.gain_sets((setup, tuned), [f"controller.{k}" for k in TUNED])
    return ts_sweep.study(setup, batch, GAINS, t_final, dt, window_start, sample_times)


def findings(result: dict) -> list[str]:
    """How far each gain set tracks and the fitted order: summary.md's list, stdout's line."""
    tracks = "track without chattering up to Ts = {} ms (L-inf {:.3g})"
    texts = [f"{LABELS[name]}: " + reach(result, name, largest_tracking(result, name), tracks)
             for name in result["names"]]
    o = result["order"]
    if o is not None:
        texts.append(f"the sampled loop tends to the continuous one at order {o['order']:.2f} "
                     f"in Ts (max |y_Ts - y| on t >= {result['window_start']:g} s, Ts = "
                     f"{', '.join(ms(t) for t in o['sample_times'])} ms, the paper's "
                     "gains; one exponential-Euler step of the controller per sample: first "
                     "order)")
    return texts


def markdown(result: dict) -> str:
    return "\n".join(["## The controller sampled at Ts (zero-order hold)", "",
                      *table(result), "", criterion(result),
                      *(f"- {s}" for s in findings(result))])
