"""Training the frame-wise action classifier of the action-order metric (built-in corpus).

`segmo fit --config configs/action_classifier/synthetic.yaml --data.root DIR`, then
`segmo export runs/action_classifier/synthetic/version_0/checkpoints/last.ckpt --out
models/action_classifier`, used with `segmo evaluate --action-classifier DIR`.
`segmo evaluate --action-classifier train` runs this task in its own process instead
(`train_action_classifier`: a plain Lightning Trainer, no run directory).

Data: `MotionDataModule(frame_labels=True)` (`segmo.data.actions`): whole clips z-scored
with the dataset's statistics, which are copied into the model; one label per frame, the
main action of its ground-truth span; frames outside every span are ignored. Classes are
the train split's action names, kept in checkpoints so that `load_from_checkpoint`
rebuilds the network before loading. Loss: cross-entropy over the labelled frames.
Optimiser: AdamW with a one-cycle schedule (peak `lr`) over all the steps of the run.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import lightning as L
import torch
import torch.nn.functional as F
from torch import Tensor

from segmo.data.attributes import ATTRIBUTES, attribute_slices, num_attribute_classes
from segmo.data.collate import IGNORE
from segmo.data.datamodule import MotionDataModule
from segmo.errors import SegmoError
from segmo.models.action_classifier import (
    ActionClassifier,
    ActionClassifierConfig,
    AttributeClassifier,
)
from segmo.motion.skeleton import SkeletonName, get_skeleton
from segmo.tasks.base import Task


class ActionClassifierTask(Task):
    """Trains `ActionClassifier` on batches {"motion" (b, t, d) z-scored, "labels" (b, t)}."""

    stage: ClassVar[str] = "action_classifier"
    monitor: ClassVar[str] = "val/loss"

    def __init__(
        self,
        skeleton: SkeletonName = "t2m",
        width: int = 64,
        depth: int = 4,
        kernel: int = 5,
        dropout: float = 0.1,
        lr: float = 2e-3,
        weight_decay: float = 1e-4,
    ) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.skeleton = get_skeleton(skeleton)
        self.model: ActionClassifier | None = None
        self.dataset = ""

    def _build(self, classes: list[str]) -> ActionClassifier:
        h = self.hparams
        model = ActionClassifier(ActionClassifierConfig(
            feature_dim=self.skeleton.feature_dim, num_classes=len(classes), width=h.width,
            depth=h.depth, kernel=h.kernel, dropout=h.dropout))
        model.meta = {"classes": list(classes)}
        return model

    def setup(self, stage: str) -> None:
        datamodule = self.datamodule
        if datamodule is None:
            return
        self.check_skeleton()
        if not getattr(datamodule, "frame_labels", False):
            raise SegmoError("ActionClassifierTask: the data carry no frame labels; set "
                             "data.init_args.frame_labels: true")
        self.dataset = str(datamodule.root)
        if self.model is None:
            self.model = self._build(datamodule.classes)
        else:
            self._check_classes(datamodule)
        if stage == "fit":
            with torch.no_grad():
                self.model.mean.copy_(datamodule.mean)
                self.model.std.copy_(datamodule.std)

    def _check_classes(self, datamodule) -> None:
        if self.model.classes != datamodule.classes:
            raise SegmoError(f"ActionClassifierTask: the checkpoint's classes {self.model.classes} "
                             f"are not those of {datamodule.root}'s train split "
                             f"{datamodule.classes}")

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        super().on_save_checkpoint(checkpoint)
        checkpoint["action_classes"] = list(self.model.classes)

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        super().on_load_checkpoint(checkpoint)
        if self.model is None:
            self.model = self._build(checkpoint["action_classes"])

    def configure_optimizers(self):
        self.check_optimiser()
        h = self.hparams
        optimizer = torch.optim.AdamW(self.model.parameters(), lr=h.lr, weight_decay=h.weight_decay)
        schedule = torch.optim.lr_scheduler.OneCycleLR(
            optimizer, max_lr=h.lr, total_steps=self.trainer.estimated_stepping_batches)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": schedule, "interval": "step"}}

    # -- steps -------------------------------------------------------------------------------

    def _losses(self, batch: dict[str, Any]) -> tuple[Tensor, Tensor, Tensor]:
        """(loss, correct labelled frames, labelled frames)."""
        logits = self.model(batch["motion"])  # (b, t, classes)
        labels = batch["labels"]  # (b, t)
        loss = F.cross_entropy(logits.flatten(0, 1), labels.flatten(), ignore_index=IGNORE)
        labelled = labels != IGNORE
        return loss, (logits.argmax(-1) == labels)[labelled].sum(), labelled.sum()

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> Tensor:
        loss, _, _ = self._losses(batch)
        self.log("train/loss", loss, prog_bar=True, batch_size=len(batch["id"]))
        return loss

    def _evaluate(self, prefix: str, batch: dict[str, Any]) -> None:
        loss, correct, frames = self._losses(batch)
        self.log(f"{prefix}/loss", loss, batch_size=int(frames), sync_dist=True)
        self.log(f"{prefix}/frame_accuracy", correct / frames.clamp(min=1), prog_bar=True,
                 batch_size=int(frames), sync_dist=True)

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        self._evaluate("val", batch)

    def test_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        self._evaluate("test", batch)

    # -- export ------------------------------------------------------------------------------

    def export_model(self) -> ActionClassifier:
        if self.model is None:
            raise ValueError("ActionClassifierTask.export_model: the network was never built "
                             "(no setup or checkpoint)")
        self.model.meta.update({"dataset": self.dataset, "skeleton": self.skeleton.name,
                                "fps": self.skeleton.fps})
        return self.model


class AttributeClassifierTask(ActionClassifierTask):
    """Trains `AttributeClassifier`: frames labelled with their action's side, count and
    speed (`segmo.data.attributes`; data ``frame_labels: attributes``), one cross-entropy
    per attribute over the frames where the action has it."""

    stage: ClassVar[str] = "attribute_classifier"
    CLASSES: ClassVar[list[str]] = [f"{a}={v}" for a, values in ATTRIBUTES.items() for v in values]

    def _build(self, classes: list[str]) -> AttributeClassifier:
        h = self.hparams
        model = AttributeClassifier(ActionClassifierConfig(
            feature_dim=self.skeleton.feature_dim, num_classes=num_attribute_classes(),
            width=h.width, depth=h.depth, kernel=h.kernel, dropout=h.dropout))
        model.meta = {"classes": list(classes)}
        return model

    def setup(self, stage: str) -> None:
        datamodule = self.datamodule
        if datamodule is not None and getattr(datamodule, "frame_labels", False) != "attributes":
            raise SegmoError("AttributeClassifierTask: set data.init_args.frame_labels: attributes")
        if datamodule is not None and self.model is None:
            self.model = self._build(self.CLASSES)
        super().setup(stage)

    def _check_classes(self, datamodule) -> None:
        if self.model.classes != self.CLASSES:
            raise SegmoError(f"AttributeClassifierTask: the checkpoint's classes {self.model.classes} "
                             f"are not {self.CLASSES}")

    def _losses(self, batch: dict[str, Any]) -> tuple[Tensor, Tensor, Tensor]:
        logits = self.model(batch["motion"])  # (b, t, classes)
        labels = batch["labels"]  # (b, t, attributes)
        losses, correct, counted = [], 0, 0
        for k, part in enumerate(attribute_slices().values()):
            target = labels[..., k]
            if (target != IGNORE).any():
                losses.append(F.cross_entropy(logits[..., part].flatten(0, 1), target.flatten(),
                                              ignore_index=IGNORE))
            labelled = target != IGNORE
            correct = correct + (logits[..., part].argmax(-1) == target)[labelled].sum()
            counted = counted + labelled.sum()
        loss = torch.stack(losses).sum() if losses else logits.sum() * 0.0
        return loss, torch.as_tensor(correct), torch.as_tensor(counted)


def train_action_classifier(root: str | Path, epochs: int = 15, batch_size: int = 32,
                            lr: float = 2e-3, seed: int = 0, max_motions: int | None = None,
                            width: int = 64, depth: int = 4) -> ActionClassifier:
    """Train `ActionClassifierTask` on ``ROOT``'s train split in this process and return the
    model (eval mode); no run directory, checkpoint or validation. The global random state
    is left as it was."""
    data = MotionDataModule(str(root), batch_size=batch_size, seed=seed, max_motions=max_motions,
                            frame_labels=True)
    with torch.random.fork_rng():
        torch.manual_seed(seed)  # initial weights and dropout masks
        task = ActionClassifierTask(width=width, depth=depth, lr=lr)
        trainer = L.Trainer(max_epochs=epochs, accelerator="cpu", devices=1, logger=False,
                            enable_checkpointing=False, enable_progress_bar=False,
                            enable_model_summary=False, limit_val_batches=0,
                            num_sanity_val_steps=0)
        trainer.fit(task, datamodule=data)
    return task.export_model().eval()
