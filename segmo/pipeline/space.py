"""SegMo's learned segment space (paper §4.4), where grounding and retrieval compare text
segments with motion spans.

The query text and the motion both go through the mask transformer, UNMASKED and
conditioned on the text and its segments, fed as a set (without their order embeddings,
the mode `MaskTask.order_drop_prob` trains), so that a segment is located by content.
Text segments are the alignment head's `embed_text` of the segments' projected text
vectors; a motion span is its `embed_motion` (mean ‖ max pooling + MLP) over that span of
the motion outputs. Cosine similarity compares them. Because the motion features depend
on the text prefix, every (text, motion) pair is its own forward pass; pairs are batched.

This module is the one place that reads the tokenizer's latents and the alignment head.
`SegMo.embed_segments` prepares the texts and motions and calls `embed_segments` here;
`segmo.pipeline.grounding` and `segmo.pipeline.retrieval` work on what it returns.

    space = model.embed_segments(["a person walks, then waves"], [features])
    space.similarity([[0, 5], [5, 10]])      # (1, a, 2) cosine of each segment vs each span
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import torch

from segmo.errors import SegmoError
from segmo.generation.generate import inference
from segmo.models.alignment import AlignmentHead, segment_similarity
from segmo.models.mask_transformer import MaskTransformer
from segmo.models.tokenizer import FRAMES_PER_TOKEN, RVQVAE


@dataclass
class SegmentEmbeddings:
    """b (text, motion) pairs in the learned space: text i's segments, motion i's features.

    segments: the text segments of each text (a = the most of the batch);
    text: (b, a, out_dim) embedded text segments (not normalised);
    segment_mask: (b, a) bool, slots that hold a text segment;
    num_tokens: (b,) long, valid motion tokens (frames // 4) of each motion;
    latents: (b, n, code_dim) the tokenizer's latents of the motions (the input of the
        cpd/kmeans motion segmenters), each motion encoded at its own length, zero past
        its num_tokens.
    """

    segments: list[list[str]]
    text: torch.Tensor
    segment_mask: torch.Tensor
    num_tokens: torch.Tensor
    latents: torch.Tensor
    features: torch.Tensor = field(repr=False)  # (b, n, dim) motion outputs of the pass
    head: AlignmentHead = field(repr=False)

    def motion(self, spans: Any) -> torch.Tensor:
        """Token spans (b, k, 2), or (k, 2) for every pair → embedded spans (b, k, out_dim)."""
        spans = torch.as_tensor(spans, device=self.features.device).long()
        if spans.ndim == 2:
            spans = spans.expand(self.features.shape[0], -1, -1)
        with torch.inference_mode():
            return self.head.embed_motion(self.features, spans)

    def similarity(self, spans: Any) -> torch.Tensor:
        """Cosine of each text segment with each span (spans as in `motion`) → (b, a, k)."""
        with torch.inference_mode():
            return segment_similarity(self.text, self.motion(spans))


class SegmentModel(Protocol):
    """What grounding and retrieval ask of a model (`SegMo` is one)."""

    def embed_segments(self, texts: list[str], motions: Any, *,
                       segments: list[list[str]] | None = None, lengths: Any = None,
                       normalized: bool = False) -> SegmentEmbeddings: ...

    def segment_texts(self, texts: list[str]) -> list[list[str]]: ...


def alignment_head(mask: MaskTransformer) -> AlignmentHead:
    """The mask transformer's alignment head, or SegmoError saying why there is none."""
    if mask.alignment is None:
        raise SegmoError("SegMo: this mask transformer was trained without segment alignment "
                         "(alignment: none), so it has no shared text/motion space; grounding by "
                         "similarity, retrieval and embed_pairs need a model trained with alignment "
                         "(ground(..., method='attention') needs none)")
    return mask.alignment


def embed_segments(tokenizer: RVQVAE, mask: MaskTransformer, z: torch.Tensor,
                   frames: torch.Tensor, sentence: torch.Tensor, vectors: torch.Tensor,
                   segment_mask: torch.Tensor, segments: list[list[str]],
                   words: torch.Tensor | None = None, word_mask: torch.Tensor | None = None
                   ) -> SegmentEmbeddings:
    """One unmasked pass of the mask transformer over b pairs.

    z (b, t, d) z-scored motions padded with zeros, frames (b,) their lengths (multiples
    of 4; each motion is encoded at its own length, so the padding changes none of its
    latents, and its latents past its tokens are zero); sentence (b, text_dim), vectors (b, a, text_dim), segment_mask (b, a) bool and
    segments: the text condition (`SegMo.text_condition`); words, word_mask: the texts'
    word features for a model with word keys (`SegMo.word_condition`).
    """
    head = alignment_head(mask)
    with inference([tokenizer, mask], "fp32", z.device):
        latents = tokenizer.latents(z, frames)
        base = tokenizer.quantize(latents)[..., 0]
        num_tokens = frames // FRAMES_PER_TOKEN
        token_mask = torch.arange(base.shape[1], device=z.device) < num_tokens[:, None]
        # Segments as a set: the motion features must say where each segment is from what
        # the motion does, not from where the caption put it (`TextPrefix`).
        unordered = torch.ones(len(segments), dtype=torch.bool, device=z.device)
        out = mask(base, token_mask, sentence, vectors, segment_mask, unordered=unordered,
                   words=words, word_mask=word_mask)
        text = head.embed_text(out.segment_features)
    return SegmentEmbeddings(segments=segments, text=text, segment_mask=segment_mask,
                             num_tokens=num_tokens, latents=latents,
                             features=out.motion_features, head=head)
