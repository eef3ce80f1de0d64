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
