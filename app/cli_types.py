"""Argument types and conventions shared by every ``osteonav`` command.

Numeric options are checked when the command line is parsed: each type below is an argparse
``type=`` function that returns the value or raises :class:`argparse.ArgumentTypeError` with the
accepted range, so argparse prints one line naming the option, e.g.
``osteonav simulate: error: argument --seconds: expected seconds > 0 (a finite number), got '0'``.

Option names follow one convention (issue 34): ``--seconds S`` for durations, ``--count N`` for
numbers of things, ``--captures DIR`` for capture folders, ``--rrd FILE.rrd`` / ``--no-rrd`` for
rerun logs. :func:`deprecated_alias` keeps an old spelling working, hidden from ``--help``, with a
one-line warning.
"""
from __future__ import annotations

import argparse
import math
import sys


def _number(text: str, kind, expected: str) -> float:
    try:
        value = kind(text)
    except (TypeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}") from None
    if isinstance(value, float) and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
    return value


def int_at_least(minimum: int, what: str = "an integer"):
    """A type: an integer >= ``minimum`` (``what`` names it in the message, e.g. 'a frame count')."""

    def parse(text: str) -> int:
        expected = f"{what} >= {minimum}"
        value = _number(text, int, expected)
        if value < minimum:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return value

    parse.__name__ = f"int_at_least_{minimum}"
    return parse


positive_int = int_at_least(1)
"""An integer >= 1 (counts: frames, captures, particles, jobs)."""

non_negative_int = int_at_least(0)
"""An integer >= 0 (seeds, indices)."""

seed = int_at_least(0, "a seed (an integer)")
"""A random seed: an integer >= 0 (numpy's generators refuse negative seeds)."""


def finite_float(text: str) -> float:
    """Any finite number (not nan, not inf)."""
    return float(_number(text, float, "a finite number"))


def finite_positive_float(text: str) -> float:
    """A finite number > 0 (scales, rates, frames per second)."""
    value = float(_number(text, float, "a finite number > 0"))
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text!r}")
    return value


def positive_seconds(text: str) -> float:
    """A duration in seconds: a finite number > 0 (leave the option out for the default)."""
    value = float(_number(text, float, "seconds > 0 (a finite number)"))
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected seconds > 0 (a finite number), got {text!r}")
    return value


def seconds_over(minimum: float, why: str = ""):
    """A type: a duration in seconds, finite and > ``minimum`` (``why`` explains the bound)."""

    def parse(text: str) -> float:
        expected = f"seconds > {minimum:g}" + (f" ({why})" if why else "")
        value = float(_number(text, float, expected))
        if value <= minimum:
            raise argparse.ArgumentTypeError(f"expected {expected}, got {text!r}")
        return value

    parse.__name__ = "seconds_over"
    return parse


class _DeprecatedAlias(argparse.Action):
    """Stores like the option it stands for, after a one-line warning on stderr."""

    def __init__(self, option_strings, dest, new: str, inner: argparse.Action, **kwargs):
        self.new, self.inner = new, inner
        super().__init__(option_strings, dest, nargs=inner.nargs, type=inner.type, choices=inner.choices, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"{parser.prog}: warning: {option_string} is deprecated; use {self.new}", file=sys.stderr)
        self.inner(parser, namespace, values, self.new)


def deprecated_alias(parser: argparse.ArgumentParser, old: str, new: str) -> None:
    """Accept ``old`` as a hidden, deprecated spelling of the already added option ``new``."""
    inner = next(a for a in parser._actions if new in a.option_strings)
    parser.add_argument(old, dest=inner.dest, action=_DeprecatedAlias, new=new, inner=inner, help=argparse.SUPPRESS,
                        default=argparse.SUPPRESS)
