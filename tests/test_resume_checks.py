"""A resume with a changed config is refused first: one line naming the old and the new
value, exit 2, before the banner or any work, and nothing in --out changes (issue 32, 9c).
tune's and worst-case's are in tests/test_tuning_loop.py and tests/test_worst_case.py."""

from dscjax.cli.main import main


def test_sweep_resume_with_a_changed_config_is_refused_before_anything(tmp_path, capsys):
    out = tmp_path / "s"
    argv = ["sweep", "--samples", "8", "--chunk", "8", "--t-final", "0.5", "--float64",
            "--worst", "0", "--random", "0", "--no-plot", "--quiet", "--out", str(out)]
    assert main(argv) == 0
    before = {f: f.read_bytes() for f in out.rglob("*") if f.is_file()}
    capsys.readouterr()
    assert main([*argv, "--resume", "--seed", "1"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.splitlines() == [
        f"dscjax sweep: error: --resume: {out / 'sweep.json'} was made with other settings "
        f"(seed 0 (now 1)); use the same settings, or --overwrite to start afresh"]
    assert {f: f.read_bytes() for f in out.rglob("*") if f.is_file()} == before
