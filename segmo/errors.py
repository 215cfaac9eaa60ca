"""The one error type a user of segmo sees.

`SegmoError` is an expected failure caused by what the user gave: a file, an argument, a
config, a model directory, a dataset folder. Its message is one line that names the file
(and line) or the argument, and says what to do where that is not obvious. The `segmo`
command prints it as ``segmo COMMAND: message`` and exits with status 2, without a
traceback (``segmo --debug COMMAND ...`` shows it). Anything else that escapes a command is
a bug and keeps its traceback.

It is a `ValueError`, so notebook code that catches ValueError keeps working.

    raise SegmoError(f"{path}:{line}: expected 'caption#tokens#from#to'")
"""

from __future__ import annotations

import argparse
import math


class SegmoError(ValueError):
    """An expected failure caused by the user's input; the message is one line."""

    def __init__(self, message: str) -> None:
        # One line, so that the command prints exactly one: a multi-line message from a
        # library (jsonargparse, numpy) is folded here rather than at every raise.
        lines = (part.strip() for part in str(message).splitlines())
        super().__init__(" ".join(part for part in lines if part))


class FolderBusyError(SegmoError):
    """A data folder is being written by another process (`segmo.files.FolderLock`)."""


class ArgumentParser(argparse.ArgumentParser):
    """`argparse.ArgumentParser` whose errors raise `SegmoError` instead of printing the
    usage and exiting, so that a bad argument reaches the user as the one line every
    other failure does (``segmo generate: argument --steps: invalid int value: 'x'``)."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise SegmoError(f"{message} (see `{self.prog} --help`)")


def finite_float(text: str) -> float:
    """argparse type: a finite number (NaN and inf are refused, naming the argument)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """argparse type: a whole number >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return value


def non_negative_int(text: str) -> int:
    """argparse type: a whole number >= 0 (seeds, counts that may be zero)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {text!r}")
    return value
