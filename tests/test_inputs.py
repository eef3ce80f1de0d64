"""What a new user types (issue 25): absurd horizons and work that cannot finish, duplicate
keys, configs of another format, the whole config of every command, count options, degenerate
waveforms. Each bad input is one line on stderr naming the option or field, exit 2, and
nothing written."""

import json
import tomllib

import numpy as np
import pytest
from commands import exit_code

from dscjax import config, validation
from dscjax.cli.main import main
from dscjax.validation import ConfigError

COMMANDS_WITH_EXAMPLE = ("simulate", "stability", "hysteresis", "sweep", "tune", "worst-case")
# what each command needs besides the horizon to get as far as its checks
EXTRA = {"worst-case": ["--range", "plant.g[1]=30%"]}


def _refused(capsys, argv, out):
    """Run argv (with --out `out`); the one stderr line of a refusal, after checking that the
    exit code is 2 and that nothing was created."""
    code = exit_code([*argv, "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert not out.exists()
    return err


# -- defect class 2: absurd horizons and steps, work that cannot finish --------------------------


@pytest.mark.parametrize("command", [*COMMANDS_WITH_EXAMPLE, "reproduce"])
def test_a_horizon_beyond_the_step_counter_is_refused_by_its_option(command, tmp_path, capsys):
    err = _refused(capsys, [command, "--t-final", "1e9", *EXTRA.get(command, [])],
                   tmp_path / "o")
    assert err.startswith(f"dscjax {command}: error: --t-final / ")
    assert ("= 1e+12 steps, more than the 2,147,483,647 the integrator's step counter holds "
            "(got t_final=1e+09, dt=0.001); use a shorter --t-final") in err


@pytest.mark.parametrize("command", [*COMMANDS_WITH_EXAMPLE, "reproduce"])
@pytest.mark.parametrize("value", ["inf", "nan", "-1"])
def test_a_non_finite_horizon_on_the_command_line_is_refused_by_its_option(command, value,
                                                                         tmp_path, capsys):
    err = _refused(capsys, [command, "--t-final", value, *EXTRA.get(command, [])],
                   tmp_path / "o")
    assert err == (f"dscjax {command}: error: argument --t-final: must be a finite number > 0 "
                   f"(got '{value}')")


@pytest.mark.parametrize("command", COMMANDS_WITH_EXAMPLE)
@pytest.mark.parametrize(("name", "text", "wanted"), [
    ("c.toml", "[simulation]\nt_final = inf\n", "simulation.t_final must be a finite number > 0 "
     "(got inf)"),
    ("c.toml", "[simulation]\ndt = nan\n", "simulation.dt must be a finite number > 0 (got nan)"),
    ("c.json", '{"simulation": {"t_final": Infinity}}', "simulation.t_final must be a finite "
     "number > 0 (got inf)"),
])
def test_a_non_finite_horizon_in_a_config_is_refused_by_its_field(command, name, text, wanted,
                                                                  tmp_path, capsys):
    cfg = tmp_path / name
    cfg.write_text(text)
    err = _refused(capsys, [command, "--config", str(cfg), *EXTRA.get(command, [])],
                   tmp_path / "o")
    assert err == f"dscjax {command}: error: {wanted}"


@pytest.mark.parametrize(("command", "section", "more"), [
    ("worst-case", "worst", []), ("sweep", "sweep", []), ("tune", "tuning", []),
    # the requirement a worst-case search maximises, shown by --print-config
    ("worst-case", "tuning", ["--metric", "requirement:envelope", "--print-config"])])
def test_a_commands_own_section_that_is_not_a_table_is_refused_by_its_name(command, section,
                                                                          more, tmp_path,
                                                                          capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text(f"{section} = 1\n")
    err = _refused(capsys, [command, "--config", str(cfg), *EXTRA.get(command, []), *more],
                   tmp_path / "o")
    assert err == f"dscjax {command}: error: '{section}' must be a table ([{section}])"


@pytest.mark.parametrize("command", ["simulate", "sweep", "tune"])
def test_a_non_finite_model_number_in_a_config_is_refused_by_its_field(command, tmp_path,
                                                                      capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[controller]\nk = [nan, 1.0]\n")
    err = _refused(capsys, [command, "--config", str(cfg)], tmp_path / "o")
    assert err.endswith("controller.k must be finite (got [nan, 1])")


def test_whole_steps_names_the_fields_and_never_overflows():
    assert validation.whole_steps(20.0, 1e-3) == 20_000
    with pytest.raises(ConfigError, match=r"^--t-final must be a finite number > 0 \(got inf\)$"):
        validation.whole_steps(float("inf"), 1e-3, "--t-final", "--dt")
    with pytest.raises(ConfigError, match=r"^simulation.dt must be a finite number > 0 "
                                          r"\(got nan\)$"):
        validation.whole_steps(1.0, float("nan"))
    for t_final, dt in ((1e300, 1e-300), (1.0, 5e-324), (2.0**31, 1.0)):
        with pytest.raises(ConfigError, match="the integrator's step counter holds"):
            validation.whole_steps(t_final, dt)
    assert validation.whole_steps(2.0**31 - 1, 1.0) == validation.MAX_STEPS


@pytest.fixture
def two_cores(monkeypatch):
    """The optimistic batch speed of a 2-core CPU, whatever machine runs the test."""
    monkeypatch.setattr(validation, "batch_speed", lambda: 2 * validation.MEMBER_STEPS_PER_S_CORE)


def test_a_sweep_that_cannot_end_within_a_day_is_refused_with_the_estimate(two_cores,
                                                                           monkeypatch,
                                                                           tmp_path, capsys):
    # the time estimate, not the memory check (its table needs 16.4 GiB), whatever the machine
    monkeypatch.setattr(validation, "available_memory", lambda: 2**40)
    err = _refused(capsys, ["sweep", "--samples", "1e8", "--t-final", "200"], tmp_path / "o")
    assert err == ("dscjax sweep: error: 100,000,000 samples of T = 200 s at dt = 0.001 s "
                   "(200,000 steps) needs at least 27.8 h (2,200,000 consecutive RK4 steps, "
                   "2e+13 in all, at speeds above any dscjax reaches), more than the limit of "
                   "24 h; use fewer --samples, a shorter --t-final or a larger --dt")


def test_work_that_cannot_fit_in_memory_is_refused_with_the_estimate(monkeypatch, tmp_path,
                                                                     capsys):
    monkeypatch.setattr(validation, "available_memory", lambda: 2**30)
    err = _refused(capsys, ["sweep", "--samples", "1e8", "--t-final", "0.1"], tmp_path / "o")
    assert err.endswith("the results table (100,000,000 samples x 22 columns) needs about "
                        "16.4 GiB of memory, more than the 1 GiB available; use fewer "
                        "--samples, a shorter --t-final or a larger --dt")
    err = _refused(capsys, ["hysteresis", "--t-final", "1e5"], tmp_path / "o")
    assert "t, u and w at every step (2 amplitude(s)) needs about 3.73 GiB of memory, more " \
           "than the 1 GiB available" in err


def test_one_generation_or_iteration_beyond_the_time_limit_is_refused(two_cores, tmp_path,
                                                                      capsys):
    err = _refused(capsys, ["tune", "--t-final", "2000", "--time-limit", "0.01"], tmp_path / "o")
    # 64 candidates x 2e6 steps over 2 cores at 1e8 steps/s each (dscjax.validation's bound)
    assert "one generation (64 candidates x 1 plant(s)) of T = 2000 s at dt = 0.001 s " \
           "(2,000,000 steps) needs at least 0.64 s" in err
    assert err.endswith("more than --time-limit 0.01 s; use a shorter --t-final or a larger "
                        "--dt, or a larger --time-limit")
    err = _refused(capsys, ["worst-case", "--range", "hysteresis.alpha=30%", "--t-final",
                            "2000", "--time-limit", "0.01"], tmp_path / "o")
    assert "one search iteration of T = 2000 s at dt = 0.001 s (2,000,000 steps) needs at " \
           "least" in err and "more than --time-limit 0.01 s" in err


def test_check_work_passes_work_that_can_finish(two_cores, monkeypatch):
    monkeypatch.setattr(validation, "available_memory", lambda: 2**30)
    day = validation.TIME_LIMIT_S
    validation.check_work(validation.Work(steps=day * validation.STEPS_PER_S, memory=2**30),
                          what="x", fix="y")
    with pytest.raises(ConfigError, match=r"^x needs at least 24.2 h .* more than the limit "
                                          r"of 24 h; y$"):
        validation.check_work(validation.Work(steps=1.01 * day * validation.STEPS_PER_S),
                              what="x", fix="y")
    with pytest.raises(ConfigError, match=r"^x: it needs about 1 GiB of memory, more than "
                                          r"the 1 GiB available; y$"):
        validation.check_work(validation.Work(memory=2**30 + 1, memory_what="it"), what="x",
                              fix="y")


def test_loop_sizes_are_each_setups_own_whatever_was_sized_before():
    # the floats of the loop's state (m) and of a saved point (k) and a float's bytes, which
    # the memory estimates are made of, counted from the initial state and the observation of
    # one vector-field call; setups of another dtype and order sized in turn (the sizes are
    # kept per structure and leaf type)
    import math

    import jax

    import dscjax
    from dscjax.cli.common import loop_sizes
    from dscjax.closed_loop import initial_state, prepared, vector_field

    def floats(tree):
        return sum(math.prod(np.shape(a)) for a in jax.tree.leaves(tree))

    paper = dscjax.paper_example()
    for setup in (paper, dscjax.cast(paper, np.float32), dscjax.order_n_example(4), paper):
        ready = prepared(setup)
        state = initial_state(ready)
        _, observation = jax.eval_shape(lambda s=state, r=ready: vector_field(0.0, s, r))
        m = floats(state)
        assert loop_sizes(setup) == (m, m + floats(observation),
                                     jax.tree.leaves(state)[0].dtype.itemsize)


# -- defect class 5: duplicate keys ----------------------------------------------------------------


@pytest.mark.parametrize(("name", "text", "key"), [
    ("c.toml", "[controller]\nk = [1.0, 2.0]\nk = [3.0, 1.0]\n", "controller.k"),
    ("c.toml", "[controller]\nk = [1.0, 2.0]\n\n[controller]\neta = [0.1, 0.1]\n", "controller"),
    ("c.toml", '[sweep.ranges]\n"hysteresis.alpha" = "30%"\n"hysteresis.alpha" = "20%"\n',
     "sweep.ranges.hysteresis.alpha"),
    ("c.toml", "[tuning]\noptimizer.steps = 3\noptimizer.steps = 4\n", "tuning.optimizer.steps"),
    ("c.toml", '["a)b"]\nx = 1\n\n["a)b"]\ny = 2\n', "a)b"),  # a key with a parenthesis
    ("c.json", '{"controller": {"k": [1.0, 2.0], "k": [3.0, 1.0]}}', "controller.k"),
    ("c.json", '{"plant": {"g": [1.0, 1.0]}, "plant": {"x0": [0.0, 0.0]}}', "plant"),
])
def test_a_key_given_twice_is_refused_with_its_path(name, text, key, tmp_path, capsys):
    cfg = tmp_path / name
    cfg.write_text(text)
    with pytest.raises(ConfigError) as info:
        config.read(cfg)
    assert str(info.value) == f"duplicate key '{key}' in {cfg}"
    command = "sweep" if "sweep" in text else "tune" if "tuning" in text else "simulate"
    err = _refused(capsys, [command, "--config", str(cfg)], tmp_path / "o")
    assert err == f"dscjax {command}: error: duplicate key '{key}' in {cfg}"


@pytest.mark.parametrize("name", ["c.yaml", "c.yml", "c.ini", "config"])
def test_a_config_of_another_format_is_named_as_such(name, tmp_path, capsys):
    cfg = tmp_path / name
    cfg.write_text("controller:\n  k: [10.0, 0.45]\n")
    err = _refused(capsys, ["simulate", "--config", str(cfg)], tmp_path / "o")
    assert f"{cfg}: configs are TOML (.toml) or JSON (.json) (got " in err
    assert "not valid TOML" not in err


# -- defect class 7: the whole config of every command, help that is true -------------------------


@pytest.mark.parametrize("command", COMMANDS_WITH_EXAMPLE)
def test_every_command_with_example_prints_its_whole_config_and_loads_it_back(command,
                                                                            tmp_path, capsys):
    argv = [command, "--example", "pi", *EXTRA.get(command, []), "--print-config"]
    assert main(argv) == 0
    text = capsys.readouterr().out
    tables = [line for line in text.splitlines() if line.startswith("[")]
    assert tables[:5] == ["[simulation]", "[plant]", "[hysteresis]", "[controller]",
                          "[reference]"]
    own = {"sweep": "[sweep]", "tune": "[tuning]"}
    if command in own:
        assert own[command] in tables
    cfg = tmp_path / "printed.toml"
    cfg.write_text(text)
    # laid over the default example it is the same config: it holds the whole of it
    assert main([command, "--config", str(cfg), *EXTRA.get(command, []),
                 "--print-config"]) == 0
    assert capsys.readouterr().out == text
    assert tomllib.loads(text)["hysteresis"]["kind"] == "pi"


@pytest.mark.parametrize("command", COMMANDS_WITH_EXAMPLE)
def test_the_example_help_promises_only_what_the_command_takes(command, capsys):
    with pytest.raises(SystemExit):
        main([command, "--help"])
    helps = " ".join(capsys.readouterr().out.split())
    assert "--print-config shows it whole" in helps and "--print-config " in helps


# -- defect class 8: counts, waveforms, printed numbers, banners, colours ------------------------


def test_a_count_written_as_an_integral_float_is_accepted(capsys):
    assert main(["sweep", "--samples", "1e5", "--worst", "2.0", "--print-config"]) == 0
    sweep = tomllib.loads(capsys.readouterr().out)["sweep"]
    assert sweep["samples"] == 100_000 and sweep["worst"] == 2


@pytest.mark.parametrize(("text", "wanted"), [
    ("fourier:4:0", "--disturbance: the bound D must be a finite number > 0"),
    ("spline:4:0", "--disturbance: the bound D must be a finite number > 0"),
    ("spline:1:0.5", "--disturbance: K must be an integer >= 2 for spline (got 1)"),
    ("fourier:0:0.5", "--disturbance: K must be an integer >= 1 for fourier (got 0)"),
])
def test_a_waveform_with_nothing_to_search_is_refused(text, wanted, tmp_path, capsys):
    from dscjax.worst import DisturbanceSpec

    with pytest.raises(ConfigError, match=wanted.replace("(", r"\(").replace(")", r"\)")):
        DisturbanceSpec.parse(text)
    err = _refused(capsys, ["worst-case", "--disturbance", text], tmp_path / "o")
    assert wanted in err
    assert DisturbanceSpec.parse("spline:2:0.5").size == 2


def test_printed_numbers_are_the_shortest_decimals_of_their_dtype(capsys):
    assert main(["simulate", "--print-config", "--float32"]) == 0
    plant = tomllib.loads(capsys.readouterr().out)["plant"]
    assert plant["theta"] == [0.1, 0.0] and plant["x0"] == [0.08, 0.1]
    assert main(["simulate", "--example", "pi", "--print-config"]) == 0
    r = tomllib.loads(capsys.readouterr().out)["hysteresis"]["r"]
    assert r == [0.2, 0.4, 0.6, 0.8, 1.0, 1.2, 1.4, 1.6, 1.8, 2.0]
    assert main(["sweep", "--print-config"]) == 0  # in the sweep's dtype
    ranges = tomllib.loads(capsys.readouterr().out)["sweep"]["ranges"]
    assert ranges["hysteresis.psi"] == [0.0735, 0.1365]
    assert validation.shortest(np.float32(0.1), np.float32) == 0.1
    assert validation.shortest(0.1 + 0.2, np.float64) == 0.30000000000000004  # float64: exact


@pytest.mark.parametrize(("argv", "wanted"), [
    (["worst-case", "--range", "hysteresis.alpha=30%", "--methods", "gradient,annealing"],
     "--methods must be one of 'gradient', 'random', 'cma' (got 'annealing')"),
    (["worst-case", "--range", "hysteresis.alpha=30%", "--gradient-coarsening", "7"],
     "--gradient-coarsening 7 must divide the number of steps t_final/dt = 20000"),
])
def test_a_bad_setting_is_reported_before_any_banner(argv, wanted, tmp_path, capsys):
    err = _refused(capsys, argv, tmp_path / "o")
    assert err == f"dscjax {argv[0]}: error: {wanted}"


def test_worst_vs_nominal_has_one_colour_per_case_and_a_legend_in_each_panel(tmp_path):
    from types import SimpleNamespace

    from dscjax.worst import report as worst_report

    t = np.linspace(0.0, 1.0, 11)
    nominal = SimpleNamespace(t=t, e=0.1 * t, u=t)
    worst = SimpleNamespace(t=t, e=0.2 * t, u=2 * t)
    result = SimpleNamespace(problem=SimpleNamespace(metric="linf_error_window"), value=0.2,
                             nominal_value=0.1)
    fig = worst_report._plot_worst(tmp_path / "w.png", worst, nominal, result)
    for ax in fig.axes:
        assert [line.get_label() for line in ax.lines] == ["nominal", "worst case"]
        assert ax.get_legend() is not None
    colours = [[line.get_color() for line in ax.lines] for ax in fig.axes]
    assert colours[0] == colours[1] and colours[0][0] != colours[0][1]


def test_progress_counts_read_one_generation_and_two_generations():
    import io

    from dscjax.progress import Progress

    lines = io.StringIO()
    bar = Progress(None, desc="  tune", unit="generation", file=lines, every_s=0.0)
    bar.update_to(1, "sigma 0.3")
    bar.update_to(2, "sigma 0.2")
    first, second = lines.getvalue().splitlines()
    assert first.startswith("  tune 1 generation, ") and first.endswith("; sigma 0.3")
    assert second.startswith("  tune 2 generations, ")


def test_the_cma_progress_line_shows_sigma_not_lr():
    from tuning.checkpoint import format_progress

    row = {"loss": 0.5, "accepted": True, "best_loss": 0.4, "terms": ["linf"], "linf": 0.4,
           "linf_window": 0.01, "max_abs_u": 6.0, "lr": 0.25}
    assert format_progress(row, "sigma").endswith("max|u| 6  sigma 0.25")
    assert format_progress(row).endswith("max|u| 6  lr 0.25")


def test_a_json_config_with_every_key_once_still_loads(tmp_path):
    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps({"controller": {"k": [7.0, 0.5]}, "plant": {"g": [1.0, 1.0]}}))
    setup, _ = config.from_dict(config.read(cfg))
    assert np.asarray(setup.controller.k).tolist() == [7.0, 0.5]


def test_refinement_stops_at_the_step_counter():
    import dataclasses

    from dscjax.integrate import solver
    from dscjax.runspec import RunSpec
    from dscjax.simulate import counted_levels

    def levels(n_steps, name="rk4"):
        return counted_levels(dataclasses.replace(RunSpec.make(refine=6), n_steps=n_steps,
                                                  solver=solver(name)))

    assert levels(20_000) == 6  # ETDRK4 at dt, dt/2, ..., dt/32
    assert levels(validation.MAX_STEPS // 4) == 3  # dt/4 still counts
    assert levels(validation.MAX_STEPS // 4, "etdrk4") == 2
    assert levels(validation.MAX_STEPS) == 1  # ETDRK4 at dt only


# -- issue 32: invalid TOML says where; a number in quotes says it is a string ----------------


@pytest.mark.parametrize(("text", "where"), [
    ("[controller]\nk = 1 2\n", "line 2, column 7: not valid TOML: Expected newline"),
    ("# a comment\n\n[plant]\ng = [1.0, 1.0\n", "line 4 (the end of the file): not valid TOML: "
     "Unclosed array"),
    ("[controller\nk = 1\n", "line 1, column 12: not valid TOML"),
])
def test_invalid_toml_names_the_file_and_the_line(text, where, tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text(text)
    err = _refused(capsys, ["simulate", "--config", str(cfg)], tmp_path / "o")
    assert err.startswith(f"dscjax simulate: error: {cfg}, {where}"), err


@pytest.mark.parametrize(("command", "text", "wanted"), [
    ("simulate", '[controller]\nk = "10"\n', "controller.k must be a number or a list of "
     "numbers, not text in quotes (got a string, '10')"),
    ("simulate", '[controller]\nk = [10, "2"]\n', "controller.k must be a number or a list of "
     "numbers, not text in quotes (controller.k[1] is a string, '2')"),
    ("simulate", '[simulation]\ndt = "0.001"\n', "simulation.dt must be a finite number > 0 "
     "(got a string, '0.001')"),
    ("simulate", '[simulation]\nsave_every = "2"\n', "simulation.save_every must be an integer "
     ">= 1, or \"none\" (got a string, '2')"),
    ("sweep", '[sweep]\nseed = "1"\n', "sweep.seed must be an integer >= 0 (got a string, '1')"),
    ("sweep", '[sweep]\nthreshold = "0.1"\n', "sweep.threshold must be a finite number > 0, or "
     "\"none\" (got a string, '0.1')"),
])
def test_a_number_in_quotes_is_named_a_string(command, text, wanted, tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text(text)
    err = _refused(capsys, [command, "--config", str(cfg)], tmp_path / "o")
    assert err == f"dscjax {command}: error: {wanted}"


# -- issue 38 item 7e: a directory given as a config file ------------------------------------


@pytest.mark.parametrize("name", ["results", "results.toml"])  # (a suffix makes no file)
@pytest.mark.parametrize("argv", [["simulate", "--config"], ["sweep", "--config"],
                                  ["sweep", "--gains"], ["sensitivity", "--config"]])
def test_a_directory_given_as_a_config_is_named_as_such(argv, name, tmp_path, capsys):
    folder = tmp_path / name
    folder.mkdir()
    err = _refused(capsys, [*argv, str(folder)], tmp_path / "o")
    assert err == (f"dscjax {argv[0]}: error: {argv[1]}: {str(folder)!r} is a directory (give "
                   f"a .toml or .json file)")
