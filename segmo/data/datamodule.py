"""`MotionDataModule`: splits, statistics and loaders of one dataset folder (docs/design.md).

`setup` refuses a dataset before training starts, with counts: motions with NaN/inf or
absurd values (`segmo.data.checks`), and texts missing from the text-feature cache.
"""

from __future__ import annotations

import warnings
from functools import cached_property
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from lightning.pytorch import LightningDataModule
from torch.utils.data import DataLoader, Dataset

from segmo.data.actions import ActionFrameDataset, action_classes
from segmo.data.checks import MAX_ABS_Z, missing_texts
from segmo.data.collate import collate
from segmo.data.humanml3d import MotionDataset
from segmo.data.layout import load_stats, shared_ids, split_file
from segmo.data.sampling import EpochSampler, ResumableDataLoader
from segmo.data.windows import MotionWindowDataset
from segmo.errors import LARGEST_WHOLE_NUMBER, SegmoError
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.motion.skeleton import SkeletonSpec, get_skeleton
from segmo.text.cache import TextFeatureCache
from segmo.text.rules import MAX_SEGMENTS


class MotionDataModule(LightningDataModule):
    """A HumanML3D-layout folder as train/val/test/predict loaders.

    Splits come from ``ROOT/{train,val,test}.txt`` in file order (``max_motions`` keeps the
    first N ids of each); predict uses the test split. Without ``window`` every split is a
    `MotionDataset` (one sample per caption; random crop offsets for train only). With
    ``window`` (tokenizer training) train is a `MotionWindowDataset` of random windows and
    val/test are whole clips, one per motion. The train order of epoch e is a permutation
    drawn from ``(seed, e)`` and its crops from ``(seed, e, index)``; the loader's position
    is saved in checkpoints (`segmo.data.sampling`), so a resumed run continues with the
    batches an uninterrupted one would have seen. Under DDP each rank takes its share of
    that order. With ``frame_labels`` (the action classifier; built-in corpus only) every
    split is an `ActionFrameDataset`: whole clips with one action label per frame
    (``frame_labels: attributes``: the action's side, count and speed classes per frame). The last
    incomplete batch is dropped only when a rank's share of the train set holds more than
    one batch. ``group_by_length`` (caption samples only) forms each train batch from clips
    of similar length (`segmo.data.sampling.group_by_length`): a batch pads to its own
    longest clip, which on the built-in corpus cuts the padded positions of the token
    stages by about a third; the clips of the dropped incomplete batch are still a random
    choice, as without it. ``text_tokens="words"`` adds each caption's per-word features
    from the text-feature cache (word-level conditioning; linked to the transformers'
    ``text_tokens`` under ``segmo fit``). ``max_abs_z`` bounds the feature values
    (`segmo.data.checks`; None checks for NaN/inf only). ``unit_length`` is obsolete: a
    motion token is `FRAMES_PER_TOKEN` frames, fixed by the tokenizer's encoder; configs
    written when it was an option (``unit_length: 4``) still load, any other value is an error.

    Example::

        dm = MotionDataModule("data/synth", batch_size=32)
        dm.setup("fit")
        batch = next(iter(dm.train_dataloader()))  # motion (b, t, d), mask (b, t), ...
    """

    def __init__(
        self,
        root: str,
        skeleton: str = "t2m",
        batch_size: int = 64,
        num_workers: int = 0,
        window: int | None = None,
        text_segments: str | None = None,
        text_features: str | None = None,
        max_segments: int = MAX_SEGMENTS,
        unit_length: int | None = None,
        seed: int = 0,
        max_motions: int | None = None,
        preload: bool = True,
        strict: bool = False,
        max_abs_z: float | None = MAX_ABS_Z,
        frame_labels: bool | Literal["actions", "attributes"] = False,
        group_by_length: bool = False,
        text_tokens: Literal["none", "words"] = "none",
    ) -> None:
        super().__init__()
        self.save_hyperparameters()
        if batch_size <= 0:
            raise SegmoError(f"data.init_args.batch_size={batch_size} must be positive")
        for name, value, low in (("batch_size", batch_size, 1), ("num_workers", num_workers, 0),
                                 ("seed", seed, 0), ("max_motions", max_motions, 1)):
            if value is not None and not low <= value <= LARGEST_WHOLE_NUMBER:
                raise SegmoError(f"data.init_args.{name}={value} must be a whole number from "
                                 f"{low} to 2^63 - 1")
        if unit_length not in (None, FRAMES_PER_TOKEN):
            raise SegmoError(f"data.init_args.unit_length={unit_length}: a motion token is always "
                             f"{FRAMES_PER_TOKEN} frames (the tokenizer's fixed stride); remove the option")
        if frame_labels and window is not None:
            raise SegmoError("data.init_args: frame_labels gives whole clips; it takes no window")
        self.root = Path(root)
        if not self.root.is_dir():
            raise SegmoError(f"data.init_args.root={root!r}: no such dataset folder")
        self.skeleton: SkeletonSpec = get_skeleton(skeleton)
        self.batch_size = batch_size
        self.num_workers = num_workers
        self.window = window
        self.text_segments = text_segments
        self.text_features = text_features
        self.max_segments = max_segments
        self.seed = seed
        self.max_motions = max_motions
        self.preload = preload
        self.strict = strict
        self.max_abs_z = max_abs_z
        self.frame_labels = frame_labels
        self.group_by_length = group_by_length
        self.text_tokens = text_tokens
        self.datasets: dict[str, Dataset] = {}

    @property
    def feature_dim(self) -> int:
        return self.skeleton.feature_dim

    @cached_property
    def _stats(self) -> tuple[Any, Any]:
        return load_stats(self.root, self.skeleton)

    @property
    def mean(self) -> torch.Tensor:
        """(d,) float32, a fresh copy of ``ROOT/Mean.npy``."""
        return torch.tensor(self._stats[0])

    @property
    def std(self) -> torch.Tensor:
        """(d,) float32, a fresh copy of ``ROOT/Std.npy``."""
        return torch.tensor(self._stats[1])

    @cached_property
    def classes(self) -> list[str]:
        """The action classes of ``frame_labels`` (those of the train split's ground truth)."""
        return action_classes(self.root)

    @cached_property
    def text_cache(self) -> Any:
        """The text-feature cache shared by all splits, or None."""
        if self.text_features is None:
            return None
        return TextFeatureCache.open(self.root, self.text_features)

    def dataset(self, split: str) -> Dataset:
        """The dataset of ``split`` ("train", "val" or "test"), built on first use."""
        if split not in ("train", "val", "test"):
            raise ValueError(f"unknown split {split!r}; expected 'train', 'val' or 'test'")
        if split not in self.datasets:
            shared = shared_ids(self.root) if not self.datasets else None  # once, at the first
            if shared:
                warnings.warn(shared, stacklevel=2)
            self.datasets[split] = self._build(split)
        return self.datasets[split]

    def _build(self, split: str) -> Dataset:
        train = split == "train"
        mean, std = self._stats
        if self.frame_labels:
            return ActionFrameDataset(self.root, split, self.skeleton, classes=self.classes,
                                      mean=mean, std=std, max_motions=self.max_motions,
                                      preload=self.preload, strict=self.strict,
                                      max_abs_z=self.max_abs_z,
                                      targets="attributes" if self.frame_labels == "attributes" else "actions")
        common = dict(skeleton=self.skeleton, mean=mean, std=std, random_crop=train,
                      seed=self.seed, max_motions=self.max_motions, preload=self.preload,
                      strict=self.strict, max_abs_z=self.max_abs_z)
        if self.window is not None:
            return MotionWindowDataset(self.root, split, window=self.window if train else None,
                                       **common)
        return MotionDataset(self.root, split, text_segments=self.text_segments,
                             text_cache=self.text_cache, max_segments=self.max_segments,
                             text_tokens=self.text_tokens, **common)

    def setup(self, stage: str | None = None) -> None:
        splits = {"fit": ("train", "val"), "validate": ("val",), "test": ("test",),
                  "predict": ("test",), None: ("train", "val", "test")}[stage]
        for split in splits:
            self._check_texts(split, self.dataset(split))
        # The split a stage cannot do without, before the Trainer prints its banners and
        # makes a run folder (validation may be switched off: its loader says so on use).
        self._check_not_empty({"fit": "train"}.get(stage, splits[0]))

    def _check_not_empty(self, split: str) -> None:
        ds = self.dataset(split)
        if len(ds) == 0:
            raise SegmoError(f"{split_file(self.root, split)}: no usable samples "
                             f"(summary: {getattr(ds, 'summary', {})})")

    def _check_texts(self, split: str, ds: Dataset) -> None:
        """Every caption and segment of ``split`` is in the text-feature cache, or one error."""
        if self.text_cache is None or not isinstance(ds, MotionDataset):
            return
        missing, total = missing_texts((e.caption for e in ds.entries),
                                       (s for e in ds.entries for s in e.segments), self.text_cache)
        if missing:
            segments = f" --segments {self.text_segments}" if self.text_segments else ""
            raise SegmoError(
                f"{self.text_cache.folder}: {len(missing)} of {total} texts of the {split} split "
                f"are not in the text-feature cache (first: {missing[0]!r}); update it with "
                f"`segmo encode-texts --data {self.root} --encoder {self.text_features}{segments}`")

    def _loader(self, split: str, train: bool = False) -> DataLoader:
        self._check_not_empty(split)
        ds = self.dataset(split)
        common = dict(batch_size=self.batch_size, num_workers=self.num_workers,
                      persistent_workers=self.num_workers > 0, collate_fn=collate,
                      # Seeds the workers; without it the loader draws from the global RNG,
                      # which the tasks' dropout and masking must have to themselves.
                      generator=torch.Generator().manual_seed(self.seed))
        if not train:
            return DataLoader(ds, **common)
        lengths = None
        if self.group_by_length:
            if not hasattr(ds, "crop_length"):
                raise SegmoError(f"data.init_args.group_by_length: the {type(ds).__name__} of this "
                                 "stage has fixed-size samples; remove the option")
            lengths = np.array([ds.crop_length(i) for i in range(len(ds))])
        sampler = EpochSampler(ds, seed=self.seed, lengths=lengths, batch_size=self.batch_size)
        return ResumableDataLoader(ds, sampler=sampler, drop_last=len(sampler) > self.batch_size,
                                   **common)

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", train=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val")

    def test_dataloader(self) -> DataLoader:
        return self._loader("test")

    def predict_dataloader(self) -> DataLoader:
        return self._loader("test")
