"""What every command does with its --out and its long work (issue 25): one rule for an --out
that holds results (refused, --overwrite, --resume), one process per --out (a lock naming the
holder; a dead holder never blocks), a full disk (one line, exit 4, no temporary file, a
--resume that finishes), and Ctrl-C at any point of a tuning generation (the state saved is a
whole one and the hint resumes it; a second Ctrl-C stops at once without saving).

Faults are real: SIGINT sent to this process from inside the work, a lock held by another
process, writes past RLIMIT_FSIZE in a subprocess (EFBIG, SIGXFSZ ignored).
"""

import csv
import dataclasses
import json
import os
import shlex
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import dscjax
import tuning
import tuning.search
from dscjax import files, search
from dscjax.cli.main import main
from dscjax.progress import Abort, critical, handle_interrupts
from dscjax.search.cma import ReplayCMA
from tuning.runner import run

DSCJAX = str(Path(sys.executable).parent / "dscjax")  # the console script, as a user runs it

# every command with small sizes, and one file it writes (an earlier run's result)
COMMANDS = {
    "simulate": (["--t-final", "0.2", "--no-plot"], "metrics.json"),
    "stability": (["--t-final", "0.2", "--no-plot"], "stability.json"),
    "hysteresis": (["--t-final", "0.5"], "loop.npz"),
    "reproduce": (["--t-final", "0.2"], "summary.md"),
    "tune": (["--t-final", "0.2", "--heldout", "0", "--no-plot"], "checkpoint.json"),
    "sweep": (["--samples", "8", "--t-final", "0.2", "--no-plot"], "chunks/chunk_000000.npz"),
    "worst-case": (["--t-final", "0.2", "--range", "hysteresis.alpha=30%", "--no-plot"],
                   "worst.json"),
    "export": (["--sample-time", "0.001"], "dsc_controller.c"),
}
RESUMABLE = ("tune", "sweep", "worst-case")


def _err(capsys) -> list[str]:
    return capsys.readouterr().err.strip().splitlines()


def _listing(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*"))
            if p.is_file()}


def _iterations(history: Path) -> list[int]:
    """The iteration column of a tuning run's history.csv."""
    with open(history, newline="") as f:
        return [int(r["iteration"]) for r in csv.DictReader(f)]


def _no_temporary_files(out: Path) -> None:
    assert not list(out.rglob(".*.tmp")), list(out.rglob(".*.tmp"))


# -- the one rule of --out -------------------------------------------------------------------


@pytest.mark.parametrize("command", COMMANDS)
def test_an_out_holding_results_is_refused_in_one_line_and_left_as_it_was(command, tmp_path,
                                                                          capsys):
    args, result = COMMANDS[command]
    out = tmp_path / "out"
    (out / result).parent.mkdir(parents=True)
    (out / result).write_bytes(b"an earlier run")
    (out / "notes.txt").write_text("mine")
    before = _listing(out)
    assert main([command, *args, "--out", str(out)]) == 2
    how = ("--resume to continue them, --overwrite to start afresh (deleting only them)"
           if command in RESUMABLE else "--overwrite to replace them")
    shown = result.split("/")[0] + ("/" if "/" in result else "")
    assert _err(capsys)[-1] == (f"dscjax {command}: error: --out {str(out)!r} already holds "
                                f"files this command writes ({shown}); {how}, or give "
                                f"another --out")
    assert _listing(out) == before and not (out / files.LOCK).exists()


@pytest.mark.parametrize("adversarial", [[], ["--adversarial", "1"]])
def test_tune_refuses_its_out_before_it_runs_the_loop(adversarial, tmp_path, capsys,
                                                      monkeypatch):
    from tuning import runner

    def ran(*a, **k):
        raise AssertionError("the start scales ran (and compiled the loop) before --out")

    monkeypatch.setattr(runner, "start_scales", ran)
    out = tmp_path / "a-file"
    out.write_text("mine")
    assert main(["tune", *COMMANDS["tune"][0], *adversarial, "--out", str(out)]) == 2
    err = _err(capsys)
    assert len(err) == 1 and err[0].startswith(f"dscjax tune: error: --out {str(out)!r}: "
                                               f"cannot write the output there"), err
    assert out.read_text() == "mine"


@pytest.mark.parametrize("command", COMMANDS)
def test_overwrite_deletes_what_the_command_writes_and_nothing_else(command, tmp_path):
    import importlib

    module = importlib.import_module(f"dscjax.cli.{command.replace('-', '_')}")
    outputs = module.OUTPUTS
    for pattern in outputs.files:
        (tmp_path / pattern.replace("*", "x")).write_text("old")
    for pattern in outputs.folders:
        (tmp_path / pattern.replace("*", "1")).mkdir()
        (tmp_path / pattern.replace("*", "1") / "inside.npz").write_text("old")
    mine = ["notes.txt", "results.csv", "my_round", "figure.svg"]
    for name in mine:
        (tmp_path / name).write_text("mine")
    assert len(outputs.found(tmp_path)) == len(outputs.files) + len(outputs.folders)
    outputs.remove(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(mine)


def test_a_new_empty_or_unrelated_out_is_used_and_overwrite_starts_afresh(tmp_path, capsys):
    out = tmp_path / "s"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    argv = ["simulate", "--t-final", "0.2", "--out", str(out)]
    assert main(argv) == 0
    assert {"trajectory.npz", "metrics.json", "trajectory.png"} <= set(os.listdir(out))
    # --overwrite: the earlier figure goes (this run writes none), the user's file stays
    assert main([*argv, "--no-plot", "--overwrite"]) == 0
    assert sorted(os.listdir(out)) == ["metrics.json", "notes.txt", "trajectory.npz"]
    capsys.readouterr()


def test_a_refused_run_leaves_no_new_out_behind(tmp_path, capsys, monkeypatch):
    import importlib

    out = tmp_path / "new" / "deeper"
    with pytest.raises(SystemExit) as stop:  # argparse's own refusal, before any file
        main(["simulate", "--t-final", "-1", "--out", str(out)])
    assert stop.value.code == 2
    assert not (tmp_path / "new").exists()

    def refuse(*a, **k):  # an error found after --out was made (the library's own checks)
        raise dscjax.ConfigError("simulation.dt: refused for the test")

    monkeypatch.setattr(importlib.import_module("dscjax.simulate"), "simulate", refuse)
    assert main(["simulate", "--t-final", "0.2", "--out", str(out)]) == 2
    assert _err(capsys)[-1].endswith("refused for the test")
    assert not (tmp_path / "new").exists()


# -- one process per --out -------------------------------------------------------------------


def _hold(out: Path) -> subprocess.Popen:
    """A process holding the lock of `out` (as a running `dscjax sweep --out out` does)."""
    code = ("import sys, time\nfrom dscjax import files\n"
            "with files.lock_out(sys.argv[1], argv=['dscjax', 'sweep', '--out', sys.argv[1]]):\n"
            "    print('locked', flush=True)\n    time.sleep(600)\n")
    holder = subprocess.Popen([sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE,
                              text=True)
    assert holder.stdout.readline().strip() == "locked"
    return holder


@pytest.fixture(scope="module")
def held(tmp_path_factory):
    out = tmp_path_factory.mktemp("held")
    holder = _hold(out)
    yield out, holder
    holder.kill()
    holder.wait()


@pytest.mark.parametrize("command", COMMANDS)
def test_a_second_process_on_the_same_out_is_refused_naming_the_first(command, held, capsys):
    out, holder = held
    info = json.loads((out / files.LOCK).read_text())
    args, _ = COMMANDS[command]
    assert main([command, *args, "--out", str(out)]) == 2
    assert _err(capsys)[-1] == (
        f"dscjax {command}: error: --out {str(out)!r} is in use by another dscjax process "
        f"(pid {holder.pid} on host {socket.gethostname()}, since {info['started']}: dscjax "
        f"sweep --out {out}); wait for it to end, or give another --out")
    assert sorted(os.listdir(out)) == [files.LOCK]  # nothing written, the lock is the holder's


def test_a_dead_holder_never_blocks(tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    holder = _hold(out)
    holder.send_signal(signal.SIGKILL)  # as a crash would: no clean-up
    holder.wait()
    assert (out / files.LOCK).exists()  # its stale file stays; the kernel dropped the lock
    assert main(["simulate", "--t-final", "0.2", "--no-plot", "--out", str(out)]) == 0
    assert sorted(os.listdir(out)) == ["metrics.json", "trajectory.npz"]  # (lock removed)
    capsys.readouterr()


# -- a full disk ------------------------------------------------------------------------------


# runs ARGV with files limited to LIMIT bytes; SIGXFSZ ignored, so that a write past it fails
# with EFBIG instead of killing the process (both survive the exec; no fork of this process,
# whose JAX threads a fork would copy)
LIMITED = ("import os, resource, signal, sys\n"
           "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
           "resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[1]),) * 2)\n"
           "os.execv(sys.argv[2], sys.argv[2:])\n")


def _run_hint(command: str) -> None:
    """The command a hint prints, run to its end: the console script's arguments through
    `main` in this process, whose programs the test's earlier runs compiled already."""
    script, *argv = shlex.split(command)
    assert script == DSCJAX
    assert main(argv) == 0


def _full_disk_then_resume(argv, out: Path, limit: int, written: str, kept) -> None:
    """Run `dscjax ARGV` with files limited to `limit` bytes: exit 4, one line naming
    `written` and the command to continue, no temporary file, `kept(out)` holds; then that
    command, unlimited, finishes."""
    # without the suite's compilation cache: JAX's write of a program past the limit would
    # leave it there cut short, for every later process to read
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    proc = subprocess.run([sys.executable, "-c", LIMITED, str(limit), DSCJAX, *argv],
                          capture_output=True, text=True,
                          env=env | {"DSCJAX_NO_COMPILATION_CACHE": "1"})
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 4, proc.stderr[-3000:]
    command = shlex.join([DSCJAX, *argv, "--resume"])
    assert err[-1] == (f"dscjax {argv[0]}: error: no space left on the device writing "
                       f"{out / written} (File too large); free space and rerun with: "
                       f"{command}")
    assert "Traceback" not in proc.stderr
    _no_temporary_files(out)
    kept(out)
    _run_hint(command)


def test_a_sweep_whose_disk_fills_says_so_in_one_line_and_resumes(tmp_path):
    # each chunk of 8 samples fits under the limit, results.npz of 32 does not
    out = tmp_path / "sweep"
    argv = ["sweep", "--samples", "32", "--chunk", "8", "--t-final", "0.2", "--float64",
            "--worst", "0", "--random", "0", "--no-plot", "--quiet", "--out", str(out)]
    def kept(out):  # every block, whole
        assert all(files.read_npz(out / "chunks" / f"chunk_{b:06d}.npz") for b in range(4))

    _full_disk_then_resume(argv, out, 8000, "results.npz", kept)
    with np.load(out / "results.npz") as z:
        assert z["sample"].tolist() == list(range(32))


def test_a_tuning_run_whose_disk_fills_says_so_in_one_line_and_resumes(tmp_path):
    # a checkpoint every generation: search.npz grows by a row per generation and passes the
    # limit after the first few checkpoints were written whole
    out = tmp_path / "tune"
    cfg = tmp_path / "every.toml"
    cfg.write_text("[tuning.optimizer]\nsave_interval = 1\n")
    argv = ["tune", "--tuning", str(cfg), "--t-final", "0.2", "--heldout", "0", "--steps",
            "12", "--no-plot", "--quiet", "--out", str(out)]
    def kept(out):  # the last checkpoint written whole, part of the way
        assert 1 <= json.loads((out / "checkpoint.json").read_text())["iteration"] < 12

    # the limit: half-way between the state file after the first generation and after the
    # whole run (it grows by a history row per generation), so that some generations are
    # saved whole before a write fails
    ref, first = tmp_path / "ref", tmp_path / "first"
    assert main([*argv[:-1], str(ref)]) == 0
    one = [a if a != "12" else "1" for a in argv[:-1]]
    assert main([*one, str(first)]) == 0
    limit = ((ref / "search.npz").stat().st_size + (first / "search.npz").stat().st_size) // 2
    _full_disk_then_resume(argv, out, limit, "search.npz", kept)
    report = json.loads((out / "report.json").read_text())
    assert report["run"]["iterations"] == 12
    assert _iterations(out / "history.csv") == list(range(12))


# -- Ctrl-C at every point of a tuning generation ---------------------------------------------

STEPS = 4  # generations of the uninterrupted run; the interrupts land in generation 1


# search_problem: conftest's (cma over STEPS generations, each saved)


@pytest.fixture(scope="module")
def straight(search_problem, tmp_path_factory):
    assert search_problem.cfg.optimizer.steps == STEPS
    out = tmp_path_factory.mktemp("straight")
    return run(search_problem, out), out


def _ctrl_c(times: int = 1) -> None:
    """Ctrl-C: SIGINT, `times` presses, each handled before the next (sent to the main
    thread, which runs Python's signal handlers, so that it is taken at once)."""
    for _ in range(times):
        signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)


def _in_generation(monkeypatch, where: str, generation: int, times: int = 1):
    """Press Ctrl-C once, inside `generation` at `where`; returns the progress callback that
    counts the generations."""
    state = {"generation": 0, "pressed": False}

    def counting(row):
        state["generation"] = row["iteration"] + 1

    def wrap(owner, name, before=True, when=lambda *a: True):
        original = getattr(owner, name)

        def wrapped(*a, **k):
            hit = (state["generation"] == generation and when(*a)
                   and not state["pressed"])
            state["pressed"] |= hit
            if hit and before:
                _ctrl_c(times)
            result = original(*a, **k)
            if hit and not before:
                _ctrl_c(times)
            return result
        monkeypatch.setattr(owner, name, wrapped)

    if where == "ask":  # a population asked, not told yet
        wrap(ReplayCMA, "ask", before=False)
    elif where == "simulate":
        wrap(tuning.search.TuneProblem, "evaluate")
    elif where == "gradient":  # adam's exact gradient
        wrap(tuning.search.TuneProblem, "value_and_grad")
    elif where == "tell":  # told, before the incumbent and the counters
        wrap(ReplayCMA, "tell", before=False)
    elif where == "checkpoint":  # inside the write of the state file
        wrap(files, "atomic_write", when=lambda path, data: Path(path).name == "search.npz")
    return counting


def _same_search(out, other):
    """The two runs' final states, read back from their state files: equal bitwise."""
    a, b = search.load(out / "search.npz"), search.load(other / "search.npz")
    np.testing.assert_array_equal(a.trace.best_z, b.trace.best_z)
    assert a.trace.evaluations == b.trace.evaluations
    assert a.arrays.keys() == b.arrays.keys()
    for key, value in b.arrays.items():
        np.testing.assert_array_equal(a.arrays[key], value, err_msg=key)


@pytest.mark.parametrize("where", ["ask", "simulate", "tell", "checkpoint",
                                   "progress"])
def test_ctrl_c_anywhere_in_a_generation_saves_a_whole_state_that_resumes_exactly(
        where, search_problem, straight, tmp_path, monkeypatch):
    out = tmp_path / "run"
    counting = _in_generation(monkeypatch, where, generation=1)

    def progress(row):
        counting(row)
        if where == "progress" and row["iteration"] == 1:
            _ctrl_c()  # between two generations: not deferred

    with handle_interrupts(), pytest.raises(KeyboardInterrupt):
        run(search_problem, out, progress=progress)
    monkeypatch.undo()
    meta = json.loads((out / "checkpoint.json").read_text())
    assert (meta["iteration"], meta["stop_reason"]) == (2, "interrupted")  # generation 1 done
    _no_temporary_files(out)
    again = run(search_problem, out, resume=True)
    assert again.resumed_from == 2 and again.trace.iterations == STEPS
    _same_search(out, straight[1])


def test_a_second_ctrl_c_stops_at_once_keeping_the_last_checkpoint(search_problem, straight,
                                                                    tmp_path, monkeypatch,
                                                                    capsys):
    out = tmp_path / "run"
    counting = _in_generation(monkeypatch, "simulate", generation=2, times=2)
    with handle_interrupts(), pytest.raises(Abort):
        run(search_problem, out, progress=counting)
    monkeypatch.undo()
    assert "Ctrl-C again stops at once, without saving" in capsys.readouterr().err
    meta = json.loads((out / "checkpoint.json").read_text())
    assert (meta["iteration"], meta["stop_reason"]) == (2, None)  # generation 1's, as it was
    run(search_problem, out, resume=True)
    _same_search(out, straight[1])


def test_adam_finishes_its_iteration_and_checkpoint_on_ctrl_c(search_problem, tmp_path,
                                                              monkeypatch):
    cfg = search_problem.cfg  # its objective, by adam (forward-mode gradients)
    problem = dataclasses.replace(search_problem, cfg=dataclasses.replace(
        cfg, optimizer=dataclasses.replace(cfg.optimizer, name=tuning.Adam(), steps=4,
                                           learning_rate=0.1, save_interval=10)))
    run(problem, tmp_path / "full")
    counting = _in_generation(monkeypatch, "gradient", generation=1)  # inside iteration 1
    with handle_interrupts(), pytest.raises(KeyboardInterrupt):
        run(problem, tmp_path / "cut", progress=counting)
    monkeypatch.undo()
    meta = json.loads((tmp_path / "cut" / "checkpoint.json").read_text())
    assert (meta["iteration"], meta["stop_reason"]) == (2, "interrupted")
    assert _iterations(tmp_path / "cut" / "history.csv") == [0, 1]
    run(problem, tmp_path / "cut", resume=True)
    _same_search(tmp_path / "cut", tmp_path / "full")


def test_without_the_command_nothing_is_deferred_and_no_handler_is_left():
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt), critical():  # a library: Ctrl-C as usual
        _ctrl_c()
        time.sleep(1)
    with handle_interrupts():
        assert signal.getsignal(signal.SIGINT) is not before
    assert signal.getsignal(signal.SIGINT) is before


def test_the_interrupt_hint_of_tune_resumes_a_run_cut_inside_a_generation(tmp_path, capsys,
                                                                          monkeypatch):
    """The issue's case: Ctrl-C while a generation is being simulated; the hint, run as
    printed, continues the run (it used to exit 2: CMA-ES could not replay)."""
    cfg = tmp_path / "small.toml"
    cfg.write_text('[tuning]\nparams = ["controller.k"]\n')
    out = tmp_path / "t"
    # --time-limit 0: the 3 generations whatever the machine's load (the default 100 s limit
    # counts the resumed run's time too)
    argv = ["tune", "--tuning", str(cfg), "--t-final", "0.2", "--heldout", "0", "--steps",
            "3", "--time-limit", "none", "--no-plot", "--quiet", "--out", str(out)]
    _in_generation(monkeypatch, "simulate", generation=0)
    assert main(argv) == 130
    last = _err(capsys)[-1]
    assert last.startswith("dscjax tune: interrupted; the checkpoint (iteration 1, best loss ")
    command = shlex.split(last.split("continue with: ")[1])
    assert command == ["dscjax", *argv, "--resume"]
    monkeypatch.undo()
    assert main(command[1:]) == 0
    assert json.loads((out / "checkpoint.json").read_text())["iteration"] == 3


def test_the_hints_repeat_the_program_as_typed_and_overwrite_what_is_there(tmp_path, capsys,
                                                                          monkeypatch):
    import importlib

    out = tmp_path / "s"

    def cut(*a, **k):  # after trajectory.npz, before metrics.json
        raise KeyboardInterrupt

    monkeypatch.setattr(importlib.import_module("dscjax.cli.simulate"), "write_json", cut)
    monkeypatch.setattr(sys, "argv", [".venv/bin/dscjax", "simulate", "--t-final", "0.2",
                                      "--no-plot", "--out", str(out)])
    assert main() == 130
    assert _err(capsys)[-1].endswith(
        f"run the same command again: .venv/bin/dscjax simulate --t-final 0.2 --no-plot "
        f"--out {out} --overwrite")
    assert os.listdir(out) == ["trajectory.npz"]


def test_a_second_ctrl_c_is_one_line_saying_nothing_was_saved(tmp_path, capsys, monkeypatch):
    import importlib

    def pressed_twice(*a, **k):  # inside a step that a first Ctrl-C does not cut
        with critical():
            _ctrl_c(times=2)

    monkeypatch.setattr(importlib.import_module("dscjax.cli.simulate"), "write_npz",
                        pressed_twice)
    out = tmp_path / "s"
    argv = ["simulate", "--t-final", "0.2", "--no-plot", "--out", str(out)]
    assert main(argv) == 130
    err = _err(capsys)
    assert "Ctrl-C: finishing the current step to save a whole state" in err[-3]
    assert err[-1] == (f"dscjax simulate: interrupted again: stopped at once without saving "
                       f"the step under way; nothing is kept (the files are written when the "
                       f"run ends); run the same command again: dscjax {shlex.join(argv)}")
    assert not out.exists()  # it made the directory and left nothing in it


def test_a_sweep_cut_while_writing_a_chunk_keeps_it_whole(tmp_path, capsys, monkeypatch):
    out = tmp_path / "s"
    argv = ["sweep", "--samples", "16", "--chunk", "8", "--t-final", "0.2", "--float64",
            "--worst", "0", "--random", "0", "--no-plot", "--quiet", "--out", str(out)]
    write = files.atomic_write

    def cut(path, data):
        if Path(path).name == "chunk_000000.npz":
            _ctrl_c()
        write(path, data)

    monkeypatch.setattr(files, "atomic_write", cut)
    assert main(argv) == 130
    assert "1 finished block(s) are kept" in _err(capsys)[-1]
    assert files.read_npz(out / "chunks" / "chunk_000000.npz") is not None
    _no_temporary_files(out)
    monkeypatch.undo()
    assert main([*argv, "--resume"]) == 0
    capsys.readouterr()


def test_nested_critical_sections_raise_once_at_the_outermost_end():
    done = []
    with handle_interrupts(), pytest.raises(KeyboardInterrupt):
        with critical():
            with critical():
                _ctrl_c()
                done.append("inner")
            done.append("outer")  # the inner end did not raise
        done.append("after")  # never reached
    assert done == ["inner", "outer"]


def test_replayed_cma_es_saved_between_ask_and_tell_asks_the_same_population_again():
    def make():
        return ReplayCMA(np.ones(3), 0.5, {"seed": 3, "verbose": -9, "popsize": 5,
                                           "randn": np.random.RandomState(3).randn})

    a = make()
    for _ in range(3):
        x = a.ask()
        a.tell(x, (x ** 2).sum(axis=1))
    pending = a.ask()  # a Ctrl-C here: asked, never told
    b = make()
    b.replay({k: np.array(v) for k, v in a.arrays().items()})
    np.testing.assert_array_equal(b.ask(), pending)


# -- SIGTERM (timeout, batch schedulers, docker stop): handled as Ctrl-C (issue 32) -----------


def test_a_sweep_sent_sigterm_keeps_its_blocks_exits_143_and_resumes(tmp_path):
    out = tmp_path / "sweep"
    argv = ["sweep", "--samples", "64", "--chunk", "8", "--t-final", "0.2", "--float64",
            "--worst", "0", "--random", "0", "--no-plot", "--quiet", "--out", str(out)]
    proc = subprocess.Popen([DSCJAX, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    first = out / "chunks" / "chunk_000000.npz"
    deadline = time.monotonic() + 600
    while not first.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)  # mid-run: at the latest, while the nominal run compiles
    _, err = proc.communicate(timeout=600)
    assert proc.returncode == 143, err[-3000:]
    assert "Traceback" not in err
    blocks = sorted((out / "chunks").glob("chunk_*.npz"))
    assert blocks and all(files.read_npz(b) is not None for b in blocks)  # each whole
    _no_temporary_files(out)
    command = shlex.join([DSCJAX, *argv, "--resume"])
    assert err.strip().splitlines()[-1] == (
        f"dscjax sweep: interrupted by SIGTERM; {len(blocks)} finished block(s) are kept in "
        f"{out}/chunks; continue with: {command}")
    _run_hint(command)
    with np.load(out / "results.npz") as z:
        assert z["sample"].tolist() == list(range(64))
