"""Search a start that does not diverge for `order_n_example(n)` (how STARTS[6] below was
found): CMA-ES over the log of k_i, tau_i, gamma_g, gamma_phi, gamma_zeta,
gamma_d, sat_width and eps, every population one batched simulation (ETDRK4, dt = 1e-3).

Score: a member that diverges at t_d < T costs 10 + 100 (T - t_d)/T (so living longer is
better); one that survives costs its L-inf error over the whole horizon [0, T]. The horizon T
grows 2, 5, 10, 20 s: as soon as the best member of a generation survives T, the search
restarts around it (sigma 0.3) at the next horizon. At 20 s one more generation (sigma 0.2) is
drawn around the first survivor and the best survivor printed. Run as is (n = 6, 2026-11-24) it
prints the design of L-inf 0.389 with k = (1.191, 1.222, 2.420, 3.043, 1.742, 0.763). STARTS[6]
is the best member of a later generation of that last stage in the interactive run this script
was written from (not kept exactly), rounded to 4 digits; both track over 20 s.

    python experiments/order_n_start.py            # n = 6, from k_i = 1, tau_i = 0.1
"""

from __future__ import annotations

import argparse

import numpy as np

# Order 6 diverges with every uniform (tau, k): its linearised loop is unstable at tau = 0.05,
# k = 4, and the start on the reference's derivative chain kicks u like 1/tau^5. This
# non-uniform design (k_i, tau_i, the adaptation rates, eps and the sat width; everything else,
# the plant and the reference are order_n_example(6)'s), found by this search, needs ETDRK4:
# classical RK4 at dt = 1e-3 blows up at t = 4 ms, where u' is largest.
STARTS = {6: dict(
    k=np.array([1.589, 1.214, 2.407, 2.415, 1.487, 0.7754]),
    tau=np.array([0.2317, 0.02329, 0.3151, 0.09354, 0.04346]),
    gamma_g=np.array([0.6882, 0.8046, 1.251, 1.351, 0.7702, 3.526]),
    gamma_phi=np.array([0.3463, 0.3644, 0.6199, 0.4614, 0.5244]),
    gamma_zeta=1.996, gamma_d=1.502, sat_width=0.03819, eps=1.184)}


def fields(n):
    return [("k", n), ("tau", n - 1), ("gamma_g", n), ("gamma_phi", n - 1), ("gamma_zeta", 0),
            ("gamma_d", 0), ("sat_width", 0), ("eps", 0)]


def unpack(n, X):
    """Rows of log-parameters -> {"controller.NAME": (B, ...) array}."""
    out, i = {}, 0
    for name, size in fields(n):
        m = max(size, 1)
        v = np.exp(X[:, i:i + m])
        i += m
        out[f"controller.{name}"] = v if size else v[:, 0]
    return out


def main():
    import cma
    import jax

    jax.config.update("jax_enable_x64", True)
    import dscjax

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--order", type=int, default=6)
    p.add_argument("--max-generations", type=int, default=50, help="per horizon")
    args = p.parse_args()
    n = args.order
    base = dscjax.order_n_example(n, dtype=np.float64)
    x = np.r_[np.zeros(n), np.log(np.full(n - 1, 0.1)), np.zeros(2 * n - 1), 0.0, 0.0,
              np.log(0.05), np.log(0.5)]
    # (horizon, sigma, seed); the last: one generation around the first 20 s survivor
    stages = ((2.0, 0.5, 1), (5.0, 0.3, 2), (10.0, 0.3, 2), (20.0, 0.3, 2), (20.0, 0.2, 1))
    for stage, (t_final, sigma, seed) in enumerate(stages):
        es = cma.CMAEvolutionStrategy(x, sigma, {"popsize": 16, "seed": seed, "verbose": -9})
        last = stage == len(stages) - 1
        for _ in range(1 if last else args.max_generations):
            X = np.array(es.ask())
            traj = dscjax.simulate_batch(base, unpack(n, X), t_final=t_final, dt=1e-3,
                                         refine=0, solver="etdrk4")
            div = np.asarray(traj.diverged)
            t_div = np.where(div, np.asarray(traj.t_diverged), t_final)
            score = np.where(div, 10.0 + 100.0 * (t_final - t_div) / t_final,
                             np.minimum(np.asarray(traj.metrics["linf_error"]), 10.0))
            es.tell(list(X), list(score))
            i = int(np.argmin(score))
            print(f"T = {t_final:g} s, generation {es.countiter}: best {score[i]:.4g}, "
                  f"{int(div.sum())}/16 diverged", flush=True)
            if not div[i]:
                x = X[i]
                break
        else:
            if not last:
                print(f"no member survived {t_final:g} s")
                return
    print({k: np.round(v[0], 4).tolist() for k, v in unpack(n, x[None]).items()})


if __name__ == "__main__":
    main()
