"""Export joint positions to BVH (Biovision hierarchy) for Blender, MotionBuilder, game engines.

The hierarchy is the skeleton's own joint tree (t2m: the 22 SMPL joints) with one rest
pose (a T-pose; `segmo.motion.skeleton_fit`), and the motion is what a fixed skeleton
fitted to the joints does: generated joints whose bones stretch become a skeleton whose
bones do not, as close to them as fixed bones allow. With `foot_lock` the feet stay put
while they touch the ground (the contact rule of HumanML3D's features), which removes
the foot sliding a generator leaves.

Channels: the root has `Xposition Yposition Zposition` and three rotation channels, every
other joint three rotation channels, in degrees. A Tait-Bryan order locks where its middle
angle reaches 90 degrees, and near there a small turn moves its other two angles a lot; so
each file picks, per joint, the order whose angle curves change least between frames
(`euler_orders`); the root's order turns about y first (``YXZ`` or ``YZX``), so that the
heading of a walking, turning human is one channel and never the middle one. The angles are continuous from frame to frame (of the two
triples of each rotation, and their turns by 360 degrees, the one nearest the previous
frame), and at an exact lock the first angle keeps its previous value. The channel order
is the BVH one: ``Zrotation Yrotation Xrotation`` means R = Rz(z) @ Ry(y) @ Rx(x), and a
child's position is parent + R_parent_world @ offset.
"""

from __future__ import annotations

import math
import numbers
import warnings
from pathlib import Path
from typing import Any, Literal

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from segmo.errors import SegmoError
from segmo.motion.checks import joints_problem
from segmo.motion.skeleton import SkeletonSpec, get_skeleton
from segmo.motion.skeleton_fit import SkeletonFit, check_bone_scale, fit_motion

__all__ = ["ANIMATION_FPS", "MAX_BVH_FPS", "MIN_BVH_FPS", "check_bvh_fps", "joints_to_bvh",
           "euler_orders", "continuous_euler", "metres_scale", "write_bvh"]

# Frame rate of the BVH files segmo writes for animation tools (`segmo generate`, `edit`,
# `compose`, `serve`, `GenerationOutput.save`): at the data's 20 fps a punch or a kick turns a
# joint by 50-60 degrees between frames (the real HumanML3D fixture too), which a tool's
# interpolation between keys cannot follow; at 60 fps (slerp between the data's frames, which
# are kept) no channel of the corpus test split moves by more than 30 degrees a frame.
ANIMATION_FPS = 60.0
# The frame rates a BVH file is written at or resampled from: from 12 fps, the lowest rate
# animation plays at, at which the shortest motion (one token, 4 frames at 20 fps: 0.15 s)
# still has two frames, to 480 fps, above what motion capture records; beyond it the
# resampled rotations only grow (1e7 fps asked for 28.8 GiB), below it a motion collapses
# to one pose.
MIN_BVH_FPS, MAX_BVH_FPS = 12.0, 480.0

END_SITE_LENGTH = 0.05  # metres: the nominal tip drawn after leaf joints
ROOT_ORDERS = ("YXZ", "YZX")  # heading (about y, up) first
ORDERS = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")


def euler_orders(local: np.ndarray) -> list[str]:
    """Each joint's Euler order (intrinsic, the BVH channel order) for local rotations
    (t, j, 3, 3): the one whose continuous angles (`continuous_euler`) change least from
    one frame to the next (the smallest largest change); near its lock an order turns a
    small rotation into a large change of its first and last angles. The root chooses
    among `ROOT_ORDERS`, the others among all six Tait-Bryan orders, ties going to the
    first listed."""
    t, j = local.shape[:2]
    worst = {}
    for order in ORDERS:
        angles = continuous_euler(local, order)  # (t, j, 3)
        worst[order] = (np.abs(np.diff(angles, axis=0)).max((0, 2)) if t > 1 else np.zeros(j))
    orders = []
    for joint in range(j):
        allowed = ROOT_ORDERS if joint == 0 else ORDERS
        orders.append(min(allowed, key=lambda o: (round(float(worst[o][joint]), 9), allowed.index(o))))
    return orders


def continuous_euler(rotations: np.ndarray, order: str) -> np.ndarray:
    """(t, ..., 3, 3) rotations -> (t, ..., 3) intrinsic Euler angles in radians,
    continuous in t.

    Each rotation has two triples (a, b, c) and (a + pi, pi - b, c + pi); the sequence of
    choices with the smallest summed squared change between frames is taken (a two-state
    Viterbi pass), then each angle is unwrapped (shifted by the multiple of 2 pi nearest
    its previous value). At (or within 1e-6 of) the lock, where only a combination of the
    first and third angles is defined, the first keeps its previous value and the third
    takes the rest.
    """
    t = len(rotations)
    batch = rotations.shape[1:-2]
    if t == 0:
        return np.zeros((0, *batch, 3))
    flat = np.asarray(rotations, dtype=np.float64).reshape(t, -1, 3, 3)
    n = flat.shape[1]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # scipy's "gimbal lock detected"
        base = Rotation.from_matrix(flat.reshape(-1, 3, 3)).as_euler(order).reshape(t, n, 3)
    alternative = np.stack([base[..., 0] + np.pi, np.pi - base[..., 1], base[..., 2] + np.pi], -1)
    candidates = np.stack([base, alternative], axis=2)  # (t, n, 2, 3)

    def change(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        d = (b - a + np.pi) % (2 * np.pi) - np.pi
        return (d * d).sum(-1)

    cost = np.zeros((n, 2))
    back = np.zeros((t, n, 2), dtype=np.int64)
    for f in range(1, t):
        total = cost[:, :, None] + change(candidates[f - 1][:, :, None], candidates[f][:, None, :])
        back[f] = total.argmin(1)
        cost = total.min(1)
    choice = np.zeros((t, n), dtype=np.int64)
    choice[-1] = cost.argmin(-1)
    for f in range(t - 1, 0, -1):
        choice[f - 1] = back[f, np.arange(n), choice[f]]
    out = np.take_along_axis(candidates, choice[:, :, None, None], axis=2)[:, :, 0]
    out = np.unwrap(out, axis=0)
    axes = {"X": np.array([1.0, 0, 0]), "Y": np.array([0, 1.0, 0]), "Z": np.array([0, 0, 1.0])}
    for f, k in zip(*np.nonzero(np.abs(np.cos(base[..., 1])) < 1e-6)):
        if f == 0:
            continue
        a, b = out[f - 1, k, 0], out[f, k, 1]
        rest = (Rotation.from_rotvec(axes[order[1]] * b).inv()
                * Rotation.from_rotvec(axes[order[0]] * a).inv() * Rotation.from_matrix(flat[f, k]))
        c = float(rest.as_rotvec() @ axes[order[2]])
        out[f, k] = [a, b, c + 2 * np.pi * np.round((out[f - 1, k, 2] - c) / (2 * np.pi))]
    return out.reshape(t, *batch, 3)


def check_bvh_fps(fps: Any, name: str) -> float:
    """`fps` as a float when it is a frame rate in [MIN_BVH_FPS, MAX_BVH_FPS]; a SegmoError
    naming the argument `name` otherwise."""
    try:
        value = float(fps)
    except (TypeError, ValueError):
        value = float("nan")
    if not MIN_BVH_FPS <= value <= MAX_BVH_FPS:  # NaN too
        raise SegmoError(f"{name}: expected a frame rate in [{MIN_BVH_FPS:g}, {MAX_BVH_FPS:g}] "
                         f"fps, got {fps!r}")
    return value


def _resample(fit: SkeletonFit, fps: float, target_fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Root (t', 3) and local rotations (t', j, 3, 3) at `target_fps` (linear / slerp)."""
    t = len(fit.root)
    if target_fps == fps or t < 2:
        return fit.root, fit.local
    times = np.arange(t) / fps
    new_times = np.arange(int(np.floor(times[-1] * target_fps + 1e-9)) + 1) / target_fps
    # k / target_fps can pass the last time by a rounding error (75 / 20 -> 84 / 22.4), and
    # Slerp refuses a time past its last
    new_times = np.minimum(new_times, times[-1])
    root = np.stack([np.interp(new_times, times, fit.root[:, k]) for k in range(3)], -1)
    local = np.empty((len(new_times), *fit.local.shape[1:]))
    for joint in range(fit.local.shape[1]):
        local[:, joint] = Slerp(times, Rotation.from_matrix(fit.local[:, joint]))(new_times).as_matrix()
    return root, local


def check_scale(scale: Any, where: str) -> None:
    """A BVH's length scale must be a finite number > 0 (0 collapses every bone, a negative
    one mirrors the motion through the origin, NaN writes 'nan' into the file)."""
    if isinstance(scale, bool) or not isinstance(scale, numbers.Real) \
            or not math.isfinite(scale) or scale <= 0:
        raise ValueError(f"{where}: scale must be a finite number > 0, got {scale!r}")


def metres_scale(skeleton: str | SkeletonSpec) -> float:
    """The scale that writes a skeleton's lengths in metres, what animation tools take a
    BVH's units for (Blender imports one unit as one metre): 1 for t2m, whose data are in
    metres, 0.001 for KIT-ML's millimetres (a KIT file in millimetres imported as a figure
    1.7 km tall)."""
    return get_skeleton(skeleton).unit


def write_bvh(fit: SkeletonFit, path: str | Path, skeleton: str | SkeletonSpec = "t2m",
              fps: float | None = None, target_fps: float | None = None,
              scale: float | None = None) -> Path:
    """Write a fitted skeleton (`segmo.motion.skeleton_fit.fit_skeleton`) as a BVH file.

    fps: the fit's frame rate (default the skeleton's); target_fps: the file's (default
    the same; other rates are resampled, rotations by slerp); both within [MIN_BVH_FPS,
    MAX_BVH_FPS] (`check_bvh_fps`). scale multiplies the fit's lengths, which are in the
    skeleton's data units; default: metres (`metres_scale`).
    """
    spec = get_skeleton(skeleton)
    scale = metres_scale(spec) if scale is None else scale
    if tuple(fit.parents) != tuple(spec.parents):  # another skeleton's fit, or none
        raise ValueError(f"write_bvh: the fit is of a skeleton of {len(fit.parents)} joints "
                         f"other than {spec.name!r}; pass the skeleton it was fitted to")
    check_scale(scale, "write_bvh")
    fps = check_bvh_fps(spec.fps if fps is None else fps, "write_bvh: fps")
    target_fps = fps if target_fps is None else check_bvh_fps(target_fps, "write_bvh: target_fps")
    root, local = _resample(fit, fps, target_fps)
    orders = euler_orders(local)
    angles = np.stack([np.degrees(continuous_euler(local[:, j], orders[j]))
                       for j in range(spec.num_joints)], 1)  # (t, j, 3) in each joint's order
    children: list[list[int]] = [[] for _ in range(spec.num_joints)]
    for c, p in enumerate(spec.parents):
        if p >= 0:
            children[p].append(c)

    lines = ["HIERARCHY"]

    def write(joint: int, depth: int) -> None:
        pad = "  " * depth
        offset = fit.offsets[joint] * scale
        rotation = " ".join(f"{axis}rotation" for axis in orders[joint])
        lines.append(f"{pad}{'ROOT' if joint == 0 else 'JOINT'} {spec.joint_names[joint]}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {offset[0]:.6f} {offset[1]:.6f} {offset[2]:.6f}")
        if joint == 0:
            lines.append(f"{pad}  CHANNELS 6 Xposition Yposition Zposition {rotation}")
        else:
            lines.append(f"{pad}  CHANNELS 3 {rotation}")
        for child in children[joint]:
            write(child, depth + 1)
        if not children[joint]:
            tip = np.asarray(spec.tpose_directions[joint], dtype=np.float64) * END_SITE_LENGTH / spec.unit * scale
            lines.append(f"{pad}  End Site")
            lines.append(f"{pad}  {{")
            lines.append(f"{pad}    OFFSET {tip[0]:.6f} {tip[1]:.6f} {tip[2]:.6f}")
            lines.append(f"{pad}  }}")
        lines.append(f"{pad}}}")

    write(0, 0)
    lines += ["MOTION", f"Frames: {len(root)}", f"Frame Time: {1.0 / target_fps:.6f}"]
    order = _depth_first(children)
    for frame in range(len(root)):
        values = list(root[frame] * scale)
        for joint in order:
            values.extend(angles[frame, joint])
        lines.append(" ".join(f"{v:.6f}" for v in values))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


def joints_to_bvh(
    joints: Any,
    path: str | Path,
    fps: float | None = None,
    skeleton: str | SkeletonSpec = "t2m",
    scale: float | None = None,
    target_fps: float | None = None,
    foot_lock: bool = True,
    contacts: np.ndarray | None = None,
    bone_lengths: Literal["skeleton", "motion"] | None = None,
) -> Path:
    """Write joints (t, j, 3) (numpy or torch, y up) as a BVH file and return its path.

    fps: the joints' frame rate, default the skeleton's (t2m: 20); target_fps: the file's
    (default the same); both within [MIN_BVH_FPS, MAX_BVH_FPS]. scale multiplies all lengths
    of the data units (default: metres, `metres_scale`; for t2m, whose data are metres, 100
    gives centimetres; KIT-ML's are millimetres, and 1 keeps them). foot_lock, contacts,
    bone_lengths: see `segmo.motion.skeleton_fit.fit_motion`; `write_bvh` writes a fit made
    elsewhere.
    """
    spec = get_skeleton(skeleton)
    scale = metres_scale(spec) if scale is None else scale
    check_scale(scale, "joints_to_bvh")  # before the fit
    for name, value in (("fps", fps), ("target_fps", target_fps)):
        if value is not None:  # before the fit
            check_bvh_fps(value, f"joints_to_bvh: {name}")
    if hasattr(joints, "detach"):
        joints = joints.detach().cpu()
        joints = (joints if joints.is_complex() else joints.double()).numpy()  # bf16 has no numpy type
    if np.iscomplexobj(joints):  # np.asarray would drop the imaginary part
        raise ValueError("joints_to_bvh: joints are complex numbers; expected real positions")
    # C order: a Fortran-ordered copy of the same joints rounded differently in the fit and
    # wrote other (equivalent) Euler triples
    positions = np.ascontiguousarray(joints, dtype=np.float64)
    if positions.ndim != 3 or positions.shape[1:] != (spec.num_joints, 3) or len(positions) < 1:
        raise ValueError(
            f"joints_to_bvh: joints must be (t, {spec.num_joints}, 3) for skeleton {spec.name!r}, "
            f"got {positions.shape}"
        )
    problem = joints_problem(positions * spec.unit)
    if problem:
        raise ValueError(f"joints_to_bvh: {problem}")
    if bone_lengths in (None, "skeleton"):
        check_bone_scale(positions, spec, "joints_to_bvh")
    fit = fit_motion(positions, spec, foot_lock=foot_lock, contacts=contacts, bone_lengths=bone_lengths)
    return write_bvh(fit, path, spec, fps=fps, target_fps=target_fps, scale=scale)


def _depth_first(children: list[list[int]]) -> list[int]:
    """Joint order of the MOTION columns: the order joints appear in the hierarchy."""
    order, stack = [], [0]
    while stack:
        joint = stack.pop()
        order.append(joint)
        stack.extend(reversed(children[joint]))
    return order
