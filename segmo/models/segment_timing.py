"""Segment timing: which text segment each motion position belongs to, as a condition of
the mask transformer, and a head that predicts the segments' durations from the text.

The mask transformer is told the order of the segments but not how long each lasts; on
the built-in corpus the actions it loses are the short ones beside long ones (docs/quality.md,
"Segment timing"). With timing, every motion position also gets a learned embedding of
its segment's number (1..A, the slot order), so that a motion token knows which segment
it is in and reads that slot. Training takes the spans from the data's ground truth or
from the motion segmenter (`segmo.tasks.mask.MaskTask.segment_timing`) and leaves them
out of a share of the samples, so the model also generates without them. At generation
the spans come from the user or from `TimingHead`: a share of the motion per segment,
predicted from what the segment says, cut into whole tokens in execution order
(`shares_to_spans`).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class SegmentTiming(nn.Module):
    """The segment number of each motion position → a vector added to its token embedding;
    with `text`, also that segment's projected text vector through a linear map, so that a
    position reads what its own segment says without finding the slot by attention."""

    def __init__(self, dim: int, max_segments: int, text: bool = False) -> None:
        super().__init__()
        self.index = nn.Parameter(torch.randn(max_segments, dim) * 0.02)
        # Absent without `text`, so that such a model is exactly the one before it.
        self.text = nn.Linear(dim, dim) if text else None

    @staticmethod
    def token_segments(spans: torch.Tensor, known: torch.Tensor, n: int) -> torch.Tensor:
        """spans (b, a, 2) long token spans (start, end exclusive), known (b, a) bool →
        (b, n) long: the slot whose known span holds each position, −1 where none does."""
        position = torch.arange(n, device=spans.device)[None, None]  # (1, 1, n)
        inside = (position >= spans[..., :1]) & (position < spans[..., 1:]) & known[..., None]
        first = inside.float().argmax(dim=1)  # the first slot holding it (spans tile)
        return torch.where(inside.any(dim=1), first, -1)

    def forward(self, token_segments: torch.Tensor,
                segment_content: torch.Tensor | None = None) -> torch.Tensor:
        """token_segments (b, n) long, −1 = unknown → (b, n, dim), zero where unknown;
        segment_content (b, a, dim): the projected segment vectors (`Condition.content`
        without the sentence), read where the module has `text`."""
        slot = token_segments.clamp(min=0)
        added = self.index[slot]
        if self.text is not None:
            if segment_content is None:
                raise ValueError("SegmentTiming: a module with text needs segment_content")
            gathered = segment_content.gather(
                1, slot[..., None].expand(-1, -1, segment_content.shape[-1]))
            added = added + self.text(gathered)
        known = (token_segments >= 0)[..., None]
        return added * known.to(added.dtype)


class TimingHead(nn.Module):
    """Each segment's share of the motion, from its projected text vector: a score per
    segment, softmax over a caption's segments."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.score = nn.Sequential(nn.Linear(dim, dim), nn.GELU(), nn.Linear(dim, 1))

    def forward(self, segments: torch.Tensor, segment_mask: torch.Tensor) -> torch.Tensor:
        """segments (b, a, dim), segment_mask (b, a) bool → log shares (b, a), −inf at
        empty slots (NaN in a row without segments: every caption has one)."""
        scores = self.score(segments.float()).squeeze(-1)
        return scores.masked_fill(~segment_mask, float("-inf")).log_softmax(dim=-1)


def timing_loss(log_shares: torch.Tensor, spans: torch.Tensor, known: torch.Tensor
                ) -> torch.Tensor:
    """Cross-entropy of the predicted shares against the true ones.

    log_shares (b, a) from `TimingHead`, spans (b, a, 2) true token spans, known (b, a)
    bool: the rows' slots with a true span (a row counts when all its segments are known)
    → scalar; 0 (with a gradient) when no row counts."""
    durations = (spans[..., 1] - spans[..., 0]).clamp(min=0).float() * known
    total = durations.sum(-1, keepdim=True)
    rows = known.any(-1) & (total[:, 0] > 0)
    if not bool(rows.any()):  # keeps the head in the graph (DDP wants every gradient)
        return (log_shares.masked_fill(~known, 0.0) * 0.0).sum()
    target = durations[rows] / total[rows]
    return -(target * log_shares[rows].masked_fill(~known[rows], 0.0)).sum(-1).mean()


def shares_to_spans(shares: torch.Tensor, segment_mask: torch.Tensor,
                    lengths: torch.Tensor) -> torch.Tensor:
    """Shares of the motion → contiguous token spans in execution order.

    shares (b, a) ≥ 0 (normalised here over the valid slots), segment_mask (b, a) bool with
    the valid slots first, lengths (b,) tokens → spans (b, a, 2) long (start, end
    exclusive) that tile [0, length): each valid segment gets at least one token where the
    motion has as many tokens as segments; empty slots get (length, length).
    """
    b, a = segment_mask.shape
    mask = segment_mask.bool()
    shares = shares.float().clamp(min=0) * mask
    total = shares.sum(-1, keepdim=True)
    count = mask.sum(-1, keepdim=True)
    # A row whose shares are all 0 splits evenly.
    shares = torch.where(total > 0, shares / total.clamp(min=1e-12),
                         mask.float() / count.clamp(min=1))
    n = lengths.long().to(shares.device)[:, None]
    ends = torch.round(shares.cumsum(-1) * n).long()
    # At least one token each and room for the segments after it: with f_k = end_k − k,
    # end_k ≥ end_{k−1} + 1 is f non-decreasing, and end_k ≤ n − (count − 1 − k) is
    # f_k ≤ n − count + 1, a bound that keeps it so.
    slot = torch.arange(a, device=shares.device)[None]
    f = torch.cummax((ends - slot).clamp(min=1), dim=-1).values
    f = torch.minimum(f, n - count + 1)
    ends = torch.cummax((f + slot).clamp(0, None), dim=-1).values
    ends = torch.minimum(ends, n)
    ends = torch.where(mask, ends, n.expand(b, a))
    ends = torch.where(slot == count - 1, n.expand(b, a), ends)  # the last ends with the motion
    starts = torch.cat([ends.new_zeros(b, 1), ends[:, :-1]], dim=-1)
    starts = torch.where(mask, starts, n.expand(b, a))
    return torch.stack([starts, ends], dim=-1)


def durations_to_spans(durations: torch.Tensor, segment_mask: torch.Tensor,
                       lengths: torch.Tensor) -> torch.Tensor:
    """Durations in any unit (seconds, frames) per segment → token spans of motions
    `lengths` (b,) tokens long, the durations read as shares (`shares_to_spans`)."""
    if not bool(torch.isfinite(durations).all()) or bool((durations < 0).any()):
        raise ValueError("segment durations must be finite and ≥ 0")
    return shares_to_spans(durations, segment_mask, lengths)


def predicted_spans(head: TimingHead, segments: torch.Tensor, segment_mask: torch.Tensor,
                    lengths: torch.Tensor) -> torch.Tensor:
    """The head's spans: segments (b, a, dim) projected text vectors, segment_mask (b, a),
    lengths (b,) tokens → (b, a, 2) long."""
    log_shares = head(segments, segment_mask)
    return shares_to_spans(F.softmax(log_shares.masked_fill(~segment_mask, -1e9), -1),
                           segment_mask, lengths)
