"""torchrl_silp.validation: each check against the rule it states, on values hypothesis draws."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchrl_silp.validation import (
    all_finite,
    check_bool,
    check_choice,
    check_finite,
    check_float,
    check_int,
    check_nonnegative_float,
    check_nonnegative_int,
    check_positive_float,
    check_positive_int,
    check_probability,
    check_tensor,
)

SETTINGS = settings(max_examples=200, deadline=None, derandomize=True)
# names as callers spell them: plain, dotted config fields, indexed dict entries
NAMES = st.sampled_from(["n_tasks", "planner.d", "std['obstacle']", "batch_size[1]"])
NOT_NUMBERS = st.one_of(st.booleans(), st.text(max_size=3), st.none(), st.lists(st.integers(), max_size=2),
                        st.just(torch.tensor(1.0)))


def raised(call):
    try:
        call()
    except (TypeError, ValueError) as err:
        return err
    return None


@SETTINGS
@given(st.integers(-10**12, 10**12), st.one_of(st.none(), st.integers(-5, 5)), st.one_of(st.none(), st.integers(-5, 5)),
       NAMES)
def test_check_int_passes_exactly_the_ints_within_the_bounds(value, low, high, name):
    inside = (low is None or value >= low) and (high is None or value <= high)
    err = raised(lambda: check_int(value, name=name, minimum=low, maximum=high))
    if inside:
        assert err is None
        assert check_int(value, name=name, minimum=low, maximum=high) == value
    else:
        assert type(err) is ValueError
        assert str(err).startswith(f"{name} must be an int") and str(err).endswith(f"got {value!r}")
        for bound in (low, high):
            if bound is not None:
                assert str(bound) in str(err)


@SETTINGS
@given(st.one_of(NOT_NUMBERS, st.floats(allow_nan=True)), NAMES)
def test_check_int_refuses_every_other_kind_with_a_type_error_naming_it(value, name):
    err = raised(lambda: check_int(value, name=name, minimum=0))
    assert type(err) is TypeError and str(err).startswith(f"{name} must be an int >= 0, got {value!r}")


def test_numpy_integers_pass_as_ints_and_none_only_where_optional():
    out = check_positive_int(np.int64(3), name="n")
    assert out == 3 and type(out) is int
    assert check_nonnegative_int(None, name="n", optional=True) is None
    with pytest.raises(TypeError, match=r"n must be an int >= 0 or None, got 'x' \(str\)"):
        check_nonnegative_int("x", name="n", optional=True)
    with pytest.raises(TypeError, match="n must be an int >= 1, got None"):
        check_positive_int(None, name="n")
    with pytest.raises(ValueError, match="n must be an int >= 1, got 0"):
        check_positive_int(0, name="n")


@SETTINGS
@given(st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10, 10)),
       st.sampled_from([None, -1.0, 0.0, 0.5]), st.sampled_from([None, 0.0, 1.0, 2.5]), st.booleans(), st.booleans(),
       NAMES)
def test_check_float_passes_exactly_the_finite_numbers_within_the_bounds(value, low, high, low_open, high_open, name):
    v = float(value)
    inside = math.isfinite(v) and (low is None or (v > low if low_open else v >= low)) and (
        high is None or (v < high if high_open else v <= high))
    call = lambda: check_float(value, name=name, low=low, high=high, low_open=low_open, high_open=high_open)  # noqa: E731
    err = raised(call)
    if inside:
        assert err is None
        out = call()
        assert type(out) is float and out == v
    else:
        assert type(err) is ValueError
        assert str(err).startswith(f"{name} must be a finite number") and str(err).endswith(f"got {value!r}")


@SETTINGS
@given(NOT_NUMBERS, NAMES)
def test_check_float_refuses_every_other_kind_with_a_type_error(value, name):
    for check in (check_positive_float, check_nonnegative_float, check_probability):
        err = raised(lambda: check(value, name=name))
        assert type(err) is TypeError and str(err).startswith(f"{name} must be a finite number")


@SETTINGS
@given(st.floats(allow_nan=True, allow_infinity=True))
def test_the_named_ranges(value):
    finite = math.isfinite(value)
    cases = [
        (lambda: check_positive_float(value, name="d", unit="metres"), finite and value > 0, "d must be a finite number > 0 (metres)"),
        (lambda: check_nonnegative_float(value, name="std"), finite and value >= 0, "std must be a finite number >= 0"),
        (lambda: check_probability(value, name="threshold"), 0 < value < 1, "threshold must be a finite number in (0, 1)"),
        (lambda: check_probability(value, name="her_ratio", closed=True), 0 <= value <= 1,
         "her_ratio must be a finite number in [0, 1]"),
    ]
    for call, ok, message in cases:
        err = raised(call)
        assert (err is None) == ok, (value, message)
        if err is not None:
            assert type(err) is ValueError and str(err) == f"{message}, got {value!r}"


@given(st.one_of(st.booleans(), st.integers(0, 1), st.text(max_size=3), st.none(), st.floats(0, 1)))
def test_check_bool_passes_only_bools(value):
    err = raised(lambda: check_bool(value, name="lazy"))
    if isinstance(value, bool):
        assert err is None and check_bool(value, name="lazy") is value
    else:
        assert type(err) is TypeError and str(err) == f"lazy must be a bool, got {value!r}"


@SETTINGS
@given(st.one_of(st.integers(-1, 3), st.booleans(), st.sampled_from(["exact", "greedy", "Exact", ""]), st.none(),
                 st.floats(0, 2)))
def test_check_choice_matches_a_choice_of_the_same_kind_only(value):
    for choices in ((0, 1, 2), ("exact", "greedy")):
        same_kind = [c for c in choices if type(c) is type(value) and c == value]
        err = raised(lambda: check_choice(value, choices, name="method"))
        if same_kind:
            assert err is None and check_choice(value, choices, name="method") == value
        else:
            assert type(err) is ValueError and str(err) == f"method must be one of {choices!r}, got {value!r}"


def test_check_choice_compares_no_tensor_elementwise():
    with pytest.raises(ValueError, match=r"guards must be one of \('all', 'inputs'\), got tensor"):
        check_choice(torch.tensor([1, 2]), ("all", "inputs"), name="guards")


FLOATS = st.sampled_from([torch.float32, torch.float64, torch.float16, torch.bfloat16])
OTHERS = st.sampled_from([torch.int64, torch.int32, torch.bool, torch.uint8])


@SETTINGS
@given(st.lists(st.integers(0, 4), max_size=3), st.one_of(FLOATS, OTHERS), st.one_of(st.none(), st.integers(1, 4)),
       st.booleans())
def test_check_tensor_against_its_rules(shape, dtype, last_dim, floating):
    x = torch.zeros(shape, dtype=dtype)
    err = raised(lambda: check_tensor(x, name="action", last_dim=last_dim, floating=floating))
    if floating and not dtype.is_floating_point:
        assert type(err) is TypeError and str(err) == f"action must be a floating tensor, got {dtype}"
    elif last_dim is not None and (not shape or shape[-1] != last_dim):
        assert type(err) is ValueError
        assert str(err) == f"action must have shape (..., {last_dim}), got {tuple(shape)}"
    else:
        assert err is None and check_tensor(x, name="action", last_dim=last_dim, floating=floating) is x


def test_check_tensor_refuses_what_is_no_tensor():
    with pytest.raises(TypeError, match="goal must be a torch.Tensor, got list"):
        check_tensor([0.0, 1.0], name="goal")


@SETTINGS
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), max_size=20), st.integers(1, 3))
def test_all_finite_and_check_finite_agree_with_isfinite(values, rows):
    x = torch.tensor(values, dtype=torch.float32).repeat(rows, 1)
    expected = all(math.isfinite(v) for v in values)
    result = all_finite(x)
    assert result.shape == () and result.dtype == torch.bool and bool(result) == expected
    err = raised(lambda: check_finite(x, name="state['obstacle']"))
    if expected:
        assert err is None and check_finite(x, name="state['obstacle']") is x
    else:
        assert type(err) is ValueError and str(err).startswith("state['obstacle'] must be finite") and "NaN" in str(err)
