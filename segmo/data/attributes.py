"""Action attributes of the built-in corpus: which side, how many times, how fast.

The corpus stores each action's parameters (`segments/<id>.json`, ``actions[k].params``);
three of them are what captions name as modifiers ("kicks with the *left* foot", "jumps
*twice*", "walks forward *slowly*"), and what the fine-grained attribute metric checks
(`segmo.evaluation.attributes`):

- ``side``: left / right / both, from the limb (kick, punch, raise_arm, hop's foot, wave's
  hand) or the direction of a movement (side_step, turn, spin, walk_circle);
- ``count``: 1-5 repetitions (jumps, hops, squats, punches, waves, claps);
- ``speed``: slow / normal / fast, with the thresholds the captions use
  (`SPEED_THRESHOLDS`; walks and runs).

`attribute_labels` turns an action's parameters into one class index per attribute
(IGNORE where the action has none), `named_attributes` says which attributes a text
segment names.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from segmo.data.collate import IGNORE
from segmo.data.layout import read_ground_truth

# (slow below, fast above) speed in m/s: where the corpus' captions say "slowly" / "quickly"
# (`segmo.synth.captions`), and the speed classes here.
SPEED_THRESHOLDS = {"walk_forward": (1.2, 1.6), "walk_backward": (0.72, 2.0), "run": (0.0, 3.4)}
ATTRIBUTES: dict[str, tuple[str, ...]] = {
    "side": ("left", "right", "both"),
    "count": ("1", "2", "3", "4", "5"),
    "speed": ("slow", "normal", "fast"),
}
# The words by which a text names each attribute (whole words, lower case).
_NAMES = {
    "side": re.compile(r"\b(left|right|both|clockwise|counterclockwise)\b"),
    "count": re.compile(r"\b(once|twice|(two|three|four|five) times)\b"),
    "speed": re.compile(r"\b(slowly|slow|quickly|fast)\b"),
}


def num_attribute_classes() -> int:
    return sum(len(v) for v in ATTRIBUTES.values())


def attribute_slices() -> dict[str, slice]:
    """Where each attribute's classes sit among the classifier's outputs."""
    out, start = {}, 0
    for name, values in ATTRIBUTES.items():
        out[name] = slice(start, start + len(values))
        start += len(values)
    return out


def attribute_labels(action: str, params: dict) -> tuple[int, int, int]:
    """(side, count, speed) class indices of one action, IGNORE where it has none."""
    side = params.get("side", params.get("foot", params.get("hand", params.get("direction"))))
    count = params.get("count")
    labels = [ATTRIBUTES["side"].index(side) if side in ATTRIBUTES["side"] else IGNORE,
              int(count) - 1 if isinstance(count, int) and 1 <= count <= 5 else IGNORE, IGNORE]
    if action in SPEED_THRESHOLDS and "speed" in params:
        slow, fast = SPEED_THRESHOLDS[action]
        speed = float(params["speed"])
        labels[2] = 0 if speed < slow else 2 if speed > fast else 1
    return tuple(labels)


def named_attributes(text: str) -> list[str]:
    """The attributes a text segment names, in ATTRIBUTES order."""
    text = text.lower()
    return [name for name, pattern in _NAMES.items() if pattern.search(text)]


def attribute_frame_labels(root: str | Path, motion_id: str, num_frames: int) -> np.ndarray:
    """(t, 3) long: each frame's action's attribute classes (IGNORE outside every span)."""
    labels = np.full((num_frames, len(ATTRIBUTES)), IGNORE, dtype=np.int64)
    for action in read_ground_truth(root, motion_id)["actions"]:
        start, end = int(action["start"]), int(action["end"])
        labels[start:end] = attribute_labels(action["action"], action.get("params") or {})
    return labels
