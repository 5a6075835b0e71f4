"""Argument checks shared by the library's public entry points.

Each check takes the value and, as a keyword, the parameter's ``name`` as the
caller spells it (``"planner_kwargs['d']"``, ``"std['obstacle']"``), and
returns the value (an ``int`` or ``float`` where it checks a number). A value of
the wrong kind raises :class:`TypeError`, one out of range :class:`ValueError`;
both messages name the parameter, what it allows and what it got, before any
work is done. ``optional=True`` also lets ``None`` through.

Examples:
    >>> from torchrl_silp.validation import check_positive_int, check_probability
    >>> check_positive_int(3, name="n_tasks")
    3
    >>> check_probability(0.5, name="threshold")
    0.5
    >>> check_positive_int(0, name="n_tasks")
    Traceback (most recent call last):
    ...
    ValueError: n_tasks must be an int >= 1, got 0
    >>> check_positive_int(True, name="n_tasks")
    Traceback (most recent call last):
    ...
    TypeError: n_tasks must be an int >= 1, got True (bool)
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Collection

import torch

__all__ = [
    "all_finite",
    "check_bool",
    "check_choice",
    "check_finite",
    "check_float",
    "check_int",
    "check_nonnegative_float",
    "check_nonnegative_int",
    "check_positive_float",
    "check_positive_int",
    "check_probability",
    "check_tensor",
]


def _got(value) -> str:
    # the value itself, and its type where its repr does not show it (True is a bool, "1" a str)
    if isinstance(value, (bool, str)) or not isinstance(value, numbers.Number):
        return f"{value!r} ({type(value).__name__})"
    return repr(value)


def _or_none(allowed: str, optional: bool) -> str:
    return f"{allowed} or None" if optional else allowed


def check_int(value, *, name: str, minimum: int | None = None, maximum: int | None = None,
              optional: bool = False) -> int | None:
    """``value`` as an ``int`` in ``[minimum, maximum]`` (either bound may be open-ended).

    Any integral number but a bool passes (``numpy.int64`` too).

    Raises:
        TypeError: ``value`` is a bool or not an integral number.
        ValueError: it lies outside the bounds.

    Examples:
        >>> check_int(4, name="batch", minimum=1, maximum=8)
        4
        >>> check_int(9, name="batch", minimum=1, maximum=8)
        Traceback (most recent call last):
        ...
        ValueError: batch must be an int in [1, 8], got 9
    """
    if minimum is not None and maximum is not None:
        allowed = f"an int in [{minimum}, {maximum}]"
    elif minimum is not None:
        allowed = f"an int >= {minimum}"
    elif maximum is not None:
        allowed = f"an int <= {maximum}"
    else:
        allowed = "an int"
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be {_or_none(allowed, optional)}, got {_got(value)}")
    if (minimum is not None and value < minimum) or (maximum is not None and value > maximum):
        raise ValueError(f"{name} must be {_or_none(allowed, optional)}, got {value!r}")
    return int(value)


def check_positive_int(value, *, name: str, optional: bool = False) -> int | None:
    """``value`` as an ``int >= 1`` (:func:`check_int`)."""
    return check_int(value, name=name, minimum=1, optional=optional)


def check_nonnegative_int(value, *, name: str, optional: bool = False) -> int | None:
    """``value`` as an ``int >= 0`` (:func:`check_int`).

    Examples:
        >>> check_nonnegative_int(0, name="n_pairs")
        0
        >>> check_nonnegative_int(-1, name="n_pairs")
        Traceback (most recent call last):
        ...
        ValueError: n_pairs must be an int >= 0, got -1
    """
    return check_int(value, name=name, minimum=0, optional=optional)


def check_float(value, *, name: str, low: float | None = None, high: float | None = None,
                low_open: bool = False, high_open: bool = False, unit: str | None = None,
                optional: bool = False) -> float | None:
    """``value`` as a finite ``float`` between ``low`` and ``high``, each bound closed unless ``*_open``.

    Any real number but a bool passes (an ``int``, ``numpy.float32``); NaN and
    infinities never do. ``unit`` (e.g. ``"metres"``) is named in the message.

    Raises:
        TypeError: ``value`` is a bool or not a real number.
        ValueError: it is not finite or lies outside the bounds.

    Examples:
        >>> check_float(2, name="scale", low=0, low_open=True)
        2.0
        >>> check_float(float("nan"), name="scale", low=0, low_open=True, unit="metres")
        Traceback (most recent call last):
        ...
        ValueError: scale must be a finite number > 0 (metres), got nan
    """
    if low is not None and high is not None:
        allowed = f"a finite number in {'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
    elif low is not None:
        allowed = f"a finite number {'>' if low_open else '>='} {low}"
    elif high is not None:
        allowed = f"a finite number {'<' if high_open else '<='} {high}"
    else:
        allowed = "a finite number"
    if unit is not None:
        allowed += f" ({unit})"
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be {_or_none(allowed, optional)}, got {_got(value)}")
    v = float(value)
    out_of_range = not math.isfinite(v) or (
        low is not None and (v <= low if low_open else v < low)
    ) or (high is not None and (v >= high if high_open else v > high))
    if out_of_range:
        raise ValueError(f"{name} must be {_or_none(allowed, optional)}, got {value!r}")
    return v


def check_positive_float(value, *, name: str, unit: str | None = None, optional: bool = False) -> float | None:
    """``value`` as a finite ``float > 0`` (:func:`check_float`).

    Examples:
        >>> check_positive_float(0.05, name="d", unit="metres")
        0.05
    """
    return check_float(value, name=name, low=0, low_open=True, unit=unit, optional=optional)


def check_nonnegative_float(value, *, name: str, unit: str | None = None, optional: bool = False) -> float | None:
    """``value`` as a finite ``float >= 0`` (:func:`check_float`)."""
    return check_float(value, name=name, low=0, unit=unit, optional=optional)


def check_probability(value, *, name: str, closed: bool = False, optional: bool = False) -> float | None:
    """``value`` as a ``float`` in ``(0, 1)``, or in ``[0, 1]`` with ``closed=True`` (:func:`check_float`).

    Examples:
        >>> check_probability(1, name="her_ratio", closed=True)
        1.0
        >>> check_probability(1, name="threshold")
        Traceback (most recent call last):
        ...
        ValueError: threshold must be a finite number in (0, 1), got 1
    """
    return check_float(value, name=name, low=0, high=1, low_open=not closed, high_open=not closed, optional=optional)


def check_bool(value, *, name: str) -> bool:
    """``value`` if it is a ``bool`` (``0`` and ``1`` are not); :class:`TypeError` otherwise.

    Examples:
        >>> check_bool(1, name="lazy")
        Traceback (most recent call last):
        ...
        TypeError: lazy must be a bool, got 1
    """
    if not isinstance(value, bool):
        raise TypeError(f"{name} must be a bool, got {value!r}")
    return value


def check_choice(value, choices: Collection, *, name: str):
    """``value`` if it is one of ``choices``; :class:`ValueError` otherwise.

    A value matches a choice of its own kind only: ``True`` is not the choice
    ``1``, nor a tensor any choice.

    Examples:
        >>> check_choice("exact", ("exact", "greedy"), name="method")
        'exact'
        >>> check_choice(True, (0, 1, 2), name="collision_type")
        Traceback (most recent call last):
        ...
        ValueError: collision_type must be one of (0, 1, 2), got True
    """
    for choice in choices:
        if value is choice or (
            isinstance(value, type(choice)) and isinstance(value, bool) == isinstance(choice, bool) and value == choice
        ):
            return value
    raise ValueError(f"{name} must be one of {tuple(choices)!r}, got {value!r}")


def all_finite(value: torch.Tensor) -> torch.Tensor:
    """A 0-dim bool tensor: whether every element of ``value`` is finite (true for an empty tensor).

    No host sync: the caller decides when to read it.

    Examples:
        >>> bool(all_finite(torch.tensor([1.0, -float("inf")])))
        False
    """
    if value.numel() == 0:
        return torch.ones((), dtype=torch.bool, device=value.device)
    # amax propagates NaN and abs turns -inf into inf: ~4x cheaper than isfinite(value).all()
    return value.abs().amax().isfinite()


def check_finite(value: torch.Tensor, *, name: str) -> torch.Tensor:
    """``value`` if it holds no NaN or infinity; :class:`ValueError` otherwise.

    Skipped inside ``torch.compile``: the check reads the data, which would break
    the graph at every call.

    Examples:
        >>> check_finite(torch.tensor([0.0, float("nan")]), name="action")
        Traceback (most recent call last):
        ...
        ValueError: action must be finite, got a tensor holding NaN or inf
    """
    if torch.compiler.is_compiling():
        return value
    if not bool(all_finite(value)):
        raise ValueError(f"{name} must be finite, got a tensor holding NaN or inf")
    return value


def check_tensor(value, *, name: str, last_dim: int | None = None, floating: bool = True) -> torch.Tensor:
    """``value`` if it is a ``torch.Tensor`` (of a floating dtype unless ``floating=False``) whose
    trailing size is ``last_dim`` (any when ``None``).

    Raises:
        TypeError: not a tensor, or not floating.
        ValueError: the trailing size differs.

    Examples:
        >>> check_tensor(torch.zeros(4, 3), name="action", last_dim=3).shape
        torch.Size([4, 3])
        >>> check_tensor(torch.zeros(4, 2), name="action", last_dim=3)
        Traceback (most recent call last):
        ...
        ValueError: action must have shape (..., 3), got (4, 2)
    """
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if floating and not value.is_floating_point():
        raise TypeError(f"{name} must be a floating tensor, got {value.dtype}")
    if last_dim is not None and value.shape[-1:] != (last_dim,):
        raise ValueError(f"{name} must have shape (..., {last_dim}), got {tuple(value.shape)}")
    return value
