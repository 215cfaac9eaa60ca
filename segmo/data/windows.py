"""`MotionWindowDataset`: motions without texts, for tokenizer training (spec §3).

Built on the reader of `segmo.data.humanml3d`, whose module docstring says what is skipped,
what raises and where the randomness comes from.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from segmo.data.checks import MAX_ABS_Z
from segmo.data.humanml3d import LoadReport, MotionStore, crop_offset
from segmo.data.layout import read_split, resolve_stats, split_file
from segmo.data.sampling import sample_rng, split_key
from segmo.errors import SegmoError
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.motion.skeleton import SkeletonSpec, get_skeleton


class MotionWindowDataset(Dataset):
    """One entry per motion of a split, for tokenizer training (texts are not read).

    ``window`` frames: a window at a random offset (``random_crop``, training) or at 0;
    motions shorter than the window are skipped and counted, and the length limits of the
    skeleton do not apply. ``window=None``: the whole clip, kept if
    ``min_frames <= t < max_frames`` and cropped to whole tokens (`FRAMES_PER_TOKEN`) from
    the end (validation). A sample is ``{"motion": (w, d) z-scored, "length": w, "id": str}``;
    the window offset is a function of ``(seed, epoch, i)``, keys are ``i`` or ``(i, epoch)``.
    """

    def __init__(
        self,
        root: str | Path,
        split: str = "train",
        skeleton: str | SkeletonSpec = "t2m",
        *,
        window: int | None = 64,
        mean: np.ndarray | None = None,
        std: np.ndarray | None = None,
        random_crop: bool = True,
        seed: int = 0,
        max_motions: int | None = None,
        preload: bool = True,
        strict: bool = False,
        max_abs_z: float | None = MAX_ABS_Z,
    ) -> None:
        if window is not None and (window <= 0 or window % FRAMES_PER_TOKEN):
            raise SegmoError(f"window={window} must be a positive multiple of "
                             f"unit_length={FRAMES_PER_TOKEN} (frames per motion token)")
        self.root = Path(root)
        self.skeleton = get_skeleton(skeleton)
        self.window = window
        self.random_crop = random_crop
        self.mean, self.std = resolve_stats(self.root, self.skeleton, mean, std)
        self.seed, self.epoch = seed, 0
        report = LoadReport(strict)
        ids = read_split(self.root, split)[:max_motions]
        self.motions = MotionStore(self.root, ids, self.skeleton, report, preload, mean=self.mean,
                                   std=self.std, max_abs_z=max_abs_z,
                                   where=str(split_file(self.root, split)))
        self.ids: list[str] = []
        for mid in ids:
            if mid not in self.motions:
                continue
            t = self.motions.lengths[mid]
            if window is not None and t < window:
                report.filtered("shorter_than_window")
            elif window is None and t < self.skeleton.min_frames:
                report.filtered("too_short")
            elif window is None and t >= self.skeleton.max_frames:
                report.filtered("too_long")
            else:
                self.ids.append(mid)
        self.summary = report.finish(f"{self.root.name}/{split}", len(self.ids), len(self.ids))
        self.problems = report.problems

    def __len__(self) -> int:
        return len(self.ids)

    def set_epoch(self, epoch: int) -> None:
        """The epoch whose windows plain integer keys get."""
        self.epoch = epoch

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, Any]:
        i, epoch = split_key(key, self.epoch)
        mid = self.ids[i]
        raw = self.motions.get(mid)
        size = self.window if self.window is not None else raw.shape[0] - raw.shape[0] % FRAMES_PER_TOKEN
        off = crop_offset(raw.shape[0], size, self.random_crop, sample_rng(self.seed, epoch, i))
        motion = torch.from_numpy((raw[off:off + size] - self.mean) / self.std)
        return {"motion": motion, "length": size, "id": mid}
