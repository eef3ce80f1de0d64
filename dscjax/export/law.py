"""The sampled controller of a config traced into flat programs (`trace` -> `Law`), for the C
emitter (`export.c`): the jaxprs of its initialisation and of `closed_loop.sample_update`,
nested calls inlined, dead code dropped; what the initialisation derives from x(0) and the
reference becomes state, everything else a constant of the concrete config.
"""

from __future__ import annotations

import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import source_info_util
from jax.extend.core import Literal

from dscjax.closed_loop import SampledState, Sampling, initial_state, prepared, sample_update
from dscjax.reference import Given, InitialOffset
from dscjax.simulate import depends_on_inputs
from dscjax.validation import ConfigError


class ExportError(ConfigError):
    """A config whose law uses something the C emitter does not write (one line)."""


def _with_given(prepared_ref, d):
    """The prepared reference (prepared from `Given(d0)`) reading the inputs d instead (the
    L-inf initialisation's decaying offset stays in the law)."""
    if isinstance(prepared_ref, Given):
        return Given(d=d)
    if isinstance(prepared_ref, InitialOffset) and isinstance(prepared_ref.base, Given):
        return dataclasses.replace(prepared_ref, base=Given(d=d))
    raise ExportError(f"reference: the controller's initialisation changes the reference in a "
                      f"way export does not know ({type(prepared_ref).__name__})")


@dataclasses.dataclass
class Program:
    """One traced function as flat, live operations and the atoms of its outputs."""

    ops: list
    outputs: list


@dataclasses.dataclass
class Law:
    """The traced initialisation and sample update, and what the C around them needs."""

    init: Program  # outputs: the initial value of every field of `state`, in order
    step: Program  # outputs: u, then the new value of every field of `state` that advances
    state: list  # [(C name, shape, advances)]: the controller's state, the delay line, then
    #              what the initialisation derives from x(0) and the step only reads
    n_ref: int  # reference values the law reads: y_r .. y_r^(n_ref - 1)
    order: int
    sample_time: float
    reads_t: bool  # whether the step reads t (the L-inf offset's decay does)


def _name(path) -> str:
    """A C identifier of a pytree path: ('controller', .c) -> 'controller_c'."""
    parts = [str(getattr(k, "name", getattr(k, "key", getattr(k, "idx", k)))) for k in path]
    return "".join(c if c.isalnum() else "_" for c in "_".join(parts)).strip("_")


def trace(setup, spec) -> Law:
    """The sampled controller of (setup, spec) as flat programs (spec sampled, float64)."""
    if not spec.sampled:
        raise ConfigError("simulation.sample_time: export needs a sampled controller")
    X0 = jax.eval_shape(lambda: initial_state(prepared(setup)))  # shapes and dtypes only
    dtype = X0.x.dtype
    if dtype != np.float64:
        raise ConfigError(f"simulation.dtype: export writes the controller from its float64 "
                          f"trace (got a {dtype} setup; turn jax_enable_x64 on)")
    n_d = setup.order + 2  # more reference derivatives than any law of this order reads
    every, dt = float(spec.sample_every), float(spec.dt)
    sampling = Sampling(every=every, delay=spec.delay, line=spec.delay,
                        scheme=spec.discretisation)
    zero = jnp.zeros((), dtype)

    def prepare_at(x0, d0):
        """{plant, controller, reference} as dscjax's loop starts with them from x(0) = x0
        and the reference's derivatives d0 at the start (`closed_loop.prepared`)."""
        plant = dataclasses.replace(setup.plant, x0=x0)
        p = prepared(setup.replace(plant=plant, reference=Given(d=d0)))
        return {"plant": p.plant, "controller": p.controller, "reference": p.reference}

    # What the initialisation derives from x(0) and the reference (the DSC's c and the L-inf
    # offset, say) becomes state that dsc_init sets; everything else stays a constant.
    d_any = (zero,) * n_d
    probe = jax.make_jaxpr(lambda x0, d0: jax.tree.leaves(prepare_at(x0, d0)))(X0.x, d_any)
    paths, treedef = jax.tree_util.tree_flatten_with_path(
        prepare_at(jnp.asarray(setup.plant.x0, dtype), d_any))
    base = [v for _, v in paths]
    which = [i for i, dep in enumerate(depends_on_inputs(probe.jaxpr)) if dep]
    # the actuator's state: sample_update moves it, nothing the C returns depends on it
    h0 = jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype), X0.h)

    def step(ctrl, past, values, x, t, d):
        given = dict(zip(which, values, strict=True))
        leaves = [given.get(i, v) for i, v in enumerate(base)]
        loop = setup.replace(**jax.tree.unflatten(treedef, leaves))
        loop = loop.replace(reference=_with_given(loop.reference, d))
        X = SampledState(x=x, h=h0, ctrl=ctrl, u=jnp.zeros_like(t), past=past)
        new = sample_update(jnp.zeros((), jnp.int32), t, X, loop, sampling, dt)
        return new.u, new.ctrl, [new.past] if spec.delay else []

    def init(x0, d0):
        p = prepare_at(x0, d0)
        loop = setup.replace(**p)
        X = initial_state(loop)  # the simulation's own X(0) of this x(0)
        u0, _ = loop.controller.law(X.ctrl, X.x, zero, loop.plant, loop.reference)
        past = jnp.full((spec.delay,), u0, dtype)  # as closed_loop.sampled_initial_state
        flat = jax.tree.leaves(p)  # `kept`: set below, before init is traced
        return X.ctrl, [past] if spec.delay else [], [flat[which[k]] for k in kept]

    leaves = jax.tree_util.tree_flatten_with_path(X0.ctrl)[0]
    ctrl_names = [_name(p) for p, _ in leaves]
    value_names = [_name(paths[i][0]) for i in which]
    values0 = [base[i] for i in which]
    ref_in = [("ref", j) for j in range(n_d)]
    # the step's inputs: the state's leaves, the delay line (a (0,) array nothing reads if no
    # delay), the derived values, x, t and the reference's derivatives
    kinds = ([("state", nm) for nm in ctrl_names] + [("state", "past" if spec.delay else None)]
             + [("state", nm) for nm in value_names] + [("x",), ("t",)] + ref_in)
    past0 = jnp.zeros((spec.delay,), dtype)
    closed = jax.make_jaxpr(step)(X0.ctrl, past0, values0, X0.x, zero, d_any)
    step_prog = _program(closed, kinds)  # u, the state that advances
    read = {a[1] for a in _atoms(step_prog) if a[0] == "in"}
    kept = [k for k, nm in enumerate(value_names) if ("state", nm) in read]
    state = ([(nm, tuple(v.shape), True) for nm, (_, v) in zip(ctrl_names, leaves, strict=True)]
             + ([("past", (spec.delay,), True)] if spec.delay else [])
             + [(value_names[k], np.shape(values0[k]), False) for k in kept])
    # every field of `state`: the controller's state, the delay line if any, the derived values
    init_prog = _program(jax.make_jaxpr(init)(X0.x, d_any), [("x",)] + ref_in)
    used = {a[1][1] for prog in (step_prog, init_prog) for a in _atoms(prog)
            if a[0] == "in" and a[1][0] == "ref"}
    n_ref = max(used, default=1) + 1
    if n_ref >= n_d:
        raise ExportError(f"reference: the law reads more than {n_d - 1} derivatives of y_r")
    return Law(init=init_prog, step=step_prog, state=state, n_ref=max(n_ref, 2), order=setup.order,
               sample_time=every * dt, reads_t=("t",) in read)


def _atoms(prog: Program) -> list:
    return [*prog.outputs, *(a for op in prog.ops for a in op.ins)]


def _program(closed, kinds) -> Program:
    """The closed jaxpr inlined into live operations; its inputs are the atoms ("in", kind,
    shape)."""
    jx = closed.jaxpr
    flat = _Flattener()
    ins = [("in", kind, v.aval.shape) for v, kind in zip(jx.invars, kinds, strict=True)]
    outs = flat.call(jx, closed.consts, ins)
    return Program(_live(flat.ops, outs), outs)


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
        self.ids = itertools.count(1)  # of the operations' outputs

    def atom(self, env, v):
        return ("lit", np.asarray(v.val)) if isinstance(v, Literal) else env[v]

    def call(self, jaxpr, consts, ins, outer: str = "") -> list:
        """The atoms of the outputs of `jaxpr` (its constants `consts`) on the input atoms
        `ins`, its operations appended; `outer`: the Python line of the call it is inlined at
        (for a library's own nested calls)."""
        env = {v: ("const", np.asarray(c)) for v, c in zip(jaxpr.constvars, consts, strict=True)}
        env |= dict(zip(jaxpr.invars, ins, strict=True))
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
                inner, consts = (sub.jaxpr, sub.consts) if hasattr(sub, "consts") else (sub, [])
                outs = self.call(inner, consts, ins[len(ins) - len(inner.invars):], where)
            else:
                outs = [("v", next(self.ids), tuple(o.aval.shape), np.dtype(o.aval.dtype))
                        for o in eqn.outvars]
                self.ops.append(Op(name, ins, outs, dict(eqn.params), where))
            env.update(zip(eqn.outvars, outs, strict=True))
        return [self.atom(env, v) for v in jaxpr.outvars]


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
