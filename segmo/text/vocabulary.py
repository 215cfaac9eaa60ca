"""Words and part-of-speech tags for the T2M evaluator's text encoder (spec §9).

The evaluator reads a caption as a sequence of `word/POS` tokens (HumanML3D text lines
carry them: `caption#word/POS word/POS ...#from#to`), wrapped as
`sos/OTHER w_1 ... w_l eos/OTHER` with at most `MAX_TEXT_LEN` = 20 caption words, exactly
like the released evaluator. Each token becomes a word index into a vocabulary and one of
the 15 POS categories of the released code: the tagger's POS when it is one of them, else
OTHER, overridden by the "VIP" category of a few motion words (left, arm, walk, slowly...).

Two vocabularies exist:
- GloVe (`Vocabulary.from_glove`): the released `our_vab_{data.npy,words.pkl,idx.pkl}`, with
  the frozen 300-d vectors; unknown words map to `unk`.
- learned (`Vocabulary.from_token_lists`): the words of the training captions, for datasets
  without GloVe (the built-in corpus); the evaluator then learns its own word vectors.

When a caption comes without its text line (e.g. a prompt typed by a user), `tag_caption`
tokenises it deterministically (lower case, punctuation dropped) and tags words with a
small lexicon (`_LEXICON` below, the function words of motion captions) and the suffix
rules "-ing/-s/-ed → VERB", everything else NOUN. The VIP override makes the tags that
matter for motion (actions, body parts, directions) the same as with a real tagger.
"""

from __future__ import annotations

import pickle
import re
from collections import Counter
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import torch

from segmo.errors import SegmoError
from segmo.text.captions import read_caption_lines, texts_file

# The 15 POS categories of the released evaluator, in its one-hot order.
POS_CATEGORIES: tuple[str, ...] = (
    "VERB", "NOUN", "DET", "ADP", "NUM", "AUX", "PRON", "ADJ", "ADV",
    "Loc_VIP", "Body_VIP", "Obj_VIP", "Act_VIP", "Desc_VIP", "OTHER",
)
POS_INDEX = {p: i for i, p in enumerate(POS_CATEGORIES)}
MAX_TEXT_LEN = 20  # caption words kept; + sos + eos = 22 tokens at most
SOS, EOS, UNK = "sos", "eos", "unk"

# Words whose category overrides the tagger's POS (the released evaluator's lists).
_VIP_WORDS = {
    "Loc_VIP": "left right clockwise counterclockwise anticlockwise forward back backward up down "
               "straight curve",
    "Body_VIP": "arm chin foot feet face hand mouth leg waist eye knee shoulder thigh",
    "Obj_VIP": "stair dumbbell chair window floor car ball handrail baseball basketball",
    "Act_VIP": "walk run swing pick bring kick put squat throw hop dance jump turn stumble stop sit "
               "lift lower raise wash stand kneel stroll rub bend balance flap jog shuffle lean "
               "rotate spin spread climb",
    "Desc_VIP": "slowly carefully fast careful slow quickly happy angry sad happily angrily sadly",
}
VIP = {w: cat for cat, words in _VIP_WORDS.items() for w in words.split()}

# Function words of motion captions, for captions that arrive without POS tags.
_LEXICON_TEXT = {
    "DET": "a an the both each every this these those another all some",
    "PRON": "he she someone somebody it its their his her they them him himself herself that "
            "who which one",
    "NUM": "once twice two three four five six seven eight nine ten 90 180 360 45",
    "ADP": "to on in with at above from by of into onto over under around across through "
           "behind towards toward like as about along off out",
    "AUX": "is are was were be been being do does did has have had can will would could",
    "ADV": "still then finally first again also slowly quickly fast forward backward backwards "
           "back ahead straight sideways up down deeply together low clockwise "
           "counterclockwise around away repeatedly briefly next later",
    "ADJ": "left right slow full quick small big large high other same",
    "OTHER": "and or but while after before when until so",
}
_LEXICON = {w: pos for pos, words in _LEXICON_TEXT.items() for w in words.split()}
_WORD = re.compile(r"[a-z0-9']+")


def pos_category(word: str, pos: str) -> int:
    """Index in `POS_CATEGORIES` of a tagged word (VIP lists first, unknown tags → OTHER)."""
    return POS_INDEX[VIP.get(word, pos if pos in POS_INDEX else "OTHER")]


def parse_tokens(field: str) -> list[tuple[str, str]]:
    """'a/DET man/NOUN waves/VERB' -> [('a', 'DET'), ('man', 'NOUN'), ('waves', 'VERB')].

    A token without '/' gets POS OTHER; the word is lower-cased.
    """
    out = []
    for token in field.split():
        word, _, pos = token.rpartition("/")
        if not word:
            word, pos = pos, "OTHER"
        out.append((word.lower(), pos))
    return out


def tag_caption(caption: str) -> list[tuple[str, str]]:
    """Deterministic tokeniser + lexicon tagger for captions without `word/POS` tokens."""
    out = []
    for word in _WORD.findall(caption.lower()):
        if word in _LEXICON:
            pos = _LEXICON[word]
        elif word.isdigit():
            pos = "NUM"
        elif word.endswith(("ing", "ed")) or (word.endswith("s") and not word.endswith("ss")):
            pos = "VERB"
        else:
            pos = "NOUN"
        out.append((word, pos))
    return out


def read_text_tokens(path: str | Path) -> list[list[tuple[str, str]]]:
    """Tagged tokens of each caption line (`segmo.text.captions.read_caption_lines`) of a
    `texts/<id>.txt` file, in line order.

    A line whose token field is empty is tagged from its caption with `tag_caption`.
    """
    out = []
    for line in read_caption_lines(path):
        parts = line.text.split("#")
        if len(parts) < 2:
            raise SegmoError(f"{path}:{line.lineno}: expected 'caption#word/POS ...#from#to'")
        out.append(parse_tokens(parts[1]) or tag_caption(parts[0]))
    return out


class Vocabulary:
    """Word ↔ index map of the evaluator, with `sos`, `eos` and `unk` always present."""

    def __init__(self, words: Sequence[str]) -> None:
        words = list(words)
        missing = [w for w in (SOS, EOS, UNK) if w not in words]
        if missing:
            raise ValueError(f"Vocabulary: the word list lacks the special words {missing}")
        if len(set(words)) != len(words):
            raise ValueError("Vocabulary: the word list has duplicates")
        self.words = words
        self.index = {w: i for i, w in enumerate(words)}

    def __len__(self) -> int:
        return len(self.words)

    @classmethod
    def from_token_lists(cls, token_lists: Iterable[Sequence[tuple[str, str]]], min_count: int = 1
                         ) -> Vocabulary:
        """The words seen at least `min_count` times, sorted, after sos/eos/unk."""
        counts = Counter(w for tokens in token_lists for w, _ in tokens)
        words = sorted(w for w, c in counts.items() if c >= min_count and w not in (SOS, EOS, UNK))
        return cls([SOS, EOS, UNK, *words])

    @classmethod
    def from_glove(cls, directory: str | Path, prefix: str = "our_vab") -> tuple[Vocabulary, np.ndarray]:
        """Read the released GloVe files `<prefix>_{data.npy,words.pkl,idx.pkl}`.

        Returns the vocabulary (words ordered by their row in the data file) and the
        vectors (num_words, 300) float32, rows in the same order.
        """
        directory = Path(directory)
        paths = [directory / f"{prefix}_{s}" for s in ("data.npy", "words.pkl", "idx.pkl")]
        for p in paths:
            if not p.is_file():
                raise FileNotFoundError(f"{p}: GloVe file not found")
        vectors = np.load(paths[0]).astype(np.float32)
        with open(paths[1], "rb") as f:
            words = list(pickle.load(f))
        with open(paths[2], "rb") as f:
            word2idx = dict(pickle.load(f))
        order = sorted(words, key=lambda w: word2idx[w])
        rows = np.array([word2idx[w] for w in order], dtype=np.int64)
        if rows.size and rows.max() >= len(vectors):
            raise ValueError(f"{paths[2]}: index {rows.max()} beyond the {len(vectors)} rows of {paths[0]}")
        return cls(order), vectors[rows]

    def encode(self, tokens: Sequence[tuple[str, str]], max_len: int = MAX_TEXT_LEN
               ) -> tuple[list[int], list[int]]:
        """Word and POS indices of `sos tokens[:max_len] eos`; unknown words → unk/OTHER."""
        words, pos = [self.index[SOS]], [POS_INDEX["OTHER"]]
        for word, tag in list(tokens)[:max_len]:
            if word in self.index:
                words.append(self.index[word])
                pos.append(pos_category(word, tag))
            else:
                words.append(self.index[UNK])
                pos.append(POS_INDEX["OTHER"])
        words.append(self.index[EOS])
        pos.append(POS_INDEX["OTHER"])
        return words, pos

    def batch(self, token_lists: Sequence[Sequence[tuple[str, str]]], max_len: int = MAX_TEXT_LEN
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Padded batch: word ids (b, l) long, POS ids (b, l) long, lengths (b,) long.

        Padding uses `unk`/OTHER like the released data loader; lengths count sos and eos.
        """
        if not token_lists:
            raise ValueError("Vocabulary.batch: empty list of captions")
        encoded = [self.encode(t, max_len) for t in token_lists]
        longest = max(len(w) for w, _ in encoded)
        words = torch.full((len(encoded), longest), self.index[UNK], dtype=torch.long)
        pos = torch.full((len(encoded), longest), POS_INDEX["OTHER"], dtype=torch.long)
        for i, (w, p) in enumerate(encoded):
            words[i, : len(w)] = torch.tensor(w)
            pos[i, : len(p)] = torch.tensor(p)
        lengths = torch.tensor([len(w) for w, _ in encoded], dtype=torch.long)
        return words, pos, lengths


class CaptionTokens:
    """(word, POS) tokens of dataset captions, read from `ROOT/texts/<motion id>.txt`.

    A sample id is the motion id, or `<motion id>#<line>` for a time-tagged sub-clip;
    `caption_index` is the line. Captions that cannot be found there, or whose line has no
    tokens, are tagged with `tag_caption`. Files are read once and cached.
    """

    def __init__(self, root: str | Path | None) -> None:
        self.root = Path(root) if root is not None else None
        self._files: dict[str, list[list[tuple[str, str]]]] = {}

    def lines(self, motion_id: str) -> list[list[tuple[str, str]]]:
        """Tokens of every caption line of one motion ([] without a text file)."""
        if motion_id not in self._files:
            path = texts_file(self.root, motion_id) if self.root is not None else None
            self._files[motion_id] = read_text_tokens(path) if path is not None and path.is_file() else []
        return self._files[motion_id]

    def __call__(self, caption: str, sample_id: str | None = None, caption_index: int | None = None
                 ) -> list[tuple[str, str]]:
        lines = self.lines(str(sample_id).split("#")[0]) if sample_id is not None else []
        tokens = lines[caption_index] if caption_index is not None and caption_index < len(lines) else None
        return tokens or tag_caption(caption)

    def batch(self, batch: dict) -> list[list[tuple[str, str]]]:
        """Tokens of each caption of a collated batch (keys caption, and id/caption_index if any)."""
        n = len(batch["caption"])
        ids = batch.get("id") or [None] * n
        indices = batch.get("caption_index") or [None] * n
        return [self(c, i, k) for c, i, k in zip(batch["caption"], ids, indices, strict=True)]
