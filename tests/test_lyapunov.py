"""Theorem 1 along trajectories (dscjax/theory.py, dscjax/alpha0_study.py).

V(t) of (44) is checked against a plain-NumPy computation from the paper's definitions (13),
(16), (19), (22), (25), (33)-(38), (44); V(0) under (67)-(68) against (69) by hand; dV/dt along
the vector field against finite differences of V(t); the gain rules (55), (60) and e_M (61)
against hand-written formulas.
"""

import dataclasses
import math

import jax
import numpy as np
import pytest

import dscjax
from dscjax.reproduce import theory
from dscjax.validation import ConfigError

LAM, PSI, ALPHA = 1.432, 0.105, 1.0
D_PAPER = (LAM - PSI) / ALPHA  # default bound of |d_n|: g_2 (lam - psi)/alpha, no dbar


# -- an independent V from the definitions, in NumPy -----------------------------------------


def _family_f_rho(p, x):
    """f_i and rho_i of the StrictFeedback family, written out from its docstring."""
    n = x.shape[0]
    q = np.cumsum(x * x)
    f = np.array([p["f_quad"][i] * x[i] ** 2 + p["f_sin"][i] * np.sin(x[i])
                  + (p["f_cross"][i] * x[i - 1] * x[i] if i else 0.0) for i in range(n)])
    return f, p["rho_const"] + p["rho_quad"] * q


def _numpy_v(traj, c_offsets, ctrl, plant, d, f_rho, yr_dot, yr=np.sin):
    """V of (44) at every saved point, from the definitions, in plain NumPy."""
    g, theta = np.asarray(plant.g), np.asarray(plant.theta)
    k, tau = np.asarray(ctrl.k), np.asarray(ctrl.tau)
    eps, g_min = float(ctrl.eps), float(ctrl.g_min)
    gamma_g, gamma_phi = np.asarray(ctrl.gamma_g), np.asarray(ctrl.gamma_phi)
    beta = LAM * g[-1]
    theta_true = np.append(theta[:-1] / g[:-1], theta[-1])  # (15), (21), (36)
    phi_true = 1.0 / g[:-1]
    t, x = np.asarray(traj.t), np.asarray(traj.x)
    z, th, ph = np.asarray(traj.z), np.asarray(traj.theta_hat), np.asarray(traj.phi_hat)
    zeta, dh = np.asarray(traj.zeta_hat), np.asarray(traj.d_hat)
    n = x.shape[1]
    out = np.empty(t.shape[0])
    for j in range(t.shape[0]):
        f, rho = f_rho(x[j])
        s = np.empty(n)
        s[0] = x[j, 0] - yr(t[j])  # (13)
        v_sig = yr_dot(t[j])  # the signal phi_hat multiplies: y_r', then z_i'
        ys = []
        for i in range(n - 1):
            if i > 0:
                s[i] = x[j, i] - z[j, i - 1] - c_offsets[i - 1]  # (19)
            x_d = (-th[j, i] * f[i] - s[i] * rho[i] ** 2 / (2 * eps * g_min) - k[i] * s[i]
                   + ph[j, i] * v_sig)  # (16), (22)
            ys.append(z[j, i] - x_d)  # (33)
            v_sig = (x_d - z[j, i]) / tau[i]  # z_(i+1)' (18), (24)
        s[n - 1] = x[j, n - 1] - z[j, n - 2] - c_offsets[n - 2]  # (25)
        V = 0.5 * sum(s[i] ** 2 / g[i] + (th[j, i] - theta_true[i]) ** 2 / gamma_g[i]
                      + (ph[j, i] - phi_true[i]) ** 2 / gamma_phi[i] + ys[i] ** 2
                      for i in range(n - 1))
        V += 0.5 * (beta * (zeta[j] - 1 / beta) ** 2 / float(ctrl.gamma_zeta)
                    + (th[j, n - 1] - theta_true[n - 1]) ** 2 / gamma_g[n - 1]
                    + (dh[j] - d) ** 2 / float(ctrl.gamma_d) + s[n - 1] ** 2)
        out[j] = V
    return out


def test_v_of_the_paper_example_matches_numpy():
    setup = dscjax.paper_example()
    traj = dscjax.simulate(setup, 1.0, 1e-3)  # the compilation the reproduce test reuses
    lv = theory.lyapunov(setup, traj)

    def f_rho(x):
        return np.array([x[0] ** 2, 0.0]), np.array([0.2, 0.1 * (x[0] ** 2 + x[1] ** 2)])

    ref = _numpy_v(traj, [0.1], setup.controller, setup.plant, D_PAPER, f_rho, np.cos)
    np.testing.assert_allclose(lv.V, ref, rtol=1e-10)
    total = sum(np.sum(np.reshape(getattr(lv, k), (len(lv.t), -1)), axis=1)
                for k in theory.TERM_NAMES)
    np.testing.assert_allclose(total, lv.V, rtol=1e-14)
    assert lv.surface.shape == (1001, 2) and lv.filter.shape == (1001, 1)


@pytest.mark.parametrize("n", [3, 4])
def test_v_of_order_n_under_linf_matches_numpy_and_69(n):
    """Order n with the L-inf initialisation (67)-(68): the reference is shifted to start at
    x_1(0) (docs/paper-readings.md #9), c_i = x_i(0), every estimate starts at 0."""
    setup = dscjax.order_n_example(n, init="linf")
    traj = dscjax.simulate(setup, 1.0, 1e-3, save_every=10)
    lv = theory.lyapunov(setup, traj, d=0.9)
    p = {k: np.asarray(getattr(setup.plant, k)) for k in setup.plant.vector_fields}
    x0 = np.asarray(setup.plant.x0)
    off, decay = x0[0] - 0.0, float(setup.controller.linf_decay_time)  # y_r(0) = sin 0 = 0

    def yr_dot(t):
        return np.cos(t) - off / decay * np.exp(-t / decay)

    ref = _numpy_v(traj, x0[1:], setup.controller, setup.plant, 0.9,
                   lambda x: _family_f_rho(p, x), yr_dot,
                   yr=lambda t: np.sin(t) + off * np.exp(-t / decay))
    np.testing.assert_allclose(lv.V, ref, rtol=1e-10)
    assert float(lv.truth.d) == 0.9
    # (69) by hand: g = 1, theta = 0.1 (theta_g = 0.1), phi = 1, gamma = 1, zeta = 1/lam
    by_hand = 0.5 * (n * 0.1 ** 2 + (n - 1) * 1.0 + LAM / LAM ** 2 + 0.9 ** 2)
    np.testing.assert_allclose(lv.V[0], by_hand, rtol=1e-14)
    assert np.all(lv.surface[0] == 0.0) and np.all(np.abs(lv.filter[0]) < 1e-30)


# -- (67)-(68) and (69) ------------------------------------------------------------------------


def test_v0_under_linf_initialisation_is_69_by_hand():
    setup = dscjax.paper_example(init="linf")
    traj = dscjax.simulate(setup, 1.0, 1e-3)
    lv = theory.lyapunov(setup, traj)
    # (69) with gamma = 8: theta_g1 = 0.1, theta_2 = 0, phi_1 = 1, zeta = 1/1.432, beta = 1.432
    assert lv.surface[0].tolist() == [0.0, 0.0] and abs(lv.filter[0, 0]) < 1e-30
    np.testing.assert_allclose(lv.theta[0], [0.1 ** 2 / 16, 0.0], rtol=1e-14)
    np.testing.assert_allclose(lv.phi[0], [1 / 16], rtol=1e-14)
    np.testing.assert_allclose(lv.zeta[0], LAM * (1 / LAM) ** 2 / 16, rtol=1e-14)
    np.testing.assert_allclose(lv.d[0], D_PAPER ** 2 / 16, rtol=1e-14)
    by_hand = (0.01 + 1.0 + 1 / 1.432 + 1.327 ** 2) / 16
    np.testing.assert_allclose(lv.V[0], by_hand, rtol=1e-14)
    s = dscjax.prepared(setup)
    np.testing.assert_allclose(theory.v0_69(s.controller, lv.truth), by_hand, rtol=1e-14)


# -- dV/dt -----------------------------------------------------------------------------------


def _frozen_unperturbed(setup):
    """All adaptation rates 0 (estimates frozen), no perturbations, smooth kinks."""
    c = setup.controller
    zero = {k: 0.0 * np.asarray(getattr(c, k)) for k in
            ("gamma_g", "gamma_phi", "gamma_zeta", "gamma_d")}
    ctrl = dataclasses.replace(c, robust_term="smooth", **zero)
    plant = dataclasses.replace(setup.plant, delta1=0.0, delta2=0.0)
    hyst = dataclasses.replace(setup.hysteresis, smooth=True)
    return dscjax.canonical(setup.replace(controller=ctrl, plant=plant, hysteresis=hyst))


def _fd_error(setup, dt, t_final=1.0):
    """max |central difference of V(t) - dV/dt along the vector field| / max |dV/dt|."""
    spec = dscjax.RunSpec.make(t_final, dt, save_every=1, window_start=0.0)
    traj = jax.jit(dscjax.run)(setup, spec)
    assert not bool(traj.diverged)
    V, V_dot = theory.lyapunov_rate(setup, traj)
    fd = (V[2:] - V[:-2]) / (2 * dt)
    return np.max(np.abs(fd - V_dot[1:-1])) / np.max(np.abs(V_dot)), traj, V


def test_dvdt_along_the_vector_field_matches_finite_differences():
    """All adaptation rates 0, no perturbations: the central difference of V(t) converges to
    the jvp of (44) along the vector field at second order."""
    setup = _frozen_unperturbed(dscjax.paper_example())
    err, traj, V = _fd_error(setup, 1e-4)
    lv = theory.lyapunov(setup, traj)
    # frozen estimates: their terms of (44) are left out (gamma = 0)
    assert np.all(lv.theta == 0) and np.all(lv.phi == 0) and np.all(lv.zeta == 0)
    assert np.all(lv.d == 0)
    np.testing.assert_allclose(V, lv.V, rtol=1e-12)
    err_half, _, _ = _fd_error(setup, 5e-5)
    assert err < 5e-4 and err_half < 1.25e-4
    assert 3.0 < err / err_half < 5.0  # O(h^2): the derivative is right, not merely close


def test_dvdt_with_adaptation_matches_finite_differences():
    setup = dscjax.paper_example(robust_term="smooth")
    setup = setup.replace(hysteresis=dataclasses.replace(setup.hysteresis, smooth=True))
    err, _, _ = _fd_error(setup, 1e-4)
    err_half, _, _ = _fd_error(setup, 5e-5)
    assert err < 1e-3 and err_half < 2.5e-4
    assert 3.0 < err / err_half < 5.0


# -- gain rules, e_M and bounds -----------------------------------------------------------------


def test_gains_55_and_tau_60():
    ctrl = dscjax.order_n_example(4).controller
    a = 2.5
    g = theory.gains_55(ctrl, a)
    np.testing.assert_allclose(g.k, [3 + a, 3.25 + a, 3.25 + a, 0.25 + a], rtol=1e-15)
    np.testing.assert_allclose(g.gamma_g, 2 * a / np.asarray(ctrl.eta), rtol=1e-15)
    np.testing.assert_allclose(g.gamma_phi, 2 * a / np.asarray(ctrl.sigma), rtol=1e-15)
    assert float(g.gamma_zeta) == pytest.approx(2 * a / 0.01)
    h = theory.gains_55(ctrl, a, hold="gamma")
    np.testing.assert_allclose(h.eta, 2 * a / np.asarray(ctrl.gamma_g), rtol=1e-15)
    np.testing.assert_allclose(h.gamma_g, ctrl.gamma_g)
    np.testing.assert_allclose(theory.tau_60(a, [2.0, 4.0], 0.5),
                               [1 / (0.25 + 4.0 + a), 1 / (0.25 + 16.0 + a)], rtol=1e-15)
    with pytest.raises(ConfigError, match="hold"):
        theory.gains_55(ctrl, a, hold="k")


def test_e_M_of_the_paper_example_by_hand():
    s = dscjax.prepared(dscjax.paper_example(init="linf"))
    tr = theory.truth(s)
    # (61): eta = sigma = eta_zeta = eta_d = eps = 0.01, c_2 = x_2(0) = 0.1, n = 2, g_min = 1
    by_hand = (0.01 * 0.1 ** 2 / 2 + 0.01 * 1 / 2 + 0.1 ** 2 / 4 + 0.01 * 0 / 2
               + 0.01 * LAM * (1 / LAM) ** 2 / 2 + 0.01 * D_PAPER ** 2 / 2
               + 0.01 / 2 + 0.01 / 2)
    np.testing.assert_allclose(theory.e_M(s.controller, tr), by_hand, rtol=1e-14)


def test_paper_gains_certify_alpha0_004():
    ctrl = dscjax.paper_example().controller
    a, allows = theory.certified_alpha0(ctrl, [10.0], mu=1.0)
    assert a == pytest.approx(0.04)  # eta_1 gamma_g1 / 2 = 0.01 * 8 / 2
    assert allows["k_1"] == pytest.approx(7.0) and allows["k_2"] == pytest.approx(0.2)
    assert allows["tau_2"] == pytest.approx(100 - 0.25 - 50.0)


def test_bounds_by_hand():
    assert theory.bound_71(0.3, 0.5) == pytest.approx(0.3)
    assert theory.bound_72(0.3, 0.5, 2.0) == pytest.approx(math.sqrt(1.2))
    b = theory.bound_65(np.array([0.0, 1.0]), 1.0, 0.2, 0.5)
    np.testing.assert_allclose(b, [1.0, 0.2 + 0.8 * math.exp(-1.0)], rtol=1e-15)


def test_default_d_includes_dbar():
    setup = dscjax.paper_example()
    setup = setup.replace(plant=dataclasses.replace(setup.plant, dbar_amp=0.3, dbar_bias=-0.1))
    assert float(theory.default_d(setup)) == pytest.approx(D_PAPER + 0.4)


def test_lyapunov_rejects_backstepping():
    from dscjax.controllers.backstepping import with_backstepping

    setup = with_backstepping(dscjax.paper_example())
    with pytest.raises(ConfigError, match="dsc"):
        theory.lyapunov(setup, None)  # refused before the trajectory is looked at


# -- the CLI ---------------------------------------------------------------------------------


def test_simulate_writes_v(tmp_path):
    from dscjax.cli.main import main

    out = tmp_path / "sim"
    assert main(["simulate", "--t-final", "1", "--save-every", "10", "--no-plot",
                 "--out", str(out)]) == 0
    data = np.load(out / "trajectory.npz")
    assert data["V"].shape == (101,) and data["V_surface"].shape == (101, 2)
    parts = sum(np.sum(np.reshape(data[f"V_{k}"], (101, -1)), axis=1) for k in theory.TERM_NAMES)
    np.testing.assert_allclose(parts, data["V"], rtol=1e-14)
    S = data["S"]
    np.testing.assert_allclose(data["V_surface"], 0.5 * S ** 2, rtol=1e-14)  # g = (1, 1)


def test_reproduce_theory_writes_lyapunov_npz_and_summary(tmp_path):
    import json

    from dscjax.cli.main import main

    out = tmp_path / "paper"
    # the horizon and alpha_0 of docs/reproduction.md's example as tests/doc_examples.py runs
    # it, on the same worker (conftest): the compiled programs are shared
    assert main(["reproduce", "--out", str(out), "--t-final", "0.2", "--dpi", "40", "--theory",
                 "--alpha0", "1"]) == 0
    data = np.load(out / "theory" / "lyapunov.npz")
    for key in ("t", "V", "surface", "filter", "theta", "phi", "zeta", "d", "y", "V_dot",
                "bound_65", "B"):
        assert key in data, key
    assert data["t"].shape == (201,) and data["surface"].shape == (201, 2)
    setup = dscjax.paper_example()
    traj = dscjax.simulate(setup, 0.2, 1e-3)
    np.testing.assert_allclose(data["V"], theory.lyapunov(setup, traj).V, rtol=1e-12)
    summary = json.loads((out / "summary.json").read_text())
    th = summary["theory"]
    assert th["paper"]["alpha0"] == pytest.approx(0.04)  # eta_i gamma_i / 2 binds
    assert th["paper"]["V0"] == pytest.approx(float(data["V"][0]))
    assert not th["paper"]["init"]["uses_67"] and not th["paper"]["init"]["uses_68"]
    rows = th["studies"][0]["rows"]
    assert [r["alpha0"] for r in rows] == [1.0]
    for row, a in zip(rows, (1.0,), strict=True):
        assert row["converged"] and row["all_hold"] and row["assumptions"]["(59)"]
        assert row["k"] == pytest.approx([3 + a, 0.25 + a])  # (55), g_min = 1
        assert row["gamma_g"] == pytest.approx([2 * a / 0.01] * 2)
        # (60) with the M that was used, and (59) on the run
        assert row["tau"][0] == pytest.approx(1 / (0.25 + row["M"][0] ** 2 / (2 * 0.1) + a))
        assert row["M_measured"][0] <= row["M"][0]
        assert row["V0"] == pytest.approx(row["v0_69"], rel=1e-12)  # (69)
        assert row["bound_72"] == pytest.approx(math.sqrt(row["C"] / a))  # g_max = 1
        assert row["bound_71"] == pytest.approx(row["C"] / (2 * a))
        assert row["C"] == pytest.approx(row["e_M"] + 0.1 / 2 + row["slack"])
        assert row["S1_inf"] <= row["bound_72"] and row["V_max"] <= row["bound_71"]
    for name in ("fig_lyapunov.png", "fig_alpha0.png", "alpha0_n2.json", "theory.json"):
        assert (out / "theory" / name).stat().st_size > 1000, name
    md = (out / "summary.md").read_text()
    assert "## Theorem 1 along trajectories" in md and "alpha_0 study, n = 2" in md
    assert "does not satisfy the theorem's assumptions" in md


def test_bad_alpha0_is_a_usage_error(tmp_path, capsys):
    from dscjax.cli.main import main

    assert main(["reproduce", "--out", str(tmp_path), "--theory", "--alpha0", "0,1"]) == 2
    assert "--alpha0" in capsys.readouterr().err


def test_study_skips_an_alpha0_that_needs_too_many_steps():
    from dscjax.reproduce import alpha0 as alpha0_study

    opts = alpha0_study.StudyOptions(alpha0=(1.0,), t_final=1.0, max_steps=10)
    res = alpha0_study.study(alpha0_study.base_setup(2), opts)
    (row,) = res["rows"]
    assert row["skipped"] and row["steps"] == 1000 and row["dt_needed"] == 1e-3
    assert "skipped: needs dt <= 0.001 s, 1000 steps" in alpha0_study.table_markdown(res)
    with pytest.raises(ConfigError, match="controller.init"):
        alpha0_study.study(dscjax.paper_example(), opts)
    with pytest.raises(ConfigError, match="mu"):
        alpha0_study.study(alpha0_study.base_setup(2), dataclasses.replace(opts, mu=0.0))
