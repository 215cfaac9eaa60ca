"""The T2M evaluator (Guo et al. 2022), the field's standard text/motion embedding (spec §9).

Motion side: a movement encoder (two Conv1d k4/s2 with dropout + LeakyReLU, then a linear
layer) over the features minus the 4 foot-contact dims, 4× shorter, then a bidirectional
GRU over the valid steps; its two final states → MLP → embedding (512).
Text side: word vectors + a linear projection of the 15-d POS one-hot (the released
model adds the two, which is a concatenation followed by one linear layer), a linear
layer, a bidirectional GRU, MLP → embedding (512). Distances are Euclidean.

Module and parameter names follow the released code so that its checkpoint
`text_mot_match/model/finest.tar` loads as is (`T2MEvaluator.from_official`):
`movement_encoder` (main, out_net), `text_encoder` (pos_emb, input_emb, gru, output_net,
hidden) and `motion_encoder` (input_emb, gru, output_net, hidden). The word vectors are
the `word_embedding` table: frozen GloVe for the released model, learned from the training
captions for datasets without GloVe (never the generator's text encoder, which the
generator could game). The vocabulary is kept in `meta["words"]`.

The evaluator has its own normalisation statistics (buffers `mean`, `std`);
`embed_motion` de-normalises with the caller's statistics and re-normalises with these.

`euclidean_distance_matrix` and `r_precision` read the embedding space: the evaluator's
own accuracy, which its training logs, and spec §9's R-precision.

Example::

    ev = T2MEvaluator.from_pretrained("models/evaluator")
    text = ev.embed_captions(["a person walks forward."])       # (1, 512)
    motion = ev.embed_motion(z, lengths, mean=ds_mean, std=ds_std)  # (b, 512)
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.nn.utils.rnn import pack_padded_sequence

from segmo.errors import SegmoError
from segmo.models.pretrained import Pretrained
from segmo.text.vocabulary import POS_CATEGORIES, Vocabulary, tag_caption


@dataclass
class EvaluatorConfig:
    feature_dim: int = 263
    num_words: int = 3
    word_dim: int = 300
    pos_dim: int = len(POS_CATEGORIES)
    text_hidden: int = 512
    movement_hidden: int = 512
    movement_dim: int = 512
    motion_hidden: int = 1024
    embed_dim: int = 512
    contact_dims: int = 4  # trailing foot-contact dims the motion side ignores
    unit_length: int = 4
    dropout: float = 0.2
    freeze_words: bool = False  # True for GloVe vectors


@dataclass
class EvaluatorOutput:
    """text (b, embed_dim) and motion (b, embed_dim) embeddings, row i of one paired with row i."""

    text: Tensor
    motion: Tensor


def _head(inp: int, hidden: int, out: int) -> nn.Sequential:
    # Index layout [Linear, LayerNorm, LeakyReLU, Linear] is the released checkpoint's.
    return nn.Sequential(nn.Linear(inp, hidden), nn.LayerNorm(hidden), nn.LeakyReLU(0.2), nn.Linear(hidden, out))


def _bigru_last(gru: nn.GRU, hidden: Tensor, x: Tensor, lengths: Tensor) -> Tensor:
    """Final forward and backward states (b, 2h) of gru over x (b, l, h), valid prefix `lengths`."""
    packed = pack_padded_sequence(x, lengths.cpu(), batch_first=True, enforce_sorted=False)
    _, last = gru(packed, hidden.expand(-1, x.shape[0], -1).contiguous())  # (2, b, h)
    return torch.cat([last[0], last[1]], dim=-1)


class MovementConvEncoder(nn.Module):
    """(b, t, d_in) → (b, t/4, d_out): two strided convolutions, then a linear layer."""

    def __init__(self, d_in: int, hidden: int, d_out: int, dropout: float) -> None:
        super().__init__()
        self.main = nn.Sequential(
            nn.Conv1d(d_in, hidden, 4, 2, 1), nn.Dropout(dropout), nn.LeakyReLU(0.2),
            nn.Conv1d(hidden, d_out, 4, 2, 1), nn.Dropout(dropout), nn.LeakyReLU(0.2),
        )
        self.out_net = nn.Linear(d_out, d_out)

    def forward(self, x: Tensor) -> Tensor:
        return self.out_net(self.main(x.transpose(1, 2)).transpose(1, 2))


class TextEncoderBiGRUCo(nn.Module):
    """Word vectors (b, l, w) + POS one-hots (b, l, p), lengths (b,) → (b, out)."""

    def __init__(self, word_dim: int, pos_dim: int, hidden: int, out: int) -> None:
        super().__init__()
        self.pos_emb = nn.Linear(pos_dim, word_dim)
        self.input_emb = nn.Linear(word_dim, hidden)
        self.gru = nn.GRU(hidden, hidden, batch_first=True, bidirectional=True)
        self.output_net = _head(2 * hidden, hidden, out)
        self.hidden = nn.Parameter(torch.randn(2, 1, hidden))

    def forward(self, words: Tensor, pos_onehot: Tensor, lengths: Tensor) -> Tensor:
        x = self.input_emb(words + self.pos_emb(pos_onehot))
        return self.output_net(_bigru_last(self.gru, self.hidden, x, lengths))


class MotionEncoderBiGRUCo(nn.Module):
    """Movement features (b, n, d), lengths (b,) in steps → (b, out)."""

    def __init__(self, d_in: int, hidden: int, out: int) -> None:
        super().__init__()
        self.input_emb = nn.Linear(d_in, hidden)
        self.gru = nn.GRU(hidden, hidden, batch_first=True, bidirectional=True)
        self.output_net = _head(2 * hidden, hidden, out)
        self.hidden = nn.Parameter(torch.randn(2, 1, hidden))

    def forward(self, movements: Tensor, lengths: Tensor) -> Tensor:
        return self.output_net(_bigru_last(self.gru, self.hidden, self.input_emb(movements), lengths))


# -- distances in the embedding space ---------------------------------------------------------
# Used by the evaluator's training (`segmo.tasks.evaluator`) and by the generation metrics
# (`segmo.evaluation.metrics`), which the tasks must not import.


def _np(x: Any) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def euclidean_distance_matrix(a: Any, b: Any) -> np.ndarray:
    """(n, d), (m, d) → (n, m) Euclidean distances."""
    a, b = _np(a), _np(b)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1]:
        raise ValueError(f"euclidean_distance_matrix: shapes {a.shape} and {b.shape} are not (n, d), (m, d)")
    sq = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T
    return np.sqrt(np.maximum(sq, 0.0))


def tie_hits(better: np.ndarray, tied: np.ndarray, ks: Sequence[int]) -> np.ndarray:
    """(n, len(ks)) expected hit at each k of items with `better` candidates strictly
    ahead and `tied` others exactly as good, the ties broken at random (R-precision here,
    retrieval in `segmo.evaluation.retrieval`)."""
    k = np.asarray(ks, dtype=np.float64)[None, :]
    return np.clip((k - better[:, None]) / (tied[:, None] + 1), 0.0, 1.0)


def r_precision(text_emb: Any, motion_emb: Any, top_k: int = 3, batch_size: int = 32) -> np.ndarray:
    """Top-1..top_k R-precision, (top_k,), of paired text/motion embeddings (n, d).

    The rows are cut into consecutive batches of `batch_size` (an incomplete last batch is
    dropped); in each, text i ranks the batch's motions by distance, and counts a hit at k
    when its own motion is among the k nearest (motions exactly as near: a tie broken at
random, `tie_hits`). Chance level at top-1 is 1/batch_size.
    """
    t, m = _np(text_emb), _np(motion_emb)
    if t.shape != m.shape:
        raise ValueError(f"r_precision: text {t.shape} and motion {m.shape} embeddings differ in shape")
    n = (len(t) // batch_size) * batch_size
    if n == 0:
        raise SegmoError(f"r_precision: fewer than batch_size={batch_size} pairs ({len(t)})")
    hits = np.zeros(top_k)
    for s in range(0, n, batch_size):
        d = euclidean_distance_matrix(t[s:s + batch_size], m[s:s + batch_size])
        # The matched motion's rank: the motions strictly nearer, and a tie broken at random
        # (as the T2M reference's argsort breaks it by position). Ties counted in its favour
        # gave a generator that draws one motion for every caption top-1 = 1.
        own = np.diag(d)[:, None]
        hits += tie_hits((d < own).sum(1), (d == own).sum(1) - 1, range(1, top_k + 1)).sum(0)
    return hits / n



class T2MEvaluator(nn.Module, Pretrained):
    """Text and motion encoders of the T2M evaluator; see the module docstring."""

    kind: ClassVar[str] = "evaluator"
    config_class: ClassVar[type] = EvaluatorConfig

    def __init__(self, config: EvaluatorConfig) -> None:
        super().__init__()
        c = self.config = config
        if c.feature_dim <= c.contact_dims:
            raise ValueError(f"EvaluatorConfig: feature_dim={c.feature_dim} must exceed contact_dims={c.contact_dims}")
        self.meta: dict = {}
        self.word_embedding = nn.Embedding(c.num_words, c.word_dim)
        self.word_embedding.weight.requires_grad_(not c.freeze_words)
        self.movement_encoder = MovementConvEncoder(
            c.feature_dim - c.contact_dims, c.movement_hidden, c.movement_dim, c.dropout)
        self.text_encoder = TextEncoderBiGRUCo(c.word_dim, c.pos_dim, c.text_hidden, c.embed_dim)
        self.motion_encoder = MotionEncoderBiGRUCo(c.movement_dim, c.motion_hidden, c.embed_dim)
        self.register_buffer("mean", torch.zeros(c.feature_dim))
        self.register_buffer("std", torch.ones(c.feature_dim))

    # -- vocabulary and statistics ---------------------------------------------------------

    @property
    def vocabulary(self) -> Vocabulary:
        words = self.meta.get("words")
        if words is None:
            raise ValueError("T2MEvaluator: no vocabulary; call set_vocabulary() or load a model directory")
        if getattr(self, "_vocab", None) is None or self._vocab.words != words:
            self._vocab = Vocabulary(words)
        return self._vocab

    def set_vocabulary(self, vocabulary: Vocabulary) -> None:
        if len(vocabulary) != self.config.num_words:
            raise ValueError(f"set_vocabulary: {len(vocabulary)} words, but the model has "
                             f"num_words={self.config.num_words}")
        self.meta["words"] = list(vocabulary.words)

    @torch.no_grad()
    def set_statistics(self, mean: Tensor, std: Tensor) -> None:
        """Copy the feature statistics (d,) the evaluator's inputs are z-scored with."""
        mean, std = torch.as_tensor(mean, dtype=torch.float32), torch.as_tensor(std, dtype=torch.float32)
        if mean.shape != self.mean.shape or std.shape != self.std.shape:
            raise ValueError(f"set_statistics: expected shape {tuple(self.mean.shape)}, got "
                             f"{tuple(mean.shape)} and {tuple(std.shape)}")
        if not bool((std > 0).all()):
            raise ValueError("set_statistics: std must be positive")
        self.mean.copy_(mean)
        self.std.copy_(std)

    # -- encoders ----------------------------------------------------------------------------

    def encode_text(self, words: Tensor, pos: Tensor, lengths: Tensor) -> Tensor:
        """Word ids (b, l) long, POS ids (b, l) long, lengths (b,) → embeddings (b, embed_dim)."""
        onehot = F.one_hot(pos, self.config.pos_dim).float()
        return self.text_encoder(self.word_embedding(words), onehot, lengths)

    def encode_motion(self, motion: Tensor, lengths: Tensor) -> Tensor:
        """Motion (b, t, d) normalised with the evaluator's own statistics, lengths (b,) frames
        → embeddings (b, embed_dim). Frames beyond a length are ignored (up to the 4-frame
        receptive-field overlap of the convolutions, as in the released model)."""
        if motion.shape[-1] != self.config.feature_dim:
            raise ValueError(f"T2MEvaluator: motion has {motion.shape[-1]} features, expected "
                             f"{self.config.feature_dim}")
        steps = torch.as_tensor(lengths).long() // self.config.unit_length
        if bool((steps < 1).any()):
            raise ValueError(f"T2MEvaluator: every length must be >= unit_length={self.config.unit_length}")
        movements = self.movement_encoder(motion[..., : self.config.feature_dim - self.config.contact_dims])
        return self.motion_encoder(movements, steps.clamp(max=movements.shape[1]))

    def forward(self, words: Tensor, pos: Tensor, text_lengths: Tensor, motion: Tensor,
                motion_lengths: Tensor) -> EvaluatorOutput:
        """Paired embeddings of b captions and b motions (motion in the evaluator's normalisation)."""
        return EvaluatorOutput(self.encode_text(words, pos, text_lengths),
                               self.encode_motion(motion, motion_lengths))

    # -- convenience for evaluation ---------------------------------------------------------

    @torch.no_grad()
    def embed_motion(self, motion: Tensor, lengths: Tensor, mean: Tensor | None = None,
                     std: Tensor | None = None) -> Tensor:
        """Embeddings (b, embed_dim) of motion (b, t, d), lengths (b,) frames.

        `motion` is z-scored with `mean`/`std` (d,) — the statistics of whoever produced it
        (dataset, tokenizer); both None means raw features. It is de-normalised with those
        and re-normalised with the evaluator's own statistics (spec §2).
        """
        if (mean is None) != (std is None):
            raise ValueError("embed_motion: give both mean and std, or neither")
        raw = motion if mean is None else motion * torch.as_tensor(std).to(motion) + torch.as_tensor(mean).to(motion)
        return self.encode_motion((raw - self.mean) / self.std, lengths)

    @torch.no_grad()
    def embed_captions(self, captions: Sequence[str | Sequence[tuple[str, str]]]) -> Tensor:
        """Embeddings (b, embed_dim) of captions: strings (tagged with `tag_caption`) or
        lists of (word, POS) tokens (from the text files)."""
        tokens = [tag_caption(c) if isinstance(c, str) else c for c in captions]
        words, pos, lengths = self.vocabulary.batch(tokens)
        device = self.mean.device
        return self.encode_text(words.to(device), pos.to(device), lengths)

    # -- the released checkpoint -------------------------------------------------------------

    @classmethod
    def from_official(cls, checkpoint: str | Path, glove_dir: str | Path, mean: str | Path | None = None,
                      std: str | Path | None = None, glove_prefix: str = "our_vab") -> T2MEvaluator:
        """Build the evaluator from the released files.

        checkpoint: `.../text_mot_match/model/finest.tar` (keys movement_encoder,
        text_encoder, motion_encoder); glove_dir: folder with `our_vab_data.npy`,
        `our_vab_words.pkl`, `our_vab_idx.pkl`; mean/std: the evaluator's `.npy` statistics,
        by default `.../text_mot_match/meta/{mean,std}.npy` next to the checkpoint.
        Sizes (feature dim 263 or 251, hidden sizes) are read from the weights.
        """
        checkpoint = Path(checkpoint)
        if not checkpoint.is_file():
            raise FileNotFoundError(f"{checkpoint}: evaluator checkpoint not found")
        try:
            state = torch.load(checkpoint, map_location="cpu", weights_only=True)
        except Exception:  # noqa: BLE001 - an old pickle with non-tensor objects
            warnings.warn(f"{checkpoint}: not loadable with weights_only=True; loading it as a full "
                          "pickle (only do this for files you trust)", stacklevel=2)
            state = torch.load(checkpoint, map_location="cpu", weights_only=False)
        missing = [k for k in ("movement_encoder", "text_encoder", "motion_encoder") if k not in state]
        if missing:
            raise ValueError(f"{checkpoint}: missing keys {missing}; not a T2M evaluator checkpoint")
        vocab, vectors = Vocabulary.from_glove(glove_dir, glove_prefix)
        conv = state["movement_encoder"]["main.0.weight"]  # (hidden, d - 4, 4)
        config = EvaluatorConfig(
            feature_dim=conv.shape[1] + 4,
            num_words=len(vocab),
            word_dim=vectors.shape[1],
            pos_dim=state["text_encoder"]["pos_emb.weight"].shape[1],
            text_hidden=state["text_encoder"]["input_emb.weight"].shape[0],
            movement_hidden=conv.shape[0],
            movement_dim=state["movement_encoder"]["out_net.weight"].shape[0],
            motion_hidden=state["motion_encoder"]["input_emb.weight"].shape[0],
            embed_dim=state["text_encoder"]["output_net.3.weight"].shape[0],
            freeze_words=True,
        )
        model = cls(config)
        model.movement_encoder.load_state_dict(state["movement_encoder"])
        model.text_encoder.load_state_dict(state["text_encoder"])
        model.motion_encoder.load_state_dict(state["motion_encoder"])
        with torch.no_grad():
            model.word_embedding.weight.copy_(torch.from_numpy(vectors))
        meta_dir = checkpoint.parent.parent / "meta"
        paths = [Path(p) if p is not None else meta_dir / f"{n}.npy" for p, n in ((mean, "mean"), (std, "std"))]
        for p in paths:
            if not p.is_file():
                raise FileNotFoundError(f"{p}: evaluator statistics not found; pass mean= and std=")
        model.set_statistics(torch.from_numpy(np.load(paths[0])), torch.from_numpy(np.load(paths[1])))
        model.set_vocabulary(vocab)
        model.meta["source"] = "official"
        return model.eval()
