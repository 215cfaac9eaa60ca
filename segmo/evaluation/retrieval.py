"""Text ↔ motion retrieval metrics, TMR-style (spec §9).

Input: a score matrix between N texts and M motions, either similarities (higher = better)
or distances (`distance=True`, lower = better), and `text_to_motion` (N,), the motion of
each text (default: text i ↔ motion i, so N = M). A motion may have several texts.

- text→motion: the rank of a text is the number of motions scoring strictly better than
  its own motion (0 = retrieved first).
- motion→text: the rank of a motion is the number of *other* motions' texts scoring
  strictly better than the best of its own texts.
A tie is broken at random, as an argsort of the scores breaks it by position: of t items
scoring exactly as well as the correct one, each is taken to come before it with chance
1/2, so the rank is the number strictly better plus t/2, and the hit at k is its expected
value (`tie_hits`). (Ties counted in favour of the correct item gave a model that answers
every text with one motion R@1 = 1.) R@k = mean hit at k; MedR = median of rank + 1
(1 = perfect).

`retrieval_metrics` evaluates the full set; `batched_retrieval_metrics` the "small batches"
protocol: one random text per motion, shuffled into batches of 32 (last incomplete batch
dropped), metrics of each 32×32 block averaged over blocks.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from segmo.models.evaluator import tie_hits

KS: tuple[int, ...] = (1, 2, 3, 5, 10)


def _np(x: Any) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def _check(scores: np.ndarray, index: np.ndarray) -> None:
    if scores.ndim != 2:
        raise ValueError(f"retrieval: scores must be (texts, motions), got shape {scores.shape}")
    if index.shape != (scores.shape[0],):
        raise ValueError(f"retrieval: text_to_motion has shape {index.shape}, expected ({scores.shape[0]},)")
    if index.size and (index.min() < 0 or index.max() >= scores.shape[1]):
        raise ValueError(f"retrieval: text_to_motion indices must lie in [0, {scores.shape[1]})")
    missing = np.setdiff1d(np.arange(scores.shape[1]), index)
    if missing.size:
        raise ValueError(f"retrieval: motions {missing[:10].tolist()} have no text")


def _text_to_motion(scores: Any, text_to_motion: Any, distance: bool
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Per text: motions scoring strictly better than its own, and other motions tied."""
    s = _np(scores)
    s = -s if distance else s
    index = np.arange(s.shape[0]) if text_to_motion is None else np.asarray(text_to_motion, dtype=np.int64)
    _check(s, index)
    correct = s[np.arange(len(index)), index][:, None]
    return (s > correct).sum(1), (s == correct).sum(1) - 1


def _motion_to_text(scores: Any, text_to_motion: Any, distance: bool
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Per motion: other motions' texts scoring strictly better than its best own text,
    and those tied with it."""
    s = _np(scores)
    s = -s if distance else s
    index = np.arange(s.shape[0]) if text_to_motion is None else np.asarray(text_to_motion, dtype=np.int64)
    _check(s, index)
    st = s.T  # (M, N): motion j's score for every text
    own = index[None, :] == np.arange(s.shape[1])[:, None]  # (M, N)
    best_own = np.where(own, st, -np.inf).max(1)[:, None]
    return ((st > best_own) & ~own).sum(1), ((st == best_own) & ~own).sum(1)


def text_to_motion_ranks(scores: Any, text_to_motion: Any = None, distance: bool = False) -> np.ndarray:
    """(N,) 0-based rank of each text's motion among all motions (ties: half each)."""
    better, tied = _text_to_motion(scores, text_to_motion, distance)
    return better + tied / 2


def motion_to_text_ranks(scores: Any, text_to_motion: Any = None, distance: bool = False) -> np.ndarray:
    """(M,) 0-based rank of each motion's best own text among the other motions' texts
    (ties: half each)."""
    better, tied = _motion_to_text(scores, text_to_motion, distance)
    return better + tied / 2


def _summary(better: np.ndarray, tied: np.ndarray, prefix: str, ks: Sequence[int]
             ) -> dict[str, float]:
    hits = tie_hits(better, tied, ks).mean(0)
    out = {f"{prefix}/R@{k}": float(hit) for k, hit in zip(ks, hits)}
    out[f"{prefix}/MedR"] = float(np.median(better + tied / 2 + 1))
    return out


def retrieval_metrics(scores: Any, text_to_motion: Any = None, distance: bool = False,
                      ks: Sequence[int] = KS) -> dict[str, float]:
    """{"t2m/R@k", "t2m/MedR", "m2t/R@k", "m2t/MedR"} on the full (N, M) score matrix."""
    return {**_summary(*_text_to_motion(scores, text_to_motion, distance), "t2m", ks),
            **_summary(*_motion_to_text(scores, text_to_motion, distance), "m2t", ks)}


def batched_retrieval_metrics(scores: Any, text_to_motion: Any = None, distance: bool = False,
                              batch_size: int = 32, ks: Sequence[int] = KS,
                              generator: np.random.Generator | None = None, seed: int = 0
                              ) -> dict[str, float]:
    """Metrics of random 32×32 blocks (one random text per motion), averaged over blocks."""
    s = _np(scores)
    index = np.arange(s.shape[0]) if text_to_motion is None else np.asarray(text_to_motion, dtype=np.int64)
    _check(s, index)
    rng = generator if generator is not None else np.random.default_rng(seed)
    num_motions = s.shape[1]
    if num_motions < batch_size:
        raise ValueError(f"batched_retrieval_metrics: {num_motions} motions, fewer than batch_size={batch_size}")
    texts_of = [np.flatnonzero(index == j) for j in range(num_motions)]
    pick = np.array([t[rng.integers(len(t))] for t in texts_of])  # one text per motion
    order = rng.permutation(num_motions)
    blocks = []
    for start in range(0, (num_motions // batch_size) * batch_size, batch_size):
        motions = order[start:start + batch_size]
        blocks.append(retrieval_metrics(s[np.ix_(pick[motions], motions)], None, distance, ks))
    return {k: float(np.mean([b[k] for b in blocks])) for k in blocks[0]}
