"""The margins of a tuning run, start against tuned gains (report.md's "Margins"):

    continuous(problem, z0, z1)    the continuous loop (RK4 at dt, refined where stiff): a check
    sample_times(problem, z0, z1)  windowed L-inf, TV(u) and chattering index against Ts, 0.1
                                   ms to 2 x the tuned loop's Ts (`dscjax.ts_sweep`),
                                   the held-out batch at the tuned Ts and above, the largest Ts
                                   up to which the gains track (`ts_sweep.judge`)
    delays(problem, z0, z1)        the input delay in samples, from the loop's own up to
                                   DELAY_MAX: the largest up to which the gains hold
                                   (`delay_judge`)
    long_run(problem, z0, z1)      LONG_FACTOR x T with measurement noise (LONG_NOISE) and a
                                   bounded disturbance (LONG_DBAR sin t): windowed L-inf and
                                   the peaks of the adaptive estimates (drift)

"Tracks" at a sample time (`ts_sweep.judge`): no divergence, a windowed L-inf at most
`ts_sweep.TRACK_FACTOR` x the same gains' figure in the loop tuned, and no chattering
(`dscjax.metrics.chatters`). At a delay, the search's own delayed check (`delay_judge`): no
divergence, the windowed L-inf at most `delay_factor` x and TV(u) at most `delay_tv_factor`
x its bound (no bound: no chattering), so gains the search accepts hold one sample. Each
returns a JSON-able dict; `markdown(margins)` is report.md's section.
"""

from __future__ import annotations

from typing import Any

import jax
import numpy as np

from dscjax import metrics, ts_sweep
from dscjax.markdown import ms, number, table, verdict, window, yes
from dscjax.runspec import step_for
from dscjax.simulate import refinement_level, simulate, simulate_batch
from dscjax.ts_sweep import cells, measured

TS_MIN = 1e-4  # the smallest Ts of the sweep [s]
TS_FACTOR = 2.0  # the sweep ends at this many times the tuned loop's Ts
LONG_FACTOR = 10  # the long run lasts this many times the tuning's horizon (200 s for 20 s)
LONG_NOISE = 1e-4  # std of the long run's measurement noise on every state
LONG_DBAR = 0.2  # amplitude of the long run's disturbance dbar = LONG_DBAR sin(t)
# an estimate drifts when its peak |.| on the second half exceeds this many times its peak on
# the quarter before (the first quarter, the transient, left out)
DRIFT_RATIO = 1.1
DRIFT_MIN_S = 100.0  # a shorter long run is reported, its drift not judged (still settling)
# the largest input delay [samples] the delay margin tries, and the length of the delay line
# on which it tries them all and the Ts sweep runs (one compiled program for them all)
DELAY_MAX = 4
ESTIMATES = ("theta_hat", "phi_hat", "zeta_hat", "d_hat")
NAMES = ("start", "tuned")


def gain_rows(problem, z0, z1) -> dict[str, np.ndarray]:
    """{leaf path: (2, ...)}: every leaf the selection tunes, at the start and tuned points."""
    paths = dict.fromkeys(n.split("[")[0].rstrip("*") for n in problem.selection.names)
    return ts_sweep.gain_sets([problem.setup_at(z) for z in (z0, z1)], paths)


def _run(problem, overrides: dict, spec=None, **change):
    """A batched run of the loop tuned with `change` (no refinement), or of `spec`, on the
    host."""
    if spec is None:
        spec = problem.objective.sim.replace(refine=0, **change)
    return jax.device_get(simulate_batch(problem.setup, overrides, spec=spec))


def continuous(problem, z0, z1) -> dict[str, Any] | None:
    """The continuous loop (the config's [simulation]) on the nominal plant, each gain set
    refined where RK4 at dt diverges (a stiff loop, not a failure); None where the continuous
    loop is the one tuned."""
    spec = problem.continuous
    if spec is None:
        return None
    out = {"dt": float(spec.dt)}
    for tag, z in zip(NAMES, (z0, z1), strict=True):
        tr = simulate(problem.setup_at(z), spec=spec, throw=False)
        j = int(tr.refinements)
        out[tag] = {"diverged": bool(tr.diverged), "refinements": j,
                    "solver": refinement_level(j, spec.solver)[0].name, "dt_used": float(tr.dt),
                    **measured(tr, ("linf_error_window", "max_abs_u", "tv_u", "chattering_index"))}
    return out


def sweep_times(ts: float) -> list[float]:
    """The sample times of the sweep: `ts_sweep.SAMPLE_TIMES` from TS_MIN up to TS_FACTOR x
    ts, and that end itself."""
    top = TS_FACTOR * ts
    out = [t for t in ts_sweep.SAMPLE_TIMES if TS_MIN * (1 - 1e-9) <= t < top * (1 - 1e-9)]
    return out + [top]


def sample_times(problem, z0, z1, nominal: dict, heldout: dict | None) -> dict[str, Any] | None:
    """`ts_sweep.study` of start and tuned gains from TS_MIN to TS_FACTOR x the tuned loop's
    Ts (its discretisation, delay and noise kept), each Ts judged against the gains' windowed
    L-inf in the loop tuned (`reference_linf` of `nominal`, {tag: the nominal plant's figures
    there}); the largest
    Ts up to which each tracks, and whether the tuned gains track at every Ts of the range.
    With `heldout` ({tag: the held-out plants' figures in the loop tuned}, `report.evaluate`;
    None: no held-out batch), the held-out batch's p95 of TV(u) on the window and its
    chattering plants at the tuned Ts (those figures) and at every larger Ts of the sweep (run
    here). None for a continuous tuned loop."""
    sim = problem.objective.sim
    if not sim.sampled:
        return None
    dt = float(problem.options.dt)
    result = ts_sweep.study(problem.setup, gain_rows(problem, z0, z1), NAMES, sim.t_final, dt,
                            float(sim.window_start), sweep_times(sim.sample_time), base=sim,
                            reference=reference_linf(nominal), line=DELAY_MAX)
    result["reference"] = "the loop tuned"
    result["largest"] = {n: ts_sweep.largest_tracking(result, n) for n in NAMES}
    result["tuned_tracks_all"] = all(result["tuned"]["tracks"])
    if heldout is not None:
        result["batch"] = heldout_at(problem, z0, z1, result["sample_times"], heldout)
    return result


def _finite(v):
    return None if v is None or not np.isfinite(v) else float(v)


def reference_linf(nominal: dict) -> dict[str, float | None]:
    """{tag: the gain set's windowed L-inf on the nominal plant in the loop tuned}, against
    which the Ts sweep and the delays judge it (None where it did not track)."""
    return {tag: _finite(nominal[tag].get("linf_error_window")) for tag in NAMES}


def batch_figures(m: dict[str, np.ndarray]) -> dict[str, Any]:
    """A batch's effort verdict from its per-plant metrics: p95 of TV(u) on the window and the
    plants that chatter (`metrics.chatters`), over the plants that did not diverge; the
    report's batch figures count their chattering plants by it (`report.batch_stats`)."""
    ok = ~np.asarray(m["diverged"]).astype(bool)
    tv = np.asarray(m["tv_u_window"], float)[ok]
    index = np.asarray(m["chattering_index"], float)[ok]
    return {"p95_tv_u_window": float(np.percentile(tv, 95)) if tv.size else None,
            "n_chattering": int(sum(metrics.chatters(v) for v in index)),
            "n_measured": int(ok.sum()), "n_diverged": int((~ok).sum())}


def heldout_at(problem, z0, z1, sample_times, heldout: dict) -> dict[str, Any]:
    """`batch_figures` of the held-out batch for start and tuned gains at each Ts of
    `sample_times` (None below the tuned loop's Ts): at the tuned Ts from `heldout` (the
    held-out check's figures), above it by one batched run of both gain sets per Ts (no
    refinement: a sampled loop that diverges is unstable, not stiff)."""
    sim = problem.objective.sim
    own = sim.sample_time
    n = len(next(iter(problem.heldout.values())))
    gains = gain_rows(problem, z0, z1)
    # rows: every held-out plant with the start gains, then with the tuned
    ov = ({p: np.repeat(v, n, axis=0) for p, v in gains.items()}
          | {p: np.concatenate([v, v]) for p, v in problem.heldout.items() if p not in gains})

    def at(ts) -> list:  # the figures of each gain set at ts
        if ts < own * (1 - 1e-9):
            return [None] * len(NAMES)
        if ts <= own * (1 + 1e-9):
            return [batch_figures(heldout[tag]) for tag in NAMES]
        h = step_for(ts, float(sim.dt))
        tr = _run(problem, ov, sample_time=ts, dt=h, save_every=int(round(sim.t_final / h)))
        m = {"diverged": tr.diverged, **tr.metrics}
        return [batch_figures({k: np.asarray(v)[i * n:(i + 1) * n] for k, v in m.items()})
                for i in range(len(NAMES))]

    rows = [at(ts) for ts in sample_times]
    return {"label": f"held-out ({n} plants)", "n": n,
            **{tag: [r[i] for r in rows] for i, tag in enumerate(NAMES)}}


def delay_judge(problem, linf, tv, index, reference) -> str | None:
    """Why a delayed loop fails the search's delayed check, in words, or None where it holds:
    diverged (a figure missing), TV(u) over `delay_tv_factor` x the TV(u) bound, else
    `ts_sweep.judge` with `delay_factor` (chattering where there is no bound, or a windowed
    L-inf over `delay_factor` x `reference`, the same gains' in the loop tuned)."""
    spec, bound = problem.cfg.objective, problem.scales.tv_max
    if linf is None or tv is None or index is None:
        return "diverged"
    if bound is not None and not tv <= spec.delay_tv_factor * bound:
        return f"TV(u) {tv / bound:.3g} x its bound"
    return ts_sweep.judge(linf, index, reference, spec.delay_factor, "the loop tuned's",
                          chatters=bound is None)


def delays(problem, z0, z1, nominal: dict) -> dict[str, Any] | None:
    """The delay margin: the loop tuned with an input delay of d samples, d from its own delay
    up to DELAY_MAX, each gain set judged by `delay_judge` against its windowed L-inf in the
    loop tuned (`reference_linf` of `nominal`, {tag: the nominal plant's figures}, which are the
    row of its own delay); the largest d up to which each holds (None: not even at its
    own delay). The sweep stops at the first d at which neither gain set holds. None for a
    continuous tuned loop."""
    sim = problem.objective.sim
    if not sim.sampled:
        return None
    gains, ref = gain_rows(problem, z0, z1), reference_linf(nominal)
    own = int(sim.delay)
    figures = (*ts_sweep.FIGURES, "tv_u")
    out: dict[str, Any] = {"sample_time": sim.sample_time, "delays": [], "max": DELAY_MAX,
                           "linf_factor": problem.cfg.objective.delay_factor,
                           "tv_limit": None if problem.scales.tv_max is None else
                           problem.cfg.objective.delay_tv_factor * problem.scales.tv_max,
                           **{tag: {k: [] for k in (*figures, "why_not")} for tag in NAMES}}

    def add(d, rows):
        out["delays"].append(d)
        for tag, r in zip(NAMES, rows, strict=True):
            for k in figures:
                out[tag][k].append(r[k])
            out[tag]["why_not"].append(delay_judge(problem, r["linf_error_window"], r["tv_u"],
                                                   r["chattering_index"], ref[tag]))

    add(own, [{k: None if nominal[tag].get("diverged") else _finite(nominal[tag].get(k))
               for k in figures} for tag in NAMES])
    for d in range(own + 1, DELAY_MAX + 1):
        if all(out[tag]["why_not"][-1] is not None for tag in NAMES):
            break
        # as a run of the Ts sweep (`sample_times`) at h = dt: its compiled program
        tr = _run(problem, gains, ts_sweep.run_spec(sim.replace(refine=0), float(sim.dt),
                                                    float(sim.dt), DELAY_MAX, delay=d))
        add(d, [measured(tr, figures, i) for i in range(len(NAMES))])
    # each gain set's last d before the first at which it fails
    out["largest"] = {tag: ts_sweep.last_held(out["delays"], out[tag]["why_not"]) for tag in NAMES}
    return out


def long_run(problem, z0, z1) -> dict[str, Any]:
    """Start and tuned gains over LONG_FACTOR x T in the tuned loop with measurement noise (a
    sampled loop only) and a bounded disturbance LONG_DBAR sin(t) (a plant with `dbar_amp`):
    windowed L-inf, and each adaptive estimate's peak |.| on the second quarter and on the
    second half (an estimate that drifts grows on the second half)."""
    sim = problem.objective.sim
    t_long = LONG_FACTOR * sim.t_final
    n = int(round(t_long / float(sim.dt)))
    change = {"t_final": t_long, "save_every": max(n // 2000, 1)}
    noise = sim.sampled and sim.noise is None
    if noise:
        change |= {"noise": LONG_NOISE, "noise_seed": 0}
    ov = gain_rows(problem, z0, z1)
    dbar = hasattr(problem.setup.plant, "dbar_amp")
    if dbar:
        ov["plant.dbar_amp"] = np.full(2, LONG_DBAR)
    tr = _run(problem, ov, **change)
    t = np.asarray(tr.t)[0]
    half = t > t_long / 2
    quarter = (t > t_long / 4) & ~half
    own = None if sim.noise is None else float(np.max(np.asarray(sim.noise)))  # the loop's
    out = {"t_final": t_long, "noise": LONG_NOISE if noise else own,
           "disturbance": f"{LONG_DBAR:g} sin(t)" if dbar else None,
           "window_start": float(sim.window_start)}
    for i, tag in enumerate(NAMES):
        est = {}
        for name in (e for e in ESTIMATES if hasattr(tr.ctrl, e)):
            v = np.abs(np.asarray(getattr(tr.ctrl, name))[i]).reshape(t.size, -1)
            a, b = float(np.max(v[quarter])), float(np.max(v[half]))
            est[name] = {"second_quarter": a, "second_half": b,
                         "bounded": bool(np.isfinite(b) and b <= DRIFT_RATIO * max(a, 1e-12))}
        gone = bool(np.asarray(tr.diverged)[i])
        bounded = not gone and all(e["bounded"] for e in est.values())
        out[tag] = {"diverged": gone, **measured(tr, ("linf_error_window", "chattering_index"), i),
                    "estimates": est, "bounded": bounded if t_long >= DRIFT_MIN_S or gone else None}
    return out


def evaluate(problem, z0, z1, ev: dict) -> dict[str, Any]:
    """Every margin (JSON-able; a margin that does not apply is None); `ev`: the report's
    per-plant figures (`report.evaluate`), against which the Ts sweep and the delays are
    judged (the nominal plant in the loop tuned) and from which the held-out batch's figures
    at the tuned Ts come."""
    return {"continuous": continuous(problem, z0, z1),
            "sample_time": sample_times(problem, z0, z1, ev["nominal"], ev["heldout"]),
            "delay": delays(problem, z0, z1, ev["nominal"]),
            "long_run": long_run(problem, z0, z1)}


def failures(margins: dict[str, Any]) -> list[str]:
    """The margins the tuned gains miss, in words (empty: every one holds)."""
    out = []
    st = margins.get("sample_time")
    if st is not None and not st["tuned_tracks_all"]:
        lost = [f"{ms(ts)} ms ({why})" for ts, why in zip(
            st["sample_times"], st["tuned"]["why_not"], strict=True) if why is not None]
        out.append(f"the tuned gains do not track at every Ts from {_ms_range(st)}: not with "
                   f"the controller sampled at {', '.join(lost)}")
    lr = margins["long_run"]
    if lr["tuned"]["bounded"] is False:
        out.append("the tuned gains " + ("diverge" if lr["tuned"]["diverged"] else
                                         "let an adaptive estimate grow")
                   + f" over the {lr['t_final']:g} s run")
    return out


def _ms_range(st: dict) -> str:
    """The Ts sweep's range, "0.1 to 2 ms"."""
    return f"{ms(st['sample_times'][0])} to {ms(st['sample_times'][-1])} ms"


def markdown(margins: dict[str, Any], nominal: dict) -> list[str]:
    """report.md's "Margins" section; `nominal`: {tag: the nominal plant's figures over the
    tuning's horizon}, whose windowed L-inf stands beside the long run's."""
    lines = ["", "## Margins (nominal plant)"]
    c = margins.get("continuous")
    if c is not None:
        lines += ["", f"**The continuous loop** (RK4 at dt = {c['dt']:g} s, refined where "
                  f"stiff):", "", *table(
                      ("", "L∞ e on [t0, T]", "max\\|u\\|", "TV(u)",
                       "chattering index on [t0, T]", "simulated by"),
                      [(tag, *cells(r, ("linf_error_window", "max_abs_u", "tv_u",
                                        "chattering_index")),
                        f"{r['solver']} at dt = {r['dt_used']:g} s"
                        + (" (RK4 at dt diverged: stiff)" if r["refinements"] else ""))
                       for tag, r in _rows(c)])]
    st = margins.get("sample_time")
    if st is not None:
        lines += ["", f"**Sample time.** The loop tuned with the controller sampled at each Ts "
                  f"from {_ms_range(st)} (`sampling.png`). "
                  + ts_sweep.criterion(st, "the same gains in the loop tuned")
                  + (" Held-out: at the tuned Ts and above." if st.get("batch") else ""), "",
                  *ts_sweep.table(st)]
    dl = margins.get("delay")
    if dl is not None:
        tv = (" and no chattering" if dl["tv_limit"] is None else
              f" and TV(u) at most {dl['tv_limit']:.4g} (`delay_tv_factor` x its bound)")
        lines += ["", f"**Delay margin.** The loop tuned (Ts = {ms(dl['sample_time'])} ms) "
                  f"with the input d samples late, up to {dl['max']}: windowed L-inf at most "
                  f"{dl['linf_factor']:g} x the same gains' at the loop's own delay{tv}:", "",
                  *table(("delay d [samples]", "gains", "L∞ e on [t0, T]", "TV(u)",
                          "chattering index", "holds"),
                         [(d, tag, *cells(r, ("linf_error_window", "tv_u", "chattering_index"), i),
                           verdict(r["why_not"][i]))
                          for i, d in enumerate(dl["delays"]) for tag, r in _rows(dl)])]
    lr = margins["long_run"]
    what = [f"measurement noise of std {lr['noise']:g} on every state"] if lr["noise"] else []
    what += [f"a bounded disturbance dbar = {lr['disturbance']}"] if lr["disturbance"] else []
    lines += ["", f"**Long run.** {lr['t_final']:g} s in the loop tuned"
              + (f", with {' and '.join(what)}" if what else "")
              + f"; an estimate is bounded when its peak |.| on the second half is at most "
              f"{DRIFT_RATIO:g} x that on the second quarter (not judged below "
              f"{DRIFT_MIN_S:g} s):", "",
              *table(("", f"L∞ e on {window(lr['window_start'], lr['t_final'])}",
                      "L∞ e over the tuning's horizon (no noise, no disturbance)",
                      "chattering index",
                      *(f"peak \\|{e}\\| 2nd quarter / 2nd half" for e in ESTIMATES
                        if e in lr["tuned"]["estimates"]), "bounded"),
                     [(tag, *cells(r, ("linf_error_window",)),
                       number(reference_linf(nominal)[tag], missing="diverged"),
                       *cells(r, ("chattering_index",)),
                       *(f"{e['second_quarter']:.4g} / {e['second_half']:.4g}"
                         for e in r["estimates"].values()),
                       "not judged" if r["bounded"] is None else yes(r["bounded"]))
                      for tag, r in _rows(lr)])]
    return lines + ["", *(f"- {v}" for v in verdicts(margins))]


def _rows(margin: dict):
    """(tag, the gain set's figures) of a margin, start then tuned."""
    return [(tag, margin[tag]) for tag in NAMES]


def verdicts(margins: dict[str, Any]) -> list[str]:
    """Each margin's verdict on each gain set, in words: report.md's list closing "Margins",
    and the console's lines; a margin the tuned gains miss is said by `failures` alone (the
    warning report.md opens with and the console ends with)."""
    out = []
    st = margins.get("sample_time")
    if st is not None:
        tracks = "track up to Ts = {} ms (at every Ts of the sweep up to it)"
        out += [f"sample time: {tag} gains " + ts_sweep.reach(st, tag, st["largest"][tag], tracks)
                for tag in NAMES]
        if st["tuned_tracks_all"]:
            out.append(f"sample time: the tuned gains track at every Ts from {_ms_range(st)}")
    dl = margins.get("delay")
    if dl is not None:
        for tag in NAMES:
            last, own = dl["largest"][tag], dl["delays"][0]
            more = " (the largest tried)" if last == dl["delays"][-1] and last >= dl["max"] else ""
            out.append(f"delay at Ts = {ms(dl['sample_time'])} ms: {tag} gains " + (
                f"do not hold even at the loop's own delay ({own}: {dl[tag]['why_not'][0]})"
                if last is None else f"hold up to an input delay of {last} sample(s){more}"))
    lr = margins["long_run"]
    if lr["tuned"]["bounded"] is False:
        return out
    judged = "bounded" if lr["tuned"]["bounded"] else f"not judged (a run under {DRIFT_MIN_S:g} s)"
    return out + [f"long run ({lr['t_final']:g} s): the tuned gains' adaptive estimates {judged}"]
