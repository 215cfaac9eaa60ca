"""The text side of a `SegMo`: captions → the tensors its transformers are conditioned on.

`TextConditioning` holds the text encoder and the text segmenter a bundle names (each built
on first use, or injected), caches sentence and word features in memory per text, and turns
a batch of captions into the sentence vectors, the ordered segment vectors with their mask,
and (for transformers with word keys) the per-word features. `SegMo.text_condition`,
`word_condition`, `encode_texts`, `segment_texts`, … hand over to it.
"""

from __future__ import annotations

from typing import Any

import torch

from segmo.errors import SegmoError
from segmo.generation.sampling import check_word_text
from segmo.models.mask_transformer import MaskTransformerConfig
from segmo.pipeline.bundle import SegMoConfig
from segmo.pipeline.inputs import check_texts, warn_truncated
from segmo.text import encoders  # looked up on use, so that tests can swap the encoder
from segmo.text.extract import ordered_text
from segmo.text.llm import get_text_segmenter


class TextConditioning:
    """Captions → condition tensors for transformers of config `model` (its text_dim,
    max_segments, text_tokens, word_attention, max_words), on `device` (`SegMo.to` moves it).

    The encoder and the segmenter are the ones `bundle` names when first used (its
    text_encoder, `segmo.text.encoders`; its text_segmenter, `segmo.text.llm`), or the
    objects given instead (`text_encoder=`: any object with `.encode(texts).sentence` and
    `.dim`; `text_segmenter=`: any object with `.segment(texts)`).
    """

    def __init__(self, model: MaskTransformerConfig, bundle: SegMoConfig, device: torch.device,
                 *, text_encoder: Any = None, text_segmenter: Any = None) -> None:
        self.model = model
        self.bundle = bundle
        self.device = device
        self._encoder = text_encoder
        self._segmenter = text_segmenter
        self._sentence_cache: dict[str, torch.Tensor] = {}
        self._word_cache: dict[str, torch.Tensor] = {}

    @property
    def encoder(self):
        if self._encoder is None:
            try:
                self._encoder = encoders.get_text_encoder(self.bundle.text_encoder)
            except (OSError, ValueError, ImportError) as error:
                raise SegmoError(
                    f"SegMo: cannot build text encoder {self.bundle.text_encoder!r} named in the "
                    f"bundle ({error}); inject one with `model.text_encoder = encoder`") from error
        return self._encoder

    @encoder.setter
    def encoder(self, encoder) -> None:
        # Features of another encoder are not these: forget both caches.
        self._encoder = encoder
        self._sentence_cache.clear()
        self._word_cache.clear()

    @property
    def segmenter(self):
        if self._segmenter is None:
            self._segmenter = get_text_segmenter(self.bundle.text_segmenter,
                                                 max_segments=self.model.max_segments)
        return self._segmenter

    @segmenter.setter
    def segmenter(self, segmenter) -> None:
        self._segmenter = segmenter

    @property
    def uses_words(self) -> bool:
        """Whether the transformers condition on the captions' words (text_tokens "words")."""
        return self.model.text_tokens == "words"

    @property
    def has_word_keys(self) -> bool:
        """Whether the words are keys of the mask transformer's self-attention (prefix
        words): what an attention recording and a word reweighting see. Words read by
        cross-attention (`word_attention: cross`) are not."""
        return self.uses_words and self.model.word_attention == "prefix"

    def encode(self, texts: list[str]) -> torch.Tensor:
        """texts → (n, text_dim) float32 sentence vectors on `device`."""
        if isinstance(texts, str):
            raise TypeError("SegMo.encode_texts(texts): texts must be a list of strings")
        missing = list(dict.fromkeys(t for t in texts if t not in self._sentence_cache))
        if missing:
            warn_truncated(self.encoder, missing)
            sentence = self.encoder.encode(missing).sentence.float().cpu()
            if sentence.shape[-1] != self.model.text_dim:
                raise SegmoError(f"SegMo: text encoder {self.bundle.text_encoder!r} gives "
                                 f"{sentence.shape[-1]}-d vectors, the models take "
                                 f"text_dim={self.model.text_dim}")
            self._sentence_cache.update(zip(missing, sentence))
        if not texts:
            return torch.zeros(0, self.model.text_dim, dtype=torch.float32, device=self.device)
        return torch.stack([self._sentence_cache[t] for t in texts]).to(self.device)

    def segment(self, texts: list[str]) -> list[list[str]]:
        """Ordered text segments of each text (≤ max_segments), by `segmenter`."""
        if isinstance(texts, str):
            raise TypeError("SegMo.segment_texts(texts): texts must be a list of strings")
        return [list(s) for s in self.segmenter.segment(list(texts))]

    def condition(self, texts: list[str], segments: list[list[str]] | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[list[str]]]:
        """texts (b) [+ segments] → sentence (b, text_dim), segment vectors (b, a, text_dim),
        segment_mask (b, a) bool, and the segments used (a = most segments of the batch)."""
        texts = check_texts(texts)
        if segments is None:
            segments = self.segment(texts)
        else:
            check_segment_lists(segments, texts)
            segments = [check_texts(s, f"text {i}, segment") for i, s in enumerate(segments)]
        limit = self.model.max_segments
        for text, segs in zip(texts, segments):
            if not 1 <= len(segs) <= limit:
                raise SegmoError(f"SegMo: {text!r:.80} has {len(segs)} segments; the model "
                                 f"takes 1..{limit}")
        a = max(len(s) for s in segments)
        flat = self.encode([t for s in segments for t in s])
        # float32 whatever torch's default dtype is (a notebook may set float64)
        vectors = torch.zeros(len(texts), a, flat.shape[-1], dtype=torch.float32,
                              device=self.device)
        mask = torch.zeros(len(texts), a, dtype=torch.bool, device=self.device)
        k = 0
        for i, segs in enumerate(segments):
            vectors[i, : len(segs)] = flat[k: k + len(segs)]
            mask[i, : len(segs)] = True
            k += len(segs)
        return self.encode(list(texts)), vectors, mask, segments

    def word_sources(self, texts: list[str], segments: list[list[str]] | None,
                     word_text: str) -> list[str]:
        """The text each row's word keys are read from: the text itself ("caption"), or its
        segments (default: `segmenter`'s) joined in execution order ("segments",
        `ordered_text`)."""
        texts = check_texts(texts)
        check_word_text(word_text)
        if word_text == "caption":
            return texts
        if segments is None:
            segments = self.segment(texts)
        check_segment_lists(segments, texts)
        return [ordered_text(list(s)) for s in segments]

    def words(self, texts: list[str], segments: list[list[str]] | None, word_text: str
              ) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """texts (b) → the per-word features (b, l, text_dim) of their word sources (the
        encoder's tokens, start and end tokens included, padded to the longest) and
        word_mask (b, l) bool; (None, None) for transformers without words."""
        if not self.uses_words:
            return None, None
        texts = self.word_sources(texts, segments, word_text)
        missing = list(dict.fromkeys(t for t in texts if t not in self._word_cache))
        if missing:
            out = self.encoder.encode(missing)
            for i, text in enumerate(missing):
                self._word_cache[text] = out.tokens[i][out.token_mask[i].bool()].float().cpu()
        rows = [self._word_cache[t][: self.model.max_words] for t in texts]
        length = max(len(r) for r in rows)
        words = torch.zeros(len(texts), length, self.model.text_dim, dtype=torch.float32,
                            device=self.device)
        mask = torch.zeros(len(texts), length, dtype=torch.bool, device=self.device)
        for i, row in enumerate(rows):
            words[i, : len(row)], mask[i, : len(row)] = row.to(self.device), True
        return words, mask

    def word_texts(self, texts: list[str], segments: list[list[str]] | None, word_text: str
                   ) -> list[list[str]]:
        """texts (b) → the text of each word key (`TextEncoder.token_texts` of the word
        source, start and end tokens included, cut at max_words); empty lists for
        transformers without words."""
        texts = check_texts(texts)
        if not self.uses_words:
            return [[] for _ in texts]
        sources = self.word_sources(texts, segments, word_text)
        return [pieces[: self.model.max_words] for pieces in self.encoder.token_texts(sources)]


def check_segment_lists(segments: Any, texts: list[str]) -> None:
    """SegmoError unless `segments` is a list (or tuple) of one entry per text (a number
    or a generator has no entries to count, a string would be read letter by letter)."""
    if not isinstance(segments, (list, tuple)):
        raise SegmoError(f"SegMo: segments must be one list of strings per text "
                         f"({len(texts)}), got a {type(segments).__name__}")
    if len(segments) != len(texts):
        raise SegmoError(f"SegMo: segments must be one list of strings per text "
                         f"({len(texts)}), got {segments!r:.80}")
