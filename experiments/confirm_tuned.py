"""Tuned gains of the paper's example re-simulated by an independent implementation.

    .venv/bin/python experiments/confirm_tuned.py results/tune [--out results/confirm_tuned]

Reads DIR/gains.json and DIR/report.json written by `dscjax tune` on the paper's example
(DSC, backlash hysteresis, paper plant) and simulates the start (paper's) gains and the tuned
gains with the plain-Python implementation of the paper's loop (tests/reference_paper.py,
sharing no code with dscjax) by classical RK4 on the same grid. Prints and writes
confirm_tuned.json: the windowed L-inf tracking error on [window_start, T], max|u| and
TV(u) = sum_k |u_(k+1) - u_k| over the step grid, from the reference and from the tuner's
report, and the reference's figures against the deployable problem's bounds (max|u| <= the
start's, TV(u) <= tv_max_factor x the start's). With --corners, the tuned gains also run on
the 8 corners of the held-out box (hysteresis alpha, lam, psi +-30 %) at dt and at dt/10: a
plant that blows up at dt and tracks at dt/10 is numerically stiff at dt, not unstable.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
import reference_paper as ref  # noqa: E402

from dscjax.metrics import default_window  # noqa: E402


def reference_params(cfg: dict) -> dict:
    """The reference's parameter dict for a config (gains.json) of the paper's example."""
    c, h, pl = cfg["controller"], cfg["hysteresis"], cfg["plant"]
    if (c["kind"], h["kind"], pl["family"]) != ("dsc", "backlash", "paper"):
        raise SystemExit("confirm_tuned: the reference implements the paper's example only "
                         "(dsc, backlash, paper plant)")
    if (c.get("variant", "full"), c.get("robust_term", "sat")) != ("full", "sat"):
        raise SystemExit("confirm_tuned: the reference implements variant 'full' with the "
                         "sat robust term only")
    g, th = pl["g"], pl["theta"]
    return dict(ref.P, g1=g[0], g2=g[1], th1=th[0], th2=th[1], alpha=h["alpha"], lam=h["lam"],
                psi=h["psi"], k1=c["k"][0], k2=c["k"][1], gam_g1=c["gamma_g"][0],
                gam_g2=c["gamma_g"][1], gam_phi=c["gamma_phi"][0], gam_z=c["gamma_zeta"],
                gam_d=c["gamma_d"], eta1=c["eta"][0], eta2=c["eta"][1], eta_z=c["eta_zeta"],
                eta_d=c["eta_d"], sigma=c["sigma"][0], eps=c["eps"], gmin=c["g_min"],
                tau=c["tau"][0], c2=c["c"][0], width=c["sat_width"])


def figures(p: dict, cfg: dict, t_final: float, dt: float, window_start: float) -> dict:
    c, pl = cfg["controller"], cfg["plant"]
    est = (c["theta_hat0"][0], c["theta_hat0"][1], c["phi_hat0"][0], c["zeta_hat0"],
           c["d_hat0"])
    n = int(round(t_final / dt))
    X = ref.rk4(ref.initial_state(p, x0=tuple(pl["x0"]), w0=cfg["hysteresis"]["w0"], est=est),
                dt, n, p)
    t = np.arange(n + 1) * dt
    u = np.array([ref.rhs(tk, Xk, p, full=True)[1]["u"] for tk, Xk in zip(t, X, strict=True)])
    keep = t >= window_start - 1e-12
    return dict(linf_error_window=float(np.max(np.abs(X[keep, 0] - np.sin(t[keep])))),
                max_abs_u=float(np.max(np.abs(u))), tv_u=float(np.sum(np.abs(np.diff(u)))),
                finite=bool(np.all(np.isfinite(X))))


def _blown_up_or(f, *args) -> dict:
    """f(*args), or {"finite": False} when the plain-Python run overflows (math raises)."""
    try:
        with np.errstate(all="ignore"):
            return f(*args)
    except (ValueError, OverflowError):
        return {"finite": False}


def corners(cfg: dict, t_final: float, dt: float, window_start: float) -> list[dict]:
    h = cfg["hysteresis"]
    rows = []
    for a in (0.7, 1.3):
        for lam in (0.7, 1.3):
            for psi in (0.7, 1.3):
                c = json.loads(json.dumps(cfg))
                c["hysteresis"].update(alpha=a * h["alpha"], lam=lam * h["lam"],
                                       psi=psi * h["psi"])
                p = reference_params(c)
                runs = [dict(dt=d, **_blown_up_or(figures, p, c, t_final, d, window_start))
                        for d in (dt, dt / 10)]
                rows.append(dict(alpha=c["hysteresis"]["alpha"], lam=c["hysteresis"]["lam"],
                                 psi=c["hysteresis"]["psi"], runs=runs))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("tune_dir", help="the --out directory of a `dscjax tune` run")
    ap.add_argument("--out", default="results/confirm_tuned")
    ap.add_argument("--corners", action="store_true", help="also the held-out box's corners")
    args = ap.parse_args(argv)
    d = Path(args.tune_dir)
    tuned = json.loads((d / "gains.json").read_text())
    report = json.loads((d / "report.json").read_text())
    sim = tuned["simulation"]
    t_final, dt = sim["t_final"], sim["dt"]
    settings = report["settings"]
    start_cfg = settings["setup"]  # the start gains' complete setup, as the tuner read it
    window_start = default_window(t_final, settings["objective"].get("window_start"))
    rows = {}
    for tag, cfg in (("start", start_cfg), ("tuned", tuned)):
        ours = report["nominal"][tag]
        refd = figures(reference_params(cfg), cfg, t_final, dt, window_start)
        rows[tag] = dict(reference=refd, dscjax={k: ours.get(k) for k in refd if k in ours})
    bound_u = rows["start"]["reference"]["max_abs_u"]
    factor = settings["objective"]["tv_max_factor"]
    bound_tv = factor * rows["start"]["reference"]["tv_u"]
    r = rows["tuned"]["reference"]
    result = dict(
        tune_dir=str(d), t_final=t_final, dt=dt, window_start=window_start, rows=rows,
        improvement=rows["start"]["reference"]["linf_error_window"] / r["linf_error_window"],
        max_abs_u_met=r["max_abs_u"] <= bound_u * (1 + 1e-9), bound_max_abs_u=bound_u,
        tv_u_met=r["tv_u"] <= bound_tv * (1 + 1e-9), bound_tv_u=bound_tv)
    print(f"{'gains':6} {'figure':18} {'reference':>12} {'dscjax':>12} {'rel. diff':>10}")
    for tag, row in rows.items():
        for k, v in row["reference"].items():
            if k == "finite":
                continue
            o = row["dscjax"].get(k)
            rel = abs(v - o) / abs(o) if o else float("nan")
            print(f"{tag:6} {k:18} {v:12.6g} {o if o is None else f'{o:12.6g}':>12} {rel:10.2e}")
    print(f"reference: L-inf {result['improvement']:.2f}x lower with the tuned gains; max|u| "
          f"{r['max_abs_u']:.4f} <= {bound_u:.4f}: {result['max_abs_u_met']}; TV(u) "
          f"{r['tv_u']:.3f} <= {bound_tv:.3f}: {result['tv_u_met']}")
    if args.corners:
        result["corners"] = corners(tuned, t_final, dt, window_start)
        for c in result["corners"]:
            print(f"corner alpha {c['alpha']:.4g} lam {c['lam']:.4g} psi {c['psi']:.4g}: "
                  + ", ".join(f"dt {r['dt']:g}: " + (f"L-inf {r['linf_error_window']:.4g}"
                                                    if r["finite"] else "blows up")
                              for r in c["runs"]))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "confirm_tuned.json").write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
