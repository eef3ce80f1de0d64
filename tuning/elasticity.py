"""How far each constraint of a tuning run stands from breaking: its elasticity to every tuned
number on the nominal plant (report.md's "Sensitivity of the constraints").

    rows = constraints(problem, z, checks)   # checks: `report.constraint_checks` at z

A constraint value <= bound is read as the ratio r = value / bound <= 1 (a check loop's
L-inf bound is a multiple of the loop tuned's, so r divides the two). Its elasticity to a tuned
number g is e = d ln r / d ln g: a 1 % change of g moves r by about e %. It comes from one
forward run of the loop tuned (and of each check loop) carrying one tangent per tuned number
(`jax.jvp`, vmapped), through the run the objective simulates
(`dscjax.selection.run_at`). A constraint is **fragile** where a STEP change of one
number breaks it to first order: r (1 + STEP |e|) > 1. An elasticity that is not finite (None
in the result) is one whose tangent grew without bound over the run, as it does where the loop
depends sensitively on its gains (a chaotic or chattering loop): any change may break that
constraint, so it counts as fragile.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from dscjax import xla
from dscjax.selection import Log, run_at

STEP = 0.01  # the relative change of one tuned number a constraint should survive


def terms(key: str, names: tuple[str, ...]) -> tuple[tuple[int, int, str], ...]:
    """ln r of the constraint on the report's metric `key` as (sign, loop, metric) terms:
    loop 0 the loop tuned, i the check loop names[i - 1] (`report._exact`'s keys)."""
    for i, name in enumerate(names, start=1):
        if key == f"{name}_linf_window":  # its L-inf / (factor x L-inf)
            return (1, i, "linf_error_window"), (-1, 0, "linf_error_window")
        if key.startswith(f"{name}_"):
            return ((1, i, key.removeprefix(f"{name}_")),)
    return ((1, 0, key),)


def _figures(z, setup, loops, selection, keys):
    """(the figures `keys` of each loop, stacked; whether each loop diverged)."""
    runs = [run_at(selection, setup, z, spec) for spec in loops]
    return (jnp.stack([r.metrics[k] for r, names in zip(runs, keys, strict=True) for k in names]),
            jnp.stack([r.diverged for r in runs]))


@functools.partial(xla.jit, lean=True, static_argnums=(3, 4))
def _jacobian(z, *args):
    """(figures (k,), d figures / d z ({name: (k, ...)}), diverged): forward mode, one tangent
    per tuned number, vectorised. A report computes it once, so its compile time is its cost,
    and forward mode compiles sooner than reverse mode's pull-backs (benchmarks.md, "The
    tuner's AD mode for one plant")."""
    flat, unravel = ravel_pytree(z)

    def push(v):
        return jax.jvp(lambda x: _figures(unravel(x), *args), (flat,), (v,), has_aux=True)

    y, columns, diverged = jax.vmap(push, out_axes=(None, 1, None))(
        jnp.eye(flat.size, dtype=flat.dtype))
    return y, jax.vmap(unravel)(columns), diverged


def elasticities(problem, z, figures: list[tuple[int, str]]) -> dict[str, Any] | None:
    """{(loop, metric): {number: d ln figure / d ln g}} of the loop tuned (loop 0) and the
    check loops (1, 2, ...) at z on the nominal plant, for each tuned number g by name (a vector's
    elements as "path[i]"; a number tuned in linear coordinates scaled by its value: still
    d ln figure / d ln |g|); None where a loop diverged or a figure is 0."""
    obj, sel = problem.objective, problem.selection
    loops = [obj.sim] + [c.sim for c in obj.checks]
    keys = tuple(tuple(dict.fromkeys(m for lp, m in figures if lp == i))
                 for i in range(len(loops)))
    used = [i for i, k in enumerate(keys) if k]
    y, grad, diverged = jax.device_get(_jacobian(
        z, obj.setup, tuple(loops[i].program() for i in used), sel, tuple(keys[i] for i in used)))
    if np.any(diverged) or not np.all(np.asarray(y) > 0):  # no d ln of a figure of 0
        return None
    columns = [p.name for p in sel.columns(obj.setup)]
    # d figure / d ln g of each tuned item's numbers
    rows = [np.asarray(grad[t.name], float).reshape(len(y), -1)
            * (1.0 if isinstance(t.transform, Log) else np.ravel(np.asarray(z[t.name], float)))
            for t in sel.items]
    d = np.concatenate(rows, axis=1) / np.asarray(y, float)[:, None]
    flat = [(i, m) for i in used for m in keys[i]]
    return {f: dict(zip(columns, map(float, d[j]), strict=True)) for j, f in enumerate(flat)}


def constraints(problem, z, checks: list[dict[str, Any]]) -> dict[str, Any] | None:
    """Each constraint of `checks` (`report.constraint_checks` at z, with their metric `key`)
    with its elasticity to every tuned number, the largest, and the numbers a STEP change of
    which breaks it to first order (`fragile`); None if a loop diverged at z. The constraints
    of a check loop that is not `smooth` (the delayed input) are left out."""
    rough = tuple(f"{c.name}_" for c in problem.objective.checks if not c.smooth)
    checks = [c for c in checks if not (rough and c["key"].startswith(rough))]
    if not checks:
        return None
    names = tuple(c.name for c in problem.objective.checks)
    needed = [(lp, m) for c in checks for _, lp, m in terms(c["key"], names)]
    el = elasticities(problem, z, needed)
    if el is None:
        return None
    rows = []
    for c in checks:
        e = {name: sum(sign * el[(lp, m)][name] for sign, lp, m in terms(c["key"], names))
             for name in next(iter(el.values()))}
        e = {n: float(v) if np.isfinite(v) else None for n, v in e.items()}
        ratio = c["value"] / c["bound"]
        top = max(e, key=lambda n: np.inf if e[n] is None else abs(e[n]))
        fragile = ([n for n, v in e.items() if v is None or ratio * (1 + STEP * abs(v)) > 1]
                   if c["met"] else [])
        rows.append({k: c[k] for k in ("name", "key", "value", "bound", "relative_margin")}
                    | {"elasticity": e, "largest": {"number": top, "elasticity": e[top]},
                       "fragile": fragile})
    return {"step": STEP, "rows": rows}


def text(e: float | None) -> str:
    """An elasticity as the report prints it."""
    return "not finite" if e is None else f"{e:.3g}"


NAMED = 3  # the fragile numbers a warning names per constraint, the largest first


def warning(sens: dict[str, Any] | None) -> str | None:
    """The fragile constraints in one sentence (None: none): per constraint its margin and
    the NAMED numbers with the largest elasticities (those not finite first)."""
    if not sens:
        return None

    def which(r):
        e = r["elasticity"]
        if len(r["fragile"]) == len(e) and all(v is None for v in e.values()):
            return "every tuned number (elasticity not finite)"
        # those not finite first, then the largest
        first = sorted(r["fragile"], key=lambda n: (e[n] is not None, -abs(e[n] or 0.0)))
        named = [f"{n} (elasticity {text(e[n])})" for n in first[:NAMED]]
        more = len(r["fragile"]) - len(named)
        return ", ".join(named) + (f" and {more} more" if more else "")

    parts = [f"{r['name']} (margin {100 * r['relative_margin']:.3g} % of its bound) by "
             f"{which(r)}" for r in sens["rows"] if r["fragile"]]
    if not parts:
        return None
    return (f"a {100 * sens['step']:g} % change of one tuned number breaks a constraint (to "
            f"first order, nominal plant): " + "; ".join(parts))
