"""Bad input: one clear message naming the field and the allowed range."""

import dataclasses
import subprocess
import sys

import numpy as np
import pytest
from commands import exit_code

import dscjax
from dscjax import config, validation
from dscjax.validation import ConfigError


def _set(setup, path, value):
    return dscjax.params.set(setup, path, np.asarray(value, dtype=float))


@pytest.mark.parametrize("path,value,pattern", [
    ("hysteresis.lam", 0.05,
     r"hysteresis.lam must be > hysteresis.psi \(got lam=0.05, psi=0.105\)"),
    ("hysteresis.alpha", 0.0, r"hysteresis.alpha must be > 0 \(got 0\)"),
    ("hysteresis.alpha", -1.0, r"hysteresis.alpha must be > 0 \(got -1\)"),
    ("controller.k", [10.0, -0.45], r"controller.k must be > 0 \(got \[10, -0.45\]\)"),
    ("controller.tau", [0.0], r"controller.tau must be > 0"),
    ("controller.gamma_d", 0.0, r"controller.gamma_d must be > 0"),
    ("controller.eps", -0.01, r"controller.eps must be > 0"),
    ("controller.eta", [0.01, -1.0], r"controller.eta must be >= 0"),
    ("plant.g", [1.0, -1.0], r"plant.g must be > 0"),
    ("controller.k", [10.0, 0.45, 1.0],
     r"controller.k must have shape \(2,\) for a plant of order n=2 \(got shape \(3,\)\)"),
    ("hysteresis.alpha", np.nan, r"hysteresis.alpha must be"),
])
def test_bad_setup_values(paper_setup, path, value, pattern):
    with pytest.raises(ConfigError, match=pattern):
        dscjax.simulate(_set(paper_setup, path, value), 1.0, 1e-3)


def test_bad_static_choice(paper_setup):
    bad = paper_setup.replace(controller=dataclasses.replace(paper_setup.controller,
                                                              variant="none"))
    with pytest.raises(ConfigError, match=r"controller.variant must be one of 'full', 'no_dhat', "
                                          r"'no_dhat_no_zeta' \(got 'none'\)"):
        dscjax.simulate(bad, 1.0, 1e-3)


@pytest.mark.parametrize("kw,pattern", [
    (dict(dt=0.0), r"simulation.dt must be a finite number > 0 \(got 0.0\)"),
    (dict(dt=-1e-3), r"simulation.dt must be a finite number > 0"),
    (dict(t_final=0.0), r"simulation.t_final must be a finite number > 0"),
    (dict(t_final=float("inf")), r"simulation.t_final must be a finite number > 0 \(got inf\)"),
    (dict(dt=float("nan")), r"simulation.dt must be a finite number > 0 \(got nan\)"),
    (dict(t_final=1e9), r"simulation.t_final / simulation.dt = 1e\+12 steps, more than the "
                        r"2,147,483,647 the integrator's step counter holds"),
    (dict(dt=0.03, t_final=0.9),
     r"simulation.dt = 0.03 is too large for RK4 on the fastest filter: dt / "
                    r"min\(controller.tau\) must be <= 2.785 \(got min tau = 0.01, ratio 3\); "
                    r"use dt <= 0.0278$"),
    (dict(t_final=1.0005), r"simulation.t_final must be a whole number of steps"),
    (dict(window_start=5.0), r"simulation.window_start must be in \[0, t_final\)"),
])
def test_bad_run_settings(paper_setup, kw, pattern):
    args = dict(t_final=1.0, dt=1e-3) | kw
    with pytest.raises(ConfigError, match=pattern):
        dscjax.simulate(paper_setup, **args)


def test_order_mismatch_from_config():
    with pytest.raises(ConfigError, match=r"controller.k must have shape \(3,\) for a plant of "
                                          r"order n=3 \(got shape \(2,\)\)"):
        setup, _ = config.from_dict({"plant": {"family": "strict_feedback", "g": [1, 1, 1],
                                               "theta": [0, 0, 0], "x0": [0, 0, 0],
                                               "f_quad": [0, 0, 0], "f_sin": [0, 0, 0],
                                               "f_cross": [0, 0, 0], "rho_const": [0, 0, 0],
                                               "rho_quad": [0, 0, 0], "delta_sin": [0, 0, 0],
                                               "delta_quad": [0, 0, 0]}})
        dscjax.validate_setup(setup)


@pytest.mark.parametrize("d,pattern", [
    ({"hysteresis": {"alpah": 1.0}}, r"unknown key 'hysteresis.alpah' \(allowed: kind, alpha"),
    ({"plants": {}}, r"unknown section 'plants'"),
    ({"simulation": {"dtt": 1.0}}, r"unknown key 'simulation.dtt'"),
    ({"controller": {"k": "ten"}}, r"controller.k must be a number or a list of numbers"),
    ({"controller": {"kind": "pid"}}, r"controller.kind must be one of 'dsc'"),
    ({"simulation": {"dtype": "float16"}}, r"simulation.dtype must be one of"),
    ({"simulation": {"save_every": 2.5}}, r"simulation.save_every must be an integer"),
])
def test_bad_config_keys(d, pattern):
    with pytest.raises(ConfigError, match=pattern):
        config.from_dict(d)


def _cli(*args, cwd):
    """`python -m dscjax.cli.main ARGS` in a process of its own: the exit code and stderr a
    user's shell sees."""
    return subprocess.run([sys.executable, "-m", "dscjax.cli.main", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


def _main(capsys, *args) -> tuple[int, str]:
    """(exit code, stderr) of `dscjax ARGS` run through `main` in this process (argparse's
    refusals exit by SystemExit)."""
    return exit_code(args), capsys.readouterr().err


def test_cli_bad_config_exits_2_without_traceback(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[hysteresis]\nlam = 0.1\npsi = 0.5\n")
    r = _cli("simulate", "--config", str(cfg), "--out", str(tmp_path / "o"), cwd=tmp_path)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    assert "hysteresis.lam must be > hysteresis.psi (got lam=0.1, psi=0.5)" in r.stderr


def test_cli_unreadable_config_and_bad_dt(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, err = _main(capsys, "simulate", "--config", str(tmp_path / "missing.toml"))
    assert code == 2 and "cannot read config file" in err
    assert "Traceback" not in err
    code, err = _main(capsys, "simulate", "--dt", "-1")
    assert code == 2 and "argument --dt: must be a finite number > 0 (got '-1')" in err
    assert not (tmp_path / "results").exists()


def test_cli_divergence_exits_3_with_time(tmp_path, capsys):
    # dt = 0.02 passes the filter check (dt/tau = 2 < 2.785) but not the loop's initial
    # transient (local spectral radius ~490 at t = 0): RK4 diverges at t = 0.04 s
    # --refine 0: no ETDRK4 re-run at smaller steps (which would track)
    code, err = _main(capsys, "simulate", "--dt", "0.02", "--t-final", "4", "--out",
                      str(tmp_path / "o"), "--no-plot", "--refine", "0")
    assert code == 3, err
    assert "diverged at t = " in err and "Traceback" not in err
    import json

    m = json.loads((tmp_path / "o" / "metrics.json").read_text())
    assert m["diverged"] is True and 0 < m["t_diverged"] < 4
    data = np.load(tmp_path / "o" / "trajectory.npz")
    assert np.all(np.isfinite(data["x"])) and np.all(np.isfinite(data["u"]))


def test_library_divergence_error_carries_the_trajectory(paper_setup):
    with pytest.raises(dscjax.DivergenceError, match=r"diverged at t = 0.04 s.*spectral radius "
                                                      r"4[0-9][0-9]") as info:
        dscjax.simulate(paper_setup, 4.0, 0.02, refine=0)
    tr = info.value.trajectory
    assert bool(tr.diverged) and np.all(np.isfinite(np.asarray(tr.x)))


def test_stability_profile_of_the_paper_example(paper_setup):
    tr = dscjax.simulate(paper_setup, 2.0, 1e-3, save_every=10)
    prof = dscjax.closed_loop.spectrum_along(paper_setup, tr)
    # the filter mode -1/tau = -100 is always there; the initial transient peaks near 490
    assert prof.radius.min() > 70.0
    assert 400 < prof.radius.max() < 600 and prof.t_peak < 0.05
    assert prof.suggested_dt == pytest.approx(2.785 / prof.radius.max())


def test_the_stability_map_judges_each_step_over_its_own_horizon(paper_setup):
    # `dscjax stability` runs the steps at and above dt, and the bisection, for dt's count of
    # steps (a longer horizon, one program): each verdict must be that of a run of the step's
    # own count alone. alpha = 10: RK4 at 1 ms diverges within milliseconds. 32 ms is past
    # RK4's bound on the fastest filter, which `simulate` refuses and the map must report on
    # (as the batches below do: a batch reports a diverged row in its status). The
    # README's horizon, dt and tau scales: the programs of its `dscjax stability` example.
    from dscjax.step_size import stability_map

    setup = _set(paper_setup, "hysteresis.alpha", 10.0)
    t_final, dt = 0.2, 1e-3
    assert 0.032 / np.min(setup.controller.tau) > validation.RK4_REAL_STABILITY
    m = stability_map(setup, t_final, dt, factors=(0.5, 1.0, 2.0, 32.0), bisections=2)
    own = m.tau_scale.tolist().index(1.0)
    assert m.stable[own].tolist() == [True, False, False, False]  # bisected in (0.5, 1) ms
    assert 5e-4 < m.largest_stable_dt < 1e-3 and not m.beyond_grid

    def alone(step):  # the step's own count of steps, nothing after the horizon
        n = max(round(t_final / step), 1)
        tau = {"controller.tau": np.asarray(setup.controller.tau)[None] * m.tau_scale[:, None]}
        run = dscjax.simulate_batch(setup, tau, n * step, step, refine=0)
        return np.asarray(run.diverged), np.asarray(run.t_diverged)

    for j, step in enumerate(m.dt):  # every tau scale's verdict
        diverged, t_div = alone(step)
        assert diverged.tolist() == (~m.stable[:, j]).tolist()
        np.testing.assert_allclose(t_div, m.t_diverged[:, j], rtol=1e-12)
    assert not alone(m.largest_stable_dt)[0][own]
