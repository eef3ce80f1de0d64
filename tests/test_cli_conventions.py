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
