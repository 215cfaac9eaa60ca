"""Token sampling: the options of a generation (`SamplingOptions`), top-k, temperature,
categorical or Gumbel-max draws (spec §8).

All randomness comes from an optional `torch.Generator`, so a seed fixes the result.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Literal, get_args

import torch

from segmo.errors import SegmoError
from segmo.models.mask_transformer import cosine_schedule

__all__ = ["Guidance", "Remasking", "Sampler", "SamplingOptions", "Unconditional", "WordText",
           "check_word_text", "cosine_schedule", "gumbel_noise", "sample_tokens", "top_k_count"]

Sampler = Literal["categorical", "gumbel"]
Guidance = Literal["cfg", "sink_ctrl"]
Unconditional = Literal["none", "local"]
WordText = Literal["caption", "segments"]
SegmentTiming = Literal["predicted", "none"]
Remasking = Literal["confidence", "segments"]
# The most decoding steps: far above any useful schedule (MoMask decodes in 10, the demo
# bundle in 4), so that a typo cannot make the schedule itself take gigabytes.
MAX_STEPS = 1000
# The largest guidance scale or weight (in size): far above any useful one (bundles use 2
# to 5), and small enough that the guided float32 logits cannot overflow to inf, which
# turns every probability into NaN and draws the worst token.
MAX_SCALE = 1e6
SCALES = ("guidance_scale", "residual_guidance_scale", "segment_guidance", "ctrl_lambda",
          "ctrl_k_base", "ctrl_alpha", "sink_ratio", "choice_temperature")


def check_word_text(value: object) -> None:
    """SegmoError unless `value` is a `WordText` ("caption" or "segments")."""
    if value not in get_args(WordText):
        raise SegmoError(f"SegMo: word_text must be 'caption' or 'segments', got {value!r}")


@dataclass(frozen=True)
class SamplingOptions:
    """How a generation or an edit draws its tokens; checked when built.

    guidance_scale: classifier-free guidance scale of the base tokens (spec §8: 4 for
        HumanML3D, 2 for KIT; a bundle's own scales are `SegMo.sampling`);
    residual_guidance_scale: the same for the residual layers;
    residual_guided_layers: how many residual layers, from the first, are guided (None =
        all); the layers above run their conditional rows alone, half a pass each
        (`segmo.generation.generate.residual_decode`);
    steps: masked-decoding steps of the base tokens;
    temperature: of the draws, 0 = greedy; top_k_ratio: share of the codebook a draw
        keeps (MoMask: 0.1, 52 of 512 codes); sampler: "categorical" or "gumbel";
    guidance: "cfg" (u + s·(c − u)) or "sink_ctrl", MLA-Gen's sink-aware controlled
        guidance on the base tokens' logits (eq. 9–10): with E = c − u and E_prev the
        corrected difference of the position's previous prediction,
        S = E + (ctrl_lambda − 1)·E_prev, E ← E − k_eff·sign(S) with
        k_eff = ctrl_k_base·(1 + ctrl_alpha·sink_ratio), then u + s·E. ctrl_k_base = 0 is
        plain CFG. Starting values are the paper's (λ 6, k 2, α 0.18, for flow
        velocities); sink_ratio: the model's measured SinkRatio
        (`tools/attention_report.py`), 0 by default;
    unconditional: what the unconditional rows of the base tokens' guidance keep: "none"
        (no text) or "local" (the segments and words, without the sentence: MLA-Gen's
        unconditional branch, for mask transformers trained with `local_uncond_prob`); the
        residual layers' unconditional rows keep no text either way;
    word_text: what the word keys of a transformer with words (`text_tokens: words`) are
        read from: "caption" (the caption's tokens, in the order it mentions the actions) or
        "segments" (its text segments joined in execution order, `ordered_text`: "a man
        walks, then a man jumps" for "before jumping, a man walks", the order the segment
        keys carry). Models without words ignore it;
    segment_timing: for a mask transformer trained with segment timing, "predicted" gives
        it the spans its timing head predicts from the segments, "none" none (as the share
        of training samples without timing); durations given to the generation win over
        both. Models without timing ignore it;
    remasking: which tokens each decoding step masks again: "confidence" (MoMask: the
        ⌈γ(t)·m⌉ least confident of the motion's m) or "segments" (the ⌈γ(t)·m_j⌉ least
        confident of each segment's m_j, so that a short segment fixes its share of tokens
        at every step as a long one does), for a mask transformer given segment spans
        (`segment_timing`); generations without spans, and edits, remask by confidence;
    segment_guidance: per-segment guidance of the base tokens, w ≥ 0 (0 = off): besides
        u + s·(c − u), each segment j of a caption adds w·(c − c₋ⱼ), where c₋ⱼ is the
        conditional prediction with segment j hidden, so that every segment, a short one
        beside long ones included, pushes the motion towards what it says. One more pass
        per segment and step; for mask transformers trained with segment dropout
        (`segment_drop_prob`), with guidance "cfg";
    choice_temperature: MaskGIT's randomised choice of the tokens a decoding step masks
        again, τ ≥ 0 (0 = off, MoMask's choice by confidence alone): they are ranked by
        log-confidence plus τ·(1 − t)·Gumbel noise, t the step's time in [0, 1], so early
        steps do not fix only the tokens the model is surest of.

    Raises SegmoError naming the first option a generation cannot use (NaN guidance, a
    scale or weight beyond ±`MAX_SCALE`, 0 steps...).

        >>> SamplingOptions(steps=20, temperature=0.5)
    """

    guidance_scale: float = 4.0
    residual_guidance_scale: float = 5.0
    steps: int = 10
    residual_guided_layers: int | None = None
    temperature: float = 1.0
    top_k_ratio: float = 0.1
    sampler: Sampler = "categorical"
    guidance: Guidance = "cfg"
    ctrl_lambda: float = 6.0
    ctrl_k_base: float = 2.0
    ctrl_alpha: float = 0.18
    sink_ratio: float = 0.0
    unconditional: Unconditional = "none"
    word_text: WordText = "caption"
    segment_timing: SegmentTiming = "predicted"
    remasking: Remasking = "confidence"
    segment_guidance: float = 0.0
    choice_temperature: float = 0.0

    def __post_init__(self) -> None:
        for name in ("guidance_scale", "residual_guidance_scale", "temperature", "top_k_ratio",
                     "ctrl_lambda", "ctrl_k_base", "ctrl_alpha", "sink_ratio",
                     "segment_guidance", "choice_temperature"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real) \
                    or not math.isfinite(value):
                raise SegmoError(f"SegMo: {name} must be a finite number, got {value!r}")
        for name in SCALES:
            if abs(getattr(self, name)) > MAX_SCALE:
                raise SegmoError(f"SegMo: {name} must be in [-{MAX_SCALE:g}, {MAX_SCALE:g}] "
                                 f"(beyond, the guided logits overflow), got "
                                 f"{getattr(self, name)!r}")
        if self.temperature < 0:
            raise SegmoError(f"SegMo: temperature must be >= 0 (0 = greedy), got "
                             f"{self.temperature!r}")
        if not 0 < self.top_k_ratio <= 1:
            raise SegmoError(f"SegMo: top_k_ratio must be in (0, 1], got {self.top_k_ratio!r}")
        steps = self.steps
        if isinstance(steps, bool) or not isinstance(steps, numbers.Integral) \
                or not 1 <= steps <= MAX_STEPS:
            raise SegmoError(f"SegMo: steps must be a whole number in [1, {MAX_STEPS}], got "
                             f"{steps!r}")
        layers = self.residual_guided_layers
        if layers is not None and (isinstance(layers, bool) or not isinstance(layers, numbers.Integral)
                                   or layers < 0):
            raise SegmoError(f"SegMo: residual_guided_layers must be a whole number >= 0 or "
                             f"None (all), got {layers!r}")
        if self.guidance not in get_args(Guidance):
            raise SegmoError(f"SegMo: guidance must be 'cfg' or 'sink_ctrl', got "
                             f"{self.guidance!r}")
        if self.unconditional not in get_args(Unconditional):
            raise SegmoError(f"SegMo: unconditional must be 'none' or 'local', got "
                             f"{self.unconditional!r}")
        check_word_text(self.word_text)
        if self.segment_timing not in get_args(SegmentTiming):
            raise SegmoError(f"SegMo: segment_timing must be 'predicted' or 'none', got "
                             f"{self.segment_timing!r}")
        if self.remasking not in get_args(Remasking):
            raise SegmoError(f"SegMo: remasking must be 'confidence' or 'segments', got "
                             f"{self.remasking!r}")
        if self.segment_guidance < 0:
            raise SegmoError(f"SegMo: segment_guidance must be >= 0 (0 = off), got "
                             f"{self.segment_guidance!r}")
        if self.choice_temperature < 0:
            raise SegmoError(f"SegMo: choice_temperature must be >= 0 (0 = off), got "
                             f"{self.choice_temperature!r}")
        if self.segment_guidance and self.guidance != "cfg":
            raise SegmoError("SegMo: segment_guidance works with guidance 'cfg' only, got "
                             f"guidance {self.guidance!r}")
        if self.sampler not in get_args(Sampler):
            raise SegmoError(f"SegMo: sampler must be 'categorical' or 'gumbel', got "
                             f"{self.sampler!r}")


def top_k_count(vocabulary: int, ratio: float) -> int:
    """How many logits "keep ratio of the logits" keeps: ⌈ratio·v⌉ (MoMask: 52 of 512)."""
    if not 0 < ratio <= 1:
        raise ValueError(f"top_k_ratio must be in (0, 1], got {ratio}")
    return max(1, math.ceil(ratio * vocabulary))


def gumbel_noise(shape: torch.Size, generator: torch.Generator | None = None,
                 device: torch.device | None = None) -> torch.Tensor:
    """Standard Gumbel noise of `shape`, −log(−log u), one uniform draw u per element from
    `generator` (the Gumbel-max draw of `sample_tokens`, MaskGIT's choice noise)."""
    u = torch.rand(shape, generator=generator, dtype=torch.float32, device=device)
    return -torch.log((-torch.log(u.clamp(min=1e-20))).clamp(min=1e-20))


def sample_tokens(logits: torch.Tensor, top_k_ratio: float = 0.1, temperature: float = 1.0,
                  sampler: Sampler = "categorical",
                  generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Draw one token per row among its top-k logits and return it with its probability.

    logits (..., v) → (tokens (...) long, confidence (...) float32), where confidence is the
    probability of the drawn token under softmax(top-k logits), whatever the temperature T
    of the draw (as MoMask's `probs_without_temperature`): at a small T the drawn tokens'
    probabilities under softmax(top-k logits / T) are all 1, and ranking them for
    re-masking would fall to their positions; temperature 0 is greedy.
    Only the k candidates are normalised and sampled, which is what filtering the others to
    −inf would give, at a fraction of the cost. "categorical" inverts the CDF with one
    uniform per row; "gumbel" adds Gumbel noise to the k scaled logits and takes the argmax.
    """
    if temperature < 0:
        raise ValueError(f"sample_tokens: temperature must be ≥ 0, got {temperature}")
    if sampler not in ("categorical", "gumbel"):
        raise ValueError(f"sample_tokens: sampler must be 'categorical' or 'gumbel', got {sampler!r}")
    logits = logits.float()
    k = top_k_count(logits.shape[-1], top_k_ratio)
    if k < logits.shape[-1]:
        values, candidates = logits.topk(k, dim=-1, sorted=False)
        # topk's unsorted order is an implementation detail (threads, precision); put the
        # candidates in code order so that a seed maps to the same token everywhere.
        candidates, order = candidates.sort(dim=-1)
        values = values.gather(-1, order)
    else:
        values, candidates = logits, None
    # Less the row's largest first: a tiny temperature then takes the others to −inf and
    # keeps the best at 0, where values / 1e-40 overflowed to inf, NaN probabilities and
    # the worst token.
    shifted = values - values.amax(dim=-1, keepdim=True)
    scaled = shifted / temperature if temperature > 0 else shifted
    probs = torch.softmax(scaled, dim=-1)
    confidence = probs if temperature in (0, 1) else torch.softmax(shifted, dim=-1)
    if temperature == 0:
        choice = values.argmax(dim=-1, keepdim=True)
    elif sampler == "categorical":
        cdf = probs.cumsum(dim=-1)
        u = torch.rand((*cdf.shape[:-1], 1), generator=generator, dtype=cdf.dtype,
                       device=cdf.device)
        choice = torch.searchsorted(cdf, u * cdf[..., -1:], right=True).clamp(max=k - 1)
    else:
        choice = (scaled + gumbel_noise(scaled.shape, generator, scaled.device)).argmax(
            dim=-1, keepdim=True)
    tokens = choice if candidates is None else candidates.gather(-1, choice)
    return tokens[..., 0], confidence.gather(-1, choice)[..., 0]
