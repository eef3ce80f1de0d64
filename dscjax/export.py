"""A config's digital controller as C99: the sampled loop's update law, exactly.

    files = dscjax.export.c_files(setup, spec)   # {"dsc_controller.h": text, ".c": text}

The C is generated from the jaxpr of `closed_loop.sample_update` (the law, the advance of the
controller's states by `spec.discretisation`, the delay line) for the concrete config: gains,
sample time and delay are constants; the plant state x, the time t and the reference's
derivatives are the inputs. One C statement per primitive, in double precision, with no
dependency beyond <math.h>. Measurement noise belongs to the sensor, not the controller.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from dscjax.closed_loop import SampledState, Sampling, initial_state, prepared, sample_update
from dscjax.reference import Given, InitialOffset
from dscjax.validation import ConfigError

HEADER, SOURCE = "dsc_controller.h", "dsc_controller.c"
SCHEME_DOC = {"exponential-euler": "c += Ts phi(-lam Ts) c', phi(z) = (e^z - 1)/z, lam = 1/tau "
              "for a filter, 0 for an estimate", "euler": "forward Euler, c += Ts c'"}


class ExportError(ConfigError):
    """A config whose law uses something the C emitter does not write (one line)."""


# -- tracing: the sample update as one flat program ---------------------------------------------


def _with_given(setup, prepared_ref, d):
    """The prepared reference with the config's reference replaced by the inputs (the L-inf
    initialisation's decaying offset stays in the law)."""
    if prepared_ref is setup.reference:
        return Given(d=d)
    if isinstance(prepared_ref, InitialOffset) and prepared_ref.base is setup.reference:
        return dataclasses.replace(prepared_ref, base=Given(d=d))
    raise ExportError(f"reference: the controller's initialisation changes the reference in a "
                      f"way export does not know ({type(prepared_ref).__name__})")


@dataclasses.dataclass
class Law:
    """The traced sample update and what the C around it needs."""

    ops: list  # flat, live operations (after inlining and dead-code removal)
    state: list  # [(C name, shape, initial values (flat))], the controller's state
    outputs: list  # [atom of u, atoms of the new state leaves in `state` order]
    n_ref: int  # reference values the law reads: y_r .. y_r^(n_ref - 1)
    order: int
    sample_time: float


def trace(setup, spec) -> Law:
    """The sampled controller of (setup, spec) as a flat program (spec sampled, float64)."""
    if not spec.sampled:
        raise ConfigError("simulation.sample_time: export needs a sampled controller")
    s = prepared(setup)
    X0 = initial_state(s)
    if X0.x.dtype != np.float64:
        raise ConfigError(f"simulation.dtype: export writes the controller in float64 (got a "
                          f"{X0.x.dtype} setup; turn jax_enable_x64 on)")
    n = setup.order
    n_d = n + 2  # more reference derivatives than any law of order n reads
    every, dt = float(spec.sample_every), float(spec.dt)
    sampling = Sampling(every=every, delay=spec.delay, scheme=spec.discretisation)
    u0, _ = s.controller.law(X0.ctrl, X0.x, jnp.zeros((), X0.x.dtype), s.plant, s.reference)
    past0 = jnp.full((spec.delay,), u0, X0.x.dtype)

    def step(ctrl, past, x, t, d):
        loop = s.replace(reference=_with_given(setup, s.reference, d))
        X = SampledState(x=x, h=X0.h, ctrl=ctrl, u=jnp.zeros_like(t), past=past)
        new = sample_update(jnp.zeros((), jnp.int32), t, X, loop, sampling, dt)
        return new.u, new.ctrl, new.past

    zero = jnp.zeros((), X0.x.dtype)
    closed = jax.make_jaxpr(step)(X0.ctrl, past0, X0.x, zero, (zero,) * n_d)
    leaves = jax.tree_util.tree_flatten_with_path(X0.ctrl)[0]
    names = ["".join(c if c.isalnum() else "_" for c in jax.tree_util.keystr(p)).strip("_")
             for p, _ in leaves] + (["past"] if spec.delay else [])
    values = [v for _, v in leaves] + ([past0] if spec.delay else [])
    state = [(nm, np.shape(v), np.ravel(np.asarray(v, np.float64)))
             for nm, v in zip(names, values, strict=True)]
    jx = closed.jaxpr
    # the inputs: the state's leaves, the delay line (a (0,) array nothing reads if no delay),
    # x, t and the reference's derivatives
    kinds = ([("state", nm) for nm in names] + ([] if spec.delay else [("state", None)])
             + [("x",), ("t",)] + [("ref", j) for j in range(n_d)])
    flat = _Flattener()
    env = {v: ("in", kind, v.aval.shape) for v, kind in zip(jx.invars, kinds, strict=True)}
    env |= {v: ("const", np.asarray(c)) for v, c in zip(jx.constvars, closed.consts,
                                                         strict=True)}
    flat.inline(jx, env)
    outs = [flat.atom(env, v) for v in jx.outvars][:1 + len(names)]
    ops = _live(flat.ops, outs)
    used = {a[1][1] for a in [*outs, *(a for op in ops for a in op.ins)]
            if a[0] == "in" and a[1][0] == "ref"}
    n_ref = max(used, default=1) + 1
    if n_ref >= n_d:
        raise ExportError(f"reference: the law reads more than {n_d - 1} derivatives of y_r")
    return Law(ops=ops, state=state, outputs=outs, n_ref=max(n_ref, 2), order=n,
               sample_time=every * dt)


@dataclasses.dataclass
class Op:
    prim: str
    ins: list  # atoms: ("v", id, shape, dtype) | ("lit", value) | ("const", array) | ("in", ...)
    outs: list  # [("v", id, shape, dtype)]
    params: dict
    where: str  # the Python line it comes from


# primitives whose outputs are their inputs, element for element (flat row-major data)
_ALIASES = {"optimization_barrier", "copy", "copy_p", "squeeze", "reshape", "expand_dims"}
# calls whose jaxpr runs once, as it is (loops and conditionals are not: refused by the emitter)
_CALLS = {"jit", "pjit", "closed_call", "core_call", "remat", "checkpoint", "custom_jvp_call",
          "custom_vjp_call", "custom_vjp_call_jaxpr"}


class _Flattener:
    """Inlines nested jaxprs (jit, custom_jvp_call, ...) into one list of operations."""

    def __init__(self):
        self.ops: list[Op] = []
        self.count = 0

    def atom(self, env, v):
        return ("lit", np.asarray(v.val)) if isinstance(v, jax.extend.core.Literal) else env[v]

    def inline(self, jaxpr, env, outer: str = ""):
        """Append the operations of `jaxpr` (inputs and constants in `env`); `outer`: the
        Python line of the call it is inlined at (for a library's own nested calls)."""
        from jax._src import source_info_util

        for eqn in jaxpr.eqns:
            try:
                where = _short(source_info_util.summarize(eqn.source_info)) or outer
            except Exception:  # a comment only: never a reason to fail
                where = outer
            ins = [self.atom(env, v) for v in eqn.invars]
            name = eqn.primitive.name
            sub = next((eqn.params[k] for k in ("jaxpr", "call_jaxpr", "fun_jaxpr")
                        if k in eqn.params), None) if name in _CALLS else None
            if name in _ALIASES or (name == "convert_element_type"
                                    and eqn.invars[0].aval.dtype == eqn.outvars[0].aval.dtype):
                for o, a in zip(eqn.outvars, ins, strict=False):  # reshaped, same data
                    shape = tuple(o.aval.shape)
                    env[o] = ((*a[:2], shape, *a[3:]) if a[0] in ("v", "in")
                              else (a[0], np.reshape(a[1], shape)))
                continue
            if sub is not None:
                inner = sub.jaxpr if hasattr(sub, "consts") else sub
                consts = sub.consts if hasattr(sub, "consts") else []
                ienv = {v: ("const", np.asarray(c)) for v, c in zip(inner.constvars, consts,
                                                                     strict=True)}
                n_in = len(inner.invars)
                ienv |= dict(zip(inner.invars, ins[len(ins) - n_in:], strict=True))
                self.inline(inner, ienv, where)
                for o, v in zip(eqn.outvars, inner.outvars, strict=True):
                    env[o] = self.atom(ienv, v)
                continue
            outs = []
            for o in eqn.outvars:
                self.count += 1
                outs.append(("v", self.count, tuple(o.aval.shape), np.dtype(o.aval.dtype)))
                env[o] = outs[-1]
            self.ops.append(Op(name, ins, outs, dict(eqn.params), where))


def _short(where: str) -> str:
    """'/.../dscjax/controllers/dsc.py:157:13 (DSC.law)' -> 'controllers/dsc.py:157 (DSC.law)'."""
    path, _, rest = where.partition(" ")
    parts = path.split(":")
    name = (parts[0].rsplit("/dscjax/", 1)[-1] if "/dscjax/" in parts[0]
            else parts[0].rsplit("/", 1)[-1])
    return f"{name}:{parts[1]} {rest}" if len(parts) > 1 else where


def _live(ops, outs):
    need = {a[1] for a in outs if a[0] == "v"}
    kept = []
    for op in reversed(ops):
        if any(o[1] in need for o in op.outs):
            kept.append(op)
            need |= {a[1] for a in op.ins if a[0] == "v"}
    return kept[::-1]


# -- the C -----------------------------------------------------------------------------------


def _num(x) -> str:
    """A C literal that reads back as exactly x (the shortest repr of a double)."""
    x = np.asarray(x)
    if x.dtype.kind in "biu":
        return str(int(x))
    f = float(x)
    if not np.isfinite(f):
        return "NAN" if np.isnan(f) else ("INFINITY" if f > 0 else "(-INFINITY)")
    return f"({f!r})" if f < 0 else repr(f)


def _size(shape) -> int:
    return int(np.prod(shape, dtype=int))


def _shape(a) -> tuple:
    return tuple(a[2]) if a[0] in ("v", "in") else np.shape(a[1])


class _Emitter:
    def __init__(self, law: Law):
        self.law = law
        self.lines: list[str] = []
        self.declared: dict[int, tuple] = {}  # op output id -> the shape it is declared with

    def el(self, a, i: int) -> str:
        """The C expression of flat element i of atom a (a size-1 atom broadcasts)."""
        if a[0] in ("lit", "const"):
            arr = np.ravel(a[1])
            return _num(arr[i if arr.size > 1 else 0])
        j = i if _size(a[2]) > 1 else 0
        if a[0] == "v":
            return f"v{a[1]}" if self.declared[a[1]] == () else f"v{a[1]}[{j}]"
        kind, *what = a[1]
        if kind in ("x", "t"):
            return "t" if kind == "t" else f"x[{j}]"
        if kind == "ref":
            return ("yr", "yr_dot")[what[0]] if what[0] < 2 else f"yr_higher[{what[0] - 2}]"
        full = {nm: shp for nm, shp, _ in self.law.state}[what[0]]
        return f"s->{what[0]}" + ("" if full == () else f"[{j}]")

    def op(self, op: Op):
        out = op.outs[0]
        n = _size(out[2])
        f = _ELEMENTWISE.get(op.prim)
        if f is not None:
            vals = [f([self.el(a, i) for a in op.ins], op.params) for i in range(n)]
        elif op.prim in _MOVES:
            vals = [self.el(op.ins[k], int(j)) for k, j in _index_map(op)]
        elif op.prim == "dot_general":
            vals = _dot(self, op)
        elif op.prim in ("reduce_sum", "reduce_max", "reduce_min"):
            vals = _reduce(self, op)
        else:
            raise ExportError(f"controller: export cannot write the primitive "
                              f"'{op.prim}' ({op.where}) in C")
        ctype = "double" if out[3].kind == "f" else "long long"
        self.declared[out[1]] = out[2]
        if out[2] == ():
            self.lines.append(f"    {ctype} v{out[1]} = {vals[0]};")
        elif vals:
            self.lines.append(f"    {ctype} v{out[1]}[{len(vals)}] = {{{', '.join(vals)}}};")


def _bin(fmt):
    return lambda a, p: fmt.format(*a)


def _integer_pow(a, p):
    """x^y by JAX's own sequence of products (its lowering), so the rounding is the same."""
    x, y = a[0], int(p["y"])
    if y == 0:
        return "1.0"
    recip, y = y < 0, abs(y)
    acc, cur = None, f"({x})"
    while y > 0:
        if y & 1:
            acc = cur if acc is None else f"({acc} * {cur})"
        y >>= 1
        if y > 0:
            cur = f"({cur} * {cur})"
    return f"(1.0 / {acc})" if recip else acc


def _convert(a, p):
    dtype = np.dtype(p["new_dtype"])
    if dtype.kind == "f":
        return f"(double)({a[0]})"
    if dtype.kind == "b":
        return f"(({a[0]}) != 0)"
    return f"(long long)({a[0]})"


def _select(a, p):
    expr = a[-1]  # select_n(which, case_0, case_1, ...)
    for k in range(len(a) - 2, 0, -1):
        expr = f"(({a[0]}) == {k - 1} ? {a[k]} : {expr})"
    return expr


_ELEMENTWISE = {
    "add": _bin("({} + {})"), "add_any": _bin("({} + {})"), "sub": _bin("({} - {})"),
    "mul": _bin("({} * {})"), "div": _bin("({} / {})"), "neg": _bin("(-{})"),
    "max": _bin("dsc_max_({}, {})"), "min": _bin("dsc_min_({}, {})"),
    "pow": _bin("pow({}, {})"), "atan2": _bin("atan2({}, {})"), "rem": _bin("fmod({}, {})"),
    "abs": _bin("fabs({})"), "exp": _bin("exp({})"), "expm1": _bin("expm1({})"),
    "log": _bin("log({})"), "log1p": _bin("log1p({})"), "sqrt": _bin("sqrt({})"),
    "rsqrt": _bin("(1.0 / sqrt({}))"), "sin": _bin("sin({})"), "cos": _bin("cos({})"),
    "tan": _bin("tan({})"), "tanh": _bin("tanh({})"), "atan": _bin("atan({})"),
    "logistic": _bin("(1.0 / (1.0 + exp(-{})))"), "square": _bin("({0} * {0})"),
    "sign": _bin("dsc_sign_({})"), "floor": _bin("floor({})"), "ceil": _bin("ceil({})"),
    "lt": _bin("({} < {})"), "le": _bin("({} <= {})"), "gt": _bin("({} > {})"),
    "ge": _bin("({} >= {})"), "eq": _bin("({} == {})"), "ne": _bin("({} != {})"),
    "and": _bin("({} & {})"), "or": _bin("({} | {})"), "not": _bin("(!{})"),
    "integer_pow": _integer_pow, "convert_element_type": _convert, "select_n": _select,
}


def _index_map(op):
    """(operand, flat index) of every flat output element of a data-movement primitive."""
    shapes = [_shape(a) for a in op.ins]
    ids = [np.arange(_size(s)).reshape(s) for s in shapes]
    p = op.params
    if op.prim == "broadcast_in_dim":
        keep = [1] * len(p["shape"])
        for d, s in zip(p["broadcast_dimensions"], shapes[0], strict=True):
            keep[d] = s
        got = np.broadcast_to(ids[0].reshape(keep), p["shape"])
        return [(0, j) for j in got.ravel()]
    if op.prim == "slice":
        strides = p.get("strides") or (1,) * len(shapes[0])
        sl = tuple(slice(a, b, c) for a, b, c in zip(p["start_indices"], p["limit_indices"],
                                                     strides, strict=True))
        return [(0, j) for j in ids[0][sl].ravel()]
    if op.prim == "transpose":
        return [(0, j) for j in np.transpose(ids[0], p["permutation"]).ravel()]
    if op.prim == "rev":
        return [(0, j) for j in np.flip(ids[0], p["dimensions"]).ravel()]
    if op.prim in ("concatenate", "stack"):
        tagged = [k * 1_000_000 + a for k, a in enumerate(ids)]
        got = (np.concatenate(tagged, axis=p["dimension"]) if op.prim == "concatenate"
               else np.stack(tagged, axis=p["axis"]))
        return [(int(g) // 1_000_000, int(g) % 1_000_000) for g in got.ravel()]
    raise AssertionError(op.prim)


_MOVES = ("broadcast_in_dim", "slice", "transpose", "rev", "concatenate", "stack")


def _dot(em, op):
    a, b = op.ins
    (ca, cb), (ba, bb) = op.params["dimension_numbers"]
    if ba or bb:
        raise ExportError(f"controller: batched dot_general ({op.where})")
    sa, sb = _shape(a), _shape(b)
    ia, ib = np.arange(_size(sa)).reshape(sa), np.arange(_size(sb)).reshape(sb)
    fa = [d for d in range(len(sa)) if d not in ca]
    fb = [d for d in range(len(sb)) if d not in cb]
    ia = np.transpose(ia, fa + list(ca)).reshape(-1, _size([sa[d] for d in ca]))
    ib = np.transpose(ib, fb + list(cb)).reshape(-1, _size([sb[d] for d in cb]))
    return ["(" + " + ".join(f"{em.el(a, int(x))} * {em.el(b, int(y))}"
                             for x, y in zip(ra, rb, strict=True)) + ")"
            for ra in ia for rb in ib]


def _reduce(em, op):
    a = op.ins[0]
    shape = _shape(a)
    axes = tuple(op.params["axes"])
    ids = np.arange(_size(shape)).reshape(shape)
    rest = [d for d in range(len(shape)) if d not in axes]
    groups = np.transpose(ids, rest + list(axes)).reshape(-1, _size([shape[d] for d in axes]))
    out = []
    for g in groups:
        expr = em.el(a, int(g[0]))
        for j in g[1:]:
            e = em.el(a, int(j))
            expr = {"reduce_sum": f"({expr} + {e})", "reduce_max": f"dsc_max_({expr}, {e})",
                    "reduce_min": f"dsc_min_({expr}, {e})"}[op.prim]
        out.append(expr)
    return out


def step_signature(law: Law) -> str:
    extra = ",\n                const double *yr_higher" if law.n_ref > 2 else ""
    return ("double dsc_step(void *state, double t, const double *x, double yr, "
            f"double yr_dot{extra})")


def c_files(setup, spec, *, source: str = "") -> dict[str, str]:
    """{"dsc_controller.h": text, "dsc_controller.c": text} of the sampled controller of
    (setup, spec); `source` names the config in the header, which lists the gains."""
    from dscjax import config

    law, gains = trace(setup, spec), config.model_to_dict("controller", setup.controller)
    return {HEADER: _header(law, spec, source, gains), SOURCE: _source(law, spec)}


def _header(law, spec, source, gains) -> str:
    n_hi = law.n_ref - 2
    ref_doc = ("yr, yr_dot: the reference y_r(t) and its derivative"
               + (f";\n *   yr_higher[j] = the derivative j + 2 of y_r(t), j = 0..{n_hi - 1} "
                  f"(the law reads them)" if n_hi else ""))
    glines = "\n".join(f" *   {k} = {v}" for k, v in gains.items())
    delay = (f"input delay: {spec.delay} sample(s):\n * dsc_step returns the input computed "
             f"{spec.delay} sample(s) before (the initial one until then)" if spec.delay
             else "no input delay")
    return f"""/* dsc_controller.h: the digital controller of {source or 'a dscjax config'},
 * generated by `dscjax export`: exactly the update law of dscjax's sampled loop.
 *
 * Order n = {law.order}; sample time Ts = {law.sample_time!r} s; {delay}.
 * The controller's states advance by {spec.discretisation}:
 *   {SCHEME_DOC[spec.discretisation]}.
 * dsc_step reads the plant state x (n values, measured at t), t and the reference:
 *   {ref_doc}.
 * Call dsc_step once per sample, at t = k Ts, k = 0, 1, ..., and hold its u until t + Ts.
 * C99, double precision, only <math.h>; compile without -ffast-math for dscjax's numbers.
 *
 * The controller (its gains and initial estimates):
{glines}
 */
#ifndef DSC_CONTROLLER_H
#define DSC_CONTROLLER_H
#include <stddef.h>

#define DSC_ORDER {law.order}
#define DSC_REFERENCE_DERIVATIVES {law.n_ref - 1}  /* y_r' .. y_r^({law.n_ref - 1}) */

size_t dsc_state_size(void);          /* bytes of the controller's state */
void   dsc_init(void *state);         /* the config's initial estimates and filters */
{step_signature(law)};
/* one sample: x = the plant state ({law.order} values) at time t; returns u to hold until t + Ts,
   and advances the controller's states by one sample */
double dsc_sample_time(void);
int    dsc_order(void);

#endif
"""


def _source(law: Law, spec) -> str:
    fields = "\n".join(f"    double {nm}{'' if shp == () else f'[{_size(shp)}]'};"
                       for nm, shp, _ in law.state)
    init = [f"    s->{nm}{'' if shp == () else f'[{i}]'} = {_num(v)};"
            for nm, shp, vals in law.state for i, v in enumerate(vals)]
    em = _Emitter(law)
    last = None
    for op in law.ops:
        if op.where and op.where != last:
            em.lines.append(f"    /* {op.where} */")
            last = op.where
        em.op(op)
    u, *new = law.outputs  # all read before the state is written (u may be s->past[...])
    tail = [f"    double u_out = {em.el(u, 0)};"]
    for (nm, shp, _), a in zip(law.state, new, strict=True):
        vals = ", ".join(em.el(a, i) for i in range(_size(shp)))
        tail.append(f"    double next_{nm}[{_size(shp)}] = {{{vals}}};")
    tail += [f"    s->{nm}{'' if shp == () else f'[{i}]'} = next_{nm}[{i}];"
             for nm, shp, _ in law.state for i in range(_size(shp))]
    body = "\n".join(em.lines + tail)
    unused = ["t", "x", "yr", "yr_dot"] + (["yr_higher"] if law.n_ref > 2 else [])
    voids = " ".join(f"(void){u_};" for u_ in unused)
    return f"""/* dsc_controller.c: generated by `dscjax export` from the jaxpr of dscjax's sample
 * update (closed_loop.sample_update); see dsc_controller.h. */
#include <math.h>
#include <stddef.h>
#include "dsc_controller.h"

typedef struct {{
{fields}
}} dsc_state;

size_t dsc_state_size(void) {{ return sizeof(dsc_state); }}

double dsc_sample_time(void) {{ return {_num(law.sample_time)}; }}

int dsc_order(void) {{ return {law.order}; }}

void dsc_init(void *state) {{
    dsc_state *s = (dsc_state *)state;
{chr(10).join(init)}
}}

/* max and min as XLA computes them: NaN if either is */
static inline double dsc_max_(double a, double b) {{
    return (a != a || b != b) ? a + b : (a > b ? a : b);
}}
static inline double dsc_min_(double a, double b) {{
    return (a != a || b != b) ? a + b : (a < b ? a : b);
}}
static inline double dsc_sign_(double a) {{ return a > 0.0 ? 1.0 : (a < 0.0 ? -1.0 : a); }}

{step_signature(law)} {{
    dsc_state *s = (dsc_state *)state;
    {voids}
{body}
    return u_out;
}}
"""


__all__ = ["HEADER", "SOURCE", "ExportError", "Law", "c_files", "trace"]
