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
>>> dask_address("tcp://10.0.0.5:8786")
'tcp://10.0.0.5:8786'
>>> dask_address("notanaddr")
Traceback (most recent call last):
argparse.ArgumentTypeError: got 'notanaddr'; expected a Dask scheduler address such as tcp://HOST:PORT (missing port number in address 'notanaddr')
"""
from __future__ import annotations

import argparse
import math

__all__ = ["positive_int", "positive_float", "nonnegative_float", "nonzero_float", "dask_address"]


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


def nonzero_float(text: str) -> float:
    """A finite number other than 0 (signed step sizes)."""
    return _number(text, lambda v: v != 0, "a finite nonzero number")


def dask_address(text: str) -> str:
    """A Dask scheduler address (``tcp://host:8786``, ``host:8786``, ``tls://...``), checked
    with Dask's own parser before a client is made (which would raise on a malformed one)."""
    from distributed.comm.addressing import get_address_host_port, parse_address
    from distributed.comm.registry import get_backend
    what = "a Dask scheduler address such as tcp://HOST:PORT"
    try:
        scheme, _ = parse_address(text)
        get_backend(scheme)                          # a scheme Dask knows
        if scheme in ("tcp", "tls", "ws", "wss"):
            host, port = get_address_host_port(text)
            if not host or not 0 < port < 65536:
                raise ValueError(f"host {host!r}, port {port}")
    except (ValueError, TypeError) as err:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected {what} ({err})") from None
    return text
