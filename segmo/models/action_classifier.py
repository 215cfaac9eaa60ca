"""The frame-wise action classifier of the action-order metric (built-in corpus).

Dilated 1-D convolutions over z-scored features (receptive field
1 + (kernel − 1)·(2^depth − 1) frames), one label per frame; trained on the ground-truth
spans of the corpus by `segmo.tasks.action_classifier`, used by
`segmo.evaluation.action_order`. A motion's action sequence is read without any ground
truth (`predict_sequence`): frame-wise class probabilities → moving average over `smooth`
frames → argmax → runs; runs shorter than `min_frames` are dropped and equal neighbours
merged.

Example::

    clf = ActionClassifier.from_pretrained("models/action_classifier")
    clf.predict_sequence(np.load("data/synth/new_joint_vecs/000042.npy"))  # ['walk_forward', 'wave']
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from segmo.models.pretrained import Pretrained


@dataclass
class ActionClassifierConfig:
    feature_dim: int = 263
    num_classes: int = 1
    width: int = 64
    depth: int = 4  # dilations 1, 2, 4, ... : receptive field 1 + (kernel-1)·(2^depth − 1)
    kernel: int = 5
    dropout: float = 0.1


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
            raise ValueError("ActionClassifier: no class names in meta; train it "
                             "(segmo.tasks.action_classifier) or load a directory")
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


class AttributeClassifier(ActionClassifier):
    """The same network read as three frame-wise classifiers of the action's attributes
    (`segmo.data.attributes`: side, count, speed); trained by
    `segmo.tasks.action_classifier.AttributeClassifierTask`, used by
    `segmo.evaluation.attributes`. `meta["classes"]` holds ``"attribute=value"`` names."""

    kind: ClassVar[str] = "attribute_classifier"

    def span_attributes(self, features: Any, start: int, end: int) -> dict[str, str]:
        """Raw features (t, d) → each attribute's value over frames [start, end): the
        class of the largest mean probability (softmax within the attribute). The
        attributes and their values come from the class names, "attribute=value"."""
        groups: dict[str, list[tuple[int, str]]] = {}
        for index, name in enumerate(self.classes):
            attribute, _, value = name.partition("=")
            groups.setdefault(attribute, []).append((index, value))
        self.eval()
        x = torch.as_tensor(np.asarray(features), dtype=torch.float32, device=self.mean.device)
        with torch.no_grad():
            logits = self(((x - self.mean) / self.std)[None])[0, start:end]  # (span, classes)
        out = {}
        for attribute, members in groups.items():
            mean = logits[:, [i for i, _ in members]].softmax(-1).mean(0)
            out[attribute] = members[int(mean.argmax())][1]
        return out
