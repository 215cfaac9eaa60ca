"""`ActionFrameDataset`: whole motions with one action label per frame (built-in corpus).

The data of the frame-wise action classifier behind the action-order metric
(`segmo.tasks.action_classifier`). Labels come from the ground truth's ``actions``
(`segmo.data.layout.read_actions`): a frame inside an action's span gets that action's
class (the main action; arm overlays, "with", are not labels), a frame outside every span
gets `IGNORE`. Classes are the sorted action names of the train split, for every split;
an action of val/test that the train split lacks is ignored as well. With
``targets="attributes"`` each frame gets its action's (side, count, speed) classes instead
(`segmo.data.attributes`), the data of the attribute classifier.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from segmo.data.attributes import attribute_frame_labels
from segmo.data.checks import MAX_ABS_Z
from segmo.data.collate import IGNORE
from segmo.data.humanml3d import LoadReport, MotionStore
from segmo.data.layout import read_actions, read_split, resolve_stats, split_file
from segmo.data.sampling import split_key
from segmo.motion.skeleton import SkeletonSpec, get_skeleton


def action_classes(root: str | Path, split: str = "train") -> list[str]:
    """Sorted action names of the ground truth of ``split`` (reads no motion file)."""
    return sorted({a for mid in read_split(root, split) for a in read_actions(root, mid)[0]})


class ActionFrameDataset(Dataset):
    """One entry per motion of a split: the whole clip (no crop, no length limits),
    z-scored, and its labels. A sample is ``{"motion": (t, d), "length": t, "id": str,
    "labels": (t,) long}`` ((t, 3) for attributes). What is skipped and what raises is `MotionDataset`'s
    (`segmo.data.humanml3d`); a motion without ground truth raises."""

    def __init__(
        self,
        root: str | Path,
        split: str = "train",
        skeleton: str | SkeletonSpec = "t2m",
        *,
        classes: list[str] | None = None,
        mean: np.ndarray | None = None,
        std: np.ndarray | None = None,
        max_motions: int | None = None,
        preload: bool = True,
        strict: bool = False,
        max_abs_z: float | None = MAX_ABS_Z,
        targets: str = "actions",
    ) -> None:
        if targets not in ("actions", "attributes"):
            raise ValueError(f"ActionFrameDataset: targets must be 'actions' or 'attributes', got {targets!r}")
        self.root = Path(root)
        self.skeleton = get_skeleton(skeleton)
        self.mean, self.std = resolve_stats(self.root, self.skeleton, mean, std)
        self.classes = list(classes) if classes is not None else action_classes(self.root)
        report = LoadReport(strict)
        ids = read_split(self.root, split)[:max_motions]
        self.motions = MotionStore(self.root, ids, self.skeleton, report, preload, mean=self.mean,
                                   std=self.std, max_abs_z=max_abs_z,
                                   where=str(split_file(self.root, split)))
        self.ids = [mid for mid in ids if mid in self.motions]
        index = {c: i for i, c in enumerate(self.classes)}
        self.labels: dict[str, np.ndarray] = {}
        for mid in self.ids:
            if targets == "attributes":
                self.labels[mid] = attribute_frame_labels(self.root, mid, self.motions.lengths[mid])
                continue
            labels = np.full(self.motions.lengths[mid], IGNORE, dtype=np.int64)
            for action, (start, end) in zip(*read_actions(self.root, mid, len(labels)),
                                            strict=True):
                labels[start:end] = index.get(action, IGNORE)
            self.labels[mid] = labels
        self.summary = report.finish(f"{self.root.name}/{split}", len(self.ids), len(self.ids))
        self.problems = report.problems

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, Any]:
        i, _ = split_key(key, 0)  # nothing here depends on the epoch
        mid = self.ids[i]
        raw = self.motions.get(mid)
        return {"motion": torch.from_numpy((raw - self.mean) / self.std), "length": raw.shape[0],
                "id": mid, "labels": torch.from_numpy(self.labels[mid])}
