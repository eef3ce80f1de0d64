"""What every subcommand does alike (issue 9): unwritable output directories, help defaults
that match the code's, interrupt and resume, stdout against stderr, --version."""

import pytest

from dscjax.cli.main import main

COMMANDS = ("simulate", "sweep", "tune", "reproduce")


def _one_line_error(capsys, code):
    captured = capsys.readouterr()
    assert code == 2, captured.err
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in captured.err, captured.err
    return lines[0]


@pytest.mark.parametrize("command", COMMANDS)
@pytest.mark.parametrize("where", ["under_a_file", "proc"])
def test_unwritable_out_is_one_line_and_exit_2(command, where, tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("")
    out = str(afile / "sub") if where == "under_a_file" else "/proc/dscjax-test/x"
    line = _one_line_error(capsys, main([command, "--out", out]))
    assert f"--out {out!r}" in line and "cannot write" in line


def _help(command) -> dict[str, str]:
    """{option: its help text, whitespace collapsed, %-formatted as --help prints it}."""
    import argparse
    import importlib

    sub = argparse.ArgumentParser(prog="dscjax").add_subparsers()
    p = importlib.import_module(f"dscjax.cli.{command}").add_parser(sub)
    fmt = p._get_formatter()
    return {a.option_strings[-1]: " ".join(fmt._expand_help(a).split())
            for a in p._actions if a.option_strings and a.help}


def _expected_defaults():
    import dataclasses

    from dscjax import reproduce
    from dscjax.config import SimOptions
    from dscjax.sweep import SweepSettings
    from tuning.config import TuningConfig

    sim, sw, tu = SimOptions(), SweepSettings(), TuningConfig()
    horizon = {"--t-final": f"{sim.t_final:g}", "--dt": f"{sim.dt:g}"}
    assert dataclasses.is_dataclass(tu.optimizer)
    return {
        "simulate": horizon,
        "tune": horizon | {
            "--lr": f"{tu.optimizer.learning_rate:g}", "--steps": str(tu.optimizer.steps),
            "--time-limit": f"{tu.optimizer.time_limit:g}", "--batch": str(tu.robust.batch),
            "--aggregate": tu.robust.aggregate, "--cvar-level": f"{tu.robust.cvar_level:g}",
            "--seed": str(tu.robust.seed), "--heldout": str(tu.heldout.batch),
            "--gradient": tu.optimizer.gradient},
        "sweep": horizon | {
            "--samples": str(sw.samples), "--seed": str(sw.seed), "--worst": str(sw.worst),
            "--random": str(sw.random), "--method": sw.method, "--parallel": sw.parallel,
            "--float64": sw.dtype},
        "reproduce": {"--t-final": f"{reproduce.T_FINAL:g}", "--dt": f"{reproduce.DT:g}",
                      "--dpi": str(reproduce.DPI),
                      "--repeats": str(reproduce.COMPLEXITY_REPEATS)},
    }


@pytest.mark.parametrize("command", COMMANDS)
def test_help_states_the_defaults_the_code_uses(command):
    helps = _help(command)
    for option, value in _expected_defaults()[command].items():
        assert f"default {value}" in helps[option], (option, helps[option])


@pytest.mark.parametrize("argv, wanted, unwanted", [
    (["sweep", "--t0", "30"], "simulation.window_start must be in [0, t_final) = [0, 20)",
     "alpha"),
    (["reproduce", "--complexity", "--orders", "8-2"], "did you mean 2-8?", "n >= 2"),
    (["sweep", "--range", "hysteresis.alpha=0.5-1.5"], "(got 'hysteresis.alpha=0.5-1.5')",
     "['"),
    (["sweep", "--grid", "hysteresis.alpha=0.5:1.5"], "(got 'hysteresis.alpha=0.5:1.5')",
     "['"),
])
def test_messages_blame_what_is_wrong(argv, wanted, unwanted, tmp_path, capsys):
    line = _one_line_error(capsys, main([*argv, "--out", str(tmp_path / "o")]))
    assert wanted in line and unwanted not in line, line


def test_params_set_with_an_unknown_path_raises_config_error():
    import dscjax

    setup = dscjax.paper_example()
    with pytest.raises(dscjax.ConfigError, match=r"no parameter 'controller\.kk'.*allowed: k,"):
        dscjax.params.set(setup, "controller.kk", 1.0)
    with pytest.raises(KeyError):  # and still a KeyError for code that catches lookups
        dscjax.params.get(setup, "plant.nope")
