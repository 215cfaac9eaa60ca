"""Fit a fixed skeleton to joint positions: what a BVH file (and an animation tool) needs.

Joint positions from a generator do not keep their bone lengths (a generated forearm may
grow and shrink by centimetres from frame to frame), while a BVH skeleton has one rest
pose and moves only by rotating its bones. `fit_skeleton` finds, for every frame, the root
position and the joint rotations of a skeleton with fixed bones that put its joints as
close as possible to the given ones (least squares over all joints, not bone by bone, so
that an error in one bone's length is not carried down the rest of the chain), and
optionally locks the feet while they are in contact with the ground.

Convention (the BVH one): a joint's rotation turns its child bones; the world rotation of
joint p is ``W_p = W_parent(p) @ L_p`` and a child's position is
``x_c = x_p + W_p @ offset_c``. Leaves turn nothing and keep their parent's rotation.

The rest pose: a T-pose, bones along the skeleton's ``tpose_directions`` (arms out along
x, head up), with the skeleton's reference bone lengths (``bone_lengths="skeleton"``) or
the motion's median bone lengths (``"motion"``); the children of a joint with several
children (pelvis: hips and spine; spine3: neck and collars) keep the motion's own layout,
averaged over its frames and turned as a whole onto those directions, because their
directions there are only nominal. So the files of one skeleton share their bone lengths
and limb directions, but those children's offsets differ from motion to motion by up to a
few centimetres (and `segmo.motion.bvh` picks each file's Euler orders): give each file
its own armature rather than one file's action another's.

Solving: the shortest-arc rotation of each bone (single child) or the Kabsch rotation
(several children) gives the start; a few L-BFGS iterations (torch, float64) then
minimise the squared distance of all joints, with a small penalty on the change between
frames of each joint's correction, which keeps the unobservable twist about a bone from
wandering.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import torch

from segmo.motion.features import FOOT_CONTACT_THRESHOLD
from segmo.motion.kinematics import bone_lengths as measure_bone_lengths
from segmo.motion.quaternion import qbetween, quat_to_matrix
from segmo.motion.skeleton import SkeletonSpec, get_skeleton

__all__ = ["SkeletonFit", "fit_motion", "fit_skeleton", "foot_contacts", "foot_skating", "lock_feet"]

CONTACT_HEIGHT = 0.05  # metres above the motion's lowest foot height that still count as ground
LOCK_BLEND = 3  # frames over which a locked foot moves to a new anchor or back to its own path
LOCK_RADIUS = 0.04  # metres a foot may slide "in contact" before it is anchored anew
LOCK_WEIGHT = 10.0  # weight of a locked foot joint's squared error in the fit


@dataclass
class SkeletonFit:
    """A fixed skeleton moving through a motion.

    offsets: (j, 3) rest offset of each joint from its parent (root: zeros).
    root: (t, 3) root positions.
    local: (t, j, 3, 3) local rotations (root: its world rotation; leaves: identity).
    parents: the skeleton's parent of each joint (-1 for the root).
    """

    offsets: np.ndarray
    root: np.ndarray
    local: np.ndarray
    parents: tuple[int, ...]

    @property
    def joints(self) -> np.ndarray:
        """(t, j, 3) joint positions of the skeleton (forward kinematics)."""
        return _forward(torch.from_numpy(self.local), torch.from_numpy(self.root),
                        torch.from_numpy(self.offsets), self.parents).numpy()


def _children(parents: tuple[int, ...]) -> list[list[int]]:
    children: list[list[int]] = [[] for _ in parents]
    for c, p in enumerate(parents):
        if p >= 0:
            children[p].append(c)
    return children


def _levels(parents: tuple[int, ...]) -> list[tuple[list[int], list[int]]]:
    """Joints grouped by depth below the root, with their parents: (joints, parents) per
    level, so that forward kinematics takes one step per level instead of per joint."""
    depth = [0] * len(parents)
    for c in range(1, len(parents)):
        depth[c] = depth[parents[c]] + 1
    return [([c for c in range(len(parents)) if depth[c] == d],
             [parents[c] for c in range(len(parents)) if depth[c] == d])
            for d in range(1, max(depth) + 1)]


def _forward(local: torch.Tensor, root: torch.Tensor, offsets: torch.Tensor,
             parents: tuple[int, ...]) -> torch.Tensor:
    """(t, j, 3, 3) local rotations, (t, 3) root, (j, 3) offsets -> (t, j, 3) positions."""
    world = torch.empty_like(local)
    positions = torch.empty(*local.shape[:2], 3, dtype=local.dtype)
    world[:, 0], positions[:, 0] = local[:, 0], root
    for joints, above in _levels(parents):
        positions[:, joints] = positions[:, above] + (world[:, above] @ offsets[joints, :, None])[..., 0]
        world[:, joints] = world[:, above] @ local[:, joints]
    return positions


def _kabsch(rest: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """Rotations (t, 3, 3) minimising sum_k |R rest_k - observed_t,k|^2.
    rest: (k, 3) or (t, k, 3); observed: (t, k, 3)."""
    h = np.einsum("...ki,tkj->tij", rest, observed)
    u, _, vt = np.linalg.svd(h)
    v, ut = np.swapaxes(vt, 1, 2), np.swapaxes(u, 1, 2)
    fix = np.ones((len(h), 3))
    fix[:, 2] = np.sign(np.linalg.det(v @ ut))
    return v @ (fix[:, :, None] * ut)


def _rest_offsets(positions: np.ndarray, spec: SkeletonSpec, children: list[list[int]],
                  lengths: np.ndarray) -> np.ndarray:
    offsets = np.asarray(spec.tpose_directions, dtype=np.float64) * lengths[:, None]
    for p, kids in enumerate(children):
        if len(kids) < 2:
            continue
        observed = positions[:, kids] - positions[:, p : p + 1]  # (t, k, 3)
        # The layout in frame 0, then its average over all frames in the joint's own frame
        # (one Procrustes-mean step), so that one odd frame does not set the rest pose.
        rotations = _kabsch(observed[0], observed)  # (t, 3, 3): frame 0's layout -> frame t
        mean = np.einsum("tji,tkj->ki", rotations, observed) / len(observed)  # R^T observed
        # Turned as a whole onto the nominal directions (hips along x, spine up, ...), so
        # that the rest pose faces the skeleton's front as the raw offsets do.
        nominal = np.asarray(spec.tpose_directions, dtype=np.float64)[kids] * lengths[kids, None]
        mean = mean @ _kabsch(mean, nominal[None])[0].T
        for k, c in enumerate(kids):
            offsets[c] = mean[k] / max(np.linalg.norm(mean[k]), 1e-12) * lengths[c]
    return offsets


def _transported(rest: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(t, 3, 3) rotations mapping `rest` (3,) onto each of `directions` (t, 3): the
    shortest arc in frame 0, then each frame's rotation is the previous one turned by the
    shortest arc between consecutive directions (parallel transport). The twist about the
    bone, which positions do not show, then changes as little as possible from frame to
    frame; the shortest arc from the rest direction alone flips it by up to 180 degrees
    when a bone passes opposite its rest direction (a shin kicked up, an arm raised)."""
    d = torch.from_numpy(directions)
    step = quat_to_matrix(qbetween(d[:-1], d[1:])).numpy() if len(d) > 1 else np.zeros((0, 3, 3))
    out = np.empty((len(directions), 3, 3))
    out[0] = quat_to_matrix(qbetween(torch.from_numpy(rest), d[0])).numpy()
    for f in range(1, len(directions)):
        out[f] = step[f - 1] @ out[f - 1]
    return out


def _initial_pose(positions: np.ndarray, offsets: np.ndarray, children: list[list[int]],
                  parents: tuple[int, ...]) -> np.ndarray:
    """(t, j, 3, 3) world rotations, joint by joint from the root: each joint aims its
    rest child offsets at the observed children as seen from where the fitted skeleton
    put the joint (one child: `_transported`; several: Kabsch), so that a bone that is too
    long or short in the data moves its own end only and not the whole chain."""
    t, j = positions.shape[:2]
    world = np.empty((t, j, 3, 3))
    fitted = np.empty_like(positions)
    fitted[:, 0] = positions[:, 0]
    for p in range(j):
        kids = children[p]
        if not kids:
            world[:, p] = world[:, parents[p]]
            continue
        observed = positions[:, kids] - fitted[:, p : p + 1]
        if len(kids) == 1:
            world[:, p] = _transported(offsets[kids[0]], observed[:, 0])
        else:
            world[:, p] = _kabsch(offsets[kids], observed)
        for c in kids:
            fitted[:, c] = fitted[:, p] + world[:, p] @ offsets[c]
    return world


def _rotvec_to_matrix(v: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula, (..., 3) -> (..., 3, 3), smooth at 0 (for autograd)."""
    theta2 = (v * v).sum(-1, keepdim=True)[..., None]
    theta = (theta2 + 1e-20).sqrt()
    small = theta2 < 1e-8
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / (theta2 + 1e-20))
    x, y, z = v.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*v.shape, 3)
    eye = torch.eye(3, dtype=v.dtype).expand_as(k)
    return eye + a * k + b * (k @ k)


def fit_skeleton(joints: Any, skeleton: str | SkeletonSpec = "t2m",
                 bone_lengths: Literal["skeleton", "motion"] | None = None,
                 iterations: int = 60, smoothness: float = 1e-3,
                 weights: np.ndarray | None = None) -> SkeletonFit:
    """Fit a fixed skeleton to `joints` (t, j, 3), y up, in the skeleton's units.

    bone_lengths: "skeleton" (the spec's reference lengths; the default where it has
    them) or "motion" (the median of the motion's own). iterations: L-BFGS iterations of
    the least-squares refinement (0 keeps the bone-by-bone start). smoothness: weight of
    the penalty on frame-to-frame changes of the corrections. weights: optional (t, j)
    weights of each joint's squared error (the foot lock raises the locked feet's).
    """
    spec = get_skeleton(skeleton)
    if hasattr(joints, "detach"):
        joints = joints.detach().cpu().numpy()
    if np.iscomplexobj(joints):  # np.asarray would drop the imaginary part
        raise ValueError("fit_skeleton: joints are complex numbers; expected real positions")
    positions = np.asarray(joints, dtype=np.float64)
    if positions.ndim != 3 or positions.shape[1:] != (spec.num_joints, 3) or len(positions) < 1:
        raise ValueError(f"fit_skeleton: joints must be (t, {spec.num_joints}, 3) for skeleton "
                         f"{spec.name!r}, got {positions.shape}")
    if not np.isfinite(positions).all():
        raise ValueError("fit_skeleton: joints hold NaN or inf")
    if bone_lengths is None:
        bone_lengths = "skeleton" if spec.reference_bone_lengths is not None else "motion"
    if bone_lengths == "skeleton":
        if spec.reference_bone_lengths is None:
            raise ValueError(f"fit_skeleton: skeleton {spec.name!r} has no reference bone "
                             "lengths; use bone_lengths='motion'")
        lengths = np.asarray(spec.reference_bone_lengths, dtype=np.float64) / spec.unit
    elif bone_lengths == "motion":
        lengths = np.median(measure_bone_lengths(torch.from_numpy(positions), spec.parents).numpy(), 0)
    else:
        raise ValueError(f"fit_skeleton: bone_lengths must be 'skeleton' or 'motion', got {bone_lengths!r}")
    parents = tuple(spec.parents)
    children = _children(parents)
    offsets = _rest_offsets(positions, spec, children, lengths)
    world = _initial_pose(positions, offsets, children, parents)
    local = np.swapaxes(world[:, [max(p, 0) for p in parents]], -1, -2) @ world
    local[:, 0] = world[:, 0]
    leaves = [c for c in range(len(parents)) if not children[c]]
    local[:, leaves] = np.eye(3)
    fit = SkeletonFit(offsets, positions[:, 0].copy(), local, parents)
    if iterations > 0:
        # One thread: the tensors are tiny, and a second thread only waits on a busy core
        # (measured: 0.5 s with one, 3-8 s with two beside a training run on 2 cores).
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            fit = _refine(fit, positions, children, iterations, smoothness, weights)
        finally:
            torch.set_num_threads(threads)
    return fit


def _refine(fit: SkeletonFit, target: np.ndarray, children: list[list[int]], iterations: int,
            smoothness: float, weights: np.ndarray | None) -> SkeletonFit:
    movable = [p for p in range(len(fit.parents)) if children[p]]
    start = torch.from_numpy(fit.local)
    offsets = torch.from_numpy(fit.offsets)
    goal = torch.from_numpy(target)
    w = torch.ones(goal.shape[:2], dtype=goal.dtype) if weights is None else torch.as_tensor(weights, dtype=goal.dtype)
    delta = torch.zeros(len(target), len(movable), 3, dtype=torch.float64, requires_grad=True)
    shift = torch.zeros(len(target), 3, dtype=torch.float64, requires_grad=True)
    scale = 1.0 / max(float((goal - goal.mean((0, 1))).pow(2).mean()), 1e-12)

    def pose() -> tuple[torch.Tensor, torch.Tensor]:
        local = start.clone()
        local[:, movable] = start[:, movable] @ _rotvec_to_matrix(delta)
        return local, torch.from_numpy(fit.root) + shift

    optimizer = torch.optim.LBFGS([delta, shift], lr=1.0, max_iter=iterations, history_size=20,
                                  tolerance_grad=1e-12, tolerance_change=1e-14,
                                  line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        optimizer.zero_grad()
        local, root = pose()
        error = ((_forward(local, root, offsets, fit.parents) - goal) ** 2).sum(-1)
        loss = (w * error).sum() * scale / len(goal)
        if len(goal) > 1 and smoothness > 0:
            loss = loss + smoothness * (delta[1:] - delta[:-1]).pow(2).sum() / len(goal)
        loss.backward()
        return loss

    optimizer.step(closure)
    with torch.no_grad():
        local, root = pose()
    return SkeletonFit(fit.offsets, root.numpy(), local.numpy(), fit.parents)


# How far (a factor) the bones of joints from elsewhere may be from the skeleton's
# reference lengths when those are used: captured motions are within a few per cent.
MAX_BONE_RATIO = 2.0


def check_bone_scale(positions: np.ndarray, skeleton: str | SkeletonSpec, where: str) -> None:
    """ValueError when the bones of `positions` (t, j, 3) are more than MAX_BONE_RATIO times
    longer or shorter than the skeleton's reference lengths: joints in centimetres, or no
    skeleton at all, would get the reference's bones under a root that moves in other
    units, a BVH of another motion. (A model's own joints are fitted to the reference
    whatever their bones; this is for joints given from elsewhere.)"""
    spec = get_skeleton(skeleton)
    if spec.reference_bone_lengths is None:
        return
    reference = np.asarray(spec.reference_bone_lengths, dtype=np.float64) / spec.unit
    measured = np.median(measure_bone_lengths(torch.from_numpy(positions), spec.parents).numpy(), 0)
    ratio = float(measured.sum() / reference.sum())
    if not 1 / MAX_BONE_RATIO <= ratio <= MAX_BONE_RATIO:
        raise ValueError(f"{where}: the joints' bones are {ratio:.3g} times as long as the "
                         f"{spec.name!r} skeleton's: positions in other units than the "
                         "skeleton's, or not this skeleton? Convert them, or pass "
                         "bone_lengths='motion'")


def fit_motion(joints: Any, skeleton: str | SkeletonSpec = "t2m", foot_lock: bool = True,
               contacts: np.ndarray | None = None,
               bone_lengths: Literal["skeleton", "motion"] | None = None) -> SkeletonFit:
    """The fixed skeleton that a BVH file (and a generated motion's joints) shows: with
    `foot_lock`, each foot joint held where it touched down while in contact (`contacts`
    (t, 4) bool: left ankle, left toe, right ankle, right toe; default `foot_contacts` of
    the joints), its error weighted LOCK_WEIGHT times in the fit; bone lengths as in
    `fit_skeleton`."""
    spec = get_skeleton(skeleton)
    if hasattr(joints, "detach"):
        joints = joints.detach().cpu().numpy()
    positions = np.asarray(joints, dtype=np.float64)
    weights = None
    if contacts is not None:
        contacts = np.asarray(contacts)
        if contacts.dtype != bool:  # the features' contact channels (0.1-1.1) all read True
            raise ValueError(f"fit_motion: contacts must be booleans, got {contacts.dtype} "
                             "(threshold contact channels first, e.g. features[:, -4:] > 0.5)")
        if not foot_lock:
            raise ValueError("fit_motion: contacts given with foot_lock=False, which locks no "
                             "foot; pass foot_lock=True or leave contacts out")
    if foot_lock and positions.ndim == 3 and positions.shape[1:] == (spec.num_joints, 3):
        contacts = foot_contacts(positions, spec) if contacts is None else contacts
        if contacts.shape != (len(positions), 4):
            raise ValueError(f"fit_motion: contacts must be ({len(positions)}, 4), got {contacts.shape}")
        feet = list(spec.feet_left) + list(spec.feet_right)
        weights = np.ones(positions.shape[:2])
        weights[:, feet] += (LOCK_WEIGHT - 1) * contacts
        positions = lock_feet(positions, contacts, spec)
    return fit_skeleton(positions, spec, bone_lengths=bone_lengths, weights=weights)


# ---------------------------------------------------------------- feet
def foot_contacts(joints: np.ndarray, skeleton: str | SkeletonSpec = "t2m") -> np.ndarray:
    """(t, 4) bool: left ankle, left toe, right ankle, right toe in contact with the ground.

    A foot joint is in contact in a frame when it moves less than HumanML3D's threshold
    to the next frame (its features' contact rule) and is within 5 cm of the motion's
    lowest foot height.
    """
    spec = get_skeleton(skeleton)
    positions = np.asarray(joints, dtype=np.float64)
    feet = list(spec.feet_left) + list(spec.feet_right)
    step = ((positions[1:, feet] - positions[:-1, feet]) ** 2).sum(-1)  # (t-1, 4)
    step = np.concatenate([step, step[-1:]], 0) if len(step) else np.zeros((len(positions), 4))
    slow = step < FOOT_CONTACT_THRESHOLD / spec.unit**2
    height = positions[:, feet, 1]
    low = height < height.min() + CONTACT_HEIGHT / spec.unit
    return slow & low


def foot_skating(joints: np.ndarray, contacts: np.ndarray, skeleton: str | SkeletonSpec = "t2m",
                 fps: float | None = None) -> float:
    """Mean horizontal speed (units per second) of the foot joints in the frames where
    `contacts` (t, 4) says they touch the ground; 0 when they never do."""
    spec = get_skeleton(skeleton)
    positions = np.asarray(joints, dtype=np.float64)
    feet = list(spec.feet_left) + list(spec.feet_right)
    speed = np.linalg.norm(np.diff(positions[:, feet][..., [0, 2]], axis=0), axis=-1)
    speed = speed * (spec.fps if fps is None else fps)  # (t-1, 4)
    both = contacts[:-1] & contacts[1:]
    return float(speed[both].mean()) if both.any() else 0.0


def lock_feet(joints: np.ndarray, contacts: np.ndarray, skeleton: str | SkeletonSpec = "t2m",
              radius: float = LOCK_RADIUS) -> np.ndarray:
    """Target joints (t, j, 3) in which each foot joint stays where it touched down while
    `contacts` (t, 4) says it is on the ground, heights kept.

    A foot that slides further than `radius` (metres) from its anchor while still "in
    contact" (the contact rule also takes slow steps) gets a new anchor where it is,
    reached over LOCK_BLEND frames instead of in one jump; after a contact the locked
    foot eases back to its own path over LOCK_BLEND frames.
    """
    spec = get_skeleton(skeleton)
    target = np.array(joints, dtype=np.float64)
    radius = radius / spec.unit
    feet = list(spec.feet_left) + list(spec.feet_right)
    for k, joint in enumerate(feet):
        own = target[:, joint, :][:, [0, 2]].copy()
        locked = own.copy()
        anchor = previous = correction = None
        since = after = 0
        for f in range(len(own)):
            if contacts[f, k]:
                if anchor is None or np.linalg.norm(own[f] - anchor) > radius:
                    previous, anchor, since = anchor, own[f].copy(), 0
                w = (since + 1) / (LOCK_BLEND + 1)
                locked[f] = anchor if previous is None or since >= LOCK_BLEND else (1 - w) * previous + w * anchor
                since += 1
                correction = None
            else:
                if anchor is not None:  # the contact just ended: ease out from the lock
                    correction, after = locked[f - 1] - own[f - 1], 0
                anchor = previous = None
                if correction is not None and after < LOCK_BLEND:
                    after += 1
                    locked[f] = own[f] + correction * (1 - after / (LOCK_BLEND + 1))
        target[:, joint, 0], target[:, joint, 2] = locked[:, 0], locked[:, 1]
    return target
