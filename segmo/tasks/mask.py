"""Training stage 2: the mask transformer with segment alignment (spec §4–§5, paper §3).

Each step takes the batch's base tokens (cached, or encoded by the frozen tokenizer:
`TransformerTask`), masks base tokens with
the cosine schedule, predicts them from the caption and its segments, and adds
λ · alignment loss between the text segments (their projected text vectors, which carry
no slot order: `segmo.models.transformer.TextPrefix`) and motion segments (spans from
`segmo.segmentation` aggregated over the outputs of the masked input). Validation
measures what the paper's claims rest on: held-out masked-token accuracy under a fixed
masking, and — where the data has ground-truth spans (the built-in corpus) — how often a
text segment's most similar motion segment is its own (`segment_top1`).
"""

from __future__ import annotations

import warnings
from typing import ClassVar, Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from segmo.data.collate import related_samples
from segmo.data.motion_tokens import tokenizer_digest
from segmo.errors import SegmoError
from segmo.models.alignment import AlignmentConfig
from segmo.models.hub import portable_path
from segmo.models.mask_transformer import (
    MaskTransformer,
    MaskTransformerConfig,
    mask_ratio_time,
    mask_tokens,
    masked_token_loss,
    masked_token_losses,
    weighted_mean,
)
from segmo.models.segment_timing import timing_loss
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.segmentation import SegmenterName, segment_batch
from segmo.tasks.alignment_loss import AlignmentLoss, AlignMethod
from segmo.tasks.common import (
    TransformerTask,
    check_shares,
    text_condition,
    token_lengths,
    token_mask,
    word_condition,
)

ALIGNMENT_TEMPERATURE = 0.1  # τ of the alignment loss (spec §5)


def former_temperature(temperature: float, alignment_temperature: float) -> float:
    """The alignment temperature of a config or checkpoint that names it `temperature`
    (its name until it was told apart from the sampling temperature)."""
    if alignment_temperature != ALIGNMENT_TEMPERATURE and alignment_temperature != temperature:
        raise SegmoError(f"model.init_args.temperature={temperature} and alignment_temperature="
                         f"{alignment_temperature}: temperature is the former name of "
                         "alignment_temperature; set only alignment_temperature")
    warnings.warn("model.init_args.temperature is the former name of alignment_temperature "
                  "(the alignment loss's τ); read as alignment_temperature="
                  f"{temperature}. Rename it in the config.", FutureWarning, stacklevel=3)
    return temperature


def gt_token_spans(spans: list, num_segments: Tensor, lengths: Tensor, slots: int,
                   min_segments: int = 2) -> tuple[Tensor, Tensor]:
    """Ground-truth frame spans → token spans (b, slots, 2) and a (b,) bool of usable samples.

    A sample is usable when it has ground truth with as many spans as text segments
    (≥ min_segments) and every span covers at least one token.
    """
    b = len(spans)
    out = torch.zeros(b, slots, 2, dtype=torch.long)
    usable = torch.zeros(b, dtype=torch.bool)
    for i, sample_spans in enumerate(spans):
        a = int(num_segments[i])
        if sample_spans is None or len(sample_spans) != a or a < min_segments or a > slots:
            continue
        n = int(lengths[i]) // FRAMES_PER_TOKEN
        tokens = [(round(s / FRAMES_PER_TOKEN), round(e / FRAMES_PER_TOKEN)) for s, e in sample_spans]
        tokens = [(min(s, n), min(e, n)) for s, e in tokens]
        if all(e > s for s, e in tokens):
            out[i, :a] = torch.tensor(tokens)
            usable[i] = True
    return out, usable


def segment_balanced_weights(spans: Tensor, known: Tensor, valid: Tensor) -> Tensor:
    """Token weights (b, n) under which every segment of a sample counts alike in the loss.

    spans (b, a, 2) token spans [start, end), known (b, a) bool, valid (b, n) bool. A token
    inside known span j weighs (mean length of the sample's known spans) / (length of span
    j): each known segment holds the same total weight and the sample the same total as
    unweighted. Tokens outside every known span, and samples with fewer than two known
    spans, weigh 1; padded tokens 0.
    """
    positions = torch.arange(valid.shape[1], device=valid.device)
    length = (spans[..., 1] - spans[..., 0]).clamp(min=0)
    known = known & (length > 0)
    inside = known[..., None] & (positions >= spans[..., :1]) & (positions < spans[..., 1:])
    count = known.sum(1)
    mean = (length * known).sum(1) / count.clamp(min=1)
    per_segment = torch.where(known, mean[:, None] / length.clamp(min=1), 0.0)
    weights = torch.einsum("ba,ban->bn", per_segment, inside.float())
    balanced = inside.any(1) & (count >= 2)[:, None]
    return torch.where(balanced, weights, 1.0) * valid


def mask_whole_segment(inputs: Tensor, target: Tensor, valid: Tensor, spans: Tensor,
                       known: Tensor, chosen: Tensor, mask_id: int,
                       generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
    """Mask every token of one known segment, drawn at random, of each `chosen` sample.

    inputs, target (b, n) from `mask_tokens`, valid (b, n) bool the real tokens; spans
    (b, a, 2) token spans, known (b, a) bool, chosen (b,) bool; a chosen sample without a
    known span of at least one token is left as it is. Returns the new (inputs, target):
    the segment's tokens become `mask_id` and are predicted, besides the positions
    `mask_tokens` chose.
    """
    known = known & (spans[..., 1] > spans[..., 0]) & chosen[:, None]
    draw = torch.rand(known.shape, generator=generator, device=known.device)
    pick = draw.masked_fill(~known, -1.0).argmax(1)  # (b,) a known slot where there is one
    span = spans.gather(1, pick[:, None, None].expand(-1, 1, 2))[:, 0]  # (b, 2)
    positions = torch.arange(inputs.shape[1], device=inputs.device)
    inside = ((positions >= span[:, :1]) & (positions < span[:, 1:])
              & known.any(1)[:, None] & valid)
    return torch.where(inside, mask_id, inputs), target | inside


def reversed_order(segment_mask: Tensor) -> Tensor:
    """(b, a) bool → (b, a) long permutation reversing each sample's valid segments.

    Valid segments are a prefix of the slots; padded slots stay where they are. The
    permutation is its own inverse.
    """
    a = segment_mask.shape[1]
    count = segment_mask.sum(1, keepdim=True)
    slots = torch.arange(a, device=segment_mask.device).expand_as(segment_mask)
    return torch.where(slots < count, count - 1 - slots, slots)


def segment_top1(text: Tensor, motion: Tensor, mask: Tensor) -> tuple[int, int]:
    """Text segments whose most similar motion segment (same sample) is their own.

    text, motion (b, a, d); mask (b, a) bool → (correct, total).
    """
    sim = torch.einsum("bid,bjd->bij", F.normalize(text, dim=-1), F.normalize(motion, dim=-1))
    sim = sim.masked_fill(~mask[:, None, :], float("-inf"))
    pick = sim.argmax(dim=-1)  # (b, a)
    own = torch.arange(text.shape[1], device=text.device).expand_as(pick)
    return int(((pick == own) & mask).sum()), int(mask.sum())


class MaskTask(TransformerTask):
    """Trains `MaskTransformer` (+ its alignment head) on batches with cached text features."""

    stage: ClassVar[str] = "mask"
    monitor: ClassVar[str] = "val/mask_loss"

    def __init__(
        self,
        tokenizer: str,
        cond_drop_prob: float = 0.1,
        order_drop_prob: float = 0.0,
        alignment: Literal[AlignMethod, "none"] = "in_sample",
        alignment_weight: float = 1.0,
        alignment_temperature: float = ALIGNMENT_TEMPERATURE,
        segmenter: SegmenterName = "uniform",
        alignment_spans: Literal["segmenter", "truth"] = "segmenter",
        alignment_dim: int = 512,
        temperature: float | None = None,
        sink_mask_t: float | None = None,
        segment_timing: Literal["none", "truth", "segmenter"] = "none",
        timing_drop_prob: float = 0.3,
        timing_weight: float = 0.1,
        position_text: bool = False,
        loss_weighting: Literal["token", "segment"] = "token",
        segment_mask_prob: float = 0.0,
        segment_drop_prob: float = 0.0,
        **kwargs,
    ) -> None:
        """`alignment*`, `segmenter`: the alignment loss (`AlignmentLoss`; "none" trains
        plain MoMask, without a head); `alignment_dim` the head's width. `alignment_spans`:
        the motion spans the loss aggregates, from `segmenter` (SegMo) or, where a sample has
        them, the data's ground-truth spans ("truth": an oracle segmenter on the built-in
        corpus, which tells how much the loss is held back by its segmenter's spans; samples
        without usable ground truth keep `segmenter`'s). `temperature` is the
        former name of `alignment_temperature` (configs and checkpoints written before hold
        it): it is read as that, with a warning. `sink_mask_t`: MLA-Gen's sink mask
        (`MaskTransformerConfig.sink_mask_t`), applied to the samples whose mask ratio's t
        exceeds it. `segment_timing`: each segment slot also carries its span in motion tokens
        (`segmo.models.segment_timing`), from the data's ground-truth spans ("truth"; samples
        without them train without timing) or from `segmenter` ("segmenter", for data
        without ground truth); left out of a share `timing_drop_prob` of the samples, so the
        model also generates without them; the timing head learns each segment's share of
        the motion at `timing_weight`. `position_text`: with timing, each motion position
        also gets its own segment's text vector (`SegmentTiming` with text), so that it need
        not find its segment's slot by attention. `loss_weighting`: "token" weighs every
        masked token alike (MoMask); "segment" weighs each segment of a sample alike
        (`segment_balanced_weights`), so a short action counts as much as a long one, with
        the data's ground-truth spans where a sample has them and `segmenter`'s elsewhere.
        `segment_mask_prob`: the share of samples in which every token of one of their
        segments (drawn at random; spans as for `loss_weighting`) is masked besides the
        random masking (`mask_whole_segment`), so the model learns to fill a segment from
        its text between visible neighbours. `segment_drop_prob`: each segment slot of a
        sample is hidden from attention with this probability (segment dropout; validation
        hides none), so the model also predicts with a segment missing, which per-segment
        guidance compares against (`SamplingOptions.segment_guidance`). The other arguments
        (`**kwargs`) are `TransformerTask`'s."""
        super().__init__(tokenizer=tokenizer, cond_drop_prob=cond_drop_prob, **kwargs)
        if temperature is not None:  # checkpoints of this run hold the new name only
            alignment_temperature = former_temperature(temperature, alignment_temperature)
            self.hparams.update(alignment_temperature=alignment_temperature, temperature=None)
        # cond_drop_prob and local_uncond_prob: TransformerTask.
        check_shares(order_drop_prob=order_drop_prob, timing_drop_prob=timing_drop_prob,
                     segment_mask_prob=segment_mask_prob, segment_drop_prob=segment_drop_prob)
        for name, weight in (("alignment_weight", alignment_weight), ("timing_weight", timing_weight)):
            if not weight >= 0.0:
                raise SegmoError(f"model.init_args.{name}={weight}: a weight >= 0")
        if not alignment_temperature > 0.0:
            raise SegmoError(f"model.init_args.alignment_temperature={alignment_temperature}: "
                             "a temperature > 0")
        if alignment_dim < 1:
            raise SegmoError(f"model.init_args.alignment_dim={alignment_dim}: a width >= 1")
        align, self.alignment_loss = None, None
        if alignment != "none":
            self.alignment_loss = AlignmentLoss(alignment, alignment_temperature,
                                                alignment_weight, segmenter)
            align = AlignmentConfig(out_dim=alignment_dim)
        if segment_timing not in ("none", "truth", "segmenter"):
            raise SegmoError(f"model.init_args.segment_timing={segment_timing!r}: one of "
                             "none, truth, segmenter")
        if alignment_spans not in ("segmenter", "truth"):
            raise SegmoError(f"model.init_args.alignment_spans={alignment_spans!r}: one of "
                             "segmenter, truth")
        if loss_weighting not in ("token", "segment"):
            raise SegmoError(f"model.init_args.loss_weighting={loss_weighting!r}: one of "
                             "token, segment")
        if position_text and segment_timing == "none":
            raise SegmoError("model.init_args.position_text=true needs segment_timing truth "
                             "or segmenter (it reads each position's segment)")
        self.model = MaskTransformer(MaskTransformerConfig(**self.transformer_config(),
                                                           alignment=align,
                                                           sink_mask_t=sink_mask_t,
                                                           segment_timing=segment_timing != "none",
                                                           position_text=position_text))

    # -- one step ----------------------------------------------------------------------------

    @torch.no_grad()
    def tokens(self, batch: dict) -> tuple[Tensor, Tensor, Tensor]:
        """Base tokens (b, n), token mask (b, n), token lengths (b,) of a batch."""
        indices = self.batch_tokens(batch)
        lengths = token_lengths(batch["lengths"])
        return indices[..., 0], token_mask(batch["lengths"], indices.shape[1]), lengths

    def spans(self, batch: dict, num_segments: Tensor, lengths: Tensor) -> Tensor:
        """Motion-segment token spans (b, A, 2) from the configured segmenter."""
        method = self.hparams.segmenter
        features = None
        if method != "uniform":
            with torch.no_grad():  # the tokenizer's latents describe the motion itself
                features = self.tokenizer.encoder(batch["motion"].transpose(1, 2)).transpose(1, 2)
        return segment_batch(features, num_segments, lengths, method,
                             max_segments=self.hparams.max_segments)

    def timing(self, batch: dict, segment_mask: Tensor, lengths: Tensor,
               motion_spans: Tensor | None = None) -> tuple[Tensor, Tensor] | None:
        """The segments' token spans (b, a, 2) and which are known (b, a) bool, from the
        ground truth or the segmenter (`segment_timing`; `motion_spans`: the segmenter's
        spans where the caller has them already); None for a model without timing."""
        source = self.hparams.segment_timing
        if source == "none":
            return None
        if source == "segmenter":
            if motion_spans is None:
                num_segments = torch.minimum(segment_mask.sum(1), lengths)
                motion_spans = self.spans(batch, num_segments, lengths).to(lengths.device)
            return motion_spans, segment_mask & (motion_spans[..., 1] > motion_spans[..., 0])
        spans, usable = gt_token_spans(batch.get("spans") or [None] * len(lengths),
                                       segment_mask.sum(1), batch["lengths"],
                                       segment_mask.shape[1], min_segments=1)
        return spans.to(lengths.device), segment_mask & usable.to(lengths.device)[:, None]

    def segment_spans(self, batch: dict, segment_mask: Tensor, num_segments: Tensor,
                      motion_spans: Tensor) -> tuple[Tensor, Tensor]:
        """The token spans (b, a, 2) that `loss_weighting: segment` balances and
        `segment_mask_prob` masks, and which are known (b, a) bool: the ground truth where a
        sample has it, else the segmenter's."""
        truth, usable = gt_token_spans(batch.get("spans") or [None] * len(num_segments),
                                       segment_mask.sum(1), batch["lengths"],
                                       segment_mask.shape[1])
        usable = usable.to(motion_spans.device)
        spans = torch.where(usable[:, None, None], truth.to(motion_spans.device), motion_spans)
        slots = torch.arange(segment_mask.shape[1], device=segment_mask.device)
        return spans, segment_mask & (slots < num_segments[:, None])

    def step(self, batch: dict, generator: torch.Generator | None = None,
             drop: Tensor | None = None, unordered: Tensor | None = None,
             timing_drop: Tensor | None = None,
             segment_masked: Tensor | None = None,
             hidden: Tensor | None = None) -> dict[str, Tensor]:
        """Losses of one batch; `drop` (condition dropped), `unordered` (segments without
        order), `timing_drop` (segment timing left out) and `segment_masked` (one whole
        segment masked) are drawn with their probabilities unless given, (b,) bool; so is
        `hidden` (b, a) bool, the segment slots dropped (`segment_drop_prob`)."""
        base, valid, lengths = self.tokens(batch)
        sentence, segments, segment_mask = text_condition(batch)
        inputs, target = mask_tokens(base, valid, self.model.config.codebook_size, generator)
        b = base.shape[0]
        if drop is None:
            drop = torch.rand(b, device=base.device) < self.hparams.cond_drop_prob
        if unordered is None:
            unordered = torch.rand(b, device=base.device) < self.hparams.order_drop_prob
        if hidden is None and self.hparams.segment_drop_prob > 0:
            hidden = segment_mask & (torch.rand(segment_mask.shape, device=base.device)
                                     < self.hparams.segment_drop_prob)
        # The motion segmenter's spans, cut once for the alignment loss, segmenter timing and
        # the segment options (where a sample lacks ground truth).
        num_segments = torch.minimum(segment_mask.sum(1), lengths)
        motion_spans = None
        segment_options = (self.hparams.loss_weighting == "segment"
                           or self.hparams.segment_mask_prob > 0)
        truth_aligned = (self.alignment_loss is not None
                         and self.hparams.alignment_spans == "truth")
        if (self.alignment_loss is not None or self.hparams.segment_timing == "segmenter"
                or segment_options):
            motion_spans = self.spans(batch, num_segments, lengths).to(base.device)
        if segment_options or truth_aligned:
            known_spans = self.segment_spans(batch, segment_mask, num_segments, motion_spans)
        if self.hparams.segment_mask_prob > 0:
            if segment_masked is None:
                segment_masked = torch.rand(b, device=base.device) < self.hparams.segment_mask_prob
            inputs, target = mask_whole_segment(inputs, target, valid, *known_spans, segment_masked,
                                                self.model.config.codebook_size, generator)
        timing = self.timing(batch, segment_mask, lengths, motion_spans)
        spans, span_known = (None, None) if timing is None else timing
        if timing is not None:
            if timing_drop is None:
                timing_drop = torch.rand(b, device=base.device) < self.hparams.timing_drop_prob
            span_known = span_known & ~timing_drop[:, None]
        sink_rows = self.model.sink_mask_rows(mask_ratio_time(target, valid))
        out = self.model(inputs, valid, sentence, segments, segment_mask, drop, unordered,
                         **word_condition(batch, self.model), sink_rows=sink_rows,
                         keep_local=self.keep_local(drop), spans=spans, span_known=span_known,
                         hidden_segments=hidden)
        if self.hparams.loss_weighting == "segment":
            # mask_loss stays the plain mean, comparable across runs; training follows the
            # balanced one. One cross-entropy pass serves both.
            losses = masked_token_losses(out.logits, base, target)
            weights = segment_balanced_weights(*known_spans, valid)[target]
            mask_loss = losses.mean()
            balanced = weighted_mean(losses, weights)
        else:
            mask_loss = masked_token_loss(out.logits, base, target)
        correct = (out.logits.argmax(-1) == base) & target
        terms = {"mask_loss": mask_loss,
                 "accuracy": correct.sum() / target.sum().clamp(min=1)}
        loss = mask_loss
        if self.hparams.loss_weighting == "segment":
            terms["mask_loss_balanced"] = loss = balanced
        if timing is not None:
            # The head learns from the text vectors without moving them: detached.
            log_shares = self.model.timing_head(out.segment_features.detach(), segment_mask)
            terms["timing_loss"] = timing_loss(log_shares, *timing)
            loss = loss + self.hparams.timing_weight * terms["timing_loss"]
        if self.alignment_loss is not None:
            # Segments the motion cannot hold (a > tokens; tiny clips only) sit out.
            keep = segment_mask & (torch.arange(segment_mask.shape[1], device=base.device)
                                   < num_segments[:, None])
            aligned = self.alignment_loss(
                self.model.alignment, out.motion_features, lengths, out.segment_features,
                keep & ~drop[:, None], known_spans[0] if truth_aligned else motion_spans,
                out.sentence_features, related_samples(batch).to(base.device),
            )
            terms["align"] = aligned.losses["align"]
            loss = loss + self.alignment_loss.weight * terms["align"]
        terms["loss"] = loss
        return terms

    def training_step(self, batch: dict, batch_idx: int) -> Tensor:
        terms = self.step(batch)
        b = batch["motion"].shape[0]
        self.log("train/loss", terms["loss"], prog_bar=True, batch_size=b)
        self.log_dict({f"train/{k}": v for k, v in terms.items() if k != "loss"}, batch_size=b)
        return terms["loss"]

    # -- evaluation --------------------------------------------------------------------------

    def _evaluate(self, prefix: str, batch: dict, batch_idx: int) -> None:
        b = batch["motion"].shape[0]
        # The same masking every epoch, so the accuracy of two runs is comparable.
        generator = torch.Generator(device=batch["motion"].device).manual_seed(batch_idx)
        never = torch.zeros(b, dtype=torch.bool, device=batch["motion"].device)
        no_segment = torch.zeros_like(text_condition(batch)[2], dtype=torch.bool)
        terms = self.step(batch, generator, drop=never, unordered=never, timing_drop=never,
                          segment_masked=never, hidden=no_segment)
        self.log_dict({f"{prefix}/{k}": v for k, v in terms.items()}, batch_size=b,
                      sync_dist=True, prog_bar=False)
        if batch.get("spans") is not None:
            self._log_segment_top1(prefix, batch)
        if self.hparams.segment_timing != "none":
            self._log_timing_iou(prefix, batch)

    def _log_timing_iou(self, prefix: str, batch: dict) -> None:
        """Mean temporal IoU of the timing head's spans with the training spans (ground
        truth or segmenter), over the segments of the samples whose spans are known."""
        _, _, lengths = self.tokens(batch)
        _, segments, segment_mask = text_condition(batch)
        spans, known = self.timing(batch, segment_mask, lengths)
        known = known & (known.sum(1) == segment_mask.sum(1))[:, None]
        any_rank = self.trainer.strategy.reduce(known.any().float(), reduce_op="sum")
        if float(any_rank) == 0:  # every rank decides alike (see `_log_segment_top1`)
            return
        predicted = self.model.predict_spans(segments, segment_mask, lengths)
        inter = (torch.minimum(predicted[..., 1], spans[..., 1])
                 - torch.maximum(predicted[..., 0], spans[..., 0])).clamp(min=0)
        union = (predicted[..., 1] - predicted[..., 0]) + (spans[..., 1] - spans[..., 0]) - inter
        iou = torch.where(union > 0, inter / union.clamp(min=1), 0.0)
        total = int(known.sum())
        self.log(f"{prefix}/timing_iou", (iou * known).sum() / max(total, 1),
                 batch_size=total, sync_dist=True)

    def _log_segment_top1(self, prefix: str, batch: dict) -> None:
        base, valid, lengths = self.tokens(batch)
        sentence, segments, segment_mask = text_condition(batch)
        gt, usable = gt_token_spans(batch["spans"], segment_mask.sum(1), batch["lengths"],
                                    segment_mask.shape[1])
        gt, usable = gt.to(base.device), usable.to(base.device)
        mask = segment_mask & usable[:, None] & (gt[..., 1] > gt[..., 0])
        # Under DDP every rank must log the same keys (they are all-reduced at the end of the
        # epoch), so whether to score this batch is decided for all ranks at once; a rank
        # without ground truth here logs with weight 0.
        any_rank = self.trainer.strategy.reduce(mask.any().float(), reduce_op="sum")
        if float(any_rank) == 0:
            return
        words = word_condition(batch, self.model)
        out = self.model(base, valid, sentence, segments, segment_mask, **words)
        total = int(mask.sum())
        weight, total = total, max(total, 1)
        # Head-free score: mean motion feature over the span vs the segment's text vector.
        inside = (torch.arange(base.shape[1], device=base.device) >= gt[..., :1]) & (
            torch.arange(base.shape[1], device=base.device) < gt[..., 1:])
        pooled = torch.einsum("ban,bnd->bad", inside.float(), out.motion_features)
        correct_raw, _ = segment_top1(out.segment_features, pooled, mask)
        self.log(f"{prefix}/segment_top1_raw", correct_raw / total, batch_size=weight, sync_dist=True)
        if self.model.alignment is None:
            return
        head = self.model.alignment

        def top1(run, order: Tensor | None = None) -> float:
            """Own-head segment top-1 of a pass whose segments were fed in `order` (b, a)."""
            text = head.embed_text(run.segment_features)
            if order is not None:  # back to the original slots (the permutation is an involution)
                text = text.gather(1, order[..., None].expand(-1, -1, text.shape[-1]))
            return segment_top1(text, head.embed_motion(run.motion_features, gt), mask)[0] / total

        self.log(f"{prefix}/segment_top1", top1(out), batch_size=weight, sync_dist=True,
                 prog_bar=True)
        # The motion features see the segments in their slot order, so they can simply copy
        # slot i into the i-th span. Fed in reverse order, a model whose motion features
        # describe the motion itself still finds each segment's own span; one that copies
        # does not. Fed as a set (unordered, as grounding feeds them) only content is left.
        order = reversed_order(segment_mask)
        fed = segments.gather(1, order[..., None].expand_as(segments))
        reversed_run = self.model(base, valid, sentence, fed, segment_mask, **words)
        self.log(f"{prefix}/segment_top1_reversed", top1(reversed_run, order),
                 batch_size=weight, sync_dist=True)
        unordered = torch.ones(base.shape[0], dtype=torch.bool, device=base.device)
        unordered_run = self.model(base, valid, sentence, segments, segment_mask,
                                   unordered=unordered, **words)
        self.log(f"{prefix}/segment_top1_unordered", top1(unordered_run), batch_size=weight,
                 sync_dist=True)

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        self._evaluate("val", batch, batch_idx)

    def test_step(self, batch: dict, batch_idx: int) -> None:
        self._evaluate("test", batch, batch_idx)

    # -- export ------------------------------------------------------------------------------

    def export_model(self) -> MaskTransformer:
        self.model.meta = {
            "tokenizer": portable_path(self.hparams.tokenizer),
            "tokenizer_digest": tokenizer_digest(self.tokenizer),  # checked by `segmo bundle`
            "text_encoder": self.hparams.text_encoder,
            "alignment": self.hparams.alignment,
            "segmenter": self.hparams.segmenter,
            "cond_drop_prob": self.hparams.cond_drop_prob,
            "segment_timing": self.hparams.segment_timing,
            "segment_drop_prob": self.hparams.segment_drop_prob,
        }
        return self.model
