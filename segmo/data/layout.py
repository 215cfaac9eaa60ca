"""The dataset folder (HumanML3D layout, docs/design.md "Dataset folder"): one reader.

Everything above `segmo.data` that reads a dataset folder goes through these functions:
the datasets, evaluation, pipeline grounding, the demo and the tools; the built-in corpus
(`segmo.synth`) writes its files at the paths named here. The text side of the folder
(``texts/``, ``text_segments/``, ``text_features/``) belongs to `segmo.text`, below this
package: caption lines are read by `segmo.text.captions` (which this module reuses), text
segments by `segmo.text.extract` and the dataset, text features by `segmo.text.cache`.
The motion-token cache (``motion_tokens/``) is `segmo.data.motion_tokens`'s.

    ROOT/<split>.txt              ids, one per line          read_split
    ROOT/Mean.npy, ROOT/Std.npy   (d,) train statistics      load_stats
    ROOT/new_joint_vecs/<id>.npy  (t, d) raw features        read_motion
    ROOT/segments/<id>.json       ground truth (built-in)    read_ground_truth, read_actions
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from segmo.errors import SegmoError
from segmo.files import read_npy
from segmo.motion.skeleton import SkeletonSpec, get_skeleton
from segmo.text.captions import read_text, texts_file

MOTIONS, JOINTS, GROUND_TRUTH = "new_joint_vecs", "new_joints", "segments"
SPLITS = ("train", "val", "test")
STATISTICS = ("Mean.npy", "Std.npy")

__all__ = ["GROUND_TRUTH", "JOINTS", "MOTIONS", "SPLITS", "STATISTICS", "caption_spans",
           "check_stats", "ground_truth_file", "has_ground_truth", "joints_file", "load_stats",
           "motion_file", "read_actions", "read_ground_truth", "read_motion", "read_split",
           "resolve_stats", "shared_ids", "split_file", "stats_files", "texts_file"]


# ----------------------------------------------------------------------------- paths


def split_file(root: str | Path, split: str) -> Path:
    return Path(root) / f"{split}.txt"


def stats_files(root: str | Path) -> tuple[Path, Path]:
    """``ROOT/Mean.npy``, ``ROOT/Std.npy``."""
    return Path(root) / STATISTICS[0], Path(root) / STATISTICS[1]


def motion_file(root: str | Path, motion_id: str) -> Path:
    return Path(root) / MOTIONS / f"{motion_id}.npy"


def joints_file(root: str | Path, motion_id: str) -> Path:
    return Path(root) / JOINTS / f"{motion_id}.npy"


def ground_truth_file(root: str | Path, motion_id: str) -> Path:
    return Path(root) / GROUND_TRUTH / f"{motion_id}.json"


def has_ground_truth(root: str | Path) -> bool:
    """Whether the folder carries ground-truth segments (the built-in corpus does)."""
    return (Path(root) / GROUND_TRUTH).is_dir()


# ----------------------------------------------------------------------------- splits, motions


def read_split(root: str | Path, split: str) -> list[str]:
    """Ids of ``ROOT/<split>.txt``, one per non-blank line, in file order; an id listed
    twice is refused (it would be sampled twice as often, and counted twice in a score)."""
    path = split_file(root, split)
    if path.is_dir():
        raise SegmoError(f"{path}: is a folder, not a split file (one motion id per line)")
    if not path.exists():  # a broken link too
        raise FileNotFoundError(f"split file not found: {path}")
    line_of: dict[str, int] = {}
    for number, line in enumerate(read_text(path).splitlines(), 1):
        motion_id = line.strip()
        if not motion_id:
            continue
        if motion_id in line_of:
            raise SegmoError(f"{path}:{number}: id {motion_id!r} again (first on line "
                             f"{line_of[motion_id]}); list each motion once")
        line_of[motion_id] = number
    if not line_of:
        raise SegmoError(f"split file lists no ids: {path}")
    return list(line_of)


def shared_ids(root: str | Path) -> str | None:
    """One line naming the motions that two split files of `root` both list (a test motion
    also trained on makes the test score one of memory), None when the splits are disjoint.
    Split files that are missing or unreadable are left to the readers that need them."""
    ids = {}
    for split in SPLITS:
        try:
            ids[split] = set(read_split(root, split))
        except (OSError, SegmoError):
            continue
    shared = [(a, b, sorted(ids[a] & ids[b])) for i, a in enumerate(ids) for b in list(ids)[i + 1:]]
    parts = [f"{len(common)} in both {a}.txt and {b}.txt (first: {common[0]})"
             for a, b, common in shared if common]
    if not parts:
        return None
    return f"{root}: the splits share motions: {'; '.join(parts)}"


def read_motion(root: str | Path, motion_id: str) -> np.ndarray:
    """The raw (un-normalised) features (t, d) of ``ROOT/new_joint_vecs/<id>.npy``;
    SegmoError naming the file when it is missing, not a .npy array of real numbers, not
    (frames ≥ 1, features), or holds NaN or inf (an evaluation skipped such a motion, or
    failed on it without naming it)."""
    path = motion_file(root, motion_id)
    if not path.is_file():
        raise SegmoError(f"{path}: motion file not found (listed in a split of {root})")
    array = read_npy(path)
    if array.ndim != 2 or not array.shape[0] or not array.shape[1]:
        raise SegmoError(f"{path}: shape {array.shape}, expected (frames, features)")
    if not np.isfinite(array).all():
        raise SegmoError(f"{path}: holds NaN or inf")
    return array


# ----------------------------------------------------------------------------- statistics


def load_stats(root: str | Path, skeleton: str | SkeletonSpec = "t2m") -> tuple[np.ndarray, np.ndarray]:
    """``ROOT/Mean.npy`` and ``ROOT/Std.npy`` as read-only float32 copies, each (d,)."""
    paths = stats_files(root)
    for path in paths:
        if not path.is_file():
            raise FileNotFoundError(f"normalisation statistics not found: {path}")
    arrays = []
    for path in paths:
        try:
            arrays.append(np.load(path))
        except (OSError, ValueError, EOFError) as error:
            raise SegmoError(f"{path}: not a readable .npy array ({error})") from None
    return check_stats(*arrays, skeleton, *map(str, paths))


def check_stats(mean: Any, std: Any, skeleton: str | SkeletonSpec = "t2m", mean_name: str = "mean",
                std_name: str = "std") -> tuple[np.ndarray, np.ndarray]:
    """Validated read-only float32 copies (d,) of mean and std (the inputs are never aliased)."""
    spec = get_skeleton(skeleton)
    out = []
    for name, arr in ((mean_name, mean), (std_name, std)):
        kind = np.asarray(arr).dtype.kind
        if kind not in "fiu":  # complex would lose its imaginary part, text fails to convert
            raise SegmoError(f"{name}: values of type {np.asarray(arr).dtype}, not real numbers")
        arr = np.array(arr, dtype=np.float32)  # always a copy
        if arr.shape != (spec.feature_dim,):
            raise SegmoError(f"{name}: shape {arr.shape}, expected ({spec.feature_dim},) "
                             f"for skeleton {spec.name!r}")
        if not np.isfinite(arr).all():
            raise SegmoError(f"{name}: contains NaN or inf")
        arr.setflags(write=False)
        out.append(arr)
    if (out[1] <= 0).any():
        raise SegmoError(f"{std_name}: non-positive std in dims {np.flatnonzero(out[1] <= 0).tolist()[:10]}")
    return out[0], out[1]


def resolve_stats(root: Path, spec: SkeletonSpec, mean: Any, std: Any) -> tuple[np.ndarray, np.ndarray]:
    """The given statistics (validated copies), or those of ``root`` when both are None."""
    if mean is None and std is None:
        return load_stats(root, spec)
    if mean is None or std is None:
        raise SegmoError("pass both mean and std, or neither (then ROOT/Mean.npy, Std.npy are read)")
    return check_stats(mean, std, spec)


# ----------------------------------------------------------------------------- ground truth


def read_ground_truth(root: str | Path, motion_id: str) -> dict[str, Any]:
    """The record of ``ROOT/segments/<id>.json`` (docs/design.md: ``actions``, ``captions``,
    each caption's ``segments`` with ``text``, ``action``, ``start``, ``end`` frames)."""
    path = ground_truth_file(root, motion_id)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no ground truth (only the built-in corpus has "
                                "segments/<id>.json)")
    try:
        record = json.loads(read_text(path))
    except json.JSONDecodeError as error:
        raise SegmoError(f"{path}:{error.lineno}: not valid JSON: {error.msg}") from None
    if not isinstance(record, dict):
        raise SegmoError(f"{path}: not a ground-truth file (a JSON object expected)")
    problem = ground_truth_problem(record)
    if problem:
        raise SegmoError(f"{path}: not a ground-truth file ({problem})")
    return record


def _is_frame(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def ground_truth_problem(record: dict[str, Any]) -> str | None:
    """What is wrong with the frame spans of a ground-truth record, None when nothing is.

    Checked where present (a reader asks for the keys it needs): ``num_frames`` a whole
    number ≥ 1; each span of ``actions`` and of every caption's ``segments`` (a non-empty
    list) whole frames with 0 ≤ start < end ≤ num_frames, in order and not overlapping, as
    `segmo synth` writes them (docs/design.md); each action's ``action`` (and a caption
    segment's, where given) a name, a non-empty string."""
    frames = record.get("num_frames")
    if "num_frames" in record and not (_is_frame(frames) and frames >= 1):
        return f"num_frames {frames!r}: expected a whole number >= 1"
    end_limit = frames if "num_frames" in record else None

    def spans_problem(where: str, spans: Any, action_required: bool) -> str | None:
        if not isinstance(spans, list) or not spans:
            return f"{where}: expected a non-empty list"
        previous_end = 0
        for j, span in enumerate(spans):
            if not isinstance(span, dict):
                return f"{where}[{j}]: expected an object"
            action = span.get("action")
            if (action_required or "action" in span) and not (isinstance(action, str) and action):
                return f"{where}[{j}]: action {action!r}: expected a name (a non-empty string)"
            start, end = span.get("start"), span.get("end")
            if not (_is_frame(start) and _is_frame(end)):
                return f"{where}[{j}]: start {start!r}, end {end!r}: expected whole frames"
            if not previous_end <= start < end or (end_limit is not None and end > end_limit):
                bound = f" <= num_frames {end_limit}" if end_limit is not None else ""
                return (f"{where}[{j}]: start {start}, end {end}: expected {previous_end} <= start "
                        f"< end{bound} (spans in order, not overlapping)")
            previous_end = end
        return None

    if "actions" in record:
        problem = spans_problem("actions", record["actions"], action_required=True)
        if problem:
            return problem
    if "captions" in record:
        captions = record["captions"]
        if not isinstance(captions, list):
            return "captions: expected a list"
        for i, caption in enumerate(captions):
            if not isinstance(caption, dict) or "segments" not in caption:
                return f"captions[{i}]: expected an object with segments"
            problem = spans_problem(f"captions[{i}].segments", caption["segments"],
                                    action_required=False)
            if problem:
                return problem
    return None


def first_captions(root: str | Path, split: str) -> list[tuple[str, dict[str, Any], dict[str, Any]]]:
    """(motion id, ground-truth record, its first caption) of every motion of `split`, in
    split order: what the corpus tools score (`segmo evaluate` scores the first caption)."""
    if not has_ground_truth(root):
        raise SegmoError(f"{root}: no ground truth (segments/<id>.json): only the built-in "
                         "corpus (segmo synth) has it")
    out = []
    for motion_id in read_split(root, split):
        record = read_ground_truth(root, motion_id)
        out.append((motion_id, record, record["captions"][0]))
    return out


def _check_num_frames(root: str | Path, motion_id: str, record: dict[str, Any],
                      num_frames: int) -> None:
    """Refuse a ground-truth record made for a motion of another length than the motion's
    `num_frames` (the file of another motion, copied or renamed): its spans would be cut to
    the motion, empty ones included, without a word."""
    recorded = record.get("num_frames")
    if recorded is not None and recorded != num_frames:
        raise SegmoError(f"{ground_truth_file(root, motion_id)}: num_frames {recorded}, but "
                         f"{motion_file(root, motion_id)} has {num_frames} frames (the ground "
                         "truth of another motion?)")


def caption_spans(root: str | Path, motion_id: str, num_lines: int, num_frames: int
                  ) -> list[tuple[tuple[int, int], ...]] | None:
    """Per caption line of ``texts/<id>.txt``, the frame spans (start, end exclusive) of its
    ground-truth segments; None when the motion has no ground truth. The record must be
    of a motion of `num_frames` frames, the motion's."""
    path = ground_truth_file(root, motion_id)
    if not path.is_file():
        return None
    record = read_ground_truth(root, motion_id)
    _check_num_frames(root, motion_id, record, num_frames)
    try:
        captions = record["captions"]
        spans = [tuple((int(s["start"]), int(s["end"])) for s in c["segments"]) for c in captions]
    except (KeyError, TypeError, ValueError) as error:
        raise SegmoError(f"{path}: not a ground-truth file (captions[i].segments[j].start/end "
                         f"expected; {type(error).__name__}: {error})") from None
    if len(captions) != num_lines:
        raise SegmoError(f"{path} has {len(captions)} captions but {texts_file(root, motion_id)} "
                         f"has {num_lines} lines")
    return spans


def read_actions(root: str | Path, motion_id: str, num_frames: int | None = None
                 ) -> tuple[list[str], list[tuple[int, int]]]:
    """Action names and frame spans (end exclusive) of a motion's ground truth; arm overlays
    ("with") are left out: the main action names the span. Given the motion's
    `num_frames`, the record must be of a motion that long."""
    path = ground_truth_file(root, motion_id)
    record = read_ground_truth(root, motion_id)
    if num_frames is not None:
        _check_num_frames(root, motion_id, record, num_frames)
    try:
        actions = record["actions"]
        return [a["action"] for a in actions], [(int(a["start"]), int(a["end"])) for a in actions]
    except (KeyError, TypeError, ValueError) as error:
        raise SegmoError(f"{path}: not a ground-truth file (actions[i].action/start/end "
                         f"expected; {type(error).__name__}: {error})") from None
