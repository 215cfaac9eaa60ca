"""Length estimator: sentence vector → distribution over motion lengths (spec §8).

Classes are token lengths: class k ↔ n = k + 1 tokens ↔ 4·(k + 1) frames, for
n = 1..max_tokens. Training is cross-entropy against `frames_to_classes(lengths)`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from segmo.models.pretrained import Pretrained
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.models.transformer import init_weights


@dataclass
class LengthEstimatorConfig:
    text_dim: int = 512
    hidden: int = 256
    max_tokens: int = 49
    dropout: float = 0.2


class LengthEstimator(nn.Module, Pretrained):
    """Two-layer MLP (LayerNorm, LeakyReLU, dropout) on the pooled sentence vector."""

    kind = "length"
    config_class = LengthEstimatorConfig

    def __init__(self, config: LengthEstimatorConfig) -> None:
        super().__init__()
        self.config = config
        self.meta: dict = {}
        h = config.hidden
        self.mlp = nn.Sequential(
            nn.Linear(config.text_dim, h), nn.LayerNorm(h), nn.LeakyReLU(0.2),
            nn.Dropout(config.dropout),
            nn.Linear(h, h // 2), nn.LayerNorm(h // 2), nn.LeakyReLU(0.2),
            nn.Linear(h // 2, config.max_tokens),
        )
        self.apply(init_weights)

    def forward(self, sentence: torch.Tensor) -> torch.Tensor:
        """sentence (b, text_dim) → logits (b, max_tokens) over token lengths 1..max_tokens."""
        if sentence.dim() != 2 or sentence.shape[1] != self.config.text_dim:
            raise ValueError(f"LengthEstimator: sentence must be (b, {self.config.text_dim}), "
                             f"got {tuple(sentence.shape)}")
        return self.mlp(sentence)

    def frames_to_classes(self, lengths: torch.Tensor) -> torch.Tensor:
        """lengths (b,) in frames, multiples of 4 in [4, 4·max_tokens] → classes (b,) long."""
        limit = FRAMES_PER_TOKEN * self.config.max_tokens
        bad = (lengths % FRAMES_PER_TOKEN != 0) | (lengths < FRAMES_PER_TOKEN) | (lengths > limit)
        if bool(bad.any()):
            raise ValueError(f"LengthEstimator.frames_to_classes: lengths must be multiples of "
                             f"{FRAMES_PER_TOKEN} in [{FRAMES_PER_TOKEN}, {limit}], got "
                             f"{lengths[bad].tolist()}")
        return (lengths // FRAMES_PER_TOKEN - 1).long()

    @torch.no_grad()
    def sample(self, sentence: torch.Tensor, generator: torch.Generator | None = None,
               temperature: float = 1.0) -> torch.Tensor:
        """Sample a length per sentence from the softmax: sentence (b, text_dim) →
        lengths (b,) long in frames. temperature 0 takes the most likely length."""
        logits = self(sentence).float()
        if temperature == 0:
            classes = logits.argmax(dim=-1)
        else:
            probs = torch.softmax(logits / temperature, dim=-1)
            classes = torch.multinomial(probs, 1, generator=generator)[:, 0]
        return (classes + 1) * FRAMES_PER_TOKEN
