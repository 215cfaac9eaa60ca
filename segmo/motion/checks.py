"""Is this array a motion? The check every reader of user motions applies.

A corrupt file can hold finite numbers and still be no motion (a feature of 1e30 trains
a NaN model). A value is refused when it is not finite, or when it lies more than
`MAX_DEVIATIONS` standard deviations from the dataset mean, with each std floored at
`STD_FLOOR` so that a feature that hardly varies in training (a joint that never moves
relative to the root) does not flag ordinary motions. On the real HumanML3D clip in
`../shared/fixtures` the largest deviation is 24 std; 1e30 is 1e31.

    check_motion_values(features, mean, std, "new_joint_vecs/000001.npy")
"""

from __future__ import annotations

from typing import Any

import numpy as np

from segmo.errors import SegmoError

MAX_DEVIATIONS = 1e3
STD_FLOOR = 1e-2


def motion_problem(features: Any, mean: Any = None, std: Any = None) -> str | None:
    """Why `features` (t, d) are no motion ("frame 3, dim 7: nan"), or None when they are.

    Without `mean` and `std` only finiteness is checked."""
    x = np.asarray(features, dtype=np.float64)
    bad = ~np.isfinite(x)
    if mean is not None and std is not None:
        scale = np.maximum(np.asarray(std, dtype=np.float64), STD_FLOOR)
        with np.errstate(invalid="ignore", over="ignore"):
            bad |= np.abs(x - np.asarray(mean, dtype=np.float64)) > MAX_DEVIATIONS * scale
    if not bad.any():
        return None
    where = np.argwhere(bad)
    first = tuple(int(v) for v in where[0])
    at = f"frame {first[0]}, dim {first[1]}" if x.ndim == 2 else f"index {first}"
    return (f"{len(where)} value(s) are NaN/inf or more than {MAX_DEVIATIONS:g} std from the "
            f"mean (a corrupt file, not a motion); the first, at {at}, is {x[first]:g}")


def check_motion_values(features: Any, mean: Any = None, std: Any = None,
                        name: str = "motion") -> None:
    """Raise SegmoError naming `name` when `features` are no motion (`motion_problem`)."""
    problem = motion_problem(features, mean, std)
    if problem is not None:
        raise SegmoError(f"{name}: {problem}")
