"""Disturbance waveforms and the worst-case search (issue 14).

Kept fast: the search engine is checked on a linear oscillator with a known worst case (its
programs compile in about a second); the DSC loop runs only forward (random sampling) over a
1.5 s horizon, compiled once for the module.
"""

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from commands import exit_code

import dscjax
from dscjax import config, search
from dscjax import disturbance as dm
from dscjax.cli.main import main
from dscjax.worst import DisturbanceSpec, Programs, best_value, run_methods

# -- waveforms ----------------------------------------------------------------------------------


def test_fourier_matches_its_closed_form():
    coef = np.array([0.1, 0.2, -0.3, 0.05, 0.4, 0.0, -0.1])  # K = 3
    period = 2.5
    t = np.linspace(0.0, 5.0, 101)
    w = 2 * np.pi / period
    ref = coef[0] + sum(coef[j] * np.cos(j * w * t) + coef[3 + j] * np.sin(j * w * t)
                        for j in (1, 2, 3))
    got = np.asarray(dm.sample(dm.Fourier(coef, np.array(period)), t))
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-13)


def test_spline_interpolates_and_stays_within_its_knots():
    rng = np.random.default_rng(0)
    knots = rng.uniform(-1, 1, 9)
    spline = dm.Spline(knots, np.array(4.0))
    np.testing.assert_allclose(np.asarray(dm.sample(spline, np.linspace(0, 4, 9))), knots,
                               atol=1e-14)
    fine = np.asarray(dm.sample(spline, np.linspace(0, 4, 4001)))
    assert fine.max() <= knots.max() + 1e-14 and fine.min() >= knots.min() - 1e-14
    assert spline.max_abs() == np.max(np.abs(knots))


def test_fourier_projection_meets_the_bound_on_the_half_step_grid():
    grid = dm.half_step_grid(2.0, 1e-2)

    def projected(coef):  # the search's projection of a waveform onto max |dbar| <= 0.5
        values = dm.sample(dm.Fourier(coef, np.array(2.0)), grid)
        return np.asarray(dm.Fourier.project_coefficients(jnp.asarray(coef), 0.5, values))

    small = dm.Fourier(projected(np.array([0.5, 1.0, 0.0, 0.0, 2.0])), np.array(2.0))
    peak = np.max(np.abs(np.asarray(dm.sample(small, grid))))
    assert peak == pytest.approx(0.5, rel=1e-12)
    inside = np.array([0.1, 0.1, 0.0])
    np.testing.assert_array_equal(projected(inside), inside)


def test_disturbance_config_round_trip(tmp_path):
    setup = dscjax.paper_example()
    plant = setup.plant.__class__(**{**{f: getattr(setup.plant, f) for f in (
        "g", "theta", "x0", "rho1", "rho2", "delta1", "delta2", "delta_freq", "dbar_amp",
        "dbar_freq", "dbar_bias")}, "disturbance": dm.Spline(np.array([0.1, -0.2, 0.3]),
                                                          np.array(20.0))})
    setup = setup.replace(plant=plant)
    path = tmp_path / "c.toml"
    path.write_text(config.to_toml(setup))
    back, _ = config.from_dict(config.read(path))
    np.testing.assert_array_equal(back.plant.disturbance.knots, [0.1, -0.2, 0.3])
    assert float(back.plant.disturbance.horizon) == 20.0
    # no waveform: none written, none read
    assert "[plant.disturbance]" not in config.to_toml(dscjax.paper_example())


def test_disturbance_spec_errors():
    assert DisturbanceSpec.parse("fourier:16:0.5").size == 33
    assert DisturbanceSpec.parse("spline:8:1").size == 8
    for bad, word in (("fourier:0:0.5", "K"), ("spline:3:-1", "D"), ("sine:3:1", "kind"),
                      ("fourier:3", "fourier:K:D")):
        with pytest.raises(dscjax.ConfigError, match=word):
            DisturbanceSpec.parse(bad)


# -- the search on a problem with a known worst case --------------------------------------------

W, ZETA, T, DT, D, K = 2.0, 0.1, 6.0, 1e-2, 0.5, 25


@pytest.fixture(scope="module")
def oscillator():
    """x'' + 2 zeta w x' + w^2 x = dbar(t), x(0) = x'(0) = 0, metric x(T), |dbar| <= D: the
    worst disturbance is bang-bang, dbar(t) = D sign(h(T - t)) with h the impulse response,
    and the worst value is D int_0^T |h|. A spline of K knots cannot switch instantly: it gets
    within 2 % (the best spline on these knots reaches 0.9893 of it)."""
    n = int(round(T / DT))
    grid = dm.half_step_grid(T, DT)
    basis = np.stack([np.asarray(dm.sample(dm.Spline(e, np.array(T)), grid))
                      for e in np.eye(K)], axis=1)

    def one(c):
        dv = jnp.asarray(basis) @ (D * c)

        def f(y, d):
            return jnp.stack([y[1], -2 * ZETA * W * y[1] - W * W * y[0] + d])

        def step(y, k):
            d0, dh, d1 = dv[2 * k], dv[2 * k + 1], dv[2 * k + 2]
            k1 = f(y, d0)
            k2 = f(y + DT / 2 * k1, dh)
            k3 = f(y + DT / 2 * k2, dh)
            k4 = f(y + DT * k3, d1)
            return y + DT / 6 * (k1 + 2 * k2 + 2 * k3 + k4), None

        y, _ = jax.lax.scan(step, jnp.zeros(2), jnp.arange(n))
        return y[0], jnp.asarray(False)

    prog = Programs.from_functions(0, K, basis, dm.Spline.project_coefficients,
                                   jax.vmap(one), one)
    wd = W * math.sqrt(1 - ZETA ** 2)
    s = np.linspace(0, T, 200_001)
    exact = D * np.trapezoid(np.abs(np.exp(-ZETA * W * s) * np.sin(wd * s) / wd), s)
    return prog, exact


EVALS = 400  # the gradient's 4 starts for about 90 iterations (a screen of 16 first)


def test_gradient_search_finds_the_bang_bang_worst_case(oscillator):
    prog, exact = oscillator
    # a count of evaluations, not a time: the same points whatever the machine's load
    traces = run_methods(prog, time_limit=600.0, max_evals=EVALS, starts=4,
                         methods=("gradient", "random"), batch=16)
    grad, rand = traces["gradient"], traces["random"]
    assert exact * 0.98 <= best_value(grad) <= exact * 1.001
    assert best_value(grad) > 1.3 * best_value(rand)  # sampling is far off in 25 dimensions
    # the worst spline is bang-bang: its knots sit on the bound
    assert np.mean(np.abs(grad.best_z) > 0.99) > 0.7


def _rows(trace):
    return [{k: v for k, v in r.items() if k != "seconds"} for r in trace.history]


def _same(a, b):
    np.testing.assert_equal(a, b)  # (NaN == NaN here)


@pytest.mark.parametrize("method", ["gradient", "cma"])  # cma: replayed from its fitness
def test_search_resumes_losing_nothing_finished(oscillator, tmp_path, method):
    prog, _ = oscillator

    class Stop(Exception):
        pass

    def stop_at(n):
        def progress(_method, tr, limit):
            if tr.iterations == n:
                raise Stop

        return progress

    with pytest.raises(Stop):
        run_methods(prog, time_limit=60.0, starts=2, methods=(method,), out_dir=tmp_path,
                    fingerprint="fp", progress=stop_at(3))
    path = tmp_path / f"state_{method}.npz"
    saved = search.load(path).trace
    assert saved.iterations == 3
    with pytest.raises(dscjax.ConfigError, match=r"caller 'fp' \(now 'other'\)"):
        run_methods(prog, time_limit=60.0, starts=2, methods=(method,), out_dir=tmp_path,
                    fingerprint="other", resume=True)
    resumed = run_methods(prog, time_limit=saved.seconds + 0.2, starts=2, methods=(method,),
                          out_dir=tmp_path, resume=True, fingerprint="fp")[method]
    assert resumed.iterations > 3
    _same(_rows(resumed)[:3], _rows(saved))
    # the same iterates as a run that was never interrupted
    (tmp_path / "fresh").mkdir()
    with pytest.raises(Stop):
        run_methods(prog, time_limit=60.0, starts=2, methods=(method,),
                    out_dir=tmp_path / "fresh", fingerprint="fp",
                    progress=stop_at(resumed.iterations))
    fresh = search.load(tmp_path / "fresh" / f"state_{method}.npz").trace
    _same(_rows(fresh), _rows(resumed))
    np.testing.assert_array_equal(fresh.best_z, resumed.best_z)


@pytest.mark.parametrize("method, evaluations, iterations",
                         [("random", 64, 4),      # batches of 16: 16, 32, 48, 64 >= 50
                          ("gradient", 52, 10)])  # a screening batch of 16, then 4 starts
                                                  # per step: 16 + 9 x 4 = 52 >= 50
def test_max_evals_ends_a_search_after_that_many_evaluations(oscillator, method, evaluations,
                                                             iterations):
    """The count is the batches' sizes summed until it reaches max_evals (gradient: a
    screening batch, then M starts per iteration), whatever time is left; and a count-capped
    search is a function of its seed alone."""
    prog, _ = oscillator
    runs = [run_methods(prog, time_limit=600.0, max_evals=50, starts=4, methods=(method,),
                        batch=16, seed=5)[method] for _ in range(2)]
    for tr in runs:
        assert (tr.evaluations, tr.iterations) == (evaluations, iterations)
    _same(_rows(runs[0]), _rows(runs[1]))
    np.testing.assert_array_equal(runs[0].best_z, runs[1].best_z)


def test_a_count_capped_search_resumes_to_the_uninterrupted_one(oscillator, tmp_path):
    prog, _ = oscillator
    short = run_methods(prog, time_limit=600.0, max_evals=32, methods=("random",), batch=16,
                        out_dir=tmp_path, fingerprint="fp")["random"]
    assert short.evaluations == 32
    longer = run_methods(prog, time_limit=600.0, max_evals=80, methods=("random",), batch=16,
                         out_dir=tmp_path, resume=True, fingerprint="fp")["random"]
    whole = run_methods(prog, time_limit=600.0, max_evals=80, methods=("random",), batch=16,
                        fingerprint="fp")["random"]
    assert longer.evaluations == whole.evaluations == 80
    _same(_rows(longer)[:2], _rows(short))
    _same(_rows(longer), _rows(whole))


# -- the command --------------------------------------------------------------------------------

ARGS = ["worst-case", "--t-final", "1.5", "--range", "hysteresis.alpha=30%",
        "--range", "plant.g[1]=0.7:1.3", "--disturbance", "fourier:2:0.3",
        "--methods", "random", "--batch", "4", "--time-limit", "0.3", "--no-plot", "--quiet"]


@pytest.fixture(scope="module")
def searched(tmp_path_factory):
    out = tmp_path_factory.mktemp("worst")
    assert main([*ARGS, "--out", str(out)]) == 0
    return out


def test_worst_case_outputs_and_exact_reproduction(searched, tmp_path):
    worst = json.loads((searched / "worst.json").read_text())
    assert worst["metric"] == "linf_error_window"
    assert set(worst["parameters"]) == {"hysteresis.alpha", "plant.g[1]"}
    assert worst["disturbance"]["kind"] == "fourier" and worst["disturbance"]["K"] == 2
    assert len(worst["disturbance"]["coefficients"]) == 5
    assert worst["disturbance"]["period"] == 1.5
    with np.load(searched / "worst_trajectory.npz") as z:
        assert z["t_half"].shape == (2 * 1500 + 1,) and z["dbar"].shape == z["t_half"].shape
        assert np.max(np.abs(z["dbar"])) <= 0.3 * (1 + 1e-12)
        # e = y - y_r with the paper's reference y_r = sin t
        np.testing.assert_allclose(z["e"], z["x"][:, 0] - np.sin(z["t"]), rtol=0, atol=1e-12)
        assert z["t"].shape == z["u"].shape == z["w"].shape == z["e"].shape
    assert "| random |" in (searched / "report.md").read_text()
    out = tmp_path / "sim"
    assert main(["simulate", "--config", str(searched / "worst_config.toml"), "--out", str(out),
                 "--no-plot"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["linf_error_window"] == worst["value"]  # exactly
    # a trajectory one can look at: every step of 1.5 s at dt = 1e-3, not the search's two
    # metrics-only points (its save_every = 1500 stays out of the config)
    with np.load(out / "trajectory.npz") as z:
        np.testing.assert_allclose(z["t"], np.arange(1501) * 1e-3, rtol=0, atol=1e-12)
    assert config.from_dict(config.read(searched / "worst_config.toml"))[1].save_every == 1
    # plant.g[1] = 0.7:1.3 reaches below controller.g_min = 1 (Assumption 4), as simulate warns
    assert worst["warnings"] == [
        "Assumption 4 (g_min <= |g_i|) does not hold: controller.g_min = 1 but plant.g has "
        "|g_2| = 0.7 for part of --range plant.g[1] = [0.7, 1.3]; the design's guarantees "
        "(Theorem 1) do not apply there"]


@pytest.mark.parametrize("command", ["simulate", "sweep", "tune", "worst-case", "stability",
                                     "hysteresis"])
def test_every_printed_config_replays_as_a_whole_trajectory(command, tmp_path, capsys):
    """`--print-config` of every command, loaded back by `dscjax simulate --config`: the
    trajectory holds every step of the horizon (another command's own table is its own)."""
    assert main([command, "--print-config", "--t-final", "0.25"]) == 0
    printed = tmp_path / "printed.toml"
    printed.write_text(capsys.readouterr().out)
    out = tmp_path / "sim"
    assert main(["simulate", "--config", str(printed), "--out", str(out), "--no-plot"]) == 0
    with np.load(out / "trajectory.npz") as z:
        np.testing.assert_allclose(z["t"], np.arange(251) * 1e-3, rtol=0, atol=1e-12)


def test_a_box_of_one_dimension_is_searched_and_warned_of(tmp_path, capsys):
    """A box of one dimension, by CMA-ES and random sampling (pycma 4.5 alone fails on it),
    on plant.g[1] across controller.g_min = 1: the Assumption 4 warning on stderr, before the
    search, and in worst.json; the worst point lies in the box."""
    out = tmp_path / "w"
    assert main(["worst-case", "--t-final", "1.5", "--range", "plant.g[1]=0.7:1.3", "--methods",
                 "cma,random", "--batch", "4", "--max-evals", "8", "--time-limit", "600",
                 "--no-plot", "--out", str(out)]) == 0
    err = capsys.readouterr().err.splitlines()
    # each phase says what it does: a method's compilation, then its bar (search seconds,
    # after an iteration that compiled nothing), the re-check
    said = [i for i, line in enumerate(err) if line.startswith(("  cma: compiling",
                                                                "  random: compiling",
                                                                "  re-checking "))]
    assert len(said) == 3 and said == sorted(said)
    cma_bar = [i for i, line in enumerate(err) if line.startswith("  cma      ")]
    random_bar = [i for i, line in enumerate(err) if line.startswith("  random   ")]
    assert cma_bar and all(said[0] < i < said[1] for i in cma_bar)
    assert random_bar and all(said[1] < i < said[2] for i in random_bar)
    # no bar for an iteration that compiled (or loaded) programs: the first line is the
    # second iteration's (CMA-ES: 1 + 4 then 4 evaluations; random: 4 then 4)
    assert err[cma_bar[0]].endswith(", 9 evaluations")
    assert err[random_bar[0]].endswith(", 8 evaluations")
    warning = ("dscjax worst-case: warning: Assumption 4 (g_min <= |g_i|) does not hold: "
               "controller.g_min = 1 but plant.g has |g_2| = 0.7 for part of --range "
               "plant.g[1] = [0.7, 1.3]; the design's guarantees (Theorem 1) do not apply there")
    assert err[1] == warning and err.count(warning) == 1
    worst = json.loads((out / "worst.json").read_text())
    assert worst["warnings"] == [warning.split("warning: ", 1)[1]]
    assert set(worst["methods"]) == {"cma", "random"}
    assert all(m["evaluations"] >= 8 for m in worst["methods"].values())
    assert 0.7 <= worst["parameters"]["plant.g[1]"] <= 1.3


def test_worst_case_refuses_to_mix_runs_and_resumes(searched, capsys):
    assert main([*ARGS, "--out", str(searched)]) == 2
    assert "--resume" in capsys.readouterr().err
    assert main([*ARGS, "--out", str(searched), "--resume", "--seed", "3"]) == 2
    # refused first, in one line naming the old and the new value
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("dscjax worst-case: error: --resume: ")
    assert "was made with other settings (seed 0 (now 3))" in err[0]
    before = json.loads((searched / "worst.json").read_text())["methods"]["random"]
    assert main([*ARGS, "--out", str(searched), "--resume"]) == 0
    after = json.loads((searched / "worst.json").read_text())["methods"]["random"]
    assert after["evaluations"] == before["evaluations"]  # its time was spent: nothing redone


def test_max_evals_option_caps_each_method(tmp_path):
    args = [a for a in ARGS if a not in ("--time-limit", "0.3")]
    assert main([*args, "--time-limit", "600", "--max-evals", "6", "--out", str(tmp_path)]) == 0
    worst = json.loads((tmp_path / "worst.json").read_text())
    assert worst["methods"]["random"]["evaluations"] == 8  # two batches of 4


@pytest.mark.parametrize("extra, field", [
    (["--range", "hysteresis.alpha=2:1"], "lower bound > upper bound"),
    (["--range", "plant.nope=1:2"], "plant.nope"),
    (["--disturbance", "fourier:0:0.5"], "K must be"),
    (["--disturbance", "spline:4:-0.5"], "D must be"),
    (["--disturbance", "spline:1:0.5"], "K must be an integer >= 2 for spline (got 1)"),
    (["--max-evals", "0"], "argument --max-evals: must be an integer >= 1, or \"none\" (got "
                           "'0')"),
])
def test_bad_boxes_give_one_line_and_exit_2(extra, field, tmp_path, capsys):
    code = exit_code(["worst-case", "--t-final", "1", "--out", str(tmp_path / "o"), *extra])
    assert code == 2 and not (tmp_path / "o").exists()
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and field in err and "Traceback" not in err


def test_requirement_margin_metric_matches_a_hand_computed_margin(tmp_path):
    """--metric requirement:envelope maximises max_t (|e(t)| - b(t)); the value reported for
    the worst setup is recomputed here from its trajectory at every step, by NumPy."""
    cfg = tmp_path / "req.toml"
    cfg.write_text("[tuning.requirements.envelope]\nb0 = 0.05\nb_inf = 0.01\ndecay = 0.3\n")
    out = tmp_path / "w"
    assert main(["worst-case", "--config", str(cfg), "--t-final", "1.5",
                 "--metric", "requirement:envelope", "--range", "hysteresis.alpha=30%",
                 "--methods", "random", "--batch", "4", "--time-limit", "0.3", "--no-plot",
                 "--quiet", "--out", str(out)]) == 0
    worst = json.loads((out / "worst.json").read_text())
    assert worst["metric"] == "requirement:envelope"
    setup, options = config.from_dict(config.read(out / "worst_config.toml"))
    traj = dscjax.simulate(setup, options.t_final, options.dt)
    t, e = np.asarray(traj.t), np.asarray(traj.e)
    b = 0.01 + (0.05 - 0.01) * np.exp(-t / 0.3)
    assert worst["value"] == pytest.approx(np.max(np.abs(e) - b), rel=1e-12, abs=1e-15)
    # a requirement the config does not hold: one line naming it
    assert main(["worst-case", "--config", str(cfg), "--t-final", "1",
                 "--metric", "requirement:u_rate", "--range", "hysteresis.alpha=30%",
                 "--out", str(tmp_path / "x")]) == 2
