"""dscjax identify: bad records get one line; the actuator alone and the plant with its actuator
are identified from synthetic records of known numbers, each hysteresis model; the 95 %
intervals cover the truth about 95 % of the time over noise seeds; a number the data cannot
fix is named; the CLI writes a config that simulate and tune load."""

import json
import tomllib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dscjax
from dscjax import params
from dscjax.cli.main import main
from dscjax.config import example
from dscjax.identify import Problem, Record, estimates, read, solve, solve_starts
from dscjax.identify.experiment import Experiment, simulate
from dscjax.identify.fit import noise_level
from dscjax.validation import ConfigError

T_ACT = np.linspace(0.0, 2.0, 201)  # an actuator record: 201 samples at 10 ms


def _u(t):
    """A rich input: growing and shrinking loops at two frequencies."""
    return 2.5 * np.sin(1.7 * t) * (0.6 + 0.4 * np.cos(0.9 * t)) + 0.4 * np.sin(7.3 * t)


def _actuator_record(setup, noise, seed, t=T_ACT, hold="zoh"):
    """w of `setup`'s hysteresis driven by _u, simulated independently of the fit's code: the
    model's own `jump` between samples (zoh) via numpy, plus Gaussian noise."""
    h = setup.hysteresis
    u = _u(t)
    state = h.init_state(u[0])
    w = [float(h.output(u[0], state))]
    jump = jax.jit(type(h).jump)  # one sample at a time, as a digital controller holds u
    for k in range(1, t.size):
        state = jump(h, u[k - 1], u[k], state)
        w.append(float(h.output(u[k], state)))
    rng = np.random.default_rng(seed)
    return Record(t, u, {"w": np.asarray(w) + noise * rng.standard_normal(t.size)})


def _record_csv(path, rec):
    """`rec` as CSV: t, u, then its measured columns."""
    data = np.column_stack([rec.t, rec.u, *rec.y.values()])
    np.savetxt(path, data, delimiter=",", header=",".join(["t", "u", *rec.y]), comments="",
               fmt="%.10g")


def _write_csv(path, header, rows):
    path.write_text(",".join(header) + "\n" + "\n".join(",".join(r) for r in rows) + "\n")
    return path


GOOD = [[f"{0.01 * k:g}", f"{np.sin(k):.4f}", f"{np.cos(k):.4f}"] for k in range(30)]


@pytest.mark.parametrize("header, rows, message", [
    (["t", "u", "x1"], GOOD[:5] + [["0.05", "nan", "1"]] + GOOD[6:],
     "r.csv, line 7, column 'u': nan (every value must be a finite number)"),
    (["t", "u", "x1"], GOOD[:9] + [["0.05", "1", "1"]] + GOOD[10:],
     "r.csv, line 11, column 't': 0.05 is not after the time before it, 0.08 (times must "
     "increase)"),
    (["t", "u", "x1"], GOOD[:8], "r.csv: 8 samples; at least 20 are needed"),
    (["t", "u", "x3"], GOOD, "r.csv: column 'x3': the model has no such state (order 2: x1, "
                             "x2; w: the actuator's output)"),
    (["t", "v", "x1"], GOOD, "r.csv: no column 'u' (the columns are: t, v, x1; a record needs "
                             "t, u and one of x1, x2, w)"),
    (["t", "u", "x1"], GOOD[:3] + [["0.03", "abc", "1"]] + GOOD[4:],
     "r.csv, line 5, column 'u': not a number ('abc')"),
])
def test_a_bad_record_is_one_line_naming_file_column_and_line(tmp_path, capsys, header, rows,
                                                              message):
    path = _write_csv(tmp_path / "r.csv", header, rows)
    with pytest.raises(ConfigError) as err:
        read(path, order=2)
    assert str(err.value) == f"{tmp_path}/{message}"
    code = main(["identify", "--data", str(path), "--free", "plant.g", "--out",
                 str(tmp_path / "o")])
    err_lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err_lines == [f"dscjax identify: error: {tmp_path}/{message}"]
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("fitted, validated", [
    (["x1", "x2"], ["w"]),  # plant data validated on an actuator record
    (["x1", "x2"], ["x1"]),  # a column of the fit not measured
    (["w"], ["x1", "w"]),  # the actuator alone validated with a plant state
])
def test_a_validation_record_must_measure_the_fits_columns(tmp_path, capsys, fitted, validated):
    data = _write_csv(tmp_path / "a.csv", ["t", "u", *fitted],
                      [r[:2] + r[2:] * len(fitted) for r in GOOD])
    val = _write_csv(tmp_path / "b.csv", ["t", "u", *validated],
                     [r[:2] + r[2:] * len(validated) for r in GOOD])
    code = main(["identify", "--data", str(data), "--validate", str(val), "--free", "plant.g",
                 "--out", str(tmp_path / "o")])
    err_lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err_lines == [
        f"dscjax identify: error: --validate: {val} measures {', '.join(validated)}; it must "
        f"measure the columns of --data {data}: {', '.join(fitted)}"]
    assert not (tmp_path / "o").exists()
    # the library's identify() refuses it alike, before its fit
    from dscjax.identify.run import IdentifySettings, identify
    from dscjax.runspec import RunSpec

    with pytest.raises(ConfigError, match="^--validate: .* it must measure the columns"):
        identify(example("paper"), RunSpec.make(1.0, 1e-3), read(data, 2), IdentifySettings(
            free=("plant.g",)), validation=read(val, 2))
    # and a fit of nothing (the command's --free is required; the library refused it too)
    with pytest.raises(ConfigError, match="^--free: give the numbers to fit"):
        identify(example("paper"), RunSpec.make(1.0, 1e-3), read(data, 2), IdentifySettings())


@pytest.mark.parametrize("good_data", [False, True])
def test_a_bad_free_path_is_refused_before_the_data_and_the_out_directory(tmp_path, capsys,
                                                                          good_data):
    data = tmp_path / "r.csv"
    if good_data:  # then --out, which holds an earlier run's file, would refuse next
        _write_csv(data, ["t", "u", "x1"], GOOD)
    out = tmp_path / "o"
    out.mkdir()
    (out / "identified.toml").write_text("kept")  # refused without --overwrite
    code = main(["identify", "--data", str(data), "--free", "plant.nope", "--out", str(out)])
    err_lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err_lines) == 1
    assert err_lines[0].startswith("dscjax identify: error: --free: unknown parameter "
                                   "'plant.nope' (the numbers of the setup are: ")
    assert (out / "identified.toml").read_text() == "kept"


@pytest.mark.parametrize("columns, free, message", [
    # an actuator record (u, w) sees no plant number: refused once the record is read
    (["t", "u", "w"], "hysteresis.alpha,plant.g[1]",
     "--free must name hysteresis.* numbers, which act on an actuator (u, w) record (got "
     "plant.g[1])"),
    # the measured u drives the experiment: the controller never acts, refused before the data
    (["t", "u", "x1"], "controller.k,plant.g",
     "--free must name plant.* or hysteresis.* numbers, which act on a plant record (got "
     "controller.k)"),
])
def test_numbers_the_experiment_does_not_depend_on_are_refused_before_the_fit(
        tmp_path, capsys, columns, free, message):
    data = _write_csv(tmp_path / "r.csv", columns, GOOD)
    code = main(["identify", "--data", str(data), "--free", free, "--out", str(tmp_path / "o")])
    assert code == 2 and capsys.readouterr().err.strip().splitlines() == [
        f"dscjax identify: error: {message}"]
    assert not (tmp_path / "o").exists()
    # the library's identify() refuses it alike
    from dscjax.identify.run import IdentifySettings, identify
    from dscjax.runspec import RunSpec

    with pytest.raises(ConfigError) as err:
        identify(example("paper"), RunSpec.make(1.0, 1e-3), read(data, 2),
                 IdentifySettings(free=tuple(free.split(","))))
    assert str(err.value) == message


def test_an_npz_record_reads_as_a_csv_one(tmp_path):
    t = np.arange(25) * 0.01
    np.savez(tmp_path / "r.npz", t=t, u=np.sin(t), w=np.cos(t))
    rec = read(tmp_path / "r.npz", order=None)
    assert list(rec.y) == ["w"] and np.array_equal(rec.t, t)
    np.savez(tmp_path / "bad.npz", t=t[::-1], u=t, w=t)
    with pytest.raises(ConfigError, match=r"bad.npz, index 1, column 't'"):
        read(tmp_path / "bad.npz", order=None)


def test_noise_level_estimates_white_noise_on_a_smooth_signal():
    t = np.linspace(0, 10, 5001)
    rng = np.random.default_rng(1)
    assert noise_level(np.sin(t) + 0.01 * rng.standard_normal(t.size)) == pytest.approx(
        0.01, rel=0.05)


def test_the_held_input_experiment_is_the_models_own_jump_and_the_linear_one_its_rate():
    """The actuator alone, u held between samples: w equals the model's closed-form steps
    (`jump`) at every sample to round-off; u linear between samples: the ODE (4) integrated
    with u' constant, which tends to the model's run under u(t) itself."""
    setup = dscjax.paper_example()
    rec = _actuator_record(setup, 0.0, 0)
    _, w, _ = simulate(setup, Experiment.make(rec.t, rec.u, plant=False, dt=1e-3))
    np.testing.assert_allclose(np.asarray(w), rec.y["w"], rtol=0, atol=1e-12)
    t = np.linspace(0.0, 2.0, 2001)
    _, w_lin, _ = simulate(setup, Experiment.make(t, _u(t), plant=False, dt=1e-3,
                                                  hold="linear"))
    from dscjax.hysteresis import open_loop

    _, _, w_ref = open_loop(setup.hysteresis, lambda s: 2.5 * jnp.sin(1.7 * s) * (
        0.6 + 0.4 * jnp.cos(0.9 * s)) + 0.4 * jnp.sin(7.3 * s), 2.0, 1e-3)
    assert np.max(np.abs(np.asarray(w_lin) - w_ref)) < 1e-4


ACTUATORS = [
    ("backlash", {"hysteresis.alpha": 0.8, "hysteresis.lam": 1.6, "hysteresis.psi": 0.13},
     ["hysteresis.alpha", "hysteresis.lam", "hysteresis.psi"]),
    ("pi", {"hysteresis.p0": 0.9, "hysteresis.p*": 1.3},
     ["hysteresis.p0", "hysteresis.p*"]),
    ("gpi", {"hysteresis.p0": 1.1, "hysteresis.p*": 0.8}, ["hysteresis.p0", "hysteresis.p*"]),
    ("bouc_wen", {"hysteresis.a": 1.3, "hysteresis.A": 0.8, "hysteresis.beta": 0.5,
                  "hysteresis.gamma": 0.2},
     ["hysteresis.a", "hysteresis.A", "hysteresis.beta", "hysteresis.gamma"]),
]


@pytest.mark.parametrize("kind, truth, free", ACTUATORS, ids=[a[0] for a in ACTUATORS])
def test_the_actuator_alone_is_identified_on_every_model(kind, truth, free):
    """Each model's numbers from a record of w made with other numbers (noise std 1e-3): the
    fit starts from the model's defaults and ends within 4 standard errors of the truth (the
    95 % level is the coverage test's)."""
    base = example(kind if kind != "backlash" else "paper", dtype=np.float64)
    true = params.set_many(base, {k: v for k, v in truth.items() if not k.endswith("*")})
    for k, v in truth.items():
        if k.endswith("*"):
            true = params.set_many(true, {k[:-1]: v * np.asarray(params.get(base, k[:-1]))})
    rec = _actuator_record(true, 1e-3, 7)
    problem = Problem.make(base, rec, free, plant=False, dt=1e-2)
    fit, _ = solve_starts(problem, 2, max_steps=100)
    est = {e.name: e for e in estimates(problem, fit)[0]}
    for name, value in truth.items():
        e = est[name]
        assert e.identifiable, e
        assert abs(e.value - value) <= 4 * e.se, (name, value, e)  # a scale "p*": its factor


def test_the_intervals_cover_the_truth_about_95_percent_of_the_time():
    """20 noise seeds x 3 numbers of the backlash-like model: the 95 % intervals hold the
    truth in at least 52 of 60 (a binomial(60, 0.95) falls below 52 with probability 2e-3)
    and at most 60."""
    base = dscjax.paper_example()
    true = params.set_many(base, {"hysteresis.alpha": 0.8, "hysteresis.lam": 1.6,
                                  "hysteresis.psi": 0.13})
    truth = {"hysteresis.alpha": 0.8, "hysteresis.lam": 1.6, "hysteresis.psi": 0.13}
    covered = 0
    for seed in range(20):
        rec = _actuator_record(true, 5e-3, 100 + seed)
        problem = Problem.make(base, rec, list(truth), plant=False, dt=1e-2)
        fit = solve(problem, max_steps=100)
        covered += sum(e.low <= truth[e.name] <= e.high for e in estimates(problem, fit)[0])
    assert 52 <= covered <= 60, covered


def _plant_record(kind, truth, t_final=1.0, seed=3):
    """The paper's closed loop behind the `kind` actuator, sampled at 5 ms, with `truth`
    instead of the config's numbers; x1, x2 measured with noise std 1e-3."""
    base = example(kind if kind != "backlash" else "paper", dtype=np.float64)
    tr = dscjax.simulate(params.set_many(base, truth), t_final, 1e-3, sample_time=5e-3,
                         save_every=5)
    t, x = np.asarray(tr.t), np.asarray(tr.x)
    rng = np.random.default_rng(seed)
    return base, Record(t, np.asarray(tr.u), {f"x{i + 1}": x[:, i] + 1e-3 * rng.standard_normal(
        t.size) for i in range(2)})


PLANTS = [("backlash", "hysteresis.lam", 1.6), ("pi", "hysteresis.p0", 0.5),
          ("gpi", "hysteresis.p0", 0.5), ("bouc_wen", "hysteresis.a", 1.2)]


@pytest.mark.parametrize("kind, slope, value", PLANTS, ids=[p[0] for p in PLANTS])
def test_the_plant_with_its_actuator_is_identified_on_every_model(kind, slope, value):
    """theta_1 of the plant and the actuator's slope from x1, x2 of a closed-loop record (u
    measured): the truth within 4 standard errors, each number identified."""
    truth = {"plant.theta[0]": 0.15, slope: value}
    base, rec = _plant_record(kind, {"plant.theta": np.array([0.15, 0.0]), slope: value})
    problem = Problem.make(base, rec, list(truth), plant=True, dt=1e-3)
    for e in estimates(problem, solve(problem))[0]:
        assert e.identifiable and abs(e.value - truth[e.name]) <= 4 * e.se, e


def test_multiple_shooting_fits_each_segments_start_and_names_what_the_record_cannot_fix():
    """Two segments: the second's start state is fitted to where the measured states are. g_2
    and lam enter the loop only through their product (x_2' = g_2 w, and w scales with lam and
    psi): with the three free, g_2 and lam are named not identifiable, theta_1 is identified."""
    base, rec = _plant_record("backlash", {"plant.theta": np.array([0.15, 0.0]),
                                           "hysteresis.lam": 1.6})
    problem = Problem.make(base, rec, ["plant.g[1]", "hysteresis.lam", "hysteresis.psi",
                                       "plant.theta[0]"], plant=True, dt=1e-3, segments=2)
    fit = solve(problem)
    est = {e.name: e for e in estimates(problem, fit)[0]}
    assert not est["plant.g[1]"].identifiable and not est["hysteresis.lam"].identifiable
    assert "undetermined" in est["plant.g[1]"].why
    assert est["plant.theta[0]"].identifiable
    assert abs(est["plant.theta[0]"].value - 0.15) <= 4 * est["plant.theta[0]"].se
    # the product is what the record fixes: g_2 lam = 1 x 1.6
    assert est["plant.g[1]"].value * est["hysteresis.lam"].value == pytest.approx(1.6, rel=1e-3)
    x, k = np.asarray(fit.theta["x"]), problem.exp.starts[1]
    assert np.allclose(x[1], [rec.y["x1"][k], rec.y["x2"][k]], atol=5e-3)


def test_the_command_writes_a_config_that_simulate_and_tune_load(tmp_path, capsys):
    true = params.set_many(dscjax.paper_example(), {"hysteresis.alpha": 0.8,
                                                    "hysteresis.lam": 1.6})
    rec = _actuator_record(true, 1e-3, 5)
    _record_csv(tmp_path / "act.csv", rec)
    out = tmp_path / "id"
    code = main(["identify", "--data", str(tmp_path / "act.csv"), "--free",
                 "hysteresis.alpha,hysteresis.lam", "--dt", "0.01", "--out", str(out),
                 "--no-plot"])
    assert code == 0, capsys.readouterr().err
    report = json.loads((out / "report.json").read_text())
    assert report["experiment"] == "actuator" and report["columns"] == ["w"]
    fitted = report["fit"]["w"]["nrmse_fit_percent"]
    assert fitted > 95 and report["validation"]["figures"]["w"]["nrmse_fit_percent"] > 90
    ident = tomllib.loads((out / "identified.toml").read_text())
    lo, hi = ident["tuning"]["robust"]["ranges"]["hysteresis.alpha"]
    alpha = next(p for p in report["parameters"] if p["name"] == "hysteresis.alpha")
    assert (lo, hi) == (alpha["low"], alpha["high"]) and lo < ident["hysteresis"]["alpha"] < hi
    assert abs(alpha["value"] - 0.8) <= 4 * alpha["se"]
    from dscjax import config

    setup, _ = config.from_dict({k: v for k, v in ident.items() if k != "tuning"})
    assert float(setup.hysteresis.lam) == pytest.approx(1.6, rel=1e-2)
    from tuning.config import from_dict

    box = {r.name: (r.low, r.high) for r in from_dict(ident["tuning"]).robust.ranges}
    assert box["hysteresis.lam"] == tuple(ident["tuning"]["robust"]["ranges"]["hysteresis.lam"])
