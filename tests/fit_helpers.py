"""Callbacks that tests pass to `segmo fit` (``--trainer.callbacks+=fit_helpers.X``).

The tests put this folder on PYTHONPATH for `python -m segmo fit` subprocesses (and DDP
ranks, which Lightning starts with the same command line).
"""

from __future__ import annotations

import time
from pathlib import Path

import lightning as L
import torch


class PoisonBatch(L.Callback):
    """Sets every floating-point tensor of training batch ``at_batch`` to NaN."""

    def __init__(self, at_batch: int = 1) -> None:
        self.at_batch = at_batch

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step == self.at_batch:
            for value in batch.values():
                if isinstance(value, torch.Tensor) and value.is_floating_point():
                    value.fill_(float("nan"))


class HangAt(L.Callback):
    """Writes ``marker`` and sleeps before training step ``step`` (the test kills it then)."""

    def __init__(self, step: int, marker: str) -> None:
        self.step, self.marker = step, marker

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_step == self.step:
            Path(self.marker).write_text(str(self.step))
            time.sleep(600)


class SaveRankState(L.Callback):
    """At the end of training, saves each rank's state dict and the sample ids it trained
    on to ``DIRECTORY/rank<k>.pt``."""

    def __init__(self, directory: str) -> None:
        self.directory = directory
        self.ids: list[str] = []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        self.ids += [str(i) for i in batch.get("id", [])]

    def on_train_end(self, trainer, pl_module):
        Path(self.directory).mkdir(parents=True, exist_ok=True)
        state = {k: v.detach().cpu().clone() for k, v in pl_module.state_dict().items()}
        torch.save({"state": state, "ids": self.ids, "step": trainer.global_step,
                    "world_size": trainer.world_size},
                   Path(self.directory) / f"rank{trainer.global_rank}.pt")


class SaveStepWeights(L.Callback):
    """After every optimizer step, keeps the task's trainable weights; at the end of
    training, saves them to ``DIRECTORY/steps.pt`` as {global step: state}."""

    def __init__(self, directory: str) -> None:
        self.directory = directory
        self.steps: dict[int, dict[str, torch.Tensor]] = {}

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.steps[trainer.global_step] = {name: p.detach().cpu().clone()
                                           for name, p in pl_module.named_parameters() if p.requires_grad}

    def on_train_end(self, trainer, pl_module):
        Path(self.directory).mkdir(parents=True, exist_ok=True)
        torch.save(self.steps, Path(self.directory) / "steps.pt")



class LastCheckpointSteps(L.Callback):
    """Before each training step, notes the global step that the run's last.ckpt holds
    (`steps`: {global step: last.ckpt's step, or None before there is one})."""

    def __init__(self) -> None:
        self.steps: dict[int, int | None] = {}

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        last = Path(trainer.checkpoint_callback.dirpath) / "last.ckpt"
        self.steps[trainer.global_step] = (
            torch.load(last, weights_only=False)["global_step"] if last.is_file() else None)
