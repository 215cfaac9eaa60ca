"""Checks that refuse a dataset before training starts, with counts (docs/design.md).

* Feature values: a motion whose features are NaN/inf, or lie more than ``max_abs_z``
  standard deviations from the dataset's mean (Mean.npy/Std.npy), is refused, all of a
  split's offenders in one message (`segmo.motion.checks` says what one motion may hold
  and why the bound is 1000). Such a file trains a NaN model: one
  ``new_joint_vecs/<id>.npy`` holding 1e30 made the RVQ loss inf on its first batch and
  every later one NaN.
* Text features: every caption and every text segment of a split must have its sentence
  vector in the text-feature cache; otherwise the run would stop with a KeyError at the
  first batch that holds one.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

from segmo.errors import SegmoError
from segmo.motion.checks import MAX_ABS_Z, value_problem

__all__ = ["MAX_ABS_Z", "missing_texts", "refuse_values", "value_problem"]

SHOWN = 3  # offending files named in a message


def refuse_values(where: str, problems: list[tuple[Path, str]], total: int,
                  max_abs_z: float | None) -> None:
    """Raise one `SegmoError` for the motions of ``where`` whose values are unusable."""
    if not problems:
        return
    shown = "; ".join(f"{path}: {detail}" for path, detail in problems[:SHOWN])
    more = f" (+{len(problems) - SHOWN} more)" if len(problems) > SHOWN else ""
    bound = f"|z| > {max_abs_z:g}" if max_abs_z is not None else "non-finite only"
    raise SegmoError(f"{where}: {len(problems)} of {total} motion files hold NaN/inf or absurd "
                     f"feature values ({bound}, z against the dataset's Mean.npy/Std.npy): "
                     f"{shown}{more}; fix or remove them (data.init_args.max_abs_z sets the bound)")


def missing_texts(captions: Iterable[str], segments: Iterable[str], cache: Any
                  ) -> tuple[list[str], int]:
    """Texts a split needs (its captions and text segments, each a sentence vector) that
    ``cache`` lacks, in first-use order, and how many it needs."""
    needed = list(dict.fromkeys([*captions, *segments]))
    return [t for t in needed if t not in cache], len(needed)
