"""The digital controller (issue 27): a held input moves each hysteresis model along its own
curve (`Hysteresis.jump`), checked against closed forms written here from the models' equations."""

import dataclasses
import math

import numpy as np
import pytest
from commands import exit_code
from compilations import lean

from dscjax.hysteresis import Backlash, BoucWen, GeneralizedPI, PrandtlIshlinskii

STEPS = [(0.0, 2.0, 0.3), (1.5, -2.0, 0.1), (-0.4, -0.1, -0.6), (0.7, 0.7, 0.2)]


@pytest.mark.parametrize("u_from, u_to, w", STEPS)
def test_backlash_jump_is_the_closed_form_of_dw_du(u_from, u_to, w):
    a, lam, psi = 1.3, 1.432, 0.105
    got = float(Backlash(alpha=a, lam=lam, psi=psi).jump(u_from, u_to, w))
    # dw/du = s a (lam u - w) + psi, s = sgn(u_to - u_from), solved by hand:
    # w = lam u - s (lam - psi)/a + C e^(-s a u)
    s = 1.0 if u_to >= u_from else -1.0
    c = (w - lam * u_from + s * (lam - psi) / a) * math.exp(s * a * u_from)
    want = lam * u_to - s * (lam - psi) / a + c * math.exp(-s * a * u_to)
    assert got == pytest.approx(want, rel=1e-13, abs=1e-14)


def test_plays_jump_to_the_clamp_at_the_new_input():
    r, p, z = np.array([0.0, 0.3, 0.8]), np.array([0.5, 0.2, 0.4]), np.array([0.1, -0.5, 0.6])
    pi = PrandtlIshlinskii(p0=0.3, r=r, p=p)
    for u_to in (-1.0, 0.05, 0.4, 2.0):
        np.testing.assert_allclose(pi.jump(0.2, u_to, z), np.clip(z, u_to - r, u_to + r),
                                   rtol=0, atol=0)
    el, er = np.array([3.0, 0.4, -0.1, 0.05]), np.array([2.5, 0.5, 0.2, -0.1])
    gpi = GeneralizedPI(envelope_left=el, envelope_right=er, p0=0.3, r=r, p=p)
    for u_to in (-1.0, 0.4, 2.0):
        lo = el[0] * np.tanh(el[1] * u_to + el[2]) + el[3] - r
        hi = er[0] * np.tanh(er[1] * u_to + er[2]) + er[3] + r
        np.testing.assert_allclose(gpi.jump(0.2, u_to, z), np.maximum(lo, np.minimum(hi, z)),
                                   rtol=1e-15, atol=1e-15)


@pytest.mark.parametrize("u_from, u_to, h, rel", [(0.0, 0.05, 0.3, 1e-14), (0.5, 0.3, 0.9, 1e-10),
                                                  (0.0, 2.0, 0.3, 1e-6)])
def test_bouc_wen_jump_is_the_closed_form_for_n_1(u_from, u_to, h, rel):
    A, beta, gamma = 1.0, 0.6, 0.15
    got = float(BoucWen(A=A, beta=beta, gamma=gamma, n=1.0).jump(u_from, u_to, h))
    # n = 1, h > 0 along the step: dh/du = A - (beta s + gamma) h
    s = 1.0 if u_to >= u_from else -1.0
    k = beta * s + gamma
    want = A / k + (h - A / k) * math.exp(-k * (u_to - u_from))
    assert want > 0
    # RK4 in u over JUMP_SUBSTEPS substeps: round-off for the steps of a sampled input
    # (|du| well below 1), O(du^4) for a step across the whole loop
    assert got == pytest.approx(want, rel=rel)


# -- the sampled loop against an independent per-sample implementation -------------------------

T_SHORT = 2.0


@pytest.mark.parametrize("every, delay", [(1, 0), (5, 0), (2, 2)])
def test_the_sampled_loop_equals_a_hand_written_per_sample_loop(paper_setup, every, delay):
    import reference_paper as ref

    import dscjax

    n = int(T_SHORT / 1e-3)
    want, u_want = ref.sampled_rk4(ref.initial_state(), 1e-3, n, every, delay=delay)
    spec = dscjax.RunSpec.make(T_SHORT, 1e-3, save_every=1, sample_time=every * 1e-3,
                               delay=delay)
    if delay:  # a delay line one longer than the delay: the next delay runs on it below
        spec = dataclasses.replace(spec, line=delay + 1)
    traj = dscjax.simulate(paper_setup, spec=spec)
    # round-off of 2,000 steps of arithmetic done in another order: |x|, |u| ~ 1
    np.testing.assert_allclose(np.asarray(traj.x), want[:, :2], rtol=0, atol=1e-11)
    np.testing.assert_allclose(np.asarray(traj.w), want[:, 2], rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(traj.u), u_want, rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(traj.z)[:, 0], want[:, 3], rtol=0, atol=1e-9)
    batch = dscjax.simulate_batch(paper_setup, {"hysteresis.alpha": np.array([0.8, 1.0])},
                                  spec=spec)
    np.testing.assert_allclose(np.asarray(batch.x[1]), want[:, :2], rtol=0, atol=1e-11)
    if delay:  # one sample later, on the same line: the same compiled program, its own input
        from dscjax.simulate import _simulate

        before = _simulate.top._cache_size()
        _, u_late = ref.sampled_rk4(ref.initial_state(), 1e-3, n, every, delay=delay + 1)
        late = dscjax.simulate(paper_setup, spec=spec.replace(delay=delay + 1))
        np.testing.assert_allclose(np.asarray(late.u), u_late, rtol=0, atol=1e-10)
        assert _simulate.top._cache_size() == before


def test_a_delay_longer_than_its_delay_line_is_refused():
    """A spec's delay line is as long as its delay; a delay beyond its line, which indexing
    would clamp silently, or not a whole number of samples, is refused where it is set."""
    import dscjax
    from dscjax.closed_loop import Sampling

    spec = dscjax.RunSpec.make(1.0, 1e-3, sample_time=1e-3)
    assert (spec.line, spec.replace(delay=3).line) == (0, 3)
    must = r"\.delay must be an integer in \[0, {}\] \(got {}\)$"
    with pytest.raises(ValueError, match="^RunSpec" + must.format(0, 2)):
        dataclasses.replace(spec, delay=2)
    with pytest.raises(ValueError, match="^Sampling" + must.format(1, r"1\.0")):
        Sampling(every=1.0, delay=1.0, line=1)  # within its line, but a float


@pytest.mark.parametrize("every, delay", [(5, 0), (2, 1)])
def test_the_forward_euler_sampled_loop_equals_a_hand_written_one(paper_setup, every, delay):
    import reference_paper as ref

    import dscjax

    n = int(T_SHORT / 1e-3)
    want, u_want = ref.sampled_rk4(ref.initial_state(), 1e-3, n, every, delay=delay,
                                   scheme="euler")
    spec = dscjax.RunSpec.make(T_SHORT, 1e-3, save_every=1, sample_time=every * 1e-3,
                               delay=delay, discretisation="euler")
    traj = dscjax.simulate(paper_setup, spec=spec)
    np.testing.assert_allclose(np.asarray(traj.x), want[:, :2], rtol=0, atol=1e-11)
    np.testing.assert_allclose(np.asarray(traj.u), u_want, rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(traj.z)[:, 0], want[:, 3], rtol=0, atol=1e-9)
    # the two schemes differ in the filter (tau = 0.05 s, Ts = 5 ms: visibly)
    expo, _ = ref.sampled_rk4(ref.initial_state(), 1e-3, n, every, delay=delay)
    assert np.max(np.abs(expo[:, 3] - want[:, 3])) > 1e-6


def test_the_default_discretisation_is_the_loop_without_the_option(paper_setup):
    import dscjax

    base = dict(save_every=1, sample_time=5e-3)  # the program of a test above
    plain = dscjax.simulate(paper_setup, spec=dscjax.RunSpec.make(T_SHORT, 1e-3, **base))
    named = dscjax.simulate(paper_setup, spec=dscjax.RunSpec.make(
        T_SHORT, 1e-3, discretisation="exponential-euler", **base))
    np.testing.assert_array_equal(np.asarray(named.x), np.asarray(plain.x))
    np.testing.assert_array_equal(np.asarray(named.u), np.asarray(plain.u))
    assert "discretisation" not in dscjax.RunSpec.make(T_SHORT, 1e-3, **base).describe()


def test_the_sampled_output_tends_to_the_continuous_one_at_first_order(paper_setup):
    import dscjax

    dt, t_final = 1e-4, 2.0
    cont = dscjax.simulate(paper_setup, t_final, dt, save_every=10)
    window = np.asarray(cont.t) >= 1.0  # after the initial transient, whose fast modes
    errors, steps = [], (32, 16, 8, 4, 2)  # are not resolved by the coarser samples
    for every in steps:
        s = dscjax.simulate(paper_setup, spec=dscjax.RunSpec.make(
            t_final, dt, save_every=10, sample_time=every * dt))
        y, y_cont = np.asarray(s.x)[:, 0], np.asarray(cont.x)[:, 0]
        errors.append(float(np.max(np.abs(y - y_cont)[window])))
    order = np.polyfit(np.log(np.asarray(steps) * dt), np.log(errors), 1)[0]
    # a zero-order hold and one exponential-Euler step per sample: first order in Ts
    assert abs(order - 1.0) < 0.1, (order, errors)


def test_the_sampled_loop_has_an_exact_gradient(paper_setup):
    import jax

    import dscjax

    spec = dscjax.RunSpec.make(1.0, 1e-3, save_every=100, sample_time=2e-3, refine=0)

    def l2(k):
        s = dscjax.params.set(paper_setup, "controller.k", k)
        return dscjax.simulate(s, spec=spec, throw=False).metrics["l2_error"]

    k0 = np.asarray(paper_setup.controller.k)
    g = np.asarray(lean(jax.grad(l2))(k0))
    h = 1e-6
    fd = [(float(l2(k0 + h * e)) - float(l2(k0 - h * e))) / (2 * h) for e in np.eye(2)]
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_measurement_noise_is_seeded(paper_setup):
    import dscjax

    def run(**kw):
        return np.asarray(dscjax.simulate(paper_setup, spec=dscjax.RunSpec.make(
            0.5, 1e-3, sample_time=1e-3, **kw)).u)

    quiet = run()
    np.testing.assert_array_equal(run(noise=0.0), quiet)  # std 0: the noiseless loop, exactly
    a, b, c = run(noise=1e-3, noise_seed=1), run(noise=1e-3, noise_seed=1), run(
        noise=1e-3, noise_seed=2)
    np.testing.assert_array_equal(a, b)
    assert np.max(np.abs(a - c)) > 1e-4 and np.max(np.abs(a - quiet)) > 1e-4


def test_noise_of_the_wrong_length_is_one_config_error_before_any_run(paper_setup):
    import dscjax
    from dscjax.validation import ConfigError

    spec = dscjax.RunSpec.make(0.5, 1e-3, sample_time=1e-3, noise=[1e-3, 1e-3, 1e-3])
    with pytest.raises(ConfigError, match=r"^simulation.noise must be one number or one per "
                       r"state of the plant, 2 numbers \(got 3\)$"):
        dscjax.simulate(paper_setup, spec=spec)


@pytest.mark.parametrize("argv, line", [
    (["--sample-time", "0.0015"], "--sample-time must be a whole multiple > 0 of simulation.dt "
                                  "(got sample_time=0.0015, dt=0.001, ratio 1.5)"),
    (["--sample-time", "0"], "argument --sample-time: must be a finite number > 0, or "
                             "\"none\" (got '0')"),
    (["--sample-time=-1e-3"], "argument --sample-time: must be a finite number > 0, or "
                              "\"none\" (got '-1e-3')"),
    (["--sample-time", "5", "--t-final", "2"], "--sample-time must be <= --t-final = 2 "
                                               "(got 5)"),
    (["--delay", "2"], "--delay applies to a sampled controller: give simulation.sample_time "
                       "too"),
    (["--discretisation", "rk4"], "argument --discretisation: must be one of "
                                  "'exponential-euler', 'euler' (got 'rk4')"),
])
def test_bad_sample_times_are_one_line_and_exit_2(tmp_path, capsys, argv, line):
    out = tmp_path / "o"
    assert exit_code(["simulate", *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and line in err[0], err
    assert not out.exists()
