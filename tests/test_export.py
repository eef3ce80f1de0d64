"""`dscjax export` (issues 33, 38): the C controller, compiled by the system's C compiler and
loaded by ctypes, driven in closed loop with a plant written here (RK4 with u held, the
hysteresis jumped at each new input), equals dscjax's sampled simulation, started by dsc_init
from whatever x(0) the plant has; the float variant is the double one to its rounding bound."""

import ctypes
import dataclasses
import functools
import json
import re
import shutil
import subprocess

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

CC = shutil.which("cc") or shutil.which("gcc")
DT = 1e-3
EPS32 = float(np.finfo(np.float32).eps)

needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler (cc or gcc) on PATH: the "
                              "exported controller cannot be compiled here")


def _load(setup, spec, directory, precision="double"):
    """The exported controller of (setup, spec), compiled into a shared library, and the
    number of reference values its dsc_init and dsc_step take (y_r, y_r', ...)."""
    from dscjax import export

    files = export.c_files(setup, spec, source="a test", precision=precision)
    m = int(files[export.HEADER].split("#define DSC_REFERENCE_DERIVATIVES ")[1].split()[0]) + 1
    for name, text in files.items():
        (directory / name).write_text(text)
    lib_path = directory / "libdsc.so"
    # -Wdouble-promotion: a float controller that computes anything in double is refused
    subprocess.run([CC, "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic",
                    "-Wdouble-promotion", "-ffp-contract=off", "-shared", "-fPIC", "-o",
                    str(lib_path), str(directory / export.SOURCE), "-lm"], check=True)
    lib = ctypes.CDLL(str(lib_path))
    real = ctypes.c_double if precision == "double" else ctypes.c_float
    lib.dsc_state_size.restype = ctypes.c_size_t
    lib.dsc_sample_time.restype = real
    lib.dsc_step.restype = real
    more = [ctypes.POINTER(real)] if m > 2 else []
    args = [ctypes.c_void_p, real, ctypes.POINTER(real), real, real, *more]
    lib.dsc_step.argtypes = lib.dsc_init.argtypes = args
    lib.real = real
    return lib, m


@functools.partial(jax.jit, static_argnames="every")
def _segment(plant, hyst, x, h, u_from, u_to, k, every):
    """The actuator's hysteresis jumps from u_from to u_to, then `every` RK4 steps of the
    plant with w held, from the sample k."""
    h = hyst.jump(u_from, u_to, h)
    w = hyst.output(u_to, h)

    def rk4(j, x):
        t = (k * every + j).astype(x.dtype) * DT
        k1 = plant.rhs(x, w, t)
        k2 = plant.rhs(x + 0.5 * DT * k1, w, t + 0.5 * DT)
        k3 = plant.rhs(x + 0.5 * DT * k2, w, t + 0.5 * DT)
        k4 = plant.rhs(x + DT * k3, w, t + DT)
        return x + (k1 + 2.0 * (k2 + k3) + k4) * (DT / 6.0)

    return jax.lax.fori_loop(0, every, rk4, x), h


@jax.jit
def _start(setup):
    """(the prepared setup, X(0), u(0)) of the simulation (one program, not op by op)."""
    from dscjax.closed_loop import initial_state, prepared

    s = prepared(setup)
    X0 = initial_state(s)
    return s, X0, s.controller.law(X0.ctrl, X0.x, jnp.zeros_like(X0.x[0]), s.plant,
                                   s.reference)[0]


@functools.partial(jax.jit, static_argnames="m")
def _reference(ref, times, m):
    """(y_r, ..., y_r^(m-1)) at times, (K, m)."""
    return jax.vmap(lambda t: jnp.stack(ref.derivatives(t, m - 1)))(times)


def _closed_loop(setup, lib, m, every, n_samples):
    """The C controller with the plant of `setup`, from its x(0): dsc_init(0, x(0), y_r(0),
    ...), then at t_k = k Ts, u_k = dsc_step(x(t_k), y_r, y_r', ... (m reference values)),
    the actuator's hysteresis jumps from u_(k-1) to u_k, then `every` RK4 steps of the plant
    with w held. Returns (u_k (K,), x(t_k) (K, n))."""
    # the config's own reference: the C reads its values
    d = np.asarray(_reference(setup.reference, np.arange(n_samples) * (every * DT), m))
    # the actuator's state at t = 0, which the plant brings: the simulation's own
    s, X0, u0 = _start(setup)
    x, h, u_prev = X0.x, X0.h, float(u0)
    real, n = lib.real, setup.order
    state = ctypes.create_string_buffer(lib.dsc_state_size())
    xbuf, higher = (real * n)(), (real * max(m - 2, 1))()

    def reference(k):
        higher[:m - 2] = d[k, 2:].tolist()
        return float(d[k, 0]), float(d[k, 1]), *([higher] if m > 2 else [])

    xbuf[:] = np.asarray(x).tolist()
    lib.dsc_init(state, 0.0, xbuf, *reference(0))
    us, xs = np.empty(n_samples), np.empty((n_samples, n))
    for k in range(n_samples):
        xs[k] = np.asarray(x)
        xbuf[:] = xs[k].tolist()
        us[k] = u = lib.dsc_step(state, k * every * DT, xbuf, *reference(k))
        x, h = _segment(s.plant, s.hysteresis, x, h, u_prev, u, jnp.asarray(k), every)
        u_prev = u
    return us, xs


def _build(example, init=None):
    from dscjax.config import example as build

    setup = build(example, dtype=np.float64)
    if init is not None:
        setup = setup.replace(controller=dataclasses.replace(setup.controller, init=init))
    return setup


CASES = [  # (example, controller.init, x(0) of the plant (None: the config's), horizon,
    #         sample time in steps, delay, discretisation)
    # issue 38: from rest the C started with the filter state of the config's x(0)
    ("paper", None, (0.0, 0.0), 2.0, 1, 0, "exponential-euler"),
    # c, the reference's offset and the delay line's first input all come from x(0) (from
    # (2, 0.1) the paper's own initialisation diverges, in the simulation too)
    ("paper", "linf", (2.0, 0.1), 2.0, 1, 1, "exponential-euler"),
    ("order-4", None, None, 1.0, 1, 0, "euler"),
    ("pi", None, (0.02, 0.0), 1.0, 2, 1, "exponential-euler"),
    # the law reads y_r'' too (a third reference argument)
    ("backstepping", None, (0.0, 0.0), 1.0, 1, 0, "exponential-euler"),
]


@needs_cc
@pytest.mark.parametrize("example, init, x0, t_final, every, delay, scheme", CASES)
def test_the_exported_controller_is_the_sampled_loop(tmp_path, example, init, x0, t_final,
                                                     every, delay, scheme):
    """Exported from the config, run from x(0) (the config's or another): u(t_k) and x(t_k)
    equal `simulate` of the config with plant.x0 = x(0), to round-off."""
    import dscjax
    from dscjax import params

    setup = _build(example, init)
    spec = dscjax.RunSpec.make(t_final, DT, save_every=1, sample_time=every * DT, delay=delay,
                               discretisation=scheme)
    lib, m = _load(setup, spec, tmp_path)
    assert lib.dsc_order() == setup.order and lib.dsc_sample_time() == every * DT
    assert m == (3 if example == "backstepping" else 2)
    if x0 is not None:
        setup = params.set(setup, "plant.x0", np.array(x0))
    traj = dscjax.simulate(setup, spec=spec)
    us, xs = _closed_loop(setup, lib, m, every, int(round(t_final / (every * DT))))
    u_want = np.asarray(traj.u)[:-1:every]
    x_want = np.asarray(traj.x)[:-1:every]
    assert np.max(np.abs(u_want)) > 0.1  # the loop does something
    # round-off only: libm's and XLA's exp, sin, ... may differ by an ulp
    np.testing.assert_allclose(us, u_want, rtol=1e-9, atol=1e-9 * np.max(np.abs(u_want)))
    np.testing.assert_allclose(xs, x_want, rtol=1e-9, atol=1e-9 * np.max(np.abs(x_want)))


# -- dsc_init and one sample, against the simulation's own functions --------------------------


def _state_fields(setup, spec):
    """[(name, size, advances)] of the C's state in its order, as export.trace lays it."""
    from dscjax import export

    return [(nm, int(np.prod(shp, dtype=int)), adv)
            for nm, shp, adv in export.trace(setup, spec).state]


@needs_cc
@pytest.mark.parametrize("init, delay", [("linf", 2), ("zero_surfaces", 1)])
def test_dsc_init_is_the_simulations_initial_state_of_any_x0(tmp_path, init, delay):
    """dsc_init(t0, x0, y_r(0), ...) writes the controller's state, the delay line and what
    the initialisation derives (c, the reference's offset) exactly as `initial_state` and
    `prepared` compute them for a setup with plant.x0 = x0, at random x0."""
    import dscjax
    from dscjax import params

    setup = _build("paper", init)
    spec = dscjax.RunSpec.make(1.0, DT, sample_time=DT, delay=delay)
    lib, _ = _load(setup, spec, tmp_path)
    fields = _state_fields(setup, spec)
    size = sum(k for _, k, _ in fields) + 1  # and t0, last
    assert lib.dsc_state_size() == 8 * size
    rng = np.random.default_rng(1)
    yr, yr_dot = (float(v) for v in setup.reference.derivatives(jnp.zeros(()), 1))
    for _ in range(3):
        x0 = rng.uniform(-1.0, 1.0, setup.order)
        buf = (ctypes.c_double * size)()
        # the C reads the reference's values, not t0, which it keeps as its time origin
        lib.dsc_init(buf, 0.25, (ctypes.c_double * setup.order)(*x0.tolist()), yr, yr_dot)
        s, X0, u0 = _start(params.set(setup, "plant.x0", x0))
        want = {"past": np.full(delay, float(u0))}
        want |= {nm: np.ravel(v) for nm, v in zip(
            [f[0] for f in fields], jax.tree.leaves(X0.ctrl), strict=False)}
        if init in ("linf", "zero_surfaces"):
            want["controller_c"] = np.ravel(s.controller.c)
        if init == "linf":
            want["reference_offset"] = np.ravel(s.reference.offset)
        got, at = {}, 0
        for nm, k, _ in fields:
            got[nm], at = np.asarray(buf[at:at + k]), at + k
        assert sorted(got) == sorted(k for k in want if k != "past" or delay)
        for nm in got:  # (u0 of zero surfaces is a cancellation: zero to rounding, 1e-13)
            np.testing.assert_allclose(got[nm], want[nm], rtol=1e-13, atol=1e-12, err_msg=nm)
        assert buf[size - 1] == 0.25  # t0


# a user's plant functions (module level: equal plants hash equal)
def _f_by_matrices(x, p):
    """f_1 = x_1^2, f_2 = 0, written with a matrix product, a transpose and reductions."""
    m = jnp.stack([x, -x])
    return jnp.stack([jnp.dot(p["e"], x) ** 2,
                      0.0 * jnp.sum(m.T @ x) * jnp.max(x) * jnp.min(x)])


def _rho(x, p):
    return jnp.stack([0.2, 0.1 * jnp.sum(x * x)])


def _delta(x, t, p):
    return jnp.zeros(2)


def _dbar(t, p):
    return 0.0


def _custom_plant_setup():
    from dscjax.config import paper_example
    from dscjax.plant import CustomPlant

    plant = CustomPlant(jnp.ones(2), jnp.array([0.1, 0.0]), jnp.array([0.08, 0.1]),
                        {"e": jnp.array([1.0, 0.0])}, _f_by_matrices, _rho, _delta, _dbar)
    setup = paper_example(dtype=np.float64).replace(plant=plant)
    return setup.replace(controller=dataclasses.replace(setup.controller, robust_term="smooth"))


def _order3_linf_setup():
    setup = _build("order-3")
    return setup.replace(controller=dataclasses.replace(
        setup.controller, init="linf", robust_term="sgn", variant="no_dhat_no_zeta"))


@needs_cc
@pytest.mark.parametrize("build, delay, scheme", [(_custom_plant_setup, 0, "euler"),
                                                  (_order3_linf_setup, 2, "exponential-euler")])
def test_one_sample_of_the_c_equals_the_sample_update(tmp_path, build, delay, scheme):
    """One sample of the C, at random states and times, against `closed_loop.sample_update`:
    u and every state (the leaves in order, then the delay line). A user's plant functions
    with dot_general, transpose and reductions and the smooth robust term; the L-inf
    initialisation's time-dependent reference offset (dsc_init at the config's x(0)), sgn,
    no adaptation of zeta."""
    import dscjax
    from dscjax.closed_loop import SampledState, Sampling, initial_state, prepared, sample_update

    setup = build()
    spec = dscjax.RunSpec.make(1.0, DT, sample_time=2 * DT, delay=delay, discretisation=scheme)
    lib, _ = _load(setup, spec, tmp_path)
    s = prepared(setup)
    X0 = initial_state(s)
    n = setup.order
    size = lib.dsc_state_size() // 8
    buf = (ctypes.c_double * size)()
    y0, y0_dot = (float(v) for v in setup.reference.derivatives(jnp.zeros(()), 1))
    lib.dsc_init(buf, 0.0, (ctypes.c_double * n)(*np.asarray(X0.x).tolist()), y0, y0_dot)
    rng = np.random.default_rng(0)
    for k in range(4):
        ctrl = jax.tree.map(lambda a: a + 0.1 * rng.standard_normal(np.shape(a)), X0.ctrl)
        past = rng.standard_normal(delay)
        x, t = X0.x + 0.5 * rng.standard_normal(n), 0.37 * k
        new = jax.jit(sample_update)(jnp.asarray(k), t, SampledState(
            x=x, h=X0.h, ctrl=ctrl, u=jnp.zeros(()), past=jnp.asarray(past)), s,
            Sampling(every=2.0, delay=delay, line=delay, scheme=spec.discretisation), DT)
        # the state starts with the leaves, in order, then the delay line
        flat = np.concatenate([np.ravel(a) for a in jax.tree.leaves(ctrl)] + [past])
        buf[:flat.size] = flat.tolist()
        yr, yr_dot = (float(v) for v in setup.reference.derivatives(jnp.asarray(t), 1))
        u = lib.dsc_step(buf, t, (ctypes.c_double * n)(*np.asarray(x).tolist()), yr, yr_dot)
        want = np.concatenate([np.ravel(a) for a in jax.tree.leaves(new.ctrl)]
                              + [np.asarray(new.past)])
        np.testing.assert_allclose(u, float(new.u), rtol=1e-13)
        np.testing.assert_allclose(np.asarray(buf[:flat.size]), want, rtol=1e-13, atol=1e-15)


# -- the float variant -------------------------------------------------------------------------


# the primitives whose result a float evaluation rounds (the others move or compare values)
ROUNDED = {"add", "add_any", "sub", "mul", "div", "exp", "exp2", "expm1", "log", "log1p",
           "sqrt", "rsqrt", "cbrt", "sin", "cos", "tan", "tanh", "atan", "atan2", "pow",
           "integer_pow", "logistic", "square", "rem", "dot_general", "reduce_sum"}


def _rounding_gain(fn, *example):
    """A jitted g(*args) -> (outputs, G) of fn: its outputs (flat) and, per output element,
    G = sum_i |d out / d delta_i| over every rounding i of a float evaluation of fn, each
    modelled as v (1 + delta_i): every element of every input, every constant and every
    arithmetic result of fn's jaxpr (a sum of L terms: L roundings; x^y: |y| - 1
    products). With every |delta_i| <= eps, |float - exact| <= eps G to first order."""
    from jax.extend.core import Literal

    calls = ("jaxpr", "call_jaxpr", "fun_jaxpr")
    closed = jax.make_jaxpr(fn)(*example)

    def run(draw, args):
        """fn's outputs with every rounding v -> draw(v, count)."""
        def floating(v):
            return jnp.issubdtype(jnp.asarray(v).dtype, jnp.floating)

        def ev(jaxpr, consts, ins):
            env = dict(zip(jaxpr.invars, ins, strict=True))
            env |= {v: draw(jnp.asarray(c), 1) if floating(c) else c
                    for v, c in zip(jaxpr.constvars, consts, strict=True)}

            def read(v):
                if isinstance(v, Literal):  # 0, 1, 0.5, ...: no rounding
                    exact = np.float32(v.val) == v.val
                    return draw(jnp.asarray(v.val), 1) if floating(v.val) and not exact else v.val
                return env[v]

            for eqn in jaxpr.eqns:
                vals = [read(v) for v in eqn.invars]
                name = eqn.primitive.name
                sub = next((eqn.params[k] for k in calls if k in eqn.params), None)
                if sub is not None:
                    inner = getattr(sub, "jaxpr", sub)
                    outs = ev(inner, getattr(sub, "consts", []),
                              vals[len(vals) - len(inner.invars):])
                else:
                    outs = eqn.primitive.bind(*vals, **eqn.params)
                    outs = outs if eqn.primitive.multiple_results else [outs]
                    if name in ROUNDED and floating(outs[0]):
                        count = (max(np.size(vals[0]) // max(np.size(outs[0]), 1), 1)
                                 if name in ("reduce_sum", "dot_general") else
                                 max(abs(int(eqn.params["y"])) - 1, 1) if name == "integer_pow"
                                 else 1)
                        outs = [draw(outs[0], count)]
                env.update(zip(eqn.outvars, outs, strict=True))
            return [read(v) for v in jaxpr.outvars]

        flat = [draw(jnp.asarray(a), 1) if floating(a) else a for a in jax.tree.leaves(args)]
        return jnp.concatenate([jnp.ravel(o) for o in ev(closed.jaxpr, closed.consts, flat)])

    sizes = []
    jax.eval_shape(lambda args: run(lambda v, count: sizes.append(jnp.size(v)) or v, args),
                   example)

    def perturbed(deltas, args):  # deltas: one vector, sliced in the order run draws
        at = iter(np.cumsum([0, *sizes[:-1]]).tolist())

        def draw(v, count):
            i = next(at)
            return v * (1 + count * deltas[i:i + jnp.size(v)].reshape(jnp.shape(v)))

        return run(draw, args)

    @jax.jit
    def gain(*args):
        out, pullback = jax.vjp(lambda d: perturbed(d, args), jnp.zeros(sum(sizes)))
        jac = jax.vmap(pullback)(jnp.eye(out.size, dtype=out.dtype))[0]  # (outputs, deltas)
        return out, jnp.sum(jnp.abs(jac), axis=1)

    return gain


def _gain_sets():
    """[setup]: the paper's example with its own gains and with `dscjax tune`'s
    (reproduce.sampling.TUNED)."""
    from dscjax.config import from_dict
    from dscjax.params import cast
    from dscjax.reproduce.sampling import TUNED

    setup = _build("paper")
    # float64 arrays, not Python floats: one compiled program serves both
    return [setup, cast(from_dict({"controller": TUNED}, base=setup)[0], np.dtype("float64"))]


def _sample(s, ctrl, x, t, d):
    """One sample of the double loop's controller (setup `s` prepared, its reference given
    by d = (y_r, y_r')): u and the next state, flat."""
    from dscjax.closed_loop import SampledState, Sampling, sample_update
    from dscjax.reference import Given

    # h: the backlash's output, which the controller never reads
    X = SampledState(x=x, h=jnp.zeros_like(t), ctrl=ctrl, u=jnp.zeros_like(t),
                     past=jnp.zeros((0,)))
    new = sample_update(jnp.zeros((), jnp.int32), t, X, s.replace(reference=Given(d=d)),
                        Sampling(every=1.0), DT)
    return jnp.concatenate([new.u[None], ravel_pytree(new.ctrl)[0]])


@functools.cache
def _sample_gain():
    """`_rounding_gain` of `_sample` for the paper's example (any gains: they are arguments)."""
    from dscjax.closed_loop import initial_state, prepared

    s = prepared(_gain_sets()[0])
    X0 = initial_state(s)
    return _rounding_gain(_sample, s, X0.ctrl, X0.x, jnp.zeros(()), (jnp.zeros(()),) * 2)


@needs_cc
def test_one_float_sample_of_the_tuned_gains_is_the_double_one_within_its_rounding_bound(
        tmp_path):
    """The float C's sample (u and the next state) at states along the double loop of the
    tuned gains (high gains, a boundary layer 5 times thinner than the paper's), against
    `sample_update` in float64: |float - exact| <= 2 eps32 G per output, G = the law's gain
    from relative roundings (`_rounding_gain`: every input, constant and operation rounded
    once by at most one ulp, eps32); 2 for the second-order terms, (L eps32)^2 for a chain of
    L << 1/eps32 roundings."""
    import dscjax
    from dscjax.closed_loop import initial_state, prepared

    setup = _gain_sets()[1]
    spec = dscjax.RunSpec.make(1.0, DT, save_every=1, sample_time=DT)
    lib, _ = _load(setup, spec, tmp_path, precision="float")
    s = prepared(setup)
    X0 = initial_state(s)
    traj = dscjax.simulate(setup, spec=spec)
    d_all = _reference(setup.reference, traj.t, 2)
    n, size = setup.order, lib.dsc_state_size() // 4
    buf = (ctypes.c_float * size)()
    lib.dsc_init(buf, 0.0, (ctypes.c_float * n)(*np.asarray(X0.x).tolist()),
                 *(float(v) for v in d_all[0]))
    gain = _sample_gain()
    for k in np.linspace(0, len(traj.t) - 2, 10).astype(int):
        ctrl = jax.tree.map(lambda a, k=k: a[k], traj.ctrl)
        x, t, d = traj.x[k], traj.t[k], tuple(d_all[k])
        want, g = (np.asarray(a) for a in gain(s, ctrl, x, t, d))
        flat = np.asarray(ravel_pytree(ctrl)[0])
        buf[:flat.size] = flat.tolist()
        u = lib.dsc_step(buf, float(t), (ctypes.c_float * n)(*np.asarray(x).tolist()),
                         *(float(v) for v in d))
        got = np.concatenate([[u], np.asarray(buf[:flat.size], float)])
        assert np.all(np.abs(got - want) <= 2 * EPS32 * g), (k, got - want, g)


@needs_cc
def test_the_float_loop_from_rest_is_the_double_one_within_its_rounding_bound(tmp_path):
    """The float C in closed loop from dsc_init at rest (the paper's gains) against the
    double loop: at every sample, |u_f - u| and |x_f - x| <= 2 eps32 B, B = sum over the
    samples j so far and the controller's outputs o (u and its next state) of |d (u or x) /
    d r_jo| G_jo: the loop's gain from a perturbation r_jo of output o at sample j (reverse
    mode through the double loop) times the law's gain G_jo from float roundings at that
    sample (`_rounding_gain`). The first-order bound of every rounding of the float
    controller as the loop propagates it; it holds while the loop is smooth: a loop that
    chatters in the boundary layer of sat (the tuned gains from rest) is not."""
    import dscjax
    from dscjax import params
    from dscjax.closed_loop import initial_state, prepared

    n_samples = 100
    setup = _gain_sets()[0]
    spec = dscjax.RunSpec.make(n_samples * DT, DT, save_every=1, sample_time=DT)
    lib, m = _load(setup, spec, tmp_path, precision="float")
    setup = params.set(setup, "plant.x0", np.zeros(2))
    s = prepared(setup)
    X0 = initial_state(s)
    flat0, unravel = ravel_pytree(X0.ctrl)
    times = jnp.arange(n_samples) * DT
    d_all = _reference(setup.reference, times, 2)
    u0, _ = s.controller.law(X0.ctrl, X0.x, 0.0, s.plant, s.reference)

    def loop(r):
        """The double loop with r (K, outputs) added to the controller's outputs at each
        sample: (u_k, x(t_k)) (K, 1 + n), and (those, the controller's state, x) before each
        sample."""
        def one(carry, inputs):
            x, h, u_prev, ctrl = carry
            t, d, rk = inputs
            out = _sample(s, unravel(ctrl), x, t, tuple(d)) + rk
            x_next, h = _segment(s.plant, s.hysteresis, x, h, u_prev, out[0],
                                 jnp.round(t / DT).astype(jnp.int32), 1)
            return (x_next, h, out[0], out[1:]), (jnp.concatenate([out[:1], x]), ctrl, x)

        outs = jax.lax.scan(one, (X0.x, X0.h, jnp.asarray(u0), flat0), (times, d_all, r))[1]
        return outs[0], outs

    zero = jnp.zeros((n_samples, 1 + flat0.size))
    loop_gain, (want, ctrls, xs) = jax.jit(jax.jacrev(loop, has_aux=True))(zero)
    gain = _sample_gain()
    # on host arrays: no small program per sample
    ctrls, xs, times, d_all = (jax.tree.map(np.asarray, a)
                               for a in (jax.vmap(unravel)(ctrls), xs, times, d_all))
    law_gain = [gain(s, jax.tree.map(lambda a, k=k: a[k], ctrls), xs[k], times[k],
                     tuple(d_all[k]))[1] for k in range(n_samples)]
    bound = 2 * EPS32 * np.einsum("kajo,jo->ka", np.abs(np.asarray(loop_gain)),
                                  np.asarray(law_gain))
    us, xs_f = _closed_loop(setup, lib, m, 1, n_samples)
    err = np.abs(np.concatenate([us[:, None], xs_f], axis=1) - want)
    assert np.max(err[:, 0]) > 0  # float rounds
    assert np.all(err <= bound), np.max(err / np.maximum(bound, 1e-300))


# -- the command -----------------------------------------------------------------------------


def test_a_config_without_a_sample_time_is_refused_in_one_line(tmp_path, capsys):
    from dscjax.cli.main import main

    out = tmp_path / "c"
    assert main(["export", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["dscjax export: error: --sample-time is needed: the config has no "
                   "simulation.sample_time (a continuous controller); give --sample-time TS, "
                   "a number > 0 [s], e.g. 0.001"]
    assert not out.exists()


@pytest.mark.parametrize("ts, line", [
    # issue 38 item 7: the first was exported for dt = 0.00075, the last silently, the
    # second named --t-final, which export does not have
    ("0.0015", "--sample-time must be a whole multiple > 0 of the config's simulation.dt "
               "(got sample_time=0.0015, dt=0.001, ratio 1.5)"),
    ("1e-300", "--sample-time must be a whole multiple > 0 of the config's simulation.dt "
               "(got sample_time=1e-300, dt=0.001, ratio 1e-297)"),
    ("1e6", "--sample-time must be <= the config's simulation.t_final = 20 (got 1e+06)")])
def test_export_checks_the_sample_time_as_simulate_does(tmp_path, capsys, ts, line):
    """The C is exact for `simulate --sample-time TS` of the config: a TS simulate refuses is
    refused, by the same check, naming the config's step and horizon."""
    from dscjax.cli.main import main

    for command in ("export", "simulate"):
        out = tmp_path / command
        assert main([command, "--sample-time", ts, "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and not out.exists()
        if command == "export":
            assert err == [f"dscjax export: error: {line}"]


def test_export_reads_the_gains_file_and_its_sample_time(tmp_path, capsys):
    from dscjax import config
    from dscjax.cli.main import main

    gains = config.to_dict(config.example("order-3"))
    gains["controller"]["k"] = [7.25, 1.5, 0.75]
    gains["simulation"] |= {"sample_time": 0.002, "delay": 1, "discretisation": "euler"}
    path = tmp_path / "gains.json"
    path.write_text(json.dumps(gains))
    out = tmp_path / "c"
    assert main(["export", "--gains", str(path), "--out", str(out)]) == 0
    header = (out / "dsc_controller.h").read_text()
    for text in ("Order n = 3", "Ts = 0.002 s", "input delay: 1 sample", "advance by euler",
                 "k = [7.25, 1.5, 0.75]", f"--gains {path}", "double yr, double yr_dot)",
                 " * Actuator limit: none. dsc_step returns u unbounded, as the simulated "
                 "loop applies it;", "dsc_init starts the controller from the measured plant "
                 "state x0 at time t0"):
        assert text in header, text
    assert capsys.readouterr().out.endswith(f"wrote {out}/dsc_controller.h, "
                                            "dsc_controller.c\n")
    for text in ("void dsc_init(void *state, double t0, const double *x0, double yr, double "
                 "yr_dot);", "double dsc_step(void *state, double t, const double *x, double "
                 "yr, double yr_dot);"):
        assert text in header, text
    if CC is not None:  # a C99 compiler takes it without a warning
        subprocess.run([CC, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic",
                        "-fsyntax-only", str(out / "dsc_controller.c")], check=True)
    # the sample time is a whole multiple of the config's own step
    gains["simulation"] |= {"dt": 5e-4, "t_final": 1.0}
    path.write_text(json.dumps(gains))
    assert main(["export", "--gains", str(path), "--sample-time", "0.0015", "--out",
                 str(out), "--overwrite"]) == 0
    assert "Ts = 0.0015 s" in (out / "dsc_controller.h").read_text()


def test_export_precision_float_is_c_float_throughout(tmp_path, capsys):
    from dscjax.cli.main import main

    out = tmp_path / "c"
    assert main(["export", "--sample-time", "0.001", "--precision", "float", "--out",
                 str(out)]) == 0
    assert capsys.readouterr().out.endswith("/dsc_controller.h, dsc_controller.c\n")
    for text in ("void dsc_init(void *state, float t0, const float *x0, float yr, float yr_dot);",
                 "float dsc_step(void *state, float t, const float *x, float yr, float yr_dot);"):
        assert text in (out / "dsc_controller.h").read_text(), text
    source = (out / "dsc_controller.c").read_text()
    assert "double" not in source and "expm1f(" in source and "(-0.45f)" in source
    assert "C99, single precision: C float throughout" in (out / "dsc_controller.h").read_text()
    if CC is not None:  # nothing is promoted to double
        subprocess.run([CC, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic",
                        "-Wdouble-promotion", "-fsyntax-only", str(out / "dsc_controller.c")],
                       check=True)


def test_a_constant_beyond_float_is_refused_naming_it(tmp_path, capsys):
    from dscjax.cli.main import main

    config = tmp_path / "tiny.toml"
    config.write_text("[controller]\nsat_width = 1e-50\n")
    out = tmp_path / "c"
    assert main(["export", "--config", str(config), "--sample-time", "0.001", "--precision",
                 "float", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.fullmatch(
        r"dscjax export: error: controller: the constant 1e-50 \(controllers/adaptive.py:\d+ "
        r"\(AdaptiveLaws._robust\)\) is beyond the range of C float; export it in double "
        r"\(--precision double\)", err[0]), err
    assert not out.exists()


def _f_cumulative(x, p):
    return jnp.stack([jnp.cumsum(x * x)[0], 0.0 * x[1]])


def test_a_primitive_the_emitter_does_not_write_is_refused_naming_it():
    import dscjax
    from dscjax import export
    from dscjax.config import paper_example
    from dscjax.plant import CustomPlant

    plant = CustomPlant(jnp.ones(2), jnp.array([0.1, 0.0]), jnp.array([0.08, 0.1]), {},
                        _f_cumulative, _rho, _delta, _dbar)
    setup = paper_example(dtype=np.float64).replace(plant=plant)
    with pytest.raises(export.ExportError, match=r"^controller: export cannot write the "
                       r"primitive 'cumsum' \(test_export.py:\d+ \(_f_cumulative\)\) in C$"):
        export.c_files(setup, dscjax.RunSpec.make(1.0, DT, sample_time=DT))


def _f_huge(x, p):
    return jnp.concatenate([np.zeros(1_000_001), x * x])[1_000_000:1_000_002]


def test_an_array_beyond_what_export_writes_is_refused_naming_it():
    # export writes at most 1,000,000 elements per array; a larger operand was mis-indexed
    # (its element 1,000,000 read as the next operand's first) and written out silently
    import dscjax
    from dscjax import export
    from dscjax.config import paper_example
    from dscjax.plant import CustomPlant

    plant = CustomPlant(jnp.ones(2), jnp.array([0.1, 0.0]), jnp.array([0.08, 0.1]), {},
                        _f_huge, _rho, _delta, _dbar)
    setup = paper_example(dtype=np.float64).replace(plant=plant)
    with pytest.raises(export.ExportError, match=r"^controller: operand 1 of 'concatenate' "
                       r"\(test_export.py:\d+ \(_f_huge\)\) has 1000001 elements; export "
                       r"writes arrays of at most 1000000 elements$"):
        export.c_files(setup, dscjax.RunSpec.make(1.0, DT, sample_time=DT))
