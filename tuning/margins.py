"""The margins of a tuning run, start against tuned gains (report.md's "Margins"):

    continuous(problem, z0, z1)    the continuous loop (RK4 at dt, refined where stiff): a check
    sample_times(problem, z0, z1)  windowed L-inf against Ts, 0.1 ms to 2 x the tuned loop's Ts
                                   (`dscjax.reproduce.sampling.study`), the largest Ts tracked
    long_run(problem, z0, z1)      LONG_FACTOR x T with measurement noise (LONG_NOISE) and a
                                   bounded disturbance (LONG_DBAR sin t): windowed L-inf and
                                   the peaks of the adaptive estimates (drift)

Each returns a JSON-able dict; `markdown(margins)` is report.md's section.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from dscjax import params
from dscjax.reproduce import sampling
from dscjax.simulate import refinement_level, simulate, simulate_batch

TS_MIN = 1e-4  # the smallest Ts of the sweep [s]
TS_FACTOR = 2.0  # the sweep ends at this many times the tuned loop's Ts
LONG_FACTOR = 10  # the long run lasts this many times the tuning's horizon (200 s for 20 s)
LONG_NOISE = 1e-4  # std of the long run's measurement noise on every state
LONG_DBAR = 0.2  # amplitude of the long run's disturbance dbar = LONG_DBAR sin(t)
# an estimate drifts when its peak |.| on the second half exceeds this many times its peak on
# the quarter before (the first quarter, the transient, left out)
DRIFT_RATIO = 1.1
DRIFT_MIN_S = 100.0  # a shorter long run is reported, its drift not judged (still settling)
ESTIMATES = ("theta_hat", "phi_hat", "zeta_hat", "d_hat")
NAMES = ("start", "tuned")


def gain_rows(problem, z0, z1) -> dict[str, np.ndarray]:
    """{leaf path: (2, ...)}: every leaf the selection tunes, at the start and tuned points."""
    setups = [jax.tree.map(np.asarray, problem.selection.apply(problem.setup, z))
              for z in (z0, z1)]
    paths = dict.fromkeys(n.split("[")[0].rstrip("*") for n in problem.selection.names)
    return {p: np.stack([np.asarray(params.get(s, p)) for s in setups]) for p in paths}


def continuous(problem, z0, z1) -> dict[str, Any] | None:
    """The continuous loop (the config's [simulation]) on the nominal plant, each gain set
    refined where RK4 at dt diverges (a stiff loop, not a failure); None where the continuous
    loop is the one tuned."""
    spec = problem.continuous
    if spec is None:
        return None
    out = {"dt": float(spec.dt)}
    for tag, z in zip(NAMES, (z0, z1), strict=True):
        setup = jax.tree.map(np.asarray, problem.selection.apply(problem.setup, z))
        tr = simulate(setup, spec=spec, throw=False)
        j = int(tr.refinements)
        out[tag] = {"diverged": bool(tr.diverged), "refinements": j,
                    "solver": refinement_level(j, spec.solver.name)[0], "dt_used": float(tr.dt),
                    **{k: None if bool(tr.diverged) else float(tr.metrics[k])
                       for k in ("linf_error_window", "max_abs_u", "tv_u")}}
    return out


def sweep_times(ts: float) -> list[float]:
    """The sample times of the sweep: `sampling.SAMPLE_TIMES` from TS_MIN up to TS_FACTOR x
    ts, and that end itself."""
    top = TS_FACTOR * ts
    out = [t for t in sampling.SAMPLE_TIMES if TS_MIN * (1 - 1e-9) <= t < top * (1 - 1e-9)]
    return out + [top]


def sample_times(problem, z0, z1) -> dict[str, Any] | None:
    """`sampling.study` of start and tuned gains from TS_MIN to TS_FACTOR x the tuned loop's
    Ts (its discretisation, delay and noise kept), the largest Ts each tracks, and whether the
    tuned gains track at every Ts of the range; None for a continuous tuned loop."""
    sim = problem.objective.sim
    if not sim.sampled:
        return None
    dt = float(problem.options.dt)
    result = sampling.study(problem.setup, sim.t_final, dt, float(sim.window_start),
                            sweep_times(sim.sample_time), gains=gain_rows(problem, z0, z1),
                            names=NAMES, base=sim)
    result["largest"] = {n: sampling.largest_tracking(result, n) for n in NAMES}
    result["tuned_tracks_all"] = all(v is not None for v in result["tuned"]["sampled"])
    return result


def long_run(problem, z0, z1) -> dict[str, Any]:
    """Start and tuned gains over LONG_FACTOR x T in the tuned loop with measurement noise (a
    sampled loop only) and a bounded disturbance LONG_DBAR sin(t) (a plant with `dbar_amp`):
    windowed L-inf, and each adaptive estimate's peak |.| on the second quarter and on the
    second half (an estimate that drifts grows on the second half)."""
    sim = problem.objective.sim
    t_long = LONG_FACTOR * sim.t_final
    n = int(round(t_long / float(sim.dt)))
    change = {"t_final": t_long, "save_every": max(n // 2000, 1), "refine": 0}
    noise = sim.sampled and sim.noise is None
    if noise:
        change |= {"noise": LONG_NOISE, "noise_seed": 0}
    spec = sim.replace(**change)
    ov = gain_rows(problem, z0, z1)
    dbar = hasattr(problem.setup.plant, "dbar_amp")
    if dbar:
        ov["plant.dbar_amp"] = np.full(2, LONG_DBAR)
    tr = jax.device_get(simulate_batch(problem.setup, ov, spec=spec))
    t = np.asarray(tr.t)[0]
    half = t > t_long / 2
    quarter = (t > t_long / 4) & ~half
    own = None if sim.noise is None else float(np.max(np.asarray(sim.noise)))  # the loop's
    out = {"t_final": t_long, "noise": LONG_NOISE if noise else own,
           "disturbance": f"{LONG_DBAR:g} sin(t)" if dbar else None,
           "window_start": float(sim.window_start)}
    for i, tag in enumerate(NAMES):
        row: dict[str, Any] = {"diverged": bool(np.asarray(tr.diverged)[i]),
                               "linf_error_window": None}
        if not row["diverged"]:
            row["linf_error_window"] = float(np.asarray(tr.metrics["linf_error_window"])[i])
        est = {}
        for name in ESTIMATES:
            if not hasattr(tr.ctrl, name):
                continue
            v = np.abs(np.asarray(getattr(tr.ctrl, name))[i]).reshape(t.size, -1)
            a, b = float(np.max(v[quarter])), float(np.max(v[half]))
            est[name] = {"second_quarter": a, "second_half": b,
                         "bounded": bool(np.isfinite(b) and b <= DRIFT_RATIO * max(a, 1e-12))}
        row["estimates"] = est
        row["bounded"] = (not row["diverged"] and all(e["bounded"] for e in est.values())
                          if t_long >= DRIFT_MIN_S or row["diverged"] else None)
        out[tag] = row
    return out


def evaluate(problem, z0, z1) -> dict[str, Any]:
    """All three margins (JSON-able; a margin that does not apply is None)."""
    return {"continuous": continuous(problem, z0, z1),
            "sample_time": sample_times(problem, z0, z1),
            "long_run": long_run(problem, z0, z1)}


def failures(margins: dict[str, Any]) -> list[str]:
    """The margins the tuned gains miss, in words (empty: every one holds)."""
    out = []
    st = margins.get("sample_time")
    if st is not None and not st["tuned_tracks_all"]:
        lost = [f"{1e3 * ts:g} ms" for ts, v in zip(st["sample_times"], st["tuned"]["sampled"],
                                                     strict=True) if v is None]
        out.append(f"the tuned gains diverge with the controller sampled at {', '.join(lost)}")
    lr = margins.get("long_run")
    if lr is not None and lr["tuned"]["bounded"] is False:
        out.append("the tuned gains " + ("diverge" if lr["tuned"]["diverged"] else
                                         "let an adaptive estimate grow")
                   + f" over the {lr['t_final']:g} s run")
    return out


def _f(v):
    return "diverged" if v is None else f"{v:.4g}"


def markdown(margins: dict[str, Any], short_linf: dict[str, float | None]) -> list[str]:
    """report.md's "Margins" section; `short_linf`: each gain set's windowed L-inf over the
    tuning's horizon (nominal plant), beside the long run's."""
    lines = ["", "## Margins (nominal plant)"]
    c = margins.get("continuous")
    if c is not None:
        lines += ["", f"**The continuous loop** (a check, not tuned: RK4 at dt = "
                  f"{c['dt']:g} s, refined where stiff; a stiff continuous loop is not a "
                  f"failure):", "", "| | L∞ e on [t0, T] | max\\|u\\| | TV(u) | simulated by |",
                  "|---|---|---|---|---|"]
        for tag in NAMES:
            r = c[tag]
            how = (f"{r['solver']} at dt = {r['dt_used']:g} s"
                   + (" (RK4 at dt diverged: stiff)" if r["refinements"] else ""))
            lines.append(f"| {tag} | {_f(r['linf_error_window'])} | {_f(r['max_abs_u'])} | "
                         f"{_f(r['tv_u'])} | {how} |")
    st = margins.get("sample_time")
    if st is not None:
        lines += ["", f"**Sample time.** The loop tuned with the controller sampled at each Ts "
                  f"from {1e3 * st['sample_times'][0]:g} to {1e3 * st['sample_times'][-1]:g} ms "
                  f"(its discretisation, delay and noise kept; the continuous loop at the "
                  f"finest plant step as Ts -> 0; figure `sampling.png`):", "",
                  *sampling.table(st, NAMES), ""]
        for tag in NAMES:
            last = st["largest"][tag]
            lines.append(f"- {tag} gains: " + (f"track up to Ts = {1e3 * last[0]:g} ms (the "
                                               f"largest of the sweep they track)" if last else
                                               "diverge at every Ts of the sweep"))
        lines.append("- the tuned gains " + ("track at every Ts of the range" if
                                            st["tuned_tracks_all"] else
                                            "do NOT track at every Ts of the range"))
    lr = margins["long_run"]
    what = " and ".join(x for x in (
        f"measurement noise of std {lr['noise']:g} on every state" if lr["noise"] else "",
        f"a bounded disturbance dbar = {lr['disturbance']}" if lr["disturbance"] else "") if x)
    lines += ["", f"**Long run.** {lr['t_final']:g} s in the loop tuned"
              + (f", with {what}" if what else "")
              + f"; an estimate counts as bounded when its peak |.| on the second half is at "
              f"most {DRIFT_RATIO:g} x its peak on the second quarter (the first, the "
              f"transient, left out; not judged below {DRIFT_MIN_S:g} s):", "",
              f"| | L∞ e on [{lr['window_start']:g}, {lr['t_final']:g}] s | L∞ e over the "
              f"tuning's horizon (no noise, no disturbance) | "
              + " | ".join(f"peak \\|{e}\\| 2nd quarter / 2nd half" for e in ESTIMATES
                           if e in lr["tuned"]["estimates"]) + " | bounded |",
              "|---|---|---|" + "---|" * len(lr["tuned"]["estimates"]) + "---|"]
    for tag in NAMES:
        r = lr[tag]
        cells = [f"{e['second_quarter']:.4g} / {e['second_half']:.4g}"
                 for e in r["estimates"].values()]
        lines.append(f"| {tag} | {_f(r['linf_error_window'])} | {_f(short_linf[tag])} | "
                     + " | ".join(cells) + " | " + {True: "yes", False: "**no**", None:
                                                   "not judged"}[r["bounded"]] + " |")
    return lines
