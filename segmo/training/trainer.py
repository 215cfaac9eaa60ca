"""The Trainer `segmo fit` builds: Lightning's, with `precision: auto`.

``--trainer.precision auto`` (the built-in corpus' recipes) trains in ``bf16-mixed`` where
the hardware computes bf16 natively and in ``32-true`` elsewhere: on a CPU the choice of
`segmo.cpu.auto_precision` (AVX-512 BF16 or AMX: bf16; AVX2 hosts, where bf16 is emulated
and several times slower or does not run at all: fp32), on a CUDA GPU whether it supports
bf16. The choice and its reason are logged once. Every other value is Lightning's.
"""

from __future__ import annotations

from typing import Literal

import torch
from lightning.fabric.connector import _PRECISION_INPUT
from lightning.pytorch import Trainer
from lightning.pytorch.utilities import rank_zero_info

from segmo import cpu


def auto_training_precision(accelerator: object = "auto") -> tuple[str, str]:
    """The Lightning precision `precision="auto"` trains with, and why."""
    on_gpu = accelerator in ("auto", "gpu", "cuda") and torch.cuda.is_available()
    if on_gpu:
        if torch.cuda.is_bf16_supported():
            return "bf16-mixed", f"native bf16 on {torch.cuda.get_device_name()}"
        return "32-true", f"{torch.cuda.get_device_name()} has no bf16"
    kind, reason = cpu.auto_precision()
    return ("bf16-mixed" if kind == "bf16" else "32-true"), reason


class SegmoTrainer(Trainer):
    """`lightning.pytorch.Trainer`, whose ``precision`` also takes ``"auto"``."""

    def __init__(self, *args, precision: _PRECISION_INPUT | Literal["auto"] | None = None, **kwargs) -> None:
        if precision == "auto":
            precision, reason = auto_training_precision(kwargs.get("accelerator", "auto"))
            rank_zero_info(f"precision auto: {precision} ({reason})")
        super().__init__(*args, precision=precision, **kwargs)
