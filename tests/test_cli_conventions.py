"""What every subcommand does alike (issue 9): unwritable output directories, help defaults
that match the code's, interrupt and resume, stdout against stderr, --version."""

import errno
import os
import signal
import threading

import pytest
from commands import exit_code

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
    from dscjax.cli.main import _available_commands, build_parser

    p = build_parser(_available_commands()).subcommands[command]
    fmt = p._get_formatter()
    return {a.option_strings[-1]: " ".join(fmt._expand_help(a).split())
            for a in p._actions if a.option_strings and a.help}


def _expected_defaults():
    import dataclasses

    from dscjax import reproduce
    from dscjax.runspec import RunSpec
    from dscjax.sweep import SweepSettings
    from tuning.config import TuningConfig

    sim, sw, tu = RunSpec.make(), SweepSettings(), TuningConfig()
    horizon = {"--t-final": f"{sim.t_final:g}", "--dt": f"{sim.dt:g}"}
    assert dataclasses.is_dataclass(tu.optimizer)
    return {
        "simulate": horizon,
        "tune": horizon | {
            "--lr": f"{tu.optimizer.learning_rate:g}",
            "--steps": "none" if tu.optimizer.steps is None else str(tu.optimizer.steps),
            "--time-limit": f"{tu.optimizer.time_limit:g}", "--batch": str(tu.robust.batch),
            "--aggregate": tu.robust.aggregate.name, "--cvar-level": f"{tu.robust.cvar_level:g}",
            "--seed": str(tu.robust.seed), "--heldout": str(tu.heldout.batch),
            "--gradient": tu.optimizer.gradient.name},
        "sweep": horizon | {
            "--samples": str(sw.samples), "--seed": str(sw.seed), "--worst": str(sw.worst),
            "--random": str(sw.random), "--method": sw.method.name,
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
    (["sweep", "--window-start", "30"], "--window-start must be in [0, t_final) = [0, 20)",
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


@pytest.mark.parametrize("argv, missing", [
    (["sweep", "--resume"], "sweep.json"),
    (["tune", "--resume"], "checkpoint.json"),
    (["reproduce", "--complexity", "--resume"], "complexity_rows.json"),
    (["worst-case", "--range", "hysteresis.alpha=30%", "--resume"], "worst_case.json"),
    # the missing run is named first, even where the settings given are refused too
    (["tune", "--tuning", "BAD", "--resume"], "checkpoint.json"),
    (["tune", "--tuning", "BAD", "--adversarial", "1", "--resume"], "adversarial.json"),
])
def test_resuming_nothing_is_an_error_naming_the_directory(argv, missing, tmp_path, capsys):
    out, bad = tmp_path / "new", tmp_path / "bad.toml"
    bad.write_text('[tuning]\nparams = ["controller.nope"]\n')  # an unknown parameter
    argv = [str(bad) if a == "BAD" else a for a in argv]
    line = _one_line_error(capsys, main([*argv, "--out", str(out)]))
    assert f"nothing to resume in {out} ({missing} is missing)" in line, line


def test_reproduce_resume_needs_complexity(tmp_path, capsys):
    line = _one_line_error(capsys, main(["reproduce", "--resume", "--out", str(tmp_path)]))
    assert "--complexity" in line


def _interrupted(capsys, argv):
    import shlex

    assert main(argv) == 130
    err = capsys.readouterr().err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"dscjax {argv[0]}: interrupted; "), err
    command = last.split("continue with: ", 1)[1] if "continue with: " in last else None
    return last, command and shlex.split(command)


def test_sweep_interrupt_prints_the_resume_command_that_finishes_it(tmp_path, capsys,
                                                                     monkeypatch):
    from dscjax.progress import Progress

    def stop(*args):  # Ctrl-C after the first round
        raise KeyboardInterrupt

    out = tmp_path / "s"
    # the block shape and horizon of tests/test_sweep.py: one compiled program serves both
    argv = ["sweep", "--samples", "16", "--chunk", "8", "--t-final", "0.5", "--float64",
            "--worst", "0", "--random", "0", "--no-plot", "--out", str(out)]
    monkeypatch.setattr(Progress, "update_to", stop)
    last, command = _interrupted(capsys, argv)
    assert "1 finished block(s) are kept" in last
    assert command == ["dscjax", *argv, "--resume"]
    monkeypatch.undo()
    assert main(command[1:]) == 0
    assert (out / "results.npz").exists()


def test_tune_interrupt_prints_the_resume_command(tmp_path, capsys, monkeypatch):
    import json

    import tuning.runner

    out = tmp_path / "t"

    def interrupted_run(problem, out_dir, **kw):  # as the real loop does on Ctrl-C
        (out_dir / "checkpoint.json").write_text(json.dumps({"iteration": 3, "best_loss": 0.5}))
        raise KeyboardInterrupt

    monkeypatch.setattr(tuning.runner, "run", interrupted_run)
    argv = ["tune", "--t-final", "0.2", "--heldout", "0", "--overwrite", "--out", str(out)]
    last, command = _interrupted(capsys, argv)
    assert "checkpoint (iteration 3, best loss 0.5) is kept" in last
    assert command == ["dscjax", "tune", "--t-final", "0.2", "--heldout", "0", "--out",
                       str(out), "--resume"]


def test_simulate_interrupt_says_what_to_run(tmp_path, capsys, monkeypatch):
    import importlib

    def stop(*a, **k):
        raise KeyboardInterrupt

    # the module, not the function dscjax.simulate that dscjax/__init__.py exports
    monkeypatch.setattr(importlib.import_module("dscjax.simulate"), "simulate", stop)
    argv = ["simulate", "--t-final", "0.5", "--out", str(tmp_path)]
    last, command = _interrupted(capsys, argv)
    assert command is None
    assert last.endswith(f"run the same command again: dscjax simulate --t-final 0.5 --out "
                         f"{tmp_path}")


def test_reproduce_interrupt_says_what_to_run(tmp_path, capsys, monkeypatch):
    import dscjax.reproduce

    def stop(*a, **k):
        (tmp_path / "c" / "complexity_rows.json").write_text("{}")
        raise KeyboardInterrupt

    monkeypatch.setattr(dscjax.reproduce, "family_loops", stop)
    argv = ["reproduce", "--out", str(tmp_path / "p")]
    (tmp_path / "c").mkdir()
    last, command = _interrupted(capsys, argv)
    assert command is None and last.endswith(f"run the same command again: dscjax "
                                             f"reproduce --out {tmp_path / 'p'}")
    (tmp_path / "c" / "complexity_rows.json").unlink()  # (a fresh --out: stop writes it)
    argv = ["reproduce", "--complexity", "--out", str(tmp_path / "c")]
    last, command = _interrupted(capsys, argv)
    assert command == ["dscjax", *argv, "--resume"]


@pytest.mark.parametrize(("argv", "wanted"), [
    (["tune", "--effort-bounds", "everywhere"],
     "dscjax tune: error: argument --effort-bounds: must be one of 'nominal', 'per_plant' (got "
     "'everywhere')"),
    (["tune", "--method", "cma_grad"],  # a removed method
     "dscjax tune: error: argument --method: must be one of 'cma', 'adam' (got 'cma_grad')"),
    (["sweep", "--samples", "many"],
     "dscjax sweep: error: argument --samples: must be an integer >= 1 (got 'many')"),
    (["sweep", "--samples", "1.5"],
     "dscjax sweep: error: argument --samples: must be an integer >= 1 (got '1.5')"),
    (["hysteresis", "--bogus", "1"], "dscjax hysteresis: error: unrecognized arguments: "
     "--bogus 1"),
    (["stability", "--print-config", "--samples", "3"], "dscjax stability: error: "
     "unrecognized arguments: --samples 3"),
    (["frobnicate"], "dscjax: error: argument COMMAND: invalid choice: 'frobnicate'"),
])
def test_argparse_errors_are_one_line_and_exit_2(argv, wanted, capsys):
    with pytest.raises(SystemExit) as stop:
        main(argv)
    err = capsys.readouterr().err
    assert stop.value.code == 2 and len(err.strip().splitlines()) == 1
    assert err.strip().startswith(wanted) and "usage" not in err


def test_version_comes_from_one_place(capsys):
    import importlib.metadata
    import tomllib
    from pathlib import Path

    import dscjax

    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    # the version, then what JAX sees (tests/test_device.py)
    assert capsys.readouterr().out.splitlines()[0] == f"dscjax {dscjax.__version__}"
    project = tomllib.loads((Path(__file__).parents[1] / "pyproject.toml").read_text())
    assert "version" not in project["project"] and "version" in project["project"]["dynamic"]
    assert project["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "dscjax.__version__"}
    assert importlib.metadata.version("dscjax") == dscjax.__version__


def test_results_on_stdout_diagnostics_on_stderr(tmp_path, capsys):
    import numpy as np

    assert main(["simulate", "--t-final", "2", "--no-plot", "--out", str(tmp_path)]) == 0
    captured = capsys.readouterr()
    assert "wrote" in captured.out and "L-inf error" in captured.out
    assert "dscjax simulate: DSC (full), n=2," in captured.err
    assert "wrote" not in captured.err and "n=2" not in captured.out
    # the headline leads with the windowed error and says the window (issue 32): over the
    # whole run it is the initial error |x1(0) - yr(0)| = 0.08 of the paper's example
    with np.load(tmp_path / "trajectory.npz") as z:
        assert np.all(np.diff(z["t"]) > 0) and len(z["t"]) == 2001  # every step saved
        window = float(np.max(np.abs(z["e"][z["t"] >= 1.0 - 1e-12])))
        assert abs(z["e"][0]) == pytest.approx(0.08)
    headline = captured.out.strip().splitlines()[-1]
    assert headline.startswith(f"  L-inf error on [1, 2] s {window:.4g} (over the whole run "
                               f"0.08, from the initial error)"), headline


def test_print_config_lists_window_start(capsys):
    assert main(["simulate", "--print-config"]) == 0
    out = capsys.readouterr().out
    assert "# window_start = 1.0 " in out and "# save_every = 1 " in out


# -- issue 32: the output path, repeated options, names as typed, signals, headlines ---------

ALL_COMMANDS = {"simulate": [], "sweep": [], "tune": [], "reproduce": [], "stability": [],
                "hysteresis": [], "worst-case": ["--range", "hysteresis.alpha=30%"]}


@pytest.mark.parametrize("command", ALL_COMMANDS)
@pytest.mark.parametrize("where", ["name_too_long", "a_file_above", "the_out_is_a_file",
                                   "empty"])
def test_an_out_the_system_refuses_is_one_line_naming_it_before_any_work(
        command, where, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    afile = tmp_path / "afile"
    afile.write_text("kept")
    out, reason = {
        "name_too_long": (str(tmp_path / ("x" * 291) / "sub"),
                          os.strerror(errno.ENAMETOOLONG)),
        "a_file_above": (str(afile / "sub"), os.strerror(errno.ENOTDIR)),
        "the_out_is_a_file": (str(afile), "it is a file, not a directory"),
        "empty": ("", "an empty path"),
    }[where]
    line = _one_line_error(capsys, main([command, *ALL_COMMANDS[command], "--out", out]))
    assert line.startswith(f"dscjax {command}: error: --out {out!r}: "), line
    assert reason in line, line
    assert sorted(os.listdir(tmp_path)) == ["afile"] and afile.read_text() == "kept"


def test_a_read_only_file_system_is_named_as_such(tmp_path, monkeypatch):
    from dscjax import files

    class ReadOnly:
        f_flag = os.ST_RDONLY

    # what a read-only mount answers (root may write anywhere else, so the fault is staged)
    monkeypatch.setattr(os, "access", lambda path, mode: False)
    monkeypatch.setattr(os, "statvfs", lambda path: ReadOnly())
    assert files.out_problem(tmp_path / "new") == f"{os.strerror(errno.EROFS)}: {tmp_path}"
    assert files.out_problem(tmp_path) == os.strerror(errno.EROFS)


def test_every_single_valued_option_of_every_command_is_refused_when_repeated(capsys):
    import argparse

    from dscjax.cli.common import Once
    from dscjax.cli.main import _available_commands, build_parser

    parser = build_parser(_available_commands())
    for name, sub in parser.subcommands.items():
        for action in sub._actions:
            if type(action) is not argparse._HelpAction and action.option_strings:
                takes_one = action.nargs is None and not isinstance(
                    action, argparse._StoreConstAction | argparse._AppendAction)
                assert isinstance(action, Once) == takes_one, (name, action.option_strings)
    for command, extra in ALL_COMMANDS.items():
        with pytest.raises(SystemExit) as stop:  # argparse's error, before the command runs
            main([command, *extra, "--out", "a", "--out", "b"])
        line = _one_line_error(capsys, stop.value.code)
        assert line == (f"dscjax {command}: error: argument --out: given twice (first 'a', "
                        f"then 'b'); give it once")


def test_noise_takes_one_number_or_one_per_state_as_its_help_says(capsys):
    argv = ["simulate", "--sample-time", "0.01", "--print-config"]
    assert main([*argv, "--noise", "0.01,0.02"]) == 0
    assert "noise = [0.01, 0.02]" in capsys.readouterr().out
    assert main([*argv, "--noise", "0.03"]) == 0
    assert "noise = 0.03" in capsys.readouterr().out
    line = _one_line_error(capsys, main([*argv, "--noise", "0.01,0.02,0.03"]))
    assert line == ("dscjax simulate: error: --noise must be one number or one per state of "
                    "the plant, 2 numbers (got 3)")
    assert "separated by commas" in _help("simulate")["--noise"]


@pytest.mark.parametrize(("argv", "wanted"), [
    (["sweep", "--grid", "hysteresis.alpha=0.7:1.3:0"],
     "--grid hysteresis.alpha: the number of grid points must be >= 2 (got 0)"),
    (["sweep", "--threshold", "-1"], "argument --threshold: must be a finite number > 0, or "
                                     "\"none\" (got '-1')"),
    (["sweep", "--range", "plant.g[5]=0.8:1.2"],
     "--range: index 5 of 'plant.g' is out of range (it has 2 elements, indices 0..1)"),
    (["tune", "--cvar-level", "2"], "argument --cvar-level: must be a finite number in (0, 1] "
                                    "(got '2')"),
    (["tune", "--adversarial", "1", "--disturbance", "sine"],
     "--disturbance must be fourier:K:D or spline:K:D (got 'sine')"),
])
def test_an_error_names_the_option_as_typed(argv, wanted, tmp_path, capsys):
    line = _one_line_error(capsys, exit_code([*argv, "--out", str(tmp_path / "o")]))
    assert line.startswith(f"dscjax {argv[0]}: error: {wanted}"), line


def test_an_error_from_a_config_names_its_key(tmp_path, capsys):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[sweep]\nthreshold = -1\n")
    line = _one_line_error(capsys, main(["sweep", "--config", str(cfg), "--out",
                                         str(tmp_path / "o")]))
    assert line == ("dscjax sweep: error: sweep.threshold must be a finite number > 0, or "
                    "\"none\" (got -1)")


@pytest.mark.parametrize(("command", "theirs", "other", "shared"), [
    ("reproduce", ("sweep.json", "summary.json"), "sweep", "summary.json"),
    ("sweep", ("fig1_hysteresis.png", "summary.json"), "reproduce", "summary.json"),
])
def test_a_command_never_replaces_another_commands_files(command, theirs, other, shared,
                                                          tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    for name in theirs:
        (out / name).write_text(f"{other}'s")
    for again in ([], ["--overwrite"]):
        line = _one_line_error(capsys, main([command, *again, "--out", str(out)]))
        assert line == (f"dscjax {command}: error: --out {str(out)!r} holds the results of "
                        f"another command, which this one would replace (`dscjax {other}`: "
                        f"{shared}); give another --out")
        assert {p.name: p.read_text() for p in out.iterdir()} == {
            name: f"{other}'s" for name in theirs}


def test_an_interrupted_reproduce_names_the_figures_it_kept(tmp_path, capsys, monkeypatch):
    import dscjax.reproduce

    out = tmp_path / "p"

    def stop(*a, **k):  # a figure is finished, then Ctrl-C
        (out / "fig1_hysteresis.png").write_bytes(b"png")
        raise KeyboardInterrupt

    monkeypatch.setattr(dscjax.reproduce, "family_loops", stop)
    assert main(["reproduce", "--out", str(out)]) == 130
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last == (f"dscjax reproduce: interrupted; the 1 file(s) finished before it are kept "
                    f"in {out} (fig1_hysteresis.png), the rest is not written; run the same "
                    f"command again: dscjax reproduce --out {out} --overwrite")
    assert (out / "fig1_hysteresis.png").read_bytes() == b"png"


@pytest.mark.parametrize(("signum", "code", "name"), [(signal.SIGTERM, 143, "SIGTERM"),
                                                       (signal.SIGHUP, 129, "SIGHUP")])
def test_sigterm_and_sighup_are_handled_as_ctrl_c(signum, code, name, tmp_path, capsys,
                                                  monkeypatch, request):
    import dscjax.cli.common
    from dscjax.progress import Abort, Terminated, critical, handle_interrupts

    def send():
        signal.pthread_kill(threading.main_thread().ident, signum)

    # the disposition a terminal gives (under nohup SIGHUP is ignored, and stays ignored: the
    # next test), restored after
    previous = signal.signal(signum, signal.SIG_DFL)
    request.addfinalizer(lambda: signal.signal(signum, previous))
    before = signal.getsignal(signum)
    with handle_interrupts():  # inside a step: deferred to its end, with its number
        with pytest.raises(Terminated) as info, critical():
            send()
            finished = True
        assert finished and info.value.signum == signum
        with pytest.raises(Abort) as info, critical():  # twice: at once
            send()
            send()
        assert info.value.signum == signum
    assert signal.getsignal(signum) is before

    def stop(args, **_):
        send()

    monkeypatch.setattr(dscjax.cli.common, "load_setup", stop)
    out = tmp_path / "s"
    assert main(["simulate", "--out", str(out)]) == code
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith(f"dscjax simulate: interrupted by {name}; nothing is kept"), last


def test_an_ignored_sighup_stays_ignored():
    from dscjax.progress import handle_interrupts

    before = signal.signal(signal.SIGHUP, signal.SIG_IGN)  # as under nohup
    try:
        with handle_interrupts():
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, before)


def test_reproduce_summary_md_leads_with_the_windowed_error_and_says_the_window():
    from dscjax.reproduce.markdown import summary_markdown
    from dscjax.reproduce.runs import ESTIMATES, METRIC_FIELDS

    values = {k: float(i + 1) for i, k in enumerate(METRIC_FIELDS)}  # distinct, to find each
    run = {**values, "diverged": False,
           "estimates": {k: {"min": 0.0, "max": 1.0, "final": 0.5} for k in ESTIMATES}}
    text = summary_markdown({"t_final": 20.0, "dt": 1e-3, "window_start": 1.0, "claims": [],
                             "runs": {"dsc": run}, "interpretations": [], "figures": {}})
    lines = text.splitlines()
    head = lines[lines.index("## Runs") + 2]
    row = next(line for line in lines if line.startswith("| dsc | "))
    cells = dict(zip(head.strip("|").split(" | "), row.strip("|").split(" | "), strict=True))
    assert list(cells)[1].strip() == "L∞ e on [1, 20] s"
    assert float(cells["L∞ e on [1, 20] s"]) == values["linf_error_after_1s"]
    assert float(cells["L∞ e on [0, T] (the initial error)"]) == values["linf_error"]


def test_a_phase_that_lasts_says_what_it_does_and_a_short_one_says_nothing():
    import io
    import time

    from dscjax.progress import Phase, Progress

    log = io.StringIO()
    with Phase("  the held-out check", after_s=0.0, every_s=60.0, file=log):
        for _ in range(6000):  # the work lasts until the phase has said what it does
            if log.getvalue():
                break
            time.sleep(0.01)
    lines = log.getvalue().splitlines()
    assert lines[0].startswith("  the held-out check ... (00:00 elapsed)"), lines
    assert lines[-1].startswith("  the held-out check: done in ") and len(lines) == 2, lines
    quiet = io.StringIO()
    with Phase("  quick", after_s=30.0, file=quiet):
        pass
    assert quiet.getvalue() == ""
    # no ETA from a unit timed by nothing (the one that compiled), one once a unit was timed
    bar = Progress(10, desc="  tune", unit="generation", initial=1, file=log, every_s=0.0)
    bar.update_to(1)
    assert "ETA" not in log.getvalue().splitlines()[-1]
    bar.update_to(2)
    assert "ETA" in log.getvalue().splitlines()[-1]


def test_a_command_without_a_hint_of_its_own_says_what_to_run_again(tmp_path, capsys,
                                                                    monkeypatch):
    import dscjax.cli.common

    def stop(args):
        signal.pthread_kill(threading.main_thread().ident, signal.SIGTERM)

    monkeypatch.setattr(dscjax.cli.common, "load_setup", stop)
    out = tmp_path / "st"
    assert main(["stability", "--out", str(out)]) == 143
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last == (f"dscjax stability: interrupted by SIGTERM; nothing is kept; run the same "
                    f"command again: dscjax stability --out {out}")
