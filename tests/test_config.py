"""TOML config: round trip, overlay on the default, JSON, dtype."""

import json
import tomllib

import numpy as np
import pytest

import dscjax
from dscjax import config
from dscjax.runspec import MAX_SAVED_POINTS, RunSpec, auto_stride


def _same(a, b):
    da, db = config.to_dict(a), config.to_dict(b)
    return da == db


def test_default_toml_round_trips():
    text = config.to_toml(dscjax.paper_example(dtype=np.float64))
    setup, options = config.from_dict(tomllib.loads(text))
    assert _same(setup, dscjax.paper_example(dtype=np.float64))
    assert options == RunSpec.make()
    # and writing it again gives the same text
    assert config.to_toml(setup, options) == text
    # keys whose default is a rule are shown, commented out with the value they take
    assert "\n# window_start = 1.0 " in text and "\n# save_every = 1 " in text


def test_partial_config_overlays_the_default():
    setup, opts = config.from_dict({"hysteresis": {"alpha": 2.5}, "controller": {"k": [8, 0.5]},
                                    "simulation": {"dt": 5e-4}})
    assert float(setup.hysteresis.alpha) == 2.5
    np.testing.assert_array_equal(setup.controller.k, [8.0, 0.5])
    assert float(setup.hysteresis.lam) == 1.432 and opts.dt == 5e-4 and opts.t_final == 20.0


def test_kind_change_starts_from_the_new_class():
    setup, _ = config.from_dict({"reference": {"kind": "smooth_step", "height": 0.5}})
    assert type(setup.reference).__name__ == "SmoothStep"
    assert float(setup.reference.height) == 0.5 and float(setup.reference.rise_time) == 0.5


def test_every_paper_parameter_is_settable():
    names = set(dscjax.params.numeric_paths(dscjax.paper_example()))
    for path in ("plant.g", "plant.theta", "plant.x0", "plant.rho1", "plant.delta2",
                 "hysteresis.alpha", "hysteresis.lam", "hysteresis.psi", "hysteresis.w0",
                 "controller.k", "controller.tau", "controller.c", "controller.gamma_g",
                 "controller.gamma_phi", "controller.gamma_zeta", "controller.gamma_d",
                 "controller.eta", "controller.sigma", "controller.eta_zeta", "controller.eta_d",
                 "controller.eps", "controller.g_min", "controller.sat_width",
                 "controller.theta_hat0", "controller.phi_hat0", "controller.zeta_hat0",
                 "controller.d_hat0", "reference.amplitude", "reference.frequency"):
        assert path in names, path


def test_json_config_loads(tmp_path):
    d = config.to_dict(dscjax.paper_example(dtype=np.float64))
    d["controller"]["k"] = [7.0, 0.5]
    path = tmp_path / "gains.json"
    path.write_text(json.dumps({"controller": {"k": [7.0, 0.5]}}))
    setup, _ = config.from_dict(config.read(path))
    np.testing.assert_array_equal(setup.controller.k, [7.0, 0.5])


def test_order_n_family_from_config_simulates():
    n3 = dscjax.order_n_example(3, dtype=np.float64)
    d = config.to_dict(n3)
    setup, _ = config.from_dict(json.loads(json.dumps(d)))
    a = dscjax.simulate(dscjax.cast(setup, np.float64), 1.0, 1e-3, save_every=100)
    b = dscjax.simulate(n3, 1.0, 1e-3, save_every=100)
    np.testing.assert_allclose(np.asarray(a.x), np.asarray(b.x), atol=1e-13)


@pytest.mark.parametrize("suffix, text, field", [
    (".toml", "[controller]\nk = [10.0, true]\n", "controller.k[1]"),
    (".json", '{"controller": {"k": [10.0, true]}}', "controller.k[1]"),
    (".toml", "[hysteresis]\nalpha = false\n", "hysteresis.alpha"),
    (".json", '{"plant": {"x0": [true, 0.0]}}', "plant.x0[0]"),
    (".toml", '[sweep.ranges]\n"hysteresis.alpha" = [0.5, true]\n',
     "sweep.ranges.hysteresis.alpha[1]"),
    (".toml", "[tuning.bounds]\n\"controller.k\" = [true, 100.0]\n", "controller.k"),
])
def test_booleans_are_not_numbers(suffix, text, field, tmp_path, capsys):
    from dscjax.cli.main import main

    cfg = tmp_path / f"c{suffix}"
    cfg.write_text(text)
    command = "sweep" if "sweep" in text else "tune" if "tuning" in text else "simulate"
    # tune checks its bounds when it builds the problem, after --print-config
    tail = ["--out", str(tmp_path / "out")] if command == "tune" else ["--print-config"]
    code = main([command, "--config", str(cfg), *tail])
    err = capsys.readouterr().err
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert field in err and ("boolean" in err or "number" in err), err


@pytest.mark.parametrize("name", ["paper", "backstepping", "order-3", "order-4"])
def test_every_examples_printed_config_round_trips(name, tmp_path, capsys):
    # `--print-config` prints the COMPLETE config of the example: laid over the DEFAULT
    # (paper) example it gives the same setup; two of them also run (compiling is slow)
    from dscjax.cli.main import main

    assert main(["simulate", "--example", name, "--print-config"]) == 0
    text = capsys.readouterr().out
    setup, _ = config.from_dict(tomllib.loads(text))
    assert _same(setup, dscjax.config.example(name, dtype=np.float64))
    if name in ("backstepping", "order-3"):
        (tmp_path / "c.toml").write_text(text)
        assert main(["simulate", "--config", str(tmp_path / "c.toml"), "--t-final", "0.05",
                     "--no-plot", "--out", str(tmp_path / "o")]) == 0
        m = json.loads((tmp_path / "o" / "metrics.json").read_text())
        assert m["diverged"] is False and m["linf_error"] > 0


@pytest.mark.parametrize("n_steps", [1, 20_000, 20_011, 40_000, 1_000_003, 2_147_483_629])
def test_the_automatic_stride_keeps_about_the_documented_number_of_points(n_steps):
    # 20,011 and 1,000,003 are prime: a stride that had to divide N kept t = 0 and T only
    from dscjax.integrate import saved_steps

    every = auto_stride(n_steps)
    points = saved_steps(n_steps, every)
    assert points[-1] == n_steps and points.size <= MAX_SAVED_POINTS
    assert every == 1 or points.size > MAX_SAVED_POINTS // 2


def test_a_prime_step_count_saves_the_strided_steps_and_t_final(paper_setup):
    from dscjax.integrate import saved_steps

    every_step = dscjax.simulate(paper_setup, 0.211, 1e-3, save_every=1)  # 211 steps, prime
    strided = dscjax.simulate(paper_setup, 0.211, 1e-3, save_every=10)
    k = saved_steps(211, 10)
    assert strided.t.shape == (23,) and float(strided.t[-1]) == pytest.approx(0.211, rel=1e-15)
    for name in ("t", "x", "u", "w", "u_dot", "yr", "S"):
        np.testing.assert_allclose(np.asarray(getattr(strided, name)),
                                   np.asarray(getattr(every_step, name))[k], rtol=1e-13,
                                   atol=1e-13, err_msg=name)
    batch = dscjax.simulate_batch(paper_setup, {"hysteresis.alpha": np.array([1.0, 1.1])},
                                  0.211, 1e-3, save_every=10)
    np.testing.assert_allclose(np.asarray(batch.x[0]), np.asarray(strided.x), rtol=1e-12,
                               atol=1e-15)
    assert float(batch.t[0, -1]) == pytest.approx(0.211, rel=1e-15)


def test_grouped_steps_keep_the_run_and_its_saved_points():
    # 2,000 steps of 0.1 ms saving every 10th, taken 10 at a time: 200 steps of 10 substeps,
    # every step saved; the same horizon, saved times and table; refining it halves the
    # substep (2^2 x 10 of dt/4 to a step); a group that does not divide the steps is refused
    spec = RunSpec.make(0.2, 1e-4, save_every=10, sample_time=5e-4)
    g = spec.grouped(10)
    assert (g.n_steps, g.save_every, int(g.substeps)) == (200, 1, 10)
    assert g.t_final == pytest.approx(0.2) and g.n_saved == spec.n_saved == 201
    assert g.to_table() == spec.to_table() and g.sample_every == spec.sample_every == 5
    r = g.refined(2, g.solver)
    assert (r.n_steps, int(r.substeps), r.sample_every) == (200, 40, 20)
    assert r.t_final == pytest.approx(0.2)
    with pytest.raises(ValueError, match="m = 3 must divide n_steps = 2000 and save_every"):
        spec.grouped(3)
