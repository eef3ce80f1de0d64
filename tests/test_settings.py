"""The settings schema: each rule's reading, writing and message (`dscjax.rules`); the four
readers of a group's declarations (table, TOML data, command line, docs rows)
on a group of its own."""

import argparse
import dataclasses

import pytest

from dscjax import rules
from dscjax import settings as st
from dscjax.validation import ConfigError


@dataclasses.dataclass(frozen=True)
class Inner:
    level: float = st.setting(0.2, "CVaR level", rules.Number(gt=0, le=1))


@dataclasses.dataclass(frozen=True)
class Group:
    time_limit: float | None = st.setting(100.0, "wall seconds", rules.Maybe(rules.Positive()),
                                          flag="--time-limit")
    steps: int = st.setting(3, "iterations", rules.AtLeast(1))
    name: str = st.setting("a", "which", rules.Choice(("a", "b")), flag="--name")
    bound: float | str | None = st.setting("start", "a bound",
                                           rules.Maybe(rules.Either((rules.Choice(("start",)),
                                                               rules.Positive()))))
    noise: float | tuple | None = st.setting(None, "std",
                                             rules.Maybe(rules.Numbers(rules.Number(ge=0))))
    inner: Inner = st.group(Inner)
    other: Inner = st.group(Inner, factory=lambda: Inner(0.5), flags={"level": "--level"})

    def validate(self, prefix):
        if self.name == "b" and self.steps < 2:
            raise ConfigError(f"{prefix}.steps must be >= 2 with {prefix}.name = 'b'")


@pytest.mark.parametrize("rule, value, expected", [
    (rules.Positive(), 2, 2.0), (rules.AtLeast(1), 5, 5),
    (rules.Maybe(rules.Positive()), "none", None),
    (rules.Maybe(rules.Positive()), "None", None), (rules.Number(gt=0, le=1), 1, 1.0),
    (rules.Numbers(), [1, 2.5], (1.0, 2.5)), (rules.Strings(), ["a.b", "c"], ("a.b", "c")),
])
def test_rules_read_values_from_files(rule, value, expected):
    assert rule.parse(value) == expected


@pytest.mark.parametrize("rule, value, must", [
    (rules.Positive(), 0, "a finite number > 0"), (rules.Positive(), True, "a finite number > 0"),
    (rules.Positive(), "10", "a finite number > 0"),
    (rules.Positive(), float("inf"), "a finite number > 0"),
    (rules.AtLeast(1), 1.0, "an integer >= 1"), (rules.AtLeast(0), -1, "an integer >= 0"),
    (rules.Number(gt=0, le=1), 1.5, "a finite number in (0, 1]"),
    (rules.Number(ge=0, lt=1), 1, "a finite number in [0, 1)"),
    (rules.Maybe(rules.Positive()), 0, 'a finite number > 0, or "none"'),
    (rules.Choice(("rk4", "etdrk4")), "euler", "one of 'rk4', 'etdrk4'"),
    (rules.Numbers(rules.Number(ge=0)), [1, -1], "one finite number >= 0 or a list of them"),
])
def test_rules_refuse_with_what_the_value_must_be(rule, value, must):
    with pytest.raises(rules.Invalid) as err:
        rule.parse(value)
    assert err.value.must == must and err.value.value == value


def test_the_command_line_and_a_file_spell_values_alike():
    assert rules.Maybe(rules.Positive()).from_text("none") is None
    assert rules.Maybe(rules.Positive()).from_text("2.5") == 2.5
    assert rules.AtLeast(0).from_text("1e5") == 100_000  # a count typed in floating notation
    assert rules.Numbers().from_text("0.01,0,0.02") == (0.01, 0.0, 0.02)
    assert rules.Numbers().from_text("0.01") == 0.01
    with pytest.raises(rules.Invalid):
        rules.AtLeast(0).from_text("1.5")
    with pytest.raises(rules.Invalid):
        rules.Maybe(rules.Positive()).from_text("0")


def test_a_strategy_is_read_as_its_object_and_written_as_its_name():
    class CVaR:
        pass

    rule = rules.Choice({"mean": "MEAN", "cvar": CVaR})
    assert rule.parse("cvar") is CVaR and rule.dump(CVaR) == "cvar"
    assert rule.parse(CVaR) is CVaR  # built in code


def test_from_table_parses_nests_validates_and_names_the_path():
    g = st.from_table(Group, {"time_limit": "none", "name": "b", "steps": 2,
                              "inner": {"level": 0.5}, "noise": [0.1, 0.2]}, "tuning.opt.")
    assert (g.time_limit, g.name, g.steps, g.inner.level, g.noise) == (
        None, "b", 2, 0.5, (0.1, 0.2))
    over = st.from_table(Group, {"steps": 7}, "tuning.opt.", base=g)  # laid over a base
    assert (over.steps, over.name, over.inner.level) == (7, "b", 0.5)
    cases = [({"steps": 0}, "tuning.opt.steps must be an integer >= 1 (got 0)"),
             ({"time_limit": 0}, 'tuning.opt.time_limit must be a finite number > 0, or "none" '
                                 '(got 0)'),
             ({"inner": {"level": 2}}, "tuning.opt.inner.level must be a finite number in (0, 1] "
                                       "(got 2)"),
             ({"stepz": 1}, "unknown key 'tuning.opt.stepz' (allowed: time_limit, steps, "
                            "name, bound, noise, inner, other)"),
             ({"inner": 3}, "'tuning.opt.inner' must be a table ([tuning.opt.inner])"),
             ({"name": "b", "steps": 1}, "tuning.opt.steps must be >= 2 with tuning.opt.name "
                                         "= 'b'"),
             ({"bound": "end"}, 'tuning.opt.bound must be one of \'start\' or a finite number > 0, '
                                'or "none" (got a string, \'end\')')]
    for table, message in cases:
        with pytest.raises(ConfigError) as err:
            st.from_table(Group, table, "tuning.opt.")
        assert str(err.value) == message


def test_to_table_round_trips_through_from_table():
    g = Group(time_limit=None, bound=3.0, noise=(0.1, 0.0), inner=Inner(0.7))
    table = st.to_table(g)
    assert table == {"time_limit": "none", "steps": 3, "name": "a", "bound": 3.0,
                     "noise": [0.1, 0.0], "inner": {"level": 0.7}, "other": {"level": 0.5}}
    assert st.from_table(Group, table, "x.") == g
    assert st.to_table(Group())["bound"] == "start" and st.to_table(Group())["noise"] == "none"


def test_options_parse_by_the_rule_and_name_the_option_typed(capsys):
    p = argparse.ArgumentParser(prog="t", exit_on_error=False)
    st.add_arguments(p, Group, "tuning.opt.")
    args = p.parse_args(["--time-limit", "none", "--name", "b", "--level", "0.3"])
    assert st.given(args, Group, "tuning.opt.") == (
        {"time_limit": None, "name": "b", "other": {"level": 0.3}},
        {"tuning.opt.time_limit": "--time-limit", "tuning.opt.name": "--name",
         "tuning.opt.other.level": "--level"})
    assert st.given(p.parse_args([]), Group, "tuning.opt.") == ({}, {})
    with pytest.raises(argparse.ArgumentError) as err:
        p.parse_args(["--time-limit", "0"])
    assert str(err.value) == ("argument --time-limit: must be a finite number > 0, or \"none\" "
                              "(got '0')")
    help_text = " ".join(p.format_help().split())
    assert "(default 0.5, or the config's tuning.opt.other.level)" in help_text
    assert "wall seconds (default 100, or the config's tuning.opt.time_limit)" in help_text


def test_doc_rows_list_every_key_with_default_range_and_option():
    rows = st.doc_rows(Group, "tuning.opt.")
    assert rows[2] == ('| `tuning.opt.time_limit` | `100` | a finite number > 0, or "none" | '
                       'wall seconds | `--time-limit` |')
    # the second occurrence of a group: its own default and option
    assert rows[-1] == ("| `tuning.opt.other.level` | `0.5` | a finite number in (0, 1] | "
                        "CVaR level | `--level` |")
    rows = rows[:-1]
    assert rows[-1] == ("| `tuning.opt.inner.level` | `0.2` | a finite number in (0, 1] | "
                        "CVaR level |  |")
    assert len(rows) == 2 + 6


def settings_groups() -> dict:
    """{table: the settings group declaring it}: the tables of docs/settings.md."""
    from dscjax.identify.run import IdentifySettings
    from dscjax.runspec import Simulation
    from dscjax.sweep import SweepSettings
    from dscjax.worst import WorstSettings
    from tuning.config import TuningConfig

    return {"simulation": Simulation, "sweep": SweepSettings, "tuning": TuningConfig,
            "worst": WorstSettings, "identify": IdentifySettings}


def settings_docs(text: str) -> str:
    """`text` (a docs page) with each marked block `<!-- settings NAME -->` ... `<!-- end
    settings -->` replaced by the key table of the group NAME, generated from its declarations
    (`dscjax.settings.doc_rows`)."""
    import re

    groups = settings_groups()

    def table(match):
        rows = st.doc_rows(groups[match[1]], f"{match[1]}.")
        return "\n".join([f"<!-- settings {match[1]} -->", *rows, "<!-- end settings -->"])

    return re.sub(r"<!-- settings (\w+) -->.*?<!-- end settings -->", table, text, flags=re.S)


def test_docs_settings_md_holds_the_declarations_tables():
    """docs/settings.md's key tables are generated from the declarations: regenerated, the
    page is unchanged (regenerate it with settings_docs above)."""
    from pathlib import Path

    page = Path(__file__).resolve().parents[1] / "docs" / "settings.md"
    text = page.read_text()
    assert settings_docs(text) == text
    # every table a config may hold has its block (a new command's table must be added above)
    from dscjax.config import COMMAND_TABLES

    assert set(settings_groups()) == {"simulation", *COMMAND_TABLES}
    for name in settings_groups():
        assert f"<!-- settings {name} -->" in text
    assert "| `tuning.optimizer.time_limit` | `200` |" in text


def test_a_setting_named_validate_is_read_not_called():
    # identify's --validate FILE is a setting named like a group's cross-field check
    from dscjax.identify.run import IdentifySettings

    s = st.from_table(IdentifySettings, {"validate": "other.csv"}, "identify.")
    assert s.validate == "other.csv"
