"""Checks that refuse a dataset before training starts, with counts (docs/design.md).

* Feature values: a motion whose features are NaN/inf, or lie more than ``max_abs_z``
  standard deviations from the dataset's mean (Mean.npy/Std.npy), is refused. Such a file
  trains a NaN model: one ``new_joint_vecs/<id>.npy`` holding 1e30 made the RVQ loss inf
  on its first batch and every later one NaN. `MAX_ABS_Z` = 1000 is ~40x the largest
  |z| of real data: 24.3 on the HumanML3D clip 012314 against the real HumanML3D Mean/Std
  (frame 28, dim 257, a joint velocity), 24.8 over a 400-motion built-in corpus and 24.2
  over a 2,000-motion one against their own statistics (23.9 against HumanML3D's). With
  statistics computed over N frames no frame can be more than sqrt(N - 1) deviations
  away (Samuelson), which the bound only reaches for N ≈ 10^6; MoMask's statistics,
  whose std is divided by up to 25 in a few dims, stay within 25 x 24.3 ≈ 600.
* Text features: every caption (sentence vector and token features) and every text
  segment of a split must be in the text-feature cache; otherwise the run would stop with
  a KeyError at the first batch that holds one.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from segmo.errors import SegmoError

MAX_ABS_Z = 1000.0
SHOWN = 3  # offending files named in a message


def value_problem(arr: np.ndarray, mean: np.ndarray, std: np.ndarray,
                  max_abs_z: float | None) -> str | None:
    """Where (t, d) raw features ``arr`` are non-finite or beyond ``max_abs_z``, or None."""
    finite = np.isfinite(arr)
    if not finite.all():
        frame, dim = np.argwhere(~finite)[0]
        return f"frame {frame} dim {dim} is {arr[frame, dim]} ({int((~finite).sum())} non-finite values)"
    if max_abs_z is None or arr.size == 0:
        return None
    with np.errstate(over="ignore"):  # a huge value may overflow float32 here: still caught
        z = np.abs((arr.astype(np.float64) - mean) / std)
    frame, dim = np.unravel_index(int(z.argmax()), z.shape)
    if z[frame, dim] <= max_abs_z:
        return None
    return (f"frame {frame} dim {dim} is {arr[frame, dim]:.6g}, {z[frame, dim]:.3g} standard "
            f"deviations from the mean (max_abs_z={max_abs_z:g})")


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
    """Texts a split needs that ``cache`` lacks, in first-use order, and how many it needs.

    Captions need a sentence vector and token features, segments a sentence vector."""
    needed: dict[str, bool] = {}  # text -> needs token features
    for text in captions:
        needed[text] = True
    for text in segments:
        needed.setdefault(text, False)
    missing = [t for t, tokens in needed.items()
               if t not in cache or (tokens and not cache.has_tokens(t))]
    return missing, len(needed)
