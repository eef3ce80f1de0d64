"""Open-loop check of every hysteresis model (issue 15's target) and of how the plays are
advanced.

1. For u = 3.5 sin(2.3 t), dt = 1e-3, 6 s, runs `dscjax hysteresis --example KIND` for each
   model and compares its loop.npz with an independent implementation of the definitions:
   backlash by the closed form (5)-(6) on each monotone segment, P-I and generalized P-I by
   the play recursion in NumPy on the step grid with the input's extrema inserted (the
   continuous-time operator), Bouc-Wen by scipy's DOP853 at rtol = atol = 1e-12, restarted at
   every reversal of u. Target: max|w - w_ref| <= 1e-4 max|w_ref|.
2. The ODE form z' = u' [on the active branch] of the P-I plays, by the same RK4 in NumPy,
   against the same reference: what the exact clamp (`hysteresis.py`) avoids.

Usage: python experiments/hysteresis_open_loop.py [--out DIR]   (about 20 s)
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

from dscjax.cli.main import main as dscjax_main
from dscjax.config import example

A, OMEGA, T, DT = 3.5, 2.3, 6.0, 1e-3


def u_of(t):
    return A * np.sin(OMEGA * t)


def du_of(t):
    return A * OMEGA * np.cos(OMEGA * t)


def reversals(t_final):
    """Times of the extrema of u on (0, t_final)."""
    k = np.arange(0, int(t_final * OMEGA / np.pi) + 2)
    tk = (np.pi / 2 + k * np.pi) / OMEGA
    return tk[(tk > 0) & (tk < t_final)]


def ref_backlash(h, t):
    alpha, lam, psi, w = (float(h.alpha), float(h.lam), float(h.psi), float(h.w0))
    edges = np.concatenate([[0.0], reversals(t[-1]), [t[-1]]])
    out = np.empty_like(t)
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        s = np.sign(du_of(0.5 * (a + b)))
        u0 = u_of(a)
        sel = (t >= a) & (t <= b)
        for tt, idx in ((t[sel], sel), (np.array([b]), None)):
            decay = np.exp(-alpha * s * (u_of(tt) - u0))
            val = lam * u_of(tt) + (w - lam * u0) * decay + (psi - lam) / (alpha * s) * (1 - decay)
            if idx is not None:
                out[idx] = val
            else:
                w_next = val[0]
        w = w_next
    return out


def ref_plays(h, t):
    """w at the grid times by the play recursion over the grid and the extrema of u."""
    r, p, p0 = (np.asarray(x, float) for x in (h.r, h.p, h.p0))
    if h.kind == "pi":
        def band(u):
            return u - r, u + r
    else:
        el, er = np.asarray(h.envelope_left, float), np.asarray(h.envelope_right, float)

        def band(u):
            return (el[0] * np.tanh(el[1] * u + el[2]) + el[3] - r,
                    er[0] * np.tanh(er[1] * u + er[2]) + er[3] + r)
    tt = np.concatenate([t, reversals(t[-1])])
    order = np.argsort(tt, kind="stable")
    on_grid = order < len(t)
    z = np.broadcast_to(np.asarray(h.z0, float), r.shape).copy()
    w = []
    for i, k in enumerate(order):
        lo, hi = band(u_of(tt[k]))
        z = np.maximum(lo, np.minimum(hi, z))
        if on_grid[i]:
            w.append(p0 * u_of(tt[k]) + p @ z)
    return np.array(w)


def ref_bouc_wen(h, t):
    a, b, A_, beta, gamma, n = (float(x) for x in (h.a, h.b, h.A, h.beta, h.gamma, h.n))

    def rhs(tt, y):
        du, hh = du_of(tt), y[0]
        return [A_ * du - beta * abs(du) * abs(hh) ** (n - 1) * hh - gamma * du * abs(hh) ** n]

    edges = np.concatenate([[0.0], reversals(t[-1]), [t[-1]]])
    hh, out = float(h.h0), np.empty_like(t)
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        sel = (t >= lo) & (t <= hi)
        sol = solve_ivp(rhs, (lo, hi), [hh], method="DOP853", rtol=1e-12, atol=1e-12,
                        dense_output=True)
        out[sel] = sol.sol(t[sel])[0]
        hh = sol.y[0, -1]
    return a * u_of(t) + b * out


def ode_form_pi(h, t):
    """The plays as the ODE z' = u' [on the active branch], classical RK4 (the rejected form)."""
    r, p, p0 = (np.asarray(x, float) for x in (h.r, h.p, h.p0))

    def rate(tt, z):
        u, du = u_of(tt), du_of(tt)
        dragged = ((z <= u - r) & (du > 0)) | ((z >= u + r) & (du < 0))
        return np.where(dragged, du, 0.0)

    z = np.maximum(u_of(0.0) - r, np.minimum(u_of(0.0) + r, np.zeros_like(r)))
    w = [p0 * u_of(0.0) + p @ z]
    for k in range(len(t) - 1):
        tk = t[k]
        k1 = rate(tk, z)
        k2 = rate(tk + DT / 2, z + DT / 2 * k1)
        k3 = rate(tk + DT / 2, z + DT / 2 * k2)
        k4 = rate(tk + DT, z + DT * k3)
        z = z + DT / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        w.append(p0 * u_of(t[k + 1]) + p @ z)
    return np.array(w)


REFS = {"paper": ref_backlash, "pi": ref_plays, "gpi": ref_plays, "bouc_wen": ref_bouc_wen}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=None, help="keep the loops here (default: a temp dir)")
    args = ap.parse_args()
    root = Path(args.out or tempfile.mkdtemp(prefix="dscjax-open-loop-"))
    rows = {}
    for name, ref in REFS.items():
        out = root / name
        rc = dscjax_main(["hysteresis", "--example", name, "--amplitude", str(A), "--omega",
                          str(OMEGA), "--t-final", str(T), "--dt", str(DT), "--out", str(out)])
        assert rc == 0, rc
        with np.load(out / "loop.npz") as f:
            t, w = f["t"], f["w"][0]
        h = example(name, dtype=np.float64).hysteresis
        w_ref = ref(h, t)
        err = float(np.max(np.abs(w - w_ref)) / np.max(np.abs(w_ref)))
        rows[h.kind] = {"max_abs_w": float(np.max(np.abs(w_ref))), "rel_error": err,
                        "target_met": err <= 1e-4}
        print(f"{h.kind:9s} max|w| = {np.max(np.abs(w_ref)):.4f}  "
              f"max|w - w_ref| / max|w_ref| = {err:.2e}  {'ok' if err <= 1e-4 else 'MISSED'}")
    h = example("pi", dtype=np.float64).hysteresis
    t = np.arange(int(round(T / DT)) + 1) * DT
    w_ref = ref_plays(h, t)
    err_ode = float(np.max(np.abs(ode_form_pi(h, t) - w_ref)) / np.max(np.abs(w_ref)))
    rows["pi_ode_form"] = {"rel_error": err_ode}
    print(f"P-I plays as the ODE z' = u' [active branch], RK4: {err_ode:.2e} of max|w| "
          f"(the exact clamp: {rows['pi']['rel_error']:.2e})")
    (root / "summary.json").write_text(json.dumps(rows, indent=1))
    print(f"wrote {root}/summary.json")


if __name__ == "__main__":
    main()
