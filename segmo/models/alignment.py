"""Segment alignment head (SegMo §3.4, spec §5). Pure torch.

Motion side: m_i = MLP(concat(mean(h[s_i:e_i]), max(h[s_i:e_i]))) over the mask
transformer's output features h and token spans from `segmo.segmentation`. Text side: an
MLP over the segment features (the mask transformer's projected text vectors, which carry
no slot order, so that ordered slots cannot meet the loss by position alone). Both land
in a shared `out_dim` space compared by cosine similarity.

The head is part of the model (a bundle's `mask/` holds it); the losses that train it, and
their settings (method, temperature, weight, motion segmenter), are the mask task's:
`segmo.tasks.alignment_loss`.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

# Fields that the `alignment` entry of a mask config.json written before the loss moved to
# the task holds: the loss's settings and a copy of the transformer's max_segments. Read
# and ignored, so that those model directories still load.
FORMER_FIELDS = ("method", "temperature", "weight", "segmenter", "max_segments")


@dataclass
class AlignmentConfig:
    """What the head is built from: `out_dim`, the width of the shared space (512 in SegMo)."""

    out_dim: int = 512

    def __post_init__(self) -> None:
        if self.out_dim < 1:
            raise ValueError(f"AlignmentConfig: out_dim={self.out_dim} must be ≥ 1")

    @classmethod
    def from_dict(cls, values: dict) -> AlignmentConfig:
        """From the `alignment` entry of a config.json (older files: `FORMER_FIELDS` ignored)."""
        return cls(**{k: v for k, v in values.items() if k not in FORMER_FIELDS})


def span_mask(spans: torch.Tensor, n: int) -> torch.Tensor:
    """`(b, a, 2)` token spans → `(b, a, n)` bool, True inside `[start, end)`."""
    index = torch.arange(n, device=spans.device)
    return (index >= spans[..., :1]) & (index < spans[..., 1:])


def _mlp(dim_in: int, dim: int, out_dim: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(dim_in, dim), nn.GELU(), nn.Linear(dim, out_dim))


class SegmentAggregator(nn.Module):
    """m_i = MLP(concat(mean, max)) of motion features over each span (paper eq. 6)."""

    def __init__(self, dim: int, out_dim: int):
        super().__init__()
        self.mlp = _mlp(2 * dim, dim, out_dim)

    def forward(self, h: torch.Tensor, spans: torch.Tensor) -> torch.Tensor:
        """h `(b, n, dim)`, spans `(b, a, 2)` long → `(b, a, out_dim)`.

        Empty spans (padding) pool to zeros; their outputs are meaningless and must be
        masked by the caller.
        """
        weights = span_mask(spans, h.shape[1]).to(h.dtype)  # (b, a, n)
        count = weights.sum(-1, keepdim=True).clamp(min=1.0)
        mean = torch.einsum("ban,bnd->bad", weights, h) / count
        return self.mlp(torch.cat([mean, span_max(h, spans)], dim=-1))


def span_max(h: torch.Tensor, spans: torch.Tensor) -> torch.Tensor:
    """Max of h `(b, n, dim)` over each span `(b, a, 2)` → `(b, a, dim)`; empty spans give 0.

    The rows of the non-empty spans are gathered one span after another and reduced by
    `torch.segment_reduce`, so the work is the spans' total length. Masking h per span
    instead, a `(b, a, n, dim)` block, took 3.6 times as long in a training step's forward
    and backward (a = 5 slots, most of them short or empty; 12.4 against 3.4 ms on one
    Zen 3 core) and twice as long for the 1,225 windows of every length that grounding
    scores on a 49-token motion. Same values and gradients.
    """
    b, n, dim = h.shape
    start = spans[..., 0].clamp(0, n)
    length = (spans[..., 1].clamp(0, n) - start).clamp(min=0)  # (b, a)
    present = length > 0
    peak = h.new_zeros(*length.shape, dim)
    if not bool(present.any()):
        return peak
    lengths = length[present]
    first = (start + n * torch.arange(b, device=h.device)[:, None])[present]
    # Row k of span s, the spans one after another: first[s] + k for k < lengths[s], at
    # place (lengths[:s].sum() + k) of the gathered rows.
    total = int(lengths.sum())
    shift = torch.repeat_interleave(first - (lengths.cumsum(0) - lengths), lengths,
                                    output_size=total)
    rows = h.reshape(b * n, dim)[shift + torch.arange(total, device=h.device)]
    return peak.masked_scatter(present[..., None], torch.segment_reduce(rows, "max", lengths=lengths))


class AlignmentHead(nn.Module):
    """Projects text segments and aggregates motion spans into the shared space.

    `dim` is the width of both inputs (the mask transformer's width, 384 in MoMask). A model
    trained without alignment has no head at all (its parameters would receive no gradient,
    which DDP rejects by default). Trained by `segmo.tasks.alignment_loss.AlignmentLoss`.
    """

    def __init__(self, dim: int, config: AlignmentConfig | None = None):
        super().__init__()
        self.config = config or AlignmentConfig()
        self.aggregator = SegmentAggregator(dim, self.config.out_dim)
        self.text_proj = _mlp(dim, dim, self.config.out_dim)

    def embed_text(self, segments: torch.Tensor) -> torch.Tensor:
        """`(b, a, dim)` → `(b, a, out_dim)` (not normalised)."""
        return self.text_proj(segments)

    def embed_motion(self, h: torch.Tensor, spans: torch.Tensor) -> torch.Tensor:
        """h `(b, n, dim)`, spans `(b, a, 2)` (segments or sliding windows) → `(b, a, out_dim)`."""
        return self.aggregator(h, spans)


def segment_similarity(text: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
    """Cosine matrix `(b, a, a')` between text `(b, a, d)` and motion `(b, a', d)` segments."""
    return torch.einsum("bid,bjd->bij", F.normalize(text, dim=-1), F.normalize(motion, dim=-1))


def paired_cosine(text: torch.Tensor, motion: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Cosines of the valid pairs: text, motion `(b, a, d)`, mask `(b, a)` → `(k,)`."""
    return F.cosine_similarity(text, motion, dim=-1)[mask]


def isc_from_cosines(cosines: torch.Tensor) -> tuple[float, float]:
    """ISC (paper Fig. 4) of `(k,)` paired cosines (`paired_cosine`, concatenated over
    batches) → (mean, coefficient of variation: population std / mean, inf for a zero
    mean); raises on an empty set."""
    if cosines.numel() == 0:
        raise ValueError("isc_from_cosines: no valid segment pair (mask all False)")
    mean = float(cosines.mean())
    std = float(cosines.std(unbiased=False))
    return mean, (std / mean if mean != 0 else float("inf"))
