"""Batching of `MotionDataset` / `MotionWindowDataset` / `ActionFrameDataset` samples."""

from __future__ import annotations

from typing import Any

import torch

# Per-sample values that are passed through as plain lists (strings, ragged structures).
LIST_KEYS = ("caption", "segments", "id", "caption_index", "spans")
IGNORE = -100  # a frame label that counts for nothing (`F.cross_entropy`'s ignore_index)


def _pad(seqs: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Right-pad (t_i, d) tensors with zeros to (b, t_max, d); mask (b, t_max) True = valid."""
    t_max = max(s.shape[0] for s in seqs)
    out = seqs[0].new_zeros(len(seqs), t_max, *seqs[0].shape[1:])
    mask = torch.zeros(len(seqs), t_max, dtype=torch.bool)
    for i, s in enumerate(seqs):
        out[i, : s.shape[0]] = s
        mask[i, : s.shape[0]] = True
    return out, mask


def _codes(values: list[Any]) -> torch.Tensor:
    """(b,) long: equal values get equal codes."""
    index: dict[Any, int] = {}
    return torch.tensor([index.setdefault(v, len(index)) for v in values], dtype=torch.long)


def related_samples(batch: dict[str, Any]) -> torch.Tensor:
    """(b, b) bool: True where two samples of a batch are the same motion (``id``) or have
    the same caption (case and surrounding spaces aside), the diagonal included. A
    contrastive loss never takes such a pair as a negative: a caption of one also describes
    the other's motion. A motion's captions are separate samples, so they share batches.
    Without ``id`` every sample counts as its own motion."""
    captions = [str(c).strip().lower() for c in batch["caption"]]
    ids = _codes([str(i) for i in batch["id"]] if batch.get("id") else list(range(len(captions))))
    caps = _codes(captions)
    return (ids[:, None] == ids[None]) | (caps[:, None] == caps[None])


def collate(samples: list[dict[str, Any]]) -> dict[str, Any]:
    """Pad a list of samples into a batch.

    Returns ``motion`` (b, t, d) zero-padded to the longest motion, ``mask`` (b, t) bool
    (True = valid frame), ``lengths`` (b,) long; lists for ``caption``, ``segments``, ``id``,
    ``caption_index``, ``spans`` (whichever the samples have); and when text features are
    present ``sentence`` (b, dim), ``segment_features`` (b, A, dim), ``segment_mask``
    (b, A) bool; per-word ``word_features`` (b, l, dim) zero-padded to the longest caption
    with ``word_mask`` (b, l) bool; frame ``labels`` (b, t) or (b, t, k) long padded with `IGNORE`;
    cached motion ``tokens`` (b, t // 4, q) long padded with 0.
    """
    if not samples:
        raise ValueError("collate: empty list of samples")
    keys = samples[0].keys()
    for s in samples[1:]:
        if s.keys() != keys:
            raise ValueError(f"collate: samples have different keys: {sorted(keys)} vs {sorted(s.keys())}")
    motion, mask = _pad([s["motion"] for s in samples])
    batch: dict[str, Any] = {
        "motion": motion,
        "mask": mask,
        "lengths": torch.tensor([s["length"] for s in samples], dtype=torch.long),
    }
    for key in LIST_KEYS:
        if key in keys:
            batch[key] = [s[key] for s in samples]
    for key in ("sentence", "segment_features", "segment_mask"):
        if key in keys:
            batch[key] = torch.stack([s[key] for s in samples])
    if "word_features" in keys:
        batch["word_features"], batch["word_mask"] = _pad([s["word_features"] for s in samples])
    if "tokens" in keys:  # padded tokens are 0, a code: the token mask leaves them out
        batch["tokens"] = _pad([s["tokens"] for s in samples])[0]
    if "labels" in keys:  # (t,) action labels or (t, k) attribute labels per sample
        batch["labels"] = torch.full((*mask.shape, *samples[0]["labels"].shape[1:]), IGNORE,
                                     dtype=torch.long)
        for i, s in enumerate(samples):
            batch["labels"][i, : len(s["labels"])] = s["labels"]
    return batch
