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

Where a sequence fails: `error_kind` names how a predicted sequence differs ("missing",
"extra", "substituted", "reordered"), and `recall_by_share` says how often each true action
is found (paired with an equal predicted action by an optimal edit alignment,
`matched_actions`) by its share of the motion's frames, so that short actions lost beside
long ones show as such. `frame_confusions` says, frame by frame on the true spans, which
action each action is read as (how a tokenizer's reconstruction blurs a leap forward into a
jump in place: `tools/eval_tokenizer.py --action-classifier`).

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

__all__ = ["ERROR_KINDS", "SHARE_BINS", "collapse", "collapse_spans", "edit_distance", "error_kind",
           "error_shares", "evaluate_action_order", "frame_confusions", "matched_actions", "normalised_edit_distance",
           "recall_by_share", "sequence_accuracy"]

ERROR_KINDS = ("missing", "extra", "substituted", "reordered")
# Upper edges of the action-share bins of `recall_by_share` (share of the motion's frames),
# and the bins' names in its output.
SHARE_BINS = (0.2, 0.4)
_SHARE_BIN_NAMES = (f"<{SHARE_BINS[0]:g}", *[f"{lo:g}-{hi:g}" for lo, hi in zip(SHARE_BINS, SHARE_BINS[1:])],
                    f">={SHARE_BINS[-1]:g}")


def edit_distance(a: Sequence[Any], b: Sequence[Any]) -> int:
    """Levenshtein distance (insertions, deletions, substitutions cost 1)."""
    return _edit_table(a, b)[-1][-1]


def _edit_table(a: Sequence[Any], b: Sequence[Any]) -> list[list[int]]:
    """table[i][j]: edit distance between a[:i] and b[:j]."""
    table = [list(range(len(b) + 1))]
    for i, x in enumerate(a, 1):
        row = [i]
        for j, y in enumerate(b, 1):
            row.append(min(table[i - 1][j] + 1, row[j - 1] + 1, table[i - 1][j - 1] + (x != y)))
        table.append(row)
    return table


def matched_actions(pred: Sequence[Any], true: Sequence[Any]) -> list[bool]:
    """For each true action, whether an optimal edit alignment of `pred` to `true` pairs it
    with an equal predicted action, of the optimal alignments the one with the most such
    pairs: ["walk", "sit"] against ["walk", "jump", "sit"] → [True, False, True]; ["walk",
    "jump"] against ["jump", "walk"] → one of the two (two edits either way: substitute
    both, or match one and insert and delete the other)."""
    # best[i][j]: (edits, -matches) of aligning pred[:i] with true[:j], compared in order
    best = [[(i + j, 0) for j in range(len(true) + 1)] for i in range(len(pred) + 1)]

    def moves(i: int, j: int) -> list[tuple[tuple[int, int], int, int, bool]]:
        """The steps into (i, j): (cost, from i, from j, a match)."""
        same = pred[i - 1] == true[j - 1]
        diagonal = best[i - 1][j - 1]
        return [((diagonal[0] + (not same), diagonal[1] - same), i - 1, j - 1, same),
                ((best[i - 1][j][0] + 1, best[i - 1][j][1]), i - 1, j, False),
                ((best[i][j - 1][0] + 1, best[i][j - 1][1]), i, j - 1, False)]

    for i in range(1, len(pred) + 1):
        for j in range(1, len(true) + 1):
            best[i][j] = min(cost for cost, *_ in moves(i, j))
    found = [False] * len(true)
    i, j = len(pred), len(true)
    while i > 0 and j > 0:
        _, i_from, j_from, match = next(m for m in moves(i, j) if m[0] == best[i][j])
        found[j - 1] = found[j - 1] or match
        i, j = i_from, j_from
    return found


def error_kind(pred: Sequence[Any], true: Sequence[Any]) -> str | None:
    """How `pred` differs from `true`: None (equal), "missing" (fewer actions), "extra"
    (more), "reordered" (the same actions in another order), "substituted" (as many, some
    of them other actions)."""
    pred, true = list(pred), list(true)
    if pred == true:
        return None
    if len(pred) != len(true):
        return "missing" if len(pred) < len(true) else "extra"
    return "reordered" if sorted(map(str, pred)) == sorted(map(str, true)) else "substituted"


def error_shares(pred_seqs: Sequence[Sequence[str]], true_seqs: Sequence[Sequence[str]]) -> dict[str, float]:
    """Share of the motions of each `ERROR_KINDS` kind (the four add up to 1 − sequence
    accuracy)."""
    kinds = [error_kind(p, t) for p, t in _pairs(pred_seqs, true_seqs)]
    return {kind: kinds.count(kind) / len(kinds) for kind in ERROR_KINDS}


def collapse_spans(segments: Sequence[dict], frames: int) -> tuple[list[str], list[float]]:
    """A caption's true action sequence (consecutive repeats merged, as `collapse`) and each
    action's share of the motion's `frames` (a merged action's spans summed), from its
    ground-truth segments (dicts with "action", "start", "end" in frames)."""
    actions: list[str] = []
    shares: list[float] = []
    for seg in segments:
        share = max(int(seg["end"]) - int(seg["start"]), 0) / max(frames, 1)
        if actions and actions[-1] == seg["action"]:
            shares[-1] += share
        else:
            actions.append(seg["action"])
            shares.append(share)
    return actions, shares


def recall_by_share(pred_seqs: Sequence[Sequence[str]], true_seqs: Sequence[Sequence[str]],
                    shares: Sequence[Sequence[float]]) -> dict[str, dict[str, float]]:
    """Share of the true actions found (`matched_actions`) per bin of their share of the
    motion's frames (`SHARE_BINS`: "<0.2", "0.2-0.4", ">=0.4"); bins without actions are
    left out. `shares[i]` holds one value per action of `true_seqs[i]`."""
    found: dict[str, list[bool]] = {name: [] for name in _SHARE_BIN_NAMES}
    for (pred, true), share in zip(_pairs(pred_seqs, true_seqs), shares, strict=True):
        if len(share) != len(true):
            raise ValueError(f"need a share per true action, got {len(share)} for {len(true)}")
        for hit, value in zip(matched_actions(pred, true), share, strict=True):
            found[_SHARE_BIN_NAMES[int(np.searchsorted(SHARE_BINS, value, side="right"))]].append(hit)
    return {name: {"recall": float(np.mean(hits)), "actions": float(len(hits))}
            for name, hits in found.items() if hits}


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


def frame_confusions(classifier: ActionClassifier, dataset_root: str | Path, features: dict[str, np.ndarray],
                     top: int = 8) -> dict[str, Any]:
    """Frame-wise reading of the true spans of motions `features` (id → raw (t, d), e.g.
    reconstructions; frames past a clip's end are left out): each action's frame accuracy
    ("frame_accuracy": {action: share}) and the `top` most frequent confusions
    ("confusions": [{"true", "read_as", "frames", "share"}], share of the true action's
    frames), most frames first."""
    root = Path(dataset_root)
    index = {c: i for i, c in enumerate(classifier.classes)}
    hits: dict[str, int] = {}
    totals: dict[str, int] = {}
    wrong: dict[tuple[str, str], int] = {}
    for mid, x in features.items():
        labels = classifier.frame_probabilities(x).argmax(1)
        actions, spans = read_actions(root, mid)
        for action, (start, end) in zip(actions, spans, strict=True):
            read = labels[start:min(end, len(labels))]
            if not len(read):
                continue
            totals[action] = totals.get(action, 0) + len(read)
            hits[action] = hits.get(action, 0) + int((read == index.get(action, -1)).sum())
            for label, count in zip(*np.unique(read, return_counts=True), strict=True):
                name = classifier.classes[int(label)]
                if name != action:
                    wrong[(action, name)] = wrong.get((action, name), 0) + int(count)
    ranked = sorted(wrong.items(), key=lambda kv: (-kv[1], kv[0]))[:top]
    return {"frame_accuracy": {a: hits[a] / totals[a] for a in sorted(totals)},
            "confusions": [{"true": t, "read_as": r, "frames": n, "share": n / totals[t]}
                           for (t, r), n in ranked]}


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
