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


def test_a_resume_with_nothing_to_resume_says_so_before_judging_the_settings(tmp_path, capsys):
    """--resume into a directory without the run's record names the missing record first,
    even where the settings given would be refused too (nothing is compiled)."""
    bad = tmp_path / "bad.toml"
    bad.write_text('[tuning]\nparams = ["controller.nope"]\n')
    for extra, record in (((), "checkpoint.json"), (("--adversarial", "1"), "adversarial.json")):
        out = tmp_path / f"empty-{record}"
        out.mkdir()
        assert main(["tune", "--tuning", str(bad), "--resume", "--out", str(out), *extra]) == 2
        assert capsys.readouterr().err.splitlines() == [
            f"dscjax tune: error: --resume: nothing to resume in {out} ({record} is missing); "
            f"run without --resume to start afresh"]
