"""RK4 driver: order of convergence, save stride, divergence status, checkpointing."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from compilations import lean

from dscjax.integrate import (
    SOLVERS,
    STATUS_OK,
    Checkpointed,
    TimeParallel,
    integrate,
    rk4_step,
    rk4_steps,
    saved_steps,
)


def _oscillator(t, y, args):
    """y = (p, q): p' = q, q' = -w^2 p + sin(t); obs = energy-like scalar."""
    w = args
    dy = {"p": y["q"], "q": -w * w * y["p"] + jnp.sin(t)}
    return dy, y["p"] * y["p"]


def _exact(t, w):
    # p'' + w^2 p = sin t, p(0) = 1, p'(0) = 0  (w != 1)
    a = 1.0 / (w * w - 1.0)
    p = np.cos(w * t) + a * (np.sin(t) - np.sin(w * t) / w)
    q = -w * np.sin(w * t) + a * (np.cos(t) - np.cos(w * t))
    return p, q


def _run(dt, t_final=2.0, w=3.0, save_every=1):
    n = int(round(t_final / dt))
    y0 = {"p": jnp.array(1.0), "q": jnp.array(0.0)}
    return integrate(_oscillator, y0, dt, n, jnp.array(w), save_every=save_every)


def test_rk4_fourth_order_on_known_solution():
    dts = np.array([0.04, 0.02, 0.01, 0.005])
    errs = []
    for dt in dts:
        res = _run(dt)
        p_end = float(res.ys["p"][-1])
        errs.append(abs(p_end - _exact(2.0, 3.0)[0]))
    order = np.polyfit(np.log(dts), np.log(errs), 1)[0]
    assert 3.7 < order < 4.3, (order, errs)


def test_rk4_step_matches_exponential():
    y1 = rk4_step(lambda t, y, a: -a * y, 0.0, jnp.array(1.0), 0.1, 2.0)
    # local error of RK4 on y' = -2y is (0.2)^5/120 ~ 2.7e-6
    assert abs(float(y1) - np.exp(-0.2)) < 3e-6


def test_rk4_steps_are_the_amplification_factor_to_the_nth_and_end_at_each_step():
    # on y' = -a y every RK4 step multiplies y by R(z) = 1 + z + z^2/2 + z^3/6 + z^4/24,
    # z = -a dt, so n steps give R(z)^n; `after` sees each step's end time t0 + k dt
    a, dt, n = 2.0, 0.1, 7
    z = -a * dt
    r = 1 + z + z * z / 2 + z**3 / 6 + z**4 / 24
    y = rk4_steps(lambda t, y, a_: -a_ * y, 0.5, jnp.array(1.0), dt, n, a)
    assert abs(float(y) - r**n) < 1e-15
    ends = rk4_steps(lambda t, y, _: jnp.zeros_like(y), 0.5, jnp.array(0.0), dt, n, None,
                     after=lambda t, y: y + t)
    assert abs(float(ends) - sum(0.5 + k * dt for k in range(1, n + 1))) < 1e-12


def test_save_stride_and_times():
    full = _run(0.01, save_every=1)
    strided = _run(0.01, save_every=20)
    assert full.ys["p"].shape == (201,)
    assert strided.ys["p"].shape == (11,)
    np.testing.assert_array_equal(np.asarray(full.ys["p"])[::20], np.asarray(strided.ys["p"]))
    np.testing.assert_array_equal(np.asarray(full.obs)[::20], np.asarray(strided.obs))
    p_exact, _ = _exact(np.arange(11) * 0.2, 3.0)
    np.testing.assert_allclose(np.asarray(strided.ys["p"]), p_exact, atol=1e-6)


def test_a_stride_that_does_not_divide_the_steps_keeps_every_s_th_step_and_the_last():
    # 197 steps (a prime) saved every 20: k = 0, 20, ..., 180 and 197 (t = T); the single
    # forward run, the time-parallel jvp's outputs and the batched rows layout agree
    n, dt, s = 197, 0.01, 20
    y0 = {"p": jnp.array(1.0), "q": jnp.array(0.0)}
    full = integrate(_oscillator, y0, dt, n, jnp.array(3.0))
    k = saved_steps(n, s)
    np.testing.assert_array_equal(k, [*range(0, 197, 20), 197])
    strided = integrate(_oscillator, y0, dt, n, jnp.array(3.0), save_every=s)
    np.testing.assert_array_equal(np.asarray(full.ys["p"])[k], np.asarray(strided.ys["p"]))
    np.testing.assert_array_equal(np.asarray(full.obs)[k], np.asarray(strided.obs))
    primal, _ = jax.jvp(lambda w: integrate(_oscillator, y0, dt, n, w, save_every=s).ys["p"],
                        (jnp.array(3.0),), (jnp.array(1.0),))
    np.testing.assert_allclose(np.asarray(primal), np.asarray(strided.ys["p"]), rtol=1e-14)

    def f(t, y, args):  # with a batch: (shared args, the member's w)
        return _oscillator(t, y, args[1])

    for checkpoint_every in (None, 7):
        batch = integrate(f, {"p": jnp.array([1.0, 0.5]), "q": jnp.zeros(2)}, dt, n, (),
                          batch=jnp.array([3.0, 2.0]), save_every=s,
                          gradient=TimeParallel(every=checkpoint_every))
        assert batch.ys["p"].shape == (2, k.size)
        np.testing.assert_allclose(np.asarray(batch.ys["p"][0]), np.asarray(strided.ys["p"]),
                                   rtol=1e-13)
        np.testing.assert_allclose(np.asarray(batch.obs[0]), np.asarray(strided.obs),
                                   rtol=1e-13)


def test_gradient_through_a_stride_that_does_not_divide_the_steps():
    def loss(w, time_parallel):
        res = integrate(_oscillator, {"p": jnp.array(1.0), "q": jnp.array(0.0)}, 0.005, 397, w,
                        save_every=10, gradient=TimeParallel() if time_parallel else Checkpointed())
        return jnp.sum(res.ys["p"] ** 2) + jnp.sum(res.obs)

    grad, value = lean(jax.grad(loss), static_argnums=1), lean(loss, static_argnums=1)
    g_tp = grad(jnp.array(3.0), True)
    assert float(g_tp) == pytest.approx(float(grad(jnp.array(3.0), False)), rel=1e-12)
    h = 1e-6
    fd = (value(jnp.array(3.0 + h), True) - value(jnp.array(3.0 - h), True)) / (2 * h)
    assert float(g_tp) == pytest.approx(float(fd), rel=1e-6)

    def batch_loss(ws, checkpoint_every):
        def f(t, y, args):
            return _oscillator(t, y, args[1])

        res = integrate(f, {"p": jnp.ones(2), "q": jnp.zeros(2)}, 0.005, 397, (), batch=ws,
                        save_every=10, gradient=TimeParallel(every=checkpoint_every))
        return jnp.sum(res.ys["p"] ** 2)

    ws = jnp.array([2.0, 3.0])
    batch_grad = lean(jax.grad(batch_loss), static_argnums=1)
    np.testing.assert_allclose(np.asarray(batch_grad(ws, 4)), np.asarray(batch_grad(ws, None)),
                               rtol=1e-13)


class _Count:
    """A reduction that counts the samples it sees."""

    def init(self, dtype):
        return jnp.zeros((), dtype)

    def update(self, acc, k, t, y, obs, dt):
        return acc + 1.0

    def finalize(self, acc, t_final):
        return {"count": acc}


jax.tree_util.register_pytree_node(_Count, lambda r: ((), None), lambda _, __: _Count())


def test_running_accumulator_sees_every_step():
    res = integrate(_oscillator, {"p": jnp.array(1.0), "q": jnp.array(0.0)}, 0.01, 100,
                    jnp.array(3.0), save_every=50, reduction=_Count())
    assert float(res.acc) == 101.0  # k = 0..N


def _blowup(t, y, args):
    return y * y, y  # y' = y^2, y(0) = 1: y = 1/(1 - t), blows up at t = 1


@pytest.mark.parametrize("bound,code", [(1e3, 2), (np.inf, 1)])
def test_divergence_is_reported_not_returned_as_nan(bound, code):
    res = integrate(_blowup, jnp.array(1.0), 1e-3, 2000, (), state_bound=bound)
    assert int(res.status.code) == code
    t_bad = int(res.status.step) * 1e-3
    # y = 1/(1-t) passes 1e3 at t = 0.999; RK4 goes non-finite a little after t = 1
    assert 0.99 < t_bad < 1.2, t_bad
    assert np.all(np.isfinite(np.asarray(res.ys)))
    assert np.all(np.isfinite(np.asarray(res.obs)))


def test_a_run_that_skips_once_diverged_gives_the_same_numbers_for_fewer_evaluations():
    # y' = y^2 from 1 leaves the bound 1e3 at t = 0.999 (dt = 1e-3), in the fourth part of
    # 256 steps; the last four parts (steps 1024..2047) are not stepped. Saved every 4th step
    # (a part is 64 blocks) f is evaluated once a block (4 x 64), saved at the end alone (one
    # block of 8 parts) once a part (4), instead of four times a step (RK4's stages, 4 x 1024).
    # Every output is the same (the observation y + t reads the time), for one run and for a
    # batch that diverges.
    calls = []

    def blowup(t, y, args):
        return y * y, y + t

    def f(t, y, args):
        jax.debug.callback(lambda: calls.append(1))
        return blowup(t, y, args)

    def run(skip, every, y0=1.0, batch=None):
        calls.clear()
        res = jax.block_until_ready(integrate(
            f if batch is None else blowup, jnp.asarray(y0), 1e-3, 2048, (), batch=batch,
            save_every=every, state_bound=1e3, reduction=_Count(), skip_diverged=skip))
        return res, len(calls)

    two = ([1.0, 2.0], jnp.zeros(2))
    for every, observed in ((4, 4 * 64), (2048, 4)):
        (full, n_full), (skipped, n_skipped) = run(False, every), run(True, every)
        assert int(full.status.code) == 2 and 999 <= int(full.status.step) < 1024
        assert (n_full, n_skipped) == (4 * 2048 + 1, 4 * 1024 + observed + 1)
        for a, b in ((full, skipped), (run(False, every, *two)[0], run(True, every, *two)[0])):
            for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
                np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_healthy_run_has_ok_status():
    res = _run(0.01)
    assert int(res.status.code) == STATUS_OK and int(res.status.step) == -1


def test_time_parallel_gradient_equals_autodiff_and_finite_differences():
    def loss(w, time_parallel):
        res = integrate(_oscillator, {"p": jnp.array(1.0), "q": jnp.array(0.0)}, 0.005, 400, w,
                        save_every=10, gradient=TimeParallel() if time_parallel else Checkpointed())
        return jnp.sum(res.ys["p"] ** 2) + jnp.sum(res.obs)

    grad, value = lean(jax.grad(loss), static_argnums=1), lean(loss, static_argnums=1)
    g_tp = grad(jnp.array(3.0), True)
    g_ad = grad(jnp.array(3.0), False)
    assert float(g_tp) == pytest.approx(float(g_ad), rel=1e-12)
    tangent = lean(jax.jacfwd(loss), static_argnums=1)(jnp.array(3.0), True)
    assert float(tangent) == pytest.approx(float(g_ad), rel=1e-12)
    # and both equal central finite differences of the same discrete map
    h = 1e-6
    fd = (value(jnp.array(3.0 + h), True) - value(jnp.array(3.0 - h), True)) / (2 * h)
    assert float(g_tp) == pytest.approx(float(fd), rel=1e-6)


def test_checkpointed_batch_gradient_equals_plain():
    def loss(ws, ck):
        def f(t, y, args):
            return _oscillator(t, y, args[1])

        y0 = {"p": jnp.ones(2), "q": jnp.zeros(2)}
        res = integrate(f, y0, 0.005, 400, (), batch=ws, save_every=400,
                        gradient=TimeParallel(every=ck))
        return jnp.sum(res.ys["p"] ** 2)

    ws = jnp.array([2.0, 3.0])
    grad = lean(jax.grad(loss), static_argnums=1)
    g_plain, g_ckpt = grad(ws, None), grad(ws, 100)
    np.testing.assert_allclose(np.asarray(g_ckpt), np.asarray(g_plain), rtol=1e-13)


def test_batched_layout_equals_single_runs():
    y0 = {"p": jnp.array([1.0, 0.5, -0.2]), "q": jnp.zeros(3)}
    ws = jnp.array([2.0, 3.0, 4.0])

    def f(t, y, args):  # with a batch: (shared args, the member's w)
        return _oscillator(t, y, args[1])

    batched = integrate(f, y0, 0.01, 100, (), batch=ws, save_every=10)
    for i in range(3):
        single = integrate(_oscillator, {"p": y0["p"][i], "q": y0["q"][i]}, 0.01, 100, ws[i],
                           save_every=10)
        np.testing.assert_allclose(np.asarray(batched.ys["p"][i]), np.asarray(single.ys["p"]),
                                   rtol=0, atol=1e-14)


# -- components held inside a step (`frozen`), updated by `project` only ------------------------

R = np.array([0.05, 0.3])


def _held_field(t, y, args):
    """x' = -a x + sin(3t) + 0.5 sum(z); z's rate is deliberately nonzero: held, it is unused."""
    a = args
    dx = -a * y["x"] + jnp.sin(3.0 * t) + 0.5 * jnp.sum(y["z"])
    return {"x": dx, "z": jnp.full_like(y["z"], 100.0)}, y["x"]


def _held_project(k, t, y, args):
    return {"x": y["x"], "z": jnp.maximum(y["x"] - R, jnp.minimum(y["x"] + R, y["z"]))}


def _held_reference(x0, z0, a, dt, n):
    """RK4 of x with z constant over each step, then the play recursion z <- clamp(x), in NumPy."""
    x, z, xs, zs = float(x0), np.array(z0, float), [], []
    for k in range(n):
        xs.append(x)
        zs.append(z.copy())
        t, held = k * dt, z.sum()

        def g(tt, xx, held=held):
            return -a * xx + np.sin(3.0 * tt) + 0.5 * held

        k1 = g(t, x)
        k2 = g(t + dt / 2, x + dt / 2 * k1)
        k3 = g(t + dt / 2, x + dt / 2 * k2)
        k4 = g(t + dt, x + dt * k3)
        x = x + dt / 6 * (k1 + 2 * (k2 + k3) + k4)
        z = np.maximum(x - R, np.minimum(x + R, z))
    xs.append(x)
    zs.append(z.copy())
    return np.array(xs), np.array(zs)


def _held_run(x0, z0, a, solver="rk4", **kw):
    def rates(t, y, args, obs):  # a decay for x; z's is ignored like its rate
        return {"x": args * jnp.ones_like(y["x"]), "z": jnp.full_like(y["z"], 7.0)}

    y0 = {"x": jnp.asarray(x0), "z": jnp.asarray(z0)}
    return integrate(_held_field, y0, 0.01, 300, jnp.asarray(a), project=_held_project,
                     frozen={"x": False, "z": True}, rates=rates, solver=SOLVERS[solver](),
                     **kw)


def test_held_components_follow_the_reference_recursion():
    """Held components ignore their rate in every stage; the rest is RK4 with them constant;
    the update after each step is the play recursion, in the single and the batched layout."""
    x_ref, z_ref = _held_reference(0.2, [0.0, 0.5], 0.7, 0.01, 300)
    single = _held_run(0.2, [0.0, 0.5], 0.7)
    np.testing.assert_allclose(np.asarray(single.ys["x"]), x_ref, rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(single.ys["z"]), z_ref, rtol=0, atol=1e-14)

    def f(t, y, args):
        return _held_field(t, y, args[1])

    def proj(k, t, y, args):
        return _held_project(k, t, y, args[1])

    y0 = {"x": jnp.array([0.2, -0.4]), "z": jnp.array([[0.0, 0.5], [0.1, -0.2]])}
    batched = integrate(f, y0, 0.01, 300, (), batch=jnp.array([0.7, 1.3]), project=proj,
                        frozen={"x": False, "z": True})
    for i, (x0, z0, a) in enumerate([(0.2, [0.0, 0.5], 0.7), (-0.4, [0.1, -0.2], 1.3)]):
        x_ref, z_ref = _held_reference(x0, z0, a, 0.01, 300)
        np.testing.assert_allclose(np.asarray(batched.ys["x"][i]), x_ref, rtol=0, atol=1e-14)
        np.testing.assert_allclose(np.asarray(batched.ys["z"][i]), z_ref, rtol=0, atol=1e-14)


def test_held_components_under_the_exponential_step_and_gradients():
    """ETDRK4: the held z is the recursion of the x it produced (to the rounding of x, not to
    the solver's error), whatever its rate; the time-parallel derivative through held
    components equals JAX's own."""
    res = _held_run(0.2, [0.0, 0.5], 0.7, solver="etdrk4")
    x, z = np.asarray(res.ys["x"]), np.asarray(res.ys["z"])
    np.testing.assert_allclose(z[1:], np.maximum(x[1:, None] - R,
                                                 np.minimum(x[1:, None] + R, z[:-1])),
                               rtol=0, atol=1e-15)
    x_ref, _ = _held_reference(0.2, [0.0, 0.5], 0.7, 0.01, 300)
    assert np.max(np.abs(x - x_ref)) < 1e-8  # both fourth order, same held z

    for solver in ("rk4", "etdrk4"):
        def loss(a, time_parallel, solver=solver):
            grad = TimeParallel() if time_parallel else Checkpointed()
            return jnp.sum(_held_run(0.2, [0.0, 0.5], a, solver, gradient=grad).ys["x"] ** 2)

        grad = lean(jax.grad(loss), static_argnums=1)
        g_tp, g_ad = grad(0.7, True), grad(0.7, False)
        np.testing.assert_allclose(float(g_tp), float(g_ad), rtol=1e-12, err_msg=solver)
        assert float(g_tp) != 0.0


def test_holding_a_component_of_zero_rate_changes_no_bit():
    """Holding a component whose rate is exactly 0 changes nothing: RK4 leaves it unchanged
    in every stage anyway, so the held run (which goes through the select of a packed chunk
    that mixes held and live elements) equals the plain one bitwise."""
    def f(t, y, a):
        return {"p": -a * y["p"] + jnp.sin(t) * y["q"], "q": 0.0 * y["q"]}, y["p"]

    y0 = {"p": jnp.array(1.0), "q": jnp.array(0.3)}
    plain = integrate(f, y0, 0.01, 200, jnp.array(3.0))
    held = integrate(f, y0, 0.01, 200, jnp.array(3.0), frozen={"p": False, "q": True})
    for k in ("p", "q"):
        np.testing.assert_array_equal(np.asarray(plain.ys[k]), np.asarray(held.ys[k]))
    assert float(plain.ys["p"][-1]) != float(y0["p"])
