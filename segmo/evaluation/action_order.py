"""Action-order accuracy on the built-in corpus: does a motion perform the right actions in
the right order?

A small frame-wise action classifier (`ActionClassifier`: dilated 1-D convolutions over
z-scored features, one label per frame) is trained on the ground-truth spans of the
corpus (`ROOT/segments/<id>.json`, `segmo.data.layout.read_actions`; classes = action names; arm overlays ("with") are
ignored, the label is the main action). A motion's action sequence is then read without
any ground truth: frame-wise class probabilities → moving average over `smooth` frames →
argmax → runs; runs shorter than `min_frames` are dropped and equal neighbours merged.

`sequence_accuracy` (exact match) and `normalised_edit_distance` (Levenshtein distance /
the longer length; a missing or extra action costs 1, two swapped actions 2) compare
predicted and true sequences. Consecutive repeats of an action in a true sequence are
merged, since no frame labelling can separate them.

Example::

    clf = ActionClassifier.fit("data/synth", epochs=15)
    clf.save_pretrained("models/action_classifier")
    clf.predict_sequence(np.load("data/synth/new_joint_vecs/000042.npy"))  # ['walk_forward', 'wave']
    evaluate_action_order(clf, "data/synth", split="test")
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from segmo.data.layout import read_actions, read_motion, read_split, split_file, stats_files
from segmo.errors import SegmoError
from segmo.models.pretrained import Pretrained


@dataclass
class ActionClassifierConfig:
    feature_dim: int = 263
    num_classes: int = 1
    width: int = 64
    depth: int = 4  # dilations 1, 2, 4, ... : receptive field 1 + (kernel-1)·(2^depth − 1)
    kernel: int = 5
    dropout: float = 0.1


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


def collapse(labels: Sequence[Any]) -> list[Any]:
    """Merge consecutive repeats: [a, a, b, a] → [a, b, a]."""
    return [x for i, x in enumerate(labels) if i == 0 or x != labels[i - 1]]


class ActionClassifier(nn.Module, Pretrained):
    """Frame-wise action classifier; see the module docstring. Buffers `mean`, `std` (d,);
    class names in `meta["classes"]`."""

    kind: ClassVar[str] = "action_classifier"
    config_class: ClassVar[type] = ActionClassifierConfig

    def __init__(self, config: ActionClassifierConfig) -> None:
        super().__init__()
        c = self.config = config
        self.meta: dict = {}
        self.input = nn.Conv1d(c.feature_dim, c.width, 1)
        self.blocks = nn.ModuleList(
            nn.Conv1d(c.width, c.width, c.kernel, padding=(c.kernel // 2) * 2**i, dilation=2**i)
            for i in range(c.depth)
        )
        self.dropout = nn.Dropout(c.dropout)
        self.head = nn.Conv1d(c.width, c.num_classes, 1)
        self.register_buffer("mean", torch.zeros(c.feature_dim))
        self.register_buffer("std", torch.ones(c.feature_dim))

    @property
    def classes(self) -> list[str]:
        if "classes" not in self.meta:
            raise ValueError("ActionClassifier: no class names in meta; train with fit() or load a directory")
        return self.meta["classes"]

    def forward(self, motion: Tensor) -> Tensor:
        """Motion (b, t, d) z-scored with the buffers → logits (b, t, num_classes)."""
        x = self.input(motion.transpose(1, 2))
        for block in self.blocks:
            x = x + self.dropout(F.gelu(block(x)))  # residual: keeps the deep stack trainable
        return self.head(x).transpose(1, 2)

    @torch.no_grad()
    def frame_probabilities(self, features: Any) -> np.ndarray:
        """Raw features (t, d) → class probabilities (t, num_classes)."""
        x = torch.as_tensor(np.asarray(features), dtype=torch.float32, device=self.mean.device)
        if x.ndim != 2 or x.shape[1] != self.config.feature_dim:
            raise ValueError(f"ActionClassifier: expected features (t, {self.config.feature_dim}), got {tuple(x.shape)}")
        self.eval()
        return self(((x - self.mean) / self.std)[None])[0].softmax(-1).cpu().numpy()

    def predict_sequence(self, features: Any, smooth: int = 15, min_frames: int = 12) -> list[str]:
        """The action sequence of one motion, raw features (t, d), without ground truth."""
        p = self.frame_probabilities(features)
        if smooth > 1:
            kernel = np.ones(smooth) / smooth
            p = np.stack([np.convolve(np.pad(c, smooth // 2, mode="edge"), kernel, "valid")[: len(c)]
                          for c in p.T], axis=1)
        labels = p.argmax(1)
        runs, start = [], 0
        for i in range(1, len(labels) + 1):
            if i == len(labels) or labels[i] != labels[start]:
                runs.append((int(labels[start]), i - start))
                start = i
        kept = [c for c, n in runs if n >= min_frames] or [max(runs, key=lambda r: r[1])[0]]
        return [self.classes[c] for c in collapse(kept)]

    @classmethod
    def fit(cls, dataset_root: str | Path, split: str = "train", epochs: int = 15, batch_size: int = 32,
            lr: float = 2e-3, seed: int = 0, max_motions: int | None = None, width: int = 64,
            depth: int = 4, log: bool = False) -> ActionClassifier:
        """Train on the ground-truth spans of `split`; statistics from `ROOT/Mean.npy`/`Std.npy`."""
        root = Path(dataset_root)
        ids = read_split(root, split)[:max_motions]
        motions, labels, names = [], [], set()
        for mid in ids:
            actions, spans = read_actions(root, mid)
            names.update(actions)
            motions.append(read_motion(root, mid).astype(np.float32))
            labels.append((actions, spans))
        classes = sorted(names)
        index = {c: i for i, c in enumerate(classes)}
        targets = []
        for m, (actions, spans) in zip(motions, labels, strict=True):
            y = np.full(len(m), -100, dtype=np.int64)  # frames outside every span are ignored
            for a, (s, e) in zip(actions, spans, strict=True):
                y[s:e] = index[a]
            targets.append(y)
        gen = torch.Generator().manual_seed(seed)
        with torch.random.fork_rng():
            torch.manual_seed(seed)  # initial weights and dropout masks, without touching global state
            model = cls(ActionClassifierConfig(feature_dim=motions[0].shape[1], num_classes=len(classes),
                                               width=width, depth=depth))
            model.meta = {"classes": classes, "dataset": str(root)}
            mean, std = (torch.from_numpy(np.load(path)).float() for path in stats_files(root))
            model.mean.copy_(mean)
            model.std.copy_(std)
            opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=1e-4)
            steps = epochs * ((len(ids) + batch_size - 1) // batch_size)
            sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=lr, total_steps=steps)
            model.train()
            for epoch in range(epochs):
                order = torch.randperm(len(ids), generator=gen).tolist()
                total = 0.0
                for s in range(0, len(order), batch_size):
                    rows = order[s:s + batch_size]
                    t = max(len(motions[r]) for r in rows)
                    x = torch.zeros(len(rows), t, motions[0].shape[1])
                    y = torch.full((len(rows), t), -100, dtype=torch.long)
                    for k, r in enumerate(rows):
                        x[k, : len(motions[r])] = torch.from_numpy(motions[r])
                        y[k, : len(targets[r])] = torch.from_numpy(targets[r])
                    logits = model((x - model.mean) / model.std)
                    loss = F.cross_entropy(logits.reshape(-1, len(classes)), y.reshape(-1), ignore_index=-100)
                    opt.zero_grad()
                    loss.backward()
                    opt.step()
                    sched.step()
                    total += float(loss.detach()) * len(rows)
                if log:
                    print(f"ActionClassifier epoch {epoch}: loss {total / len(ids):.4f}", flush=True)
        return model.eval()


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
