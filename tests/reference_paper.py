"""An independent implementation of the paper's closed loop (Section 4, eq. 73), for tests.

Written by hand from the paper in plain Python floats, sharing no code with dscjax: the
control law (74)-(78), the adaptive laws (17), (29), (31), (32), the filter (18), the plant
(73) and the hysteresis (4), with u' derived by hand with the chain rule.

State X = [x1, x2, w, z2, theta_g1, theta_2, phi_1, zeta, d_hat].

As a command, it re-simulates the gains of a config of the paper's example (the gains.json of
`dscjax tune`) by classical RK4 on the same grid and prints the windowed L-inf error, max|u|
and TV(u); beside a tuning run's report.json also the start gains', dscjax's own figures and
the problem's bounds; --corners adds the held-out box's 8 corners at dt and dt/10:

    python tests/reference_paper.py results/tune/gains.json [--corners]
"""

from __future__ import annotations

import math

import numpy as np

P = dict(
    g1=1.0, g2=1.0, th1=0.1, th2=0.0, alpha=1.0, lam=1.432, psi=0.105,
    k1=10.0, k2=0.45, gam=8.0, eta1=0.01, eta2=0.01, eta_z=0.01, eta_d=0.01, sigma=0.01,
    eps=0.01, gmin=1.0, tau=0.01, c2=0.1, width=0.01,
)
# Each adaptive law may have its own rate (a tuner's gains do); unset, every law uses `gam`.
RATES = ("gam_g1", "gam_g2", "gam_phi", "gam_z", "gam_d")


def x2d_of(x1, th1h, ph1, t, p=P):
    s1 = x1 - math.sin(t)
    return (-th1h * x1 * x1 - s1 * 0.2**2 / (2 * p["eps"] * p["gmin"]) - p["k1"] * s1
            + ph1 * math.cos(t))


def initial_state(p=P, x0=(0.08, 0.1), w0=0.0, est=(0.05, 0.0, 1.0, 0.5, 1.0)):
    th1h, th2h, ph1, zeta, dh = est
    z2 = x2d_of(x0[0], th1h, ph1, 0.0, p)  # z_2(0) = x_2d(0), eq. (18)
    return np.array([x0[0], x0[1], w0, z2, th1h, th2h, ph1, zeta, dh])


def rhs(t, X, p=P, full=False):
    x1, x2, w, z2, th1h, th2h, ph1, zeta, dh = (float(v) for v in X)
    eps = p["eps"]
    g_g1, g_g2, g_phi, g_z, g_d = (p.get(r, p["gam"]) for r in RATES)
    yr, yr1, yr2 = math.sin(t), math.cos(t), -math.sin(t)

    # control law, eqs. (74)-(78)
    s1 = x1 - yr
    f1 = x1 * x1
    rho1 = 0.2
    x2d = -th1h * f1 - s1 * rho1**2 / (2 * eps * p["gmin"]) - p["k1"] * s1 + ph1 * yr1
    z2dot = (x2d - z2) / p["tau"]
    s2 = x2 - z2 - p["c2"]
    rho2 = 0.1 * (x1 * x1 + x2 * x2)
    f2 = 0.0
    q = s2 / p["width"]
    sat = max(-1.0, min(1.0, q))
    ubar = -p["k2"] * s2 - th2h * f2 - s2 * rho2**2 / (2 * eps) + z2dot - sat * dh
    u = zeta * ubar

    # plant (73) with the true parameters and perturbations
    x1dot = p["g1"] * x2 + p["th1"] * f1 + 0.2 * math.sin(x2)
    x2dot = p["g2"] * w + p["th2"] * f2 + 0.1 * (x1 * x1 + x2 * x2) * math.sin(t) ** 3

    # adaptive laws
    th1dot = g_g1 * (f1 * s1 - p["eta1"] * th1h)
    th2dot = g_g2 * (f2 * s2 - p["eta2"] * th2h)
    ph1dot = -g_phi * (yr1 * s1 + p["sigma"] * ph1)
    zetadot = -g_z * (ubar * s2 + p["eta_z"] * zeta)
    dhdot = g_d * (abs(s2) - p["eta_d"] * dh)

    # u' by the chain rule
    s1dot = x1dot - yr1
    f1dot = 2 * x1 * x1dot
    x2d_dot = (-th1dot * f1 - th1h * f1dot - s1dot * rho1**2 / (2 * eps * p["gmin"])
               - p["k1"] * s1dot + ph1dot * yr1 + ph1 * yr2)
    z2ddot = (x2d_dot - z2dot) / p["tau"]
    s2dot = x2dot - z2dot
    rho2dot = 0.2 * (x1 * x1dot + x2 * x2dot)
    satdot = (s2dot / p["width"]) if abs(q) < 1.0 else 0.0
    ubardot = (-p["k2"] * s2dot - (s2dot * rho2**2 + 2 * s2 * rho2 * rho2dot) / (2 * eps)
               + z2ddot - satdot * dh - sat * dhdot)
    udot = zetadot * ubar + zeta * ubardot

    # hysteresis (4)
    wdot = p["alpha"] * abs(udot) * (p["lam"] * u - w) + p["psi"] * udot

    d = np.array([x1dot, x2dot, wdot, z2dot, th1dot, th2dot, ph1dot, zetadot, dhdot])
    if full:
        return d, dict(u=u, yr=yr, s1=s1, s2=s2, udot=udot)
    return d


def rk4(X0, dt, n_steps, p=P):
    """Classical RK4 on t_k = k dt in plain numpy (the same grid as dscjax)."""
    X = np.array(X0, dtype=float)
    out = np.empty((n_steps + 1, X.size))
    out[0] = X
    for k in range(n_steps):
        t = k * dt
        k1 = rhs(t, X, p)
        k2 = rhs(t + 0.5 * dt, X + 0.5 * dt * k1, p)
        k3 = rhs(t + 0.5 * dt, X + 0.5 * dt * k2, p)
        k4 = rhs(t + dt, X + dt * k3, p)
        X = X + (dt / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)
        out[k + 1] = X
    return out


# -- the sampled (digital) controller, sample by sample ------------------------------------------


def _law(t, X, p=P):
    """u and the controller states' derivatives at (t, X), the plant read exactly."""
    x1, x2, w, z2, th1h, th2h, ph1, zeta, dh = (float(v) for v in X)
    eps = p["eps"]
    g_g1, g_g2, g_phi, g_z, g_d = (p.get(r, p["gam"]) for r in RATES)
    yr, yr1 = math.sin(t), math.cos(t)
    s1 = x1 - yr
    f1 = x1 * x1
    x2d = -th1h * f1 - s1 * 0.2**2 / (2 * eps * p["gmin"]) - p["k1"] * s1 + ph1 * yr1
    z2dot = (x2d - z2) / p["tau"]
    s2 = x2 - z2 - p["c2"]
    rho2 = 0.1 * (x1 * x1 + x2 * x2)
    sat = max(-1.0, min(1.0, s2 / p["width"]))
    ubar = -p["k2"] * s2 - s2 * rho2**2 / (2 * eps) + z2dot - sat * dh
    rates = dict(
        th1=g_g1 * (f1 * s1 - p["eta1"] * th1h), th2=g_g2 * (0.0 - p["eta2"] * th2h),
        ph1=-g_phi * (yr1 * s1 + p["sigma"] * ph1), zeta=-g_z * (ubar * s2 + p["eta_z"] * zeta),
        dh=g_d * (abs(s2) - p["eta_d"] * dh), x2d=x2d)
    return zeta * ubar, rates


def _backlash_step(w, u_from, u_to, p=P):
    """w after u moves monotonically from u_from to u_to: dw/du = s alpha (lam u - w) + psi."""
    if u_to == u_from:
        return w
    s = 1.0 if u_to > u_from else -1.0
    a, lam, psi = p["alpha"], p["lam"], p["psi"]
    # the linear ODE's solution: w = lam u - s (lam - psi)/a + C e^(-s a u)
    c = (w - lam * u_from + s * (lam - psi) / a) * math.exp(s * a * u_from)
    return lam * u_to - s * (lam - psi) / a + c * math.exp(-s * a * u_to)


def sampled_rk4(X0, dt, n_steps, every, p=P, delay=0, scheme="exponential-euler"):
    """The loop with the controller sampled every `every` steps (Ts = every dt): at each
    sample the law reads x, and the input computed `delay` samples before (the first one
    while there is none) is held until the next sample (the hysteresis jumps along its curve
    when it changes); the filter advances by its exact response to the held x2d
    (z <- x2d + (z - x2d) e^(-Ts/tau)) and the estimates by forward Euler; the plant is
    integrated by RK4 with w held. scheme "euler": the filter by forward Euler too,
    z <- z + Ts (x2d - z)/tau. Returns (states (N+1, 9), held u (N+1,))."""
    X = np.array(X0, dtype=float)
    ts = every * dt
    u_held, _ = _law(0.0, X, p)
    computed = []
    out = np.empty((n_steps + 1, X.size))
    us = np.empty(n_steps + 1)
    for k in range(n_steps + 1):
        t = k * dt
        if k % every == 0:  # the controller's sample at t_k
            u_law, r = _law(t, X, p)
            computed.append(u_law)
            u_new = computed[max(len(computed) - 1 - delay, 0)]
            X[2] = _backlash_step(X[2], u_held, u_new, p)
            if scheme == "euler":
                X[3] += ts * (r["x2d"] - X[3]) / p["tau"]
            else:
                X[3] = r["x2d"] + (X[3] - r["x2d"]) * math.exp(-ts / p["tau"])
            X[4] += ts * r["th1"]
            X[5] += ts * r["th2"]
            X[6] += ts * r["ph1"]
            X[7] += ts * r["zeta"]
            X[8] += ts * r["dh"]
            u_held = u_new
        out[k], us[k] = X, u_held
        if k == n_steps:
            break

        def plant(tt, x, w=X[2]):
            x1, x2 = x
            return np.array([p["g1"] * x2 + p["th1"] * x1 * x1 + 0.2 * math.sin(x2),
                             p["g2"] * w + 0.1 * (x1 * x1 + x2 * x2) * math.sin(tt) ** 3])

        x = X[:2]
        k1 = plant(t, x)
        k2 = plant(t + 0.5 * dt, x + 0.5 * dt * k1)
        k3 = plant(t + 0.5 * dt, x + 0.5 * dt * k2)
        k4 = plant(t + dt, x + dt * k3)
        X[:2] = x + (dt / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)
    return out, us


# -- the command: a config's gains re-simulated -------------------------------------------------

# The parts of the paper's example this loop hard-codes: a config must have these values.
FIXED = {"controller.kind": "dsc", "controller.variant": "full", "controller.robust_term": "sat",
         "controller.init": "paper", "hysteresis.kind": "backlash", "hysteresis.smooth": False,
         "plant.family": "paper", "plant.rho1": 0.2, "plant.rho2": 0.1, "plant.delta1": 0.2,
         "plant.delta2": 0.1, "plant.delta_freq": 1.0, "plant.dbar_amp": 0.0,
         "plant.dbar_bias": 0.0, "reference.kind": "sine", "reference.amplitude": 1.0,
         "reference.frequency": 1.0, "reference.phase": 0.0, "reference.offset": 0.0}


class Refused(Exception):
    """A config this loop does not implement (one line for the user)."""


def params_of(cfg: dict) -> dict:
    """This loop's parameters for a config (a dscjax config dict) of the paper's example."""
    for path, value in FIXED.items():
        section, key = path.split(".")
        got = cfg.get(section, {}).get(key, value)
        if got != value:
            raise Refused(f"{path} must be {value!r} here: this loop implements the paper's "
                          f"example only (got {got!r})")
    c, h, pl = cfg["controller"], cfg["hysteresis"], cfg["plant"]
    g, th = pl["g"], pl["theta"]
    return dict(P, g1=g[0], g2=g[1], th1=th[0], th2=th[1], alpha=h["alpha"], lam=h["lam"],
                psi=h["psi"], k1=c["k"][0], k2=c["k"][1], gam_g1=c["gamma_g"][0],
                gam_g2=c["gamma_g"][1], gam_phi=c["gamma_phi"][0], gam_z=c["gamma_zeta"],
                gam_d=c["gamma_d"], eta1=c["eta"][0], eta2=c["eta"][1], eta_z=c["eta_zeta"],
                eta_d=c["eta_d"], sigma=c["sigma"][0], eps=c["eps"], gmin=c["g_min"],
                tau=c["tau"][0], c2=c["c"][0], width=c["sat_width"])


def figures(cfg: dict, t_final: float, dt: float, window_start: float) -> dict:
    """Windowed L-inf of e on [window_start, T], max|u| and TV(u) = sum |u_(k+1) - u_k| over
    the step grid; {"finite": False} if the run blows up."""
    p, c, pl = params_of(cfg), cfg["controller"], cfg["plant"]
    est = (c["theta_hat0"][0], c["theta_hat0"][1], c["phi_hat0"][0], c["zeta_hat0"],
           c["d_hat0"])
    n = int(round(t_final / dt))
    try:
        with np.errstate(all="ignore"):
            X = rk4(initial_state(p, x0=tuple(pl["x0"]), w0=cfg["hysteresis"]["w0"], est=est),
                    dt, n, p)
            t = np.arange(n + 1) * dt
            u = np.array([rhs(tk, Xk, p, full=True)[1]["u"] for tk, Xk in zip(t, X,
                                                                             strict=True)])
    except (ValueError, OverflowError):  # math raises where the run overflows
        return {"finite": False}
    if not np.all(np.isfinite(X)):
        return {"finite": False}
    keep = t >= window_start - 1e-12
    return {"finite": True,
            "linf_error_window": float(np.max(np.abs(X[keep, 0] - np.sin(t[keep])))),
            "max_abs_u": float(np.max(np.abs(u))), "tv_u": float(np.sum(np.abs(np.diff(u))))}


def _line(name: str, f: dict, dscjax_figures: dict | None = None) -> str:
    if not f["finite"]:
        return f"{name}: blows up"
    out = (f"{name}: L-inf {f['linf_error_window']:.6g}, max|u| {f['max_abs_u']:.6g}, "
           f"TV(u) {f['tv_u']:.6g}")
    if dscjax_figures:
        rel = [abs(f[k] - dscjax_figures[k]) / abs(dscjax_figures[k])
               for k in ("linf_error_window", "max_abs_u", "tv_u") if dscjax_figures.get(k)]
        out += f" (dscjax's report: largest relative difference {max(rel):.1e})"
    return out


def main(argv=None) -> int:
    import argparse
    import json
    import sys
    from pathlib import Path

    ap = argparse.ArgumentParser(
        prog="reference_paper.py", description="Re-simulate the gains of a config of the "
        "paper's example (e.g. the gains.json of dscjax tune) in this independent loop.")
    ap.add_argument("gains", help="a JSON config of the paper's example")
    ap.add_argument("--corners", action="store_true",
                    help="also the corners of the held-out box (alpha, lam, psi +-30 %%) at dt "
                    "and dt/10")
    a = ap.parse_args(argv)
    path = Path(a.gains)
    try:
        cfg = json.loads(path.read_text())
        sim = cfg.get("simulation", {})
        t_final, dt = float(sim.get("t_final", 20.0)), float(sim.get("dt", 1e-3))
        window = sim.get("window_start")
        window = (1.0 if t_final > 1.0 else 0.0) if window is None else float(window)
        tuned = figures(cfg, t_final, dt, window)
        report_path = path.with_name("report.json")
        report = json.loads(report_path.read_text()) if report_path.exists() else None
        start = None
        if report is not None:
            start = figures(report["settings"]["setup"], t_final, dt, window)
    except (OSError, ValueError, KeyError, TypeError, Refused) as err:
        what = f"missing key {err}" if isinstance(err, KeyError) else str(err)
        print(f"reference_paper.py: error: {path}: {what}", file=sys.stderr)
        return 2
    nominal = (report or {}).get("nominal", {})
    print(f"{path}: T = {t_final:g} s, dt = {dt:g}, windowed L-inf on [{window:g} s, T]")
    print(_line("gains", tuned, nominal.get("tuned")))
    if start is not None and start["finite"] and tuned["finite"]:
        factor = report["settings"]["objective"].get("tv_max_factor", 1.5)
        print(_line("start gains", start, nominal.get("start")))
        print(f"L-inf {start['linf_error_window'] / tuned['linf_error_window']:.4g}x lower; "
              f"max|u| {tuned['max_abs_u']:.6g} <= {start['max_abs_u']:.6g}: "
              f"{tuned['max_abs_u'] <= start['max_abs_u'] * (1 + 1e-9)}; TV(u) "
              f"{tuned['tv_u']:.6g} <= {factor:g} x {start['tv_u']:.6g}: "
              f"{tuned['tv_u'] <= factor * start['tv_u'] * (1 + 1e-9)}")
    if a.corners:
        h = cfg["hysteresis"]
        for fa in (0.7, 1.3):
            for fl in (0.7, 1.3):
                for fp in (0.7, 1.3):
                    c = json.loads(json.dumps(cfg))
                    c["hysteresis"].update(alpha=fa * h["alpha"], lam=fl * h["lam"],
                                           psi=fp * h["psi"])
                    runs = [_line(f"dt {d:g}", figures(c, t_final, d, window))
                            for d in (dt, dt / 10)]
                    print(f"corner alpha x{fa:g}, lam x{fl:g}, psi x{fp:g}: " + "; ".join(runs))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
