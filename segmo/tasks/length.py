"""The length estimator: sentence vector → motion length in tokens (spec §8).

MoMask never shipped one; this is a small classifier over token lengths 1..max_tokens,
trained with cross-entropy on the dataset's (cropped) lengths. Generation samples from
its softmax when the user gives no length.
"""

from __future__ import annotations

from typing import ClassVar

import torch
import torch.nn.functional as F
from torch import Tensor

from segmo.models.length_estimator import LengthEstimator, LengthEstimatorConfig
from segmo.tasks.base import Task
from segmo.tasks.common import check_max_tokens, check_text_features, token_lengths


class LengthTask(Task):
    """Trains `LengthEstimator` on batches with cached sentence vectors."""

    stage: ClassVar[str] = "length"
    monitor: ClassVar[str] = "val/loss"

    def __init__(
        self,
        text_dim: int = 512,
        text_encoder: str | None = None,
        hidden: int = 256,
        max_tokens: int = 49,
        dropout: float = 0.2,
        lr: float = 1e-3,
        weight_decay: float = 1e-4,
        warmup_steps: int = 100,
        milestones: list[int] = [],  # noqa: B006 - jsonargparse needs a plain default
        gamma: float = 0.1,
    ) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.model = LengthEstimator(LengthEstimatorConfig(
            text_dim=text_dim, hidden=hidden, max_tokens=max_tokens, dropout=dropout))

    def check_before_training(self, datamodule) -> None:
        super().check_before_training(datamodule)
        check_max_tokens(datamodule, self.hparams.max_tokens)

    def setup(self, stage: str) -> None:
        check_text_features(self)
        check_max_tokens(self.datamodule, self.hparams.max_tokens)

    def step(self, batch: dict) -> dict[str, Tensor]:
        logits = self.model(batch["sentence"])
        target = self.model.frames_to_classes(batch["lengths"])
        tokens = token_lengths(batch["lengths"]).float()
        predicted = (logits.argmax(-1) + 1).float()
        return {
            "loss": F.cross_entropy(logits, target),
            "accuracy": (logits.argmax(-1) == target).float().mean(),
            # Within ±2 tokens (±8 frames) is what matters for a plausible length.
            "within2": ((predicted - tokens).abs() <= 2).float().mean(),
            "abs_error_tokens": (predicted - tokens).abs().mean(),
        }

    def training_step(self, batch: dict, batch_idx: int) -> Tensor:
        terms = self.step(batch)
        self.log("train/loss", terms["loss"], prog_bar=True, batch_size=len(batch["lengths"]))
        return terms["loss"]

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        terms = self.step(batch)
        self.log_dict({f"val/{k}": v for k, v in terms.items()}, batch_size=len(batch["lengths"]),
                      sync_dist=True)

    def test_step(self, batch: dict, batch_idx: int) -> None:
        terms = self.step(batch)
        self.log_dict({f"test/{k}": v for k, v in terms.items()}, batch_size=len(batch["lengths"]),
                      sync_dist=True)

    @torch.no_grad()
    def export_model(self) -> LengthEstimator:
        self.model.meta = {"text_encoder": self.hparams.text_encoder}
        return self.model
