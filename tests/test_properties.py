"""Property tests (hypothesis) of the two small languages every feature shares: parameter
paths (`dscjax.params.Param`) and ranges (`dscjax.params.parse_range`, `from_value`).

Pure host code, no JAX tracing: 100 examples each, a few seconds in all.
"""

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dscjax.params import Param, Range, from_table, parse_range
from dscjax.validation import ConfigError

FAST = settings(max_examples=100, deadline=None)

identifiers = st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,7}", fullmatch=True)
paths = st.lists(identifiers, min_size=1, max_size=3).map(".".join)
indices = st.none() | st.integers(0, 10_000)
params = st.builds(Param, paths, indices)
# numbers that `Range.spec` writes exactly (10 significant digits)
numbers = st.floats(-1e6, 1e6, allow_nan=False).map(lambda x: float(f"{x:.10g}"))
percent = st.floats(0.01, 500.0).map(lambda p: float(f"{p:g}"))


@FAST
@given(params)
def test_a_parameter_name_parses_back_to_the_same_parameter(p):
    assert Param.parse(p.name) == p
    assert Param.parse(f"  {p.name} ") == p


@FAST
@given(st.text(max_size=30))
def test_any_text_is_a_parameter_or_a_config_error_naming_the_field(text):
    try:
        p = Param.parse(text, "sweep.ranges")
    except ConfigError as e:
        assert str(e).startswith("sweep.ranges: ")
    else:
        assert Param.parse(p.name) == p


@FAST
@given(params, numbers, numbers, st.none() | st.integers(1, 50))
def test_an_absolute_range_round_trips_through_its_spec(p, low, high, num):
    r = Range(p, low=low, high=high, num=num)
    assert parse_range(r.spec(), grid=num is not None) == r


@FAST
@given(params, percent)
def test_a_relative_range_round_trips_through_its_spec(p, pct):
    r = parse_range(f"{p.name}={pct:g}%")
    assert r.param == p and r.low is None and r.high is None
    assert math.isclose(r.rel, pct / 100)
    assert parse_range(r.spec()) == r


@FAST
@given(params, numbers, numbers)
def test_the_command_line_and_a_toml_table_give_the_same_range(p, low, high):
    assert from_table({p.name: [low, high]}, "sweep.ranges") == (
        parse_range(f"{p.name}={low!r}:{high!r}"),)


@FAST
@given(st.text(max_size=30), st.booleans())
def test_any_range_text_is_a_range_or_a_config_error(text, grid):
    try:
        r = parse_range(text, grid=grid)
    except ConfigError as e:
        assert str(e).startswith("--grid" if grid else "--range")
    else:
        assert isinstance(r, Range) and (r.num is not None) == grid


@pytest.mark.parametrize("text", ["alpha", "a.b=1", "a=1:2:3", "a=0%", "a=-5%", "a=x:1",
                                  "1a=1:2", "a[-1]=1:2", "a..b=1:2"])
def test_malformed_ranges_are_config_errors(text):
    with pytest.raises(ConfigError):
        parse_range(text)
