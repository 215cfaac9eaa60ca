"""Datasets in the HumanML3D layout: the folder reader (`layout`), datasets, collate and the
Lightning DataModule."""

from typing import Any

from segmo.data.collate import collate
from segmo.data.humanml3d import MotionDataset
from segmo.data.layout import load_stats, read_split
from segmo.data.windows import MotionWindowDataset
from segmo.text.captions import Caption, parse_text_line

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
