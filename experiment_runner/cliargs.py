"""Argument types of the ``nanostage`` commands: a bad value is argparse's one-line error
(``nanostage campaign: error: argument --trials: got -3; expected an integer >= 1``, exit 2),
before any work starts.

Examples
--------
>>> import argparse
>>> p = argparse.ArgumentParser(prog="demo")
>>> _ = p.add_argument("--trials", type=positive_int)
>>> p.parse_args(["--trials", "5"]).trials
5
>>> positive_int("0")
Traceback (most recent call last):
argparse.ArgumentTypeError: got 0; expected an integer >= 1
>>> positive_float("nan")
Traceback (most recent call last):
argparse.ArgumentTypeError: got nan; expected a finite number > 0
"""
from __future__ import annotations

import argparse
import math

__all__ = ["positive_int", "positive_float", "nonnegative_float"]


def positive_int(text: str) -> int:
    """An integer >= 1 (trial counts, worker counts)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected an integer >= 1") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"got {value}; expected an integer >= 1")
    return value


def _number(text: str, ok, what: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected {what}") from None
    if not (math.isfinite(value) and ok(value)):
        raise argparse.ArgumentTypeError(f"got {text}; expected {what}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0 (durations, rates, requirements)."""
    return _number(text, lambda v: v > 0, "a finite number > 0")


def nonnegative_float(text: str) -> float:
    """A finite number >= 0."""
    return _number(text, lambda v: v >= 0, "a finite number >= 0")
