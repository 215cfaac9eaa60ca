"""What the mask transformer's motion tokens attend to over a given motion: the recording
behind attention grounding (`SegMo.ground(..., method="attention")`) and the attention
diagnostics (`segmo.evaluation.attention`).

    maps = motion_attention(model, ["a person walks, then jumps"], [["walks", "jumps"]], [features])
    profile = segment_profile(maps[-1], 0)   # (A, n): each segment's weight at each token
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from segmo.generation.generate import inference
from segmo.models.attention_recorder import AttentionMap


def motion_attention(model: Any, texts: Sequence[str], segments: Sequence[Sequence[str]],
                     motions: Sequence[Any]) -> list[AttentionMap]:
    """The mask transformer's attention over given motions (raw features (t, d) each, e.g.
    real ones whose segment spans are known): one conditional pass with every base token of
    the motion visible, recorded (`SegMo.record_attention`). Row i of each map is motion i."""
    sentence, vectors, segment_mask, _ = model.text_condition(list(texts), [list(s) for s in segments])
    tokens = [model.encode_motion(motion)[0, :, 0] for motion in motions]  # in eval mode
    n = max(len(t) for t in tokens)
    indices = torch.zeros(len(tokens), n, dtype=torch.long, device=model.device)
    token_mask = torch.zeros(len(tokens), n, dtype=torch.bool, device=model.device)
    for i, t in enumerate(tokens):
        indices[i, :len(t)], token_mask[i, :len(t)] = t, True
    words, word_mask = model.word_condition(list(texts), [list(s) for s in segments])
    with inference([model.mask], "fp32", model.device), model.record_attention() as recording:
        condition = model.mask.condition(sentence, vectors, segment_mask, words=words,
                                         word_mask=word_mask)
        model.mask.forward_condition(indices, token_mask, condition)
    return recording.of("mask")


def segment_profile(m: AttentionMap, row: int) -> np.ndarray:
    """(A, n) the head-mean weight of each segment key at each motion position of the map's
    row `row` (an index into `m.rows`); NaN at positions it did not query."""
    return key_profile(m, row, "segment ")


def key_profile(m: AttentionMap, row: int, kind: str) -> np.ndarray:
    """(K, n) the head-mean weight of each key whose label starts with `kind` ("segment ",
    "word ") at each motion position of row `row`, keys in prefix order; NaN at positions
    it did not query."""
    keys = [i for i, label in enumerate(m.key_labels) if label.startswith(kind)]
    n = m.key_valid.shape[1] - m.prefix_length
    weights = m.weights[row].mean(0)[:, keys]  # (q, K)
    out = np.full((len(keys), n), np.nan, dtype=np.float32)
    out[:, m.queries[row].numpy()] = weights.T.numpy()
    return out
