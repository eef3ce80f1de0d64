"""An independent implementation of the paper's closed loop (Section 4, eq. 73), for tests.

Written by hand from the paper in plain Python floats, sharing no code with dscjax: the
control law (74)-(78), the adaptive laws (17), (29), (31), (32), the filter (18), the plant
(73) and the hysteresis (4), with u' derived by hand with the chain rule.

State X = [x1, x2, w, z2, theta_g1, theta_2, phi_1, zeta, d_hat].
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


def sampled_rk4(X0, dt, n_steps, every, p=P, delay=0):
    """The loop with the controller sampled every `every` steps (Ts = every dt): at each
    sample the law reads x, and the input computed `delay` samples before (the first one
    while there is none) is held until the next sample (the hysteresis jumps along its curve
    when it changes); the filter advances by its exact response to the held x2d
    (z <- x2d + (z - x2d) e^(-Ts/tau)) and the estimates by forward Euler; the plant is
    integrated by RK4 with w held. Returns (states (N+1, 9), held u (N+1,))."""
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
