"""Masked decoding of base tokens and residual decoding (spec §8); temporal editing,
which refills a span with the same decoding, is `segmo.generation.editing`.

Every transformer pass runs the conditional and the unconditional branch of
classifier-free guidance as ONE batch of 2b rows (rows b..2b−1 have their text prefix
masked out), and the text prefix is projected and encoded once per call, not once per step.

    indices = generate_tokens(mask_model, residual_model, sentence, segments, segment_mask,
                              lengths=torch.tensor([196, 120]), generator=torch.Generator().manual_seed(0))
    features = decode_tokens(tokenizer, indices, lengths)     # (b, t, d) z-scored
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from segmo import cpu
from segmo.errors import SegmoError
from segmo.generation.sampling import SamplingOptions, cosine_schedule, gumbel_noise, sample_tokens
from segmo.models.attention_recorder import is_recorded
from segmo.models.mask_transformer import MaskTransformer
from segmo.models.residual_transformer import ResidualTransformer
from segmo.models.segment_timing import SegmentTiming, durations_to_spans
from segmo.models.text_prefix import Condition
from segmo.models.tokenizer import FRAMES_PER_TOKEN

Precision = Literal["auto", "fp32", "bf16"]


def token_mask_from_lengths(lengths: torch.Tensor, max_tokens: int) -> torch.Tensor:
    """lengths (b,) in frames → token_mask (b, n) bool with n = max(lengths) // 4.

    Raises ValueError unless every length is a multiple of 4 in [4, 4·max_tokens].
    """
    lengths = torch.as_tensor(lengths)
    limit = FRAMES_PER_TOKEN * max_tokens
    if lengths.dim() != 1 or lengths.numel() == 0:
        raise ValueError(f"lengths must be a non-empty (b,) tensor of frame counts, "
                         f"got shape {tuple(lengths.shape)}")
    bad = (lengths % FRAMES_PER_TOKEN != 0) | (lengths < FRAMES_PER_TOKEN) | (lengths > limit)
    if bool(bad.any()):
        raise ValueError(f"lengths must be multiples of {FRAMES_PER_TOKEN} frames in "
                         f"[{FRAMES_PER_TOKEN}, {limit}] (max_tokens={max_tokens}); "
                         f"got {lengths[bad].tolist()}")
    tokens = lengths.long() // FRAMES_PER_TOKEN
    return torch.arange(int(tokens.max()), device=lengths.device) < tokens[:, None]


def guidance_condition(model: MaskTransformer | ResidualTransformer, sentence: torch.Tensor,
                       segments: torch.Tensor, segment_mask: torch.Tensor,
                       words: torch.Tensor | None = None, word_mask: torch.Tensor | None = None,
                       unconditional: str = "none", spans: torch.Tensor | None = None
                       ) -> Condition:
    """The prefix of a 2b-row guidance batch: rows 0..b−1 conditional, b..2b−1 not (their
    words dropped with the rest; with unconditional "local" they drop the sentence only and
    keep segments and words, MLA-Gen's unconditional branch). words (b, l, text_dim),
    word_mask (b, l): the captions' word features, for a model with word keys; spans
    (b, a, 2): the segments' token spans, for a mask transformer with segment timing
    (`segment_spans`)."""
    b = sentence.shape[0]
    drop = torch.arange(2 * b, device=sentence.device) >= b
    two = (lambda x: None if x is None else torch.cat([x, x]))  # noqa: E731
    extra = {} if model.config.text_tokens == "none" else {
        "words": two(words), "word_mask": two(word_mask)}
    if unconditional == "local":
        extra["keep_local"] = drop
    if spans is not None:
        extra["spans"] = two(spans)
    return model.condition(torch.cat([sentence, sentence]), torch.cat([segments, segments]),
                           torch.cat([segment_mask, segment_mask]), drop, **extra)


@dataclass
class SegmentGuidance:
    """Per-segment guidance's rows (`SamplingOptions.segment_guidance`): one row for each
    segment of each caption, the caption's text with that segment hidden.

    condition: the r rows' prefix (`MaskTransformer.condition` with `hidden_segments`);
    rows: (r,) long, the batch row (caption) of each; weight: w of w·(c − c₋ⱼ).
    """

    condition: Condition
    rows: torch.Tensor
    weight: float


def segment_guidance_condition(model: MaskTransformer, sentence: torch.Tensor,
                               segments: torch.Tensor, segment_mask: torch.Tensor,
                               weight: float, words: torch.Tensor | None = None,
                               word_mask: torch.Tensor | None = None,
                               spans: torch.Tensor | None = None) -> SegmentGuidance | None:
    """The rows of per-segment guidance with weight `weight` for captions of (b, a)
    `segment_mask` (arguments as `guidance_condition`); None when the weight is 0 or no
    caption has a segment."""
    rows, slots = segment_mask.bool().nonzero(as_tuple=True)
    if not weight or rows.numel() == 0:
        return None
    hidden = F.one_hot(slots, segment_mask.shape[1]).bool()
    extra = {} if model.config.text_tokens == "none" else {
        "words": words[rows], "word_mask": word_mask[rows]}
    if spans is not None:
        extra["spans"] = spans[rows]
    condition = model.condition(sentence[rows], segments[rows], segment_mask[rows],
                                hidden_segments=hidden, **extra)
    return SegmentGuidance(condition, rows, float(weight))


def segment_guided(logits: torch.Tensor, without: torch.Tensor, guidance: SegmentGuidance,
                   scale: float) -> torch.Tensor:
    """Guidance batch logits (2b, m, v) and the logits (r, m, v) of `guidance`'s rows →
    u + s·(c − u) + w·Σⱼ (c − c₋ⱼ), (b, m, v) float32."""
    conditional = logits[: logits.shape[0] // 2].float()
    difference = conditional[guidance.rows] - without.float()
    return guided_logits(logits, scale).index_add_(0, guidance.rows, difference,
                                                   alpha=guidance.weight)


def segment_spans(model: MaskTransformer, segments: torch.Tensor, segment_mask: torch.Tensor,
                  token_mask: torch.Tensor, timing: str = "predicted",
                  durations: torch.Tensor | None = None) -> torch.Tensor | None:
    """The segments' token spans (b, a, 2) a mask transformer with segment timing is
    given: from `durations` (b, a) (any unit, read as shares of each motion) where given,
    else from the model's timing head (`timing` "predicted"); None for a model without
    timing or with `timing` "none" (the model generates as trained without spans). A row
    of `durations` that is all 0 is a sample without durations: the head's spans."""
    if not model.config.segment_timing:
        return None
    lengths = token_mask.sum(1)
    if durations is not None:
        durations = torch.as_tensor(durations, dtype=torch.float32, device=segments.device)
        if durations.shape != segment_mask.shape:
            raise ValueError(f"durations must be (b, a) = {tuple(segment_mask.shape)}, one per "
                             f"segment slot, got {tuple(durations.shape)}")
        given = (durations * segment_mask).sum(1) > 0
        if bool(given.all()):
            return durations_to_spans(durations, segment_mask.bool(), lengths)
        spans = model.predict_spans(segments, segment_mask, lengths)
        if bool(given.any()):
            spans[given] = durations_to_spans(durations[given], segment_mask[given].bool(),
                                              lengths[given])
        return spans
    if timing == "none":
        return None
    return model.predict_spans(segments, segment_mask, lengths)


def guided_logits(logits: torch.Tensor, scale: float) -> torch.Tensor:
    """logits (2b, n, v) of a guidance batch → u + s·(c − u), (b, n, v) float32."""
    conditional, unconditional = logits.float().chunk(2)
    return unconditional + scale * (conditional - unconditional)


def resolve_precision(precision: Precision, device: torch.device | str = "cpu"
                      ) -> tuple[Literal["fp32", "bf16"], str]:
    """What `precision` runs as on `device`, and why: ("fp32" | "bf16", reason).

    "auto" is bf16 only on a CPU with native bf16 (`segmo.cpu.auto_precision`), fp32 on
    other CPUs and on other devices; "fp32" and "bf16" are taken as asked.
    """
    if precision not in ("auto", "fp32", "bf16"):
        raise SegmoError(f"precision must be 'auto', 'fp32' or 'bf16', got {precision!r}")
    device = torch.device(device)
    if precision == "bf16" and device.type == "cpu" and not cpu.onednn_bf16():
        return "bf16", ("asked for; this CPU has no oneDNN bf16 path, so it runs in torch's "
                        "reference kernels, several times slower than fp32")
    if precision != "auto":
        return precision, "asked for"
    if device.type != "cpu":
        return "fp32", f"auto chooses bf16 on CPUs with native bf16 only, not on {device.type}"
    return cpu.auto_precision()  # type: ignore[return-value]


def _autocast(precision: Precision, device: torch.device | str) -> torch.autocast:
    """bf16 autocast where `precision` resolves to "bf16", a disabled one for "fp32"."""
    device = torch.device(device)
    precision, _ = resolve_precision(precision, device)
    if precision == "bf16" and device.type == "cpu" and not cpu.onednn_bf16():
        # Asked for explicitly: run it (the same bf16 arithmetic as on a native CPU, in
        # torch's reference kernels), and say once per process what it costs here.
        warnings.warn("bf16 on this CPU runs in torch's reference kernels, several times "
                      "slower than fp32 (no oneDNN bf16: needs AVX512BW/VL/DQ or "
                      "AVX-NE-CONVERT); precision 'auto' or 'fp32' is faster here",
                      UserWarning, stacklevel=1)
    return torch.autocast(device.type, dtype=torch.bfloat16, enabled=precision == "bf16")


@contextmanager
def inference(models: list[nn.Module], precision: Precision = "fp32",
              device: torch.device | str = "cpu") -> Iterator[None]:
    """Eval mode (restored afterwards), inference mode and, for bf16, autocast: how every
    pass of the pipeline runs, so that a model left in train mode (fine-tuned in a
    notebook) gives the same numbers as in eval mode, without dropout."""
    autocast = _autocast(precision, device)
    modes = [(model, model.training) for model in models]
    for model, _ in modes:
        model.eval()
    try:
        with torch.inference_mode(), autocast:
            yield
    finally:
        for model, mode in modes:
            model.train(mode)


def _sampled_positions(select: torch.Tensor) -> tuple[torch.Tensor | None, torch.Tensor]:
    """select (b, n) bool, the positions a pass samples → (positions (b, m) long, picked
    (b, m) bool): per row, in ascending order, m = the largest row count of positions,
    holding that row's selected ones (picked) and, for rows with fewer, filler positions
    whose outputs go unused. (None, select) when m = n: the pass computes every position.
    A pass computes its last block, head and classifier only at these positions."""
    n = select.shape[1]
    m = int(select.sum(dim=1).max())
    if m == n:
        return None, select
    # A stable sort puts each row's selected positions first, in ascending order.
    first = (~select).to(torch.uint8).argsort(dim=1, stable=True)[:, :m]
    positions = first.sort(dim=1).values
    return positions, select.gather(1, positions)


def _draw(logits: torch.Tensor, select: torch.Tensor, scale: float, options: SamplingOptions,
          generator: torch.Generator | None, without: torch.Tensor | None = None,
          segment_guidance: SegmentGuidance | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Guidance batch logits (2b, m, v), select (b, m) bool → tokens (k,), confidence (k,)
    for the k selected positions (row-major order), guided with `scale`; with `without`,
    the logits of `segment_guidance`'s rows, also per segment (`segment_guided`)."""
    guided = (guided_logits(logits, scale) if without is None
              else segment_guided(logits, without, segment_guidance, scale))[select]
    return sample_tokens(guided, options.top_k_ratio, options.temperature, options.sampler,
                         generator)


class SinkControl:
    """MLA-Gen's sink-ctrl guidance over the steps of one masked decoding
    (`SamplingOptions.guidance`): keeps each position's last corrected guidance difference
    E_prev (b, n, v), carried to the step that predicts it again."""

    def __init__(self, options: SamplingOptions, shape: torch.Size, vocabulary: int,
                 device: torch.device) -> None:
        self.options = options
        self.k = options.ctrl_k_base * (1.0 + options.ctrl_alpha * options.sink_ratio)
        self.previous = torch.zeros(*shape, vocabulary, dtype=torch.float32, device=device)

    def guided(self, logits: torch.Tensor, positions: torch.Tensor | None,
               picked: torch.Tensor) -> torch.Tensor:
        """Guidance batch logits (2b, m, v) at `positions` (b, m) (None = all n), picked
        (b, m) → the guided logits (k, v) of the picked positions, row-major."""
        conditional, unconditional = logits.float().chunk(2)
        difference = conditional - unconditional
        b, m, v = difference.shape
        where = (torch.arange(m, device=logits.device).expand(b, m) if positions is None
                 else positions)
        index = where[..., None].expand(b, m, v)
        previous = self.previous.gather(1, index)
        signal = difference + (self.options.ctrl_lambda - 1.0) * previous
        difference = difference - self.k * torch.sign(signal)
        self.previous.scatter_(1, index, torch.where(picked[..., None], difference, previous))
        return (unconditional + self.options.guidance_scale * difference)[picked]


def masked_count(t: float, counts: torch.Tensor) -> torch.Tensor:
    """How many of `counts` (b,) editable tokens the decoding step at t ∈ [0, 1] masks and
    predicts: ⌈γ(t)·m⌉, at least 1 where m > 0, and 0 where m = 0 → (b,) long."""
    num = torch.ceil(cosine_schedule(t) * counts).long().clamp(min=1)
    return torch.where(counts > 0, num, 0)


def remasked(scores: torch.Tensor, editable: torch.Tensor, t: float,
             groups: torch.Tensor | None = None) -> torch.Tensor:
    """The tokens the decoding step at t masks again → (b, n) bool.

    scores (b, n): confidence, +inf where a token is final or not editable; editable (b, n)
    bool. Without groups, the ⌈γ(t)·m⌉ least confident of each row's m editable tokens
    (`masked_count`, MoMask); groups (b, n) long, each position's group (`token_groups`):
    the ⌈γ(t)·m_j⌉ least confident of each group's m_j (`SamplingOptions.remasking`
    "segments"). A group's count falls with t, so its masked tokens are always among the
    ones predicted at the step before."""
    if groups is None:
        ranks = scores.argsort(dim=1).argsort(dim=1)
        return ranks < masked_count(t, editable.sum(dim=1))[:, None]
    is_masked = torch.zeros_like(editable)
    for group in range(int(groups.max()) + 1):
        inside = editable & (groups == group)
        ranks = scores.masked_fill(~inside, math.inf).argsort(dim=1).argsort(dim=1)
        is_masked |= (ranks < masked_count(t, inside.sum(dim=1))[:, None]) & inside
    return is_masked


def noisy_confidence(scores: torch.Tensor, temperature: float,
                     generator: torch.Generator | None = None) -> torch.Tensor:
    """MaskGIT's randomised choice: scores (b, n) confidences in [0, 1], +inf where final →
    log-confidence + temperature·Gumbel noise, +inf kept (`SamplingOptions.choice_temperature`;
    the caller anneals the temperature). One uniform draw per position from `generator`."""
    gumbel = gumbel_noise(scores.shape, generator, scores.device)
    noisy = torch.log(scores.clamp(min=1e-30)) + temperature * gumbel
    return torch.where(torch.isinf(scores), scores, noisy)


def token_groups(spans: torch.Tensor, n: int) -> torch.Tensor:
    """spans (b, a, 2) token spans of the segments (`segment_spans`) → (b, n) long: each
    position's segment slot, a (one group past the slots) where no span holds it."""
    known = spans[..., 1] > spans[..., 0]
    slots = SegmentTiming.token_segments(spans, known, n)
    return torch.where(slots >= 0, slots, spans.shape[1])


def _guidance_pass(model: MaskTransformer, ids: torch.Tensor, token_mask: torch.Tensor,
                   condition: Condition, positions: torch.Tensor | None,
                   sink_rows: torch.Tensor | None = None) -> torch.Tensor:
    """The logits (2b, m, v) of one mask pass over a guidance batch (rows b..2b−1
    unconditional), computing unconditional rows with identical inputs once: they attend
    to no text, so rows of the same ids, token mask and sampled positions have the same
    output. (At the first step of a generation every token is masked, and every
    unconditional row of one length is the same.)"""
    b = ids.shape[0] // 2
    if bool(condition.mask[b:].any()):  # unconditional rows with text in them: not alike
        return model.forward_condition(ids, token_mask, condition, positions, sink_rows).logits
    key = [ids[b:], token_mask[b:].long()] + ([] if positions is None else [positions[b:]])
    unique, inverse = torch.unique(torch.cat(key, dim=1), dim=0, return_inverse=True)
    if unique.shape[0] == b:
        return model.forward_condition(ids, token_mask, condition, positions, sink_rows).logits
    rows = torch.arange(b, device=ids.device)
    first = torch.full((unique.shape[0],), b, device=ids.device).scatter_reduce(
        0, inverse, rows, "amin")  # the first unconditional row of each distinct input
    keep = torch.cat([rows, b + first])
    logits = model.forward_condition(ids[keep], token_mask[keep], condition.rows(keep),
                                     None if positions is None else positions[keep],
                                     None if sink_rows is None else sink_rows[keep]).logits
    return logits[torch.cat([rows, b + inverse])]


def masked_decode(model: MaskTransformer, ids: torch.Tensor, editable: torch.Tensor,
                  token_mask: torch.Tensor, condition: Condition, options: SamplingOptions,
                  generator: torch.Generator | None = None,
                  spans: torch.Tensor | None = None,
                  segment_guidance: SegmentGuidance | None = None) -> torch.Tensor:
    """Iteratively fill the `editable` base tokens; the others stay fixed and visible.

    ids (b, n) long, editable (b, n) bool ⊆ token_mask (b, n) bool, condition from
    `guidance_condition` → ids (b, n). At step t ∈ linspace(0, 1, options.steps), the
    ⌈γ(t)·m⌉ (≥ 1) lowest-confidence editable tokens are (re-)masked and predicted with
    `options.guidance_scale`, m = editable count. A token kept at one step is final (MoMask):
    its confidence becomes +inf. With `options.remasking` "segments" and the segments'
    token spans (b, a, 2), the count is taken per segment (`remasked`). With
    `options.choice_temperature` τ > 0 the step ranks the tokens by log-confidence plus
    τ·(1 − t)·Gumbel noise (`noisy_confidence`, MaskGIT) instead of confidence. With
    `segment_guidance` (`segment_guidance_condition`) every step also runs its rows and
    guides per segment (`segment_guided`).

    A step whose masked input equals the previous step's reuses that pass' logits and
    draws anew (exact: the model is a function of its input). With the cosine schedule
    this is the second step whenever m < 66 (⌈γ(1/9)·m⌉ = m, everything masked again): one
    pass of ten saved. Not while an attention recording is open, which wants every pass.
    """
    if not bool(editable.any()):
        return ids
    groups = (token_groups(spans, ids.shape[1])
              if options.remasking == "segments" and spans is not None else None)
    scores = torch.zeros(ids.shape, dtype=torch.float32, device=ids.device).masked_fill(
        ~editable, math.inf)
    mask2 = torch.cat([token_mask, token_mask])
    control = SinkControl(options, ids.shape, model.config.codebook_size, ids.device) \
        if options.guidance == "sink_ctrl" else None
    reuse = not is_recorded(model)
    previous: tuple | None = None  # (ids, sink, logits, logits of the segment rows)
    for t in torch.linspace(0, 1, options.steps, dtype=torch.float32).tolist():
        ranked = scores
        if options.choice_temperature and 0 < t < 1:  # t = 0 masks all, t = 1 no noise
            ranked = noisy_confidence(scores, options.choice_temperature * (1 - t), generator)
        is_masked = remasked(ranked, editable, t, groups)
        ids = ids.masked_fill(is_masked, model.mask_id)
        positions, picked = _sampled_positions(is_masked)
        sink = model.config.sink_mask_t is not None and t > model.config.sink_mask_t
        if previous is not None and previous[1] == sink and torch.equal(previous[0], ids):
            logits, without = previous[2:]  # the same input: the same pass
        else:
            twice = None if positions is None else torch.cat([positions, positions])
            sink_rows = mask2.new_ones(mask2.shape[0]) if sink else None
            logits = _guidance_pass(model, torch.cat([ids, ids]), mask2, condition, twice,
                                    sink_rows)
            without = None
            if segment_guidance is not None:
                rows = segment_guidance.rows
                without = model.forward_condition(
                    ids[rows], token_mask[rows], segment_guidance.condition,
                    None if positions is None else positions[rows],
                    rows.new_ones(rows.shape, dtype=torch.bool) if sink else None).logits
            previous = (ids.clone(), sink, logits, without) if reuse else None
        if control is None:
            tokens, confidence = _draw(logits, picked, options.guidance_scale, options, generator,
                                       without, segment_guidance)
        else:
            guided = control.guided(logits, positions, picked)
            tokens, confidence = sample_tokens(guided, options.top_k_ratio, options.temperature,
                                               options.sampler, generator)
        ids[is_masked] = tokens  # is_masked and picked list the same positions in one order
        scores = torch.full_like(scores, math.inf)
        scores[is_masked] = confidence
    return ids


def residual_decode(model: ResidualTransformer, indices: torch.Tensor, regenerate: torch.Tensor,
                    token_mask: torch.Tensor, condition: Condition, options: SamplingOptions,
                    generator: torch.Generator | None = None,
                    layers: Sequence[int] | None = None) -> torch.Tensor:
    """Fill layers 1..q−1 one pass each, only where `regenerate` (b, n) is True, guided with
    `options.residual_guidance_scale` on the first `options.residual_guided_layers` layers
    (all by default); the others are drawn from the conditional rows alone, a pass over b
    rows instead of 2b. `layers`: the residual layers to draw (None = all); the others keep
    `indices`' codes, which the layers drawn above them read as they are.

    indices (b, n, q) long (layer 0 set; other layers kept where not regenerated) →
    (b, n, q), padded positions −1. The summed input embedding grows by one layer per pass.
    """
    b, _, q = indices.shape
    drawn = set(range(1, q) if layers is None else layers)
    if not drawn <= set(range(1, q)):
        raise ValueError(f"residual_decode: layers must be in 1..{q - 1}, got {sorted(drawn)}")
    indices = indices.clone()
    indices[..., 1:] = indices[..., 1:].masked_fill(~token_mask[..., None], -1)
    regenerate = regenerate & token_mask
    if not bool(regenerate.any()):
        return indices
    guided = q - 1 if options.residual_guided_layers is None else options.residual_guided_layers
    mask2 = torch.cat([token_mask, token_mask])
    conditional = condition.rows(torch.arange(b, device=indices.device))
    x = model.embed_layer(indices[..., 0], 0)
    positions, picked = _sampled_positions(regenerate)
    twice = None if positions is None else torch.cat([positions, positions])
    for layer in range(1, q):
        if layer in drawn:
            if layer <= guided:
                logits = model.forward_embedded(torch.cat([x, x]), layer, mask2, condition,
                                                twice).logits
                tokens, _ = _draw(logits, picked, options.residual_guidance_scale, options,
                                  generator)
            else:
                logits = model.forward_embedded(x, layer, token_mask, conditional,
                                                positions).logits
                tokens, _ = sample_tokens(logits.float()[picked], options.top_k_ratio,
                                          options.temperature, options.sampler, generator)
            codes = indices[..., layer].masked_fill(~token_mask, -1)
            codes[regenerate] = tokens
            indices[..., layer] = codes
        if layer < q - 1:
            x = x + model.embed_layer(indices[..., layer], layer)
    return indices


def check_models(mask_model: MaskTransformer, residual_model: ResidualTransformer | None) -> None:
    """ValueError unless the two transformers share codebook, text width and segments, and
    the residual's words (if it reads any) are the mask transformer's. The words go to both
    and a residual without word keys ignores them, so a words mask transformer may pair with
    a residual one without; the other way round the residual would get no words."""
    if residual_model is None:
        return
    fields = ["codebook_size", "text_dim", "max_segments"]
    if residual_model.config.text_tokens == "words":
        fields += ["text_tokens", "max_words"]
    for field in fields:
        a, b = getattr(mask_model.config, field), getattr(residual_model.config, field)
        if a != b:
            raise ValueError(f"mask and residual transformers disagree on {field}: {a} vs {b}")


def fill_tokens(mask_model: MaskTransformer, residual_model: ResidualTransformer | None,
                indices: torch.Tensor, editable: torch.Tensor, token_mask: torch.Tensor,
                sentence: torch.Tensor, segments: torch.Tensor, segment_mask: torch.Tensor,
                options: SamplingOptions, generator: torch.Generator | None,
                precision: Precision, words: torch.Tensor | None = None,
                word_mask: torch.Tensor | None = None,
                spans: torch.Tensor | None = None) -> torch.Tensor:
    """Draw the `editable` tokens of `indices` under a text condition; keep the others.

    indices (b, n, q) long; editable ⊆ token_mask (b, n) bool. Base tokens at the editable
    positions are masked and refilled by masked decoding with every other position
    visible, then residual layers 1..q−1 are drawn there (q = 1: base tokens only).
    spans (b, a, 2): the segments' token spans, for a mask transformer with segment timing
    (`segment_spans`; None: without, as edits run). → (b, n, q), −1 where token_mask is
    False. Generation is the case editable = token_mask.
    """
    models = [mask_model] + ([residual_model] if residual_model is not None else [])
    with inference(models, precision, sentence.device):
        condition = guidance_condition(mask_model, sentence, segments, segment_mask, words, word_mask,
                                       options.unconditional, spans)
        per_segment = segment_guidance_condition(
            mask_model, sentence, segments, segment_mask, options.segment_guidance, words,
            word_mask, spans)
        ids = indices[..., 0].masked_fill(editable, mask_model.mask_id)
        base = masked_decode(mask_model, ids, editable, token_mask, condition, options, generator,
                             spans, per_segment)
        out = indices.clone()
        out[..., 0] = torch.where(token_mask, base, -1)
        if residual_model is None:
            return out
        # The residual transformer's unconditional rows drop all text: `unconditional` is an
        # option of the base tokens' guidance, whose model is the one trained for it.
        condition = guidance_condition(residual_model, sentence, segments, segment_mask, words,
                                       word_mask)
        return residual_decode(residual_model, out, editable, token_mask, condition, options,
                               generator)


def generate_tokens(
    mask_model: MaskTransformer,
    residual_model: ResidualTransformer | None,
    sentence: torch.Tensor,
    segments: torch.Tensor,
    segment_mask: torch.Tensor,
    lengths: torch.Tensor,
    *,
    options: SamplingOptions | None = None,
    generator: torch.Generator | None = None,
    precision: Precision = "auto",
    words: torch.Tensor | None = None,
    word_mask: torch.Tensor | None = None,
    durations: torch.Tensor | None = None,
) -> torch.Tensor:
    """Text → motion tokens, drawn as `options` say (default `SamplingOptions()`).

    sentence (b, text_dim), segments (b, a, text_dim), segment_mask (b, a) bool, words
    (b, l, text_dim) and word_mask (b, l) bool (for models with word keys; ignored by others),
    lengths (b,) frames (multiples of 4 in [4, 4·max_tokens]) → indices (b, n, q) long with
    n = max(lengths) // 4, q = residual_model.config.num_quantizers (1 without a residual
    model); positions beyond a sample's length hold −1. durations (b, a): how long each
    segment lasts, for a mask transformer with segment timing (any unit, read as shares of
    the motion; without them such a model predicts them, `segment_spans`). Models run in
    eval mode (their mode is restored afterwards); precision "bf16" runs the passes under
    bf16 autocast, "auto" does so on CPUs with native bf16 only (`resolve_precision`).
    """
    check_models(mask_model, residual_model)
    lengths = torch.as_tensor(lengths, device=sentence.device)
    token_mask = token_mask_from_lengths(lengths, mask_model.config.max_tokens)
    q = residual_model.config.num_quantizers if residual_model is not None else 1
    empty = torch.full((*token_mask.shape, q), -1, device=sentence.device)
    options = options or SamplingOptions()
    with inference([mask_model], "fp32", sentence.device):
        spans = segment_spans(mask_model, segments, segment_mask, token_mask,
                              options.segment_timing, durations)
    return fill_tokens(mask_model, residual_model, empty, token_mask, token_mask, sentence,
                       segments, segment_mask, options, generator, precision, words, word_mask,
                       spans)


def decode_tokens(tokenizer, indices: torch.Tensor, lengths: torch.Tensor,
                  precision: Precision = "auto") -> torch.Tensor:
    """Tokens → motion features with a tokenizer (design.md, `RVQVAE.decode`).

    indices (b, n, q') with q' ≤ tokenizer.num_quantizers (missing layers decode as zero
    codes, index −1); lengths (b,) frames (multiples of 4) → features (b, t, d) float32,
    frames ≥ length set to 0. Each sample is decoded from its own tokens only, so the same
    tokens give the same motion whatever the other samples' lengths (`RVQVAE.decode` with
    lengths). precision "bf16" runs the decoder under bf16 autocast (half the time on a CPU
    with native bf16), "auto" does so where the CPU has it (`resolve_precision`).
    """
    b, n, q = indices.shape
    missing = tokenizer.num_quantizers - q
    if missing < 0:
        raise ValueError(f"decode_tokens: indices have {q} layers, the tokenizer has "
                         f"{tokenizer.num_quantizers}")
    if missing:
        indices = torch.cat([indices, indices.new_full((b, n, missing), -1)], dim=2)
    with torch.inference_mode(), _autocast(precision, indices.device):
        features = tokenizer.decode(indices, lengths.to(indices.device)).float()
    frames = torch.arange(features.shape[1], device=features.device)
    return features * (frames < lengths.to(features.device)[:, None])[..., None]
