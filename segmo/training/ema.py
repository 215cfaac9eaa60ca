"""`EMA`: an exponential moving average of a task's weights, kept during `segmo fit`.

Lightning's `WeightAveraging` does the bookkeeping: the average is updated after every
optimizer step, validation runs on the averaged weights, the checkpoint's ``state_dict``
holds them (the trained weights go under ``current_model_state``, from which a resumed run
continues) and the task ends training with them, so `segmo export` writes the average.

Why not Lightning's own `EMAWeightAveraging`: it averages with ``decay * ema + (1 - decay)
* weight``, which rounds a frozen weight away from itself a little at every step (the
token-level tasks carry their frozen tokenizer); `torch.lerp` here leaves a weight that did
not change bit for bit as it was.

Turn it on for any stage, in the YAML or on the command line::

    segmo fit --config configs/mask/synthetic.yaml \\
        --trainer.callbacks+=segmo.training.ema.EMA --trainer.callbacks.decay=0.999
"""

from __future__ import annotations

from lightning.pytorch.callbacks import WeightAveraging
from torch.optim.swa_utils import get_ema_multi_avg_fn

from segmo.errors import SegmoError


class EMA(WeightAveraging):
    """The average ``ema <- ema + (1 - decay) * (weight - ema)`` of every weight and buffer
    after each optimizer step from ``start_step`` on (the first update copies the weights).
    ``decay`` 0.999 averages over about the last 1,000 steps."""

    def __init__(self, decay: float = 0.999, start_step: int = 0) -> None:
        if not 0.0 < decay < 1.0:
            raise SegmoError(f"EMA: decay must lie strictly between 0 and 1, got {decay}")
        if start_step < 0:
            raise SegmoError(f"EMA: start_step must be 0 or more, got {start_step}")
        super().__init__(multi_avg_fn=get_ema_multi_avg_fn(decay))
        self.decay = decay
        self.start_step = start_step

    def should_update(self, step_idx: int | None = None, epoch_idx: int | None = None) -> bool:
        return step_idx is not None and step_idx >= self.start_step
