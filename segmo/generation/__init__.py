"""Inference-time decoding: masked base-token decoding with classifier-free guidance,
residual decoding, temporal editing (spec §8). Pure torch, no Lightning."""

from segmo.generation.generate import (
    decode_tokens,
    edit_tokens,
    generate_tokens,
    guidance_condition,
    guided_logits,
    token_mask_from_lengths,
)
from segmo.generation.sampling import SamplingOptions, cosine_schedule, sample_tokens, top_k_count

__all__ = [
    "SamplingOptions",
    "cosine_schedule",
    "decode_tokens",
    "edit_tokens",
    "generate_tokens",
    "guidance_condition",
    "guided_logits",
    "sample_tokens",
    "token_mask_from_lengths",
    "top_k_count",
]
