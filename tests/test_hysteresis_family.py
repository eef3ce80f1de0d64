"""Prandtl-Ishlinskii, generalized P-I and Bouc-Wen (issue 15) against independent references.

Short horizons and one compiled program per model (vmapped over amplitudes) keep this fast.
"""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

import dscjax
from dscjax import config, params
from dscjax.cli.main import main
from dscjax.config import example
from dscjax.hysteresis import BoucWen, GeneralizedPI, PrandtlIshlinskii, open_loop, sine_loops
from dscjax.validation import ConfigError, validate_setup

DT = 1e-3


def play_recursion(u, lo, hi, z0):
    """The play operator z_k = max(lo_k, min(hi_k, z_(k-1))) over samples, in NumPy."""
    z, out = np.asarray(z0, float), []
    for k in range(len(u)):
        z = np.maximum(lo[k], np.minimum(hi[k], z))
        out.append(z)
    return np.array(out)


# A monotone-piecewise input whose knots lie on the step grid: there the sampled recursion is
# the continuous operator, so the model must match it to round-off.
KNOTS_T = np.array([0.0, 0.3, 0.5, 0.9, 1.0, 1.4, 1.5])
KNOTS_U = np.array([0.0, 2.0, 0.7, 2.6, 1.9, -1.2, -0.4])


def knot_input(t):
    import jax.numpy as jnp

    return jnp.interp(t, jnp.asarray(KNOTS_T), jnp.asarray(KNOTS_U))


@pytest.mark.parametrize("model", [
    PrandtlIshlinskii(p0=0.3, r=np.array([0.0, 0.25, 0.6, 1.1]),
                      p=np.array([0.2, 0.5, 0.3, 0.8]), z0=np.array([0.1, -0.4, 0.9, 0.0])),
    GeneralizedPI(envelope_left=np.array([3.0, 0.4, -0.1, 0.05]),
                  envelope_right=np.array([2.5, 0.5, 0.2, -0.1]), p0=0.3,
                  r=np.array([0.1, 0.4, 0.9]), p=np.array([0.5, 0.3, 0.8]), z0=0.2),
], ids=["pi", "gpi"])
def test_plays_equal_the_recursion_on_a_monotone_piecewise_input(model):
    t, u, w = open_loop(model, knot_input, KNOTS_T[-1], DT)
    u_np = np.interp(t, KNOTS_T, KNOTS_U)
    r = np.asarray(model.r)
    if model.kind == "pi":
        lo, hi = u_np[:, None] - r, u_np[:, None] + r
    else:
        def g(e, x):
            return e[0] * np.tanh(e[1] * x + e[2]) + e[3]
        lo = g(np.asarray(model.envelope_left), u_np[:, None]) - r
        hi = g(np.asarray(model.envelope_right), u_np[:, None]) + r
    z = play_recursion(u_np, lo, hi, np.broadcast_to(model.z0, r.shape))
    w_ref = float(model.p0) * u_np + z @ np.asarray(model.p)
    np.testing.assert_allclose(u, u_np, atol=1e-12)
    np.testing.assert_allclose(w, w_ref, atol=1e-12)


def test_one_play_with_zero_threshold_is_linear():
    model = PrandtlIshlinskii(p0=0.4, r=np.array([0.0]), p=np.array([1.1]))
    _, u, w = open_loop(model, knot_input, KNOTS_T[-1], DT)
    np.testing.assert_allclose(w, 1.5 * u, atol=1e-13)


def bouc_wen_reference(m, amplitude, omega, t):
    """scipy DOP853 at 1e-12, restarted at every reversal of u (|u'| has a kink there)."""
    a, b, A, beta, gamma, n = (float(x) for x in (m.a, m.b, m.A, m.beta, m.gamma, m.n))

    def rhs(tt, y):
        du = amplitude * omega * np.cos(omega * tt)
        h = y[0]
        return [A * du - beta * abs(du) * abs(h) ** (n - 1) * h - gamma * du * abs(h) ** n]

    rev = (np.pi / 2 + np.pi * np.arange(10)) / omega
    edges = np.concatenate([[0.0], rev[rev < t[-1]], [t[-1]]])
    h, out = float(m.h0), np.empty_like(t)
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        sel = (t >= lo) & (t <= hi)
        sol = solve_ivp(rhs, (lo, hi), [h], method="DOP853", rtol=1e-12, atol=1e-12,
                        dense_output=True)
        out[sel], h = sol.sol(t[sel])[0], sol.y[0, -1]
    return a * amplitude * np.sin(omega * t) + b * out


AMPLITUDES = (1.0, 3.5, 12.0)
BOUC_WEN = {
    "n1": BoucWen(),  # the example: beta = 0.6, gamma = 0.15, n = 1
    "n2_gamma_negative": BoucWen(a=0.8, b=-0.7, A=2.0, beta=0.5, gamma=-0.3, n=2.0, h0=0.5),
    "beta_equals_gamma": BoucWen(A=1.5, beta=0.4, gamma=0.4, n=1.5, h0=-0.2),
}


@pytest.fixture(scope="module")
def bouc_wen_loops():
    return {k: sine_loops(m, AMPLITUDES, 2.3, 3.0, DT) for k, m in BOUC_WEN.items()}


@pytest.mark.parametrize("name", list(BOUC_WEN))
def test_bouc_wen_matches_scipy_and_stays_within_its_bound(name, bouc_wen_loops):
    m = BOUC_WEN[name]
    t, u, w = bouc_wen_loops[name]
    for k, amplitude in enumerate(AMPLITUDES):
        w_ref = bouc_wen_reference(m, amplitude, 2.3, t)
        assert np.max(np.abs(w[k] - w_ref)) <= 1e-6 * np.max(np.abs(w_ref))
        h = (w[k] - float(m.a) * u[k]) / float(m.b)
        assert np.max(np.abs(h)) <= float(m.h_max()) * (1 + 1e-9)


def test_closed_loop_plays_are_the_exact_recursion_and_stay_in_their_band():
    """Along the DSC loop (a batch sweeping p[3]: the batch layout's clamp hook; the single
    trajectory's is `open_loop`'s): every step's play outputs are the recursion of the step
    grid's u, and |z - u| <= r."""
    setup = example("pi")
    p3 = np.array([[0.6], [1.0], [1.4]]) * float(setup.hysteresis.p[3])
    ov = params.overrides(setup, [params.Param.parse("hysteresis.p[3]")], p3)
    batch = dscjax.simulate_batch(setup, ov, t_final=0.5, dt=DT, refine=0, save_every=1)
    r = np.asarray(setup.hysteresis.r)
    for i in range(3):
        z, u = np.asarray(batch.h[i]), np.asarray(batch.u[i])
        assert np.all(np.abs(z - u[:, None]) <= r + 1e-12)
        expect = np.maximum(u[1:, None] - r, np.minimum(u[1:, None] + r, z[:-1]))
        np.testing.assert_allclose(z[1:], expect, atol=1e-13)
    assert not np.any(np.asarray(batch.diverged))


def numpy_band(model, u):
    """The clamp's bounds of every play at the inputs u (T,), in NumPy: (T, N) each."""
    r = np.asarray(model.r)
    if model.kind == "pi":
        return u[:, None] - r, u[:, None] + r

    def g(e, x):
        return e[0] * np.tanh(e[1] * x + e[2]) + e[3]

    return (g(np.asarray(model.envelope_left), u[:, None]) - r,
            g(np.asarray(model.envelope_right), u[:, None]) + r)


@pytest.mark.parametrize("kind,solver", [("pi", "rk4"), ("gpi", "rk4"), ("pi", "etdrk4")])
def test_single_run_plays_are_the_exact_recursion(kind, solver):
    """One trajectory (the packed layout, plays held inside each step): every step's play
    outputs are the recursion of the step grid's u, and w is p0 u + sum p_j z_j."""
    setup = example(kind)
    traj = dscjax.simulate(setup, t_final=0.5, dt=DT, solver=solver)
    z, u, w = np.asarray(traj.h), np.asarray(traj.u), np.asarray(traj.w)
    lo, hi = numpy_band(setup.hysteresis, u)
    np.testing.assert_allclose(z[1:], np.maximum(lo[1:], np.minimum(hi[1:], z[:-1])),
                               rtol=0, atol=1e-13)
    np.testing.assert_allclose(w, float(setup.hysteresis.p0) * u
                               + z @ np.asarray(setup.hysteresis.p), rtol=0, atol=1e-13)


BAD = [
    ({"kind": "pi", "r": [0.4, 0.2], "p": [1.0, 1.0]}, "hysteresis.r must be strictly increasing"),
    ({"kind": "pi", "r": [-0.1, 0.2], "p": [1.0, 1.0]}, "hysteresis.r must be >= 0"),
    ({"kind": "pi", "r": [0.1, 0.2], "p": [1.0, 1.0, 1.0]}, "hysteresis.p must have one weight"),
    ({"kind": "pi", "r": [0.1, 0.2], "p": [1.0, 1.0], "z0": [0.0, 0.0, 0.0]},
     "hysteresis.z0 must be one number or one per threshold"),
    ({"kind": "pi", "p0": -0.1}, r"hysteresis.p0 must be >= 0"),
    ({"kind": "pi", "r": 0.3}, "hysteresis.r must be a list"),
    ({"kind": "gpi", "envelope_left": [1.0, -1.0, 0.0, 0.0]},
     "hysteresis.envelope_left = .* must be increasing"),
    ({"kind": "gpi", "envelope_right": [1.0, 1.0, 0.0]}, "hysteresis.envelope_right must"),
    ({"kind": "bouc_wen", "beta": -0.5, "gamma": 0.2},
     r"hysteresis.beta \+ hysteresis.gamma must be > 0 \(got beta=-0.5, gamma=0.2\)"),
    ({"kind": "bouc_wen", "n": 0.5}, "hysteresis.n must be >= 1"),
    ({"kind": "bouc_wen", "A": 0.0}, "hysteresis.A must be > 0"),
    ({"kind": "bouc_wen", "alpha": 1.0}, "unknown key 'hysteresis.alpha'"),
    ({"kind": "prandtl"}, "hysteresis.kind"),
]


@pytest.mark.parametrize("table, message", BAD)
def test_bad_hysteresis_configs_name_the_field(table, message):
    with pytest.raises(ConfigError, match=message) as err:
        validate_setup(config.from_dict({"hysteresis": table})[0])
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("kind", ["backlash", "pi", "gpi", "bouc_wen"])
def test_toml_round_trip_of_every_kind(kind):
    import tomllib

    setup, options = config.from_dict({"hysteresis": {"kind": kind}})
    back, _ = config.from_dict(tomllib.loads(config.to_toml(setup, options)))
    assert type(back.hysteresis) is type(setup.hysteresis)
    for f in ("r", "p", "envelope_left", "beta", "lam"):
        if hasattr(setup.hysteresis, f):
            np.testing.assert_array_equal(getattr(back.hysteresis, f),
                                          getattr(setup.hysteresis, f))


def test_old_kind_key_is_refused_as_an_unknown_key(tmp_path, capsys):
    # hysteresis.model, the kind key's spelling before hysteresis.kind, is no longer read
    cfg = tmp_path / "old.toml"
    cfg.write_text('[hysteresis]\nmodel = "bouc_wen"\n')
    assert main(["hysteresis", "--config", str(cfg), "--out", str(tmp_path / "loop")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert "unknown key 'hysteresis.model' (allowed: kind," in err
    assert len(err.strip().splitlines()) == 1


def test_hysteresis_command_writes_the_loop_and_refuses_bad_input(tmp_path, capsys):
    cfg = tmp_path / "pi.toml"
    cfg.write_text('[hysteresis]\nkind = "pi"\n')
    out = tmp_path / "loop"
    assert main(["hysteresis", "--config", str(cfg), "--amplitude", "3.5", "--t-final", "0.5",
                 "--out", str(out)]) == 0
    with np.load(out / "loop.npz") as f:
        assert f["t"].shape == (501,) and f["u"].shape == f["w"].shape == (1, 501)
        assert str(f["kind"]) == "pi"
    assert (out / "loop.png").stat().st_size > 0
    capsys.readouterr()
    with pytest.raises(SystemExit) as stop:
        main(["hysteresis", "--omega", "0", "--out", str(out)])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "Traceback" not in err
    assert "argument --omega: must be a finite number > 0 (got '0')" in err
    cfg.write_text('[hysteresis]\nkind = "pi"\nr = [0.5, 0.1]\np = [1.0, 1.0]\n')
    assert main(["hysteresis", "--config", str(cfg), "--out", str(out)]) == 2
    assert "hysteresis.r must be strictly increasing" in capsys.readouterr().err


@pytest.fixture(scope="module")
def pi_sweep():
    """One float64 grid over a scale of the whole weight vector p and one element r[3]."""
    from dscjax.params import parse_range
    from dscjax.sweep import SweepSettings, run_sweep

    setup = example("pi")
    ranges = (parse_range("hysteresis.p*=0.7:1.3:2", grid=True),
              parse_range("hysteresis.r[3]=0.7:0.9:2", grid=True))
    settings = SweepSettings(method=params.Grid(), ranges=ranges, dtype="float64", worst=0,
                             random=0)
    return setup, run_sweep(setup, settings, t_final=0.4, dt=DT, window_start=0.1)


def test_sweeping_a_scale_or_an_element_equals_setting_it(pi_sweep):
    setup, res = pi_sweep
    cols = res.columns
    assert list(cols["hysteresis.p*"]) == [0.7, 0.7, 1.3, 1.3]
    assert list(cols["hysteresis.r[3]"]) == [0.7, 0.9, 0.7, 0.9]
    p, r = np.asarray(setup.hysteresis.p), np.asarray(setup.hysteresis.r)
    for i in (0, 3):  # (0.7, r3 = 0.7) and (1.3, r3 = 0.9)
        s, r3 = float(cols["hysteresis.p*"][i]), float(cols["hysteresis.r[3]"][i])
        one = params.set_many(setup, {"hysteresis.p": s * p,
                                      "hysteresis.r": np.where(np.arange(r.size) == 3, r3, r)})
        ref = dscjax.simulate(one, 0.4, DT, window_start=0.1).metrics
        for name in ("linf_error_window", "l2_error", "max_abs_u", "max_abs_w"):
            assert cols[name][i] == pytest.approx(float(ref[name]), rel=1e-12, abs=0), name


def test_scale_syntax_is_checked_by_the_one_parser(tmp_path, capsys):
    from dscjax.params import Param, check, parse_range

    assert Param.parse("hysteresis.p*") == Param("hysteresis.p", scale=True)
    assert parse_range("hysteresis.p*=30%").resolve(example("pi")).low == pytest.approx(0.7)
    for ranges, message in (
            (["hysteresis.p0*=0.7:1.3"], "'hysteresis.p0' is a scalar"),
            (["hysteresis.p*=0.7:1.3", "hysteresis.p[3]=10%"], "both change 'hysteresis.p'"),
            (["hysteresis.p*=-1:1.3"], "hysteresis.p must be >= 0")):
        with pytest.raises(ConfigError, match=message):
            check([parse_range(r) for r in ranges], example("pi"), "--range")
    assert main(["sweep", "--example", "pi", "--range", "hysteresis.p0*=0.7:1.3",
                 "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "'hysteresis.p0' is a scalar" in err and "Traceback" not in err


def test_a_tuned_scale_multiplies_the_vector():
    import jax.numpy as jnp

    from dscjax.selection import Selection

    setup = example("pi")
    sel = Selection.build(setup, ["controller.tau", "controller.k*"])
    assert sel.names == ("controller.tau", "controller.k*") and sel.size(setup) == 2
    z = sel.init(setup)
    assert float(z["controller.k*"]) == 0.0
    tuned = sel.apply(setup, {**z, "controller.k*": jnp.log(2.5)})
    np.testing.assert_allclose(tuned.controller.k, 2.5 * np.asarray(setup.controller.k),
                               rtol=1e-15)


# -- issue 38 item 7f: what each model does with the first input, at t = 0 ---------------------

# x(0) = (0.5, 0.1): the law's first input is u(0) = -1.71, which drags most plays from z0
START = {"plant.x0": np.array([0.5, 0.1])}
FIRST = {"paper": {"hysteresis.w0": 0.3}, "bouc_wen": {"hysteresis.h0": 0.2},
         "pi": {"hysteresis.z0": 0.2}, "gpi": {"hysteresis.z0": 0.2}}


def _start(name, **sampled):
    """(u(0), w(0), u_0 held by a sampled controller, its w) of the example `name` from rest
    at START: the closed loop's own initial state and output, evaluated eagerly."""
    import jax.numpy as jnp

    from dscjax import closed_loop as cl
    from dscjax.simulate import canonical

    setup = cl.prepared(canonical(params.set_many(example(name), START | FIRST[name])))
    X0 = cl.initial_state(setup)
    _, obs = cl.vector_field(jnp.zeros(()), X0, setup)
    held = cl.sampled_initial_state(setup, cl.Sampling(every=1.0, **sampled), 1e-3)
    w_held = setup.hysteresis.output(held.u, held.h)
    return setup, float(obs.u), float(obs.w), float(held.u), float(w_held)


def _play_outputs(setup, u, z0):
    """max(lo(u) - r, min(hi(u) + r, z0)) in NumPy: the plays dragged from z0 to u at once."""
    h = setup.hysteresis
    r = np.asarray(h.r)
    if h.kind == "gpi":
        lo, hi = (a * np.tanh(b * u + c) + d for a, b, c, d in
                  (np.asarray(h.envelope_left), np.asarray(h.envelope_right)))
    else:
        lo = hi = u
    return np.maximum(lo - r, np.minimum(hi + r, z0))


@pytest.mark.parametrize("name", ["paper", "bouc_wen", "pi", "gpi"])
def test_the_first_input_at_t0_is_what_docs_hysteresis_says(name):
    setup, u0, w0, u_held, w_held = _start(name)
    h = setup.hysteresis
    assert u0 == pytest.approx(-1.7125, abs=1e-4)
    if name == "paper":  # w(0) = w0, whatever u(0)
        assert w0 == 0.3
    elif name == "bouc_wen":  # h(0) = h0: w(0) = a u(0) + b h0
        assert w0 == pytest.approx(float(h.a) * u0 + float(h.b) * 0.2, rel=1e-14)
    else:  # the plays dragged from z0 to u(0): w(0) = p0 u(0) + sum p_j z_j(0)
        z = _play_outputs(setup, u0, 0.2)
        assert 0 < np.sum(z != 0.2) < len(z)  # some plays dragged, some not
        assert w0 == pytest.approx(float(h.p0) * u0 + np.sum(np.asarray(h.p) * z), rel=1e-14)
    # the sampled controller's first sample holds u(0) itself: no jump at t = 0 (the
    # backlash's closed form from u(0) to u(0), to round-off)
    assert u_held == u0 and w_held == pytest.approx(w0, rel=1e-13)


def test_a_noisy_first_sample_moves_the_backlash_along_its_curve():
    setup, u0, w0, u_held, w_held = _start("paper", noise=0.05, seed=3.0)
    h = setup.hysteresis
    alpha, lam, psi = (float(x) for x in (h.alpha, h.lam, h.psi))
    assert abs(u_held - u0) > 0.1 and abs(w_held - w0) > 1e-3  # it read a noisy x
    s = np.sign(u_held - u0)  # eqs. (5)-(6) from (u(0), w0) to the sampled input
    decay = np.exp(-alpha * s * (u_held - u0))
    d1 = (w0 - lam * u0) * decay + (psi - lam) / (alpha * s) * (1 - decay)
    assert w_held == pytest.approx(lam * u_held + d1, rel=1e-12)
    # with a one-sample delay the actuator holds the noise-free u(0) for the first sample
    _, _, _, u_late, w_late = _start("paper", noise=0.05, seed=3.0, delay=1, line=1)
    assert u_late == u0 and w_late == pytest.approx(w0, rel=1e-13)
