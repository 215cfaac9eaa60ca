"""The segment-alignment loss of the mask task (SegMo §3.5, spec §5, paper Table 3).

`segmo.models.alignment.AlignmentHead` embeds text segments and motion spans in a shared
space; `AlignmentLoss` holds how the task trains it: the method, the temperature τ, the
weight λ with which the task adds it to the mask loss (1.0 HumanML3D, 0.1 KIT) and the
motion segmenter that gives the spans. Methods (`AlignMethod`), each unweighted:
- `in_sample` (SegMo): symmetric InfoNCE within each sample, a caption's segments are
  each other's negatives;
- `batch`: every valid segment of the batch against every other;
- `global`: sentence vs whole motion (aggregated over its valid tokens), CLIP-style;
  in both, samples of the same motion or caption (a motion's captions are separate
  samples that share batches) are not each other's negatives (`related`, the
  evaluator's rule: `segmo.data.collate.related_samples`); a row left without negatives
  contributes nothing;
- `token`: each motion token vs the text segments of its sample, positive = the segment
  whose span contains it (and each segment vs the tokens, positives = its span).
A task trained without alignment (`alignment: none`) builds no head and no loss.
Padded segments (mask False), padded motion tokens (beyond `lengths`) and, for `global`,
the sentences of samples left out are zeroed and excluded from logits and targets, so
whatever they hold (NaN included) changes neither the loss nor any gradient. Losses average over the contributing
rows (segments, sentences or tokens), not over B·A padded slots as eq. 8 is written.
With no contributing row a loss is a zero that stays attached to the graph.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, get_args

import torch
import torch.nn.functional as F

from segmo.models.alignment import AlignmentHead, span_mask
from segmo.segmentation import SegmenterName

AlignMethod = Literal["in_sample", "batch", "global", "token"]


@dataclass
class AlignmentOutput:
    """What `AlignmentLoss` returns.

    losses: named scalars; "align" is the loss of the configured method (unweighted),
        plus its parts ("align_t2m", "align_m2t") where the method has two directions.
    text: `(b, a, out_dim)` projected text segments (`(b, 1, out_dim)` for `global`).
    motion: `(b, a, out_dim)` aggregated motion segments (`(b, n, out_dim)` tokens for
        `token`, `(b, 1, out_dim)` for `global`).
    mask: `(b, a)` bool, the segment pairs that took part (text and span both present).
    """

    losses: dict[str, torch.Tensor]
    text: torch.Tensor | None = None
    motion: torch.Tensor | None = None
    mask: torch.Tensor | None = None
    extras: dict[str, torch.Tensor] = field(default_factory=dict)


def _info_nce(logits: torch.Tensor, valid: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """Mean cross-entropy of diagonal targets over rows.

    logits `(g, a, a)`; valid `(g, a, a)` bool pairs allowed as candidates; rows `(g, a)`
    bool rows that contribute. Returns a scalar; a graph-attached 0 if no row contributes.
    """
    if not rows.any():
        return torch.where(valid, logits, 0.0).sum() * 0.0  # padding may hold anything
    logits = logits.masked_fill(~valid, torch.finfo(logits.dtype).min)
    log_prob = logits.log_softmax(dim=-1).diagonal(dim1=-2, dim2=-1)  # (g, a)
    return -log_prob[rows].mean()


def _symmetric_info_nce(
    text: torch.Tensor, motion: torch.Tensor, valid: torch.Tensor, rows: torch.Tensor,
    temperature: float,
) -> dict[str, torch.Tensor]:
    """text, motion `(g, a, d)` paired slot by slot; valid `(g, a, a)` bool symmetric
    candidate pairs; rows `(g, a)` bool rows that contribute. Returns {"align",
    "align_t2m", "align_m2t"}."""
    sim = torch.einsum("bid,bjd->bij", F.normalize(text, dim=-1), F.normalize(motion, dim=-1))
    logits = sim / temperature
    t2m = _info_nce(logits, valid, rows)
    m2t = _info_nce(logits.transpose(1, 2), valid, rows)
    return {"align": 0.5 * (t2m + m2t), "align_t2m": t2m, "align_m2t": m2t}


def in_sample_loss(
    text: torch.Tensor, motion: torch.Tensor, mask: torch.Tensor, temperature: float = 0.1
) -> dict[str, torch.Tensor]:
    """Symmetric InfoNCE within each sample (paper eq. 8).

    text, motion `(b, a, d)` paired slot by slot; mask `(b, a)` bool. Samples with fewer
    than two valid segments contribute nothing. Returns {"align", "align_t2m", "align_m2t"}.
    """
    valid = mask[:, :, None] & mask[:, None, :]
    rows = mask & (mask.sum(-1, keepdim=True) >= 2)
    return _symmetric_info_nce(text, motion, valid, rows, temperature)


def batch_loss(
    text: torch.Tensor, motion: torch.Tensor, mask: torch.Tensor, temperature: float = 0.1,
    related: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """Symmetric InfoNCE over all valid segments of the batch together (Table 3 ablation).

    text, motion `(b, a, d)`, mask `(b, a)`; related `(b, b)` bool samples whose segments
    are not each other's negatives (same motion or caption; None: none but the diagonal).
    A sample's own segments always are. Segments left without a negative contribute nothing.
    """
    sample = torch.arange(mask.shape[0], device=mask.device)[:, None].expand_as(mask)[mask]  # (m,)
    same_sample = sample[:, None] == sample[None, :]
    valid = torch.ones_like(same_sample) if related is None else same_sample | ~related[sample][:, sample]
    rows = valid.sum(-1) >= 2
    return _symmetric_info_nce(text[mask][None], motion[mask][None], valid[None], rows[None],
                               temperature)


def global_loss(
    sentence: torch.Tensor,
    motion: torch.Tensor,
    keep: torch.Tensor | None = None,
    temperature: float = 0.1,
    related: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """CLIP-style symmetric InfoNCE between whole captions and whole motions.

    sentence, motion `(b, d)`; keep `(b,)` bool samples that take part (default all);
    related `(b, b)` bool pairs that are not negatives (same motion or caption; None: only
    the diagonal). A sample left without a negative contributes nothing.
    """
    b = sentence.shape[0]
    keep = torch.ones(b, dtype=torch.bool, device=sentence.device) if keep is None else keep
    valid = keep[:, None] & keep[None, :]
    if related is not None:
        valid = valid & (~related | torch.eye(b, dtype=torch.bool, device=valid.device))
    rows = keep & (valid.sum(-1) >= 2)
    return _symmetric_info_nce(sentence[None], motion[None], valid[None], rows[None], temperature)


def token_loss(
    text: torch.Tensor,
    tokens: torch.Tensor,
    spans: torch.Tensor,
    mask: torch.Tensor,
    temperature: float = 0.1,
) -> dict[str, torch.Tensor]:
    """Token-level contrast within each sample (Table 3 ablation).

    text `(b, a, d)` segments, tokens `(b, n, d)` per-token motion embeddings, spans
    `(b, a, 2)`, mask `(b, a)` valid segments. m2t: each token inside a valid span
    classifies its segment among the sample's valid segments; t2m: each segment against
    the sample's covered tokens, its own span's tokens all positive. Samples with fewer
    than two valid segments contribute nothing.
    """
    inside = span_mask(spans, tokens.shape[1]) & mask[..., None]  # (b, a, n)
    sample_ok = mask.sum(-1) >= 2  # (b,)
    covered = inside.any(1) & sample_ok[:, None]  # (b, n) tokens that take part
    sim = torch.einsum("bad,bnd->ban", F.normalize(text, dim=-1), F.normalize(tokens, dim=-1))
    logits = sim / temperature
    low = torch.finfo(logits.dtype).min
    if not covered.any():
        zero = torch.where(inside, logits, 0.0).sum() * 0.0
        return {"align": zero, "align_t2m": zero, "align_m2t": zero}
    # m2t: softmax over segments for each token.
    m2t_logits = logits.masked_fill(~mask[..., None], low).log_softmax(dim=1)
    m2t = -torch.where(inside, m2t_logits, 0.0).sum(1)[covered].mean()
    # t2m: multi-positive InfoNCE over the sample's covered tokens for each segment.
    over_tokens = logits.masked_fill(~covered[:, None, :], low)
    positives = over_tokens.masked_fill(~inside, low).logsumexp(-1)
    rows = mask & sample_ok[:, None]
    t2m = -(positives - over_tokens.logsumexp(-1))[rows].mean()
    return {"align": 0.5 * (t2m + m2t), "align_t2m": t2m, "align_m2t": m2t}


def whole_motion_spans(lengths: torch.Tensor) -> torch.Tensor:
    """`(b,)` token lengths → `(b, 1, 2)` spans covering each whole motion."""
    return torch.stack([torch.zeros_like(lengths), lengths], dim=-1)[:, None]


def token_spans(n: int, batch: int, device: torch.device | None = None) -> torch.Tensor:
    """`(batch, n, 2)` one-token spans, so the aggregator embeds each token on its own."""
    start = torch.arange(n, device=device)
    return torch.stack([start, start + 1], -1).expand(batch, n, 2)


@dataclass
class AlignmentLoss:
    """The alignment loss of `method` at temperature τ; `weight` λ and the motion
    `segmenter` are read by the task (it adds `weight * losses["align"]` to the mask loss
    and cuts the motion into spans with the segmenter)."""

    method: AlignMethod = "in_sample"
    temperature: float = 0.1
    weight: float = 1.0
    segmenter: SegmenterName = "uniform"

    def __post_init__(self) -> None:
        if self.method not in get_args(AlignMethod):
            raise ValueError(f"AlignmentLoss.method={self.method!r}: one of {get_args(AlignMethod)}")
        if self.segmenter not in get_args(SegmenterName):
            raise ValueError(f"AlignmentLoss.segmenter={self.segmenter!r}: one of "
                             f"{get_args(SegmenterName)}")
        if self.temperature <= 0:
            raise ValueError(f"AlignmentLoss.temperature={self.temperature} must be > 0")

    def __call__(
        self,
        head: AlignmentHead,
        h: torch.Tensor,
        lengths: torch.Tensor,
        segments: torch.Tensor,
        segment_mask: torch.Tensor,
        spans: torch.Tensor,
        sentence: torch.Tensor | None = None,
        related: torch.Tensor | None = None,
    ) -> AlignmentOutput:
        """Alignment loss of `method` through `head`.

        Args:
            head: the mask transformer's `AlignmentHead`.
            h: `(b, n, dim)` motion features (mask transformer outputs on motion tokens).
            lengths: `(b,)` valid token counts.
            segments: `(b, a, dim)` text segment features; segment_mask `(b, a)` bool.
                To leave a sample out (e.g. its condition was dropped for CFG), set
                its row of segment_mask to False.
            spans: `(b, a, 2)` motion token spans (`segmo.segmentation.segment_batch`),
                slot i paired with text segment i; `(0, 0)` = absent.
            sentence: `(b, dim)` whole-caption features, needed by `global`.
            related: `(b, b)` bool samples that are the same motion or caption
                (`segmo.data.collate.related_samples`), never each other's negatives in
                `batch` and `global`; None = every sample its own motion. `in_sample` and
                `token` contrast within a sample and do not read it.
        """
        if spans.shape[:2] != segments.shape[:2] or segment_mask.shape != segments.shape[:2]:
            raise ValueError(
                f"AlignmentLoss: spans {tuple(spans.shape)}, segments {tuple(segments.shape)} "
                f"and segment_mask {tuple(segment_mask.shape)} must agree on (b, a)"
            )
        mask = segment_mask & (spans[..., 1] > spans[..., 0])
        # Padding is zeroed before the head: masking the logits alone leaves a NaN there in
        # the matrix products of the backward pass (0 · NaN), and so in every gradient.
        h = h.masked_fill((torch.arange(h.shape[1], device=h.device) >= lengths[:, None])[..., None], 0.0)
        segments = segments.masked_fill(~mask[..., None], 0.0)
        if self.method == "global":
            if sentence is None:
                raise ValueError("AlignmentLoss: method 'global' needs sentence (b, dim)")
            keep = segment_mask.any(-1) & (lengths > 0)
            text = head.embed_text(sentence.masked_fill(~keep[:, None], 0.0)[:, None])
            motion = head.embed_motion(h, whole_motion_spans(lengths))
            losses = global_loss(text[:, 0], motion[:, 0], keep, self.temperature, related)
            return AlignmentOutput(losses, text, motion, keep[:, None])
        text = head.embed_text(segments)
        if self.method == "token":
            tokens = head.embed_motion(h, token_spans(h.shape[1], h.shape[0], h.device))
            losses = token_loss(text, tokens, spans, mask, self.temperature)
            return AlignmentOutput(losses, text, tokens, mask)
        motion = head.embed_motion(h, spans)
        if self.method == "in_sample":
            losses = in_sample_loss(text, motion, mask, self.temperature)
        else:
            losses = batch_loss(text, motion, mask, self.temperature, related)
        return AlignmentOutput(losses, text, motion, mask)
