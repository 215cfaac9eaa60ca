"""Training stage 3: the residual transformer (spec §6).

Each step takes the batch's tokens (cached, or encoded by the frozen tokenizer:
`TransformerTask`), draws a target layer j ∈ 1..q−1
per sample (favouring low layers), and predicts every valid token of layer j from the
sum of the embeddings of layers 0..j−1, the caption and its segments. The whole
condition is dropped with probability `cond_drop_prob` for classifier-free guidance.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import Tensor

from segmo.data.motion_tokens import tokenizer_digest
from segmo.models.hub import portable_path
from segmo.models.mask_transformer import masked_token_loss
from segmo.models.residual_transformer import (
    ResidualTransformer,
    ResidualTransformerConfig,
    sample_layers,
)
from segmo.tasks.common import (
    TransformerTask,
    text_condition,
    token_mask,
    word_condition,
)


class ResidualTask(TransformerTask):
    """Trains `ResidualTransformer` on batches with cached text features."""

    stage: ClassVar[str] = "residual"
    monitor: ClassVar[str] = "val/loss"

    def __init__(self, tokenizer: str, cond_drop_prob: float = 0.2, **kwargs) -> None:
        """The arguments (`**kwargs`) are `TransformerTask`'s; the condition is dropped more
        often than in the mask stage (MoMask)."""
        super().__init__(tokenizer=tokenizer, cond_drop_prob=cond_drop_prob, **kwargs)
        self.model = ResidualTransformer(ResidualTransformerConfig(
            **self.transformer_config(), num_quantizers=self.tokenizer.num_quantizers))

    def step(self, batch: dict, generator: torch.Generator | None = None,
             drop: Tensor | None = None) -> dict[str, Tensor]:
        indices = self.batch_tokens(batch)  # (b, n, q)
        b, n, q = indices.shape
        valid = token_mask(batch["lengths"], n)
        sentence, segments, segment_mask = text_condition(batch)
        layer = sample_layers(b, q, generator=generator).to(indices.device)
        if drop is None:
            drop = torch.rand(b, device=indices.device) < self.hparams.cond_drop_prob
        out = self.model(indices, layer, valid, sentence, segments, segment_mask, drop,
                         **word_condition(batch, self.model), keep_local=self.keep_local(drop))
        target = indices.gather(2, layer[:, None, None].expand(b, n, 1))[..., 0]
        loss = masked_token_loss(out.logits, target, valid)
        correct = (out.logits.argmax(-1) == target) & valid
        return {"loss": loss, "accuracy": correct.sum() / valid.sum()}

    def training_step(self, batch: dict, batch_idx: int) -> Tensor:
        terms = self.step(batch)
        b = batch["motion"].shape[0]
        self.log("train/loss", terms["loss"], prog_bar=True, batch_size=b)
        self.log("train/accuracy", terms["accuracy"], batch_size=b)
        return terms["loss"]

    def _evaluate(self, prefix: str, batch: dict, batch_idx: int) -> None:
        b = batch["motion"].shape[0]
        generator = torch.Generator().manual_seed(batch_idx)
        terms = self.step(batch, generator, drop=torch.zeros(b, dtype=torch.bool,
                                                             device=batch["motion"].device))
        self.log_dict({f"{prefix}/{k}": v for k, v in terms.items()}, batch_size=b, sync_dist=True)

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        self._evaluate("val", batch, batch_idx)

    def test_step(self, batch: dict, batch_idx: int) -> None:
        self._evaluate("test", batch, batch_idx)

    def export_model(self) -> ResidualTransformer:
        self.model.meta = {"tokenizer": portable_path(self.hparams.tokenizer),
                           "tokenizer_digest": tokenizer_digest(self.tokenizer),  # `segmo bundle`
                           "text_encoder": self.hparams.text_encoder,
                           "cond_drop_prob": self.hparams.cond_drop_prob}
        return self.model
