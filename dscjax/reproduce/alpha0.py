"""The alpha_0 study: Theorem 1's guaranteed L-inf bound (72) against what the loop does.

For each alpha_0 the DSC gets the gains of (55), the filters of (60) and the L-inf
initialisation (67)-(68), and every statement of Theorem 1 is checked along its run
(`theory.check`). M_(i+1) of (60) has no closed form: from fast filters (tau_start), M <-
(1 + margin) max_t |B(t)| under tau(M) until max_t |B(t)| <= M, so (59) holds on the run with
the M the gains were built from; the bounds are then data-driven estimates of the theorem's
constants. The RK4 step of a run is stable on the fastest filter and on the hysteresis state
(rate alpha |u'|), halved on divergence; an alpha_0 needing more than `max_steps` steps is
reported as skipped.

    result = alpha0.study(alpha0.base_setup(2))
    print(alpha0.table_markdown(result))
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import jax
import numpy as np

from dscjax.closed_loop import initial_state, prepared
from dscjax.config import order_n_example, paper_example
from dscjax.markdown import table, verdict
from dscjax.plotting import saved
from dscjax.reproduce import theory
from dscjax.reproduce.figures import RC
from dscjax.simulate import canonical, simulate
from dscjax.validation import RK4_REAL_STABILITY, ConfigError, positive

DEFAULT_ALPHA0 = tuple(float(a) for a in np.round(np.geomspace(0.1, 10.0, 10), 4))


@dataclasses.dataclass(frozen=True)
class StudyOptions:
    """Settings of the study."""

    alpha0: tuple[float, ...] = DEFAULT_ALPHA0  # the values (> 0)
    mu: float = 0.1  # of (59)-(60); the bound grows with (n-1) mu/2, 1/tau with M^2/(2 mu)
    hold: str = "eta"  # what (55) keeps: the leakages or the rates (`theory.gains_55`)
    t_final: float = 20.0  # horizon [s]
    # the step: dt_max/2^j, the largest with dt <= dt_safety x 2.785 x min tau (RK4's real
    # stability limit on the fastest filter), halved again while the run diverges
    dt_max: float = 1e-3
    dt_safety: float = 0.5
    margin: float = 0.05  # M = (1 + margin) x the measured max |B| in the fixed point
    max_iter: int = 8  # fixed-point iterations before giving up (reported: not converged)
    tau_start: float = 1e-3  # the filter constant the fixed point starts from
    max_halvings: int = 6  # halvings of a run's dt before M is doubled instead
    max_steps: int = 2_000_000  # a run needing more steps is skipped, with the dt it needed

    def validate(self):
        if not self.alpha0:
            raise ConfigError("alpha0 must be one value > 0 or more (got none)")
        for name in ("alpha0", "mu", "t_final", "dt_max", "dt_safety"):
            positive(getattr(self, name), name)


# what `default_options` changes by order n (n >= 4: as for 4)
BY_ORDER = {2: {}, 3: dict(alpha0=(0.1, 0.3, 1.0), mu=10.0, t_final=10.0),
            4: dict(alpha0=(0.1, 0.3), mu=50.0, t_final=5.0)}


def default_options(n: int, **changes) -> StudyOptions:
    """The study's settings for order n >= 2 (`BY_ORDER`), with `changes` (None values
    ignored) applied. Order n >= 3 is much stiffer (u' carries z_n'' and the hysteresis rate
    alpha |u'| needs tiny steps): fewer alpha_0, shorter runs, and a larger mu keeps tau_start
    consistent with (60), at the price of (n-1) mu/2 in the bound."""
    if n < 2:
        raise ConfigError(f"the alpha_0 study's order n must be >= 2 (got {n})")
    changes = {k: (tuple(float(a) for a in v) if k == "alpha0" else v) for k, v in changes.items()
               if v is not None}
    return StudyOptions(**BY_ORDER[min(n, 4)] | changes)


def base_setup(n: int = 2):
    """The setup the study starts from, with the L-inf initialisation (67)-(68): the paper's
    example for n = 2, `order_n_example(n)` (its plant and small gains) for n >= 3."""
    return paper_example(init="linf") if n == 2 else order_n_example(n, init="linf")


def _dt_for(tau, opts: StudyOptions) -> float:
    limit = opts.dt_safety * RK4_REAL_STABILITY * float(np.min(tau))
    j = math.ceil(math.log2(opts.dt_max / limit)) if limit < opts.dt_max else 0
    return opts.dt_max / 2 ** j


def _with(base, alpha0, M, opts):
    ctrl = theory.gains_55(base.controller, alpha0, opts.hold)
    tau = np.asarray(theory.tau_60(alpha0, M, opts.mu))
    return base.replace(controller=dataclasses.replace(ctrl, tau=tau))


class TooStiff(Exception):
    """A run would need more than `max_steps` steps; `dt` is the step it needed."""

    def __init__(self, dt: float, steps: int):
        super().__init__(f"needs dt <= {dt:.3g} s: {steps} steps")
        self.dt, self.steps = dt, steps


def _simulate(setup, dt, opts: StudyOptions):
    return simulate(setup, opts.t_final, dt, save_every=1, throw=False, refine=0)


def _run(setup, dt, opts: StudyOptions):
    """(trajectory, dt): dt halved (at most `max_halvings` times) while the run diverges or
    alpha max |u'| puts dt beyond dt_safety x RK4's limit; it may still have diverged.
    TooStiff where a run would need more than `max_steps` steps."""
    for _ in range(opts.max_halvings + 1):
        steps = int(round(opts.t_final / dt))
        if steps > opts.max_steps:
            raise TooStiff(dt, steps)
        traj = _simulate(setup, dt, opts)
        if bool(traj.diverged):
            dt /= 2
            continue
        # max_t alpha |u'(t)|: the rate of the hysteresis state, dw'/dw = -alpha |u'| (4)
        stiff = float(setup.hysteresis.alpha) * float(np.max(np.abs(np.asarray(traj.u_dot))))
        over = stiff * dt / (opts.dt_safety * RK4_REAL_STABILITY)
        if over <= 1.0:
            return traj, dt
        dt /= 2 ** math.ceil(math.log2(over))
    return traj, dt


def study_one(base, alpha0: float, opts: StudyOptions,
              log: Callable[[str], None] = lambda s: None) -> dict:
    """One alpha_0: gains (55), fixed point of tau (60) and M, the theorem checked. A first
    consistent run is tightened once: M = (1 + margin) x measured, kept if it does not diverge,
    needs no smaller dt and still satisfies (59). The final gains are re-run at dt/2 (when
    within max_steps) and the change reported (`dt_check`)."""
    t0 = time.perf_counter()
    s0 = prepared(canonical(_with(base, alpha0, np.ones(base.order - 1), opts)))
    X0 = initial_state(s0)
    b0 = np.abs(np.asarray(jax.jit(theory.b_at)(s0, X0.x[0] * 0.0, X0)))  # |B_(i+1)(0)|
    # from fast filters (tau_start where (60) allows it): a slow filter can diverge
    fast = math.sqrt(2 * opts.mu * max(1.0 / opts.tau_start - 0.25 - alpha0, 0.0))
    M = np.maximum((1 + opts.margin) * b0, fast)
    history, converged, last = [], False, None
    for it in range(opts.max_iter):
        setup = _with(base, alpha0, M, opts)
        traj, dt = _run(setup, _dt_for(setup.controller.tau, opts), opts)
        if bool(traj.diverged):
            history.append(dict(M=M.tolist(), dt=dt, diverged=True))
            M = 2 * M
            continue
        res = theory.check(setup, traj, alpha0, opts.mu, M=M)
        last = (setup, dt, res)
        history.append(dict(M=M.tolist(), M_measured=res["M_measured"].tolist(), dt=dt))
        log(f"  alpha_0 = {alpha0:g}, iteration {it + 1}: M = {np.array2string(M, precision=4)}"
            f", measured {np.array2string(res['M_measured'], precision=4)}, dt = {dt:g} s")
        if np.all(res["M_measured"] <= M):
            converged = True  # (59) holds on the run with the M that tau was built from
            break
        M = (1 + opts.margin) * res["M_measured"]
    if last is None:
        raise RuntimeError(f"alpha_0 = {alpha0}: every run diverged ({history})")
    M_tight = (1 + opts.margin) * last[2]["M_measured"]
    if converged and np.any(M_tight < M):
        # the first consistent M may be far above what the run needs (the start is fast)
        setup = _with(base, alpha0, M_tight, opts)
        dt = min(_dt_for(setup.controller.tau, opts), last[1])
        traj, dt_needed = _run(setup, dt, dataclasses.replace(opts, max_halvings=0))
        why = ("diverged" if bool(traj.diverged) else
               "needs a smaller dt" if dt_needed < dt else None)
        res = None if why else theory.check(setup, traj, alpha0, opts.mu, M=M_tight)
        if res is not None and not np.all(res["M_measured"] <= M_tight):
            why = f"(59) fails: measured {np.array2string(res['M_measured'], precision=4)}"
        history.append(dict(M=M_tight.tolist(), dt=dt, tighten=True, kept=why is None, **(
            {"M_measured": res["M_measured"].tolist()} if res is not None else {})))
        log(f"  alpha_0 = {alpha0:g}, tightened M = {np.array2string(M_tight, precision=4)}: "
            + ("kept" if why is None else f"rejected, {why}"))
        if why is None:
            last = (setup, dt, res)
    setup, dt, res = last
    row = _row(alpha0, setup, dt, res, converged, history)
    if opts.t_final / (dt / 2) <= opts.max_steps:
        traj2 = _simulate(setup, dt / 2, opts)
        s1 = float(np.max(np.abs(np.asarray(traj2.S)[:, 0])))
        v_max = float(np.max(theory.lyapunov(setup, traj2).V))
        row["dt_check"] = dict(dt=dt / 2, S1_inf=s1, V_max=v_max,
                               rel_change_S1=abs(s1 - row["S1_inf"]) / row["S1_inf"],
                               rel_change_V_max=abs(v_max - row["V_max"]) / row["V_max"])
    row["wall_s"] = time.perf_counter() - t0
    return row


def _row(alpha0, setup, dt, res, converged, history):
    gains = ("k", "tau", "gamma_g", "gamma_phi", "gamma_zeta", "gamma_d", "eta", "eta_d")
    return dict(
        alpha0=float(alpha0), **{k: np.asarray(getattr(setup.controller, k)).tolist()
                                 for k in gains}, dt=dt,
        M=np.asarray(res["M"]).tolist(), M_measured=res["M_measured"].tolist(),
        iterations=len(history), converged=converged, history=history,
        **{k: res[k] for k in ("S1_inf", "bound_72", "V0", "v0_69", "V_max", "bound_71", "e_M",
                               "C", "slack", "d", "d_n_max", "margin_63", "margin_65", "holds",
                               "assumptions")},
        all_hold=bool(all(res["holds"].values())),
        assumptions_hold=bool(converged and all(res["assumptions"].values())),
        conservatism=res["bound_72"] / res["S1_inf"],
    )


def study(base, opts: StudyOptions | None = None,
          log: Callable[[str], None] = lambda s: None) -> dict:
    """{"n", "options", "rows": one per alpha_0, "wall_s"} of the study on `base` (a DSC
    with init="linf", `base_setup`); a skipped row has alpha0, skipped, dt_needed, steps."""
    opts = opts or StudyOptions()
    opts.validate()
    if getattr(base.controller, "init", None) != "linf":
        raise ConfigError("the alpha_0 study needs the L-inf initialisation (67)-(68): "
                          f"controller.init = 'linf' (got {base.controller.init!r})")
    t0 = time.perf_counter()
    rows = []
    for a in opts.alpha0:
        t1 = time.perf_counter()
        try:
            rows.append(study_one(base, a, opts, log))
        except TooStiff as err:
            rows.append(dict(alpha0=float(a), skipped=True, dt_needed=err.dt, steps=err.steps,
                             wall_s=time.perf_counter() - t1))
            log(f"n = {base.order}, alpha_0 = {a:g}: skipped, {err} > max_steps = "
                f"{opts.max_steps} ({rows[-1]['wall_s']:.1f} s)")
        else:
            r = rows[-1]
            log(f"n = {base.order}, alpha_0 = {a:g}: ||S_1|| = {r['S1_inf']:.4g} <= (72) "
                f"{r['bound_72']:.4g}; conclusions hold: {r['all_hold']} ({r['wall_s']:.1f} s)")
    return dict(n=base.order, options=dataclasses.asdict(opts), rows=rows,
                wall_s=time.perf_counter() - t0)


def table_markdown(result: dict) -> str:
    """The study as a markdown table, one row per alpha_0."""
    return "\n".join(table(
        ("alpha_0", "k", "tau", "M used (measured)", "dt [s]", "‖S_1‖∞", "(72) bound",
         "bound / measured", "max V", "(71) bound", "V(0)", "C", "max abs d_n / d",
         "(63), (65), (70)-(72) hold"), map(_cells, result["rows"])))


def _cells(r: dict) -> tuple:
    """A row of the table: its cells."""
    if r.get("skipped"):
        return (f"{r['alpha0']:g}", f"skipped: needs dt <= {r['dt_needed']:.3g} s, "
                f"{r['steps']} steps (more than max_steps)", *[""] * 12)
    fmt = ", ".join
    failed = [k for k, v in r["holds"].items() if not v]
    return (f"{r['alpha0']:g}", fmt(f"{k:.4g}" for k in r["k"]), fmt(f"{t:.3g}" for t in r["tau"]),
            fmt(f"{m:.4g} ({mm:.4g})" for m, mm in zip(r["M"], r["M_measured"], strict=True))
            + ("" if r["converged"] else " not converged"),
            f"{r['dt']:.3g}", f"{r['S1_inf']:.4g}", f"{r['bound_72']:.4g}",
            f"{r['conservatism']:.3g}", f"{r['V_max']:.4g}", f"{r['bound_71']:.4g}",
            f"{r['V0']:.4g}", f"{r['C']:.4g}", f"{r['d_n_max'] / r['d']:.4f}",
            verdict(None if r["all_hold"] else fmt(failed)))


def plot(results: Sequence[dict], path: Path, dpi: int = 150) -> Path:
    """||S_1||_inf measured and the bound (72) against alpha_0, log axes, one colour per n
    (tab10's first for n = 2, its second for n = 3, ...)."""
    import matplotlib

    with saved(path, dpi, rc=RC, figsize=(8.6, 4.4)) as (fig, ax):
        for res in results:
            n, mu = res["n"], res["options"]["mu"]
            color = matplotlib.colormaps["tab10"](n - 2)  # not the user's global cycle
            rows = [r for r in res["rows"] if not r.get("skipped")]
            a = [r["alpha0"] for r in rows]
            ax.loglog(a, [r["bound_72"] for r in rows], "--", color=color, marker="^",
                      ms=4, label=f"n = {n}: bound (72), data-driven M, $\\mu$ = {mu:g}")
            ax.loglog(a, [r["S1_inf"] for r in rows], "-", color=color, marker="o",
                      ms=4, label=f"n = {n}: measured $\\|S_1\\|_\\infty$")
        ax.set(xlabel=r"$\alpha_0$ (gains by (55), $\tau$ by (60))", ylabel=r"$\|S_1\|_\infty$ [-]")
        ax.set_title("Theorem 1, L-inf initialisation (67)-(68): bound (72) against the "
                     "measured error", fontsize=9.5)
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    return path


