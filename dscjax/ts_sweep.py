"""How slowly a controller may be sampled: named gain sets with the controller sampled at each
Ts of a sweep (a zero-order hold on u), their windowed L-inf, TV(u) and chattering index
against Ts, the continuous loop as the Ts -> 0 line, and the order at which the sampled loop
tends to the continuous one (fitted on max |y_Ts - y| over t >= window start). `dscjax
reproduce` draws the paper's gains against `dscjax tune`'s default (`reproduce.sampling`),
`dscjax tune`'s margins start against tuned gains (`tuning.margins`).

A run **tracks** (`judge`) when it did not diverge, its windowed L-inf is at most
TRACK_FACTOR x the same gains' reference figure (by default their continuous loop's), and it
does not chatter (`dscjax.metrics.chatters`, docs/numerics.md): a small error bought by an
input that switches at the sample rate is not tracking.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from dscjax import markdown, metrics, params
from dscjax.plotting import diverged_at_top, saved
from dscjax.runspec import RunSpec, step_for
from dscjax.simulate import simulate_batch

# the sample times of the figure [s]
SAMPLE_TIMES = (1e-4, 2e-4, 5e-4, 1e-3, 2e-3, 5e-3, 1e-2, 2e-2)


# a run tracks when its windowed L-inf is at most this many times its gains' reference figure
TRACK_FACTOR = 2.0


# the figures of every run of the study (`metrics.json` names)
FIGURES = ("linf_error_window", "tv_u_window", "chattering_index")


def judge(linf: float | None, index: float | None, reference: float | None,
          factor: float = TRACK_FACTOR, whose: str = "the reference loop's",
          chatters: bool = True) -> str | None:
    """Why a run does not track, in words, or None where it tracks (module docstring):
    "diverged", "chatters (index 3.2)" or "error 2.6 x the reference loop's"; `reference`
    (the same gains' windowed L-inf in the loop they are judged against) None: the error is
    not judged. The delay margin judges with its own `factor`, the loop it names (`whose`)
    and, where a TV(u) bound judges the effort, no chattering check (`chatters` False)."""
    if linf is None or index is None:
        return "diverged"
    if chatters and metrics.chatters(index):
        return f"chatters (index {index:.3g})"
    if reference is not None and not linf <= factor * reference:
        return f"error {linf / reference:.3g} x {whose}"
    return None


def gain_sets(setups: Sequence, paths) -> dict[str, np.ndarray]:
    """{path: (len(setups), ...)}: the leaves at `paths` of each setup stacked, one row per
    gain set (`study`'s `gains`, a batch of the loop with each set)."""
    return {p: np.stack([np.asarray(params.get(s, p)) for s in setups]) for p in paths}


def measured(tr, keys: Sequence[str], i=()) -> dict[str, float | None]:
    """The figures `keys` of row i of a run (a single run: no i), None where it diverged."""
    diverged = bool(np.asarray(tr.diverged)[i])
    return {k: None if diverged else float(np.asarray(tr.metrics[k])[i]) for k in keys}


def cells(r: dict, keys: Sequence[str], i=None) -> tuple[str, ...]:
    """The figures `keys` of a gain set's results `r` (of each, the value at i where given)
    as table cells: 4 digits, a chattering index 3, "diverged" where the run diverged (None)."""
    return tuple(markdown.number(r[k] if i is None else r[k][i],
                                 ".3g" if k.endswith("chattering_index") else ".4g", "diverged")
                 for k in keys)


def plant_steps(sample_times: Sequence[float], t_final: float,
                dt: float) -> tuple[list[float], list[float]]:
    """(the sample times up to t_final, the plant's step of each run of `study`: the continuous
    one's, the finest, then one for each Ts): dt where Ts is a whole multiple of dt, else one
    fine step (the largest <= dt dividing the smallest Ts) shared by every Ts it divides, so
    that the sampled runs of the figure share one compiled program (`study` runs dt / h steps
    of h as one step of dt, a traced count, as the sample period is traced)."""
    def whole(ts, h):
        return abs(ts / h - round(ts / h)) <= 1e-9 * ts / h

    kept = [ts for ts in sample_times if ts <= t_final]
    fine = step_for(min(kept, default=dt), dt)
    steps = [dt if whole(ts, dt) else fine if whole(ts, fine) else step_for(ts, dt)
             for ts in kept]
    return kept, [min(steps, default=dt), *steps]


def total_steps(t_final: float, dt: float, sample_times: Sequence[float] = SAMPLE_TIMES) -> int:
    """The consecutive steps `study` integrates (each a batch of both gain sets)."""
    return sum(round(t_final / h) for h in plant_steps(sample_times, t_final, dt)[1])


def run_spec(spec: RunSpec, h: float, dt: float, line: int = 0, **change) -> RunSpec:
    """A run of the Ts sweep: `spec` with `change` at the plant step h <= dt, saved every dt,
    its m = dt / h steps of h taken as one (`RunSpec.grouped`, where m divides the steps), so
    that the sweep's runs share one compiled program whatever h; a sampled run's input delay
    line at least `line` long, so that a caller's runs at longer delays share it too (the
    tuning margins' delay runs: h = dt, line = the longest delay)."""
    m = max(int(round(dt / h)), 1)
    sp = spec.replace(dt=h, save_every=m, **change)
    if sp.n_steps % m == 0:
        sp = sp.grouped(m)
    return dataclasses.replace(sp, line=max(sp.line, line)) if sp.sampled else sp


def study(setup, gains: dict, names: Sequence[str], t_final: float, dt: float,
          window_start: float = 1.0, sample_times: Sequence[float] = SAMPLE_TIMES,
          base: RunSpec | None = None, reference: dict | None = None, line: int = 0) -> dict:
    """Windowed L-inf, TV(u) and chattering index on [window_start, T] (`FIGURES`) of each
    gain set (`names`; `gains` {path: (len(names), ...)}: the batch of their leaves,
    `gain_sets`),
    continuous (RK4 at the finest plant step of `plant_steps`: the Ts -> 0 limit, which RK4 at
    dt may miss for stiff gains) and sampled at each Ts, None where a run
    diverged; whether each Ts tracks (`judge` against `reference` {name: windowed L-inf},
    default each set's continuous figure, else its figure at the smallest Ts); and the order at
    which y_Ts tends to y (the first gain set: max |y_Ts - y| on t >= window_start over the
    sample times <= dt, the outputs compared every dt; None with fewer than two). `base`: a
    sampled loop whose other settings (discretisation, delay, noise) the sampled runs keep;
    `line`: the sampled runs' input delay line, if longer than the delay (`run_spec`)."""
    # no refinement: a sampled loop that diverges does so at any plant step
    spec = RunSpec.make(t_final, dt, window_start=window_start, refine=0)
    if base is not None:
        spec = base.replace(t_final=t_final, dt=dt, window_start=window_start, refine=0,
                            save_every=1, sample_time="none", delay=0, noise=None)
    keep = {} if base is None or not base.sampled else {"delay": base.delay,
                                                         "noise": base.to_table()["noise"]}

    def run(ts=None, h=dt):
        sp = run_spec(spec, h, dt, line, **({} if ts is None else {"sample_time": ts} | keep))
        tr = simulate_batch(setup, gains, spec=sp)
        return [measured(tr, FIGURES, i) for i in range(len(names))], np.asarray(tr.x)[0, :, 0]

    sample_times, (h_continuous, *steps) = plant_steps(sample_times, t_final, dt)
    cont, y = run(h=h_continuous)
    sampled = [run(ts, h) for ts, h in zip(sample_times, steps, strict=True)]
    out = {"sample_times": list(sample_times), "window_start": window_start,
           "names": list(names), "track_factor": TRACK_FACTOR}
    for i, name in enumerate(names):
        rows = [r[i] for r, _ in sampled]
        ref = (reference or {}).get(name, cont[i]["linf_error_window"])
        if ref is None:  # the continuous loop diverged (stiff at the finest step)
            ref = next((r["linf_error_window"] for r in rows if r["linf_error_window"]), None)
        why = [judge(r["linf_error_window"], r["chattering_index"], ref) for r in rows]
        out[name] = {"continuous": cont[i]["linf_error_window"],
                     **{f"continuous_{k}": cont[i][k] for k in FIGURES[1:]},
                     "sampled": [r["linf_error_window"] for r in rows],
                     **{k: [r[k] for r in rows] for k in FIGURES[1:]},
                     "reference": ref, "tracks": [w is None for w in why], "why_not": why}
    keep = np.arange(y.size) * dt >= window_start
    fine = [(ts, float(np.max(np.abs(ys - y)[keep]))) for ts, (_, ys) in
            zip(sample_times, sampled, strict=True) if ts <= dt * (1 + 1e-9)]
    out["order"] = None
    if len(fine) >= 2 and all(np.isfinite(e) and e > 0 for _, e in fine):
        ts, err = np.asarray(fine).T
        out["order"] = {"sample_times": ts.tolist(), "max_abs_dy": err.tolist(),
                        "order": float(np.polyfit(np.log(ts), np.log(err), 1)[0])}
    return out


def last_held(values: Sequence, why_not: Sequence[str | None]):
    """The last of `values` before the first that does not hold (`why_not`: None where one
    holds, else why not, as `judge` says); None where the first does not."""
    n = next((i for i, why in enumerate(why_not) if why is not None), len(why_not))
    return values[n - 1] if n else None


def largest_tracking(result: dict, name: str) -> tuple[float, float] | None:
    """(Ts, windowed L-inf) at the largest Ts of the study up to which gain set `name` tracks
    at every Ts (`judge`; None: it does not track at the smallest)."""
    r = result[name]
    return last_held(list(zip(result["sample_times"], r["sampled"], strict=True)), r["why_not"])


def reach(result: dict, name: str, last, tracks: str) -> str:
    """How far gain set `name` tracks, in words: where it tracks at the smallest Ts, `tracks`
    formatted with `last` (`largest_tracking`'s (Ts, windowed L-inf): the Ts in ms, then the
    rest), else that it does not track at the smallest Ts, and why."""
    if last:
        return tracks.format(markdown.ms(last[0]), *last[1:])
    return (f"do not track at Ts = {markdown.ms(result['sample_times'][0])} ms "
            f"({result[name]['why_not'][0]})")


def plot(result: dict, path, colors: dict, dpi: int, labels: dict) -> None:
    """The windowed L-inf of each gain set against Ts (`labels`: {name: its words})."""
    with saved(path, dpi, figsize=(6.4, 4.0)) as (fig, ax):
        ts_ms = 1e3 * np.asarray(result["sample_times"])
        for name in result["names"]:
            r, c = result[name], colors[name]
            v = np.array(r["sampled"], float)  # nan where the run diverged (None)
            ok, tracks = ~np.isnan(v), np.array(r["tracks"], bool)
            label = labels[name]
            ax.plot(ts_ms[ok], v[ok], "-", color=c, lw=1)
            ax.plot(ts_ms[tracks], v[tracks], "o", color=c, ls="none",
                    label=f"{label}, sampled: tracks")
            if (ok & ~tracks).any():
                ax.plot(ts_ms[ok & ~tracks], v[ok & ~tracks], "o", mfc="none", color=c, ms=8,
                        ls="none", label=f"{label}, sampled: chatters or error > "
                        f"{result['track_factor']:g} x")
            if r["continuous"] is not None:
                ax.axhline(r["continuous"], color=c, ls="--", lw=1,
                           label=f"{label}, continuous (Ts -> 0)")
            diverged_at_top(ax, ts_ms, v, ~ok, color=c, ms=9, mew=2, ls="none",
                            label=f"{label}: diverged")
        ax.set(xscale="log", yscale="log",
               xlabel="sample time Ts of the controller [ms] (zero-order hold)",
               ylabel=f"L-inf error on [{result['window_start']:g} s, T]")
        order = result["order"]
        ax.set_title("Sampled controller" + ("" if order is None else
                                             f" (fitted order {order['order']:.2f} in Ts)"))
        ax.legend(fontsize=8)


def criterion(result: dict, reference: str = "the same gains' continuous loop") -> str:
    """The tracking criterion of a study in one sentence."""
    return (f"A Ts tracks when the loop did not diverge, its L∞ error on "
            f"[{result['window_start']:g} s, T] is at most "
            f"{result['track_factor']:g} x that of {reference}, and its "
            f"chattering index on the window is at most {metrics.CHATTER_RATIO:g} "
            f"(docs/numerics.md, \"Chattering\").")


def table(result: dict) -> list[str]:
    """The markdown table against Ts, a row per Ts and gain set (`result["names"]`): windowed
    L-inf, TV(u) and chattering index on the window, the verdict (`judge`); with
    `result["batch"]` (a batch of plants at some Ts, {name: [None or {"p95_tv_u_window",
    "n_chattering", "n_measured"}, ...] per Ts}), its p95 of TV(u) and its chattering
    plants."""
    t0 = f"{result['window_start']:g}"
    batch = result.get("batch")
    head = ("Ts [ms]", "gains", f"L∞ e on [{t0} s, T]", f"TV(u) on [{t0} s, T]",
            "chattering index", "tracks")
    if batch:
        head += (f"{batch['label']}: p95 of TV(u)", f"{batch['label']}: chattering plants")

    def row(i, ts, n):
        r = result[n]
        own = (markdown.ms(ts), n, *cells(r, ("sampled", "tv_u_window", "chattering_index"), i),
               markdown.verdict(r["why_not"][i]))
        if not batch:
            return own
        b = batch[n][i]
        return own + (("-", "-") if b is None else (
            *cells(b, ("p95_tv_u_window",)), f"{b['n_chattering']} of {b['n_measured']}"
            + (f" ({b['n_diverged']} diverged)" if b["n_diverged"] else "")))

    continuous = ("continuous", "continuous_tv_u_window", "continuous_chattering_index")
    return markdown.table(head, [
        *(row(i, ts, n) for i, ts in enumerate(result["sample_times"]) for n in result["names"]),
        *(("continuous", n, *cells(result[n], continuous), "") + (("", "") if batch else ())
          for n in result["names"])])
