"""Cost, accuracy and memory of exact gradients through the public API, with default arguments.

    python experiments/bench_gradient.py            # 20 s horizon, batch of 256 plants
    python experiments/bench_gradient.py --quick    # 5 s horizon, batch of 16 (a smoke test)

The objective (issue 10): J = L-inf + L2 of the tracking error on [1 s, T], through
`dscjax.simulate` (save_every = 1000, everything else default) for the nominal plant, and the
mean of J over a batch of plants (alpha, lambda, psi +-30 %) through `dscjax.simulate_batch`,
differentiated with respect to the 13 DSC design numbers the tuner tunes (log-space).

1. Cost, relative to the jitted forward run of the same objective (medians of --repeats runs,
   interleaved so that load hits every method alike; compilation timed apart):
   - value_and_grad (reverse mode; the default time-parallel linearisation for one trajectory,
     the checkpointed scan for a batch),
   - jacfwd (forward mode),
   - value_and_grad with gradient="autodiff" (JAX's own reverse mode of the scan: the
     "today" of issue 10, one trajectory only),
   - finite differences as ONE batched simulation (forward: P+1 members, central: 2P).
2. Accuracy: forward against reverse mode; finite differences at several steps h.
3. Where the time goes: HLO instruction counts of the loop bodies and XLA's flop counts of one
   RK4 step, its jvp (one direction) and its vjp.
4. Peak RSS of the batch gradient (fresh process per configuration).
5. The robust tuning objective (CVaR 0.25 over 8 plants): its gradient in each tuner mode
   (forward over the batch, reverse, "plants") against its forward run (--skip-tuning: not).

Prints the tables and writes results/bench_gradient.json (or --out).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def _setup_jax():
    import jax

    jax.config.update("jax_enable_x64", True)
    return jax


def problem(t_final: float, batch: int = 0, seed: int = 0):
    """(J(z) of one plant, J(z) mean over a batch or None, z0, names)."""
    jax = _setup_jax()
    import jax.numpy as jnp

    import dscjax
    import tuning
    from tuning.runner import PAPER_PLANT_FREEZE

    setup = dscjax.paper_example()
    sel = tuning.Selection.build(setup, tuning.DSC_GAINS, freeze=PAPER_PLANT_FREEZE)
    z0 = sel.init(setup)
    n = int(round(t_final / 1e-3))
    save = 1000 if n % 1000 == 0 else n

    def objective(m):
        return m["linf_error_window"] + m["l2_error_window"]

    def J(z, gradient="time_parallel"):
        traj = dscjax.simulate(sel.apply(setup, z), t_final, 1e-3, save_every=save,
                               throw=False, gradient=gradient)
        return objective(traj.metrics)

    Jb = None
    if batch:
        rng = np.random.default_rng(seed)
        h = setup.hysteresis
        ov = {f"hysteresis.{k}": jnp.asarray(float(getattr(h, k)) * rng.uniform(0.7, 1.3, batch))
              for k in ("alpha", "lam", "psi")}

        def Jb(z):
            traj = dscjax.simulate_batch(sel.apply(setup, z), ov, t_final, 1e-3)
            return jnp.mean(objective(traj.metrics))

    del jax
    return J, Jb, z0, list(sel.names), sel, setup


def interleaved(fns: dict, arg, repeats: int) -> dict:
    """Compile each, then time all of them round-robin (load hits every method alike)."""
    jax = _setup_jax()
    out = {}
    for name, fn in fns.items():
        t0 = time.perf_counter()
        jax.block_until_ready(fn(arg))
        out[name] = {"first_call_s": time.perf_counter() - t0, "runs_s": []}
    for _ in range(repeats):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn(arg))
            out[name]["runs_s"].append(time.perf_counter() - t0)
    for v in out.values():
        v["median_s"] = float(np.median(v["runs_s"]))
        v["compile_s"] = max(v["first_call_s"] - v["median_s"], 0.0)
    return out


def fd_points(flat0: np.ndarray, central: bool, h: float) -> np.ndarray:
    steps = np.eye(flat0.size) * h
    if central:
        return np.concatenate([flat0 + steps, flat0 - steps])
    return np.concatenate([flat0[None], flat0 + steps])


def fd_gradient(values: np.ndarray, central: bool, h: float) -> np.ndarray:
    n = values.size // 2 if central else values.size - 1
    if central:
        return (values[:n] - values[n:]) / (2 * h)
    return (values[1:] - values[0]) / h


def batched_J(sel, setup, t_final):
    """J at many points z (rows of a flat array) as ONE batched simulation."""
    jax = _setup_jax()
    import jax.numpy as jnp
    from jax.flatten_util import ravel_pytree

    import dscjax
    from dscjax import params

    _, unravel = ravel_pytree(sel.init(setup))
    paths = sorted({t.path for t in sel.items})

    def run(pts):
        setups = jax.vmap(lambda p: sel.apply(setup, unravel(p)))(pts)
        ov = {p: params.get(setups, p) for p in paths}
        traj = dscjax.simulate_batch(setup, ov, t_final, 1e-3, refine=0)
        m = traj.metrics
        return m["linf_error_window"] + m["l2_error_window"]

    return lambda pts: run(jnp.asarray(pts))


def costs(t_final: float, repeats: int, batch: int) -> dict:
    jax = _setup_jax()
    from jax.flatten_util import ravel_pytree

    J, Jb, z0, names, sel, setup = problem(t_final, batch)
    res = {"t_final": t_final, "n_steps": int(round(t_final / 1e-3)), "params": names,
           "n_params": len(ravel_pytree(z0)[0])}
    single = {
        "forward": jax.jit(J),
        "value_and_grad": jax.jit(jax.value_and_grad(J)),
        "jacfwd": jax.jit(jax.jacfwd(J)),
        "value_and_grad_autodiff": jax.jit(jax.value_and_grad(lambda z: J(z, "autodiff"))),
    }
    print("  timing one trajectory ...", file=sys.stderr, flush=True)
    res["single"] = interleaved(single, z0, repeats)
    grads = {k: np.asarray(ravel_pytree(single[k](z0)[1] if k != "jacfwd" else single[k](z0))[0])
             for k in ("value_and_grad", "jacfwd", "value_and_grad_autodiff")}
    # finite differences: all members in one batched simulation
    flat0 = np.asarray(ravel_pytree(z0)[0])
    run = batched_J(sel, setup, t_final)
    fd = {}
    for central in (False, True):
        pts = fd_points(flat0, central, 1e-5)
        key = f"fd_{'central' if central else 'forward'}_batched"
        fd[key] = lambda _z, pts=pts, c=central: fd_gradient(np.asarray(run(pts)), c, 1e-5)
    fd_t = interleaved(fd, z0, repeats)
    for k, v in fd_t.items():
        v["members"] = int(fd_points(flat0, "central" in k, 1e-5).shape[0])
    res["single"] |= fd_t
    base = res["single"]["forward"]["median_s"]
    for v in res["single"].values():
        v["ratio_to_forward"] = v["median_s"] / base
    ref = grads["value_and_grad_autodiff"]
    scale = np.max(np.abs(ref))
    acc = {"time_parallel_vs_autodiff_max_rel": float(np.max(np.abs(grads["value_and_grad"] - ref))
                                                      / scale),
           "jacfwd_vs_autodiff_max_rel": float(np.max(np.abs(grads["jacfwd"] - ref)) / scale),
           "fd": []}
    for central in (False, True):
        for h in (1e-3, 1e-4, 1e-5, 1e-6, 1e-7):
            g = fd_gradient(np.asarray(run(fd_points(flat0, central, h))), central, h)
            acc["fd"].append({"central": central, "h": h,
                              "max_rel_error": float(np.max(np.abs(g - ref)) / scale)})
    res["accuracy"] = acc
    if Jb is not None:
        print(f"  timing a batch of {batch} ...", file=sys.stderr, flush=True)
        b = interleaved({"forward": jax.jit(Jb), "value_and_grad": jax.jit(jax.value_and_grad(Jb)),
                         "jacfwd": jax.jit(jax.jacfwd(Jb))}, z0, max(repeats // 2, 2))
        for v in b.values():
            v["ratio_to_forward"] = v["median_s"] / b["forward"]["median_s"]
        res["batch"] = {"size": batch} | b
    return res


def tuning_modes(t_final: float, repeats: int, batch: int = 8, level: float = 0.25) -> dict:
    """The robust tuning objective (`dscjax tune`'s: CVaR at `level` over `batch` plants,
    alpha, lam, psi +-30 %, the default terms and bounds): one batched forward run against
    its exact gradient in each tuner mode (`tuning.optimize.value_and_grad`): forward over
    the batch, reverse through the checkpointed batch, and "plants" (only the worst
    ceil(level B) plants, each by the time-parallel linearisation)."""
    jax = _setup_jax()
    from jax.flatten_util import ravel_pytree

    import dscjax
    import tuning
    from dscjax.runspec import RunSpec
    from tuning.optimize import value_and_grad

    cfg = tuning.TuningConfig(robust=tuning.BatchSpec(batch=batch, seed=0, aggregate="cvar",
                                                      cvar_level=level),
                              heldout=tuning.BatchSpec(batch=0))
    prob = tuning.build_problem(dscjax.paper_example(), RunSpec.make(t_final=t_final), cfg)
    obj = prob.objective
    ce = cfg.optimizer.checkpoint_every
    fns = {"forward_run": jax.jit(lambda z: obj.evaluate(z)[0])}
    for mode in ("forward", "reverse", "plants"):
        fns[mode] = jax.jit(lambda z, m=mode: value_and_grad(obj, z, m, ce))
    print(f"  timing the robust tuning objective (CVaR {level:g} of {batch} plants) ...",
          file=sys.stderr, flush=True)
    res = interleaved(fns, prob.z0, repeats)
    for v in res.values():
        v["ratio_to_forward"] = v["median_s"] / res["forward_run"]["median_s"]
    g = {m: np.asarray(ravel_pytree(fns[m](prob.z0)[1])[0]) for m in ("forward", "reverse",
                                                                      "plants")}
    scale = np.max(np.abs(g["forward"]))
    return {"batch": batch, "cvar_level": level, "n_params": prob.n_params,
            "auto_mode": prob.mode, "modes": res,
            "plants_vs_forward_max_rel": float(np.max(np.abs(g["plants"] - g["forward"])) / scale),
            "reverse_vs_forward_max_rel": float(np.max(np.abs(g["reverse"] - g["forward"]))
                                                / scale)}


# -- where the time goes --------------------------------------------------------------------------


def _while_bodies(hlo: str) -> list[int]:
    comps = {}
    for comp in re.split(r"\n(?=\S)", hlo):
        m = re.match(r"(?:ENTRY )?%?([\w.\-]+)", comp.split("\n")[0])
        if m:
            comps[m.group(1)] = comp
    bodies = re.findall(r"while\(.*?body=%?([\w.\-]+)", hlo)
    return [sum(1 for line in comps.get(b, "").split("\n")[1:] if " = " in line) for b in bodies]


def anatomy(t_final: float) -> dict:
    """HLO instruction counts of the loop bodies; XLA's flops of one step, its jvp and vjp."""
    jax = _setup_jax()
    import jax.numpy as jnp

    import dscjax
    from dscjax.closed_loop import initial_state, prepared, vector_field
    from dscjax.integrate import _Packer, _rk4

    J, _, z0, _, _, _ = problem(t_final)
    out = {"loop_bodies": {}}
    for name, fn in (("forward", J), ("value_and_grad", jax.value_and_grad(J)),
                     ("value_and_grad_autodiff", jax.value_and_grad(lambda z: J(z, "autodiff")))):
        hlo = jax.jit(fn).lower(z0).compile().as_text()
        out["loop_bodies"][name] = sorted(_while_bodies(hlo), reverse=True)
    s = prepared(dscjax.canonical(dscjax.paper_example()))
    yp, ap = _Packer(initial_state(s)), _Packer(s)
    y, a = yp.pack(initial_state(s)), ap.pack(s)

    def step(y, a):
        def f_obs(t, yy):
            dy, obs = vector_field(t, yp.unpack(yy), ap.unpack(a))
            return yp.pack(dy), obs

        return _rk4(f_obs, jnp.asarray(0.3), y, jnp.asarray(1e-3))[0]

    def flops(fn, *args):
        ca = jax.jit(fn).lower(*args).compile().cost_analysis()
        ca = ca[0] if isinstance(ca, list) else ca
        return {"flops": float(ca.get("flops", 0)),
                "transcendentals": float(ca.get("transcendentals", 0))}

    out["one_step"] = {
        "step": flops(step, y, a),
        "jvp_one_direction": flops(lambda y, a: jax.jvp(step, (y, a), (y, a))[1], y, a),
        "vjp_state_and_params": flops(lambda y, a: jax.vjp(step, y, a)[1](step(y, a)), y, a),
    }
    return out


# -- memory: one subprocess per configuration -----------------------------------------------------


def child(args) -> None:
    jax = _setup_jax()
    J, Jb, z0, _, _, _ = problem(args.t_final, batch=args.batch)
    fn = {"forward": Jb, "value_and_grad": jax.value_and_grad(Jb),
          "jacfwd": jax.jacfwd(Jb)}[args.mode]
    rss_base = _hwm_mib()
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(z0).compile()
    compile_s = time.perf_counter() - t0
    rss_compile = _hwm_mib()
    reset = _reset_hwm()
    t0 = time.perf_counter()
    jax.block_until_ready(compiled(z0))
    print(json.dumps({"rss_before_mib": rss_base, "rss_peak_compile_mib": rss_compile,
                      "rss_peak_run_mib": _hwm_mib() if reset else None,
                      "compile_s": compile_s, "run_s": time.perf_counter() - t0}))


def _hwm_mib() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    return float("nan")


def _reset_hwm() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _rss_now_mib(pid: int) -> float:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def memory(t_final: float, batch: int, limit_gib: float) -> list[dict]:
    rows = []
    for mode in ("forward", "value_and_grad", "jacfwd"):
        cmd = [sys.executable, __file__, "--child", "--mode", mode, "--t-final", str(t_final),
               "--batch", str(batch)]
        print(f"  memory: {mode}, batch {batch} ...", file=sys.stderr, flush=True)
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        peak, killed = 0.0, False
        while proc.poll() is None:
            peak = max(peak, _rss_now_mib(proc.pid))
            if peak > limit_gib * 1024:
                proc.kill()
                killed = True
                break
            time.sleep(0.05)
        out, err = proc.communicate()
        row = {"mode": mode, "batch": batch, "t_final": t_final, "rss_peak_sampled_mib": peak}
        if killed:
            row |= {"exceeded_limit_gib": limit_gib}
        elif proc.returncode != 0:
            row |= {"error": err.strip().splitlines()[-1:]}
        else:
            row |= json.loads(out.strip().splitlines()[-1])
        rows.append(row)
    return rows


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="5 s horizon, batch 16, 3 repeats")
    p.add_argument("--repeats", type=int, default=None)
    p.add_argument("--batch", type=int, default=None)
    p.add_argument("--memory-limit-gib", type=float, default=8.0)
    p.add_argument("--skip-memory", action="store_true")
    p.add_argument("--skip-anatomy", action="store_true")
    p.add_argument("--skip-tuning", action="store_true",
                   help="skip the robust tuning objective's gradient modes")
    p.add_argument("--only-tuning", action="store_true",
                   help="only the robust tuning objective's gradient modes (section 5)")
    p.add_argument("--out", default="results/bench_gradient.json")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--mode", default="value_and_grad", help=argparse.SUPPRESS)
    p.add_argument("--t-final", type=float, default=20.0, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        args.batch = args.batch or 256
        child(args)
        return
    t_final = 5.0 if args.quick else 20.0
    repeats = args.repeats or (3 if args.quick else 7)
    batch = args.batch or (16 if args.quick else 256)
    load = os.getloadavg()
    print(f"bench_gradient: T = {t_final:g} s, dt = 1e-3, batch {batch}, {repeats} repeats; "
          f"load average {load[0]:.2f} at start", file=sys.stderr)
    import jax

    result = {"quick": args.quick, "machine": platform.platform(), "cpus": os.cpu_count(),
              "device": str(jax.devices()[0]), "load_average_start": load}
    if not args.only_tuning:
        result["costs"] = costs(t_final, repeats, batch)
    if not args.skip_tuning:
        result["tuning"] = tuning_modes(t_final, repeats)
    if not (args.skip_anatomy or args.only_tuning):
        result["anatomy"] = anatomy(t_final)
    if not (args.skip_memory or args.only_tuning):
        result["memory"] = memory(t_final, batch, args.memory_limit_gib)
    result["load_average_end"] = os.getloadavg()
    _print(result)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}", file=sys.stderr)


LABELS = {"forward": "forward run (jit)",
          "value_and_grad": "value_and_grad (time-parallel, default)",
          "jacfwd": "jacfwd (forward mode)",
          "value_and_grad_autodiff": "value_and_grad, gradient=\"autodiff\"",
          "fd_forward_batched": "finite differences, forward, one batch",
          "fd_central_batched": "finite differences, central, one batch"}


def _print(r):
    if "costs" in r:
        _print_costs(r)
    if "tuning" in r:
        tu = r["tuning"]
        print(f"\nrobust tuning objective: CVaR {tu['cvar_level']:g} over {tu['batch']} plants, "
              f"{tu['n_params']} numbers (auto picks {tu['auto_mode']!r}; load "
              f"{r['load_average_start'][0]:.1f} -> {r['load_average_end'][0]:.1f})")
        print(f"{'':<44} {'median [s]':>11} {'x forward':>10} {'compile [s]':>12}")
        for k, label in (("forward_run", "forward run of the batch"),
                         ("forward", "value_and_grad, forward mode over the batch"),
                         ("reverse", "value_and_grad, reverse mode (checkpointed)"),
                         ("plants", "value_and_grad, plants (worst ones alone)")):
            v = tu["modes"][k]
            print(f"{label:<44} {v['median_s']:>11.4f} {v['ratio_to_forward']:>10.2f} "
                  f"{v['compile_s']:>12.1f}")
        print(f"  plants vs forward mode: max rel. difference "
              f"{tu['plants_vs_forward_max_rel']:.1e}; reverse vs forward: "
              f"{tu['reverse_vs_forward_max_rel']:.1e}")
    _print_rest(r)


def _print_costs(r):
    c = r["costs"]
    print(f"\nGradient of J (L-inf + L2 of e on [1 s, {c['t_final']:g} s], {c['n_steps']} RK4 "
          f"steps) w.r.t. {c['n_params']} design numbers, public API, default arguments "
          f"({r['device']}; load {r['load_average_start'][0]:.1f} -> "
          f"{r['load_average_end'][0]:.1f})")
    print(f"{'one trajectory':<44} {'median [s]':>11} {'x forward':>10} {'compile [s]':>12}")
    for k, label in LABELS.items():
        v = c["single"][k]
        print(f"{label:<44} {v['median_s']:>11.4f} {v['ratio_to_forward']:>10.2f} "
              f"{v['compile_s']:>12.1f}")
    if "batch" in c:
        b = c["batch"]
        print(f"\nmean J over a batch of {b['size']} plants (alpha, lam, psi +-30 %)")
        for k in ("forward", "value_and_grad", "jacfwd"):
            v = b[k]
            print(f"{LABELS.get(k, k).split(' (')[0]:<44} {v['median_s']:>11.4f} "
                  f"{v['ratio_to_forward']:>10.2f} {v['compile_s']:>12.1f}")
    a = c["accuracy"]
    print(f"\ntime-parallel vs autodiff reverse mode: max rel. difference "
          f"{a['time_parallel_vs_autodiff_max_rel']:.2e}; jacfwd vs autodiff: "
          f"{a['jacfwd_vs_autodiff_max_rel']:.2e}")
    for row in a["fd"]:
        print(f"  finite differences {'central' if row['central'] else 'forward':<8} "
              f"h = {row['h']:.0e}: max rel. error {row['max_rel_error']:.2e}")


def _print_rest(r):
    if "anatomy" in r:
        an = r["anatomy"]
        print("\nwhere the time goes: HLO instructions per loop body (largest first)")
        for k, v in an["loop_bodies"].items():
            print(f"  {LABELS.get(k, k):<42} {v}")
        s0 = an["one_step"]["step"]["flops"]
        print("XLA flops of one RK4 step of the paper's loop")
        for k, v in an["one_step"].items():
            print(f"  {k:<26} {v['flops']:>8.0f} flops ({v['flops'] / s0:5.1f}x), "
                  f"{v['transcendentals']:.0f} transcendental")
    if "memory" in r:
        print("\npeak RSS of the batch gradient [MiB] (fresh process each)")
        for m in r["memory"]:
            if "exceeded_limit_gib" in m:
                print(f"  {m['mode']:<16} > {m['exceeded_limit_gib']:g} GiB (stopped)")
            elif "error" in m:
                print(f"  {m['mode']:<16} error: {m['error']}")
            else:
                print(f"  {m['mode']:<16} setup {m['rss_before_mib']:.0f}, compile "
                      f"{m['rss_peak_compile_mib']:.0f}, run {m['rss_peak_run_mib']:.0f}, "
                      f"run {m['run_s']:.1f} s")


if __name__ == "__main__":
    main()
