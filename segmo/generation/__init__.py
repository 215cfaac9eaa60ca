"""Inference-time decoding: masked base-token decoding with classifier-free guidance,
residual decoding (`generate`), temporal editing (`editing`), the options of both
(`sampling.SamplingOptions`) (spec §8). Pure torch, no Lightning."""

from segmo.generation.editing import edit_drift, edit_tokens, token_span
from segmo.generation.generate import (
    decode_tokens,
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
    "edit_drift",
    "edit_tokens",
    "generate_tokens",
    "guidance_condition",
    "guided_logits",
    "sample_tokens",
    "token_mask_from_lengths",
    "token_span",
    "top_k_count",
]
