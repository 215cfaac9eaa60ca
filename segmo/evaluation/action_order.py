"""Action-order accuracy on the built-in corpus: does a motion perform the right actions in
the right order?

A small frame-wise action classifier (`segmo.models.action_classifier.ActionClassifier`),
trained by `segmo.tasks.action_classifier` on the ground-truth spans of the corpus
(`ROOT/segments/<id>.json`; classes = action names; arm overlays ("with") are ignored, the
label is the main action), reads each motion's action sequence without ground truth.

`sequence_accuracy` (exact match) and `normalised_edit_distance` (Levenshtein distance /
the longer length; a missing or extra action costs 1, two swapped actions 2) compare
predicted and true sequences. Consecutive repeats of an action in a true sequence are
merged, since no frame labelling can separate them.

Example::

    clf = train_action_classifier("data/synth", epochs=15)  # segmo.tasks.action_classifier
    evaluate_action_order(clf, "data/synth", split="test")
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from segmo.data.layout import read_actions, read_motion, read_split, split_file
from segmo.errors import SegmoError
from segmo.models.action_classifier import ActionClassifier, collapse

__all__ = ["collapse", "edit_distance", "evaluate_action_order", "normalised_edit_distance",
           "sequence_accuracy"]


def edit_distance(a: Sequence[Any], b: Sequence[Any]) -> int:
    """Levenshtein distance (insertions, deletions, substitutions cost 1)."""
    prev = list(range(len(b) + 1))
    for i, x in enumerate(a, 1):
        cur = [i]
        for j, y in enumerate(b, 1):
            cur.append(min(prev[j] + 1, cur[j - 1] + 1, prev[j - 1] + (x != y)))
        prev = cur
    return prev[-1]


def _pairs(pred_seqs: Sequence[Sequence[str]], true_seqs: Sequence[Sequence[str]]) -> list:
    if len(pred_seqs) != len(true_seqs) or not pred_seqs:
        raise ValueError(f"need equally many (> 0) predicted and true sequences, got {len(pred_seqs)} "
                         f"and {len(true_seqs)}")
    return list(zip(pred_seqs, true_seqs, strict=True))


def sequence_accuracy(pred_seqs: Sequence[Sequence[str]], true_seqs: Sequence[Sequence[str]]) -> float:
    """Fraction of exactly matching sequences."""
    return float(np.mean([list(p) == list(t) for p, t in _pairs(pred_seqs, true_seqs)]))


def normalised_edit_distance(pred_seqs: Sequence[Sequence[str]], true_seqs: Sequence[Sequence[str]]) -> float:
    """Mean of edit_distance(p, t) / max(len p, len t) (0 when both are empty)."""
    return float(np.mean([edit_distance(p, t) / max(len(p), len(t), 1) for p, t in _pairs(pred_seqs, true_seqs)]))


def evaluate_action_order(classifier: ActionClassifier, dataset_root: str | Path, split: str = "test",
                          max_motions: int | None = None, features: dict[str, np.ndarray] | None = None,
                          **predict_kwargs: Any) -> dict[str, float]:
    """Sequence accuracy, normalised edit distance and frame accuracy of `classifier` on the
    motions of `split` (their real features, or `features[id]` (t, d) raw, e.g. generated
    motions, for the ids given). Frame accuracy is only computed on real motions."""
    root = Path(dataset_root)
    ids = read_split(root, split)[:max_motions]
    if features is not None:
        ids = [i for i in ids if i in features]
    if not ids:
        raise SegmoError(f"evaluate_action_order: no motions to evaluate in {split_file(root, split)}")
    index = {c: i for i, c in enumerate(classifier.classes)}
    preds, trues, correct, frames = [], [], 0, 0
    for mid in ids:
        actions, spans = read_actions(root, mid)
        x = features[mid] if features is not None else read_motion(root, mid)
        preds.append(classifier.predict_sequence(x, **predict_kwargs))
        trues.append(collapse(actions))
        if features is None:
            labels = classifier.frame_probabilities(x).argmax(1)
            for a, (s, e) in zip(actions, spans, strict=True):
                correct += int((labels[s:e] == index.get(a, -1)).sum())
                frames += e - s
    out = {"sequence_accuracy": sequence_accuracy(preds, trues),
           "normalised_edit_distance": normalised_edit_distance(preds, trues), "motions": float(len(ids))}
    if frames:
        out["frame_accuracy"] = correct / frames
    return out
