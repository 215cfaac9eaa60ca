"""Datasets in the HumanML3D layout: reader, collate and the Lightning DataModule."""

from typing import Any

from segmo.data.collate import collate
from segmo.data.humanml3d import (
    Caption,
    MotionDataset,
    load_stats,
    parse_text_line,
    read_split,
)
from segmo.data.windows import MotionWindowDataset

__all__ = [
    "Caption",
    "MotionDataModule",
    "MotionDataset",
    "MotionWindowDataset",
    "collate",
    "load_stats",
    "parse_text_line",
    "read_split",
]


def __getattr__(name: str) -> Any:
    # The DataModule imports Lightning (seconds); readers and collate do not need it.
    if name == "MotionDataModule":
        from segmo.data.datamodule import MotionDataModule

        return MotionDataModule
    raise AttributeError(f"module 'segmo.data' has no attribute {name!r}")
