"""The C99 text of a traced controller (`c_files`): one C statement per primitive, in double or
float precision (`PRECISIONS`), with no dependency beyond <math.h>; `dsc_init` and `dsc_step`
around the programs of `law.trace`, the gains listed in the header.
"""

from __future__ import annotations

import functools
from fractions import Fraction

import numpy as np

from dscjax.export.law import ExportError, Law, Op, Program, trace
from dscjax.validation import one_of

HEADER, SOURCE = "dsc_controller.h", "dsc_controller.c"
PRECISIONS = ("double", "float")
SCHEME_DOC = {"exponential-euler": "c += Ts phi(-lam Ts) c', phi(z) = (e^z - 1)/z, lam = 1/tau "
              "for a filter, 0 for an estimate", "euler": "forward Euler, c += Ts c'"}
# the most elements of an array export writes (a C initialiser; `_move`'s operand tags)
MAX_ELEMENTS = 1_000_000


class _Real:
    """How the C writes a real number: `double`, or `float` throughout (constants with an f
    suffix, the float functions of C99's <math.h>: expf, sinf, ...)."""

    def __init__(self, name: str):
        self.name = name
        self.f = "f" if name == "float" else ""
        self.one = "1.0" + self.f

    def num(self, x) -> str:
        """A C literal that reads back as exactly x rounded to this type (the shortest)."""
        x = np.asarray(x)
        if x.dtype.kind in "biu":
            return str(int(x))
        f = float(x)
        if not np.isfinite(f):
            return "NAN" if np.isnan(f) else ("INFINITY" if f > 0 else "(-INFINITY)")
        text = repr(f) if self.name == "double" else _float_literal(f)
        return f"({text})" if f < 0 else text


class _OutOfRange(ValueError):
    def error(self, precision: str, where: str = "") -> ExportError:
        """The ExportError of this constant (`where`: the operation it is an operand of)."""
        return ExportError(f"controller: the constant {self.args[0]:g}{where} is beyond the "
                           f"range of C {precision}; export it in double (--precision double)")


def _float_literal(f: float) -> str:
    """The shortest decimal whose nearest float is float32(f), with the f suffix: nearer to
    it than half the distance to either neighbour, so any correctly rounding compiler reads
    exactly that float (no double rounding through a double)."""
    v = np.float32(f)
    if not np.isfinite(v) or (v == 0 and f != 0):
        raise _OutOfRange(f)
    exact = Fraction(float(v))
    lo = Fraction(float(np.nextafter(v, np.float32(-np.inf))))
    up = np.nextafter(v, np.float32(np.inf))
    hi = Fraction(float(up)) if np.isfinite(up) else 2 * exact - lo

    def reads_back(text):
        gap = Fraction(text) - exact
        return 2 * gap < hi - exact and 2 * -gap < exact - lo

    text = next(t for t in (f"{float(v):.{digits}g}" for digits in range(1, 10))
                if reads_back(t))
    if reads_back(repr(float(text))):  # 10.0 rather than 1e+01
        text = repr(float(text))
    return (text if ("." in text or "e" in text) else text + ".0") + "f"


def _size(shape) -> int:
    return int(np.prod(shape, dtype=int))


def _shape(a) -> tuple:
    return tuple(a[2]) if a[0] in ("v", "in") else np.shape(a[1])


class _Emitter:
    """C statements of one program; `x`: the C name of the plant state it reads (x, or x0 in
    dsc_init); the time it reads is `t_s`, the time since dsc_init."""

    def __init__(self, law: Law, real: _Real, x: str = "x"):
        self.real, self.x = real, x
        self.shapes = {nm: shp for nm, shp, _ in law.state}
        self.lines: list[str] = []
        self.declared: dict[int, tuple] = {}  # op output id -> the shape it is declared with

    def el(self, a, i: int) -> str:
        """The C expression of flat element i of atom a (a size-1 atom broadcasts)."""
        if a[0] in ("lit", "const"):
            arr = np.ravel(a[1])
            return self.real.num(arr[i if arr.size > 1 else 0])
        j = i if _size(a[2]) > 1 else 0
        if a[0] == "v":
            return f"v{a[1]}" if self.declared[a[1]] == () else f"v{a[1]}[{j}]"
        kind, *what = a[1]
        if kind in ("x", "t"):
            return "t_s" if kind == "t" else f"{self.x}[{j}]"
        if kind == "ref":
            return ("yr", "yr_dot")[what[0]] if what[0] < 2 else f"yr_higher[{what[0] - 2}]"
        return f"s->{what[0]}" + ("" if self.shapes[what[0]] == () else f"[{j}]")

    def program(self, prog: Program):
        last = None
        for op in prog.ops:
            if op.where and op.where != last:
                self.lines.append(f"    /* {op.where} */")
                last = op.where
            try:
                self.op(op)
            except _OutOfRange as e:
                raise e.error(self.real.name, f" ({op.where})") from None

    def op(self, op: Op):
        out = op.outs[0]
        n = _size(out[2])
        for what, a in [*((f"operand {k + 1}", a) for k, a in enumerate(op.ins)),
                        ("the result", out)]:
            if _size(_shape(a)) > MAX_ELEMENTS:
                raise ExportError(f"controller: {what} of '{op.prim}' ({op.where}) has "
                                  f"{_size(_shape(a))} elements; export writes arrays of at "
                                  f"most {MAX_ELEMENTS} elements")
        f = _ELEMENTWISE.get(op.prim)
        if f is not None:
            vals = [f([self.el(a, i) for a in op.ins], op.params, self.real) for i in range(n)]
        elif op.prim in _STRUCTURAL:
            vals = _STRUCTURAL[op.prim](self, op)
        else:
            raise ExportError(f"controller: export cannot write the primitive "
                              f"'{op.prim}' ({op.where}) in C")
        ctype = self.real.name if out[3].kind == "f" else "long long"
        self.declared[out[1]] = out[2]
        if out[2] == ():
            self.lines.append(f"    {ctype} v{out[1]} = {vals[0]};")
        elif vals:
            self.lines.append(f"    {ctype} v{out[1]}[{len(vals)}] = {{{', '.join(vals)}}};")


def _bin(fmt):
    """An elementwise primitive by a format: {} the operands, {f} the float functions'
    suffix, {one} the literal 1."""
    return lambda a, p, r: fmt.format(*a, f=r.f, one=r.one)


def _integer_pow(a, p, r):
    """x^y by JAX's own sequence of products (its lowering), so the rounding is the same."""
    x, y = a[0], int(p["y"])
    if y == 0:
        return r.one
    recip, y = y < 0, abs(y)
    acc, cur = None, f"({x})"
    while y > 0:
        if y & 1:
            acc = cur if acc is None else f"({acc} * {cur})"
        y >>= 1
        if y > 0:
            cur = f"({cur} * {cur})"
    return f"({r.one} / {acc})" if recip else acc


def _convert(a, p, r):
    dtype = np.dtype(p["new_dtype"])
    if dtype.kind == "f":
        return f"({r.name})({a[0]})"
    if dtype.kind == "b":
        return f"(({a[0]}) != 0)"
    return f"(long long)({a[0]})"


def _select(a, p, r):
    expr = a[-1]  # select_n(which, case_0, case_1, ...)
    for k in range(len(a) - 2, 0, -1):
        expr = f"(({a[0]}) == {k - 1} ? {a[k]} : {expr})"
    return expr


_ELEMENTWISE = {
    **{prim: _bin("({} " + op + " {})") for prim, op in (
        ("add", "+"), ("add_any", "+"), ("sub", "-"), ("mul", "*"), ("div", "/"), ("lt", "<"),
        ("le", "<="), ("gt", ">"), ("ge", ">="), ("eq", "=="), ("ne", "!="), ("and", "&"),
        ("or", "|"))},
    # the <math.h> function of the primitive's name (expf, sinf, ... in float)
    **{prim: _bin(prim + "{f}({})") for prim in ("exp", "expm1", "log", "log1p", "sqrt", "sin",
                                                 "cos", "tan", "tanh", "atan", "floor", "ceil")},
    "pow": _bin("pow{f}({}, {})"), "atan2": _bin("atan2{f}({}, {})"),
    "rem": _bin("fmod{f}({}, {})"), "abs": _bin("fabs{f}({})"), "neg": _bin("(-{})"),
    "not": _bin("(!{})"), "max": _bin("dsc_max_({}, {})"), "min": _bin("dsc_min_({}, {})"),
    "sign": _bin("dsc_sign_({})"), "rsqrt": _bin("({one} / sqrt{f}({}))"),
    "logistic": _bin("({one} / ({one} + exp{f}(-{})))"), "square": _bin("({0} * {0})"),
    "integer_pow": _integer_pow, "convert_element_type": _convert, "select_n": _select,
}


def _move(em, op):
    """The C expression of every flat output element of a data-movement primitive."""
    shapes = [_shape(a) for a in op.ins]
    # every operand's flat indices, tagged with the operand's number
    tagged = [k * MAX_ELEMENTS + np.arange(_size(s)).reshape(s) for k, s in enumerate(shapes)]
    ids, p = tagged[0], op.params
    if op.prim == "broadcast_in_dim":
        new = [d for d in range(len(p["shape"])) if d not in p["broadcast_dimensions"]]
        got = np.broadcast_to(np.expand_dims(ids, new), p["shape"])
    elif op.prim == "slice":
        got = ids[tuple(map(slice, p["start_indices"], p["limit_indices"],
                            p.get("strides") or (None,) * ids.ndim))]
    elif op.prim == "transpose":
        got = np.transpose(ids, p["permutation"])
    elif op.prim == "rev":
        got = np.flip(ids, p["dimensions"])
    elif op.prim == "concatenate":
        got = np.concatenate(tagged, axis=p["dimension"])
    else:  # stack
        got = np.stack(tagged, axis=p["axis"])
    return [em.el(op.ins[int(g) // MAX_ELEMENTS], int(g) % MAX_ELEMENTS) for g in got.ravel()]


def _groups(shape, axes) -> np.ndarray:
    """The flat indices of an array of `shape`: one row per index of its other axes, the
    `axes` along the row."""
    ids = np.arange(_size(shape)).reshape(shape)
    rest = [d for d in range(len(shape)) if d not in axes]
    return np.transpose(ids, rest + list(axes)).reshape(-1, _size([shape[d] for d in axes]))


def _dot(em, op):
    a, b = op.ins
    (ca, cb), (ba, bb) = op.params["dimension_numbers"]
    if ba or bb:
        raise ExportError(f"controller: batched dot_general ({op.where})")
    return ["(" + " + ".join(f"{em.el(a, int(x))} * {em.el(b, int(y))}"
                             for x, y in zip(ra, rb, strict=True)) + ")"
            for ra in _groups(_shape(a), ca) for rb in _groups(_shape(b), cb)]


def _reduce(em, op):
    """Each group's elements folded left to right by the primitive's elementwise form."""
    a = op.ins[0]
    f = _ELEMENTWISE[{"reduce_sum": "add", "reduce_max": "max", "reduce_min": "min"}[op.prim]]
    return [functools.reduce(lambda x, y: f([x, y], {}, em.real), (em.el(a, int(j)) for j in g))
            for g in _groups(_shape(a), tuple(op.params["axes"]))]


# the primitives that are not elementwise: data movement, dot_general and reductions
_STRUCTURAL = {**dict.fromkeys(("broadcast_in_dim", "slice", "transpose", "rev", "concatenate",
                                "stack"), _move), "dot_general": _dot,
               **dict.fromkeys(("reduce_sum", "reduce_max", "reduce_min"), _reduce)}


def _signatures(law: Law, r: str) -> tuple[str, str]:
    """The C declarations of dsc_init and dsc_step in real type r (no semicolon)."""
    ref = f"{r} yr, {r} yr_dot" + (f",\n                const {r} *yr_higher"
                                  if law.n_ref > 2 else "")
    return (f"void dsc_init(void *state, {r} t0, const {r} *x0, {ref})",
            f"{r} dsc_step(void *state, {r} t, const {r} *x, {ref})")


def c_files(setup, spec, *, source: str = "", precision: str = "double") -> dict[str, str]:
    """{"dsc_controller.h": text, "dsc_controller.c": text} of the sampled controller of
    (setup, spec) in C `precision` (double or float); `source` names the config in the
    header, which lists the gains."""
    from dscjax import config

    one_of(precision, "precision", PRECISIONS)
    law, gains = trace(setup, spec), config.model_to_dict("controller", setup.controller)
    real = _Real(precision)
    try:
        return {HEADER: _header(law, spec, source, gains, real), SOURCE: _source(law, real)}
    except _OutOfRange as e:  # outside an operation: an initial value, the sample time
        raise e.error(precision) from None


def _header(law, spec, source, gains, real) -> str:
    r = real.name
    init, step = _signatures(law, r)
    n_hi = law.n_ref - 2
    ref_doc = ("yr, yr_dot: the reference y_r(t) and its derivative"
               + (f";\n *   yr_higher[j] = the derivative j + 2 of y_r(t), j = 0..{n_hi - 1} "
                  f"(the law reads them)" if n_hi else ""))
    glines = "\n".join(f" *   {k} = {v}" for k, v in gains.items())
    delay = (f"input delay: {spec.delay} sample(s):\n * dsc_step returns the input computed "
             f"{spec.delay} sample(s) before (the first one until then)" if spec.delay
             else "no input delay")
    precision = ("double precision" if r == "double" else
                 "single precision: C float throughout (constants and <math.h> functions)")
    line = ", delay line" if spec.delay else ""
    derived = [nm for nm, _, advances in law.state if not advances]
    derived_doc = (f",\n * and what the initialisation derives ({', '.join(derived)}),"
                   if derived else "")
    return f"""/* dsc_controller.h: the digital controller of {source or 'a dscjax config'},
 * generated by `dscjax export`: exactly the initialisation and the update law of dscjax's
 * sampled loop.
 *
 * Order n = {law.order}; sample time Ts = {law.sample_time!r} s; {delay}.
 * The controller's states advance by {spec.discretisation.name}:
 *   {SCHEME_DOC[spec.discretisation.name]}.
 * dsc_init starts the controller from the measured plant state x0 at time t0, as dscjax's
 * loop starts from plant.x0: its filters, estimates{line}{derived_doc} are
 * computed from x0 and the reference at t0 by the simulation's own initialisation.
 * dsc_step reads the plant state x (n values, measured at t), t and the reference:
 *   {ref_doc}.
 * Call dsc_init once, then dsc_step once per sample, at t = t0 + k Ts, k = 0, 1, ..., and
 * hold its u until t + Ts. The controller is dscjax's loop started at t0 (its time origin).
 * Actuator limit: none. dsc_step returns u unbounded, as the simulated loop applies it; a
 * limit clipped by the caller makes a loop that was not simulated (the adaptive laws keep
 * adapting while u is clipped).
 * C99, {precision}, only <math.h>; compile without -ffast-math for dscjax's numbers.
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
{init};
/* the controller's state at t0 from the measured plant state x0 ({law.order} values) and the
   reference at t0 */
{step};
/* one sample: x = the plant state ({law.order} values) at time t; returns u to hold until t + Ts,
   and advances the controller's states by one sample */
{r} dsc_sample_time(void);
int    dsc_order(void);

#endif
"""


def _assign(atoms, em, fields, *, stage: bool) -> list[str]:
    """Statements writing `atoms` into the state `fields`; `stage`: all read before any is
    written (the step's u and next state may read the state being replaced)."""
    r = em.real.name
    lines, writes = [], []
    for (nm, shp, _), a in zip(fields, atoms, strict=True):
        vals = [em.el(a, i) for i in range(_size(shp))]
        if stage:
            lines.append(f"    {r} next_{nm}[{len(vals)}] = {{{', '.join(vals)}}};")
            vals = [f"next_{nm}[{i}]" for i in range(len(vals))]
        writes += [f"    s->{nm}{'' if shp == () else f'[{i}]'} = {v};" for i, v in enumerate(vals)]
    return lines + writes


def _source(law: Law, real: _Real) -> str:
    r = real.name
    init, step = _signatures(law, r)
    fields = "\n".join(f"    {r} {nm}{'' if shp == () else f'[{_size(shp)}]'};"
                       for nm, shp, _ in law.state)
    ref_names = ["yr", "yr_dot"] + (["yr_higher"] if law.n_ref > 2 else [])
    em_init = _Emitter(law, real, x="x0")
    em_init.program(law.init)
    init_body = "\n".join(
        [f"    {' '.join(f'(void){u};' for u in ['x0', *ref_names])}"]
        + em_init.lines + _assign(law.init.outputs, em_init, law.state, stage=False)
        + ["    s->t0 = t0;"])
    em = _Emitter(law, real)
    if law.reads_t:
        em.lines.append(f"    {r} t_s = t - s->t0;  /* the time since dsc_init */")
    em.program(law.step)
    u, *new = law.step.outputs  # all read before the state is written (u may be s->past[...])
    advancing = [f for f in law.state if f[2]]
    step_body = "\n".join(
        [f"    {' '.join(f'(void){u_};' for u_ in ['t', 'x', *ref_names])}"] + em.lines
        + [f"    {r} u_out = {em.el(u, 0)};"] + _assign(new, em, advancing, stage=True))
    return f"""/* dsc_controller.c: generated by `dscjax export` from the jaxprs of dscjax's
 * initialisation (closed_loop.initial_state) and sample update (closed_loop.sample_update);
 * see dsc_controller.h. */
#include <math.h>
#include <stddef.h>
#include "dsc_controller.h"

typedef struct {{
{fields}
    {r} t0;
}} dsc_state;

size_t dsc_state_size(void) {{ return sizeof(dsc_state); }}

{r} dsc_sample_time(void) {{ return {real.num(law.sample_time)}; }}

int dsc_order(void) {{ return {law.order}; }}

/* max and min as XLA computes them: NaN if either is */
static inline {r} dsc_max_({r} a, {r} b) {{
    return (a != a || b != b) ? a + b : (a > b ? a : b);
}}
static inline {r} dsc_min_({r} a, {r} b) {{
    return (a != a || b != b) ? a + b : (a < b ? a : b);
}}
static inline {r} dsc_sign_({r} a) {{ return a > 0 ? {real.one} : (a < 0 ? -{real.one} : a); }}

{init} {{
    dsc_state *s = (dsc_state *)state;
{init_body}
}}

{step} {{
    dsc_state *s = (dsc_state *)state;
{step_body}
    return u_out;
}}
"""
