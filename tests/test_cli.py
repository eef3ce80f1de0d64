"""`dscjax simulate`: the files a user gets, --print-config, variants, float32."""

import json
import re

import numpy as np
import pytest

from dscjax.cli.main import main


def test_simulate_writes_trajectory_metrics_and_plot(tmp_path):
    out = tmp_path / "run"
    assert main(["simulate", "--t-final", "2", "--out", str(out)]) == 0
    data = np.load(out / "trajectory.npz")
    n_t = 2001
    assert data["t"].shape == (n_t,) and data["x"].shape == (n_t, 2)
    for key in ("u", "w", "yr"):
        assert data[key].shape == (n_t,)
    assert data["t"][-1] == 2.0 and data["t"][1] == 1e-3
    m = json.loads((out / "metrics.json").read_text())
    for key in ("linf_error", "l2_error", "max_abs_u"):
        assert np.isfinite(m[key])
    assert m["linf_error"] == np.abs(data["x"][:, 0] - data["yr"]).max()
    assert (out / "trajectory.png").stat().st_size > 10_000


def test_print_config_round_trips(tmp_path, capsys):
    assert main(["simulate", "--print-config"]) == 0
    text = capsys.readouterr().out
    cfg = tmp_path / "c.toml"
    cfg.write_text(text.replace("alpha = 1.0", "alpha = 2.0"))
    assert main(["simulate", "--config", str(cfg), "--print-config"]) == 0
    assert "alpha = 2.0" in capsys.readouterr().out


def test_variant_flag(tmp_path):
    out = tmp_path / "v"
    assert main(["simulate", "--t-final", "1", "--variant", "no_dhat", "--save-every", "10",
                 "--no-plot", "--out", str(out)]) == 0
    data = np.load(out / "trajectory.npz")
    assert data["x"].shape == (101, 2) and np.all(data["d_hat"] == 0.0)


def test_diverged_simulation_writes_null_metrics_not_zeros(tmp_path, capsys):
    # dt = 0.02 diverges at t = 0.04 s, before the window [1, 2] s starts
    out = tmp_path / "div"
    assert main(["simulate", "--t-final", "2", "--dt", "0.02", "--no-plot", "--refine", "0",
                 "--out", str(out)]) == 3
    m = json.loads((out / "metrics.json").read_text())
    assert m["diverged"] is True and m["t_diverged"] == pytest.approx(0.04)
    for key in ("linf_error", "linf_error_window", "l2_error_window", "max_abs_u"):
        assert m[key] is None, key
    captured = capsys.readouterr()
    text = captured.out + captured.err
    assert "after t0: 0" not in text and "diverged at t = 0.04 s" in text


def test_tiny_dt_saves_a_bounded_trajectory_and_says_so(tmp_path, capsys):
    out = tmp_path / "tiny"
    assert main(["simulate", "--t-final", "0.1", "--dt", "1e-6", "--no-plot",
                 "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "saving one step in 5 and the last: 20,001 points" in err
    data = np.load(out / "trajectory.npz")
    assert data["t"].shape == (20_001,) and data["t"][1] == pytest.approx(5e-6)
    assert json.loads((out / "metrics.json").read_text())["save_every"] == 5


def test_a_prime_step_count_keeps_about_the_documented_number_of_points(tmp_path, capsys):
    out = tmp_path / "prime"
    assert main(["simulate", "--t-final", "0.20011", "--dt", "1e-5", "--no-plot",
                 "--out", str(out)]) == 0  # 20,011 steps, a prime
    assert "saving one step in 2 and the last: 10,007 points" in capsys.readouterr().err
    t = np.load(out / "trajectory.npz")["t"]
    assert t.shape == (10_007,) and t[-2] == pytest.approx(0.2001) and t[-1] == 0.20011
    assert json.loads((out / "metrics.json").read_text())["save_every"] == 2


def test_a_trajectory_that_cannot_fit_is_refused_before_any_work(tmp_path, capsys,
                                                                  monkeypatch):
    from dscjax import validation

    monkeypatch.setattr(validation, "available_memory", lambda: 100_000)
    out = tmp_path / "big"
    assert main(["simulate", "--t-final", "2", "--save-every", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "simulation.save_every = 1 keeps 2,001 points" in err[0]
    assert "available" in err[0] and "--save-every" in err[0]
    assert not out.exists()


def test_long_runs_show_progress(tmp_path, capsys, monkeypatch, short):
    import dscjax.cli.simulate as cli_simulate

    monkeypatch.setattr(cli_simulate, "PROGRESS_MIN_STEPS", 100)
    assert short == ("--t-final", "0.2")  # 200 steps of 1 ms
    assert main(["simulate", *short, "--no-plot", "--out", str(tmp_path)]) == 0
    err = capsys.readouterr().err
    assert "simulated   0 % (0/200 steps)" in err
    assert "simulated 100 % (200/200 steps)" in err and "t = 0.2 of 0.2 s" in err


def test_assumption_4_violated_is_a_warning_recorded_in_metrics(tmp_path, capsys, short):
    cfg = tmp_path / "g.toml"
    cfg.write_text("[plant]\ng = [0.5, 0.5]\n\n[controller]\ng_min = 1.0\n")
    out = tmp_path / "o"
    assert main(["simulate", "--config", str(cfg), *short, "--no-plot",
                 "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "warning: Assumption 4 (g_min <= |g_i|) does not hold" in err
    warnings = json.loads((out / "metrics.json").read_text())["warnings"]
    assert len(warnings) == 1 and "controller.g_min = 1 but plant.g has |g_1| = 0.5" in warnings[0]


def test_assumption_4_in_a_sweep_range_is_recorded_in_the_summary(tmp_path, capsys):
    out = tmp_path / "s"
    assert main(["sweep", "--range", "plant.g[1]=0.5:1.5", "--samples", "8", "--chunk", "8",
                 "--float64", "--t-final", "0.1", "--worst", "0", "--random", "0", "--no-plot",
                 "--out", str(out)]) == 0
    assert "warning: Assumption 4" in capsys.readouterr().err
    (w,) = json.loads((out / "summary.json").read_text())["warnings"]
    assert "|g_2| = 0.5 for part of sweep.ranges.plant.g[1] = [0.5, 1.5]" in w


def test_trajectory_figure_legend_outside_and_units_on_every_axis(tmp_path, paper_setup):
    import dscjax
    from dscjax.plotting import plot_trajectory

    traj = dscjax.simulate(paper_setup, 1.0, 1e-3, save_every=10)
    fig = plot_trajectory(traj, tmp_path / "t.png", title="DSC (full), n=2")
    assert fig.get_suptitle() == "DSC (full), n=2"  # the run's title, not a panel's
    assert [ax.get_title() for ax in fig.axes] == [
        "states against the reference", "tracking error", "control input", "hysteresis output"]
    assert len(fig.legends) == 1  # one legend for the figure, under the panels
    for ax in fig.axes:
        assert ax.get_legend() is None  # none inside a panel, over the curves
        assert ax.get_ylabel().endswith("[-]"), ax.get_ylabel()  # dimensionless model
    assert all(ax.get_xlabel() == "time $t$ [s]" for ax in fig.axes[2:])


def test_loss_curve_has_one_axis_per_quantity_and_a_labelled_bound(tmp_path):
    from tuning.report_plots import plot_loss_curve

    rows = [dict(iteration=i, loss=1.0 / (i + 1), best_loss=1.0 / (i + 1), accepted=i != 2,
                 linf_window=0.02 / (i + 1), max_abs_u=6.0 + 0.01 * i) for i in range(5)]
    fig = plot_loss_curve(rows, tmp_path / "l.png", u_max=6.13)
    assert len(fig.axes) == 3  # no twin axes
    boxes = {tuple(ax.get_position().bounds) for ax in fig.axes}
    assert len(boxes) == 3
    for ax in fig.axes:
        assert ax.get_legend() is not None and ax.get_ylabel()
    labels = [t.get_text() for t in fig.axes[2].get_legend().get_texts()]
    assert "bound on max|u| (6.13)" in labels


def test_heatmap_states_how_narrow_its_colour_scale_is(tmp_path):
    from dscjax.sweep.plots import plot_heatmap

    rng = np.random.default_rng(0)
    x, y = rng.uniform(0.7, 1.3, 400), rng.uniform(1.0, 1.8, 400)
    err = 0.0221 + 0.0005 * (x - 0.7) / 0.6  # a 2 % spread
    stats = plot_heatmap(x, y, err, np.zeros(400, bool), tmp_path / "h.png",
                         names=("hysteresis.alpha", "hysteresis.lam"), t0=1.0, t_final=20.0,
                         threshold=1.0, nominal_xy=(1.0, 1.4), title="",
                         refined=np.zeros(400, bool))
    assert re.fullmatch(r"colours span 0\.022\d* to 0\.022\d* = 2(\.\d)? % of the median",
                        stats["colour_scale"]), stats["colour_scale"]


def test_the_command_keeps_compiled_programs_in_a_user_cache_unless_told_not_to(tmp_path):
    # in a fresh process: the cache is JAX's global configuration (conftest opts this
    # process out); XDG_CACHE_HOME points the default directory into tmp_path
    import os
    import subprocess
    import sys

    code = ("import jax, contextlib, io\n"
            "from dscjax.cli.main import main\n"
            "for argv in (['--no-compilation-cache', 'simulate', '--print-config'],\n"
            "             ['simulate', '--print-config']):\n"
            "    with contextlib.redirect_stdout(io.StringIO()):\n"
            "        assert main(argv) == 0\n"
            "    print(repr(jax.config.jax_compilation_cache_dir),\n"
            "          jax.config.jax_compilation_cache_max_size)\n"
            "jax.config.update('jax_persistent_cache_min_compile_time_secs', 0)\n"
            "jax.jit(lambda x: x + 1)(1.0)  # written to the cache, under its lock\n")
    env = {k: v for k, v in os.environ.items() if k not in ("DSCJAX_NO_COMPILATION_CACHE",
           "JAX_COMPILATION_CACHE_DIR", "JAX_COMPILATION_CACHE_MAX_SIZE")}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    cache = tmp_path / "dscjax" / "jax"
    cache.mkdir(parents=True)
    (cache / "old-cache").write_bytes(b"a program written without a size")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    (off, off_size), (on, on_size) = (line.split() for line in out.stdout.splitlines())
    assert off in ("None", "''") and off_size == "-1"  # JAX's defaults: no cache, no limit
    # 2**30 bytes (1 GiB, the README's figure): a cache with a size is one JAX locks
    assert on == repr(str(cache)) and on_size == str(2**30)
    # JAX's own marks of a locked cache with a size: its lock file, an access time per entry;
    # the program found there without one got the oldest (8 zero bytes), or the write of the
    # new one would have failed
    written = {p.name.rsplit("-", 1)[-1] for p in cache.iterdir()}
    assert written == {".lockfile", "cache", "atime"}, written
    assert len(list(cache.glob("*-atime"))) == 2 and (cache / "old-atime").read_bytes() == bytes(8)
    assert "Error writing" not in out.stderr, out.stderr


# -- issue 38 item 2: effort in simulate's verdict --------------------------------------------

# High gains behind a one-sample input delay at 1 kHz: a limit cycle of u (chattering) that
# tracks well; the paper's gains in the same loop (one compiled program: the gains are traced).
CHATTER_K, PAPER_K = "[30.0, 5.0]", "[10.0, 0.45]"
SAMPLED_DELAY = ["--sample-time", "0.001", "--delay", "1", "--t-final", "3", "--no-plot"]


@pytest.fixture(scope="module")
def delayed_runs(tmp_path_factory):
    """{name: (trajectory.npz, metrics.json, stdout)} of the two loops."""
    import contextlib
    import io

    out = {}
    for name, k in (("chatter", CHATTER_K), ("paper", PAPER_K)):
        d = tmp_path_factory.mktemp(name)
        cfg = d / "gains.toml"
        cfg.write_text(f"[controller]\nk = {k}\n")
        text = io.StringIO()
        with contextlib.redirect_stdout(text), contextlib.redirect_stderr(io.StringIO()):
            assert main(["simulate", "--config", str(cfg), *SAMPLED_DELAY,
                         "--out", str(d / "o")]) == 0
        out[name] = (dict(np.load(d / "o" / "trajectory.npz")),
                     json.loads((d / "o" / "metrics.json").read_text()), text.getvalue())
    return out


def _effort_numpy(t, u, t0, tau=0.02):
    """max|u|, TV(u) on t >= t0 and TV(u) / TV(u low-passed) there, from the saved samples:
    u through v_k = v_(k-1) + (1 - exp(-dt/tau)) (u_k - v_(k-1)), v_0 = u_0 (docs/numerics.md)."""
    v = np.empty_like(u)
    v[0] = u[0]
    a = -np.expm1(-np.diff(t) / tau)
    for k in range(1, len(u)):
        v[k] = v[k - 1] + a[k - 1] * (u[k] - v[k - 1])
    steps = t[:-1] >= t0  # both ends of the step in the window
    tv = np.abs(np.diff(u))[steps].sum()
    return np.abs(u[t >= t0]).max(), tv, tv / np.abs(np.diff(v))[steps].sum()


EFFORT = re.compile(r"effort on \[1, 3\] s: max\|u\| ([\d.,e+-]+), TV\(u\) ([\d.,e+-]+), "
                    r"(CHATTERING|no chattering) \(index ([\d.,e+-]+) (>|<=) 1\.5")


@pytest.mark.parametrize(("name", "verdict"), [("chatter", "CHATTERING"),
                                               ("paper", "no chattering")])
def test_simulate_says_the_effort_and_whether_the_loop_chatters(delayed_runs, name, verdict):
    data, m, out = delayed_runs[name]
    assert np.all(np.diff(data["t"]) > 0) and data["t"].shape == (3001,)  # every step saved
    u_max, tv, index = _effort_numpy(data["t"], data["u"], 1.0)
    assert m["max_abs_u_window"] == pytest.approx(u_max, rel=1e-12)
    assert m["tv_u_window"] == pytest.approx(tv, rel=1e-9)
    assert m["chattering_index"] == pytest.approx(index, rel=1e-9)
    line = next(line for line in out.splitlines() if "L-inf error on [1, 3] s" in line)
    found = EFFORT.search(line)
    assert found is not None, line
    shown = [float(found[i].replace(",", "")) for i in (1, 2, 4)]
    assert shown == pytest.approx([u_max, tv, index], rel=5e-4)  # 4 digits, or whole
    assert found[3] == verdict and found[5] == (">" if verdict == "CHATTERING" else "<=")
    if verdict == "CHATTERING":  # the limit cycle: tracks, yet u switches at the sample rate
        assert line.endswith("; docs/numerics.md)") and index > 10
        assert m["linf_error_window"] < 0.01
    else:
        assert index < 1.1


def test_simulate_float32_is_rechecked_in_float64_and_says_what_it_cannot_be_trusted_with(
        tmp_path, capsys):
    """Issue 38 item 7a: the chattering loop in float32; the reference is the same loop (the
    float32 numbers) run here in float64."""
    import dscjax
    from dscjax.params import cast

    cfg = tmp_path / "gains.toml"
    cfg.write_text(f"[controller]\nk = {CHATTER_K}\n")
    out = tmp_path / "f32"
    assert main(["simulate", "--config", str(cfg), *SAMPLED_DELAY, "--float32",
                 "--out", str(out)]) == 0
    err = capsys.readouterr().err
    m = json.loads((out / "metrics.json").read_text())
    assert m["dtype"] == "float32" and np.load(out / "trajectory.npz")["x"].dtype == np.float32
    setup = dscjax.params.set(dscjax.paper_example(), "controller.k", np.array([30.0, 5.0]))
    ref = dscjax.simulate(cast(cast(setup, np.float32), np.float64), throw=False,
                          spec=dscjax.RunSpec.make(3.0, 1e-3, sample_time=1e-3, delay=1,
                                                   save_every=3000))
    check = m["float32_check"]
    untrusted = []
    for name, value in ref.metrics.items():
        r = float(value)
        assert check["float64"][name] == pytest.approx(r, rel=1e-12), name
        diff = abs(m[name] - r) / abs(r)
        assert check["rel_diff"][name] == pytest.approx(diff, rel=1e-9, abs=1e-15), name
        if diff > 1e-3:
            untrusted.append(name)
    assert "tv_u_window" in untrusted and "max_abs_u" not in untrusted  # the limit cycle's
    assert sorted(check["untrusted"]) == sorted(untrusted) and check["rtol"] == 1e-3
    worst = max(check["rel_diff"][n] for n in check["untrusted"])
    line = (f"float32 cannot be trusted with {', '.join(check['untrusted'])}: they differ from "
            f"float64 by up to {100 * worst:.3g} % (tolerance 0.1 %); rerun without --float32")
    assert f"dscjax simulate: warning: {line}\n" in err and m["warnings"] == [line]
