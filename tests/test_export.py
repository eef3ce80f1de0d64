"""`dscjax export` (issue 33): the C controller, compiled by the system's C compiler and loaded
by ctypes, driven in closed loop with a plant written here (RK4 with u held, the hysteresis
jumped at each new input), equals dscjax's sampled simulation over 20 s."""

import ctypes
import dataclasses
import shutil
import subprocess

import jax
import jax.numpy as jnp
import numpy as np
import pytest

CC = shutil.which("cc") or shutil.which("gcc")
T_FINAL, DT = 20.0, 1e-3

needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler (cc or gcc) on PATH: the "
                              "exported controller cannot be compiled here")


def _load(setup, spec, directory):
    """The exported controller of (setup, spec), compiled into a shared library, and the
    number of reference values its dsc_step takes (y_r, y_r', ...)."""
    from dscjax import export

    files = export.c_files(setup, spec, source="a test")
    m = int(files[export.HEADER].split("#define DSC_REFERENCE_DERIVATIVES ")[1].split()[0]) + 1
    for name, text in files.items():
        (directory / name).write_text(text)
    lib_path = directory / "libdsc.so"
    subprocess.run([CC, "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic",
                    "-ffp-contract=off", "-shared", "-fPIC", "-o", str(lib_path),
                    str(directory / export.SOURCE), "-lm"], check=True)
    lib = ctypes.CDLL(str(lib_path))
    lib.dsc_state_size.restype = ctypes.c_size_t
    lib.dsc_sample_time.restype = ctypes.c_double
    lib.dsc_step.restype = ctypes.c_double
    more = [ctypes.POINTER(ctypes.c_double)] if m > 2 else []
    lib.dsc_step.argtypes = [ctypes.c_void_p, ctypes.c_double, ctypes.POINTER(ctypes.c_double),
                             ctypes.c_double, ctypes.c_double, *more]
    return lib, m


def _closed_loop(setup, lib, m, every, n_samples):
    """The C controller with the plant: at t_k = k Ts, u_k = dsc_step(x(t_k), y_r, y_r', ...
    (m reference values)), the
    actuator's hysteresis jumps from u_(k-1) to u_k, then `every` RK4 steps of the plant with
    w held. Returns (u_k (K,), x(t_k) (K, n))."""
    from dscjax.closed_loop import initial_state, prepared

    s = prepared(setup)
    plant, hyst, ref = s.plant, s.hysteresis, setup.reference  # the config's own reference

    @jax.jit
    def segment(x, h, u_from, u_to, k):
        h = hyst.jump(u_from, u_to, h)
        w = hyst.output(u_to, h)

        def rk4(j, x):
            t = (k * every + j).astype(x.dtype) * DT
            k1 = plant.rhs(x, w, t)
            k2 = plant.rhs(x + 0.5 * DT * k1, w, t + 0.5 * DT)
            k3 = plant.rhs(x + 0.5 * DT * k2, w, t + 0.5 * DT)
            k4 = plant.rhs(x + DT * k3, w, t + DT)
            return x + (k1 + 2.0 * (k2 + k3) + k4) * (DT / 6.0)

        x = jax.lax.fori_loop(0, every, rk4, x)
        t_next = ((k + 1) * every).astype(x.dtype) * DT
        return x, h, jnp.stack(ref.derivatives(t_next, m - 1))

    X0 = initial_state(s)
    u0, _ = s.controller.law(X0.ctrl, X0.x, 0.0, s.plant, s.reference)
    x, h, u_prev = X0.x, X0.h, float(u0)
    d = np.asarray(jnp.stack(ref.derivatives(jnp.zeros(()), m - 1)))
    state = ctypes.create_string_buffer(lib.dsc_state_size())
    lib.dsc_init(state)
    us, xs = np.empty(n_samples), np.empty((n_samples, setup.order))
    xbuf = (ctypes.c_double * setup.order)()
    higher = (ctypes.c_double * max(m - 2, 1))()
    for k in range(n_samples):
        xk = np.asarray(x)
        xs[k] = xk
        xbuf[:] = xk.tolist()
        higher[:m - 2] = d[2:].tolist()
        u = lib.dsc_step(state, k * every * DT, xbuf, float(d[0]), float(d[1]),
                         *([higher] if m > 2 else []))
        us[k] = u
        x, h, d = segment(x, h, u_prev, u, jnp.asarray(k))
        d = np.asarray(d)
        u_prev = u
    return us, xs


CASES = [  # (example, horizon, sample time in steps, delay, discretisation, controller.init)
    ("paper", T_FINAL, 1, 0, "exponential-euler", None),
    ("order-4", T_FINAL, 1, 0, "euler", None),
    ("pi", T_FINAL, 2, 1, "exponential-euler", None),
    # the law reads y_r'' too (a third reference argument); the L-inf initialisation's
    # reference offset (eq. 68) lives inside the controller
    ("backstepping", 2.0, 1, 0, "exponential-euler", None),
    ("paper", 2.0, 1, 0, "exponential-euler", "linf"),
]


@needs_cc
@pytest.mark.parametrize("example, t_final, every, delay, scheme, init", CASES)
def test_the_exported_controller_is_the_sampled_loop(tmp_path, example, t_final, every, delay,
                                                     scheme, init):
    import dscjax
    from dscjax.config import example as build

    setup = build(example, dtype=np.float64)
    if init is not None:
        setup = setup.replace(controller=dataclasses.replace(setup.controller, init=init))
    spec = dscjax.RunSpec.make(t_final, DT, save_every=1, sample_time=every * DT, delay=delay,
                               discretisation=scheme)
    lib, m = _load(setup, spec, tmp_path)
    assert lib.dsc_order() == setup.order and lib.dsc_sample_time() == every * DT
    assert m == (3 if example == "backstepping" else 2)
    traj = dscjax.simulate(setup, spec=spec)
    n_samples = int(round(t_final / (every * DT)))
    us, xs = _closed_loop(setup, lib, m, every, n_samples)
    u_want = np.asarray(traj.u)[:-1:every]
    x_want = np.asarray(traj.x)[:-1:every]
    assert np.max(np.abs(u_want)) > 0.1  # the loop does something
    # round-off only: libm's and XLA's exp, sin, ... may differ by an ulp
    np.testing.assert_allclose(us, u_want, rtol=1e-9, atol=1e-9 * np.max(np.abs(u_want)))
    np.testing.assert_allclose(xs, x_want, rtol=1e-9, atol=1e-9 * np.max(np.abs(x_want)))


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
    path.write_text(__import__("json").dumps(gains))
    out = tmp_path / "c"
    assert main(["export", "--gains", str(path), "--out", str(out)]) == 0
    header = (out / "dsc_controller.h").read_text()
    for text in ("Order n = 3", "Ts = 0.002 s", "input delay: 1 sample", "advance by euler",
                 "k = [7.25, 1.5, 0.75]", f"--gains {path}", "double yr, double yr_dot)"):
        assert text in header, text
    assert "double dsc_step(void *state, double t, const double *x, double yr, double " \
        "yr_dot)" in capsys.readouterr().out
    if CC is not None:  # a C99 compiler takes it without a warning
        subprocess.run([CC, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic",
                        "-fsyntax-only", str(out / "dsc_controller.c")], check=True)



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
    from dscjax.config import example

    setup = example("order-3", dtype=np.float64)
    return setup.replace(controller=dataclasses.replace(
        setup.controller, init="linf", robust_term="sgn", variant="no_dhat_no_zeta"))


@needs_cc
@pytest.mark.parametrize("build, delay, scheme", [(_custom_plant_setup, 0, "euler"),
                                                  (_order3_linf_setup, 2, "exponential-euler")])
def test_one_sample_of_the_c_equals_the_sample_update(tmp_path, build, delay, scheme):
    """One sample of the C, at random states and times, against `closed_loop.sample_update`:
    u and every state (the leaves in order, then the delay line). A user's plant functions
    with dot_general, transpose and reductions and the smooth robust term; the L-inf
    initialisation's time-dependent reference offset, sgn, no adaptation of zeta."""
    import dscjax
    from dscjax.closed_loop import SampledState, Sampling, initial_state, prepared, sample_update

    setup = build()
    spec = dscjax.RunSpec.make(1.0, DT, sample_time=2 * DT, delay=delay, discretisation=scheme)
    lib, _ = _load(setup, spec, tmp_path)
    s = prepared(setup)
    X0 = initial_state(s)
    n = setup.order
    rng = np.random.default_rng(0)
    for k in range(4):
        ctrl = jax.tree.map(lambda a: a + 0.1 * rng.standard_normal(np.shape(a)), X0.ctrl)
        past = rng.standard_normal(delay)
        x, t = X0.x + 0.5 * rng.standard_normal(n), 0.37 * k
        new = sample_update(jnp.asarray(k), t, SampledState(x=x, h=X0.h, ctrl=ctrl, u=0.0,
                                                            past=jnp.asarray(past)),
                            s, Sampling(every=2.0, delay=delay, scheme=scheme), DT)
        flat = np.concatenate([np.ravel(a) for a in jax.tree.leaves(ctrl)] + [past])
        assert lib.dsc_state_size() == 8 * flat.size  # the state is the leaves, in order
        buf = (ctypes.c_double * flat.size)(*flat.tolist())
        yr, yr_dot = (float(v) for v in setup.reference.derivatives(jnp.asarray(t), 1))
        u = lib.dsc_step(buf, t, (ctypes.c_double * n)(*np.asarray(x).tolist()), yr, yr_dot)
        want = np.concatenate([np.ravel(a) for a in jax.tree.leaves(new.ctrl)]
                              + [np.asarray(new.past)])
        np.testing.assert_allclose(u, float(new.u), rtol=1e-13)
        np.testing.assert_allclose(np.asarray(buf[:]), want, rtol=1e-13, atol=1e-15)


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
