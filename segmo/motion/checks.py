"""Is this array a motion? The check every reader of user motions applies.

A corrupt file can hold finite numbers and still be no motion: one
``new_joint_vecs/<id>.npy`` holding 1e30 trains a NaN model. Raw features (t, d) are
refused when a value is NaN/inf or lies more than `MAX_ABS_Z` standard deviations from
the dataset's mean. 1000 is ~40x the largest |z| of real data: 24.3 on the HumanML3D clip
012314 against the real HumanML3D Mean/Std (frame 28, dim 257, a joint velocity), 24.8
over a 400-motion built-in corpus and 24.2 over a 2,000-motion one against their own
statistics (23.9 against HumanML3D's). With statistics computed over N frames no frame
can be more than sqrt(N - 1) deviations away (Samuelson), which the bound only reaches for
N ≈ 10^6; MoMask's statistics, whose std is divided by up to 25 in a few dims, stay within
25 x 24.3 ≈ 600.

Readers: the datasets (`segmo.data.checks`, every file of a split before training) and
the inference pipeline (a motion given to `SegMo.ground`, `edit`, retrieval).

    problem = value_problem(features, mean, std, MAX_ABS_Z)   # None, or where and what
"""

from __future__ import annotations

import numpy as np

from segmo.errors import SegmoError

MAX_ABS_Z = 1000.0
MAX_METRES = 1e4  # joints further from the origin are a corrupt file, not a motion


def joints_problem(joints: np.ndarray) -> str | None:
    """Where joint positions in metres (t, j, 3) are NaN/inf or beyond `MAX_METRES` (None
    when nowhere): what rendering and BVH export refuse (one frame of 3e38 passed the bone
    scale check and wrote rotations of ~1800 degrees)."""
    bad = ~np.isfinite(joints) | (np.abs(joints) > MAX_METRES)
    if not bad.any():
        return None
    frame = int(np.argwhere(bad)[0][0])
    return (f"{int(bad.any(axis=(1, 2)).sum())} frame(s) hold NaN/inf or joints beyond "
            f"{MAX_METRES:g} m (a corrupt file, not a motion); the first is frame {frame}")


def value_problem(arr: np.ndarray, mean: np.ndarray, std: np.ndarray,
                  max_abs_z: float | None = MAX_ABS_Z) -> str | None:
    """Where (t, d) raw features ``arr`` are non-finite or beyond ``max_abs_z``, or None."""
    arr = np.asarray(arr)
    if arr.dtype.kind not in "fiu":  # complex (its imaginary part would be dropped), text
        return f"values of type {arr.dtype}, not real numbers"
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


def check_motion_values(features: np.ndarray, mean: np.ndarray, std: np.ndarray,
                        name: str = "motion") -> None:
    """Raise SegmoError naming `name` when `features` are no motion (`value_problem`)."""
    problem = value_problem(features, mean, std)
    if problem is not None:
        raise SegmoError(f"{name}: not a motion (NaN/inf or absurd values, a corrupt file?): "
                         f"{problem}")
