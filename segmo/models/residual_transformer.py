"""The residual transformer: predicts the tokens of RVQ layer j from layers 0..j−1 (spec §6).

Prefix = [sentence, segments 1..A]; the motion input is the sum of the per-layer code
embeddings of layers 0..j−1 (index −1, a dropped or padded code, adds nothing) plus an
embedding of the target layer j. MoMask (and spec §6) put the layer in a prefix token
instead; as a prefix token it would change the prefix's encoding with every layer, while
added to the motion inputs it leaves the text prefix the same for all q−1 passes of a
generation, so it is encoded once (`condition()`), as in the mask transformer. The logits of layer j are the dot products with the embedding table of layer j
("shared weights"), so each layer's codes have a single vector used both ways.

Training (the task owns the loop; CFG drop probability 0.2 is the task's):

    layer = sample_layers(b, model.config.num_quantizers, generator)
    out = model(indices, layer, token_mask, sentence, segments, segment_mask, drop_condition)
    target = indices.gather(2, layer[:, None, None].expand(-1, n, 1))[..., 0]
    loss = masked_token_loss(out.logits, target, token_mask)
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from segmo.models.mask_transformer import cosine_schedule
from segmo.models.pretrained import Pretrained
from segmo.models.text_prefix import Condition, TextPrefix
from segmo.models.transformer import TokenHead, TransformerConfig, Trunk, init_weights


@dataclass
class ResidualTransformerConfig(TransformerConfig):
    num_quantizers: int = 6  # of the tokenizer; this model predicts layers 1..q−1


@dataclass
class ResidualTransformerOutput:
    """logits (b, n, codebook_size) for layer j; motion_features (b, n, dim) (n → m when
    `forward_embedded` is given positions)."""

    logits: torch.Tensor
    motion_features: torch.Tensor


class ResidualTransformer(nn.Module, Pretrained):
    """Bidirectional transformer over `[sentence, segments, Σ code embeddings + layer]`."""

    kind = "residual"
    config_class = ResidualTransformerConfig

    def __init__(self, config: ResidualTransformerConfig) -> None:
        super().__init__()
        if config.num_quantizers < 2:
            raise ValueError("ResidualTransformerConfig: num_quantizers must be ≥ 2 "
                             f"(there is no residual layer), got {config.num_quantizers}")
        self.config = config
        self.meta: dict = {}
        # (q, codebook_size, dim): input embedding of every layer, output weights of 1..q−1.
        self.code_embeddings = nn.Parameter(
            torch.randn(config.num_quantizers, config.codebook_size, config.dim) * 0.02
        )
        self.output_bias = nn.Parameter(torch.zeros(config.num_quantizers, config.codebook_size))
        self.layer_embeddings = nn.Parameter(torch.randn(config.num_quantizers, config.dim) * 0.02)
        self.prefix = TextPrefix(config.text_dim, config.dim, config.max_segments,
                                 config.text_tokens, config.max_words, config.word_attention,
                                 config.word_norm)
        self.trunk = Trunk(config.dim, config.depth, config.heads, config.ff_dim, config.dropout,
                           config.norm_first, config.max_tokens, config.memory_slots,
                           config.text_tokens == "words" and config.word_attention == "cross")
        self.head = TokenHead(config.dim)
        # The tied output projection; `segmo.models.cpu_inference` swaps in a faster one.
        self.project = F.linear
        self.apply(init_weights)

    def output_weight(self, layer: int) -> torch.Tensor:
        """(codebook_size, dim) output projection of `layer`: the layer's embedding table."""
        return self.code_embeddings[layer]

    def condition(self, sentence: torch.Tensor, segments: torch.Tensor,
                  segment_mask: torch.Tensor, drop_condition: torch.Tensor | None = None,
                  words: torch.Tensor | None = None, word_mask: torch.Tensor | None = None,
                  keep_local: torch.Tensor | None = None) -> Condition:
        """Text prefix tokens (b, 1 + a, dim) and their encoding by the trunk, which depends
        on neither the motion nor the layer: computed once for all residual passes. `words`
        and `word_mask`: as in `MaskTransformer.condition`."""
        condition = self.prefix(sentence, segments, segment_mask, drop_condition, None,
                                words, word_mask, keep_local)
        condition.encoded = self.trunk.encoded(condition)
        return condition

    def embed_layer(self, indices: torch.Tensor, layer: int) -> torch.Tensor:
        """indices (b, n) codes of one layer, −1 = none → embeddings (b, n, dim)."""
        table = self.code_embeddings[layer]
        return F.embedding(indices.clamp(min=0), table) * (indices >= 0)[..., None].to(table.dtype)

    def embed(self, indices: torch.Tensor, layer: torch.Tensor | int) -> torch.Tensor:
        """indices (b, n, q) codes, layer (b,) or int → Σ_{l<layer} embedding_l (b, n, dim)."""
        b, n, q = indices.shape
        if q != self.config.num_quantizers:
            raise ValueError(f"ResidualTransformer.embed: indices have {q} layers, the model "
                             f"has num_quantizers={self.config.num_quantizers}")
        layer = self._layer_tensor(layer, b, indices.device)
        # Row l of the flattened (q·codebook_size) table holds layer l's codes.
        offsets = torch.arange(q, device=indices.device) * self.config.codebook_size
        flat = self.code_embeddings.reshape(-1, self.config.dim)
        embedded = F.embedding(indices.clamp(min=0) + offsets, flat)  # (b, n, q, dim)
        keep = (indices >= 0) & (torch.arange(q, device=indices.device) < layer[:, None, None])
        return (embedded * keep[..., None].to(embedded.dtype)).sum(dim=2)

    def forward_embedded(self, x: torch.Tensor, layer: torch.Tensor | int,
                         token_mask: torch.Tensor, condition: Condition,
                         positions: torch.Tensor | None = None) -> ResidualTransformerOutput:
        """x (b, n, dim) summed embeddings of the layers below `layer`; layer (b,) or int in
        1..q−1; token_mask (b, n) bool; condition from `condition()`; positions (b, m)
        long: where logits and features are wanted (None = all n; `Trunk.forward_motion`)."""
        b = x.shape[0]
        if x.shape[:2] != token_mask.shape or b != condition.tokens.shape[0]:
            raise ValueError(f"ResidualTransformer: inputs {tuple(x.shape[:2])}, token_mask "
                             f"{tuple(token_mask.shape)} and condition batch "
                             f"{condition.tokens.shape[0]} disagree")
        token_mask = token_mask.bool()
        if isinstance(layer, int):
            self._check_layer(torch.tensor([layer]))
            layer_embedding = self.layer_embeddings[layer]
        else:
            self._check_layer(layer)
            layer_embedding = self.layer_embeddings[layer][:, None]
        encoded = self.trunk.encoded(condition)
        motion = self.trunk.forward_motion(x + layer_embedding.to(x.dtype), token_mask, encoded,
                                           positions)
        out = self.head(motion)
        if isinstance(layer, int):
            logits = self.project(out, self.output_weight(layer), self.output_bias[layer])
        else:
            weight = self.code_embeddings[layer]  # (b, codebook_size, dim)
            logits = torch.einsum("bnd,bvd->bnv", out, weight) + self.output_bias[layer][:, None]
        return ResidualTransformerOutput(logits=logits, motion_features=motion)

    def forward(self, indices: torch.Tensor, layer: torch.Tensor | int,
                token_mask: torch.Tensor, sentence: torch.Tensor, segments: torch.Tensor,
                segment_mask: torch.Tensor, drop_condition: torch.Tensor | None = None,
                words: torch.Tensor | None = None, word_mask: torch.Tensor | None = None,
                keep_local: torch.Tensor | None = None) -> ResidualTransformerOutput:
        """indices (b, n, q) codes (layers ≥ layer are ignored), layer (b,) long or int in
        1..q−1, token_mask (b, n), sentence (b, text_dim), segments (b, a, text_dim),
        segment_mask (b, a), drop_condition (b,) bool → logits of layer `layer`."""
        condition = self.condition(sentence, segments, segment_mask, drop_condition, words,
                                   word_mask, keep_local)
        return self.forward_embedded(self.embed(indices, layer), layer, token_mask, condition)

    def _layer_tensor(self, layer: torch.Tensor | int, b: int, device) -> torch.Tensor:
        if isinstance(layer, int):
            return torch.full((b,), layer, dtype=torch.long, device=device)
        if layer.shape != (b,):
            raise ValueError(f"ResidualTransformer: layer must be an int or ({b},), "
                             f"got {tuple(layer.shape)}")
        return layer

    def _check_layer(self, layer: torch.Tensor) -> None:
        q = self.config.num_quantizers
        if bool(((layer < 1) | (layer >= q)).any()):
            raise ValueError(f"ResidualTransformer: layer must be in 1..{q - 1}, "
                             f"got {layer.tolist()}")


def sample_layers(batch_size: int, num_quantizers: int,
                  generator: torch.Generator | None = None,
                  device: torch.device | str | None = None) -> torch.Tensor:
    """Draw the target layer j ∈ 1..q−1 of each sample, favouring low layers.

    With u ~ U(0, 1) and s = 1 − cos(πu/2) (dense near 0), j = 1 + ⌊s·(q−1)⌋, so
    P(j ≤ k) = (2/π)·arccos(1 − k/(q−1)). For q = 6: P(j = 1..5) ≈ 0.41, 0.18, 0.15, 0.13, 0.13.
    Low layers carry most of the signal and condition every later one. → (b,) long.
    """
    u = torch.rand(batch_size, generator=generator, device=device)
    s = 1.0 - cosine_schedule(u)
    return (1 + torch.floor(s * (num_quantizers - 1)).long()).clamp(max=num_quantizers - 1)
