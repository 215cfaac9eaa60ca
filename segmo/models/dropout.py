"""Dropout whose mask costs a third as much on the CPU: the transformers' and the
tokenizer's training.

On the CPU, `torch.nn.functional.dropout` draws every element's Bernoulli with a call of
its own to the generator: 8.8 ms for a (1152, 512) activation on one Zen 3 core, and the
mask stage's 34 dropouts took 15 % of its training step (`tools/bench_train.py`). Here the
mask comes from 64-bit draws of the same generator, each cut into four 16-bit numbers: an
element is kept where its number is at least p · 2¹⁶, and the kept elements are scaled by
1 / (1 − p'), p' being p rounded to a multiple of 2⁻¹⁶, so that the expectation is x
exactly. 2.7 ms for the same activation. Masks are as random as PyTorch's, reproducible
under `torch.manual_seed` and drawn from the default generator, whose state a resumed run
puts back (`segmo.tasks.base`). Other devices keep PyTorch's kernel, which is fast there.
"""

from __future__ import annotations

import math

import torch
from torch import nn

LEVELS = 1 << 16  # the 16-bit numbers an element's keep draw takes


def keep_scale(shape: torch.Size | tuple[int, ...], p: float, dtype: torch.dtype) -> torch.Tensor:
    """A CPU dropout mask of `shape`: 1 / (1 − p') where an element is kept, else 0, with
    p' = round(p · 2¹⁶) / 2¹⁶ the probability that it is dropped."""
    dropped = round(p * LEVELS)
    count = math.prod(shape)
    bits = torch.empty((count + 3) // 4, dtype=torch.int64).random_(-(1 << 63), None)
    numbers = bits.view(torch.int16)[:count].view(shape)  # uniform over [-2¹⁵, 2¹⁵)
    keep = numbers >= dropped - LEVELS // 2
    return keep.to(dtype).mul_(LEVELS / (LEVELS - dropped))


def dropout(x: torch.Tensor, p: float, training: bool = True) -> torch.Tensor:
    """`torch.nn.functional.dropout(x, p, training)`, with the mask of `keep_scale` on the
    CPU. A p below 2⁻¹⁷ rounds to keeping everything, as x itself."""
    if not 0.0 <= p <= 1.0:
        raise ValueError(f"dropout: p must be in [0, 1], got {p}")
    if not training or p == 0.0:
        return x
    if x.device.type != "cpu":
        return nn.functional.dropout(x, p, True)
    dropped = round(p * LEVELS)
    if dropped == 0:
        return x
    if dropped == LEVELS:
        return x * 0.0
    return x * keep_scale(x.shape, p, x.dtype)


class Dropout(nn.Dropout):
    """`nn.Dropout` with `dropout`'s CPU mask (same argument, state and repr)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return dropout(x, self.p, self.training)
