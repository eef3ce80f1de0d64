"""Cost, accuracy and memory of the exact gradient of the tuning objective.

    python experiments/bench_gradient.py            # full: 20 s horizon, batch of 256 plants
    python experiments/bench_gradient.py --quick    # 5 s horizon, batch of 16 (a smoke test)

1. Cost of one gradient of the default objective (the paper's example, the default tuned set)
   with respect to all tuned numbers, relative to one forward simulation of the same
   objective: forward mode (jacfwd: one jvp per tuned number, all in one pass), reverse mode
   without and with checkpointing, and finite differences run as ONE batched simulation
   (forward differences: P+1 members; central: 2P members). Medians of --repeats runs;
   compilation is timed apart.
2. Accuracy: forward against reverse mode, and finite differences at several steps h against
   the exact gradient.
3. Peak memory (RSS) of the gradient for a batch of plants (hysteresis +-30 %) over the whole
   horizon, with and without checkpointing, each configuration in a fresh subprocess
   (a configuration that grows past --memory-limit-gib is stopped and reported as such).

Prints tables and writes results/bench_gradient.json (or --out).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def _setup_jax():
    import jax

    jax.config.update("jax_enable_x64", True)
    return jax


def build(t_final: float, batch: int = 0, params=None):
    """The default tuning problem (paper example, default gains tuned) at horizon t_final."""
    import dataclasses

    import dscjax
    import tuning
    from dscjax.config import SimOptions

    cfg = tuning.TuningConfig(robust=tuning.BatchSpec(batch=batch, seed=0),
                              heldout=tuning.BatchSpec(batch=0))
    if params:
        cfg = dataclasses.replace(cfg, params=tuple(params))
    return tuning.build_problem(dscjax.paper_example(), SimOptions(t_final=t_final), cfg)


def timed(fn, *args, repeats=5):
    jax = _setup_jax()
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        runs.append(time.perf_counter() - t0)
    return {"compile_s": max(first - float(np.median(runs)), 0.0), "first_call_s": first,
            "median_s": float(np.median(runs)), "min_s": float(np.min(runs)),
            "runs_s": runs}, out


def fd_points(flat0: np.ndarray, central: bool, h: float) -> np.ndarray:
    """The members of a finite-difference gradient: P+1 (forward) or 2P (central) points."""
    steps = np.eye(flat0.size) * h
    if central:
        return np.concatenate([flat0 + steps, flat0 - steps])
    return np.concatenate([flat0[None], flat0 + steps])


def fd_gradient(values: np.ndarray, central: bool, h: float) -> np.ndarray:
    n = values.size // 2 if central else values.size - 1
    if central:
        return (values[:n] - values[n:]) / (2 * h)
    return (values[1:] - values[0]) / h


def costs(t_final: float, repeats: int) -> dict:
    jax = _setup_jax()
    import tuning

    problem = build(t_final)
    obj = problem.objective
    z = problem.z0
    P = problem.n_params
    res = {"t_final": t_final, "n_steps": obj.sim.n_steps, "n_params": P,
           "params": list(problem.selection.names)}
    fwd = jax.jit(lambda z: obj.evaluate(z)[0])
    res["forward"], _ = timed(fwd, z, repeats=repeats)
    configs = {
        "grad_forward_mode": lambda z: tuning.value_and_grad(obj, z, "forward"),
        "grad_reverse_mode": lambda z: tuning.value_and_grad(obj, z, "reverse", None),
        "grad_reverse_mode_ckpt100": lambda z: tuning.value_and_grad(obj, z, "reverse", 100),
        "grad_reverse_mode_ckpt1000": lambda z: tuning.value_and_grad(obj, z, "reverse",
                                                                      1000),
    }
    # Forward mode in the batch-last rows layout the sweeps use: P identical members, member j
    # carrying the tangent e_j (one jvp of the batched program gives the whole gradient).
    import jax.numpy as jnp

    from tuning.baselines import batch_loss_fn

    batch_loss, flat0, unravel = batch_loss_fn(problem)
    eye = jnp.eye(flat0.size, dtype=flat0.dtype)

    def members(z):
        pts = jnp.broadcast_to(jax.flatten_util.ravel_pytree(z)[0], eye.shape)
        value, grad = jax.jvp(batch_loss, (pts,), (eye,))
        return value[0], unravel(grad)

    configs["grad_forward_members"] = members
    grads = {}
    for name, fn in configs.items():
        print(f"  timing {name} ...", file=sys.stderr, flush=True)
        res[name], out = timed(jax.jit(fn), z, repeats=repeats)
        grads[name] = np.asarray(jax.flatten_util.ravel_pytree(out[1])[0])
    # Finite differences: ALL members in one batched simulation (batch-last rows layout),
    # the objective evaluated by the same code the gradient-free baselines use.
    for central in (False, True):
        name = f"fd_{'central' if central else 'forward'}_batched"
        print(f"  timing {name} ...", file=sys.stderr, flush=True)
        pts = jnp.asarray(fd_points(flat0, central, 1e-5))
        res[name], _ = timed(lambda p, c=central: fd_gradient(np.asarray(batch_loss(p)), c,
                                                              1e-5), pts, repeats=repeats)
        res[name]["members"] = int(pts.shape[0])
    base = res["forward"]["median_s"]
    for v in res.values():
        if isinstance(v, dict) and "median_s" in v:
            v["ratio_to_forward"] = v["median_s"] / base
    # accuracy
    ref = grads["grad_reverse_mode"]
    scale = np.max(np.abs(ref))
    acc = {"forward_vs_reverse_max_rel": float(max(np.max(np.abs(grads[k] - ref)) for k in (
               "grad_forward_mode", "grad_forward_members")) / scale),
           "ckpt_vs_plain_reverse_max_rel": float(max(np.max(np.abs(
               grads[k] - ref)) for k in ("grad_reverse_mode_ckpt100",
                                          "grad_reverse_mode_ckpt1000")) / scale), "fd": []}
    for central in (False, True):
        for h in (1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8):
            pts = jnp.asarray(fd_points(flat0, central, h))
            g = fd_gradient(np.asarray(batch_loss(pts)), central, h)
            err = float(np.max(np.abs(g - ref)) / scale)
            acc["fd"].append({"central": central, "h": h, "max_rel_error": err})
    res["accuracy"] = acc
    return res


# -- memory: one subprocess per configuration -----------------------------------------------------


def child(args) -> None:
    """Run one gradient configuration and print its peak RSS as JSON (child process)."""
    jax = _setup_jax()
    import tuning

    problem = build(args.t_final, batch=args.batch)
    obj = problem.objective
    rss_base = _hwm_mib()
    if args.mode == "simulate":
        fn = jax.jit(lambda z: obj.evaluate(z)[0])
    else:
        ce = None if args.ckpt == 0 else args.ckpt
        mode = "forward" if args.mode == "forward" else "reverse"
        fn = jax.jit(lambda z: tuning.value_and_grad(obj, z, mode, ce))
    t0 = time.perf_counter()
    compiled = fn.lower(problem.z0).compile()
    compile_s = time.perf_counter() - t0
    rss_compile = _hwm_mib()
    reset = _reset_hwm()  # from here on VmHWM is the peak of the run alone
    t0 = time.perf_counter()
    jax.block_until_ready(compiled(problem.z0))
    run_s = time.perf_counter() - t0
    print(json.dumps({"rss_peak_mib": _hwm_mib() if not reset else max(rss_compile, _hwm_mib()),
                      "rss_before_mib": rss_base,
                      "rss_peak_compile_mib": rss_compile,
                      "rss_peak_run_mib": _hwm_mib() if reset else None,
                      "compile_s": compile_s, "run_s": run_s}))


def _rss_peak_mib() -> float:
    # ru_maxrss survives exec (a child started from a big parent inherits its peak): only a
    # fallback where /proc is missing.
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _hwm_mib() -> float:
    """VmHWM of this process (peak RSS since start or since the last reset)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return float(line.split()[1]) / 1024.0
    return _rss_peak_mib()


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
    configs = [("simulate", 0), ("reverse", 0), ("reverse", 1000), ("reverse", 100),
               ("forward", 0)]
    for mode, ckpt in configs:
        cmd = [sys.executable, __file__, "--child", "--mode", mode, "--ckpt", str(ckpt),
               "--t-final", str(t_final), "--batch", str(batch)]
        ck_text = "no checkpointing" if not ckpt else f"checkpoint every {ckpt} steps"
        label = {"simulate": "forward simulation (no gradient)",
                 "forward": "gradient, forward mode",
                 "reverse": f"gradient, reverse mode, {ck_text}"}[mode]
        print(f"  memory: {label} ...", file=sys.stderr, flush=True)
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env=os.environ | {"JAX_ENABLE_X64": "1"})
        peak, killed = 0.0, False
        while proc.poll() is None:
            peak = max(peak, _rss_now_mib(proc.pid))
            if peak > limit_gib * 1024:
                proc.kill()
                killed = True
                break
            time.sleep(0.05)
        out, err = proc.communicate()
        row = {"config": label, "mode": mode, "checkpoint_every": ckpt or None,
               "batch": batch, "t_final": t_final}
        if killed:
            row |= {"rss_peak_mib": None, "exceeded_limit_gib": limit_gib}
        elif proc.returncode != 0:
            row |= {"rss_peak_mib": None, "error": err.strip().splitlines()[-1:]}
        else:
            row |= json.loads(out.strip().splitlines()[-1])
        rows.append(row)
    return rows


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="5 s horizon, batch 16, 3 repeats")
    p.add_argument("--repeats", type=int, default=None)
    p.add_argument("--memory-batch", type=int, default=None)
    p.add_argument("--memory-limit-gib", type=float, default=8.0)
    p.add_argument("--skip-memory", action="store_true")
    p.add_argument("--skip-costs", action="store_true")
    p.add_argument("--out", default="results/bench_gradient.json")
    # child mode
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--mode", default="reverse", help=argparse.SUPPRESS)
    p.add_argument("--ckpt", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--t-final", type=float, default=20.0, help=argparse.SUPPRESS)
    p.add_argument("--batch", type=int, default=256, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        child(args)
        return
    t_final = 5.0 if args.quick else 20.0
    repeats = args.repeats or (3 if args.quick else 7)
    batch = args.memory_batch or (16 if args.quick else 256)
    load = os.getloadavg()
    print(f"bench_gradient: T = {t_final:g} s, dt = 1e-3, {repeats} repeats; load average "
          f"{load[0]:.2f} at start", file=sys.stderr)
    result = {"quick": args.quick, "machine": platform.platform(), "cpus": os.cpu_count(),
              "load_average_start": load}
    if not args.skip_costs:
        result["costs"] = costs(t_final, repeats)
    if not args.skip_memory:
        result["memory"] = memory(t_final, batch, args.memory_limit_gib)
    result["load_average_end"] = os.getloadavg()
    _print(result)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}", file=sys.stderr)


def _print(r):
    if "costs" in r:
        _print_costs(r["costs"])
    if "memory" in r:
        _print_memory(r["memory"])


def _print_costs(c):
    print(f"\nOne gradient of the {c['t_final']:g} s objective ({c['n_steps']} RK4 steps) with "
          f"respect to {c['n_params']} tuned numbers, against one forward simulation")
    print(f"{'method':<34} {'median [s]':>11} {'x forward':>10} {'compile [s]':>12}")
    names = [("forward", "forward simulation"), ("grad_forward_mode", "exact, forward mode (jvp)"),
             ("grad_forward_members", "exact, forward, members layout"),
             ("grad_reverse_mode", "exact, reverse mode"),
             ("grad_reverse_mode_ckpt100", "exact, reverse, checkpoint 100"),
             ("grad_reverse_mode_ckpt1000", "exact, reverse, checkpoint 1000"),
             ("fd_forward_batched", "FD forward, one batch"),
             ("fd_central_batched", "FD central, one batch")]
    for key, label in names:
        v = c[key]
        extra = f" ({v['members']} members)" if "members" in v else ""
        print(f"{label + extra:<34} {v['median_s']:>11.4f} {v['ratio_to_forward']:>10.2f} "
              f"{v['compile_s']:>12.1f}")
    a = c["accuracy"]
    print("\nforward (both) vs reverse mode: max rel. difference "
          f"{a['forward_vs_reverse_max_rel']:.2e}; "
          f"checkpointed vs plain reverse: {a['ckpt_vs_plain_reverse_max_rel']:.2e}")
    print(f"{'finite differences':<20} {'h':>8} {'max rel. error vs exact':>24}")
    for row in a["fd"]:
        print(f"{'central' if row['central'] else 'forward':<20} {row['h']:>8.0e} "
              f"{row['max_rel_error']:>24.2e}")


def _print_memory(memory):
    if memory:
        m0 = memory[0]
        print(f"\nPeak RSS [MiB] of one evaluation, batch of {m0['batch']} plants, T = "
              f"{m0['t_final']:g} s (fresh process each: peak RSS after\n"
              f"building the problem, during compilation, and during the run alone)")
        print(f"{'configuration':<52} {'setup':>8} {'compile':>8} {'run':>8} {'run [s]':>8}")
        for m in memory:
            if m.get("rss_peak_mib") is None:
                what = (f"> {m['exceeded_limit_gib']:g} GiB (stopped)"
                        if "exceeded_limit_gib" in m else f"error: {m.get('error')}")
                print(f"{m['config']:<52} {what}")
                continue
            run = m.get("rss_peak_run_mib")
            print(f"{m['config']:<52} {m['rss_before_mib']:>8.0f} "
                  f"{m['rss_peak_compile_mib']:>8.0f} {run if run is None else f'{run:.0f}':>8} "
                  f"{m['run_s']:>8.2f}")


if __name__ == "__main__":
    main()
