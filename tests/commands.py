"""A command run in the test's process: `exit_code(argv)` is `dscjax ARGV`'s exit code through
`dscjax.cli.main.main`, argparse's refusals (which exit by SystemExit) included."""

from dscjax.cli.main import main


def exit_code(argv: list[str]) -> int:
    """The exit code a shell would see of `dscjax ARGV`, run through `main` here."""
    try:
        return main(list(argv))
    except SystemExit as stop:  # argparse's own refusals
        return stop.code


__all__ = ["exit_code"]
