"""Sequencing: sample 1-5 actions, build them, blend them into one motion.

Four corpus versions. The first three sample differently. Version 1 draws each action in turn while
leaving room for the ones still to come, so the actions of one motion last nearly
equally long. Version 2 draws every action with durations that follow the action and
its parameters (`segmo.synth.actions.SAMPLE_V2`), then redraws the longest until the
motion fits in MAX_FRAMES with its longest action at most MAX_RATIO times its shortest.
Version 3 samples as version 2 and makes every motion of two or more actions hold a
short one (SHORT_V2, about a second) beside a long one (LONG_V3, several seconds), the
longest between MIN_RATIO_V3 and MAX_RATIO times the shortest: in version 2 half of the
motions had actions of similar lengths, where a split into equal parts still finds
them (uniform R@1 at IoU 0.5 0.79 on the test split). Version 4 samples as version 3 (motion i
draws the same actions, durations and parameters) with a rig whose joints turn all their
children together (`segmo.synth.rig.rigid_branches`): in versions 1-3 the neck bone turns
apart from the collars and the spine1 bone apart from the hips, which a BVH or SMPL
hierarchy cannot show (up to 23 mm in arms-up motions).

Consecutive actions overlap by a 5-15 frame transition in which local rotations are
slerped and the root is interpolated; each action is placed where the previous one is at
the start of the transition, so the root is continuous and locomotion carries on along
the current heading. The ground-truth boundary is the middle of the transition.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from segmo.data.attributes import attribute_labels
from segmo.motion.kinematics import forward_kinematics
from segmo.motion.skeleton import T2M
from segmo.synth.actions import ACTIONS, OVERLAYS, build_action, sample_params
from segmo.synth.gait import gaussian, sliding
from segmo.synth.rig import REST_OFFSETS, axis_angle, qmul, qrot, rigid_branches, slerp, solve_pose

VERSION = 3  # what `sample_motion` and `segmo synth` build unless told otherwise
VERSIONS = (1, 2, 3, 4)
MIN_FRAMES, MAX_FRAMES = 40, 196  # feature frames (joint frames - 1)
# Version 2: the longest / shortest action of one motion (built frames); draws of the
# longest action before a short one (SHORT_V2, about a second each) takes its place.
MAX_RATIO = 5.0
FIT_ATTEMPTS, REDRAWS = 30, 4
SHORT_V2 = ("kick", "punch", "wave", "clap", "turn", "bow", "jump_in_place", "raise_arm")
# Version 3: the actions that last several seconds, and the least longest / shortest ratio
# of a motion of two or more actions.
LONG_V3 = ("walk_forward", "walk_backward", "jog", "run", "side_step", "walk_circle", "stand_still")
# With two or three actions a ratio under about 4 lets a split into equal parts still
# reach IoU 0.5 (1 : 3.5 : 1 does); four or five leave no room for 4 with 4-5 actions.
MIN_RATIO_V3 = {2: 4.0, 3: 4.0, 4: 3.5, 5: 3.5}
SEGMENT_COUNTS = (1, 2, 3, 4, 5)
SEGMENT_WEIGHTS = (0.3, 0.33, 0.22, 0.1, 0.05)
OVERLAY_PROBABILITY = 0.25
# Version 1 only: the room left for each action still to come (the shortest actions take
# about this many frames), and the actions drawn when the frames left per remaining
# segment are few, so that 4-5 segments fit.
RESERVE_FRAMES = 32
SHORT_ACTIONS = ("kick", "punch", "wave", "clap", "turn", "bow", "jump_in_place", "raise_arm",
                 "stand_up", "sit_down", "stand_still", "walk_backward")
# How often each action is drawn (relative); locomotion is the most common in real data.
ACTION_WEIGHTS = {"walk_forward": 3.0, "run": 1.5, "jog": 1.2, "walk_backward": 1.2, "turn": 1.5,
                  "sit_down": 1.0, "stand_up": 4.0, "stand_still": 0.8}


@dataclass
class Segment:
    """One executed action; start/end are feature rows (end exclusive)."""

    action: str
    params: dict
    overlay: tuple[str, dict] | None = None
    start: int = 0
    end: int = 0


@dataclass
class SynthMotion:
    """joints: (t + 1, 22, 3) generated positions (metres, y up); segments cover the t
    feature frames that `joints_to_features(joints)` gives."""

    joints: np.ndarray
    segments: list[Segment] = field(default_factory=list)

    @property
    def num_frames(self) -> int:
        return len(self.joints) - 1


def _choose(rng: np.random.Generator, sitting: bool, previous: str | None, short: bool) -> str:
    names = [n for n, a in ACTIONS.items()
             if n != previous and (a.needs == "any" or a.needs == ("sitting" if sitting else "standing"))
             and (not short or n in SHORT_ACTIONS)]
    weights = np.array([ACTION_WEIGHTS.get(n, 1.0) for n in names])
    return names[int(rng.choice(len(names), p=weights / weights.sum()))]


def _clip(rng, name, params, overlay, sitting):
    """-> (local quats (t, 22, 4) with the heading in q[:, 0], root (t, 3), yaw (t,))."""
    track = build_action(name, params, rng, sitting, overlay)
    return solve_pose(track), track.root.copy(), track.yaw.copy()


def _hold(clip, before: int, after: int):
    q, root, yaw = clip
    pad = lambda x: np.concatenate([np.repeat(x[:1], before, 0), x, np.repeat(x[-1:], after, 0)])  # noqa: E731
    return pad(q), pad(root), pad(yaw)


def sample_motion(rng: np.random.Generator, version: int = VERSION) -> SynthMotion:
    """Sample and build one motion (its joints and ground-truth segments) of corpus
    `version` (`VERSIONS`)."""
    if version == 1:
        return _sample_v1(rng)
    if version in (2, 3, 4):
        return _sample_v2(rng, version)
    raise ValueError(f"sample_motion: version must be one of {VERSIONS}, got {version!r}")


def _overlay(rng, spec):
    if spec.locomotion and rng.random() < OVERLAY_PROBABILITY:
        upper = list(OVERLAYS)[int(rng.integers(len(OVERLAYS)))]
        return upper, OVERLAYS[upper](rng)
    return None


def _sample_v2(rng: np.random.Generator, version: int) -> SynthMotion:
    """Versions 2, 3 and 4 (see the module docstring)."""
    contrast = version >= 3
    count = int(rng.choice(SEGMENT_COUNTS, p=SEGMENT_WEIGHTS))
    sitting, previous, names, seated = False, None, [], []
    for _ in range(count):  # the order of actions first (body states), then their lengths
        previous = _choose(rng, sitting, previous, short=False)
        names.append(previous)
        seated.append(sitting)
        sitting = {"sitting": True, "standing": False}.get(ACTIONS[previous].ends, sitting)
    if contrast and count >= 2:
        _hold_contrast(rng, names, seated)
    overlaps = [0] + [int(rng.integers(5, 16)) for _ in names[1:]]
    plan = [_draw(rng, name, sit, version) for name, sit in zip(names, seated)]
    while True:
        for attempt in range(FIT_ATTEMPTS):
            frames = [len(track.root) for _, _, track in plan]
            total = _blended_frames(frames, overlaps)
            # Version 3 asks for the spread where a long action could be placed.
            spread = (not contrast or len(plan) < 2 or not any(n in LONG_V3 for n in names[:len(plan)])
                      or max(frames) >= MIN_RATIO_V3[len(plan)] * min(frames))
            if total <= MAX_FRAMES + 1 and max(frames) <= MAX_RATIO * min(frames) and spread:
                return _assemble(rng, names[:len(plan)], plan, overlaps[:len(plan)],
                                 rigid=version >= 4)
            i = int(np.argmax(frames))
            if not spread and attempt % 2:  # too alike: draw the shortest again instead
                i = int(np.argmin(frames))
            if (attempt >= REDRAWS and ACTIONS[names[i]].ends is None and spread
                    and not (contrast and _only_long(names[:len(plan)], i))):
                # Its draws keep it too long: a short action takes its place instead.
                neighbours = names[max(i - 1, 0):i] + names[i + 1:i + 2]
                names[i] = choose_short(rng, seated[i], neighbours)
            plan[i] = _draw(rng, names[i], seated[i], version)
        if len(plan) == 1:  # cannot happen with the library's lengths; keep the loop finite
            raise RuntimeError(f"sample_motion: {names[0]} never fits in {MAX_FRAMES} frames")
        plan.pop()  # these actions do not fit together: drop the last one (keeps body states)


def _blended_frames(frames: list[int], overlaps: list[int]) -> int:
    """Frames of clips of `frames` blended over `overlaps` (`overlaps[0]` is 0): what `_hold`
    and `_blend` make of them (see `_sample_v1`)."""
    return sum(frames) + sum(o // 3 + (o + 1) // 2 - o for o in overlaps[1:len(frames)])


RESAMPLE_KEEPS = ("all", "named", "none")


def _named(name: str, params: dict) -> tuple:
    """What a caption can say of an action's parameters (`segmo.synth.captions`): its side,
    count and speed class (`attribute_labels`, the attribute metric's classes), a turn's
    angle ("turns around") and whether a bow is deep."""
    shape = (params.get("angle") if name == "turn" else
             params.get("angle", 0) > 55 if name == "bow" else None)
    return attribute_labels(name, params), shape


def resample_motion(rng: np.random.Generator, actions: list[dict], version: int = VERSION,
                    keep: str = "all") -> SynthMotion:
    """A new realization of a corpus motion's action sequence (its ground truth's `actions`:
    {"action", "params", optional "with": {"action", "params"}}): the same actions in the
    same order, with new transitions, rests and idiosyncrasy, and of their parameters
    (`keep`) all the given ones, what a caption can name of them (`_named`: the parameters
    drawn anew, as corpus `version` draws them, until they agree with the given ones on
    it), or none. Unless all are kept, the longest action is drawn again (up to FIT_ATTEMPTS
    times) while the motion is longer than MAX_FRAMES. What a generator that gets a
    caption's actions right could make of it (tools/fid_floor.py)."""
    if keep not in RESAMPLE_KEEPS:
        raise ValueError(f"resample_motion: keep must be one of {RESAMPLE_KEEPS}, got {keep!r}")
    names = [a["action"] for a in actions]
    seated = seated_before(names)

    def like(name: str, given: dict, sample) -> dict:
        if keep == "all":
            return given
        if keep == "none":
            return sample(rng)
        want = _named(name, given)
        for _ in range(1000):  # a few dozen at most for the rarest combination (wave: hand × count)
            params = sample(rng)
            if _named(name, params) == want:
                return params
        raise ValueError(f"resample_motion: {name} {given} names what corpus version {version} never draws")

    def draw(i: int) -> tuple[dict, tuple[str, dict] | None, object]:
        given, over = actions[i], None
        if "with" in given:
            upper = given["with"]["action"]
            over = upper, like(upper, given["with"]["params"], OVERLAYS[upper])
        params = like(names[i], given["params"], lambda r: sample_params(names[i], r, version))
        return params, over, build_action(names[i], params, rng, seated[i], over)

    overlaps = [0] + [int(rng.integers(5, 16)) for _ in names[1:]]
    plan = [draw(i) for i in range(len(names))]
    for _ in range(0 if keep == "all" else FIT_ATTEMPTS):
        frames = [len(track.root) for _, _, track in plan]
        if _blended_frames(frames, overlaps) <= MAX_FRAMES + 1:
            break
        i = int(np.argmax(frames))
        plan[i] = draw(i)
    return _assemble(rng, names, plan, overlaps, rigid=version >= 4)


def _only_long(names: list[str], i: int) -> bool:
    return names[i] in LONG_V3 and sum(n in LONG_V3 for n in names) == 1


def _hold_contrast(rng, names: list[str], seated: list[bool]) -> None:
    """Version 3: make `names` hold a long and a short action, replacing actions that leave
    the body state as it is (the body states of the sequence stay valid). With four or
    more actions only one stays long and the others become short ones: a long action 3.5×
    a short one leaves no room for a second long or a medium one in MAX_FRAMES."""
    if len(names) >= 4:
        longs = [i for i, n in enumerate(names) if n in LONG_V3]
        keep = longs[int(rng.integers(len(longs)))] if longs else -1
        for i, n in enumerate(names):
            if i != keep and ACTIONS[n].ends is None and n not in SHORT_V2:
                neighbours = names[max(i - 1, 0):i] + names[i + 1:i + 2]
                names[i] = choose_short(rng, seated[i], neighbours)
    for pool, other in ((LONG_V3, SHORT_V2), (SHORT_V2, LONG_V3)):
        if any(n in pool for n in names):
            continue
        others = sum(n in other for n in names)  # the last of the other kind stays
        slots = [i for i, n in enumerate(names) if ACTIONS[n].ends is None
                 and not (n in other and others == 1)
                 and any(ACTIONS[c].needs in ("any", "sitting" if seated[i] else "standing") for c in pool)]
        if not slots:
            continue
        i = slots[int(rng.integers(len(slots)))]
        state = "sitting" if seated[i] else "standing"
        neighbours = names[max(i - 1, 0):i] + names[i + 1:i + 2]
        choices = [n for n in pool if n not in neighbours and ACTIONS[n].needs in ("any", state)]
        if choices:
            weights = np.array([ACTION_WEIGHTS.get(n, 1.0) for n in choices])
            names[i] = choices[int(rng.choice(len(choices), p=weights / weights.sum()))]


def seated_before(names: list[str]) -> list[bool]:
    """Whether the body sits as each of the actions `names` begins (a sequence starts standing)."""
    seated, sitting = [], False
    for name in names:
        seated.append(sitting)
        sitting = {"sitting": True, "standing": False}.get(ACTIONS[name].ends, sitting)
    return seated


def choose_short(rng, sitting: bool, neighbours: list[str]) -> str:
    """A short action (`SHORT_V2`) the body can do sitting or standing, none of `neighbours`,
    drawn by `ACTION_WEIGHTS`."""
    state = "sitting" if sitting else "standing"
    names = [n for n in SHORT_V2 if n not in neighbours and ACTIONS[n].needs in ("any", state)]
    weights = np.array([ACTION_WEIGHTS.get(n, 1.0) for n in names])
    return names[int(rng.choice(len(names), p=weights / weights.sum()))]


def _draw(rng, name, sitting, version):
    spec = ACTIONS[name]
    params = sample_params(name, rng, version)
    overlay = _overlay(rng, spec)
    return params, overlay, build_action(name, params, rng, sitting, overlay)


def _assemble(rng, names, plan, overlaps, rigid: bool = False) -> SynthMotion:
    clips, segments = [], []
    for name, (params, overlay, track), overlap in zip(names, plan, overlaps):
        clip = (solve_pose(track), track.root.copy(), track.yaw.copy())
        if overlap:
            clip = _hold(clip, overlap // 3, 0)
            clips[-1] = _hold(clips[-1], 0, (overlap + 1) // 2)
        clips.append(clip)
        segments.append(Segment(name, params, overlay))
    return _finish(rng, clips, overlaps, segments, rigid)


def _sample_v1(rng: np.random.Generator) -> SynthMotion:
    count = int(rng.choice(SEGMENT_COUNTS, p=SEGMENT_WEIGHTS))
    sitting, previous = False, None
    clips, segments, overlaps = [], [], []
    total = 0
    for index in range(count):
        # Leave room for the segments still to come; later attempts only need to fit.
        reserve = RESERVE_FRAMES * (count - index - 1)
        short = (MAX_FRAMES - total) / (count - index) < 70
        for attempt in range(10):
            name = _choose(rng, sitting, previous, short)
            spec = ACTIONS[name]
            params = spec.sample(rng)
            overlay = _overlay(rng, spec)
            track = build_action(name, params, rng, sitting, overlay)
            overlap = int(rng.integers(5, 16)) if clips else 0
            pad = (overlap + 1) // 2
            length = track.num_frames + overlap // 3 + pad - overlap
            if total + length + (reserve if attempt < 7 else 0) <= MAX_FRAMES + 1:
                break
        else:
            break
        clip = (solve_pose(track), track.root.copy(), track.yaw.copy())
        if overlap:
            clip = _hold(clip, overlap // 3, 0)
        if clips:
            clips[-1] = _hold(clips[-1], 0, pad)
            total += pad
        clips.append(clip)
        overlaps.append(overlap)
        segments.append(Segment(name, params, overlay))
        total += len(clip[0]) - overlap
        previous = name
        sitting = {"sitting": True, "standing": False}.get(spec.ends, sitting)
    if not clips:  # every draw was too long: fall back to standing still
        params = ACTIONS["stand_still"].sample(rng)
        clips, overlaps = [_clip(rng, "stand_still", params, None, False)], [0]
        segments = [Segment("stand_still", params)]
    return _finish(rng, clips, overlaps, segments)


def motion_from_actions(rng: np.random.Generator, actions: list[tuple[str, dict]],
                        overlap: int = 10, overlay: tuple[str, dict] | None = None,
                        rigid: bool = False) -> SynthMotion:
    """Build a given sequence of (action, params) (for previews and tests); `overlay` runs
    an upper-body action during the first one; `rigid`: version 4's rig. Raises on an
    impossible body-state order."""
    sitting, clips, overlaps, segments = False, [], [], []
    for i, (name, params) in enumerate(actions):
        spec = ACTIONS[name]
        if spec.needs not in ("any", "sitting" if sitting else "standing"):
            raise ValueError(f"motion_from_actions: {name!r} needs a {spec.needs} body (action {i})")
        over = overlay if i == 0 else None
        clip = _clip(rng, name, params, over, sitting)
        if clips:
            clips[-1] = _hold(clips[-1], 0, (overlap + 1) // 2)
            clip = _hold(clip, overlap // 3, 0)
        clips.append(clip)
        overlaps.append(overlap if i else 0)
        segments.append(Segment(name, params, over))
        sitting = {"sitting": True, "standing": False}.get(spec.ends, sitting)
    return _finish(rng, clips, overlaps, segments, rigid)


def _finish(rng, clips, overlaps, segments, rigid: bool = False) -> SynthMotion:
    # Too short: stand a little longer before the first and after the last action.
    short = MIN_FRAMES + 1 - sum(len(c[0]) for c in clips) + sum(overlaps)
    if short > 0:
        before = int(rng.integers(0, short + 1))
        clips[0] = _hold(clips[0], before, 0)
        clips[-1] = _hold(clips[-1], 0, short - before)
    q, root, bounds = _blend(clips, overlaps)
    if rigid:
        q = rigid_branches(q)
    joints = forward_kinematics(torch.from_numpy(q), torch.from_numpy(root),
                                torch.from_numpy(REST_OFFSETS), T2M.parents).numpy()
    # A transition slerps leg rotations but interpolates the root linearly, which can push
    # a foot into the floor when one side is crouched: lift the body there, smoothly.
    sink = np.maximum(-joints[:, [7, 8, 10, 11], 1].min(1), 0.0)
    if sink.max() > 0.002:
        sink = sliding(sink, 4)  # cover the neighbourhood
        joints[..., 1] += np.maximum(gaussian(sink, 2.0), sink)[:, None]
    bounds = [0, *bounds, len(joints) - 1]
    for seg, start, end in zip(segments, bounds[:-1], bounds[1:]):
        seg.start, seg.end = int(start), int(end)
    return SynthMotion(joints, segments)


def _blend(clips, overlaps):
    """Join clips; -> world quats (t, 22, 4), root (t, 3), boundaries (frame indices)."""
    out_q, out_root, bounds = [], [], []
    yaw0, origin = 0.0, np.zeros(3)
    prev_q = prev_root = None
    for (q, root, yaw), overlap in zip(clips, overlaps):
        heading = axis_angle((0, 1, 0), yaw0)
        wq = q.copy()
        wq[:, 0] = qmul(heading, q[:, 0])
        local = root - np.array([root[0, 0], 0.0, root[0, 2]])
        wroot = qrot(heading, local) + origin
        if prev_q is not None and overlap > 0:
            w = ((np.arange(overlap) + 0.5) / overlap)
            w = w * w * (3 - 2 * w)
            tail_q, tail_root = prev_q[-overlap:], prev_root[-overlap:]
            wq[:overlap] = slerp(tail_q, wq[:overlap], np.broadcast_to(w[:, None], (overlap, 22)))
            wroot[:overlap] = (1 - w[:, None]) * tail_root + w[:, None] * wroot[:overlap]
            out_q[-1], out_root[-1] = prev_q[:-overlap], prev_root[:-overlap]
            bounds.append(sum(len(x) for x in out_q) + overlap // 2)
        out_q.append(wq)
        out_root.append(wroot)
        prev_q, prev_root = wq, wroot
        # The next clip starts where this one is when their transition begins; since
        # clips end in a hold that is where it ends, up to the hold's sway.
        yaw0 = yaw0 + yaw[-1]
        origin = np.array([wroot[-1, 0], 0.0, wroot[-1, 2]])
    return np.concatenate(out_q), np.concatenate(out_root), bounds
