"""The validators every configuration, command and function of the package uses, so that
every bad input reads the same way: ``"P_bar=-1.0: expected a value in (0, inf)"`` -- the name,
the value given, what was expected -- and raises a :class:`ValueError` (a wrong type raises
:class:`InputTypeError`, which is both a ``TypeError`` and a ``ValueError``).

Each returns the value normalised to a plain Python type (numpy scalars become int/float/
str), so that what was validated is also what is stored and written to JSON.
"""

from __future__ import annotations

import math
import numbers
import reprlib
from collections.abc import Sequence
from typing import Any

__all__ = ["InputTypeError", "ModelInputError", "check_bool", "check_choice", "check_instance", "check_int",
           "check_real", "show"]


class InputTypeError(TypeError, ValueError):
    """A value of the wrong type (a string for a number, an array for a choice, ...).

    A :class:`TypeError` by Python's convention, and a :class:`ValueError` by the project's:
    every bad input raises a ``ValueError`` whose message names the argument, the value given
    and what was expected, so one ``except ValueError`` (as in the command line) catches all
    of them.
    """


class ModelInputError(ValueError):
    """Inputs every check accepted, on which a computation still cannot be done (a solver
    that cannot solve the problem they make); the message names the inputs and what to do.
    The command line reports it in one line like any bad argument."""


_shown = reprlib.Repr()
_shown.maxstring = _shown.maxother = 60
_shown.maxlist = _shown.maxtuple = _shown.maxdict = _shown.maxset = 6


def show(value: Any) -> str:
    """A short ``repr`` of a bad value for an error message (long ones are cut), on one line
    (an array's ``repr`` may wrap)."""
    return " ".join(_shown.repr(value).split())


def _interval(low: float | None, high: float | None, low_open: bool, high_open: bool) -> str:
    lo = "-inf" if low is None else f"{low:g}"
    hi = "inf" if high is None else f"{high:g}"
    left = "(" if (low_open or low is None) else "["
    right = ")" if (high_open or high is None) else "]"
    return f"{left}{lo}, {hi}{right}"


def check_real(
    name: str,
    value: Any,
    low: float | None = None,
    high: float | None = None,
    *,
    low_open: bool = False,
    high_open: bool = False,
) -> float:
    """``value`` as a finite Python ``float`` in the interval given, else an error naming it.

    Parameters
    ----------
    name : str
        What the value is, as the user wrote it (``'P_bar'``, ``'factor'``).
    value : object
        Any real number (``int``, ``float``, numpy scalar, ``Fraction``); not ``bool``.
    low, high : float, optional
        Bounds (``None``: unbounded); closed unless ``low_open``/``high_open``.

    Returns
    -------
    float

    Raises
    ------
    InputTypeError
        If ``value`` is not a real number.
    ValueError
        If it is not finite or outside the interval; the message reads
        ``"P_bar=-1.0: expected a value in (0, inf)"``.
    """
    interval = _interval(low, high, low_open, high_open)
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise InputTypeError(
            f"{name}={show(value)}: expected a real number in {interval}, "
            f"got {type(value).__name__}"
        )
    try:
        number = float(value)
    except OverflowError:  # an int beyond the float range
        number = math.inf if value > 0 else -math.inf
    if not math.isfinite(number):
        raise ValueError(f"{name}={show(value)}: expected a finite value in {interval}")
    below = low is not None and (number <= low if low_open else number < low)
    above = high is not None and (number >= high if high_open else number > high)
    if below or above:
        raise ValueError(f"{name}={show(value)}: expected a value in {interval}")
    return number


def check_int(
    name: str, value: Any, low: int | None = None, high: int | None = None, note: str = ""
) -> int:
    """``value`` as a Python ``int`` in ``[low, high]``, else an error naming it.

    Accepts ``int`` and numpy integers, not ``bool`` and not floats (``3.0`` is refused:
    a count written as a float is usually a mistake elsewhere). ``note`` is appended to the
    message (why the range is what it is).

    Raises
    ------
    InputTypeError
        If ``value`` is not an integer.
    ValueError
        If it is outside the range; the message reads ``"n=0: expected an integer >= 1"``.
    """
    if low is not None and high is not None:
        expected = f"an integer in [{low}, {high}]"
    elif low is not None:
        expected = f"an integer >= {low}"
    elif high is not None:
        expected = f"an integer <= {high}"
    else:
        expected = "an integer"
    suffix = f" ({note})" if note else ""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise InputTypeError(
            f"{name}={show(value)}: expected {expected}, got {type(value).__name__}{suffix}"
        )
    if (low is not None and value < low) or (high is not None and value > high):
        raise ValueError(f"{name}={show(value)}: expected {expected}{suffix}")
    return int(value)


def check_choice(name: str, value: Any, choices: Sequence[str]) -> str:
    """``value`` as one of the strings ``choices``, else an error naming it and the choices.

    Only strings are compared (an array or a list is refused with the same message instead
    of numpy's "truth value of an array is ambiguous").
    """
    expected = f"expected one of {', '.join(map(repr, choices))}"
    if not isinstance(value, str):
        raise InputTypeError(f"{name}={show(value)}: {expected}, got {type(value).__name__}")
    if value not in choices:
        raise ValueError(f"{name}={show(value)}: {expected}")
    return str(value)


def check_bool(name: str, value: Any) -> bool:
    """``value`` if it is ``True`` or ``False`` (not ``0``/``1``), else an error naming it."""
    if not isinstance(value, bool):
        raise InputTypeError(
            f"{name}={show(value)}: expected True or False, got {type(value).__name__}"
        )
    return value


def check_instance(name: str, value: Any, kind: type | tuple[type, ...]) -> Any:
    """``value`` unchanged if it is an instance of ``kind``, else an error naming it."""
    if not isinstance(value, kind):
        kinds = kind if isinstance(kind, tuple) else (kind,)
        expected = " or ".join(k.__name__ for k in kinds)
        raise InputTypeError(f"{name}: expected a {expected}, got {type(value).__name__}")
    return value
