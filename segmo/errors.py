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


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0 (frame rates, durations)."""
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    """argparse type: a finite number >= 0 (weights that may be off)."""
    value = finite_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return value


# The largest whole number an argument may be: what a 64-bit integer holds (seeds, lengths
# and counts reach torch as int64; beyond it torch fails with "Overflow when unpacking long").
LARGEST_WHOLE_NUMBER = 2**63 - 1


def _whole_number(text: str, minimum: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"expected a whole number >= {minimum}, got {text!r}")
    if value > LARGEST_WHOLE_NUMBER:
        raise argparse.ArgumentTypeError(f"expected a whole number below 2^63, got {text!r}")
    return value


def ascii_whole_number(text: str) -> int | None:
    """`text` read as a whole number written in the ASCII digits 0-9 alone, or None: for a
    sign, a space, an '_' or a digit int() refuses ('²'), and for more digits than int()
    converts (over 4300, a ValueError "Exceeds the limit")."""
    if not (text.isascii() and text.isdigit()):
        return None
    try:
        return int(text)
    except ValueError:
        return None


def positive_int(text: str) -> int:
    """argparse type: a whole number >= 1."""
    return _whole_number(text, 1)


def non_negative_int(text: str) -> int:
    """argparse type: a whole number >= 0 (seeds, counts that may be zero)."""
    return _whole_number(text, 0)


def parse_durations(text: str) -> list[float]:
    """Segment durations written as "1,4" → [1.0, 4.0] (any unit: read as shares of the
    motion); ValueError naming the text for anything else (the CLI and `segmo serve`)."""
    try:
        numbers = [float(v) for v in str(text).split(",")]
    except ValueError:
        numbers = []
    if not numbers or not all(math.isfinite(v) and v >= 0 for v in numbers) or sum(numbers) <= 0:
        raise ValueError(f"{str(text)!r:.80}: expected numbers >= 0 separated by commas, not "
                         "all 0, e.g. 1,4")
    return numbers
